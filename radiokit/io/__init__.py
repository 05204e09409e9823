"""Reading and writing frames: raw C7942 files, TIFF, ITEX ``.img``, greyscale PNG, DICOM, and every file radiokit writes.

Each file layout radiokit writes has one module here, with its HDF5 paths, a typed record and
its writer and reader: the experiment (``_experiment``: :class:`ExperimentWriter`,
:func:`read_progress`), the simulation truth (``_simulation``), processed stacks (``_write``:
:class:`StackWriter`, :func:`read_stack`), registrations (``_registration``) and results
(``_results``). All follow NeXus (NXentry, NXdata, ``@default``, ``@signal``), so
:func:`read` and NeXus viewers (silx) open each at its frames.

>>> from radiokit.io import read, PRESETS
>>> sorted(PRESETS)[:3]
['c7942', 'c7942-2344', 'c7942-2344-2x2']
"""

from radiokit.errors import FormatError, InputErrors
from radiokit.io._atomic import (
    RESULTS_MARKER,
    DiskFullError,
    FileTooLargeError,
    OutputError,
    OutputExistsError,
    atomic_dir,
    atomic_h5,
    atomic_path,
    check_free_space,
    check_output,
    folder_marker,
    missing_folders,
    recover_interrupted,
    remove_empty_folders,
    remove_replaced,
)
from radiokit.io._budget import BUDGET_ENV, check_budget, check_proportion, human_bytes, memory_budget, parse_size
from radiokit.io._codecs import LossyWarning
from radiokit.io._experiment import (
    C7942_PIXEL_SIZE_MM,
    PIXEL_SIZE_RANGE_M,
    ExperimentProgress,
    ExperimentWriter,
    ImageKey,
    check_same_pixel_size,
    data_files,
    discard_unbegun,
    read_progress,
    restore_previous,
)
from radiokit.io._frames import BitDepthWarning, Frames, HalfFloatWarning, bit_depth_cause
from radiokit.io._raw import DEFAULT_PRESET, PRESETS, RawPreset
from radiokit.io._registration import RegistrationRecord, read_registration, write_registration
from radiokit.io._results import EnhancedImages, ResultsRecord, read_results, write_results
from radiokit.io._simulation import PlantedDefects, SimulationRecord, read_simulation, write_simulation
from radiokit.io._source import FORMATS, FrameSource, iter_frames, judge_all, open_frames, read, sniff
from radiokit.io._write import StackRecord, StackWriter, read_stack, write_tiff

__all__ = [
    "PIXEL_SIZE_RANGE_M",
    "check_same_pixel_size",
    "data_files",
    "read",
    "open_frames",
    "judge_all",
    "iter_frames",
    "sniff",
    "Frames",
    "FrameSource",
    "FORMATS",
    "PRESETS",
    "DEFAULT_PRESET",
    "RawPreset",
    "C7942_PIXEL_SIZE_MM",
    "ExperimentWriter",
    "ImageKey",
    "restore_previous",
    "discard_unbegun",
    "StackWriter",
    "write_tiff",
    "FormatError",
    "InputErrors",
    "BitDepthWarning",
    "HalfFloatWarning",
    "LossyWarning",
    "bit_depth_cause",
    "atomic_path",
    "atomic_dir",
    "atomic_h5",
    "remove_replaced",
    "check_output",
    "check_free_space",
    "OutputError",
    "OutputExistsError",
    "DiskFullError",
    "FileTooLargeError",
    "RESULTS_MARKER",
    "folder_marker",
    "missing_folders",
    "remove_empty_folders",
    "recover_interrupted",
    "memory_budget",
    "check_budget",
    "check_proportion",
    "parse_size",
    "human_bytes",
    "BUDGET_ENV",
    "ExperimentProgress",
    "read_progress",
    "SimulationRecord",
    "PlantedDefects",
    "read_simulation",
    "write_simulation",
    "StackRecord",
    "read_stack",
    "RegistrationRecord",
    "read_registration",
    "write_registration",
    "ResultsRecord",
    "EnhancedImages",
    "read_results",
    "write_results",
]
