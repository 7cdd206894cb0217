"""torcsrl.policies: ensembles of checkpoints (EnsemblePolicy, export_ensemble), on the shipped rangefinder drivers
(the DAgger reference and the TD3 reference read the same observations)."""

from __future__ import annotations

import re

import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.policies import (
    REFERENCE_CAMERA_POLICY,
    REFERENCE_RACER_POLICY,
    REFERENCE_POLICY,
    REFERENCE_RL_POLICY,
    CheckpointPolicy,
    EnsemblePolicy,
    PolicyError,
    SideGuard,
    export_ensemble,
    export_member,
    load_policy,
)

torch.set_num_threads(1)
A, B = str(REFERENCE_POLICY), str(REFERENCE_RL_POLICY)


@pytest.fixture(scope="module")
def states():
    """Observations of a car driven by the reference driver on the oval (the members disagree on some of them)."""
    pol = load_policy("reference")
    env = make_env(track="oval", sensors=pol.env_overrides["sensors"], control_hz=10, substeps=20)
    try:
        td = env.reset()
        out = []
        for _ in range(60):
            out.append(td.select(*pol.obs_keys).clone())
            td = env.step(pol(td))["next"]
        return torch.stack(out)
    finally:
        env.close()


def _act(pol, td):
    return pol(td.clone())["action"]


def test_ensemble_combines_its_members_actions(states):
    a, b = CheckpointPolicy(A), CheckpointPolicy(B)
    acts = torch.stack([_act(a, states), _act(b, states)])
    assert (acts[0] - acts[1]).abs().max() > 0.05  # two different drivers
    mean = load_policy(f"{A}+{B}")
    torch.testing.assert_close(_act(mean, states), acts.mean(0))
    torch.testing.assert_close(_act(load_policy(f"{A}+{B}@median"), states), acts.mean(0))  # two members: the mid-point
    cautious = _act(load_policy(f"{A}+{B}@cautious"), states)
    torch.testing.assert_close(cautious[:, 0], acts[:, :, 0].mean(0))  # steering: the mean
    torch.testing.assert_close(cautious[:, 1], acts[:, :, 1].min(0).values)  # pedal: the least throttle / most brake
    assert (cautious[:, 1] < acts[:, :, 1].mean(0)).any()
    three = load_policy(f"{A}+{B}+{A}@median")
    torch.testing.assert_close(_act(three, states), acts[0])  # odd count: the middle member (A, twice)
    medoid = _act(load_policy(f"{A}+{B}@medoid"), states)
    assert ((medoid == acts[0]).all(-1) | (medoid == acts[1]).all(-1)).all()  # every row one member's own action
    torch.testing.assert_close(_act(load_policy(f"{A}+{B}+{B}@medoid"), states), acts[1])  # B, twice: the median's side


def test_the_medoid_reduce_takes_one_members_command_where_the_mean_is_neither():
    # three racers at a car ahead: two pass it on the left (+ steer), one on the right; the mean steers at it
    acts = torch.tensor([[[0.50, 1.0]], [[-0.50, 1.0]], [[0.40, 0.2]]])  # [members, rows, (steer, pedal)]
    torch.testing.assert_close(EnsemblePolicy.combine(acts, "medoid"), torch.tensor([[0.50, 1.0]]))  # L1 to (0.4, 1.0): 0.1
    assert abs(float(EnsemblePolicy.combine(acts, "mean")[0, 0]) - 0.1333) < 1e-3
    rows = torch.randn(5, 7, 2)  # any shape of rows: each picked row is a member's row, nearest the median
    out = EnsemblePolicy.combine(rows, "medoid")
    dist = (rows - rows.quantile(0.5, dim=0)).abs().sum(-1)
    best = rows[dist.argmin(0), torch.arange(7)]
    torch.testing.assert_close(out, best)
    with pytest.raises(PolicyError, match="allowed: mean, median, cautious, medoid"):
        EnsemblePolicy.combine(rows, "loudest")


