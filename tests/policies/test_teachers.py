"""torcsrl.policies.teachers: the fast sensor teacher and the racer (SensorRacer) and its variants."""

from __future__ import annotations

import pytest

from torcsrl.policies import PolicyError, load_policy

from ._scenes import sectors, straight_road


def test_racer_passes_lifts_and_brakes_from_its_opponents_sectors():
    import math

    racer = load_policy("racer")
    r, st = straight_road(speed_kmh=36.0)  # 10 m/s: lift within 10 + 0.8 x 10 = 18 m, brake within 6 + 0.5 x 10 = 11 m
    assert racer.traffic(r, st, sectors()) == (0.0, 1.0)  # an empty road: sensor_fast
    t_right, cap = racer.traffic(r, st, sectors(s18=25.0))  # 25 m ahead, 2.2 m right of the axis (sector 18: -5 deg)
    t_left, _ = racer.traffic(r, st, sectors(s17=25.0))  # ... 2.2 m left of it
    assert t_right > 0.0 > t_left and cap == 1.0  # moves out on the other side, no lift yet
    assert abs(t_right * 6.0 + 25.0 * math.sin(math.radians(5.0)) - racer.race.pass_gap_m) < 1e-6  # pass_gap beside it
    assert racer.traffic(r, st, sectors(s18=15.0))[1] == 0.0  # in its path within the lift distance
    assert racer.traffic(r, st, sectors(s18=8.0))[1] < 0.0  # within the brake distance
    t, cap = racer.traffic(r, st, sectors(s9=4.0))  # alongside on the left: keep a pass gap right of it, no braking
    y_left = 4.0 * math.sin(math.radians(85.0))  # sector 9's centre: 85 degrees left
    assert y_left - t * 6.0 >= racer.race.pass_gap_m - 1e-6 and cap == 1.0
    assert racer.traffic(r, st, sectors(s0=30.0)) == (0.0, 1.0)  # a car behind does not matter


def test_safe_racer_brakes_as_the_bold_one_on_asphalt_and_earlier_on_low_grip():
    import math

    import numpy as np

    from torcsrl.training.demos import DemoError, known_teacher, make_teacher
    from torcsrl.policies import SensorRacer

    bold, safe, safe15 = load_policy("racer_bold"), load_policy("racer_safe"), load_policy("racer_safe:1.5")
    assert safe.k.grip_exponent == SensorRacer.SAFE_GRIP_EXPONENT == 2.0 and safe15.k.grip_exponent == 1.5
    r = np.full(19, 80.0)  # walls 80 m ahead all round: a tight bend, the car at 40 km/h
    _, st = straight_road(speed_kmh=40.0)
    assert safe.act(r, st, mu=1.0) == bold.act(r, st, mu=1.0)  # asphalt: the same driver
    pedals = [p.act(r, st, mu=0.6)[1] for p in (bold, safe15, safe)]  # dirt: less pedal as gamma grows
    assert pedals[0] > pedals[1] > pedals[2]
    # it plans with 9 mu^gamma m/s^2: on dirt racer_safe is the bold racer told it brakes at 9 x 0.36
    told = SensorRacer(**{**SensorRacer.BOLD, "decel_per_mu": 9.0 * 0.6 ** 2})
    assert safe.act(r, st, mu=0.6) == pytest.approx(told.act(r, st, mu=1.0), abs=1e-12)
    assert known_teacher("racer_safe") and known_teacher("racer_safe:1.5") and not known_teacher("racer_safer")
    assert make_teacher("racer_safe:1.5").k.grip_exponent == 1.5
    for bad, msg in (("racer_safe:x", "must be a number"), ("racer_safe:0.5", ">= 1")):
        with pytest.raises(PolicyError, match=msg):
            load_policy(bad)
        with pytest.raises(DemoError, match=msg):
            make_teacher(bad)


