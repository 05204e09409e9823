"""``radiokit acquire``: run a protocol on the lab's bench or the virtual one, and bench-top source
commands (entry-point group ``radiokit.commands``)."""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import signal
import sys
from pathlib import Path

from radiokit.checks import shown_name  # a user's file name as messages print it

SOURCE_ACTIONS = ("probe", "status", "warm-up", "on", "off")

#: The longest ``source on --for``, s. A bench check (alignment, a dose-rate reading) takes
#: minutes; an extra zero or minutes typed as seconds must not become hours of beam nobody
#: watches. Longer exposures are a protocol's (a series records what it did).
HOLD_MAX_S = 3600.0
_HOLD_HELP = (
    f"how long 'on' keeps X-rays on, s (required with 'on'; at most {HOLD_MAX_S:g}): switched off at its end, "
    "at Ctrl-C, or at a fault"
)


def add_acquire(subparsers):
    p = subparsers.add_parser(
        "acquire",
        help="run a compression-series protocol (or: acquire source probe|status|warm-up|on|off --port URL)",
        description="Run a compression-series protocol (TOML) on the lab's devices, or with --sim on the virtual "
        "bench (L8121 emulator on a pseudo-terminal, simulated panel and frame). Every frame is written "
        "and flushed as it arrives; the tube is switched off on every exit path. "
        "`radiokit acquire source ACTION --port URL` talks to the source alone; `source probe` finds which "
        "command dialect and baud rate the controller speaks, with harmless queries only, and prints the "
        "raw exchange.",
    )
    p.add_argument("protocol", help="protocol TOML file, or the word 'source' for source commands")
    p.add_argument("action", nargs="?", choices=SOURCE_ACTIONS, help="with 'source': what to do")
    p.add_argument("--sim", action="store_true", help="run on the virtual bench (emulated devices)")
    p.add_argument("--resume", action="store_true", help="complete an interrupted experiment file")
    p.add_argument(
        "--dry-run", action="store_true", help="print the plan, its duration and beam-on time; touch nothing"
    )
    p.add_argument("-o", "--output", type=Path, help="experiment file (default: the protocol's output)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing experiment file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="log every serial exchange")
    p.add_argument(
        "--dialect",
        choices=("A", "B", "auto"),
        help="the L8121 controller's command dialect (see README). With a protocol it replaces [source] "
        "dialect, and with --sim the virtual bench's emulator speaks it (A or B); source commands "
        "default to auto (probe first)",
    )
    s = p.add_argument_group("source commands (refused with a protocol: its [source] section sets these)")
    s.add_argument("--port", help="serial port URL: /dev/ttyUSB0, socket://host:port, rfc2217://host:port")
    s.add_argument(
        "--baudrate",
        type=int,
        help="the controller's baud rate (default: the dialect's; auto tries this one first, then 9600, 38400, 115200)",
    )
    s.add_argument(
        "--kv",
        type=float,
        help="tube voltage for 'on' (and 'warm-up': set before it starts), kV (the L8121: 40-150, at most 75 W)",
    )
    s.add_argument("--ua", type=float, help="tube current for 'on' (and 'warm-up'), uA (the L8121: at most 500)")
    s.add_argument("--for", dest="hold", type=float, metavar="SECONDS", help=_HOLD_HELP)
    s.add_argument("--timeout", type=float, help="warm-up time-out, s (default 1800)")
    s.add_argument(
        "--reply-timeout",
        type=float,
        help="the longest wait for each reply, s (default 2, both dialects'); not for 'probe'",
    )
    s.add_argument(
        "--ready-timeout",
        type=float,
        help="how long 'on' and 'warm-up' wait for the controller's power-on checks, s (default 30)",
    )
    p.set_defaults(func=_run)


def _run(args) -> int:
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    for h in logging.getLogger().handlers:  # the notebook file gets DEBUG; the console what was asked
        h.setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    if args.protocol == "source":
        return _source(args)
    stray = _not_for_a_protocol(args)
    if stray:
        print(f"error: {stray}", file=sys.stderr)
        return 2
    from acquisition.errors import DeviceError
    from acquisition.protocols.compression_series import check_lab, check_sim, load_protocol

    try:
        p = load_protocol(Path(args.protocol))  # a file, even when its path holds '=' (not TOML text)
    except DeviceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.output:
        p.output = str(args.output)
    if Path(p.output).suffix.lower() not in (".h5", ".hdf5", ".nxs"):  # an HDF5 file under x.tif fooled readers
        print(
            f"error: {shown_name(p.output)}: the experiment file is HDF5; name it .h5 (or .hdf5, .nxs)", file=sys.stderr
        )
        return 2
    if args.dialect:
        p.source.limits["dialect"] = args.dialect
    try:  # the lab's bench or the virtual one: refused here, before the dry run's plan or the run's first file
        (check_sim if args.sim else check_lab)(p)
    except DeviceError as exc:
        print(f"error: {shown_name(args.protocol)}: {exc}", file=sys.stderr)
        return 2
    from radiokit.io import restore_previous

    would = []
    # before every check: they are about that file
    for _, line in restore_previous(p.output, dry_run=args.dry_run, found=would):
        _say(line)
    # the dry run plans from what the run would find: the old series it puts back first, not the
    # file under the name now (an --overwrite's empty one: its resume was planned, review s38b)
    held = would[-1] if args.dry_run and would else Path(p.output)
    if args.resume and not Path(p.output).exists():
        # said here in one line, and the new file checked as any new file (the run's own log
        # warning reached the terminal with a timestamp and a logger's name)
        then = "the plan is the whole series" if args.dry_run else "starting it"
        _say(NO_FILE.format(out=shown_name(p.output), then=then))
        args.resume = False
    if not args.resume:  # the experiment file is never the protocol (an existing one: refused by run())
        from radiokit.io import check_output

        try:
            check_output(p.output, overwrite=True, inputs=[Path(args.protocol)])
        except OSError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if Path(p.output).exists() and not args.overwrite:  # refused as an option is (README: exit 2)
            print(f"error: {EXISTS.format(out=shown_name(p.output))}", file=sys.stderr)
            return 2
    code, done = _resumable(args, p, held)
    if code is not None:
        return code
    _say_unstated_exposure(args, p)  # the run's first line, before its connect (the dry run's too)
    if args.dry_run:
        return _dry_run(args, p, done)
    return _run_series(args, p)


def _say_unstated_exposure(args, p) -> None:
    """The exposure the protocol did not state and the run takes from the defaults, one line, if
    any. Why said, not refused: protocols that rely on the paper's 60 kV and 250 uA run as before;
    but a forgotten key must not reach the tube unsaid (a misspelt one is refused: unknown key)."""
    if not p.unstated_exposure:
        return
    from acquisition.protocols.compression_series import SourceSettings

    units = {"voltage_kv": "kV", "current_ua": "uA"}
    values = ", ".join(f"{key} = {getattr(SourceSettings, key):g} {units[key]}" for key in p.unstated_exposure)
    _say(
        f"note: {shown_name(args.protocol)}: the exposure is not stated in [source]; X-rays at the "
        f"default{'s' if len(p.unstated_exposure) > 1 else ''} {values} (the paper's)"
    )


#: ``--resume`` on a file that holds every frame (the run and the dry run alike).
COMPLETE = "{out}: already complete ({n} frames); nothing to resume, the file and the devices were not touched"


#: ``--resume`` on a file that does not exist (the run and the dry run alike).
NO_FILE = "{out}: nothing to resume (no file: the series stopped before its first frame); {then}"


def _resumable(args, p, held: Path | None = None) -> tuple[int | None, dict | None]:
    """With ``--resume`` on an existing file: ``(exit code or None, what it holds)``. The run and
    the dry run alike, before any device is opened: a file not to resume from (another protocol's,
    not an experiment file) is refused, exit 2, and a complete one is reported, exit 0 (the dry run
    planned its warm-up, 10 min of X-rays, where the run touches nothing). ``held``: the file the
    run would find under the name (default the name's own)."""
    held = Path(p.output) if held is None else held
    if not (args.resume and held.exists()):
        return None, None
    from acquisition.errors import DeviceError
    from acquisition.protocols.compression_series import _existing, plan
    from radiokit.io import read_progress

    try:
        done = _existing(held, p, sim=args.sim)
        if plan(p, done, warm=True).n_frames:
            return None, done
        n = read_progress(held).frames_complete
    except (DeviceError, OSError, ValueError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2, None
    _say(COMPLETE.format(out=shown_name(p.output), n=n), err=False)
    return 0, done


def _not_for_a_protocol(args) -> str | None:
    """What only source commands take, given with a protocol: the problem, one line. Ignored, it
    misled: `lab.toml --kv 40` ran at the protocol's kV with no word. A protocol takes --dialect
    (it replaces [source] dialect), never these."""
    if args.action:
        return f"{args.action!r} only follows 'source' (radiokit acquire source {args.action} --port URL)"
    if args.resume and args.overwrite:  # --overwrite was ignored without a word
        return (
            "--resume and --overwrite contradict each other: --resume completes the experiment file, "
            "--overwrite replaces it with a new series; give one"
        )
    given = [
        name
        for name, value in (
            ("--port", args.port),
            ("--baudrate", args.baudrate),
            ("--kv", args.kv),
            ("--ua", args.ua),
            ("--for", args.hold),
            ("--timeout", args.timeout),
            ("--reply-timeout", args.reply_timeout),
            ("--ready-timeout", args.ready_timeout),
        )
        if value is not None
    ]
    if not given:
        return None
    return (
        f"{', '.join(given)}: only for 'radiokit acquire source ACTION'; a protocol's port, baud rate, "
        f"exposure and time-outs are its [source] section's ({shown_name(args.protocol)})"
    )


def _dry_run(args, p, done) -> int:
    """Print the plan (what a resume still has to take, ``done``: what the file holds), its
    duration and beam-on time."""
    from acquisition.protocols.compression_series import plan

    pl = plan(p, done, sim=args.sim)
    where = "the virtual bench" if args.sim else f"source {shown_name(p.source.port)}"
    print(f"plan: {shown_name(p.name)} -> {shown_name(p.output)} on {where}{' (resuming)' if done else ''}")
    print(pl.table())
    print(
        f"\n{pl.n_frames} frames; about {pl.duration_s / 60:.1f} min, X-rays on about {pl.beam_on_s / 60:.1f} min "
        f"({_warm_up_words(pl)}; "
        f"estimates: {p.detector.frame_period_s:g} s per frame, settle {p.settle_s(args.sim):g} s per step"
        f"{', operator ' + format(p.frame.move_estimate_s, 'g') + ' s per move' if p.frame.kind == 'manual' else ''})"
    )
    return 0


def _warm_up_words(pl) -> str:
    """The plan's warm-up, in words that stay true: the virtual bench's takes seconds ("0.0 min"
    was printed), and a plan without one (a resume's, the bench's warm source) has none."""
    warm = next((row[3] for row in pl.rows if row[0] == "warm-up"), 0.0)
    if warm <= 0:
        return "no time planned for a warm-up"
    shown = f"{warm:g} s" if warm < 60 else f"{warm / 60:.1f} min"
    return f"the warm-up's {shown} included, if the source needs it"


#: An existing experiment file, without --resume or --overwrite (the run and the dry run alike).
EXISTS = "{out}: exists; raw data is never overwritten (--resume completes it; --overwrite replaces it)"


#: What a source command has said on the terminal (_say), so that its last lines do not say a
#: failed switch-off again (:func:`_tube_warning`). Emptied as each source command begins.
_SAID: list[str] = []


def _say(*lines, err=True) -> None:
    """Print, surviving a closed terminal (SIGHUP): the tube has been dealt with already."""
    for line in lines:
        _SAID.append(line)
        try:
            print(line, file=sys.stderr if err else sys.stdout, flush=True)
        except (OSError, ValueError):
            pass


class _OffFailureSaidLast(logging.Filter):
    """Keeps the driver's unconfirmed switch-offs (:data:`acquisition.l8121.OFF_FAILURE`) off the
    terminal of a source command, which says the failure itself, once, right above the X-RAYS
    warning (:func:`_tube_warning`): the driver's fail-safe, an error path's best effort and
    close() each logged their own copy, and the operator read it up to three times, the first
    among other log lines. The records still reach any other handler."""

    def filter(self, record) -> bool:
        from acquisition.l8121 import OFF_FAILURE

        return not getattr(record, OFF_FAILURE, False)


@contextlib.contextmanager
def _off_failures_said_last():
    """:class:`_OffFailureSaidLast` on the terminal's log handlers while a source command runs,
    what an earlier command in this process said forgotten. Taken off as the command ends: left
    on, a program that ran a command through :func:`main` and then drove the source through the
    Python API lost the driver's only "could not confirm X-rays off" line."""
    _SAID.clear()
    installed = []
    for h in logging.getLogger().handlers:
        if not isinstance(h, logging.FileHandler) and getattr(h, "stream", None) in (sys.stderr, sys.stdout):
            f = _OffFailureSaidLast()
            h.addFilter(f)
            installed.append((h, f))
    try:
        yield
    finally:
        for h, f in installed:
            h.removeFilter(f)


def _one_spaced(text: str) -> str:
    return " ".join(str(text).split())


def _tube_warning(src=None) -> None:
    """The X-RAYS warning, the source command's last line. Above it, the switch-off that was not
    confirmed (``src.off_failed``, kept off the terminal's log), unless a line of this command
    said it already (its error line often is that failure)."""
    from acquisition.guardian import TUBE_WARNING

    failed = getattr(src, "off_failed", None)
    if failed is not None:
        port = src.port
        text = _cli_terms(_one_spaced(failed), port)
        core = text.removeprefix(f"{port}: ")
        if not any(core in _one_spaced(line) for line in _SAID):
            _say(f"error: {text}")
    _say(TUBE_WARNING)


def _tube_line(res) -> tuple[str, bool]:
    """The operator's last line: "tube off" only when STS confirmed it."""
    if res is not None and res.tube_off:
        return f"tube off (confirmed by STS: {res.tube_state})", True
    from acquisition.guardian import TUBE_WARNING

    return TUBE_WARNING, False


def _guarded(command, *args) -> int:
    """``command(guard, *args)`` under one signal guard, kept until its last line is printed.

    A stop Python dropped in a finalizer is delivered again a moment later (the guard's
    :meth:`~acquisition.guardian.SignalGuard.settle`); one still on its way as the command ends
    is raised only as the guard is left, after the command decided its exit code and said its
    last line. That line stays the last (the tube's state), and the exit code says the command
    was stopped -- 128 + N, 0 included (the stop came while the command ran) -- unless it is 3,
    the tube not confirmed off, which nothing replaces."""
    from acquisition.guardian import SignalGuard, StopSignal

    code = None
    try:
        with SignalGuard() as guard:
            code = command(guard, *args)
            # decided and said: a stop from now until the process exits is recorded, and turns the
            # console script's exit 0 into 128 + N at its end (radiokit.cli.script; the series'
            # own command has ignored them since its outcome: _series)
            guard.finish()
            if code == 0 and guard.acknowledged is not None:
                # a stop only acknowledged ("please wait": it did not cut the switch-off short):
                # done, the tube confirmed off, but the operator asked to stop, and 0 let `radiokit
                # acquire ... && the next command` go on after the Ctrl-C (bash goes on after a
                # child that handled SIGINT itself): 128 + N, as a stop that raised (review s51rv3)
                code = 128 + guard.acknowledged
    except StopSignal as exc:
        if code is None:  # the command's own, not the guard's as it was left
            raise
        # 3 (the tube not confirmed off) is never replaced. Nor was 0 ("the command had finished
        # when the stop came", review s32-r3), but after finish() the stop signals are only recorded: a
        # stop raised here came while the command ran (lost in a finalizer, delivered again), and
        # 0 let `probe && source on` switch X-rays on after that Ctrl-C: 128 + N, as one only
        # acknowledged (review s52rvacq)
        return code if code == 3 else 128 + exc.signum
    return code


def _run_series(args, p) -> int:
    """Run the series under one signal guard, kept until the last line is printed: no signal can
    interrupt the switch-off or the report of it. Exit codes: 0 done, 1 error, 128 + signal
    number when stopped by a signal (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP, 148 Ctrl-Z), 3 whenever the tube
    could not be confirmed off (the last line then says to switch off at the controller). A
    switch-off not confirmed is said once, above that line, as the source commands say it: the
    driver's CRITICAL line, the series' repeat of it and "detached" came above the error line."""
    with _off_failures_said_last():
        return _guarded(_series, args, p)


def _series(guard, args, p) -> int:
    from acquisition.errors import DeviceError
    from acquisition.protocols.compression_series import run

    again = f"`{resume_command(args)}`"
    try:
        res = run(
            p,
            sim=args.sim,
            resume=args.resume,
            progress=not args.quiet and sys.stderr.isatty(),
            overwrite=args.overwrite,
            guard=guard,
        )
    except KeyboardInterrupt as exc:
        # the outcome is decided (stopped; the tube dealt with): a further Ctrl-C must neither cut
        # the lines below short nor end the process by SIGINT after them (SignalGuard.finish)
        guard.finish(record=False)
        r = getattr(exc, "result", None)
        _say(_stopped_line(exc, r, args, p))
        return _finish(r, 128 + getattr(exc, "signum", 2))
    except Exception as exc:
        guard.finish(record=False)
        r = getattr(exc, "result", None)
        known = isinstance(exc, (DeviceError, OSError, ValueError))
        _say(f"error: {'' if known else type(exc).__name__ + ': '}{_one_line(exc)}")
        if r is not None and r.phase != "connect" and getattr(r, "previous_aside", None) is not None:
            _say(f"stopped in phase {r.phase}; {_aside(r, args)}")
        elif r is not None and r.phase != "connect" and r.previous_kept:
            _say(f"stopped in phase {r.phase}; {_KEPT.format(out=shown_name(r.output))}")
        elif r is not None and getattr(r, "file_removed", False):
            _say(f"stopped in phase {r.phase}; {_REMOVED.format(out=shown_name(r.output))}")
        elif r is not None and getattr(r, "file_lost", False):
            _say(f"stopped in phase {r.phase}; {_lost(r)}")
        elif r is not None and r.phase != "connect":
            _say(
                f"stopped in phase {r.phase}; {r.frames_total} frames saved in {shown_name(r.output)}; {again} completes the series"
            )
        return _finish(r, 1)
    # complete, the tube confirmed off or the warning due: a Ctrl-C from here on (up to 100 ms
    # after the last line, as the interpreter finishes) changes nothing and says nothing -- the
    # exit code included: 0 says the file holds the whole series, which it does (a source
    # command's records it: SignalGuard.finish)
    guard.finish(record=False)
    if res.already_complete:  # completed since _resumable looked (raw data is never modified, DESIGN.md)
        _say(COMPLETE.format(out=shown_name(res.output), n=res.frames_total), err=False)
        return 0
    oh = sorted(res.per_frame_overhead_s)
    med = oh[len(oh) // 2] * 1000 if oh else float("nan")
    _say(
        f"{shown_name(res.output)}: {res.frames_written} frames written ({res.frames_total} in the file) in {res.seconds:.1f} s; "
        f"X-rays on {res.beam_on_s:.1f} s; write + bookkeeping {med:.1f} ms per frame (median)",
        err=False,
    )
    if guard.acknowledged is not None:  # a stop during the closing switch-off: 128 + N (_guarded)
        name = signal.Signals(guard.acknowledged).name
        _say(
            f"stopped by {name} during the closing switch-off; all {res.frames_total} frames saved: the series is complete"
        )
    return _finish(res, 0, err=False)


def _stopped_line(exc, r, args, p) -> str:
    """The line of a series a signal stopped (``exc``; ``r``: its result, if it has one): what
    the file holds, and how it is completed."""
    from acquisition.guardian import StopSignal

    name = exc.name if isinstance(exc, StopSignal) else "SIGINT"
    saved = f"{r.frames_total} frames saved in {shown_name(r.output)}" if r else "nothing saved"
    where = f"\nstopped by {name}{' in phase ' + r.phase if r else ''}"
    if r is not None and getattr(r, "previous_aside", None) is not None:
        return f"{where}; {_aside(r, args)}"
    if r is not None and r.previous_kept:
        return f"{where}; {_KEPT.format(out=shown_name(r.output))}"
    if r is not None and getattr(r, "file_removed", False):
        return f"{where}; {_REMOVED.format(out=shown_name(r.output))}"
    if r is not None and getattr(r, "file_lost", False):
        return f"{where}; {_lost(r)}"
    if r is not None and not r.frames_total and not Path(r.output).exists():  # stopped before it was made
        return f"{where}; no file was made; the same command starts the series"
    if r is not None and _holds_the_whole_series(r, p, args):
        # stopped after its last frame (before the close): "--resume completes it" offered a
        # resume that finds nothing to take
        return f"{where}; all {saved}: the series is complete"
    return f"{where}; {saved}; `{resume_command(args)}` completes it"


def _holds_the_whole_series(r, p, args) -> bool:
    """Whether the experiment file of a stopped run holds every frame of the series (what a
    ``--resume`` would find: nothing to take). False when it cannot be read."""
    if not r.frames_total:
        return False
    from acquisition.protocols.compression_series import _existing, plan

    try:
        return plan(p, _existing(Path(r.output), p, sim=args.sim), warm=True).n_frames == 0
    except Exception:  # (the file unreadable now: the usual line, which offers --resume)
        return False


#: An --overwrite stopped before its first frame: the file it was to replace is there, as it was
#: (a `--resume` would go on with that series, not start the new one).
_KEPT = "no frame taken: {out} holds the previous series, unchanged"
# the file the run made held no frame: left, it only refused the rerun ("exists")
_REMOVED = "no frame taken: {out} was not kept; the same command starts the series again"


# the file was removed while the run wrote it: "N frames saved in" it and --resume were offered
_LOST = "{out} was removed during the run: its {n} frame(s) are lost; the same command starts the series again"


def _lost(r) -> str:
    """What is left of a run whose file was removed under it; the loss said once (the error line
    says it when the removal is what stopped the run)."""
    if any(f"{shown_name(r.output)}: removed while" in line for line in _SAID):
        return "nothing saved; the same command starts the series again"
    return _LOST.format(out=shown_name(r.output), n=r.frames_total)


def _aside(r, args) -> str:
    """An --overwrite stopped before its first frame whose old file could not be put back (the
    folder turned unwritable): where it is, and how it comes back. Not `--resume`: the name holds
    the new run's empty file, and the next run of it puts the old series back first."""

    plain = resume_command(args).removesuffix(" --resume")
    return (
        f"no frame taken: the previous series could not be put back under {shown_name(r.output)}; it is kept in "
        f"{shown_name(r.previous_aside)}. Once the folder is writable, the next `{plain}` (plain, --resume or --overwrite) "
        f"puts it back first; or `mv -f {_shell_word(str(r.previous_aside))} {_shell_word(str(r.output))}`"
    )


def resume_command(args) -> str:
    """The command that completes the file this run writes: every option that chose that file or
    how its devices speak (``-o``, ``--dialect``, ``--sim``), shell-quoted. A hint that left out
    ``-o`` resumed the protocol's own default output, another file, when followed literally."""
    words = ["radiokit", "acquire", args.protocol]
    if args.sim:
        words.append("--sim")
    if args.output:
        words += ["-o", str(args.output)]
    if args.dialect:
        words += ["--dialect", args.dialect]
    return " ".join(_shell_word(w) for w in [*words, "--resume"])


def _shell_word(word: str) -> str:
    """``word`` as a shell reads it back: quoted by :func:`shlex.quote`, unless it holds a
    character a terminal acts on (an escape, a newline) or a backslash -- a name :func:`shown_name`
    prints quoted -- then in bash's ``$'...'``, each such character escaped. Why: a name with
    an escape sequence, quoted by shlex alone, reached the terminal raw in the command offered
    to complete the series."""
    import shlex

    if shown_name(word) == word:
        return shlex.quote(word)
    escaped = (
        "\\" + c
        if c in "\\'"
        else c
        if c.isprintable()
        else f"\\x{ord(c):02x}"
        if ord(c) < 0x80  # (bash's \\xHH is a byte: above 0x7f, the character's code)
        else f"\\u{ord(c):04x}"
        if ord(c) <= 0xFFFF
        else f"\\U{ord(c):08x}"
        for c in word
    )
    return "$'" + "".join(escaped) + "'"


def _one_line(exc) -> str:
    text = exc.strerror if isinstance(exc, OSError) and exc.strerror and exc.filename is None else str(exc)
    return _cli_terms(" ".join(str(text).split())) or type(exc).__name__


def _console_quiet() -> None:
    """No log line on the terminal after this: the operator's last line is the tube's state. A
    thread still unwinding (the simulated panel's beam query, a monitor's last poll) logged after
    the warning under load, and the terminal's last line was then a driver's error, not the
    warning. The notebook's file handlers keep logging."""
    for h in logging.getLogger().handlers:
        if not isinstance(h, logging.FileHandler) and getattr(h, "stream", None) in (sys.stderr, sys.stdout):
            h.setLevel(logging.CRITICAL + 1)


#: The last line when the source's port could not be opened (a mistyped port, a cable not in).
NEVER_REACHED = (
    "radiokit never reached the X-ray controller (its port could not be opened), so it sent no "
    "command and could not have switched X-rays on; check the controller's state at the unit"
)


#: The last line when a run was stopped before its first byte to the source.
NOTHING_SENT = (
    "radiokit never reached the X-ray controller (stopped before its first command), so it sent "
    "nothing and did not change the tube; check the controller's state at the unit"
)

#: The last line when a series was stopped while connecting to the virtual bench's own emulated controller.
QUERIES_ONLY = (
    "radiokit was stopped while connecting to the virtual bench's emulated X-ray controller: it sent "
    "queries at most, nothing that switches X-rays on"
)


def _finish(res, code: int, err: bool = True) -> int:
    """The last line: the tube's state, or the warning (and exit code 3) when it is not confirmed,
    or -- the port never opened, or a signal came before the first command -- that radiokit never
    reached the controller."""
    _console_quiet()
    if res is not None and res.port_never_opened:
        _say(NEVER_REACHED)
        return code or 1
    if getattr(res, "nothing_sent", False):  # (None, or a result of an older shape: no)
        _say(NOTHING_SENT)
        return code
    if getattr(res, "queries_only", False):
        _say(QUERIES_ONLY)
        return code
    if res is None or res.tube_off is None:
        return code
    line, ok = _tube_line(res)
    failed = _one_spaced(getattr(res, "off_failure", "") or "")
    if not ok and failed and not any(failed in _one_spaced(said) for said in _SAID):
        _say(f"error: {_cli_terms(failed)}")
    _say(line, err=err or not ok)
    return code if ok else 3


def _source_refusal(args) -> str | None:
    """Why a source command's options are refused before the port is opened, or None."""
    # an option the action does not read was ignored without a word (`source status --kv 60`)
    unread = [
        option
        for option, value, actions in (
            ("--kv", args.kv, ("on", "warm-up")),
            ("--ua", args.ua, ("on", "warm-up")),
            ("--for", args.hold, ("on",)),
            ("--timeout", args.timeout, ("warm-up",)),
            ("--reply-timeout", args.reply_timeout, ("status", "warm-up", "on", "off")),
            ("--ready-timeout", args.ready_timeout, ("warm-up", "on", "probe")),
        )
        if value is not None and args.action not in actions
    ]
    if unread:
        return (
            f"{', '.join(unread)}: not read by 'source {args.action}' (--kv and --ua are for 'on' and 'warm-up', "
            "--for for 'on', --ready-timeout for those and 'probe', --timeout for 'warm-up', --reply-timeout for all "
            "but 'probe'); "
            "nothing was sent"
        )
    if (hold := _hold_refusal(args)) is not None:
        return hold
    if args.action == "warm-up" and (args.kv is None) != (args.ua is None):
        return "'warm-up' takes --kv and --ua together (or neither: the lowest allowed); nothing was sent"

    if (
        args.baudrate is not None and args.baudrate <= 0
    ):  # argparse took a whole number; the driver warns of an unlisted one
        return f"--baudrate {args.baudrate}: expected a whole number of baud > 0"
    for option, value in (("--reply-timeout", args.reply_timeout), ("--ready-timeout", args.ready_timeout)):
        if value is not None and not (math.isfinite(value) and value > 0):
            return f"{option} {value:g}: expected a positive finite number of seconds; nothing was sent"
    if args.timeout is not None and not (math.isfinite(args.timeout) and args.timeout > 0):
        # refused before the port is opened, as warm_up() would refuse it after TYP and STS (exit 1)
        return (
            f"--timeout {args.timeout:g}: the warm-up time-out must be a positive finite number of "
            "seconds; nothing was sent"
        )
    from acquisition.l8121 import time_refusal  # the configuration's own bounds, said before the port opens
    from radiokit.checks import shown

    for option, value, key in (
        ("--reply-timeout", args.reply_timeout, "timeout_s"),
        ("--ready-timeout", args.ready_timeout, "ready_timeout_s"),
        ("--timeout", args.timeout, "warmup_timeout_s"),
    ):
        if value is not None and (said := time_refusal(key, value)) is not None:
            return f"{option} {shown(value)}: {said}; nothing was sent"
    return None


def _hold_refusal(args) -> str | None:
    """Why ``on``'s ``--for`` is refused, or None: no open-ended beam from a command line (L8121.md:
    the tube is never left on while waiting for a person)."""
    if args.action != "on":
        return None
    if args.hold is None:
        return (
            "'on' needs --for SECONDS: how long X-rays stay on (switched off at its end, or at Ctrl-C); "
            "nothing was sent"
        )
    if not (math.isfinite(args.hold) and 0 < args.hold <= HOLD_MAX_S):
        from radiokit.checks import shown

        return (
            f"--for {shown(args.hold)}: expected a positive number of seconds, at most {HOLD_MAX_S:g} (longer "
            "exposures are a protocol's); nothing was sent"
        )
    return None


def _source(args) -> int:
    with _off_failures_said_last():
        return _source_said_last(args)


def _source_said_last(args) -> int:
    if not args.action:
        print("error: radiokit acquire source needs an action: probe, status, warm-up, on or off", file=sys.stderr)
        return 2
    if not args.port:
        print("error: --port URL is required (e.g. /dev/ttyUSB0 or socket://host:port)", file=sys.stderr)
        return 2
    if (refusal := _source_refusal(args)) is not None:
        print(f"error: {refusal}", file=sys.stderr)
        return 2
    if args.action == "on" and (args.kv is None or args.ua is None):
        print("error: 'on' needs --kv and --ua", file=sys.stderr)
        return 2
    args.whole = None  # the whole kV and µA the driver sends (on, warm-up), once checked
    if args.kv is not None:  # on, warm-up: refused before the port is opened, nothing sent
        from acquisition.l8121 import L8121

        # the driver's own check (ratings, limits, the whole numbers it sends: it rounds half up,
        # and warns; for `on`, the tolerances judged at them), on its configuration, unconnected.
        # on() and warm_up() are given those whole numbers: they check again, but say no rounding
        unconnected = L8121(args.port, baudrate=args.baudrate, dialect=args.dialect or "auto", connect=False)
        try:
            args.whole = unconnected.validate(args.kv, args.ua, exposure=args.action == "on")
        except ValueError as exc:
            said = getattr(exc, "detail", str(exc))  # (SettingRefused: the refusal without its speaker)
            print(f"error: --kv {args.kv:g} --ua {args.ua:g}: {said}; nothing was sent", file=sys.stderr)
            return 2
    from acquisition.errors import PortBusy
    from acquisition.guardian import TUBE_WARNING
    from acquisition.transport import hold_port

    try:
        # the port held from before the probe; the guardian inherits the lock and this command
        # lets its own copy go at the guardian's READY. No other radiokit process reads this
        # controller's replies meanwhile -- but between the guardian's end (or death) and this
        # command's next open the port is unlocked: a program that takes it then gets this
        # command's switch-off refused (PortBusy), which ends loudly (the tube warning, exit 3)
        hold = hold_port(args.port)
    except PortBusy as exc:
        if args.action == "off":  # a switch-off not sent: said loudly, as any the command cannot confirm
            print(f"error: {exc}; XOF not sent: stop that program (it switches off as it ends)", file=sys.stderr)
            _say(TUBE_WARNING)
            return 3
        print(f"error: {exc}", file=sys.stderr)
        return 1
    try:
        return _source_held(args)
    finally:
        if hold is not None:
            hold.release()


def _source_held(args) -> int:
    if args.action == "probe":
        # under the command's signal guard from its first query: outside it, a Ctrl-C with the port
        # open and nothing read off ended on "interrupted" (130) and SIGTERM killed the command
        # without a word, a tube left on by other software on still (review s51rv3)
        return _guarded(_probe_command, args)
    # SIGTERM and SIGHUP (kill, a closed terminal) would otherwise end the process where it stands,
    # a warm-up or a beam left running: the guard turns them, like Ctrl-C, into an exception that
    # switches off first, and defers any further signal until that is done
    return _guarded(_source_guarded, args)


def _probe_command(guard, args) -> int:
    """``source probe``: the queries, the report and :func:`_probe_found`, under ``guard``. A stop
    during the queries ends as `source status` stopped at its connect: nothing that emits was sent,
    and no STS read the tube off -- the warning, exit 3 (the port never written to: 128 + N)."""
    from acquisition.guardian import TUBE_WARNING, StopSignal
    from acquisition.l8121 import SourceConfig, SourceState, probe

    c = SourceConfig(baudrate=args.baudrate)
    state = None
    try:
        result = probe(
            args.port, baudrates=((c.baudrate,) if c.baudrate else ()) + c.probe_baudrates, timeout_s=c.probe_timeout_s
        )
        if result.found:
            state = SourceState.__members__.get(dict(result.details).get("state", ""))
            if state is not None and state.emitting:
                guard.cleanup()  # read on: the switch-off owns the command from here (_probe_ends)
        if result.port_unavailable:  # no rate could be opened: nothing to report of the controller
            # a device error, as for every other source action and a series (README: exit 1), not
            # an option refused (2): the port may be right and its cable out
            print(f"error: {result.summary()}", file=sys.stderr)
            _say(NEVER_REACHED)
            return 1
        print(result.report())
        if not result.found:
            return 1
    except KeyboardInterrupt as exc:  # queries only were sent (the probe's PROBE_QUERIES)
        name = exc.name if isinstance(exc, StopSignal) else "SIGINT"
        if getattr(exc, "probe_sent", None) is False:
            _say(f"stopped by {name}; radiokit never reached the X-ray controller: nothing was sent")
            return 128 + getattr(exc, "signum", 2)
        if state is not None and state.confirms_off:  # stopped as the report was printed
            _say(f"stopped by {name}; tube off (confirmed by STS: {state.name})")
            return 128 + getattr(exc, "signum", 2)
        _say(f"stopped by {name} while probing the controller: no X-ray command was sent, and no STS read the tube off")
        _say(TUBE_WARNING)
        return 3
    try:
        return _probe_found(guard, result, args, state)
    except KeyboardInterrupt as exc:
        # after the report, before the power-on wait's own guard (_probe_waits): it ended on the
        # generic "interrupted", exit 128 + N, not a word of the tube (a state that emits is never
        # here: the switch-off owns the command from the probe's STS on, a stop only acknowledged)
        return _probe_stopped(exc, args, state)


def _probe_stopped(exc, args, state) -> int:
    """The end of a ``source probe`` stopped by ``exc`` once its report was printed: the tube as
    the probe's ``STS`` read it (``state``; None: a word of no state) -- confirmed off, 128 + N;
    else the warning, exit 3, as a stop during the power-on wait ends."""
    from acquisition.guardian import TUBE_WARNING, StopSignal

    name = exc.name if isinstance(exc, StopSignal) else "SIGINT"
    if state is not None and state.confirms_off:
        _say(f"stopped by {name}; tube off (confirmed by STS: {state.name})")
        return 128 + getattr(exc, "signum", 2)
    said = state.said if state is not None else "unknown"
    _say(
        f"{shown_name(args.port)}: stopped by {name} before the controller's power-on checks were waited out; the probe's STS "
        f"read state {said}: the controller has not confirmed the tube off"
    )
    _say(TUBE_WARNING)
    return 3


def _probe_found(guard, result, args, state) -> int:
    """The end of a ``source probe`` whose replies fit a dialect. Exit 0 says the tube confirmed
    off (README: exit codes), and the probe's ``STS`` is what read it: a state that emits (X-rays
    on, B's ``AGING``) is said loudly and switched off as ``source status`` does -- ``source off``
    in the dialect and at the rate found, ``XOF`` confirmed by ``STS`` (exit 0), or not (the
    warning, exit 3). No radiokit command leaves a tube on; the probe sent queries only (no
    ``XOF`` within it: it does not know the dialect until it ends). B's ``STS ERROR`` (pre-heating,
    or a refused query) shows nothing of the tube: the warning, exit 3, with nothing sent (the
    notes' pre-heating, after power-on, is no beam to switch off).

    The wait for the power-on checks, the switch-off and their lines run under one signal guard,
    finished (stop signals recorded, not acted on: :meth:`~acquisition.guardian.SignalGuard.finish`) only once the
    switch-off is confirmed or warned of. Under two, the wait's guard, finished as it ended, left
    the signals ignored until the switch-off's was entered, the tube read on meanwhile."""
    if state is not None and state.confirms_off:  # nothing to wait for or switch off
        return 0
    return _probe_ends(guard, result, args, state)


def _probe_ends(guard, result, args, state) -> int:
    """:func:`_probe_found` under its guard, the probe's ``STS`` having read ``state`` (None: a
    word of no state), which does not confirm the tube off."""
    import argparse

    from acquisition.guardian import TUBE_WARNING

    read = "the probe's STS"  # which reading the lines below report
    if state is not None and not state.emitting:
        # a unit just switched on may still be checking itself (B's STS ERROR is its pre-heating):
        # the probe's one STS said so at power-on, and "X-RAYS MAY STILL BE ON" was a false alarm
        # (review s40rr2). Its checks waited out with queries only, as `source on` waits for them
        found: dict = {}
        if _probe_waits(guard, result, args, state, found) == 3:
            return 3
        # (not `or`: SourceState is an IntEnum, and WARMUP_NEEDED is 0: review s40rr3)
        if found.get("state") is not None:
            state, read = found["state"], "the STS after the power-on checks"
        else:  # the wait's session could not read the controller (silent, refused): said so
            read = "the probe's STS (the wait for the power-on checks read nothing)"
        if state.confirms_off:
            print(f"{shown_name(args.port)}: the controller's power-on checks are over: state {state.said}")
            return 0
    if state is not None and state.emitting:
        # the switch-off owns the command from here: a stop only says "please wait" (raised before
        # `off` has opened the port, it ended on the warning with the tube on, nothing sent), and
        # sets the exit code once the tube is confirmed off (below)
        guard.cleanup()
        _say(
            f"{shown_name(args.port)}: X-RAYS ARE ON ({read} read state {state.name}): switching them off "
            "(`source off`, confirmed by STS); no radiokit command leaves them on (other software, a crash, a power "
            "cut or a hand at the controller did)"
        )
        off = argparse.Namespace(**{**vars(args), "action": "off", "dialect": result.dialect})
        off.baudrate = result.baudrate
        # a stop it only acknowledged meanwhile: 128 + N once confirmed off (_guarded)
        return _source_guarded(guard, off)
    said = state.said if state is not None else "unknown"
    _say(f"{shown_name(args.port)}: {read} read state {said}: the controller has not confirmed the tube off")
    _say(TUBE_WARNING)
    return 3


def _probe_waits(guard, result, args, state, found) -> int:
    """The probe's wait for the power-on checks (:func:`_settled_after_probe`, its outcome put in
    ``found["state"]``) under the command's signal guard: a stop during it (up to --ready-timeout)
    ended with Python's "interrupted" and no word of the tube, whose last STS had not read off
    (review s40rr3). It ends on the warning, exit 3, as the exit rule says."""
    from acquisition.guardian import TUBE_WARNING, StopSignal

    try:
        found["state"] = _settled_after_probe(result, args)
    except KeyboardInterrupt as exc:
        name = exc.name if isinstance(exc, StopSignal) else "SIGINT"
        _say(
            f"{shown_name(args.port)}: stopped by {name} while waiting out the controller's power-on checks; its last STS read "
            f"state {state.said}: the controller has not confirmed the tube off"
        )
        _say(TUBE_WARNING)
        return 3
    return 0


def _settled_after_probe(result, args):
    """The state once the controller's power-on checks are over (:meth:`L8121.settled_status`, at
    most ``--ready-timeout`` s), in the dialect and at the rate the probe found; None when it
    cannot be read. Queries only (``control=False``)."""
    from acquisition.errors import DeviceError
    from acquisition.l8121 import L8121

    ready = {} if args.ready_timeout is None else {"ready_timeout_s": args.ready_timeout}
    try:
        with L8121(args.port, baudrate=result.baudrate, dialect=result.dialect, control=False, **ready) as src:
            return src.settled_status()
    except DeviceError:
        return None


def _source_guarded(guard, args) -> int:
    from acquisition.guardian import TUBE_WARNING, StopSignal

    try:
        return _source_command(args, guard)
    except KeyboardInterrupt as exc:
        name = exc.name if isinstance(exc, StopSignal) else "SIGINT"
        _say(f"stopped by {name}; {getattr(exc, 'tube', TUBE_WARNING)}")  # tube: what is known
        if getattr(exc, "off_failed", None) is not None or getattr(exc, "may_be_on", False):
            _say(TUBE_WARNING)
            return 3
        return 128 + getattr(exc, "signum", 2)


def _source_command(args, guard) -> int:
    """Connect and run one source action. Any exception switches off (signals deferred meanwhile)
    before it propagates; an interrupt carries in ``tube`` what is known of the tube (unconfirmed,
    it becomes the switch-off error instead)."""
    from acquisition.errors import DeviceError
    from acquisition.guardian import guardian_gone

    src = None
    try:
        # made before it connects, so that a failed connect still tells what it reached (the exit rule)
        src = _source_driver(args, guard)
        try:
            # the warm-up and the held beam emit: a guardian holds the port (kill -9 gets its XOF)
            src = _behind_guardian(src) if args.action in ("warm-up", "on") else src
            src.connect()
        except KeyboardInterrupt as exc:  # connect sends queries only, and XOF if it found the tube on
            guardian_gone(src, exc)
            exc.tube = _interrupted_connect(exc)
            if getattr(exc, "tube_state", None) is None and getattr(exc, "off_failed", None) is None:
                # no switch-off in connect: one is tried now (signals deferred: the guard stays
                # stopping) by a command that controls the tube -- `off` asked for it, and every
                # other exit of `on` and `warm-up` leaves the tube off too (`off` alone also when the
                # interrupted probe found no dialect). README's one rule then: reached and not
                # confirmed off -- a tube left on (other software, a crash) may be on still -- the warning;
                # `off` that never reached the controller too (as when the port fails)
                tried = args.action != "status" and _off_anyway(src, exc, blind=args.action == "off")
                confirmed = tried or src.tube_confirmed_off
                exc.may_be_on = not confirmed and (src.port_opened or args.action == "off")
            elif getattr(exc, "tube_state", None) is not None and not getattr(exc, "guardian_off", False):
                # connect's own XOF, confirmed -- by the unit now at a reopened port (unit_unverified)?
                exc.may_be_on = not src.tube_confirmed_off
                exc.tube += " by the unit now at the reopened port, known only by its model" if exc.may_be_on else ""
            raise
        except DeviceError as exc:
            if args.action == "off":
                guard.cleanup()  # the switch-off asked for, whatever the connect found
                _off_anyway(src)
            guardian_gone(src, exc)  # then switched off after the error line (below)
            raise
        try:
            code = _source_action(src, args, guard)
            guard.settle()  # a stop lost meanwhile switches off like any other
        except KeyboardInterrupt as exc:
            # XOF whatever this command had begun (always accepted): the line then states the tube.
            # Not confirmed: off() raises the error that says to switch off at the controller, and
            # the link is let go without a second round of attempts (close() would repeat them)
            try:
                if src.off_failed is not None:  # the interrupted call's own switch-off failed already
                    raise src.off_failed
                exc.tube = f"tube off (confirmed by STS: {src.off().name})"
            finally:
                if src.off_failed:
                    src.detach()
                else:
                    src.close()
            raise
        except BaseException as exc:
            guard.cleanup()  # from here a signal must not cut the switch-off short
            _close_after(src, exc)  # a failed command leaves the tube off, or close() raises that it may not be
            raise
        # decided and said: a Ctrl-C as the link is let go (close()) ended `source on` on "stopped by
        # SIGINT; WARNING: X-RAYS MAY STILL BE ON", the tube confirmed off the line before
        guard.finish()
        src.close()
        return code
    except (DeviceError, ValueError) as exc:
        _say(f"error: {_cli_terms(str(_one_fault(exc, src)), args.port)}")
        if getattr(exc, "guardian_gone", False):
            guard.cleanup()  # a switch-off nobody confirmed: a signal must not cut it short
            _off_anyway(src)  # its outcome the last line; not confirmed, the exit rule's warning
        return _source_error_code(exc, src, args)


def _source_driver(args, guard):
    """The source command's driver, not connected. A stop as it is built (before a byte, the port
    not opened by this command): `off` goes on, the stop only acknowledged; any other action says
    nothing was sent (its ``tube``) and raises it."""
    from acquisition.l8121 import L8121

    times = {"timeout_s": args.reply_timeout, "ready_timeout_s": args.ready_timeout}
    driver = functools.partial(
        L8121,
        args.port,
        baudrate=args.baudrate,
        dialect=args.dialect or "auto",
        control=args.action != "status",
        connect=False,
        **{key: value for key, value in times.items() if value is not None},
    )
    try:
        return driver()
    except KeyboardInterrupt as exc:
        if args.action != "off":
            exc.tube = "radiokit never reached the X-ray controller: nothing was sent"
            raise
        # the switch-off asked for goes on (it ended on the warning with nothing sent, exit 128 + N
        # beside it, a tube left on on still): the stop only acknowledged, as one that comes during
        # the switch-off is, its 128 + N once the tube is confirmed off (_guarded)
        guard.cleanup()
        if guard.acknowledged is None:
            guard.acknowledged = getattr(exc, "signum", signal.SIGINT)
        _say(f"{signal.Signals(guard.acknowledged).name} received: switching the X-ray tube off first, please wait")
        return driver()


def _close_after(src, exc: BaseException) -> None:
    """``src.close()`` after the command failed with ``exc``. The switch-off error it raises (the
    tube not confirmed off) keeps ``exc`` as its ``fault``: why it was switching off, which the
    error line names first (:func:`_one_fault`)."""
    from acquisition.errors import DeviceError

    try:
        src.close()
    except DeviceError as off_exc:
        off_exc.fault = exc
        raise


def _one_fault(exc, src):
    """What a source command's error line says for ``exc``: ``exc``, or, when B's operate switch
    off REMOTE refused the connect and then its XOF, the switch-off's error, which names the
    switch and what to do, and says the tube is not confirmed off. The connect's said only the
    first half, and on a line of its own: two `error:` lines for one fault. A switch-off that
    failed as the link closed after a fault (``exc.fault``) is said after that fault: the line
    said only "could not confirm X-rays off", not why it was switching off (s43)."""
    failed = getattr(src, "off_failed", None)
    # the switch-off's error names the switch (its field, not its words: they are the operator's)
    if getattr(exc, "operate_switch", None) and getattr(failed, "operate_switch", None) is not None:
        return failed
    fault = getattr(exc, "fault", None)
    if isinstance(fault, Exception) and str(fault) and str(fault) not in str(exc):
        port = f"{src.port}: " if src is not None else ""
        off = getattr(fault, "switch_off", None)
        # a fault whose own switch-off was not confirmed: its cause alone, the switch-off's error
        # says the rest in full (the fault's "could not be confirmed" said it twice)
        said = f"{shown_name(off.port)}: {off.cause}" if off is not None and not off.confirmed else str(fault)
        return f"{said}; switching X-rays off: {str(exc).removeprefix(port)}"
    return exc


def _interrupted_connect(exc) -> str:
    """What an interrupted connect (its ``exc``) left of the tube, for the last line."""
    # who switched off: the connect's own driver (it read X-rays on), or the guardian whose start was cut short
    guardian = getattr(exc, "guardian_off", False)
    # the connect's own XOF before any STS had read the tube (L8121._off_for_unread_interrupt): no
    # X-rays were seen on, and "X-rays were on" would say they were
    unread = getattr(exc, "state_unread", False)
    if getattr(exc, "off_failed", None) is not None:  # + the warning
        was = "X-rays may be on" if guardian or unread else "X-rays were on"
        return f"{was}; switching them off failed ({exc.off_failed})"
    if getattr(exc, "tube_state", None) is not None and unread and not guardian:
        # the words off_anyway's XOF ends on: the same switch-off, sent by the connect itself
        return f"XOF sent anyway: X-rays off (confirmed by STS: {exc.tube_state.name})"
    if getattr(exc, "tube_state", None) is not None:
        who = "switched off by the X-ray guardian" if guardian else "X-rays were on"
        return f"{who}: tube off (confirmed by STS: {exc.tube_state.name})"
    if getattr(exc, "probe_sent", None) is False:
        return "radiokit never reached the X-ray controller: nothing was sent"
    return "interrupted while connecting: no X-ray command was sent"


def _behind_guardian(src):
    """``src``'s controller behind a guardian process (:mod:`acquisition.guardian`), as a series'
    is: the warm-up emits X-rays for minutes (``on`` for its ``--for``), and L8121.md has an interrupted warm-up switched off
    like an exposure, ``kill -9`` of this process included, which only another process can do (it
    left B's warm-up, which may run on into X-rays on, on for good). The dialect is resolved first
    (``auto`` probes), the guardian opens the port in it; the returned driver is not connected
    yet and knows what the probe read (``take_over``)."""
    from acquisition.errors import PortUnavailable
    from acquisition.guardian import start_guardian
    from acquisition.l8121 import L8121
    from acquisition.protocols.compression_series import SourceSettings

    resolved = src.resolve()
    try:
        link = start_guardian(
            src.port, resolved, watchdog_s=SourceSettings.watchdog_s, armed=not src.tube_confirmed_off
        )
    except PortUnavailable as exc:
        if src.probe_result is not None and src.probe_result.found:
            # the probe reached the controller, then the guardian could not take the port (another
            # program took it, the adapter dropped out): not "never reached" -- what it read, as a series says
            raise src.port_lost_after_probe(exc) from exc
        raise
    guarded = L8121(link, connect=False, config=resolved)
    guarded.take_over(src)
    return guarded


def _off_anyway(src, interrupt: BaseException | None = None, *, blind: bool = True) -> bool:
    """:func:`acquisition.guardian.off_anyway`, its error in command-line terms."""
    from acquisition.guardian import off_anyway

    return off_anyway(src, interrupt, blind=blind, describe=_one_line, say=_say)


def _source_error_code(exc, src, args) -> int:
    """The last line and the exit code of a source command that failed with ``exc`` (its error
    line already printed). One rule, as for a series (README: the exit codes): the port never
    opened -- "never reached" and 1 (`off`: the warning and 3, a tube left on before it (other software, a crash)
    is on still); the port opened and the controller did not confirm the tube off (no reply, a
    refused or garbled STS, a switch-off not confirmed, X-rays found on and left on) -- the
    warning and 3, whoever switched the tube on; else 1."""
    if src is None:  # the driver refused its configuration: nothing was opened
        return 1
    if getattr(exc, "guardian_off", False):
        # a guardian whose start failed held the port and switched off before it exited: its own
        # STS read the tube off (trusted as a connect's), or it could not confirm (the warning,
        # even when this process never opened the port: the guardian did)
        state = getattr(exc, "tube_state", None)
        if getattr(exc, "off_failed", None) is None and state is not None and state.confirms_off:
            _say(
                f"{shown_name(src.port)}: switched off by the X-ray guardian: tube off (confirmed by STS: {state.name})"
            )
            return 1
        _tube_warning(src)
        return 3
    if not src.port_opened and args.action != "off":
        # not a byte sent: the same last line and exit code as a series that could not open its port
        _say(NEVER_REACHED)
        return 1
    if not src.tube_confirmed_off:
        _tube_warning(src)
        return 3
    state = src.confirmed_off or src.last_state
    after_all = getattr(exc, "off_not_confirmed", False)  # an off() that could not confirm
    # said already: by the error line, or by "XOF sent anyway" (off's connect, a guardian gone)
    said = getattr(exc, "tube_said", False) or getattr(exc, "guardian_gone", False)
    said = said or (args.action == "off" and not after_all)
    if args.action != "status" and not said and state is not None:
        # the error line alone was the last: an `on` or `warm-up` whose connect failed and then
        # sent XOF (one STS late), or an `off` whose attempts ran out before close()'s last one
        # was confirmed (review s38b): the tube's state is the last line, as the exit rule reads it
        how = "X-rays off after all (a last XOF as the port closed): " if after_all else ""
        _say(f"{shown_name(src.port)}: {how}tube off (confirmed by STS: {state.name})")
    return 1


def _failed_on(exc, src, args):
    """The error a failed ``on`` or ``warm-up`` ends on: ``exc`` in command-line terms and what
    it left the tube in (:func:`_after_failed_on`); ``tube_said`` when that says the state. A
    fault the driver switched off for (``exc.switch_off``) is worded from that outcome
    (:func:`_off_line`), which the returned error keeps."""
    from acquisition.errors import DeviceError

    after = _after_failed_on(src, args)
    off = getattr(exc, "switch_off", None)
    if off is None:
        err = DeviceError(_cli_terms(str(exc), args.port) + after)
        err.tube_said, err.off_not_confirmed = bool(after), getattr(exc, "off_not_confirmed", False)
        return err
    err = DeviceError(_cli_terms(_off_line(off, after), args.port))
    err.switch_off, err.tube_said = off, off.confirmed or bool(after)
    return err


def _off_line(off, after: str = "") -> str:
    """The line for a fault the driver switched off for (its :class:`~acquisition.l8121.OffOutcome`):
    the cause, then the switch-off once, with the state ``STS`` confirmed ("X-rays switched off,
    confirmed by STS: STANDBY"; the line said the switch-off twice, s43rr2) and the controller's
    error code; or that it was not confirmed, and ``after``: what a later try found."""
    if off.confirmed:
        line = f"{shown_name(off.port)}: {off.cause}; X-rays switched off, confirmed by STS: {off.state.name}"
    else:
        line = f"{shown_name(off.port)}: {off.cause}; switching X-rays off could not be confirmed{after}"
    return line + (f"; controller error code {off.error_code}" if off.error_code else "")


def _after_failed_on(src, args) -> str:
    """What a refused or failed ``on`` (or ``warm-up``) left the tube in, for the end of its error
    line. on() switches off (confirmed) after any failure past its XON; a tube already on when it
    began (left on by other software, a crash: on() refuses to change a beam it did not start, warm_up() to
    start a warm-up) is switched off here,
    not left to close(): the project's rule is the tube off on every exit but a successful `on`'s,
    and the operator asked for other values, not for the old beam to go on. The line says so; a
    switch-off not confirmed raises, and the caller ends on the X-rays warning (exit 3)."""
    if src.off_failed is not None:
        return ""
    if src.may_be_on:
        state = src.off()
        return (
            f"; they were (or may have been) on from before this command (other software, a crash) and are now "
            f"off, confirmed "
            f"by STS: {state.name}; run the same command again to "
            + (f"switch them on at {args.kv:g} kV {args.ua:g} uA" if args.action == "on" else "warm up")
        )
    state = src.confirmed_off
    if state is not None:
        return f"; X-rays off, confirmed by STS: {state.name}"
    if src.tube_confirmed_off:
        # refused before anything that emits was sent (warm-up needed, interlock open): the line
        # ended on the controller's state, not on whether X-rays are off (README: exit code 1)
        return f"; X-rays off, confirmed by STS: {src.last_state.name} (nothing that emits sent since)"
    return ""


def _warm_up_line(src, args, seconds: float) -> str:
    """What a finished ``source warm-up`` did, and at which settings (the warm-up emits)."""
    values = src.warmup_values
    if values is None and src.warmup_joined:
        given = f"; --kv {args.kv:g} --ua {args.ua:g} not applied" if args.kv is not None else ""
        return (
            f"a warm-up already running (started before this command, at the controller's settings) "
            f"ended after {seconds:.1f} s of waiting{given}"
        )
    if values is None:
        given = f" (--kv {args.kv:g} --ua {args.ua:g} not set: no warm-up to run)" if args.kv is not None else ""
        return f"no warm-up needed: nothing sent that emits{given}"
    kv, ua, given = values
    how = "--kv/--ua" if given else "the lowest the configuration allows; --kv/--ua choose"
    return f"warmed up in {seconds:.1f} s; set {kv} kV {ua} uA before it started, read back by the controller ({how})"


#: Python calls the driver's messages name, and what a command-line user does instead.
_CLI_TERMS = (
    (" (use set_values() or off())", ""),
    ("; call off() before warm_up()", ""),  # the CLI switches off, and says so (_after_failed_on)
    ("(call warm_up())", "(`radiokit acquire source warm-up --port {port}`)"),
    ("(or raise [source] ready_timeout_s)", "(or raise --ready-timeout)"),
    # there is no reset action: an overload needs a person at the tube first (L8121.md: no automatic RST)
    ("then reset() by hand", "then reset the overload by hand (RST; no `radiokit acquire source` action sends it)"),
    (
        "(configure model=None to accept any model)",
        '(the source commands expect that model; a protocol\'s [source] model = "" accepts any)',
    ),
)


def _cli_terms(text: str, port: str | None = None) -> str:
    """``text`` with the Python calls of the driver's messages in command-line terms."""
    for api, cli in _CLI_TERMS:
        text = text.replace(api, cli.format(port=port or "URL"))
    return text


def _hold_beam(src, args, reading) -> None:
    """``on``'s beam held for ``--for`` s, polled as a series' beam monitor polls an exposure
    (:meth:`~acquisition.l8121.L8121.check` every ``[source] poll_s``, which also keeps the
    guardian's watchdog fed): an open interlock, an overload, a dropped beam or a controller
    error code (``SER``, read at most once a second) switches off and raises. One line says when it ends; a bar counts down on a terminal only (as ``warm-up``)."""
    import time

    from acquisition.protocols.compression_series import SourceSettings

    start, end = time.time(), time.monotonic() + args.hold
    print(
        f"{shown_name(args.port)}: X-rays ON at {reading['set_voltage_kv']} kV {reading['set_current_ua']} uA (measured "
        f"{reading['voltage_kv']:g} kV {reading['current_ua']:g} uA) until "
        f"{time.strftime('%H:%M:%S', time.localtime(start + args.hold))} ({args.hold:g} s); Ctrl-C switches them off",
        flush=True,
    )
    bar = None
    if not args.quiet and sys.stderr.isatty():
        from radiokit.progress import tqdm

        # at least one step: a hold under half a second had a bar of 0 s, which tqdm drew as a
        # bare "0s" that never moved (no countdown)
        bar = tqdm(total=max(1, round(args.hold)), desc=f"X-rays on ({shown_name(args.port)})", unit="s", leave=False)
    try:
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(SourceSettings.poll_s, left))
            src.check()
            if bar is not None:  # the time gone, on the bar's scale: full when the hold is over
                gone = 1.0 - max(end - time.monotonic(), 0.0) / args.hold
                bar.n = min(round(bar.total * gone), bar.total)
                bar.refresh()
    finally:
        if bar is not None:
            bar.close()


def _source_status(src, args) -> int | None:
    """``source status``: the state, measured beam, interlock (and B's operate switch) printed;
    a tube found or read emitting switched off and confirmed. An exit code when it decides one
    (an operate switch off REMOTE), else None: the exit rule of :func:`_source_action`."""
    kv, ua = src.measured()
    state = src.status()
    switch = src.switch_at_connect
    print(
        f"{shown_name(args.port)}: dialect {src.dialect.name} at {src.baudrate} baud, state {state.said}, "
        f"measured {kv:g} kV {ua:g} uA, interlock {'closed' if src.interlock_closed() else 'OPEN'}"
        f"{', operate switch ' + switch if switch else ''}"
    )
    if switch not in (None, "REMOTE"):
        # queries are answered, but the controller refuses XOF: a beam that is or may be on
        # (B's AGING and its ambiguous ERROR included) cannot be switched off from here
        if not state.confirms_off:
            _say(
                f"{shown_name(args.port)}: X-rays {'are' if state.emitting else 'may be'} on (state {state.name}) and the "
                f"operate switch is {switch}: radiokit cannot switch them off (remote control needs REMOTE)"
            )
            _tube_warning(src)
            return 3
        print(
            f"{shown_name(args.port)}: the operate switch is {switch}: `source on`, `off` and `warm-up` need it on REMOTE"
        )
        return 0
    if state.emitting:
        # the driver lets no link go with X-rays on (only `on` detaches): close() switched them
        # off after the line above said XRAY_ON, and the operator's last line was no longer true
        print(
            f"{shown_name(args.port)}: X-rays were on: switched off (confirmed: state {src.off().name}); "
            "no radiokit command leaves them on (other software, a crash, a power cut or a hand at the controller did)"
        )
    elif state.confirms_off and src.may_be_on:
        # found emitting at connect, read off now (a trip, a hand at the panel): that reading
        # does not clear what connect saw (nothing confirmed a switch-off), so switch off and
        # confirm, and say so; it ended on the warning, exit 3, though close() then confirmed off
        print(
            f"{shown_name(args.port)}: X-rays read on at connect, off now (state {state.name}): XOF sent and "
            f"confirmed (state {src.off().name})"
        )
    elif not state.confirms_off and (kv > 0 or ua > 0):
        # B's STS ERROR (pre-heating by L8121.md, and what a refusal looks like) says nothing
        # of the tube, and a beam is measured (left on by other software, a crash): switch off and confirm;
        # not confirmed, off() raises and the command ends on the warning (exit 3). With
        # nothing measured it is the pre-heating the notes name, and only reported
        print(
            f"{shown_name(args.port)}: state {state.name} does not show X-rays off and a beam is measured: switching off",
            flush=True,
        )
        print(f"{shown_name(args.port)}: switched off (confirmed: state {src.off().name})")
    elif not state.confirms_off:
        # nothing measured, but B's ERROR is also how B refuses a query: the controller has
        # not confirmed the tube off, and the exit rule says so (README: exit codes)
        _say(
            f"{shown_name(args.port)}: state {state.name} does not show X-rays off (B's STS ERROR: pre-heating, or a "
            "refused query); nothing is measured, but the controller has not confirmed the tube off"
        )
    return None


def _source_action(src, args, guard=None) -> int:
    """``status``, ``warm-up``, ``on`` or ``off`` on the connected ``src``; prints the outcome.
    Before the warm-up and the XON, a stop the guard raised that never reached the command (a
    library's bare ``except:`` swallowed it inside an import) is raised again, as a series does
    before each (:meth:`~acquisition.guardian.SignalGuard.raise_if_lost`)."""
    from acquisition.errors import DeviceError

    lost = getattr(guard, "raise_if_lost", lambda: None)

    if args.action == "status":
        code = _source_status(src, args)
        if code is not None:
            return code
    elif args.action == "warm-up":
        try:
            kv, ua = args.whole or (None, None)  # (checked and rounded before the port was opened)
            lost()  # no warm-up (it emits) after a stop that never reached the command
            seconds = src.warm_up(timeout_s=args.timeout, progress=not args.quiet and sys.stderr.isatty(), kv=kv, ua=ua)
        except DeviceError as exc:
            raise _failed_on(exc, src, args) from exc
        print(f"{shown_name(args.port)}: {_warm_up_line(src, args, seconds)}, state {src.status().name}")
    elif args.action == "on":  # --kv, --ua and --for: given and within bounds (checked in _source)
        # said before XON: killed in the ramp (kill -9, no handler runs) this command has no later
        # line; the guardian's XOF is what ends the beam then
        src.before_xon = lambda kv, ua: print(
            f"{shown_name(args.port)}: switching X-rays ON at {kv} kV {ua} uA for {args.hold:g} s: switched off at its end, "
            "or at Ctrl-C",
            flush=True,
        )
        try:
            lost()  # no XON after a stop that never reached the command
            r = src.on(*args.whole)  # (checked and rounded before the port was opened)
            _hold_beam(src, args, r)
        except DeviceError as exc:
            raise _failed_on(exc, src, args) from exc
        print(f"{shown_name(args.port)}: {args.hold:g} s over: tube off (confirmed by STS: {src.off().name})")
    else:
        src.off()
        print(f"{shown_name(args.port)}: X-rays off (confirmed: state {src.status().name})")
    if not src.tube_confirmed_off:  # the exit rule (README: exit codes)
        _tube_warning(src)
        return 3
    return 0
