"""Fixtures and paths shared by the test modules.

The vendor files live in ``../shared`` beside the repository (the only place they are promised);
tests that need them are marked ``needs_itex`` and skip with a message naming the missing folder.
"""

import atexit
import contextlib
import io
import locale
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from radiokit.io import ExperimentWriter, ImageKey

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
ITEX_DIR = SHARED / "data" / "hamamatsu_itex"

needs_itex = pytest.mark.skipif(
    not ITEX_DIR.is_dir(), reason=f"{ITEX_DIR}: the shared vendor files are not beside the checkout (../shared)"
)


def pytest_configure(config):
    """One thread a library in each of the suite's six xdist workers on CI's two cores: radiokit's
    pool, OpenBLAS and OpenCV each ran two, which only contended for the same cores (OpenBLAS's
    threads spin while they wait), and the suite took ~9 % more CPU (benchmarks/README.md, "The
    suite's time, session 45"). In the environment for the commands the tests start and for the
    libraries not yet loaded, and through threadpoolctl for those loaded (numpy's, scipy's). Here and
    not at import: a Dask worker that imports a test module (to run one of its functions) imports
    this file too, and must keep its own environment. The tests of the threaded paths set their own
    (test_correct, test_register, test_pipeline's Dask workers)."""
    import cv2
    import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS, so that the limit below reaches it)
    from threadpoolctl import threadpool_limits

    for name in ("RADIOKIT_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    threadpool_limits(limits=1)
    cv2.setNumThreads(1)
    # Ctrl-C as a terminal's shell gives it: a suite started in the background (`make test &`,
    # nohup) inherits SIGINT ignored, Python then installs no KeyboardInterrupt handler, and the
    # commands the tests start inherit the ignore, so every test of a stop by SIGINT failed
    # ("finished" where "interrupted" was due; session 46). A handled signal is reset to its
    # default in a child, an ignored one stays ignored.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_report_header(config):
    found = "found" if ITEX_DIR.is_dir() else "MISSING: tests that need them skip"
    return f"shared vendor files: {ITEX_DIR} ({found})"


def one_line_error(res, *needles):
    """Exit code 2, no traceback, one line on stderr naming every needle."""
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert str(needle) in lines[0], (needle, lines[0])
    return lines[0]


#: synthetic()'s experiments as first written in this process, by their arguments
_SYNTHETIC_BUILT: dict[tuple, Path] = {}


def synthetic(path, scale=1.0, shape=(160, 160), n_per_step=1, noise=0.0):
    """A slab thinned by compression with a denser square (pipeline's test experiment; noiseless, the
    background's standard deviation is exactly zero, so every CNR is infinite); with
    ``noise`` counts of Gaussian noise, so that outputs do not compress to nothing.

    Its frames are the same for the same arguments (the noise is seeded), so each experiment is
    written once per process and copied afterwards (a file's bytes; only the times recorded in
    it are the first writing's): about 150 tests each wrote one, 40 ms to a few seconds each.
    A name already taken (a file, a link, a dangling link) gets the writer itself, which refuses
    it or writes through the link as it does."""
    import shutil

    path = Path(path)
    key = (float(scale), tuple(shape), int(n_per_step), float(noise))
    built = _SYNTHETIC_BUILT.get(key)
    if built is None or not built.is_file():
        built = Path(tempfile.mkdtemp(prefix="radiokit-synthetic-")) / "exp.h5"
        _write_synthetic(built, scale, shape, n_per_step, noise)
        atexit.register(shutil.rmtree, built.parent, True)
        _SYNTHETIC_BUILT[key] = built
    if path.exists() or path.is_symlink():
        return _write_synthetic(path, scale, shape, n_per_step, noise)
    shutil.copyfile(built, path)
    return path


def _write_synthetic(path, scale, shape, n_per_step, noise):
    rng = np.random.default_rng(0)
    rows, cols = shape
    rr, cc = np.mgrid[0:rows, 0:cols]
    sq = (abs(rr - 80) < 10) & (abs(cc - 80) < 10)
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:  # a C7942 file, its pitch recorded
        for _ in range(3):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full(shape, 3100, np.uint16), image_key=ImageKey.FLAT)
        for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
            L = scale * (0.08 * tb + 0.03 * ti * sq)
            for _ in range(n_per_step):
                counts = 100 + 3000 * np.exp(-L) + rng.normal(0, noise, shape)
                w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    return path


# -- inputs built once per module -------------------------------------------------------------------
# An input that costs seconds to build (a long experiment, a `process` run) and that several tests
# only read is built once by a module-scoped fixture: read_only() marks it so that a test writing
# into it fails (where the suite does not run as root) instead of handing its neighbours another
# input; a test that changes its input works on writable_copy() of it in its own tmp_path.