def test_the_guarded_reduce_takes_the_most_cautious_pedal_only_where_a_car_is_close_ahead():
    acts = torch.tensor([[[0.10, 0.9], [0.5, 0.2]], [[0.20, 0.5], [0.4, -0.3]], [[0.30, 0.1], [0.45, 0.0]]])  # [3 members, 2 rows, A]
    medoid = EnsemblePolicy.combine(acts, "medoid")
    out = EnsemblePolicy.combine(acts, "guarded:30", torch.tensor([True, False]))
    torch.testing.assert_close(out[1], medoid[1])  # no car close ahead: the medoid
    torch.testing.assert_close(out[0], torch.tensor([0.20, 0.1]))  # the medoid's steering, the least throttle
    sep = torch.tensor([[[0.1, 0.8, 0.0]], [[0.0, 0.2, 0.6]], [[-0.1, 0.5, 0.1]]])  # action_mode=separate: steer, throttle, brake
    torch.testing.assert_close(EnsemblePolicy.combine(sep, "guarded:30", torch.tensor([True])), torch.tensor([[-0.1, 0.2, 0.6]]))  # medoid: member 3
    with pytest.raises(PolicyError, match="needs the rows with a car close ahead"):
        EnsemblePolicy.combine(acts, "guarded:30")


def test_a_guarded_racer_is_the_medoid_alone_and_brakes_with_its_most_cautious_student_behind_a_car(tmp_path):
    """The shipped racer's four students: with every sector free (alone) or a car only behind or far ahead the guarded
    ensemble drives exactly as the medoid; with a car 16 m ahead its pedal is the least of the students'."""
    members = [str(export_member(REFERENCE_RACER_POLICY, i, tmp_path / f"m{i}.pt")) for i in range(4)]
    spec = "+".join(members)
    guarded = load_policy(f"{spec}@guarded:30")
    assert guarded.reduce == "guarded:30" and guarded.guard_m == 30.0 and load_policy(f"{spec}@guarded").guard_m == EnsemblePolicy.GUARD_M
    racer = load_policy("reference_racer")
    env = make_env(track="oval", sensors=racer.env_overrides["sensors"], control_hz=10, substeps=20)
    try:  # the observation of the racer 4 s into a lap of the oval alone (~40 m/s)
        td = env.reset()
        for _ in range(40):
            td = env.step(racer(td))["next"]
        base = td.select(*racer.obs_keys).clone()
    finally:
        env.close()

    def scene(**cars):  # sector index -> distance [m]; every other sector free (200 m)
        td = base.clone()
        td["opponents"] = torch.full((36,), 200.0)
        for k, d in cars.items():
            td["opponents"][int(k[1:])] = d
        return td

    def first_action(pol_spec, td):  # a fresh ensemble: the students keep a history, so each scene starts one
        return load_policy(pol_spec)(td.clone())["action"]

    for cars in ({}, {"s0": 5.0}, {"s35": 8.0}, {"s17": 45.0}):  # alone; a car right behind (both sides); one 45 m ahead
        assert torch.equal(first_action(f"{spec}@guarded:30", scene(**cars)), first_action(f"{spec}@medoid", scene(**cars))), cars
    close = scene(s17=16.0)  # a car 16 m ahead (just left of the heading): two students brake, two do not
    acts = torch.stack([load_policy(m)(close.clone())["action"] for m in members])
    out, medoid = first_action(f"{spec}@guarded:30", close), first_action(f"{spec}@medoid", close)
    assert out[1] == acts[:, 1].min() and out[0] == medoid[0]
    assert acts[:, 1].min() < medoid[1]  # the students disagree about the pedal here: the guard changes the command
    assert torch.equal(first_action(f"{spec}@guarded:5", close), medoid)  # a 5-m guard: that car is not close


def _guard_scene(steer, tp=0.0, **cars):
    """One row: an action (steer, pedal 0.5), the opponents sectors (``s<k>=distance``, the rest free) and trackPos."""
    opp = torch.full((1, 36), 200.0)
    for k, d in cars.items():
        opp[0, int(k[1:])] = d
    return torch.tensor([[steer, 0.5]]), opp, torch.tensor([tp])


