"""torcsrl.policies: ensembles of checkpoints (EnsemblePolicy, export_ensemble), on the shipped rangefinder drivers
(the DAgger reference and the TD3 reference read the same observations)."""

from __future__ import annotations

import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.policies import (
    REFERENCE_CAMERA_POLICY,
    REFERENCE_POLICY,
    REFERENCE_RL_POLICY,
    CheckpointPolicy,
    EnsemblePolicy,
    PolicyError,
    export_ensemble,
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
    cases = {
        f"{A}+{B}@loudest": "reduce='loudest' is not known; allowed: mean, median, cautious",
        f"{A}+{REFERENCE_CAMERA_POLICY}": "must read the same observations",
        f"{A}+{tmp_path / 'nothing.pt'}": "neither a checkpoint file that exists",
    }
    for spec, msg in cases.items():
        with pytest.raises(PolicyError, match=msg.replace("(", r"\(").replace(")", r"\)")) as err:
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
