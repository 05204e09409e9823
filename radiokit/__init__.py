"""radiokit: experimental X-ray radiography for elasticity-contrast studies."""

from radiokit._version import __version__
from radiokit.errors import FormatError, RadiokitError

__all__ = ["__version__", "FormatError", "RadiokitError"]