def test_side_guard_steers_away_from_a_car_beside_and_leaves_every_other_command_alone():
    """Hand-placed cars around a racer (racer_safe reads opponents and state): sector 9 is 85 degrees left of the
    heading, sector 26 85 degrees right; a car 2.0 m to the side is 0.6 m inside the default 2.6 m of room."""
    import math

    guard = load_policy("side_guard:racer_safe:1.27:8:9")
    assert isinstance(guard, SideGuard) and guard.settings == SideGuard.DEFAULTS and guard.inner.spec == "racer_safe:1.27:8:9"
    r2 = 2.0 / math.sin(math.radians(85.0))  # 2.0 m to the side, 0.17 m ahead: beside
    push = 0.04 * 0.6  # gain_per_m x the shortfall
    for steer in (0.3, -0.2, 0.0):
        a, opp, tp = _guard_scene(steer)
        assert torch.equal(guard.correct(a, opp, tp), a)  # alone: the policy's own action
        for far in ({"s9": 8.0 / math.sin(math.radians(85.0))}, {"s17": 6.0}, {"s0": 9.0}):  # 8 m to the side; 6 m ahead; 9 m behind
            a, opp, tp = _guard_scene(steer, **far)
            assert torch.equal(guard.correct(a, opp, tp), a), far
    a, opp, tp = _guard_scene(0.3, s9=r2)  # steering left, toward the car on the left: halved, then pushed right
    out = guard.correct(a, opp, tp)
    assert out[0, 0].item() == pytest.approx(0.15 - push, abs=1e-5) and out[0, 1] == a[0, 1]  # the pedal is the policy's
    a, opp, tp = _guard_scene(-0.2, s9=r2)  # already steering away: pushed further
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(-0.2 - push, abs=1e-5)
    a, opp, tp = _guard_scene(-0.3, s26=r2)  # mirrored: a car on the right, steering toward it
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(-0.15 + push, abs=1e-5)
    a, opp, tp = _guard_scene(0.3, tp=-0.8, s9=r2)  # already 0.8 out to the right: no push off the road, still halved
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(0.15, abs=1e-6)
    behind = 2.0 / math.sin(math.radians(135.0))  # sector 4 (135 deg left): 2.0 m left, 2.0 m behind (the car it passed)
    a, opp, tp = _guard_scene(0.3, s4=behind, s26=4.0)  # the nearer car to the side decides: the one on the left
    assert guard.correct(a, opp, tp)[0, 0].item() == pytest.approx(0.15 - push, abs=1e-5)
    rows = torch.cat([_guard_scene(0.3)[0], _guard_scene(0.3, s9=r2)[0]]), torch.cat([_guard_scene(0.3)[1], _guard_scene(0.3, s9=r2)[1]])
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


def test_a_guarded_ensemble_file_drives_as_its_guard_spec(tmp_path, capsys):
    """The shipped racer's students exported with a side guard: one file that loads as the guard around the medoid,
    its settings kept, and drives as the ``side_guard:...`` spec of the same students; bad settings fail in one line."""
    from torcsrl.policies import main

    members = [str(export_member(REFERENCE_RACER_POLICY, i, tmp_path / f"m{i}.pt")) for i in range(2)]
    out = tmp_path / "guarded.pt"
    assert main(["ensemble", str(out), *members, "--reduce", "medoid", "--side-guard", "3:0.05"]) == 0
    pol = load_policy(out)
    assert isinstance(pol, SideGuard) and pol.inner.reduce == "medoid" and len(pol.inner.members) == 2
    assert pol.settings == {**SideGuard.DEFAULTS, "clear_m": 3.0, "gain_per_m": 0.05}
    spec = load_policy(f"side_guard:3:0.05:{'+'.join(members)}@medoid")
    td = {"rangefinder": torch.full((1, 19), 30.0), "state": torch.zeros(1, 11), "opponents": torch.full((1, 36), 200.0)}
    td["state"][0, 2] = 120.0  # 120 km/h
    td["opponents"][0, 9] = 2.0  # a car beside, on the left
    from tensordict import TensorDict

    a, b = pol(TensorDict(td, batch_size=[1]))["action"], spec(TensorDict(td, batch_size=[1]))["action"]
    assert torch.equal(a, b)
    bare = load_policy(f"{'+'.join(members)}@medoid")(TensorDict(td, batch_size=[1]))["action"]
    assert a[0, 0] < bare[0, 0] and a[0, 1] == bare[0, 1]  # steered right, away from it; the pedal unchanged
    assert main(["ensemble", str(tmp_path / "x.pt"), *members, "--side-guard", "wide"]) == 2 and not (tmp_path / "x.pt").exists()
    assert "not <clear m>[:<gain per m>[:<edge tp>]]" in capsys.readouterr().err
    with pytest.raises(PolicyError, match="out of range"):
        export_ensemble(members, tmp_path / "y.pt", reduce="medoid", guard={"clear_m": -2.0})
    for guard in ({"wide_m": 3.0}, {"clear_m": "wide"}):  # an unknown setting; not a number
        with pytest.raises(PolicyError, match="are not known numbers; allowed: clear_m, gain_per_m, reach_m, toward, edge_tp"):
            export_ensemble(members, tmp_path / "y.pt", reduce="medoid", guard=guard)
    assert not (tmp_path / "y.pt").exists()
    with pytest.raises(PolicyError, match="reads opponents"):
        export_ensemble([A, B], tmp_path / "z.pt", guard={"clear_m": 2.6})


