"""The compression series as the lab meets it: the L8121 emulator on a pseudo-terminal through the
real pyserial stack, the folder the C7942's vendor software writes (real TIFF files, written by a
thread that models that software from C7942.md), and the manual frame answered by a modelled
operator who takes a while at each request.

The vendor-software model saves frames *continuously*, one file per frame on read-out, whatever
the run is doing (HiPic's sequence saving; radiokit has no trigger line to the panel). Each frame
records what it saw at the start and at the end of its integration: the emulated tube's state,
the phantom (in or out) and the plate gap the operator has set. A frame is good for its label only
if both ends saw the state the label claims.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from acquisition.detector import FolderWatcher
from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError
from acquisition.frame import ManualFrame
from acquisition.l8121 import L8121
from acquisition.protocols import load_protocol, run
from acquisition.protocols.compression_series import Devices
from radiokit.io import ExperimentWriter, ImageKey

SHAPE = (16, 20)
H0 = 10.0  # mm, the phantom's initial height
STEPS = (0.15, 0.25)


class Operator:
    """The person at the frame: each request takes ``work_s``; the gap and the phantom change
    when they are done, before they press Enter (as ManualFrame records them)."""

    def __init__(self, work_s=0.1, readings=()):
        self.work_s = work_s
        self.readings = list(readings)  # what they type for each gap measured (Enter when none left)
        self.gap_mm, self.phantom_in = H0, True
        self._said = ""

    def say(self, text):
        self._said = text

    def ask(self, prompt):
        time.sleep(self.work_s)
        if "Remove the phantom" in self._said:
            self.phantom_in = False
        elif "Put the phantom back" in self._said:
            self.phantom_in = True
        elif "Turn the screws" in self._said or "again to confirm" in self._said:
            if self.readings:
                reading = self.readings.pop(0)
                self.gap_mm = float(reading)
                return reading
            self.gap_mm = float(self._said.split("plate gap of ")[1].split(" mm")[0])
        return ""


class Vendor(threading.Thread):
    """HiPic saving continuously: integrate ``period_s``, then write ``frame_NNNNN.tif``. Pixel
    (0, k) records, at the start and at the end of the integration: the tube on (0, 1), the
    phantom in (2, 3), the gap in 0.01 mm (4, 5). The others read ``fill`` counts, plus ``beam``
    with the tube on at the end (half with the phantom in): flats brighter than darks, as the run
    now judges them (constant frames of ``fill`` were refused as "flats not brighter than darks")."""

    def __init__(
        self, folder, model, operator, period_s=0.04, name=lambda k: f"frame_{k:05d}.tif", fill=100, beam=1000
    ):
        super().__init__(daemon=True)
        self.folder, self.model, self.operator, self.period_s = Path(folder), model, operator, period_s
        self.naming = name
        self.fill, self.beam = fill, beam
        self.halt = threading.Event()
        self.error = None

    def _state(self):
        return int(self.model.xray_on), int(self.operator.phantom_in), round(100 * self.operator.gap_mm)

    def run(self):
        k = 0
        try:
            while not self.halt.is_set():
                start = self._state()
                time.sleep(self.period_s)
                end = self._state()
                lit = self.beam * end[0] // (1 + end[1])
                a = np.full(SHAPE, self.fill + lit, np.uint16)
                a[0, 0:6] = [start[0], end[0], start[1], end[1], start[2], end[2]]
                tifffile.imwrite(self.folder / self.naming(k), a)
                k += 1
        except Exception as exc:  # pragma: no cover - re-raised by the test
            self.error = exc


class Watcher(FolderWatcher):
    """The lab's watcher, remembering the file each frame it handed over came from."""

    def acquire(self, n, **kw):
        self.handed = getattr(self, "handed", [])
        for frame in super().acquire(n, **kw):
            self.handed.append(frame.origin)
            yield frame


def _run_beside_the_vendor(p, dev, operator):
    """The series run while the vendor's software saves frames into the panel's folder: (its
    result, the vendor thread, stopped)."""
    vendor = Vendor(Path(p.detector.folder), dev.emulator, operator)
    vendor.start()
    try:
        return run(p, devices=dev, progress=False), vendor
    finally:
        vendor.halt.set()
        vendor.join(5)


