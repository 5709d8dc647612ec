"""The motor interface through VirtualMotors: steps, limits, backlash, blocking, image map."""

from __future__ import annotations

import time

import numpy as np
import pytest

from softplot.motors import AxisConfig, MotorError, MotorLimitError, MotorTimeout, VirtualMotors


def test_positions_on_the_step_grid():
    m = VirtualMotors()
    m.move_to(1.234, -2.0049)
    assert m.position_steps() == (123, -200)
    assert m.position() == pytest.approx((1.23, -2.00), abs=1e-12)
    m.move_by(0.004, 0.006)  # relative to the target, not the rounded position
    assert m.position_steps() == (123, -200 + 1)
    assert m.quantize(0.015, -0.015) in ((0.02, -0.02), (0.01, -0.01), (0.02, -0.01), (0.01, -0.02))


def test_travel_limits_move_nothing():
    ax = AxisConfig(min_mm=-5, max_mm=5)
    m = VirtualMotors(ax, ax)
    m.move_to(1, 1)
    with pytest.raises(MotorLimitError, match="DY target 5.0100 mm outside travel"):
        m.move_to(0, 5.01)
    with pytest.raises(MotorLimitError, match="not finite"):
        m.move_to(float("nan"), 0)
    assert m.position() == pytest.approx((1, 1))
    m.move_to(5, -5)  # the limits themselves are inside
    assert m.position() == pytest.approx((5, -5))


def test_bad_axis_configuration():
    with pytest.raises(MotorError, match="resolution"):
        AxisConfig(resolution_mm=0)
    with pytest.raises(MotorError, match="travel"):
        AxisConfig(min_mm=3, max_mm=1)
    with pytest.raises(MotorError, match="backlash"):
        AxisConfig(backlash_steps=-1)


@pytest.mark.parametrize("slack", [0, 3, 7])
def test_backlash_compensation_puts_the_plate_on_target(slack):
    """A drive with ``slack`` steps of play: compensated, the physical plate lands on every
    target from either side; uncompensated, it misses by the slack after each reversal."""
    rng = np.random.default_rng(slack)
    targets = rng.uniform(-4, 4, (40, 2))
    ax = AxisConfig(backlash_steps=slack)
    comp = VirtualMotors(ax, ax, slack_steps=(slack, slack))
    raw = VirtualMotors(slack_steps=(slack, slack))
    misses = []
    for tx, ty in targets:
        comp.move_to(tx, ty)
        raw.move_to(tx, ty)
        assert comp.plate_steps() == comp.position_steps()
        assert comp.position_steps() == (round(tx / 0.01), round(ty / 0.01))
        misses.append(np.subtract(raw.plate_steps(), raw.position_steps()))
    misses = np.abs(np.array(misses))
    assert misses.max() == slack


def test_non_blocking_moves_take_time_and_wait():
    ax = AxisConfig(max_speed_mm_s=20.0)
    m = VirtualMotors(ax, ax, simulate_time=True)
    t0 = time.monotonic()
    m.move_to(2.0, 1.0, wait=False)  # 0.1 s at 20 mm/s
    assert m.busy
    assert not m.wait(timeout=0.01)
    assert m.wait(timeout=2.0)
    assert time.monotonic() - t0 >= 0.09
    assert m.position() == pytest.approx((2.0, 1.0))
    with pytest.raises(MotorTimeout, match="not finished"):
        m.move_to(-2.0, -1.0, timeout=0.01)
    m.stop()
    dx, dy = m.position()
    assert -2.0 < dx < 2.0 and not m.busy
    assert m.target() == pytest.approx((dx, dy))
    m.home()
    assert m.position() == (0.0, 0.0)


def test_sampling_position_through_inverse_film_correction():
    # left film mm -> pixel: 1200 dpi scan, origin at the image centre, y down
    s = 1200 / 25.4

    def image_map(xy):
        return np.c_[1000 + s * xy[:, 0], 800 - s * xy[:, 1]]

    m = VirtualMotors(image_map=image_map)
    m.set_main(10.0, -5.0)
    m.move_to(1.5, 0.25)
    assert m.left_film() == pytest.approx((11.5, -4.75))
    assert m.sampling_position() == pytest.approx([1000 + s * 11.5, 800 + s * 4.75])
    assert VirtualMotors().sampling_position() == pytest.approx([0.0, 0.0])


def test_state_restore_approaches_from_the_saved_side():
    ax = AxisConfig(backlash_steps=4)
    a = VirtualMotors(ax, ax, slack_steps=(4, 4))
    a.move_to(3, 3)
    a.move_to(1.0, 2.0)  # approached from above: slack on the other side
    a.set_main(7, 8)
    st = a.state()
    b = VirtualMotors(ax, ax, slack_steps=(4, 4))
    b.restore(st)
    assert b.position_steps() == (100, 200) and b.plate_steps() == (100, 200)
    assert b.state()["direction"] == st["direction"]
    assert b.encoders() == (7, 8)