def built_once(tmp_path_factory, name, build):
    """``build(folder)``'s value, built once in the whole run rather than once in each xdist worker
    that takes one of its users: worksteal splits a module between workers, and test_pipeline's
    simulated experiment was simulated in four of them and processed in three (about 50 of the
    suite's ~1000 CPU s, session 45). The first worker to ask builds it in a folder of the run's
    shared temporary folder, under a lock; the others wait on the lock and read the pickled value.
    What ``build`` writes in ``folder`` is every user's: they only read it. A build that fails
    leaves nothing behind, and the next worker to ask tries again (and fails as loudly)."""
    import fcntl
    import pickle
    import shutil

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # pytest-of-USER/pytest-N: the run's, above each worker's popen-gwN
    done = base / f"built-once-{name}.pickle"
    with open(base / f"built-once-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if this worker dies
        if done.exists():
            return pickle.loads(done.read_bytes())
        folder = base / f"built-once-{name}"
        shutil.rmtree(folder, ignore_errors=True)  # an attempt that failed
        folder.mkdir()
        value = build(folder)
        part = done.with_suffix(".part")
        part.write_bytes(pickle.dumps(value))
        part.replace(done)
        return value


def read_only(path):
    """``path`` (a file, or every file under a folder) made read-only; returned."""
    path = Path(path)
    for p in [path, *path.rglob("*")] if path.is_dir() else [path]:
        if p.is_file():
            p.chmod(p.stat().st_mode & ~0o222)
    return path


def writable_copy(src, dst):
    """A copy of the file or folder ``src`` at ``dst`` (contents and times), its files writable by
    their owner again; returns ``dst``."""
    import shutil

    src, dst = Path(src), Path(dst)
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy2(src, dst)
    for p in [dst, *dst.rglob("*")] if dst.is_dir() else [dst]:
        if p.is_file():
            p.chmod(p.stat().st_mode | 0o200)
    return dst


# -- the command run in this process -------------------------------------------------------------
# Starting `python -m radiokit.cli` costs 0.4-0.9 s of CPU (imports) per call, and most CLI tests
# only check what a bad input prints and returns. run_cli runs radiokit.cli.main(argv) here
# instead, as the subprocess helpers did: the same argv, stdout and stderr as text decoded as
# `subprocess.run(text=True)` decodes a child's (the locale's encoding, universal newlines),
# warnings ignored (the helpers set PYTHONWARNINGS=ignore), stdout and stderr not terminals (no
# progress bars). Tests that need a process of their own (signals, rlimits, a possible hang, the
# encodings set through the environment, imports, the console script) keep the subprocess.
_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGPIPE") if hasattr(signal, name)
)


#: the loggers radiokit's commands set levels on (radiokit.cli, radiokit.pipeline): made before
#: the run, so that their state is saved and put back
_COMMANDS_LOGGERS = ("tifffile", "distributed")


def _logging_state():
    for name in _COMMANDS_LOGGERS:
        logging.getLogger(name)
    loggers = [logging.root, *(lg for lg in logging.root.manager.loggerDict.values() if isinstance(lg, logging.Logger))]
    return [
        (lg, lg.level, list(lg.handlers), lg.propagate, lg.disabled) for lg in loggers
    ], logging.root.manager.disable


def _restore_logging(state):
    # loggers first made during the run are left as their modules' imports configured them: an
    # import's configuration stays in a process whichever test imported the module first
    loggers, disable = state
    for lg, level, handlers, propagate, disabled in loggers:
        lg.setLevel(level)
        lg.handlers[:] = handlers
        lg.propagate, lg.disabled = propagate, disabled
    logging.disable(disable)


class _FdCapture:
    """What C code (libhdf5, a library's own printf) writes to file descriptor 1 or 2: a child's
    stderr held it, so a test counting stderr's lines must see it too."""

    def __init__(self, fd):
        self.fd, self.file = fd, tempfile.TemporaryFile()
        self.saved = os.dup(fd)
        os.dup2(self.file.fileno(), fd)

    def restore(self) -> bytes:
        os.dup2(self.saved, self.fd)
        os.close(self.saved)
        self.file.seek(0)
        data = self.file.read()
        self.file.close()
        return data


def _decode(data: bytes, encoding: str) -> str:
    # as subprocess.run(text=True) reads a pipe: a TextIOWrapper, universal newlines, strict
    return io.TextIOWrapper(io.BytesIO(data), encoding=encoding).read()