def _lab(tmp_path, series=None, operator=None, warmed_up=True, shape=SHAPE, **detector):
    folder = tmp_path / "frames"
    folder.mkdir(exist_ok=True)
    p = load_protocol(
        {
            "output": str(tmp_path / "series.h5"),
            # the driver's reply time-out at 1 s, as test_safety's: at 0.5 s the emulator (a thread
            # of this process) once answered late on a loaded machine (load ~7), read as no reply
            "source": {"voltage_kv": 60, "current_ua": 250, "poll_s": 0.1, "timeout_s": 1.0, "port": "emulated"},
            "detector": {"kind": "folder", "folder": str(folder), "shape": list(shape), "timeout_s": 5.0, **detector},
            "frame": {"kind": "manual", "initial_height_mm": H0},
            "series": series or {"darks": 2, "flats": 2, "frames_per_step": 2, "steps": list(STEPS), "settle_s": 0.05},
        }
    )
    model = L8121Model(dialect="A", warmup_s=0.3, ramp_s=0.1, warmed_up=warmed_up)
    server = PtyServer(model)
    server.start()
    try:
        source = L8121(server.url, poll_s=0.1, timeout_s=1.0)
    except Exception:
        server.stop()
        raise
    watcher = Watcher(
        folder, p.detector.pattern, shape=shape, timeout_s=5.0, settle_s=0.03, poll_s=0.01, bits=p.detector.bits
    )
    operator = operator or Operator()
    frame = ManualFrame(H0, ask=operator.ask, say=operator.say)
    return p, Devices(source, watcher, frame, [server.stop], emulator=model), operator


def test_frames_saved_while_the_run_waited_are_never_taken_for_the_next_batch(tmp_path):
    """Found: the vendor software saves frames whatever the run is doing, and the watcher took
    new files in arrival order from the moment it was armed. The frames that piled up while the
    operator took the phantom out, turned the screws, the gel settled and the beam ramped up
    became the next batch: every flat was a dark frame (tube off), step 1's projections were
    taken with the tube off at the uncompressed gap, and so on, all labelled as asked. Now each
    batch starts after the frames the folder holds, and drops the one in flight."""
    p, dev, operator = _lab(tmp_path)
    res, vendor = _run_beside_the_vendor(p, dev, operator)
    assert vendor.error is None
    assert res.tube_off is True and res.frames_total == 2 + 2 + 2 * len(STEPS)
    with h5py.File(p.output, "r") as h5:
        key = h5["entry/instrument/detector/image_key"][:]
        step = h5["entry/sample/compression/step"][:]
        gap_m = h5["entry/sample/compression/gap"][:]
        seen = h5["entry/instrument/detector/data"][:, 0, 0:6].astype(int)
    tube, phantom, gap = seen[:, 0:2], seen[:, 2:4], seen[:, 4:6] / 100.0
    dark, flat, proj = key == ImageKey.DARK, key == ImageKey.FLAT, key == ImageKey.PROJECTION
    assert dark.sum() == 2 and flat.sum() == 2 and proj.sum() == 2 * len(STEPS)
    assert np.all(tube[dark] == 0), tube[dark]
    assert np.all(tube[flat | proj] == 1), tube[flat | proj]
    assert np.all(phantom[flat] == 0) and np.all(phantom[proj] == 1), phantom
    for i, r in enumerate(STEPS, start=1):
        sel = proj & (step == i)
        np.testing.assert_allclose(gap[sel], H0 * (1 - r), atol=0.005)  # the gap set for this step
        np.testing.assert_allclose(gap_m[sel] * 1e3, H0 * (1 - r), atol=1e-9)  # and the one recorded


def test_vendor_software_saving_every_frame_to_one_name_stops_the_run_saying_so(tmp_path):
    """Found: vendor software saving every frame to one name (``image.tif``) gave the run at
    most one frame; the others were saved over it unseen, and the run waited out the time-out
    (X-rays on in a beam phase) to say only "no new complete file". Now the run stops with one
    error naming the file and what to change, the tube off, and no frame from that file is left
    labelled valid (the one stored, if any, is labelled invalid: its file changed afterwards)."""
    p, dev, operator = _lab(tmp_path, timeout_s=1.0)
    vendor = Vendor(Path(p.detector.folder), dev.emulator, operator, period_s=0.1, name=lambda k: "image.tif")
    vendor.start()
    try:
        with pytest.raises(DeviceError) as info:
            run(p, devices=dev, progress=False)
    finally:
        vendor.halt.set()
        vendor.join(5)
    assert vendor.error is None
    msg = str(info.value)
    assert "image.tif" in msg and "new, numbered file" in msg, msg
    assert info.value.result.tube_off is True and not dev.emulator.xray_on
    if info.value.result.file_removed:  # no frame stored: the file held nothing and is not kept
        assert not Path(p.output).exists()
        return
    with h5py.File(p.output, "r") as h5:
        key = h5["entry/instrument/detector/image_key"][:]
    assert key.size and np.all(key == ImageKey.INVALID), key


