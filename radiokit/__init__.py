"""radiokit: experimental X-ray radiography for elasticity-contrast studies.

A phantom with a stiff inclusion is radiographed at several compression steps; after the less
compressed steps are registered onto the most compressed one, their difference carries
*compression-induced contrast*. The modules, in the order the chain uses them:

- :mod:`radiokit.io` -- ``read(path)`` any frame file (raw, TIFF, HDF5, ITEX ``.img``): its
  ``.data`` is ``(n, rows, cols)``, its ``.meta`` what the file says; ``ExperimentWriter`` packs darks, flats and the steps' projections into
  one experiment file.
- :mod:`radiokit.calibrate` -- ``Calibration.from_frames(darks, flats)`` or
  ``Calibration.from_experiment(path)``: averaged dark and flat, defect map.
- :mod:`radiokit.correct` -- ``correct_frames(cal, raw, domain="log")``: offset, gain and defects,
  to line integrals ``-ln(I/I0)`` (or ``I/I0``, ``"linear"``; or ``"counts"``, the manual's
  gain-corrected grey levels).
- :mod:`radiokit.register` -- ``register(fixed, moving)``: residual-complexity B-spline
  registration (and peers), a pull field in pixels and quality checks; ``warp`` applies a field.
- :mod:`radiokit.enhance` -- ``compression_contrast(reference, registered, k)``:
  ``reference + k (D - mean D)``, ``D = reference - registered``.
- :mod:`radiokit.measure` -- ``contrast``, ``cnr``, ``weber``, ``improvement_factor``,
  ``change_ratio`` over ROI rectangles (``ROI(row0, row1, col0, col1)``, half-open, pixels).
- :mod:`radiokit.pipeline` -- ``process(path, Config())``: the whole chain on one experiment file,
  writing ``results.h5``, ``results.json`` (:mod:`radiokit.results`) and ``report.html``
  (:mod:`radiokit.report`); its module docstring has a runnable example.

Conventions: images are ``(rows, cols)`` and stacks ``(n, rows, cols)``; float32 for processing,
raw frames uint16; "log" images are ``-ln(I/I0)``, "linear" ones ``I/I0``, and the paper's
``-I/I0`` is the "negative" domain; displacement fields are ``(2, rows, cols)`` in pixels,
(row, col) order, pulling: ``registered(x) = moving(x + d(x))``. Bad input raises
:class:`FormatError` (a file: named, with what is wrong) or ``ValueError`` (an argument).

The command line (``radiokit --help``) runs the same steps: ``info``, ``calibrate``, ``correct``,
``register``, ``process``; with the ``sim`` and ``acquisition`` packages also ``sim run``,
``acquire`` and ``demo``.

>>> import numpy as np
>>> from radiokit.enhance import compression_contrast
>>> from radiokit.measure import ROI, improvement_factor
>>> reference = np.zeros((4, 4), np.float32); reference[:, :2] = 1.0  # the inclusion: columns 0-1
>>> registered = reference * 0.9  # the step before, registered: the inclusion's contrast grew
>>> enhanced = compression_contrast(reference, registered, k=1)
>>> round(improvement_factor(enhanced, reference, ROI(0, 4, 0, 2), ROI(0, 4, 2, 4)), 3)
1.1
"""

from radiokit._version import __version__
from radiokit.errors import FormatError, RadiokitError

__all__ = ["__version__", "FormatError", "RadiokitError"]
