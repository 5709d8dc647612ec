"""docs/motors.md lists exactly the GRBL commands the driver sends: every driver operation is
run against the simulator and what reached it is compared with the documented table."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from softplot.motors import AxisConfig, MotorAlarm
from softplot.motors.grbl import GrblMotors
from softplot.motors.simulator import GrblSimulator

DOC = Path(__file__).resolve().parents[1] / "docs" / "motors.md"
REALTIME = {0x3F: "?", 0x21: "!", 0x7E: "~", 0x18: "0x18", 0x85: "0x85"}


def _documented() -> set[str]:
    text = DOC.read_text()
    table = text[text.index("| sent | when |"):]
    table = table[: table.index("\n\n")]
    out = set()
    for row in table.splitlines()[2:]:
        first = row.split("|")[1]
        out.update(re.findall(r"`([^`]+)`", first))
    return out


def _token(line: str) -> str:
    """A line as the docs write it: numbers of X, Y, F and of settings as an ellipsis."""
    line = re.sub(r"^(\$\d+=).*", r"\1", line)
    return re.sub(r"(?<=[XYF])[-+]?\d+(?:\.\d*)?", "…", line)


def test_the_driver_sends_exactly_what_the_docs_list():
    ax = AxisConfig(min_mm=-100, max_mm=100)
    sim = GrblSimulator(time_scale=20, settings={20: 1, 22: 1}, encoders=True)
    own = ["$J=G91X-50F500", "G90G0X500"]  # lines this test sends itself
    with sim, GrblMotors(sim.path, ax, ax, timeout=1, reset=True, unlock=True,
                         check_encoders=True) as m:
        m.home()
        m.move_to(-1.0, -1.0)
        m.move_to(-60.0, 0.0, wait=False)
        m.wait(0.05)
        m.stop()  # feed hold, reset
        m.zero_here()
        m.command(own[0])
        time.sleep(0.05)
        m.stop()  # jog cancel
        with pytest.raises(MotorAlarm):
            m.command(own[1])
        m.recover()  # reset, $X after ALARM:2
        m.confirm_position()
        m.move_to(-1.0, 0.0)
    sent = {_token(ln) for ln in sim.log if ln not in own}
    sent |= {REALTIME[b] for b in sim.realtime_log}
    assert sent == _documented()