def test_a_frame_file_saved_over_after_it_was_stored_stops_the_run_and_the_frame_is_invalid(tmp_path):
    """A second program saves over a frame file already stored (someone saves the first dark
    from an image viewer while the run goes on; or the vendor software was still writing it
    when it was taken). The run stops at once with one error naming the file, the tube off, and
    the frame stored from it is labelled invalid (``--resume`` takes it again); the other dark
    stays valid."""
    p, dev, operator = _lab(tmp_path)
    vendor = Vendor(Path(p.detector.folder), dev.emulator, operator)
    saved_over = []

    def second_writer(phase, info=None):
        if phase == "flats":  # both darks are stored
            first = dev.detector.handed[0]
            tifffile.imwrite(first, np.full(SHAPE, 4000, np.uint16))
            saved_over.append(first)

    vendor.start()
    try:
        with pytest.raises(DeviceError) as info:
            run(p, devices=dev, progress=False, on_phase=second_writer)
    finally:
        vendor.halt.set()
        vendor.join(5)
    assert vendor.error is None and len(saved_over) == 1
    msg = str(info.value)
    assert msg.startswith(f"{saved_over[0]}: changed after it was taken as a frame"), msg
    assert info.value.result.tube_off is True and not dev.emulator.xray_on
    with h5py.File(p.output, "r") as h5:
        key = h5["entry/instrument/detector/image_key"][:]
    assert list(key[:2]) == [ImageKey.INVALID, ImageKey.DARK], key


def test_the_protocols_pixel_size_reaches_the_lab_detector(tmp_path):
    """Found: ``[detector] pixel_size_mm`` was never passed to the lab's folder watcher, which
    guessed the pitch from the frame width: a 1120-wide crop of the unbinned panel (0.05 mm)
    was stored as 0.1 mm, so every ROI and crop in mm was off by two, whatever the protocol
    said. Now a given pitch is used; without one, the preset's or the width's (2 x 2 binned)."""
    from acquisition.protocols import lab_devices

    model = L8121Model(dialect="A", warmed_up=True)
    server = PtyServer(model)
    server.start()
    try:
        for given, expected in ((0.05, 0.05), (None, 0.1)):
            p = load_protocol(
                {
                    "output": str(tmp_path / "series.h5"),
                    "source": {"port": server.url, "watchdog_s": 0},
                    "detector": {"folder": str(tmp_path), "shape": [1120, 1120], "pixel_size_mm": given},
                    "frame": {"kind": "manual", "initial_height_mm": H0},
                }
            )
            dev = lab_devices(p)
            try:
                assert dev.detector.pixel_size_mm == expected
                assert dev.detector.describe()["pixel_size_mm"] == expected
            finally:
                dev.close()
    finally:
        server.stop()
    with pytest.raises(DeviceError, match=r"pixel_size_mm = 0: expected the panel's pitch"):
        load_protocol({"detector": {"folder": str(tmp_path), "shape": [8, 8], "pixel_size_mm": 0}})
    # the experiment file refuses these when the run opens it (after connecting): a dry run must too
    for bad in (20, 5e-5):  # 2 cm; metres by mistake
        with pytest.raises(DeviceError, match=r"pixel_size_mm = .*expected the panel's pitch in mm, 0.0001 to 10"):
            load_protocol({"detector": {"folder": str(tmp_path), "shape": [8, 8], "pixel_size_mm": bad}})


