"""acquisition: drivers, emulators and protocols for the lab's X-ray bench.

- ``acquisition.transport``: serial links (pyserial ``serial_for_url``), one locked exchange at a time.
- ``acquisition.l8121``: the Hamamatsu L8121 microfocus source (either command dialect, or a safe probe);
  ``acquisition.emulators.l8121``: its emulator, in either dialect, on a pseudo-terminal or in process.
- ``acquisition.detector``: frame sources (``FolderWatcher`` for the vendor software's files,
  ``SimDetector`` for the virtual bench); ``acquisition.frame``: the compression frame.
- ``acquisition.protocols``: scripted experiments (``compression_series``).

Errors: :class:`DeviceError`, its subclasses :class:`SourceFault` and :class:`DetectorTimeout`.
"""

from acquisition.errors import DetectorTimeout, DeviceError, SourceFault

__all__ = ["DeviceError", "SourceFault", "DetectorTimeout"]
