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
