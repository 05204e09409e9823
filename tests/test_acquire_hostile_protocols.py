"""Hostile protocols for ``radiokit acquire --sim``: no X-ray command before every setting is valid.

Each case writes a protocol that drives the L8121 emulator this test serves on a pseudo-terminal
(``[sim] source_port``, through the guardian as in the lab), runs the command in this process,
and asserts: exit code 2, one line naming the protocol file (and the key) and the problem, the
emulator's received-command log free of every command that sets or switches on the beam, and no
file left beside the output (neither the experiment file nor its notebook).
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import pytest
import tomli_w

from acquisition.emulators.l8121 import L8121Model, PtyServer

#: Commands that set the exposure, start the warm-up or switch X-rays on (both dialects, L8121.md).
XRAY_COMMANDS = {"XON", "WUP", "HIV", "CUR", "PHV", "PCU"}

# the scene's panel: a C7942 (2240 x 2240 at binning 1) binned 4, so 560 x 560, 12-bit
BINNING = 4
PANEL = 2240 // BINNING


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    from sim.scene import block_scene

    scene = block_scene(size_mm=10.0, ratios=(0.15,))
    scene.detector.binning = BINNING
    scene.mesh.size_far_mm = 8.0
    path = tmp_path_factory.mktemp("scene") / "scene.toml"
    path.write_text(scene.to_toml())
    return path


@pytest.fixture
def emulator():
    model = L8121Model(dialect="A", warmup_s=0.3, ramp_s=0.05, warmed_up=True)
    server = PtyServer(model).start()
    yield model, server
    server.stop()


def protocol(tmp_path, scene_file, port, edit):
    data = {
        "output": str(tmp_path / "out" / "series.h5"),
        "source": {"voltage_kv": 60, "current_ua": 250, "dialect": "A", "timeout_s": 2.0, "poll_s": 0.1},
        "detector": {"kind": "sim", "timeout_s": 2.0},
        "frame": {"kind": "sim", "initial_height_mm": 10.0},
        "series": {"darks": 1, "flats": 1, "frames_per_step": 1, "steps": [0.0]},
        "sim": {"scene": str(scene_file), "source_port": port},
    }
    data = copy.deepcopy(data)
    edit(data)
    (tmp_path / "out").mkdir(exist_ok=True)
    path = tmp_path / "protocol.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def refused(tmp_path, scene_file, emulator, capsys, edit, *words):
    """Run the command on the edited protocol; assert the refusal, and that nothing was sent or left."""
    from radiokit.cli import main

    model, server = emulator
    path = protocol(tmp_path, scene_file, server.url, edit)
    code = main(["acquire", str(path), "--sim", "-q"])
    captured = capsys.readouterr()
    lines = [ln for ln in (captured.out + captured.err).splitlines() if ln.strip()]
    sent = [c for c in model.commands if c.split()[0] in XRAY_COMMANDS] if model.commands else []
    assert sent == [], (sent, lines)
    assert code == 2, lines
    assert len(lines) == 1 and str(path) in lines[0], lines
    for w in words:
        assert w in lines[0], lines
    assert list((tmp_path / "out").iterdir()) == []  # no experiment file, no notebook
    return lines[0]


def setting(section, key, value):
    def edit(d):
        d[section][key] = value

    return edit


# -- the virtual bench's panel is a C7942: a protocol that says otherwise is refused -------------


@pytest.mark.parametrize(
    "key, value, said",
    [
        ("shape", [2240, 2241], "shape = [2240, 2241]"),
        ("shape", [2240, 2240], "shape = [2240, 2240]"),  # the unbinned panel's, the scene bins 4
        ("preset", "c7942", "preset = 'c7942'"),
        ("bits", 8, "bits = 8"),  # the panel's 12-bit values would stop the run with X-rays on
        ("bits", 14, "bits = 14"),  # the file would record 14 bits of a 12-bit panel
    ],
)
def test_a_detector_that_is_not_the_virtual_panel_is_refused_before_any_x_ray_command(
    tmp_path, scene_file, emulator, capsys, key, value, said
):
    line = refused(tmp_path, scene_file, emulator, capsys, setting("detector", key, value), "[detector]", said)
    assert f"{PANEL} x {PANEL}" in line or "12" in line, line  # says what the virtual panel is


def test_the_virtual_panel_s_own_geometry_is_taken(tmp_path, scene_file, emulator, capsys):
    """The check refuses only what contradicts the panel: its own shape and bits are a protocol."""
    from acquisition.protocols.compression_series import check_sim, load_protocol

    path = protocol(tmp_path, scene_file, "/dev/null", setting("detector", "shape", [PANEL, PANEL]))
    check_sim(load_protocol(path))


@pytest.mark.parametrize(
    "edit, words",
    [
        (setting("sim", "binning", 0), ("[sim] binning = 0", "1, 2 or 4")),
        (setting("sim", "binning", 3), ("[sim] binning = 3", "1, 2 or 4")),
        (setting("sim", "scene", "no-such-scene.toml"), ("[sim] scene", "no such scene file")),
        # every frame would time out: the run connected, stopped at its first frame, left a notebook
        (setting("sim", "frame_period_s", 3.0), ("[sim] frame_period_s = 3", "[detector] timeout_s = 2")),
    ],
    ids=["binning 0", "binning 3", "missing scene", "frame period over the time-out"],
)
def test_a_virtual_bench_that_cannot_be_built_leaves_no_notebook(tmp_path, scene_file, emulator, capsys, edit, words):
    refused(tmp_path, scene_file, emulator, capsys, edit, *words)


def test_a_watchdog_beyond_any_timer_is_refused_not_a_guardian_traceback(tmp_path, scene_file, emulator, capsys):
    """``watchdog_s = 1e300`` passed the protocol's checks and killed the guardian (select's
    OverflowError) after the connect had begun; a watchdog is there to switch off a hung run."""
    refused(tmp_path, scene_file, emulator, capsys, setting("source", "watchdog_s", 1e300), "[source] watchdog_s")


# -- the settings the protocol already refused, now through the pty: nothing sent, nothing left ---

HOSTILE = [
    ("source", "voltage_kv", math.nan),
    ("source", "voltage_kv", math.inf),
    ("source", "voltage_kv", -60),
    ("source", "voltage_kv", 0),
    ("source", "voltage_kv", 1e300),
    ("source", "voltage_kv", "60"),
    ("source", "voltage_kv", [60]),
    ("source", "voltage_kv", {"kv": 60}),
    ("source", "current_ua", math.nan),
    ("source", "current_ua", -1),
    ("source", "current_ua", 501),
    ("source", "kv", 60),  # a typo must not fall back to the default exposure
    ("source", "voltage_kV", 60),
    ("series", "darks", -1),
    ("series", "frames_per_step", 0),
    ("series", "frames_per_step", 2.5),
    ("series", "steps", [15, 20, 25]),  # percentages, not ratios
    ("series", "steps", [0.15, 0.15]),
    ("series", "steps", [0.25, 0.2]),
    ("series", "steps", [1.5]),
    ("series", "steps", []),
    ("series", "steps", 0.15),
    ("series", "settle_s", math.inf),
    ("detector", "shape", [0, 2240]),
    ("detector", "bits", 17),
]


@pytest.mark.parametrize("section, key, value", HOSTILE, ids=[f"{s}.{k}={v!r}" for s, k, v in HOSTILE])
def test_a_hostile_setting_sends_nothing_and_leaves_nothing(
    tmp_path, scene_file, emulator, capsys, section, key, value
):
    refused(tmp_path, scene_file, emulator, capsys, setting(section, key, value), f"[{section}]")


def test_power_over_the_rating_sends_nothing(tmp_path, scene_file, emulator, capsys):
    """150 kV x 501 µA = 75.15 W, over the L8121's 75 W (the panel's kVp raised to let 150 kV through)."""

    def edit(d):
        d["detector"]["kvp_max"] = 150
        d["source"].update(voltage_kv=150, current_ua=501)

    refused(tmp_path, scene_file, emulator, capsys, edit, "[source]")


def test_the_python_api_refuses_a_detector_that_is_not_the_virtual_panel_before_any_command(
    tmp_path, scene_file, emulator
):
    """``run(p, sim=True)`` (README's example) checks what the command line does, before any file."""
    from acquisition.protocols.compression_series import ProtocolError, load_protocol, run

    model, server = emulator
    p = load_protocol(protocol(tmp_path, scene_file, server.url, setting("detector", "bits", 8)))
    with pytest.raises(ProtocolError, match=r"\[detector\] bits = 8"):
        run(p, sim=True, progress=False)
    assert model.commands == [] and list((tmp_path / "out").iterdir()) == []


# -- bounds: counts and times past any use of them (session 54) ----------------------------------

#: Every per-batch count of a protocol: each is that many frames (or discarded read-outs) in one
#: batch, the beam on for a flat's or a step's.
BATCH_COUNTS = [
    ("series", "frames_per_step"),
    ("series", "darks"),
    ("series", "flats"),
    ("detector", "discard_after_change"),
]


@pytest.mark.parametrize("section, key", BATCH_COUNTS, ids=[k for _, k in BATCH_COUNTS])
@pytest.mark.parametrize("over", ["just over", "10**9"])
def test_a_batch_count_beyond_the_ceiling_is_refused_before_any_x_ray_command(
    tmp_path, scene_file, emulator, capsys, section, key, over
):
    """``frames_per_step = 10**9`` passed (an extra zero or three: days of beam, terabytes); the
    run warned of the disk only after connecting, and then warmed the tube up."""
    from acquisition.protocols.compression_series import FRAMES_PER_BATCH_MAX

    value = FRAMES_PER_BATCH_MAX + 1 if over == "just over" else 10**9
    line = refused(tmp_path, scene_file, emulator, capsys, setting(section, key, value), f"[{section}] {key} = {value}")
    assert f"{FRAMES_PER_BATCH_MAX}" in line, line  # says the ceiling


def test_every_batch_count_at_the_ceiling_is_a_protocol(tmp_path, scene_file):
    from acquisition.protocols.compression_series import FRAMES_PER_BATCH_MAX, load_protocol

    def edit(d):
        for section, key in BATCH_COUNTS:
            d[section][key] = FRAMES_PER_BATCH_MAX

    p = load_protocol(protocol(tmp_path, scene_file, "/dev/null", edit))
    assert p.series.frames_per_step == FRAMES_PER_BATCH_MAX


def _time_keys():
    from acquisition.l8121 import TIME_LIMITS

    return sorted(TIME_LIMITS)


@pytest.mark.parametrize(
    "key, value",
    [(k, v) for k in ("warmup_timeout_s", "ready_timeout_s") for v in (1e300, math.inf, math.nan, -1.0)],
)
def test_a_warm_up_or_ready_wait_that_is_no_finite_positive_time_is_refused(
    tmp_path, scene_file, emulator, capsys, key, value
):
    refused(tmp_path, scene_file, emulator, capsys, setting("source", key, value), f"[source] {key} = ")


@pytest.mark.parametrize("key", _time_keys())
def test_every_time_of_the_source_just_past_its_bound_is_refused_naming_the_key(
    tmp_path, scene_file, emulator, capsys, key
):
    """One table (``acquisition.l8121.TIME_LIMITS``) bounds every time of the source's
    configuration; a protocol's ``[source]`` gives each, and each is refused just past its bound
    with the digits that set it apart from it."""
    from acquisition.l8121 import TIME_LIMITS
    from radiokit.checks import shown

    bound = TIME_LIMITS[key].max_s
    value = math.nextafter(bound, math.inf)
    line = refused(tmp_path, scene_file, emulator, capsys, setting("source", key, value), f"[source] {key}")
    assert f"{shown(value)} s: at most {bound:g} s" in line, line


@pytest.mark.parametrize("key", _time_keys())
def test_every_time_of_the_source_at_its_bound_is_taken(key):
    from acquisition.l8121 import TIME_LIMITS, SourceConfig

    cfg = SourceConfig(**{key: TIME_LIMITS[key].max_s})
    assert getattr(cfg, key) == TIME_LIMITS[key].max_s


@pytest.mark.parametrize("key", ["warmup_timeout_s", "ready_timeout_s"])
def test_the_driver_s_own_time_out_arguments_have_the_configuration_s_bounds(key):
    """``warm_up(timeout_s=...)`` and ``settled_status(timeout_s=...)`` are the same waits as the
    configuration's keys: refused past the same bound, before anything is sent."""
    from acquisition.l8121 import L8121, TIME_LIMITS

    src = L8121("loop://", connect=False)
    call = src.warm_up if key == "warmup_timeout_s" else src.settled_status
    with pytest.raises(ValueError, match=key):
        call(timeout_s=math.nextafter(TIME_LIMITS[key].max_s, math.inf))


@pytest.mark.parametrize(
    "action, option, key",
    [("warm-up", "--timeout", "warmup_timeout_s"), ("on", "--ready-timeout", "ready_timeout_s")],
)
@pytest.mark.parametrize("over", ["just over", "1e300"])
def test_cli_source_time_outs_past_the_configuration_s_bound_send_nothing(capsys, action, option, key, over):
    from acquisition.emulators.l8121 import L8121Model, PtyServer
    from acquisition.l8121 import TIME_LIMITS
    from radiokit.checks import shown
    from radiokit.cli import main

    bound = TIME_LIMITS[key].max_s
    value = math.nextafter(bound, math.inf) if over == "just over" else 1e300
    model = L8121Model(dialect="A", warmed_up=True)
    extra = ["--kv", "60", "--ua", "250", "--for", "1"] if action == "on" else []
    with PtyServer(model) as server:
        code = main(["acquire", "source", action, "--port", server.url, "--dialect", "A", *extra, option, repr(value)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"error: {option} {shown(value)}: at most {bound:g} s"), err
    assert err[0].endswith("nothing was sent"), err
    assert model.commands == [] and not model.xray_on


# -- the virtual panel's pitch ---------------------------------------------------------------------

#: the C7942's 50 µm pitch (C7942.md) at the scene's binning
PITCH_MM = 0.05 * BINNING


def test_a_pitch_that_is_not_the_virtual_panel_s_is_refused_before_any_x_ray_command(
    tmp_path, scene_file, emulator, capsys
):
    """``[detector] pixel_size_mm`` was overwritten by the simulated panel's pitch without a word:
    a protocol that said 0.05 mm ran, and its file said 0.2 (every length measured in it 4x)."""
    line = refused(
        tmp_path,
        scene_file,
        emulator,
        capsys,
        setting("detector", "pixel_size_mm", 0.05),
        "[detector] pixel_size_mm = 0.05",
    )
    assert f"{PITCH_MM:g} mm" in line, line  # says the virtual panel's


@pytest.mark.parametrize("binning", [None, 1, 2])
def test_the_virtual_panel_s_own_pitch_is_taken(tmp_path, scene_file, binning):
    """At the scene's binning, or at ``[sim] binning``'s: 0.05 mm times it."""
    from acquisition.protocols.compression_series import check_sim, load_protocol

    def edit(d):
        d["detector"]["pixel_size_mm"] = 0.05 * (binning or BINNING)
        if binning:
            d["sim"]["binning"] = binning

    check_sim(load_protocol(protocol(tmp_path, scene_file, "/dev/null", edit)))


# -- names as names print ------------------------------------------------------------------------


def _hostile_name(tmp_path, name="pro\x1b]2;x\x07to\ncol.toml"):
    """A protocol file named with a terminal escape and a newline, holding ``data``."""
    return tmp_path / name


@pytest.mark.parametrize(
    "edit, flags",
    [
        (setting("series", "frames_per_step", 0), []),  # refused as it loads
        (setting("detector", "bits", 8), []),  # refused by the virtual bench's check
        (lambda d: None, ["--port", "/dev/null"]),  # an option only source commands take
        (lambda d: None, ["-o", "out\x1b[2J.tif"]),  # not an HDF5 name
    ],
    ids=["load", "check", "option", "output"],
)
def test_a_hostile_file_name_is_printed_as_names_print(tmp_path, scene_file, emulator, capsys, edit, flags):
    from radiokit._names import shown
    from radiokit.cli import main

    model, server = emulator
    path = protocol(tmp_path, scene_file, server.url, edit)
    hostile = path.rename(_hostile_name(tmp_path))
    code = main(["acquire", str(hostile), "--sim", "-q", *flags])
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert code == 2 and "\x1b" not in text and "\x07" not in text, text
    lines = text.strip().splitlines()
    assert len(lines) == 1, lines
    named = shown("out\x1b[2J.tif") if flags[:1] == ["-o"] else shown(hostile)
    assert named in lines[0], lines
    assert model.commands == []


def test_an_existing_experiment_file_with_a_hostile_name_is_printed_as_names_print(
    tmp_path, scene_file, emulator, capsys
):
    from radiokit._names import shown
    from radiokit.cli import main

    model, server = emulator
    out = tmp_path / "out" / "se\x1b[2Jries.h5"

    def edit(d):
        d["output"] = str(out)

    path = protocol(tmp_path, scene_file, server.url, edit)
    out.write_bytes(b"")
    code = main(["acquire", str(path), "--sim", "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "\x1b" not in err[0], err
    assert f"error: {shown(out)}: exists" in err[0], err
    assert model.commands == []


# -- the exposure a protocol did not state ---------------------------------------------------------


class _Stamped:
    """A stream that notes, for each line written, the X-ray commands the emulator had received
    by then: what "before any X-ray command" means, observed (the output itself is kept)."""

    def __init__(self, model):
        self.model, self.lines, self._part = model, [], ""

    def write(self, text):
        self._part += text
        while "\n" in self._part:
            line, self._part = self._part.split("\n", 1)
            sent = [c for c in list(self.model.commands) if c.split()[0] in XRAY_COMMANDS]
            self.lines.append((line, sent))
        return len(text)

    def flush(self):
        pass

    def isatty(self):
        return False


def _without(stated):
    def edit(d):
        for key in ("voltage_kv", "current_ua"):
            if key not in stated:
                del d["source"][key]

    return edit


def _says_the_defaults(line, stated):
    from acquisition.protocols.compression_series import SourceSettings

    for key, unit in (("voltage_kv", "kV"), ("current_ua", "uA")):
        assert (f"{key} = {getattr(SourceSettings, key):g} {unit}" in line) == (key not in stated), line


def test_an_exposure_the_protocol_does_not_state_is_said_before_any_x_ray_command(
    tmp_path, scene_file, emulator, monkeypatch
):
    """A protocol without ``[source] voltage_kv`` and ``current_ua`` runs at the paper's 60 kV and
    250 µA (taken, not refused: protocols may rely on it), and the run says so once, before it
    sends any X-ray command (observed: the emulator's commands when the line was written)."""
    import sys

    from radiokit.cli import main

    model, server = emulator
    path = protocol(tmp_path, scene_file, server.url, _without(()))
    stream = _Stamped(model)
    monkeypatch.setattr(sys, "stderr", stream)
    assert main(["acquire", str(path), "--sim", "-q"]) == 0, stream.lines
    said = [(line, sent) for line, sent in stream.lines if "not stated" in line]
    assert len(said) == 1, stream.lines
    line, sent = said[0]
    assert sent == [] and str(path) in line, said
    _says_the_defaults(line, ())
    assert any(c.split()[0] in XRAY_COMMANDS for c in model.commands)  # the run did switch X-rays on


@pytest.mark.parametrize("stated", [("voltage_kv",), ("current_ua",)], ids=["kV only", "uA only"])
def test_the_dry_run_names_only_the_exposure_the_protocol_left_out(tmp_path, scene_file, emulator, capsys, stated):
    from radiokit.cli import main

    model, server = emulator
    path = protocol(tmp_path, scene_file, server.url, _without(stated))
    assert main(["acquire", str(path), "--sim", "--dry-run"]) == 0
    said = [ln for ln in capsys.readouterr().err.splitlines() if "not stated" in ln]
    assert len(said) == 1 and str(path) in said[0], said
    _says_the_defaults(said[0], stated)
    assert model.commands == []


def test_an_exposure_the_protocol_states_is_not_announced(tmp_path, scene_file, emulator, capsys):
    from radiokit.cli import main

    model, server = emulator
    path = protocol(tmp_path, scene_file, server.url, lambda d: None)
    assert main(["acquire", str(path), "--sim", "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert "not stated" not in captured.out + captured.err


@pytest.mark.parametrize(
    "name",
    [
        "plain.toml",
        "with space's.toml",
        "esc\x1b[2J.toml",
        "new\nline.toml",
        "back\\slash.toml",
        "bidi\u202e.toml",
        "c1\x85.toml",
    ],
)
def test_the_command_that_completes_a_series_reads_back_through_a_shell_and_prints_no_control(name):
    """The command offered to complete a stopped series names the protocol file: quoted so that
    bash reads it back as the name, and with no character the terminal acts on."""
    import argparse
    import shutil
    import subprocess
    import unicodedata

    from acquisition.cli import resume_command

    args = argparse.Namespace(protocol=name, sim=True, output=None, dialect=None)
    line = resume_command(args)
    assert not any(unicodedata.category(c) in ("Cc", "Cf", "Zl", "Zp") for c in line), line
    bash = shutil.which("bash")
    # (a UTF-8 locale, as a terminal's: bash writes $'\u0085' in the locale's encoding)
    env = {**os.environ, "LC_ALL": "C.UTF-8"}
    words = subprocess.run(
        [bash, "-c", f'set -- {line}; printf "%s\\0" "$@"'], capture_output=True, check=True, env=env
    ).stdout.split(b"\0")[:-1]
    assert [w.decode() for w in words] == ["radiokit", "acquire", name, "--sim", "--resume"]


def test_switch_off_attempts_past_their_bound_are_refused_naming_the_key(tmp_path, scene_file, emulator, capsys):
    """``off_attempts = 10**9``: a switch-off that is not confirmed would be retried for ever
    before the operator heard of it, the tube maybe on."""
    from acquisition.l8121 import OFF_ATTEMPTS_MAX, SourceConfig

    assert SourceConfig(off_attempts=OFF_ATTEMPTS_MAX).off_attempts == OFF_ATTEMPTS_MAX
    for value in (OFF_ATTEMPTS_MAX + 1, 10**9):
        line = refused(tmp_path, scene_file, emulator, capsys, setting("source", "off_attempts", value), "[source]")
        assert f"off_attempts = {value}: at most {OFF_ATTEMPTS_MAX}" in line, line


@pytest.mark.parametrize("over", ["just over", "1e300"])
def test_a_frame_wait_past_the_longest_beam_a_hung_run_may_keep_is_refused(
    tmp_path, scene_file, emulator, capsys, over
):
    """``[detector] timeout_s`` is how long the run waits for each frame -- for a flat's and a
    step's with X-rays on. 1e300 passed: a panel lost in a step kept the beam on for ever, the
    beam monitor's polls feeding the guardian's watchdog all along."""
    from acquisition.protocols.compression_series import WATCHDOG_MAX_S

    value = math.nextafter(WATCHDOG_MAX_S, math.inf) if over == "just over" else 1e300

    def edit(d):
        d["detector"]["timeout_s"] = value

    line = refused(tmp_path, scene_file, emulator, capsys, edit, "[detector] timeout_s")
    assert f"at most {WATCHDOG_MAX_S:g} s" in line, line


@pytest.mark.parametrize("action", ["status", "off"])
def test_a_source_command_prints_a_hostile_port_name_as_names_print(tmp_path, capsys, action):
    """``--port`` is a path the user typed (here a link to the emulator's pseudo-terminal, named
    with a terminal escape): the command's own lines print it as names print."""
    from acquisition.emulators.l8121 import L8121Model, PtyServer
    from radiokit._names import shown
    from radiokit.cli import main

    model = L8121Model(dialect="A", warmed_up=True)
    link = tmp_path / "tty\x1b[2J"
    with PtyServer(model) as server:
        link.symlink_to(server.url)
        code = main(["acquire", "source", action, "--port", str(link), "--dialect", "A"])
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert code == 0 and "\x1b" not in text, text
    assert shown(link) in text, text


# -- the protocol's own times: waits and estimates bounded as the source's are (review s54rvacq) --


def _protocol_time_keys():
    from acquisition.protocols.compression_series import PROTOCOL_TIME_LIMITS

    return sorted(PROTOCOL_TIME_LIMITS)


def test_every_wait_and_estimate_of_a_protocol_has_a_bound():
    """Every time of a protocol's own sections (a key ending ``_s``) is in the one table, or is a
    time bounded elsewhere (``[detector] timeout_s``, its ``settle_s`` below it, ``[source]``'s
    driver times and watchdog): a 1e300 settle stalled a series for ever, an estimate overflowed the dry run's."""
    import dataclasses

    from acquisition.l8121 import TIME_LIMITS
    from acquisition.protocols.compression_series import _SECTIONS, PROTOCOL_TIME_LIMITS

    bounded_elsewhere = {
        ("detector", "timeout_s"),
        ("detector", "settle_s"),
        ("source", "watchdog_s"),
        ("source", "poll_s"),
    }
    bounded_elsewhere |= {("source", k) for k in TIME_LIMITS}
    times = {(s, f.name) for s, cls in _SECTIONS.items() for f in dataclasses.fields(cls) if f.name.endswith("_s")}
    assert times - bounded_elsewhere == set(PROTOCOL_TIME_LIMITS)


@pytest.mark.parametrize("section, key", _protocol_time_keys(), ids=lambda v: v)
@pytest.mark.parametrize("over", ["just over", "1e300"])
def test_a_protocol_time_past_its_bound_sends_nothing(tmp_path, scene_file, emulator, capsys, section, key, over):
    """``[series] settle_s = 1e300`` was taken: the series warmed the tube up, took its darks and
    flats, then waited for ever before its first step (``[sim] settle_s`` likewise on the
    virtual bench); an estimate that large made the dry run's plan ``inf`` minutes."""
    from acquisition.protocols.compression_series import PROTOCOL_TIME_LIMITS
    from radiokit.checks import shown

    bound = PROTOCOL_TIME_LIMITS[section, key].max_s
    value = math.nextafter(bound, math.inf) if over == "just over" else 1e300
    line = refused(tmp_path, scene_file, emulator, capsys, setting(section, key, value), f"[{section}] {key}")
    assert f"{shown(value)} s: at most {bound:g} s" in line, line


def test_every_protocol_time_at_its_bound_is_a_protocol(tmp_path, scene_file):
    """The bounds refuse no protocol a lab could mean (a gel that relaxes for hours, a warm-up
    after months idle, a network share's slow writes): each at its bound is taken."""
    from acquisition.protocols.compression_series import PROTOCOL_TIME_LIMITS, load_protocol

    def edit(d):
        for (section, key), limit in PROTOCOL_TIME_LIMITS.items():
            d.setdefault(section, {})[key] = limit.max_s
        d["detector"].update(timeout_s=600.0, settle_s=599.0)  # a share whose writes pause for minutes

    p = load_protocol(protocol(tmp_path, scene_file, "/dev/null", edit))
    assert p.series.settle_s == PROTOCOL_TIME_LIMITS["series", "settle_s"].max_s


def test_the_estimates_bounds_are_the_driver_s():
    """The warm-up and ramp bounds of the protocol's estimates are the driver's waits'."""
    from acquisition.l8121 import TIME_LIMITS
    from acquisition.protocols.compression_series import PROTOCOL_TIME_LIMITS

    assert PROTOCOL_TIME_LIMITS["sim", "warmup_s"].max_s == TIME_LIMITS["warmup_timeout_s"].max_s
    assert PROTOCOL_TIME_LIMITS["source", "warmup_estimate_s"].max_s == TIME_LIMITS["warmup_timeout_s"].max_s
    assert PROTOCOL_TIME_LIMITS["sim", "ramp_s"].max_s == TIME_LIMITS["stable_timeout_s"].max_s


def test_the_settle_bound_rests_on_the_tube_s_idle_warm_up():
    """L8121.md: dialect B's DAG names a warm-up mode "after 8 h idle"; the series warms up once,
    at its start, so a step that waited longer found the tube needing a warm-up it never gets."""
    from acquisition.protocols.compression_series import PROTOCOL_TIME_LIMITS

    text = (Path(__file__).resolve().parents[1] / ".." / "shared" / "hardware" / "L8121.md").read_text()
    assert "after 8 h idle" in text
    assert PROTOCOL_TIME_LIMITS["series", "settle_s"].max_s == 8 * 3600


@pytest.mark.parametrize("value", [0, 0.0])
def test_a_frame_wait_of_no_time_is_refused(tmp_path, scene_file, emulator, capsys, value):
    """``[detector] timeout_s = 0`` was taken: every frame of a flat's batch 'timed out' at once,
    after the tube had been switched on for it."""
    refused(tmp_path, scene_file, emulator, capsys, setting("detector", "timeout_s", value), "[detector] timeout_s")


def test_a_frame_file_settle_no_shorter_than_the_frame_wait_is_refused(tmp_path, scene_file, emulator, capsys):
    """A frame file is taken once it has held still for ``[detector] settle_s``; the wait for it is
    ``timeout_s``: a settle as long as the wait timed out every frame, X-rays on."""

    def edit(d):
        d["detector"].update(timeout_s=5.0, settle_s=5.0)

    refused(tmp_path, scene_file, emulator, capsys, edit, "[detector] settle_s = 5", "timeout_s")


# -- a resume compares the pitch the file records, not 0.05 mm (review s54rvacq) -----------------


@pytest.mark.parametrize("binning", [None, 2])
def test_a_sim_resume_compares_the_virtual_panel_s_binned_pitch(tmp_path, scene_file, binning):
    """A series on the virtual panel binned 4 (pitch 0.2 mm; or [sim] binning 2: 0.1 mm), its
    protocol silent on the pitch; the same protocol with the pitch stated (what check_sim asks
    for) resumed it. The file's unset pitch was compared as 0.05 mm, and the resume refused a
    setting it never changed (``--resume --sim``: "differs in [detector] pixel_size_mm")."""
    from acquisition.protocols.compression_series import _resume_differences, load_protocol

    pitch = 0.05 * (binning or BINNING)

    def sim(pixel=None):
        def edit(d):
            if binning:
                d["sim"]["binning"] = binning
            if pixel is not None:
                d["detector"]["pixel_size_mm"] = pixel

        return load_protocol(protocol(tmp_path, scene_file, "/dev/null", edit))

    assert _resume_differences(sim(), sim(pitch), sim=True) == []
    assert _resume_differences(sim(pitch), sim(), sim=True) == []


@pytest.mark.parametrize("cols, pitch", [(1120, 0.1), (560, 0.2)])
def test_a_lab_resume_compares_the_pitch_a_binned_shape_implies(cols, pitch):
    """In the lab an unset pitch is the one the frames' width implies (the folder watcher's:
    0.05 mm times the binning a 1120 or 560 column frame means), and the file records it: a
    resume that states it is the same series; one that states 0.05 mm is not."""
    from acquisition.protocols.compression_series import _resume_differences, load_protocol

    def lab(pixel=None):
        d = {"detector": {"folder": "frames", "shape": [cols, cols]}}
        if pixel is not None:
            d["detector"]["pixel_size_mm"] = pixel
        return load_protocol(d)

    assert _resume_differences(lab(), lab(pitch), sim=False) == []
    assert _resume_differences(lab(pitch), lab(), sim=False) == []
    assert any("pixel_size_mm" in said for said in _resume_differences(lab(), lab(0.05), sim=False))


# -- the driver's and the transport's own lines name a hostile port as names print (s54rvacq) -----


def test_the_driver_s_refusal_names_a_hostile_port_as_names_print(tmp_path, capsys):
    """The driver's lines (``SourceFault: ...: X-rays not switched on: interlock open``) began
    with the port raw: a link named with a terminal escape sent it to the terminal."""
    from acquisition.emulators.l8121 import L8121Model, PtyServer
    from radiokit._names import shown
    from radiokit.cli import main

    model = L8121Model(dialect="A", warmed_up=True)
    model.open_interlock()
    link = tmp_path / "tty\x1b[2J"
    with PtyServer(model) as server:
        link.symlink_to(server.url)
        code = main(
            [
                "acquire",
                "source",
                "on",
                "--port",
                str(link),
                "--dialect",
                "A",
                "--kv",
                "60",
                "--ua",
                "250",
                "--for",
                "1",
            ]
        )
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert code != 0 and "interlock" in text, text
    assert "\x1b" not in text and shown(link) in text, text
    assert not model.xray_on


def test_the_transport_s_refusal_names_a_hostile_port_as_names_print(tmp_path, capsys):
    """A port that cannot be opened: the transport's line printed the name raw."""
    from radiokit._names import shown
    from radiokit.cli import main

    port = tmp_path / "no\x1b[2Jtty"
    code = main(["acquire", "source", "status", "--port", str(port), "--dialect", "A"])
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert code != 0 and "\x1b" not in text, text
    assert shown(port) in text, text


def test_the_driver_s_api_refusal_names_a_hostile_port_as_names_print():
    """Python API: the refusal of a warm-up time-out past its bound, nothing sent."""
    from acquisition.l8121 import L8121
    from radiokit._names import shown

    port = "/dev/no\x1b]2;x\x07tty"
    src = L8121(port, connect=False)
    with pytest.raises(ValueError) as err:
        src.warm_up(timeout_s=1e300)
    assert str(err.value).startswith(f"{shown(port)}: ") and "\x1b" not in str(err.value)
    assert src.port == port  # the name itself is kept: the port opened is the one typed


def test_a_stored_protocol_refused_names_its_file_as_names_print(tmp_path, scene_file, emulator, capsys):
    """A file whose stored protocol today's rules refuse (``settle_s = 1e300``, taken before its
    bound): the line named the file raw, an escape in its name sent to the terminal."""
    import tomllib

    from radiokit._names import shown
    from radiokit.cli import main
    from radiokit.io import ExperimentWriter

    model, server = emulator
    out = tmp_path / "out" / "ser\x1b[2Jies.h5"
    path = protocol(tmp_path, scene_file, server.url, setting("series", "settle_s", 0.0))
    data = tomllib.loads(path.read_text())
    data["series"]["settle_s"] = 1e300  # what the release before the bound recorded
    with ExperimentWriter(out, shape=(PANEL, PANEL)) as w:
        w.record_run(tomli_w.dumps(data), {})
    code = main(["acquire", str(path), "--sim", "-o", str(out), "--resume", "-q"])
    captured = capsys.readouterr()
    lines = [ln for ln in (captured.out + captured.err).splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, lines
    assert "\x1b" not in lines[0] and shown(out) in lines[0] and "[series] settle_s" in lines[0], lines
    assert model.commands == []


@pytest.mark.parametrize("key, value", [("timeout_s", 1e300), ("timeout_s", math.nan), ("min_interval_s", 1e300)])
def test_the_probe_s_own_waits_have_the_configuration_s_bounds(key, value):
    """``probe(url, timeout_s=1e300)``, the Python API's probe: each reply waited for ever (the
    same wait as ``probe_timeout_s``, bounded there); refused before the port is opened."""
    from acquisition.l8121 import probe

    with pytest.raises(ValueError, match="probe_timeout_s" if key == "timeout_s" else key):
        probe("/dev/no-such-port-s54", **{key: value})
