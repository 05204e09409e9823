"""The exceptions acquisition raises on purpose. Every message names the device (its port, folder
or model) and what went wrong."""

from radiokit.errors import RadiokitError


class DeviceError(RadiokitError):
    """An instrument did not do what was asked: no reply, an unparseable or refused reply, a lost
    link, a detector that delivered no frame in time."""


class SourceFault(DeviceError):
    """The X-ray source reported a fault while in use (interlock open, overload, beam dropped).
    The driver has already switched the tube off when this is raised."""


class DetectorTimeout(DeviceError):
    """A detector delivered fewer frames than asked within its time-out."""


class NoReply(DeviceError):
    """The device said nothing within its reply time-out (silent, or its reply path lost).
    Asking again costs another time-out: whoever switches a source off retries only a device
    that answers."""


class WriteTimedOut(DeviceError):
    """A command the device took no data of within the write time-out (its output held: CTS low,
    an XOFF): not sent whole, so never carried out. Typed, so that a switch-off knows it sent no
    ``XOF`` without reading the words of the message."""


class PortUnavailable(DeviceError):
    """The port could not be opened at all (a mistyped name, a cable not plugged in): no byte
    was sent, so nothing was switched on or off through it."""


class FramesRefused(DeviceError):
    """Darks or flats just taken that radiokit's calibration would refuse (a flat clipped at the
    ADC's top, flats not brighter than the darks, most of the panel defective): the series stops
    before the compression steps, the frames at fault (flats, darks or both, as
    :class:`radiokit.calibrate.CalibrationRefused` names them) kept but labelled invalid."""


class PortBusy(PortUnavailable):
    """Another program (another radiokit process: a series, a source command, their X-ray
    guardian) holds the port's exclusive lock: this process sent nothing through it, and must not,
    or each would read replies meant for the other."""


class GuardianLost(DeviceError):
    """The X-ray guardian process, which held the port for this one, died (``kill -9``, the OOM
    killer) while an exchange went through it: the exchange failed because of that death, not
    because of anything the controller did or said, so it says nothing of the controller's baud
    rate or dialect. The port is free, and the next exchange goes to it directly."""