def test_an_ensemble_file_drives_as_its_spec(tmp_path, states):
    out = export_ensemble([A, B], tmp_path / "ens.pt", reduce="cautious")
    pol = load_policy(out)
    assert isinstance(pol, EnsemblePolicy) and pol.reduce == "cautious" and len(pol.members) == 2
    torch.testing.assert_close(_act(pol, states), _act(load_policy(f"{A}+{B}@cautious"), states))
    assert pol.fingerprint != load_policy(f"{A}+{B}@cautious").fingerprint  # the file's bytes
    assert pol.describe()["reduce"] == "cautious" and len(pol.describe()["members"]) == 2
    with pytest.raises(PolicyError, match="is an ensemble of 2 students") as err:  # one actor expected
        CheckpointPolicy(out)
    assert "\n" not in str(err.value)
    from torcsrl.policies import export_member

    one = CheckpointPolicy(export_member(out, 1, tmp_path / "b.pt"))  # a member alone: B's actor, to the bit
    assert all(torch.equal(v, CheckpointPolicy(B).actor.state_dict()[k]) for k, v in one.actor.state_dict().items())
    for bad, msg in ((2, "has members 0..1; got 2"), (-1, "has members 0..1; got -1")):
        with pytest.raises(PolicyError, match=msg):
            export_member(out, bad, tmp_path / "x.pt")
    with pytest.raises(PolicyError, match="is not an ensemble file"):
        export_member(A, 0, tmp_path / "x.pt")
    with pytest.raises(PolicyError, match="itself an ensemble"):
        load_policy(f"{out}+{A}")
    env = make_env(track="oval", sensors=pol.env_overrides["sensors"], control_hz=10, substeps=20)
    try:
        pol.check_env(env)
        td = env.reset()
        for _ in range(30):
            td = env.step(pol(td))["next"]
        assert float(td["state"][0]) > 0.0  # it drives off the grid
    finally:
        env.close()


def test_ensemble_bad_input_fails_in_one_line(tmp_path):
    racer = export_member(REFERENCE_RACER_POLICY, 0, tmp_path / "racer0.pt")  # one student of the shipped racer
    cases = {
        f"{A}+{B}@loudest": "reduce='loudest' is not known; allowed: mean, median, cautious, medoid, guarded[:<m>]",
        f"{A}+{B}@guarded": "reads the opponents sensor, which its members do not",  # the DAgger and TD3 references
        f"{racer}+{racer}@guarded:-5": "the guard distance must be positive [m], got -5",
        f"{racer}+{racer}@guarded:near": "the guard distance must be a number of metres",
        f"{racer}+{racer}@medoid:30": "reduce='medoid:30' is not known",
        f"{A}+{racer}": "must read the same observations",  # rangefinder + state against + opponents
        f"{A}+{REFERENCE_RACER_POLICY}": "is itself a guarded ensemble",  # the shipped racer: 4 students behind a side guard
        f"{A}+{REFERENCE_CAMERA_POLICY}": "is itself an ensemble",  # the shipped camera driver is a 4-seed ensemble
        f"{A}+{tmp_path / 'nothing.pt'}": "neither a checkpoint file that exists",
    }
    for spec, msg in cases.items():
        with pytest.raises(PolicyError, match=re.escape(msg)) as err:
            load_policy(spec)
        assert "\n" not in str(err.value), spec
    with pytest.raises(PolicyError, match="at least 2 checkpoints"):
        EnsemblePolicy([CheckpointPolicy(A)])