def test_racer_safe_takes_an_asphalt_braking_rate_and_a_rate_for_a_fight():
    """``racer_safe:<gamma>:<decel>[:<fight decel>[:<fight m>]]``: the braking it plans with on asphalt [m/s^2 at mu 1]
    in place of 9 (a margin where the bold racer plans at the limit), and with a third value the rate while a car is
    within 60 m (or the fourth value; any sector): alone it drives as the second value says, in a fight as the third."""
    import numpy as np
    import torch
    from tensordict import TensorDict

    from torcsrl.training.demos import DemoError, known_teacher, make_teacher

    r, st = straight_road(speed_kmh=205.0)  # 57 m/s with 200 m free: 9 m/s^2 still accelerates, 8 must brake
    assert load_policy("racer_safe:1.5").act(r, st, mu=1.0)[1] > 0.0 > load_policy("racer_safe:1.5:8").act(r, st, mu=1.0)[1]
    m8, fight = load_policy("racer_safe:1.27:8"), load_policy("racer_safe:1.27:8:9")
    assert (m8.k.decel_per_mu, m8.k.grip_exponent, m8.race.fight_decel_per_mu) == (8.0, 1.27, None)
    assert fight.race.fight_decel_per_mu == 9.0 and load_policy("racer_safe:1.5").race.fight_decel_per_mu is None
    # on dirt (mu 0.6) gamma 1.27 with 8 plans as gamma 1.5 with 9: 4.18 m/s^2
    assert 8.0 * 0.6 ** 1.27 == pytest.approx(9.0 * 0.6 ** 1.5, abs=0.01)

    def pedal(pol, opp):
        td = TensorDict({"rangefinder": torch.tensor(r, dtype=torch.float32)[None], "state": torch.tensor(st, dtype=torch.float32)[None],
                         "opponents": torch.tensor(opp, dtype=torch.float32)[None], ("info", "surfaceMu"): torch.ones(1, 1)}, [1])
        return float(pol(td)["action"][0, 1])

    alone, far, beside = sectors(), sectors(s17=100.0), sectors(s8=40.0)  # nothing; 100 m ahead; 40 m off to the left
    assert pedal(fight, alone) == pedal(m8, alone) < 0.0  # alone: the margin
    assert pedal(fight, far) == pedal(m8, far)  # a car beyond 60 m is no fight
    assert pedal(fight, beside) == pedal(load_policy("racer_safe:1.27"), beside) > 0.0  # a car 40 m away: the limit
    wide = load_policy("racer_safe:1.27:8:9:150")  # a fight is a car within 150 m
    assert wide.race.fight_m == 150.0 and pedal(wide, far) == pedal(load_policy("racer_safe:1.27"), far) > 0.0
    assert known_teacher("racer_safe:1.27:8:9") and make_teacher("racer_safe:1.27:8:9").race.fight_decel_per_mu == 9.0
    for bad, msg in (("racer_safe:1.5:0", r"in \(0, 12\]"), ("racer_safe:1.5:8:13", r"in \(0, 12\]"),
                     ("racer_safe:1.5:8:9:60:5:1:2", "at most six"), ("racer_safe:1.5:8:9:60:5:-1", r"in \[0, 200\] m"), ("racer_safe:1.5:8:9:250", r"in \(0, 200\]"),
                     ("racer_safe:1.5:8:9:60:40", r"room kept past a car passed must be in \[0, 30\]"),
                     ("racer_safe:1.5:fast", "must be a number")):
        with pytest.raises(PolicyError, match=msg):
            load_policy(bad)
        with pytest.raises(DemoError, match=msg):
            make_teacher(bad)


def test_a_racer_with_room_to_clear_holds_its_passing_line_past_the_car_it_passed():
    """``racer_safe:...:<clear m>``: the passing line is held until the car passed is ``clear_m`` behind, then faded
    over ``rear_m`` as before (default 0: the fade starts as the car is level)."""
    import math

    now, clear = load_policy("racer_safe:1.27:8:9"), load_policy("racer_safe:1.27:8:9:60:6")
    assert now.race.clear_m == 0.0 and clear.race.clear_m == 6.0 and now.fingerprint != clear.fingerprint
    r, st = straight_road(speed_kmh=72.0)
    d, phi = 5.59, math.radians(175.0 - 10.0 * 33)  # sector 33: a car ~5 m behind, 2.4 m right (just passed on its left)
    x, y = d * math.cos(phi), d * math.sin(phi)
    aim = y / 6.0 + clear.race.pass_gap_m / 6.0  # pass_gap beside it (half-width 6 m)
    t_now, _ = now.traffic(r, st, sectors(s33=d))
    t_clear, _ = clear.traffic(r, st, sectors(s33=d))
    assert t_clear == pytest.approx(aim) and t_now == pytest.approx(aim * (x + now.race.rear_m) / now.race.rear_m) and t_now < t_clear
    far = 20.0 / abs(math.cos(math.radians(175.0 - 350.0)))  # sector 35: 20 m behind, 1.7 m right: beyond rear_m
    assert now.traffic(r, st, sectors(s35=far))[0] == 0.0 and clear.traffic(r, st, sectors(s35=far))[0] > 0.0  # still fading


