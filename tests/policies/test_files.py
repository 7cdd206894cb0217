"""torcsrl.policies.files and the command line: ensemble files (export_ensemble, export_member), guarded ensemble
files (``python -m torcsrl.policies ensemble ... --side-guard``)."""

from __future__ import annotations

import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.policies import (
    REFERENCE_RACER_POLICY,
    CheckpointPolicy,
    EnsemblePolicy,
    PolicyError,
    SideGuard,
    export_ensemble,
    export_member,
    load_policy,
)

from ._scenes import A, B, act


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
    torch.testing.assert_close(act(pol, states), act(load_policy(f"{A}+{B}@cautious"), states))
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