def test_evaluate_drives_an_ensemble_spec(tmp_path, monkeypatch):
    """python -m torcsrl.evaluate --policy 'a.pt+b.pt@cautious': a time trial with its table, under outputs/evaluate/ensemble2."""
    import json

    from torcsrl.evaluate.app import main

    monkeypatch.chdir(tmp_path)
    assert main(["--policy", f"{A}+{B}@cautious", "--track", "oval", "--laps", "1", "--no-plots", "--expert-laps", "0"]) == 0
    (run,) = (tmp_path / "outputs" / "evaluate" / "ensemble2").iterdir()
    res = json.loads(next(run.glob("*.json")).read_text())
    assert "ensemble2" in json.dumps(res) and "cautious" in json.dumps(res)


# ------------------------------------------------------------------------------ the fast sensor teacher and the racer
def _straight_road(half_width_m: float = 6.0, speed_kmh: float = 72.0):
    """Beams [m] and a raw state of a car on the axis of a straight road, heading along it."""
    import math

    import numpy as np

    from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG, STATE_SLOTS

    r = np.array([min(200.0, half_width_m / max(abs(math.sin(math.radians(a))), 1e-9)) for a in RANGEFINDER_ANGLES_DEG])
    st = np.zeros(len(STATE_SLOTS))
    st[STATE_SLOTS.index("speedX_kmh")] = speed_kmh
    return r, st


def _sectors(**cars):
    """36 free sectors (200 m) with a car at ``s<k>=distance``."""
    import numpy as np

    opp = np.full(36, 200.0)
    for k, dist in cars.items():
        opp[int(k[1:])] = dist
    return opp


def test_racer_passes_lifts_and_brakes_from_its_opponents_sectors():
    import math

    racer = load_policy("racer")
    r, st = _straight_road(speed_kmh=36.0)  # 10 m/s: lift within 10 + 0.8 x 10 = 18 m, brake within 6 + 0.5 x 10 = 11 m
    assert racer.traffic(r, st, _sectors()) == (0.0, 1.0)  # an empty road: sensor_fast
    t_right, cap = racer.traffic(r, st, _sectors(s18=25.0))  # 25 m ahead, 2.2 m right of the axis (sector 18: -5 deg)
    t_left, _ = racer.traffic(r, st, _sectors(s17=25.0))  # ... 2.2 m left of it
    assert t_right > 0.0 > t_left and cap == 1.0  # moves out on the other side, no lift yet
    assert abs(t_right * 6.0 + 25.0 * math.sin(math.radians(5.0)) - racer.race.pass_gap_m) < 1e-6  # pass_gap beside it
    assert racer.traffic(r, st, _sectors(s18=15.0))[1] == 0.0  # in its path within the lift distance
    assert racer.traffic(r, st, _sectors(s18=8.0))[1] < 0.0  # within the brake distance
    t, cap = racer.traffic(r, st, _sectors(s9=4.0))  # alongside on the left: keep a pass gap right of it, no braking
    y_left = 4.0 * math.sin(math.radians(85.0))  # sector 9's centre: 85 degrees left
    assert y_left - t * 6.0 >= racer.race.pass_gap_m - 1e-6 and cap == 1.0
    assert racer.traffic(r, st, _sectors(s0=30.0)) == (0.0, 1.0)  # a car behind does not matter