def test_keep_racer_finishes_a_pass_on_its_side_and_holds_its_lane_when_that_side_is_taken():
    """``racer_keep``: beside the car it passes, with a third car on its passing line, ``racer_safe`` takes the other
    side's line (across the passed car) while ``racer_keep`` holds its trackPos; with that side free both pass alike."""
    import math

    from torcsrl.training.demos import known_teacher, make_teacher
    from torcsrl.envs.sensors import STATE_SLOTS

    safe, keep = load_policy("racer_safe:1.27:8:9"), load_policy("racer_keep:1.27:8:9")
    assert keep.race.keep_side and not safe.race.keep_side and keep.fingerprint != safe.fingerprint
    assert keep.k.grip_exponent == 1.27 and keep.race.bend_lanes == safe.race.bend_lanes == 1.0
    assert known_teacher("racer_keep:1.27:8:9") and make_teacher("racer_keep:1.27:8:9").race.keep_side
    with pytest.raises(PolicyError, match="racer_keep:"):
        load_policy("racer_keep:fast")
    r, st = straight_road(half_width_m=10.0, speed_kmh=72.0)
    tp = 0.25
    st[STATE_SLOTS.index("trackPos")] = tp
    w, gap = 10.0, safe.race.pass_gap_m / 10.0
    d = 2.0  # sector 26 (-85 deg): the car passed, 2 m to the right, level with it (committed: |dy| > 1.5 m)
    tp_o = tp + d * math.sin(math.radians(175.0 - 10.0 * 26)) / w
    left, right = tp_o + gap, tp_o - gap
    beside = sectors(s26=d)
    assert safe.traffic(r, st, beside)[0] == pytest.approx(left) and keep.traffic(r, st, beside)[0] == pytest.approx(left)
    third = sectors(s26=d, s17=12.0 / math.cos(math.radians(5.0)))  # and a car 12 m ahead, ~1 m left: on that line
    assert safe.traffic(r, st, third)[0] == pytest.approx(right) and right < tp_o  # across the passed car's path
    target, cap = keep.traffic(r, st, third)
    assert target == pytest.approx(tp) and cap < 0.0  # holds its lane and brakes for the car ahead
    alone = sectors()
    assert keep.traffic(r, st, alone) == safe.traffic(r, st, alone) == (0.0, 1.0)


def test_yield_racer_completes_a_pass_before_the_braking_zone_or_gives_it_up():
    """``racer_yield``: within ``abandon_m`` of its braking point it starts no pass, and beside a car it has not
    cleared by a car length it holds its lane (braking while that car's centre is ahead of its own), where
    ``racer_safe`` finishes the pass into the bend; far from the bend, or a car length clear, both drive alike."""
    import math

    from torcsrl.training.demos import known_teacher, make_teacher
    from torcsrl.envs.sensors import STATE_SLOTS

    safe, yld = load_policy("racer_safe:1.27:8:9"), load_policy("racer_yield:1.27:8:9")
    assert yld.race.abandon_m == 30.0 and safe.race.abandon_m is None and yld.fingerprint != safe.fingerprint
    assert yld.k.grip_exponent == 1.27 and yld.race.bend_lanes == safe.race.bend_lanes == 1.0
    assert known_teacher("racer_yield:1.27:8:9") and make_teacher("racer_yield:1.27:8:9").race.abandon_m == 30.0
    with pytest.raises(PolicyError, match="racer_yield:"):
        load_policy("racer_yield:fast")
    r_far, st = straight_road(half_width_m=10.0, speed_kmh=72.0)  # 20 m/s: braking at 8 m/s^2 takes 25 m
    st[STATE_SLOTS.index("trackPos")] = 0.25
    r_bend = r_far.copy()
    r_bend[yld.centre] = 50.0  # the road ends 50 m ahead: within 25 + 30 m of the bend, not within 25 + 20
    cases = {"level": sectors(s26=2.0),  # -85 deg, 2 m: beside it, its centre 0.17 m ahead
             "half ahead": sectors(s28=3.0),  # -105 deg, 3 m: its centre 0.8 m behind, not yet a car length
             "clear": sectors(s33=6.0),  # -155 deg, 6 m: 5.4 m behind (a car length clear), 2.5 m right
             "to pass": sectors(s18=15.0)}  # -5 deg, 15 m ahead, 1.3 m right: a pass not yet started
    for opp in cases.values():  # far from the bend: the same driver
        assert yld.traffic(r_far, st, opp) == safe.traffic(r_far, st, opp)
    assert safe.traffic(r_bend, st, cases["level"])[0] > 0.4  # racer_safe: on into the bend on its passing line (0.43)
    assert yld.traffic(r_bend, st, cases["level"]) == (pytest.approx(0.25), -yld.race.brake)  # its lane, braking
    assert yld.traffic(r_bend, st, cases["half ahead"]) == (pytest.approx(0.25), 1.0)  # its lane, no lift
    assert yld.traffic(r_bend, st, cases["clear"]) == safe.traffic(r_bend, st, cases["clear"])
    assert safe.traffic(r_bend, st, cases["to pass"])[0] > 0.25 and yld.traffic(r_bend, st, cases["to pass"])[0] == 0.0
    later = load_policy("racer_yield:1.27:8:9:60:0:20")  # 50 m is beyond 25 + 20 m: not in the zone yet
    assert later.race.abandon_m == 20.0 and load_policy("racer_safe:1.27:8:9:60:0:20").race.abandon_m == 20.0
    assert later.traffic(r_bend, st, cases["level"]) == safe.traffic(r_bend, st, cases["level"])
    with pytest.raises(ValueError, match="abandon_m"):
        type(yld)(abandon_m=-1.0)


