"""Reading and writing frames: raw C7942 files, TIFF, ITEX ``.img`` and the experiment HDF5.

>>> from radiokit.io import read, PRESETS
>>> sorted(PRESETS)[:3]
['c7942', 'c7942-2344', 'c7942-2344-2x2']
"""
from radiokit.errors import FormatError
from radiokit.io._experiment import ExperimentWriter, ImageKey
from radiokit.io._frames import BitDepthWarning, Frames
from radiokit.io._raw import DEFAULT_PRESET, PRESETS, RawPreset
from radiokit.io._source import FORMATS, FrameSource, iter_frames, open_frames, read, sniff
from radiokit.io._write import StackWriter, write_tiff

__all__ = ["read", "open_frames", "iter_frames", "sniff", "Frames", "FrameSource", "FORMATS",
           "PRESETS", "DEFAULT_PRESET", "RawPreset", "ExperimentWriter", "ImageKey", "StackWriter",
           "write_tiff", "FormatError", "BitDepthWarning"]
