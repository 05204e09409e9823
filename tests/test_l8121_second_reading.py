"""The driver against a second, independent model of the L8121 (tests/l8121_second_reading.py).

The model was written from ../shared/hardware/L8121.md alone, before the driver's emulator or tests
were read; where the notes allow a unit to do something, it does it here, and the driver must cope.
"""

from __future__ import annotations

import time

import pytest
from l8121_second_reading import Controller, Knobs

from acquisition.l8121 import L8121


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_the_spacing_counts_from_the_last_byte_of_a_cr_lf_reply(dialect):
    # L8121.md: replies end in CR or CR LF; a controller may need ~50 ms between commands. A unit
    # whose LF follows its CR 30 ms later has answered only at the LF: counted from the CR, the
    # driver's 60 ms left it 30 ms, and this model, like a unit that needs them, lost the command.
    knobs = Knobs(dialect=dialect, eol=b"\r\n", lf_pause_s=0.03)
    with Controller(knobs) as c, L8121(c.port, dialect=dialect) as src:
        for pause in (0, 0.04, 0, 0.04):
            # asked again at once, or once the LF is waiting (as a new link to the unit, the
            # guardian's, first asks): either way the LF is the reply's last byte
            time.sleep(pause)
            assert src.interlock_closed()
    assert c.breaches == []
    assert None not in [reply for _, _, reply in c.log]


def test_b_waits_for_srb_ready_before_its_control_commands():
    # L8121.md lists B's SRB, READY or BUSY, "remote operation state", which the L8121-02 driver
    # polls in its cycle; a unit busy at first refuses control commands: the presets waited for
    # READY instead of failing at the first PHV.
    knobs = Knobs(dialect="B", b_busy_s=0.6, ramp_s=0.05)
    with Controller(knobs) as c, L8121(c.port, dialect="B") as src:
        src.on(60, 250)
        assert c.emitting()
        src.off()
    assert c.xray_commands == [("XON", 60.0, 250)]
    assert not c.emitting()
    assert "ERROR" not in [reply for _, cmd, reply in c.log if cmd != "Enter"]