def test_clean_racer_widens_its_following_corridor_near_bends_and_hold_lane_keeps_its_lane():
    import numpy as np

    from torcsrl.training.demos import known_teacher, make_teacher
    from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG, STATE_SLOTS
    from torcsrl.policies import SensorRacer

    clean, bold = load_policy("racer_clean"), load_policy("racer_bold")
    assert clean.race.bend_lanes == 1.5 and clean.k.grip_exponent == 2.0 and load_policy("racer_clean:1.5").k.grip_exponent == 1.5
    assert known_teacher("racer_clean:1.5") and make_teacher("racer_clean").race.bend_lanes == 1.5
    with pytest.raises(PolicyError, match="racer_clean:"):
        load_policy("racer_clean:fast")
    r, st = straight_road(speed_kmh=72.0)
    # braking for a bend with a car 12 m away, 3.1 m right of its path (sector 19: -15 deg; outside one lane of 2.4 m,
    # inside 1.5 lanes): the bold racer keeps its pedal, the clean one brakes
    opp = sectors(s19=12.0)
    y = 12.0 * np.sin(np.radians(-15.0))
    assert 2.4 < abs(y) < 1.5 * 2.4
    assert bold.traffic(r, st, opp, braking=True)[1] == 1.0 and clean.traffic(r, st, opp, braking=True)[1] < 0.0
    # hold_lane: not passing (a bend ahead: the farthest free point 30 deg off the heading), a car within 30 m:
    # it aims where it is rather than at the axis
    ang = np.asarray(RANGEFINDER_ANGLES_DEG)
    r = r.copy()
    r[np.argsort(np.abs(ang))[:3]] = 40.0
    r[int(np.argmin(np.abs(ang - 30.0)))] = 100.0
    st[STATE_SLOTS.index("trackPos")] = 0.3
    hold = SensorRacer(**{**SensorRacer.BOLD, "hold_lane": True})
    assert bold.traffic(r, st, sectors(s17=20.0))[0] == 0.0 and hold.traffic(r, st, sectors(s17=20.0))[0] == pytest.approx(0.3)
    assert hold.traffic(r, st, sectors(s18=50.0))[0] == 0.0  # a car 50 m ahead: no need


def test_racer_overtakes_a_slow_car_that_the_blind_teacher_runs_into(tmp_path):
    """A real 2-car race on the oval from the back of the grid against a car at 50 km/h on the centre line: the racer
    passes it without contact; sensor_fast (the same driving, no opponents sensor) hits it. The slow car is blind to a
    car alongside (side_gap_m 0): the racer alone keeps them apart."""
    from torcsrl.evaluate.race import evaluate_race

    tr = {"opponents": 1, "driver": {"kind": "slow", "speed_kmh": 50.0, "line": "centre"}, "order": "fixed", "learner_slot": "last",
          "side_gap_m": 0}
    kw = {"control_hz": 10, "substeps": 20}
    racer = evaluate_race("racer", "oval", laps=1, traffic=tr, env_kwargs=kw, plots=False, verbose=False, out_dir=tmp_path / "r")
    blind = evaluate_race("sensor_fast", "oval", laps=1, traffic=tr, env_kwargs=kw, plots=False, verbose=False, out_dir=tmp_path / "b")
    a, b = racer["episodes"][0], blind["episodes"][0]
    assert a["win"] and a["collisions"] == 0 and a["overtakes"] >= 1, a
    assert b["collisions"] > 0, b


def test_fast_teacher_laps_faster_and_the_sensor_drivers_fingerprints_differ():
    from torcsrl.evaluate import run_cell

    kw = {"control_hz": 10, "substeps": 20}
    fast, _ = run_cell(load_policy("sensor_fast"), "oval", "asphalt", laps=2, env_kwargs=kw)
    grip, _ = run_cell(load_policy("sensor_grip"), "oval", "asphalt", laps=2, env_kwargs=kw)
    assert fast[0]["success"] and grip[0]["success"] and fast[0]["off_track_events"] == 0
    assert fast[0]["fastest_lap"] < 0.97 * grip[0]["fastest_lap"], (fast[0]["fastest_lap"], grip[0]["fastest_lap"])
    prints = {load_policy(s).fingerprint for s in ("sensor", "sensor_grip", "sensor_fast", "racer", "expert", "expert_centre")}
    assert len(prints) == 6  # report caches are keyed by them