def test_the_folder_settings_of_the_protocol_reach_the_watcher(tmp_path):
    """Found with the pixel size: ``settle_s`` (how long a frame file must hold still, which a
    network share with pausing writes needs longer, and which the saved-over error names) and the
    panel's ADC depth (the watcher's "another detector model (C9730DK/C9732DK are 14-bit)" advice
    had nothing to act on) could not be set from the protocol; now both reach the watcher."""
    from acquisition.protocols import lab_devices

    model = L8121Model(dialect="A", warmed_up=True)
    server = PtyServer(model)
    server.start()
    try:
        p = load_protocol(
            {
                "output": str(tmp_path / "series.h5"),
                "source": {"port": server.url, "watchdog_s": 0},
                "detector": {
                    "folder": str(tmp_path),
                    "preset": "c7942-2x2",
                    "settle_s": 1.5,
                    "timeout_s": 12.0,
                    "bits": 14,
                },
                "frame": {"kind": "manual", "initial_height_mm": H0},
            }
        )
        dev = lab_devices(p)
        try:
            d = dev.detector.describe()
            assert (d["settle_s"], d["timeout_s"], d["shape"], d["pixel_size_mm"]) == (1.5, 12.0, [1120, 1120], 0.1)
            assert d["bits"] == 14
        finally:
            dev.close()
    finally:
        server.stop()


def test_steps_measured_out_of_order_are_said(tmp_path, caplog):
    """The operator overshoots step 1 (7.9 mm for 8.5, confirmed by typing it twice), then
    stops short at step 2 (8.0 mm for 7.5): the file holds a step 2 less compressed than step 1,
    and processing takes the steps in their numbers' order. Found: nothing said so; now the
    notebook and the console get a warning naming both steps."""
    import logging

    series = {"darks": 0, "flats": 0, "frames_per_step": 1, "steps": list(STEPS), "settle_s": 0.0}
    p, dev, operator = _lab(tmp_path, series, Operator(readings=["7.9", "7.9", "8.0"]))
    vendor = Vendor(Path(p.detector.folder), dev.emulator, operator)
    vendor.start()
    try:
        with caplog.at_level(logging.WARNING, logger="acquisition.protocol"):
            res = run(p, devices=dev, progress=False)
    finally:
        vendor.halt.set()
        vendor.join(5)
    assert res.frames_total == 2 and res.tube_off is True
    warned = [r.getMessage() for r in caplog.records if "not in increasing compression" in r.getMessage()]
    assert len(warned) == 1 and "step 2: measured compression 0.2000" in warned[0] and "step 1's 0.2100" in warned[0]


def test_ctrl_c_while_the_lab_run_waits_for_folder_frames_with_x_rays_on(tmp_path):
    """The lab's path through the command: ``radiokit acquire`` in a subprocess on the emulator's
    pseudo-terminal (through the guardian), the folder written by the vendor model, the operator
    answering the manual frame's prompts on stdin. Ctrl-C while step 1's frames are awaited with
    X-rays on: exit 130, the last line confirms the tube off, the emulated tube is off, and the
    darks and flats are in the file."""
    import os
    import signal
    import subprocess
    import sys

    import tomli_w

    folder = tmp_path / "frames"
    folder.mkdir()
    model = L8121Model(dialect="A", warmup_s=0.3, ramp_s=0.1, warmed_up=True)
    server = PtyServer(model)
    server.start()
    operator = Operator()
    vendor = Vendor(folder, model, operator, period_s=0.05)
    proto = tmp_path / "lab.toml"
    series = {"darks": 2, "flats": 2, "frames_per_step": 10**4, "steps": list(STEPS), "settle_s": 0.0}
    source = {"port": server.url, "voltage_kv": 60, "current_ua": 250, "poll_s": 0.1, "timeout_s": 0.5}
    proto.write_text(
        tomli_w.dumps(
            {
                "output": str(tmp_path / "series.h5"),
                "source": source,
                "detector": {"kind": "folder", "folder": str(folder), "shape": list(SHAPE), "settle_s": 0.03},
                "frame": {"kind": "manual", "initial_height_mm": H0},
                "series": series,
            }
        )
    )
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    code = "import sys; from radiokit.cli import script; sys.exit(script())"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "acquire", str(proto), "-q"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,
    )
    notebook = tmp_path / "series.log"

    def logged(text):
        return notebook.exists() and text in notebook.read_text(errors="replace")

    def wait(cond, what, timeout=30.0):
        end = time.monotonic() + timeout
        while not cond():
            assert proc.poll() is None, f"the run ended before {what}"
            assert time.monotonic() < end, f"timed out waiting for {what}"
            time.sleep(0.02)

    vendor.start()
    try:
        for _ in range(3):  # phantom out, phantom back in, the screws: Enter each time
            proc.stdin.write(b"\n")
        proc.stdin.flush()
        wait(lambda: logged("phase step 1") and model.xray_on, "X-rays on in step 1")
        wait(lambda: notebook.read_text(errors="replace").count("new batch") >= 3, "step 1's frames awaited")
        os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C goes to the process group
        out, _ = proc.communicate(timeout=30)
    finally:
        vendor.halt.set()
        vendor.join(5)
        if proc.poll() is None:
            proc.kill()
        server.stop()
    lines = [ln for ln in out.decode("utf-8", "replace").splitlines() if ln.strip()]
    assert proc.returncode == 130, lines[-5:]
    assert lines[-1].startswith("tube off (confirmed by STS"), lines[-5:]
    assert not model.xray_on
    with h5py.File(tmp_path / "series.h5", "r") as h5:
        key = list(h5["entry/instrument/detector/image_key"][:4])
    assert key == [ImageKey.DARK] * 2 + [ImageKey.FLAT] * 2


