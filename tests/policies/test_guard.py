"""torcsrl.policies.guard: the side guard (SideGuard) around a racer, its specs and settings."""

from __future__ import annotations

import pytest
import torch

from torcsrl.policies import PolicyError, SideGuard, load_policy

from ._scenes import guard_scene


def test_side_guard_steers_away_from_a_car_beside_and_leaves_every_other_command_alone():
    """Hand-placed cars around a racer (racer_safe reads opponents and state): sector 9 is 85 degrees left of the
    heading, sector 26 85 degrees right; a car 2.0 m to the side is 0.6 m inside the default 2.6 m of room."""
    import math

    guard = load_policy("side_guard:racer_safe:1.27:8:9")
    assert isinstance(guard, SideGuard) and guard.settings == SideGuard.DEFAULTS and guard.inner.spec == "racer_safe:1.27:8:9"
    r2 = 2.0 / math.sin(math.radians(85.0))  # 2.0 m to the side, 0.17 m ahead: beside
    push = 0.04 * 0.6  # gain_per_m x the shortfall
    for steer in (0.3, -0.2, 0.0):
        a, opp, tp = guard_scene(steer)
        assert torch.equal(guard.correct(a, opp, tp), a)  # alone: the policy's own action
        for far in ({"s9": 8.0 / math.sin(math.radians(85.0))}, {"s17": 6.0}, {"s0": 9.0}):  # 8 m to the side; 6 m ahead; 9 m behind
            a, opp, tp = guard_scene(steer, **far)
            assert torch.equal(guard.correct(a, opp, tp), a), far
    a, opp, tp = guard_scene(0.3, s9=r2)  # steering left, toward the car on the left: halved, then pushed right
    out = guard.correct(a, opp, tp)
    assert out[0, 0].item() == pytest.approx(0.15 - push, abs=1e-5) and out[0, 1] == a[0, 1]  # the pedal is the policy's
    a, opp, tp = guard_scene(-0.2, s9=r2)  # already steering away: pushed further
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(-0.2 - push, abs=1e-5)
    a, opp, tp = guard_scene(-0.3, s26=r2)  # mirrored: a car on the right, steering toward it
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(-0.15 + push, abs=1e-5)
    a, opp, tp = guard_scene(0.3, tp=-0.8, s9=r2)  # already 0.8 out to the right: no push off the road, still halved
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(0.15, abs=1e-6)
    behind = 2.0 / math.sin(math.radians(135.0))  # sector 4 (135 deg left): 2.0 m left, 2.0 m behind (the car it passed)
    a, opp, tp = guard_scene(0.3, s4=behind, s26=4.0)  # the nearer car to the side decides: the one on the left
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(0.15 - push, abs=1e-5)
    rows = torch.cat([guard_scene(0.3)[0], guard_scene(0.3, s9=r2)[0]]), torch.cat([guard_scene(0.3)[1], guard_scene(0.3, s9=r2)[1]])
    out = guard.correct(rows[0], rows[1], torch.zeros(2))  # a batch: only the row with a car beside changes
    assert out[0, 0] == 0.3 and out[1, 0].item() == pytest.approx(0.15 - push, abs=1e-5)


def test_side_guard_specs_and_settings_fail_in_one_line():
    g = load_policy("side_guard:3:0.05:0.6:racer_safe:1.27:8:9")
    assert g.settings == {**SideGuard.DEFAULTS, "clear_m": 3.0, "gain_per_m": 0.05, "edge_tp": 0.6}
    assert load_policy("side_guard:3:racer_safe").settings["clear_m"] == 3.0 and load_policy("side_guard:3:racer_safe").inner.spec == "racer_safe"
    for bad, match in (("side_guard:", "names no policy"), ("side_guard:2.6:", "names no policy"),
                       ("side_guard:expert", "reads opponents, which that policy does not"),
                       ("side_guard:-1:racer_safe", "out of range"), ("side_guard:2.6:0.04:1.5:racer_safe", "out of range"),
                       ("side_guard:side_guard:racer_safe", "already drives behind one"), ("side_guard:reference_racer", "already drives behind one"),
                       ("side_guard:racer_safe:fast", "racer_safe")):
        with pytest.raises(PolicyError, match=match) as err:
            load_policy(bad)
        assert "\n" not in str(err.value), bad