def run_cli(*args, env=None, cwd=None) -> subprocess.CompletedProcess:
    """``radiokit ARGS`` run in this process: its exit code, stdout and stderr as a
    ``subprocess.CompletedProcess``. Everything ``main`` may change (signal handlers, logging,
    warnings, the environment, the working directory, the umask, sys.argv, the standard streams)
    is restored afterwards. An exception ``main`` lets through (a bug: a traceback) is raised
    here, failing the test."""
    from radiokit.cli import main

    argv = [str(a) for a in args]
    encoding = locale.getpreferredencoding(False)
    out_bytes, err_bytes = io.BytesIO(), io.BytesIO()
    saved_streams, saved_argv, saved_env = (sys.stdout, sys.stderr), sys.argv, dict(os.environ)
    saved_cwd, saved_umask = os.getcwd(), os.umask(0o022)
    os.umask(saved_umask)
    saved_signals = {sig: signal.getsignal(sig) for sig in _SIGNALS}
    saved_formatwarning, saved_showwarning = warnings.formatwarning, warnings.showwarning
    saved_logging = _logging_state()
    for stream in saved_streams:
        stream.flush()
    fds = [_FdCapture(1), _FdCapture(2)]
    code, out_text, err_text = None, None, None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            os.environ.update({k: str(v) for k, v in (env or {}).items()})
            if cwd is not None:
                os.chdir(cwd)
            # as in a fresh process: no handler on the root logger (pytest adds its own), so that a
            # library's warning logged without one reaches stderr through logging.lastResort
            logging.root.handlers[:] = []
            logging.root.setLevel(logging.WARNING)
            sys.argv = ["radiokit", *argv]
            # a child's streams: stdout strict, stderr backslashreplace (Python's defaults for a pipe)
            sys.stdout = out_text = io.TextIOWrapper(out_bytes, encoding=encoding, errors="strict", write_through=True)
            sys.stderr = err_text = io.TextIOWrapper(
                err_bytes, encoding=encoding, errors="backslashreplace", write_through=True
            )
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse (usage errors, --help, --version), as the interpreter takes it
                if exc.code is None or isinstance(exc.code, int):
                    code = exc.code or 0
                else:
                    print(exc.code, file=sys.stderr)
                    code = 1
    finally:
        for text in (out_text, err_text):
            if text is not None:
                text.flush()
                text.detach()  # else closing the wrapper (when collected) would close the bytes
        sys.stdout, sys.stderr = saved_streams
        fd_out, fd_err = fds[0].restore(), fds[1].restore()
        sys.argv = saved_argv
        for key in set(os.environ) - set(saved_env):
            del os.environ[key]
        os.environ.update(saved_env)
        os.chdir(saved_cwd)
        os.umask(saved_umask)
        for sig, handler in saved_signals.items():
            if handler is not None:  # None: installed outside Python, cannot be put back
                signal.signal(sig, handler)
        warnings.formatwarning, warnings.showwarning = saved_formatwarning, saved_showwarning
        _restore_logging(saved_logging)
    assert isinstance(code, int), f"main returned {code!r}, not an exit code"
    stdout = _decode(out_bytes.getvalue() + fd_out, encoding)
    stderr = _decode(err_bytes.getvalue() + fd_err, encoding)
    return subprocess.CompletedProcess(["radiokit", *argv], code, stdout, stderr)


# -- the X-ray guardian of a command under test ------------------------------------------------------