def test_safe_racer_brakes_as_the_bold_one_on_asphalt_and_earlier_on_low_grip():
    import math

    import numpy as np

    from torcsrl.demos import DemoError, known_teacher, make_teacher
    from torcsrl.policies import SensorRacer

    bold, safe, safe15 = load_policy("racer_bold"), load_policy("racer_safe"), load_policy("racer_safe:1.5")
    assert safe.k.grip_exponent == SensorRacer.SAFE_GRIP_EXPONENT == 2.0 and safe15.k.grip_exponent == 1.5
    r = np.full(19, 80.0)  # walls 80 m ahead all round: a tight bend, the car at 40 km/h
    _, st = _straight_road(speed_kmh=40.0)
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

    from torcsrl.demos import DemoError, known_teacher, make_teacher

    r, st = _straight_road(speed_kmh=205.0)  # 57 m/s with 200 m free: 9 m/s^2 still accelerates, 8 must brake
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

    alone, far, beside = _sectors(), _sectors(s17=100.0), _sectors(s8=40.0)  # nothing; 100 m ahead; 40 m off to the left
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
    r, st = _straight_road(speed_kmh=72.0)
    d, phi = 5.59, math.radians(175.0 - 10.0 * 33)  # sector 33: a car ~5 m behind, 2.4 m right (just passed on its left)
    x, y = d * math.cos(phi), d * math.sin(phi)
    aim = y / 6.0 + clear.race.pass_gap_m / 6.0  # pass_gap beside it (half-width 6 m)
    t_now, _ = now.traffic(r, st, _sectors(s33=d))
    t_clear, _ = clear.traffic(r, st, _sectors(s33=d))
    assert t_clear == pytest.approx(aim) and t_now == pytest.approx(aim * (x + now.race.rear_m) / now.race.rear_m) and t_now < t_clear
    far = 20.0 / abs(math.cos(math.radians(175.0 - 350.0)))  # sector 35: 20 m behind, 1.7 m right: beyond rear_m
    assert now.traffic(r, st, _sectors(s35=far))[0] == 0.0 and clear.traffic(r, st, _sectors(s35=far))[0] > 0.0  # still fading


def test_keep_racer_finishes_a_pass_on_its_side_and_holds_its_lane_when_that_side_is_taken():
    """``racer_keep``: beside the car it passes, with a third car on its passing line, ``racer_safe`` takes the other
    side's line (across the passed car) while ``racer_keep`` holds its trackPos; with that side free both pass alike."""
    import math

    from torcsrl.demos import known_teacher, make_teacher
    from torcsrl.envs.sensors import STATE_SLOTS

    safe, keep = load_policy("racer_safe:1.27:8:9"), load_policy("racer_keep:1.27:8:9")
    assert keep.race.keep_side and not safe.race.keep_side and keep.fingerprint != safe.fingerprint
    assert keep.k.grip_exponent == 1.27 and keep.race.bend_lanes == safe.race.bend_lanes == 1.0
    assert known_teacher("racer_keep:1.27:8:9") and make_teacher("racer_keep:1.27:8:9").race.keep_side
    with pytest.raises(PolicyError, match="racer_keep:"):
        load_policy("racer_keep:fast")
    r, st = _straight_road(half_width_m=10.0, speed_kmh=72.0)
    tp = 0.25
    st[STATE_SLOTS.index("trackPos")] = tp
    w, gap = 10.0, safe.race.pass_gap_m / 10.0
    d = 2.0  # sector 26 (-85 deg): the car passed, 2 m to the right, level with it (committed: |dy| > 1.5 m)
    tp_o = tp + d * math.sin(math.radians(175.0 - 10.0 * 26)) / w
    left, right = tp_o + gap, tp_o - gap
    beside = _sectors(s26=d)
    assert safe.traffic(r, st, beside)[0] == pytest.approx(left) and keep.traffic(r, st, beside)[0] == pytest.approx(left)
    third = _sectors(s26=d, s17=12.0 / math.cos(math.radians(5.0)))  # and a car 12 m ahead, ~1 m left: on that line
    assert safe.traffic(r, st, third)[0] == pytest.approx(right) and right < tp_o  # across the passed car's path
    target, cap = keep.traffic(r, st, third)
    assert target == pytest.approx(tp) and cap < 0.0  # holds its lane and brakes for the car ahead
    alone = _sectors()
    assert keep.traffic(r, st, alone) == safe.traffic(r, st, alone) == (0.0, 1.0)


