"""Reading and writing frames: raw C7942 files, TIFF, ITEX ``.img`` and the experiment HDF5.

>>> from radiokit.io import read, PRESETS
>>> sorted(PRESETS)[:3]
['c7942', 'c7942-2344', 'c7942-2344-2x2']
"""
from radiokit.errors import FormatError
from radiokit.io._atomic import (RESULTS_MARKER, DiskFullError, OutputError, OutputExistsError, atomic_dir,
                                 atomic_h5, atomic_path, check_free_space, check_output)
from radiokit.io._budget import BUDGET_ENV, check_budget, memory_budget, parse_size
from radiokit.io._experiment import ExperimentWriter, ImageKey
from radiokit.io._frames import BitDepthWarning, Frames
from radiokit.io._raw import DEFAULT_PRESET, PRESETS, RawPreset
from radiokit.io._source import FORMATS, FrameSource, iter_frames, open_frames, read, sniff
from radiokit.io._write import StackWriter, write_tiff

__all__ = ["read", "open_frames", "iter_frames", "sniff", "Frames", "FrameSource", "FORMATS",
           "PRESETS", "DEFAULT_PRESET", "RawPreset", "ExperimentWriter", "ImageKey", "StackWriter",
           "write_tiff", "FormatError", "BitDepthWarning", "atomic_path", "atomic_dir", "atomic_h5", "check_output", "check_free_space",
           "OutputError", "OutputExistsError", "DiskFullError", "RESULTS_MARKER", "memory_budget", "check_budget",
           "parse_size", "BUDGET_ENV"]