def guardian_of(pid):
    """The pid of the X-ray guardian process that ``pid`` started (from /proc), or None."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and b"acquisition.guardian" in cmdline:
            return int(entry.name)
    return None


def _pipe_holds_bytes(path) -> bool:
    import fcntl
    import struct
    import termios

    try:
        with open(path, "rb", buffering=0) as pipe:
            return struct.unpack("i", fcntl.ioctl(pipe, termios.FIONREAD, b"\0\0\0\0"))[0] > 0
    except OSError:
        return False


class StartMissed(AssertionError):
    """``guardian_held_at_start`` stopped the guardian only after it had opened its port (and so,
    perhaps, said READY): the window the test is about was missed, not tested."""


def _holds_its_port(guardian) -> bool:
    """Whether the guardian ``guardian`` has opened a terminal (its port) of its own: a descriptor
    on /dev/pts or /dev/tty* other than the port's lock it inherited (``--lock-fd N``), which it
    holds from its first instruction. It says READY only after that open."""
    try:
        words = (Path(f"/proc/{guardian}") / "cmdline").read_bytes().split(b"\0")
        fds = list((Path(f"/proc/{guardian}") / "fd").iterdir())
    except OSError:
        return False
    lock = words[words.index(b"--lock-fd") + 1].decode() if b"--lock-fd" in words else None
    for fd in fds:
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if fd.name != lock and target.startswith(("/dev/pts/", "/dev/tty")):
            return True
    return False


@contextlib.contextmanager
def guardian_held_at_start(proc, acted, timeout_s=60.0):
    """Hold the X-ray guardian that ``proc`` starts (SIGSTOP as soon as it appears in /proc, before
    it can open the port and say READY), so that what the body does to ``proc`` (a signal) lands
    while ``proc`` waits for the guardian to start. On leaving, the guardian runs on (SIGCONT) once
    ``proc`` has acted on it: written to the guardian, ``acted()`` true (it printed), or ended.
    Yields the guardian's pid. The freeze is the start-up window made wide, not a fake."""
    end = time.monotonic() + timeout_s
    guardian = None
    while guardian is None and proc.poll() is None and time.monotonic() < end:
        guardian = guardian_of(proc.pid)
        if guardian is None:
            # a short sleep, not a spin: the spin took a whole core of the two (the command and its
            # guardian starved, flaky under -n 4); the guardian's interpreter needs far longer than
            # this to import and open the port, so it is still caught before it says READY
            time.sleep(0.01)
    assert guardian is not None, f"no X-ray guardian started by pid {proc.pid}"
    os.kill(guardian, signal.SIGSTOP)
    try:
        # On a loaded machine this process may not run for a while between two scans, and the
        # guardian then gets through its whole start first: caught after READY, ``proc`` is past
        # the wait for it (in its connect), and what the body does tests another moment (a
        # fresh-clone `make test` at load 11 failed so: the interrupt landed in connect's TYP)
        if _holds_its_port(guardian):
            raise StartMissed(f"the X-ray guardian (pid {guardian}) had opened its port when stopped")
        yield guardian
        while time.monotonic() < end and proc.poll() is None and not acted():
            if _pipe_holds_bytes(f"/proc/{guardian}/fd/0"):
                break
            time.sleep(0.01)
    finally:
        os.kill(guardian, signal.SIGCONT)


@pytest.fixture
def sigint_default():
    """Python's own Ctrl-C handler while the test sends SIGINT to this process: under ``make test &``
    the process inherits SIGINT ignored, and the signal would otherwise go nowhere before the run
    installs its guard. Restored afterwards."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def mounted_tmpfs(folder, size):
    """A tmpfs of ``size`` (mount's notation, "1m") mounted on the new folder ``folder`` (needs
    root), unmounted at the end; None where mounting is not permitted: a full disk is caused for
    real where it can be."""
    folder.mkdir()
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True)
    if ok.returncode != 0:
        yield None
        return
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def in_thread(call):
    """``call()`` run in a daemon thread: (the thread, ``out``), ``out["reply"]`` its return or
    ``out["raised"]`` what it raised (a BaseException too: the outcome is what the test looks at)."""
    out: dict = {}

    def run():
        try:
            out["reply"] = call()
        except BaseException as exc:  # the outcome looked at by the test
            out["raised"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, out


@contextlib.contextmanager
def beam_monitor(src, every_s, stop=None):
    """A series' beam monitor: ``src.check()`` in another thread every ``every_s`` (the first after
    ``every_s``) until the block ends or ``stop`` is set; yields the list its fault goes to (it stops
    at the first). The block's end sets ``stop`` and joins the thread, also when the block raised."""
    faults, stop = [], stop or threading.Event()

    def poll():
        while not stop.wait(every_s):
            try:
                src.check()
            except Exception as exc:  # recorded: the test's assertion names it
                faults.append(exc)
                return

    poller = threading.Thread(target=poll)
    poller.start()
    try:
        yield faults
    finally:
        stop.set()
        poller.join()


def square_pair(n=160):
    """``(reference, moving, mask)``: flat images, transmission 1.0 (reference) and 0.9 (moving),
    with a 40 px square at 1.3 and 1.25 in their middle (``mask``): the CNR tests' pair, whose
    contrast and noise have closed forms."""
    inside = (slice(60, 100), slice(60, 100))
    reference, moving = np.full((n, n), 1.0), np.full((n, n), 0.9)
    reference[inside], moving[inside] = 1.3, 1.25
    mask = np.zeros((n, n), bool)
    mask[inside] = True
    return reference, moving, mask


def info_items(stdout: str) -> str:
    """``radiokit info``'s text with each item's padding (its name to the table's value column, as
    wide as the table's longest name) made two spaces: ``"saturated  5 pixel(s) ..."``, whatever
    names the files' tables hold. An item's further lines (no name) are kept as printed."""
    import re

    return re.sub(r"(?m)^  (\S.*?)  +(?=\S)", r"  \1  ", stdout)