def test_a_14_bit_panel_named_in_the_protocol_runs_and_is_recorded(tmp_path):
    """A 14-bit panel (C9730DK/C9732DK) under a protocol that says ``bits = 14``: frames up to
    16383 are taken, and the file records the depth, so readers and the calibration take 16383 as
    saturation, not 4095 as wrong byte order. Without it the run stops at the first frame."""
    series = {"darks": 1, "flats": 0, "frames_per_step": 1, "steps": [0.15, 0.25], "settle_s": 0.0}
    for bits in (12, 14):
        out = tmp_path / f"bits{bits}"
        out.mkdir()
        p, dev, operator = _lab(out, series, bits=bits, timeout_s=2.0)
        vendor = Vendor(Path(p.detector.folder), dev.emulator, operator, fill=16000, beam=200)
        vendor.start()
        try:
            if bits == 12:
                with pytest.raises(DeviceError, match=r"pixel values up to 16000 exceed the 12-bit range"):
                    run(p, devices=dev, progress=False)
            else:
                assert run(p, devices=dev, progress=False).frames_total == 3
        finally:
            vendor.halt.set()
            vendor.join(5)
    with h5py.File(p.output, "r") as h5:
        assert int(h5["entry/instrument/detector/bit_depth_readout"][()]) == 14
        assert int(h5["entry/instrument/detector/data"][0].max()) == 16000


def test_a_stopped_series_stops_the_compression_frame(tmp_path):
    """Found: only the series' normal end called the frame's ``stop()``; a fault or Ctrl-C while
    a motorised stage moved left its axis running, closing on the phantom, although the
    MotorisedStage contract asks for ``stop()`` in the protocol's abort path. No motorised driver
    exists, so the stage here is the one fake of this module: an axis on a thread that closes
    the gap until it is there or stopped. Ctrl-C arrives mid-move; the tube is off and the axis
    is halted short of the target."""
    import signal

    from acquisition.frame import MotorisedStage

    class Stage(MotorisedStage):
        def __init__(self):
            super().__init__(H0)
            self.gap, self.halted, self.moving = H0, threading.Event(), threading.Event()

        def move_to(self, gap_mm):
            def axis():
                while self.gap > gap_mm and not self.halted.wait(0.01):
                    self.gap = max(gap_mm, self.gap - 0.01)
                    self.moving.set()

            threading.Thread(target=axis, daemon=True).start()
            assert self.moving.wait(5)
            signal.raise_signal(signal.SIGINT)  # Ctrl-C mid-move: the guard raises here
            while self.gap > gap_mm:  # pragma: no cover - never reached
                time.sleep(0.01)
            return self.gap

        def position(self):
            return self.gap

        def stop(self):
            self.halted.set()

        def sample_out(self):
            pass

        def sample_in(self):
            pass

    series = {"darks": 0, "flats": 0, "frames_per_step": 1, "steps": [0.5, 0.6], "settle_s": 0.0}
    p, dev, operator = _lab(tmp_path, series)
    stage = dev.frame = Stage()
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt) as info:
            run(p, devices=dev, progress=False)
    finally:
        signal.signal(signal.SIGINT, old)
    assert info.value.result.tube_off is True and not dev.emulator.xray_on
    assert stage.halted.is_set() and stage.gap > H0 * 0.5


