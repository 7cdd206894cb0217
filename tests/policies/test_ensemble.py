"""torcsrl.policies.ensemble: ensembles of checkpoints (EnsemblePolicy), on the shipped rangefinder drivers (the DAgger
reference and the TD3 reference read the same observations) and the shipped racer's students."""

from __future__ import annotations

import re

import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.policies import (
    REFERENCE_CAMERA_POLICY,
    REFERENCE_RACER_POLICY,
    CheckpointPolicy,
    EnsemblePolicy,
    PolicyError,
    export_member,
    load_policy,
)

from ._scenes import A, B, act


def test_ensemble_combines_its_members_actions(states):
    a, b = CheckpointPolicy(A), CheckpointPolicy(B)
    acts = torch.stack([act(a, states), act(b, states)])
    assert (acts[0] - acts[1]).abs().max() > 0.05  # two different drivers
    mean = load_policy(f"{A}+{B}")
    torch.testing.assert_close(act(mean, states), acts.mean(0))
    torch.testing.assert_close(act(load_policy(f"{A}+{B}@median"), states), acts.mean(0))  # two members: the mid-point
    cautious = act(load_policy(f"{A}+{B}@cautious"), states)
    torch.testing.assert_close(cautious[:, 0], acts[:, :, 0].mean(0))  # steering: the mean
    torch.testing.assert_close(cautious[:, 1], acts[:, :, 1].min(0).values)  # pedal: the least throttle / most brake
    assert (cautious[:, 1] < acts[:, :, 1].mean(0)).any()
    three = load_policy(f"{A}+{B}+{A}@median")
    torch.testing.assert_close(act(three, states), acts[0])  # odd count: the middle member (A, twice)
    medoid = act(load_policy(f"{A}+{B}@medoid"), states)
    assert ((medoid == acts[0]).all(-1) | (medoid == acts[1]).all(-1)).all()  # every row one member's own action
    torch.testing.assert_close(act(load_policy(f"{A}+{B}+{B}@medoid"), states), acts[1])  # B, twice: the median's side


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