def test_yield_racer_completes_a_pass_before_the_braking_zone_or_gives_it_up():
    """``racer_yield``: within ``abandon_m`` of its braking point it starts no pass, and beside a car it has not
    cleared by a car length it holds its lane (braking while that car's centre is ahead of its own), where
    ``racer_safe`` finishes the pass into the bend; far from the bend, or a car length clear, both drive alike."""
    import math

    from torcsrl.demos import known_teacher, make_teacher
    from torcsrl.envs.sensors import STATE_SLOTS

    safe, yld = load_policy("racer_safe:1.27:8:9"), load_policy("racer_yield:1.27:8:9")
    assert yld.race.abandon_m == 30.0 and safe.race.abandon_m is None and yld.fingerprint != safe.fingerprint
    assert yld.k.grip_exponent == 1.27 and yld.race.bend_lanes == safe.race.bend_lanes == 1.0
    assert known_teacher("racer_yield:1.27:8:9") and make_teacher("racer_yield:1.27:8:9").race.abandon_m == 30.0
    with pytest.raises(PolicyError, match="racer_yield:"):
        load_policy("racer_yield:fast")
    r_far, st = _straight_road(half_width_m=10.0, speed_kmh=72.0)  # 20 m/s: braking at 8 m/s^2 takes 25 m
    st[STATE_SLOTS.index("trackPos")] = 0.25
    r_bend = r_far.copy()
    r_bend[yld.centre] = 50.0  # the road ends 50 m ahead: within 25 + 30 m of the bend, not within 25 + 20
    cases = {"level": _sectors(s26=2.0),  # -85 deg, 2 m: beside it, its centre 0.17 m ahead
             "half ahead": _sectors(s28=3.0),  # -105 deg, 3 m: its centre 0.8 m behind, not yet a car length
             "clear": _sectors(s33=6.0),  # -155 deg, 6 m: 5.4 m behind (a car length clear), 2.5 m right
             "to pass": _sectors(s18=15.0)}  # -5 deg, 15 m ahead, 1.3 m right: a pass not yet started
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

    from torcsrl.demos import known_teacher, make_teacher
    from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG, STATE_SLOTS
    from torcsrl.policies import SensorRacer

    clean, bold = load_policy("racer_clean"), load_policy("racer_bold")
    assert clean.race.bend_lanes == 1.5 and clean.k.grip_exponent == 2.0 and load_policy("racer_clean:1.5").k.grip_exponent == 1.5
    assert known_teacher("racer_clean:1.5") and make_teacher("racer_clean").race.bend_lanes == 1.5
    with pytest.raises(PolicyError, match="racer_clean:"):
        load_policy("racer_clean:fast")
    r, st = _straight_road(speed_kmh=72.0)
    # braking for a bend with a car 12 m away, 3.1 m right of its path (sector 19: -15 deg; outside one lane of 2.4 m,
    # inside 1.5 lanes): the bold racer keeps its pedal, the clean one brakes
    opp = _sectors(s19=12.0)
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
    assert bold.traffic(r, st, _sectors(s17=20.0))[0] == 0.0 and hold.traffic(r, st, _sectors(s17=20.0))[0] == pytest.approx(0.3)
    assert hold.traffic(r, st, _sectors(s18=50.0))[0] == 0.0  # a car 50 m ahead: no need


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


def test_centre_line_expert_drives_and_an_unknown_line_fails_in_one_line():
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import ExpertPolicy

    rows, _ = run_cell(load_policy("expert_centre"), "hairpins", "asphalt", laps=1, env_kwargs={"control_hz": 10, "substeps": 20})
    assert rows[0]["success"]
    with pytest.raises(PolicyError, match=r"line='inside'; allowed: racing, centre"):
        ExpertPolicy(line="inside")


def test_the_shipped_racer_reads_the_race_sensors_and_laps_alone():
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import REFERENCE_RACER_POLICY

    racer = load_policy("reference_racer")
    assert REFERENCE_RACER_POLICY.is_file() and racer.obs_keys == ("rangefinder", "state", "opponents")
    assert racer.env_overrides["control_hz"] == 10
    assert isinstance(racer, SideGuard) and racer.settings == SideGuard.DEFAULTS  # the tenth version: a guarded medoid
    assert isinstance(racer.inner, EnsemblePolicy) and racer.inner.reduce == "medoid" and len(racer.inner.members) == 4
    rows, _ = run_cell(racer, "oval", "asphalt", laps=1)  # no opponents: its sectors read free (200 m)
    assert rows[0]["success"] and rows[0]["off_track_events"] == 0
    pol = racer.inner.members[0]  # one student: its rows batched as one car each