@pytest.mark.parametrize(
    "detector, message",
    [
        ({"preset": "c7942-3x3"}, r"preset = 'c7942-3x3': unknown; known: c7942, "),
        ({"preset": "c7942-2x2", "shape": [2240, 2240]}, r"shape = \[2240, 2240\] contradicts preset = 'c7942-2x2'"),
        ({"shape": ["a", 3]}, r"shape = \['a', 3\]: expected two whole numbers > 0"),
        ({"shape": [2240.5, 2240]}, r"expected two whole numbers"),
        ({"shape": [2240]}, r"shape = \[2240\]: expected \[rows, cols\]"),
    ],
)
def test_the_dry_run_refuses_a_frame_geometry_the_run_would_refuse(tmp_path, capsys, detector, message):
    """Found: an unknown preset, or a shape contradicting the preset, passed ``--dry-run`` and
    stopped the run only at connect; a shape of non-numbers ended the dry run in "invalid
    literal for int() with base 10: 'a'" naming neither file nor setting, and 2240.5 was
    truncated to 2240. Each is now one line at load naming the setting."""
    import tomli_w

    from radiokit.cli import main

    lab = {
        "output": str(tmp_path / "series.h5"),
        "source": {"port": "/dev/ttyUSB0"},
        "detector": {"folder": str(tmp_path), **detector},
    }
    with pytest.raises(DeviceError, match=message):
        load_protocol(lab)
    proto = tmp_path / "lab.toml"
    proto.write_text(tomli_w.dumps(lab))
    assert main(["acquire", str(proto), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {proto}: [detector]"), err


class _NoRoomForAFrame(ExperimentWriter):
    """The writer on a disk with room for the file's layout and the writer's reserve but not for
    one frame more (the reviewer's 1.3 MB tmpfs under 512 x 512 frames). The one fake here, and
    why: a disk that small needs a tmpfs, which needs root; only the free space the writer reads
    is faked, so its own room rule -- the one under test -- runs as on the real disk."""

    def _free_bytes(self):
        return self.reserve_bytes + (100 << 10)  # over the layout's 64 KiB, under a 256 x 256 frame


@pytest.mark.parametrize("resume", [False, True], ids=["fresh run", "resume"])
def test_a_disk_that_cannot_hold_the_next_frame_is_refused_before_any_x_ray_command(tmp_path, resume):
    """Found (review s41acq): with a source needing its warm-up and a disk holding less than one
    frame plus the writer's reserve, the run sent WUP -- the warm-up emits X-rays -- and stopped
    only at dark 0 with "disk full"; a resume on such a disk sent XON for the flats and failed
    the same way. Now the writer's own room rule is asked before the first X-ray command: one
    line naming the file, and neither WUP nor XON reaches the controller."""
    shape = (256, 256)  # a frame (128 KiB) larger than the file's layout, so the file itself opens
    series = {"darks": 2, "flats": 2, "frames_per_step": 1, "steps": list(STEPS), "settle_s": 0.0}
    p, dev, operator = _lab(tmp_path, series, warmed_up=resume, shape=shape)
    if resume:  # the darks of an interrupted run are in the file: a resume's first X-rays are the flats' XON
        with ExperimentWriter(p.output, shape, in_place=True) as w:
            w.record_run(p.to_toml(), {})
            for _ in range(series["darks"]):
                w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
    try:
        with pytest.raises(OSError) as info:
            run(p, devices=dev, progress=False, resume=resume, writer_factory=_NoRoomForAFrame)
    finally:
        dev.close()
    msg = str(info.value.strerror)
    assert msg.startswith(f"{p.output}: disk full") and "no X-ray command was sent" in msg, msg
    assert "\n" not in msg
    assert not {"WUP", "XON"} & set(dev.emulator.commands), dev.emulator.commands
    assert info.value.result.tube_off is True and not dev.emulator.xray_on


@pytest.mark.parametrize("resume", [False, True], ids=["fresh run, source to warm up", "resume after the darks"])
def test_a_panel_that_delivers_nothing_is_found_before_any_x_ray_command(tmp_path, resume):
    """Found (review s41acq): with the vendor software not saving (no panel), the run warmed the
    source up -- X-rays -- and found the panel missing only when the darks timed out; a resume
    after the darks switched X-rays on for the flats first. Now one frame, tube off, shows the
    panel delivers before the first X-ray command (none is stored: the darks stay "just before
    acquisition", C7942.md, not half an hour before it behind the warm-up). A fresh run's file,
    which took no frame, is not left to block the rerun; a resumed file keeps its frames."""
    series = {"darks": 2, "flats": 2, "frames_per_step": 1, "steps": list(STEPS), "settle_s": 0.0}
    p, dev, operator = _lab(tmp_path, series, warmed_up=resume, timeout_s=1.0)
    if resume:
        with ExperimentWriter(p.output, SHAPE, in_place=True) as w:
            w.record_run(p.to_toml(), {})
            for _ in range(series["darks"]):
                w.append(np.full(SHAPE, 100, np.uint16), image_key=ImageKey.DARK)
    try:  # no vendor thread: nothing ever reaches the folder
        with pytest.raises(DeviceError) as info:
            run(p, devices=dev, progress=False, resume=resume)
    finally:
        dev.close()
    msg = str(info.value)
    assert "0 of 1 frames arrived" in msg and "no X-ray command was sent" in msg, msg
    assert not {"WUP", "XON"} & set(dev.emulator.commands), dev.emulator.commands
    assert info.value.result.tube_off is True and not dev.emulator.xray_on
    if resume:
        with h5py.File(p.output, "r") as h5:
            assert list(h5["entry/instrument/detector/image_key"][:]) == [ImageKey.DARK] * 2
    else:
        assert not Path(p.output).exists() and info.value.result.file_removed


def test_the_panel_check_frame_is_not_stored_and_the_series_completes(tmp_path):
    """With a working panel, the check before the warm-up costs one frame (not stored) and the
    series is what it was: every dark with the tube off, flats and projections with it on."""
    series = {"darks": 2, "flats": 2, "frames_per_step": 1, "steps": list(STEPS), "settle_s": 0.0}
    p, dev, operator = _lab(tmp_path, series, warmed_up=False)
    res, vendor = _run_beside_the_vendor(p, dev, operator)
    assert res.tube_off is True and res.frames_total == 2 + 2 + len(STEPS)
    assert "WUP" in dev.emulator.commands
    with h5py.File(p.output, "r") as h5:
        key = h5["entry/instrument/detector/image_key"][:]
        seen = h5["entry/instrument/detector/data"][:, 0, 0:2].astype(int)
    assert list(key) == [ImageKey.DARK] * 2 + [ImageKey.FLAT] * 2 + [ImageKey.PROJECTION] * len(STEPS)
    assert np.all(seen[:2] == 0) and np.all(seen[2:] == 1), seen


def test_a_resume_after_the_flats_asks_for_the_phantom_back_before_the_first_projection(tmp_path):
    """Found (review s41acq): Ctrl-C at "Put the phantom back in the beam" (every flat taken),
    then `--resume`: its first request was the plate gap, the phantom was never asked back in,
    and the projections could be taken without it, labelled valid. The file holds no record of
    the phantom's return before its first projection: a resume that finds the flats done and no
    projection asks for it again before the first step."""

    class QuitsAtThePhantom(Operator):
        def ask(self, prompt):
            if "Put the phantom back" in self._said:
                raise KeyboardInterrupt  # Ctrl-C at the prompt
            return super().ask(prompt)

    class Told(Operator):
        def say(self, text):
            self.told = [*getattr(self, "told", []), text]
            super().say(text)

    series = {"darks": 2, "flats": 2, "frames_per_step": 1, "steps": list(STEPS), "settle_s": 0.0}
    first = QuitsAtThePhantom()
    p, dev, operator = _lab(tmp_path, series, first)
    vendor = Vendor(Path(p.detector.folder), dev.emulator, first)
    vendor.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            run(p, devices=dev, progress=False)
    finally:
        vendor.halt.set()
        vendor.join(5)
    assert not first.phantom_in and not dev.emulator.xray_on
    second = Told()
    second.phantom_in = False  # as the first run left it: out of the beam
    p, dev, operator = _lab(tmp_path, series, second)
    vendor = Vendor(Path(p.detector.folder), dev.emulator, second)
    vendor.start()
    try:
        res = run(p, devices=dev, progress=False, resume=True)
    finally:
        vendor.halt.set()
        vendor.join(5)
    assert res.tube_off is True and res.frames_total == 2 + 2 + len(STEPS)
    asked = [t for t in second.told if "phantom" in t or "Turn the screws" in t]
    assert asked and asked[0].startswith("Put the phantom back in the beam"), second.told
    with h5py.File(p.output, "r") as h5:
        key = h5["entry/instrument/detector/image_key"][:]
        seen = h5["entry/instrument/detector/data"][:, 0, 2:4].astype(int)
    proj = key == ImageKey.PROJECTION
    assert proj.sum() == len(STEPS) and np.all(seen[proj] == 1), seen[proj]  # the phantom in, start and end
