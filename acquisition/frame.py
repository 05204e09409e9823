"""The compression frame: two plates closing on the phantom, set by hand or by the virtual bench.

In the lab the plates are moved by turning screws and the gap is measured with a caliper:
:class:`ManualFrame` asks the operator and records what they measured. :class:`SimFrame` moves
the virtual bench's plates. A motorised stage would implement :class:`MotorisedStage`. All follow
:class:`CompressionFrame`; gaps are in mm, the compression ratio is ``1 - gap / initial_height``.

Examples
--------
>>> frame = ManualFrame(40.0, interactive=False)
>>> frame.gap_for(0.25), frame.move_to(frame.gap_for(0.25)), frame.ratio(30.0)
(30.0, 30.0, 0.25)
>>> replies = iter(["", "29.95"])
>>> frame = ManualFrame(40.0, ask=lambda prompt: next(replies), say=lambda text: None)
>>> frame.move_to(32.0), frame.move_to(30.0), frame.position()
(32.0, 29.95, 29.95)
"""

from __future__ import annotations

import abc
import logging
import math
import typing

from acquisition.errors import DeviceError

__all__ = ["CompressionFrame", "ManualFrame", "MotorisedStage", "SimFrame"]

log = logging.getLogger(__name__)

#: a measured gap this far from the target (a fraction of the initial height: the paper's steps,
#: 15 / 20 / 25 %, are 5 % apart) is taken only when the operator types it twice
FAR_FROM_TARGET = 0.05


@typing.runtime_checkable
class CompressionFrame(typing.Protocol):
    """What the protocols need of a compression frame."""

    initial_height_mm: float

    def move_to(self, gap_mm: float) -> float:
        """Set the plate gap; return the measured gap (mm)."""

    def position(self) -> float:
        """The current (last measured) gap, mm."""

    def stop(self) -> None:
        """Stop any motion."""

    def sample_out(self) -> None:
        """Take the phantom out of the beam (for flats)."""

    def sample_in(self) -> None:
        """Put the phantom back in the beam."""

    def ratio(self, gap_mm: float) -> float:
        """``1 - gap / initial_height``."""

    def gap_for(self, ratio: float) -> float:
        """``initial_height * (1 - ratio)``."""


class _Gaps:
    """Gap <-> ratio for frames that know the phantom's initial height."""

    initial_height_mm: float

    def _set_height(self, initial_height_mm) -> None:
        h = float(initial_height_mm)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"initial_height_mm={initial_height_mm!r}: expected a height > 0 (mm)")
        self.initial_height_mm = h

    def ratio(self, gap_mm: float) -> float:
        """The compression ratio ``1 - gap / initial_height`` of a gap."""
        return 1.0 - float(gap_mm) / self.initial_height_mm

    def gap_for(self, ratio: float) -> float:
        """The gap ``initial_height * (1 - ratio)`` of a compression ratio."""
        return self.initial_height_mm * (1.0 - float(ratio))

    def _check_gap(self, gap_mm) -> float:
        gap = float(gap_mm)
        if not (math.isfinite(gap) and gap > 0):
            raise ValueError(f"{type(self).__name__}: gap {gap_mm!r} mm: expected a positive number")
        return gap


