"""DICOM files for the benchmarks: the dataset of one grey image, its pixels left to the caller."""

from __future__ import annotations

from pydicom import uid
from pydicom.dataset import Dataset, FileMetaDataset

DX_FOR_PROCESSING = "1.2.840.10008.5.1.4.1.1.1.1.1"


def grey_dataset(syntax, shape, allocated: int, stored: int, *, signed: bool = False) -> Dataset:
    """A DX (for processing) dataset to be written in ``syntax``: its SOP UIDs and the image pixel
    module of a ``shape`` (rows, columns) grey frame, no pixels yet. ``save_as(path,
    enforce_file_format=True)`` fills the rest of its file meta from its own UIDs."""
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = syntax
    ds.SOPClassUID, ds.SOPInstanceUID = DX_FOR_PROCESSING, uid.generate_uid()
    ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = *shape, 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = allocated, stored, stored - 1, int(signed)
    return ds