class ManualFrame(_Gaps):
    """The lab's hand-screwed frame: the operator sets and measures each gap.

    Parameters
    ----------
    initial_height_mm : float
        The phantom's uncompressed height along the compression axis (the gap at ratio 0).
    interactive : bool
        Ask the operator (default). False: take every target as reached and log it (a dry run,
        or a frame already set before the run).
    ask : callable
        ``ask(prompt) -> str``, the operator's reply (default :func:`input`).
    say : callable
        ``say(text)``, an instruction to the operator (default :func:`print`).

    Notes
    -----
    :meth:`move_to` shows the target gap to 3 decimals and reads the measurement: Enter accepts
    the target, a number (``8.47`` or ``8,47``) is the measured gap, anything else is asked again,
    as is a gap wider than the initial height; one farther from the target than
    :data:`FAR_FROM_TARGET` of the initial height is taken when typed a second time.
    End of input (a closed terminal) raises :class:`DeviceError`.
    """

    kind = "manual"

    def __init__(self, initial_height_mm: float, *, interactive: bool = True, ask=input, say=print):
        self._set_height(initial_height_mm)
        self.interactive = bool(interactive)
        self.ask = ask
        self.say = say
        self._gap = self.initial_height_mm

    def _reply(self, prompt: str) -> str:
        try:
            return str(self.ask(prompt))
        except EOFError:
            # the hint was [frame] interactive = false, which records every target gap as if the
            # operator had measured it: a way to lose the measurement, not to give it
            raise DeviceError(
                "manual compression frame: no operator input (end of input: the standard input closed at the "
                "prompt); run the command at a terminal, or feed it one line per prompt (Enter, or the measured "
                "gap in mm); [frame] interactive = false would record each target gap as if it had been measured"
            ) from None

    def move_to(self, gap_mm: float) -> float:
        """Have the operator set the plates to ``gap_mm``; return the gap they measured."""
        target = self._check_gap(gap_mm)
        if not self.interactive:
            log.info(
                "manual frame: gap %.3f mm (ratio %.4f) taken as set (non-interactive)", target, self.ratio(target)
            )
            self._gap = target
            return target
        self.say(
            f"Turn the screws to a plate gap of {target:.3f} mm "
            f"(compression {100 * self.ratio(target):.1f} % of {self.initial_height_mm:.3f} mm)."
        )
        measured = self._measured(target)
        log.info("manual frame: target %.3f mm, measured %.3f mm (ratio %.4f)", target, measured, self.ratio(measured))
        self._gap = measured
        return measured

    def _measured(self, target: float) -> float:
        """The operator's reading. A gap wider than the phantom's initial height is asked again
        (it compresses nothing: a typo, 85 for 8.5, or cm for mm), and one farther from the
        target than the paper's step spacing is taken only when typed twice: either was recorded
        as the step's compression ratio without a word (85 mm on 10 mm: ratio -7.5)."""
        pending = None  # a far-off reading typed once
        while True:
            text = self._reply(f"Measured gap in mm [Enter = {target:.3f}]: ").strip()
            if not text:
                return target
            try:
                measured = float(text.replace(",", "."))
            except ValueError:
                measured = float("nan")
            if not (math.isfinite(measured) and measured > 0):
                self.say(
                    f"{text!r} is not a gap: type the measured gap in mm (e.g. {target:.3f}), or Enter if it is the target."
                )
            elif measured > self.initial_height_mm:
                self.say(
                    f"{measured:g} mm is wider than the phantom's initial height ({self.initial_height_mm:.3f} mm): "
                    f"the plates would not compress it. Type the measured gap in mm."
                )
            elif abs(measured - target) > FAR_FROM_TARGET * self.initial_height_mm and measured != pending:
                pending = measured
                self.say(
                    f"{measured:g} mm is {abs(measured - target):.3f} mm from the target {target:.3f} mm, more than "
                    f"a step of {100 * FAR_FROM_TARGET:g} % of the height: type it again to confirm, or re-measure."
                )
            else:
                return measured

    def position(self) -> float:
        """The last measured gap (the initial height before the first move)."""
        return self._gap

    def stop(self) -> None:
        """Nothing moves by itself: a no-op (logged)."""
        log.info("manual frame: stop (nothing to stop)")

    def _confirm(self, text: str) -> None:
        if not self.interactive:
            log.info("manual frame: %s (non-interactive: assumed done)", text)
            return
        self.say(text)
        self._reply("Press Enter when done: ")

    def sample_out(self) -> None:
        """Ask the operator to take the phantom out of the beam (for flats)."""
        self._confirm("Remove the phantom from the beam for flats (leave the frame as it is).")

    def sample_in(self) -> None:
        """Ask the operator to put the phantom back in the beam."""
        self._confirm("Put the phantom back in the beam, between the plates.")

    def describe(self) -> dict:
        return {
            "kind": self.kind,
            "initial_height_mm": self.initial_height_mm,
            "interactive": self.interactive,
            "gap_mm": self._gap,
        }


class MotorisedStage(_Gaps, abc.ABC):
    """The interface a motorised compression stage implements (none is built yet).

    A subclass drives one linear axis that sets the plate gap, plus whatever moves the phantom in
    and out of the beam. It should:

    - in ``__init__``, take its transport (``acquisition.transport``) and the phantom's
      ``initial_height_mm``, home the axis or check that it is homed, and know its soft limits;
    - make :meth:`move_to` blocking: validate the gap against the limits (``ValueError``), command
      the move, poll until in position or a time-out (``DeviceError`` naming the axis and port),
      and return the *encoder's* gap, not the target;
    - make :meth:`stop` safe to call at any time and from another thread (an abort in a protocol's
      ``finally``), halting the axis at once;
    - raise :class:`DeviceError` on a limit switch, a stall or a lost link, with the axis stopped.
    """

    kind = "motorised"

    def __init__(self, initial_height_mm: float):
        self._set_height(initial_height_mm)

    @abc.abstractmethod
    def move_to(self, gap_mm: float) -> float:
        """Move to ``gap_mm`` and block until there; return the measured gap (mm)."""

    @abc.abstractmethod
    def position(self) -> float:
        """The gap the encoder reads now (mm)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Halt all motion now."""

    @abc.abstractmethod
    def sample_out(self) -> None:
        """Move the phantom out of the beam (for flats), keeping the gap."""

    @abc.abstractmethod
    def sample_in(self) -> None:
        """Move the phantom back into the beam."""


class SimFrame(_Gaps):
    """The virtual bench's plates (:class:`sim.bench.VirtualBench`).

    :meth:`move_to` sets the bench to the finite-element state at ratio ``1 - gap /
    initial_height`` (solving it if the bench has not prepared it) and returns the bench's gap;
    :meth:`sample_out` / :meth:`sample_in` take the phantom out of and into the beam.

    Examples
    --------
    >>> from sim.bench import VirtualBench
    >>> from sim.scene import block_scene
    >>> frame = SimFrame(VirtualBench(block_scene(size_mm=10)))
    >>> frame.initial_height_mm, frame.move_to(frame.gap_for(0.1)), round(frame.bench.ratio, 9)
    (10.0, 9.0, 0.1)
    """

    kind = "sim"

    def __init__(self, bench):
        self.bench = bench
        self._set_height(bench.initial_height_mm)

    def move_to(self, gap_mm: float) -> float:
        gap = self._check_gap(gap_mm)
        self.bench.set_gap(gap)
        return float(self.bench.gap_mm)

    def position(self) -> float:
        return float(self.bench.gap_mm)

    def stop(self) -> None:
        """The bench moves instantly: nothing to stop."""

    def sample_out(self) -> None:
        self.bench.sample_in = False

    def sample_in(self) -> None:
        self.bench.sample_in = True

    def describe(self) -> dict:
        return {
            "kind": self.kind,
            "initial_height_mm": self.initial_height_mm,
            "gap_mm": self.position(),
            "sample_in": bool(self.bench.sample_in),
        }
