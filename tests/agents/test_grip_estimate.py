"""``algo.grip_estimate``: an imitation actor with a grip head (RMA's adaptation module) that estimates the road's
friction mu from its features, trained on the rows' privileged mu, and read by the actor detached."""

from __future__ import annotations

import re
from types import SimpleNamespace

import pytest
import torch

from _compose import compose_config
from _history import assert_policy_history_matches_training_env

RACE = ["debug=smoke", "env.track=oval", "env.max_steps=200", "eval.max_steps=30", "threads=1"]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _actor(grip_hidden=(16,)):
    from torchrl.data import Composite, Unbounded

    from torcsrl.nets import DeterministicActor, ObsEncoder

    torch.manual_seed(0)
    enc = ObsEncoder(Composite({"state": Unbounded((6,))}, shape=()), ["state"])
    return DeterministicActor(enc, -torch.ones(2), torch.ones(2), (32, 32), grip_hidden=grip_hidden)


def _batch(n=256, seed=0):
    """Rows where mu is a function of the observation (slot 0) and the label does not depend on mu."""
    from tensordict import TensorDict

    from torcsrl.envs.sensors import PRIVILEGED_SLOTS

    g = torch.Generator().manual_seed(seed)
    state = torch.rand(n, 6, generator=g) * 2 - 1
    priv = torch.zeros(n, len(PRIVILEGED_SLOTS))
    priv[:, PRIVILEGED_SLOTS.index("surfaceMu")] = 0.75 + 0.25 * state[:, 0]
    label = torch.stack([0.5 * state[:, 1], -0.3 * state[:, 2]], -1)
    return TensorDict({"state": state, "privileged": priv, "expert_action": label}, batch_size=[n])


def test_only_the_grip_loss_trains_the_grip_head():
    from torcsrl.agents._build import bc_step

    actor = _actor()
    net = SimpleNamespace(actor_network=actor, obs=lambda b: [b.get("state")])
    head_before = [p.detach().clone() for p in actor.grip_head.parameters()]
    optim = {"actor": torch.optim.Adam(actor.parameters(), lr=3e-3)}
    bc_step(net, optim, _batch(), reg=SimpleNamespace(grip_estimate=0.0))  # the actor's regression alone
    assert all(torch.equal(a, p) for a, p in zip(head_before, actor.grip_head.parameters()))  # detached: no gradient reached it
    batch, first = _batch(), None
    for _ in range(1000):
        _, extra = bc_step(net, optim, batch, reg=SimpleNamespace(grip_estimate=1.0))
        first = float(extra["loss/grip"]) if first is None else first
    assert float(extra["loss/grip"]) < 0.01 * first, (first, float(extra["loss/grip"]))
    with torch.no_grad():  # the head now reads mu from the features; the actor reads that estimate
        feats = actor.encoder(batch.get("state"))
        assert (actor.grip(feats)[:, 0] - batch.get("privileged")[:, -1]).abs().mean() < 0.03
        torch.testing.assert_close(actor(batch.get("state")), actor.act(feats, actor.grip(feats)))
        assert not torch.equal(actor.act(feats, torch.zeros(len(feats), 1)), actor.act(feats))  # the estimate is an input


def test_a_long_history_feeds_the_estimate_and_the_newest_readings_the_policy():
    """grip_inputs=history, actor_readings=R: the head reads every reading of the state history, the MLP the newest R
    (and the other keys): older readings move the action only through the estimate."""
    from torchrl.data import Composite, Unbounded

    from torcsrl.agents._build import grip_layout
    from torcsrl.nets import DeterministicActor, ObsEncoder

    spec = Composite({"rangefinder": Unbounded((19,)), "state": Unbounded((44,)), "opponents": Unbounded((36,))}, shape=())
    enc = ObsEncoder(spec, ["rangefinder", "state", "opponents"])
    grip_in, policy_in = grip_layout(enc, "history", 1)
    assert grip_in == list(range(19, 63)) and policy_in == list(range(19)) + list(range(52, 99))
    assert grip_layout(enc, "all", None) == (None, None)
    torch.manual_seed(0)
    actor = DeterministicActor(enc, -torch.ones(2), torch.ones(2), (32,), grip_hidden=(8,), grip_inputs=grip_in, policy_inputs=policy_in)
    assert actor.grip_head[0].in_features == 44 and actor.net[0].in_features == 19 + 36 + 11 + 1
    assert not any("inputs" in k for k in actor.state_dict())  # rebuilt from the config, not stored
    obs = [torch.rand(5, 19), torch.rand(5, 44), torch.rand(5, 36)]
    older = [obs[0], torch.cat([torch.rand(5, 33), obs[1][:, 33:]], -1), obs[2]]  # the same newest reading
    with torch.no_grad():
        f, g = actor.encoder(*obs), actor.encoder(*older)
        assert not torch.allclose(actor.grip(f), actor.grip(g))  # the head reads the old readings
        torch.testing.assert_close(actor.act(f, actor.grip(f)), actor.act(g, actor.grip(f)))  # the MLP does not
        assert not torch.allclose(actor.act(f, actor.grip(f)), actor.act(f, actor.grip(f) + 0.5))
    cam = ObsEncoder(Composite({"pixels": Unbounded((3, 8, 8), dtype=torch.uint8)}, shape=()), ["pixels"], cnn_channels=(4,))
    with pytest.raises(ValueError, match="select from a state history, which the actor's observations \\(pixels\\) do not hold"):
        grip_layout(cam, "history", None)


def test_an_actor_without_a_head_has_no_estimate():
    actor = _actor(grip_hidden=None)
    assert actor.grip_head is None and actor.net[0].in_features == actor.encoder.out_dim
    with pytest.raises(AttributeError, match="grip_estimate=0"):
        actor.grip(torch.zeros(1, actor.encoder.out_dim))


def test_a_grip_student_trains_logs_its_estimate_and_drives_from_its_checkpoint(tmp_path, capsys):
    """A DAgger student with a state history and a grip head: loss/grip is logged, the checkpoint rebuilds the head and
    drives a one-reading env feeding its actor exactly what the training env fed it; teacher_gap prints its estimate."""
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.training import train
    from torcsrl.utils.checkpoint import latest_checkpoint

    cfg = compose_config(*RACE, "algo=dagger", "state_history=4", "algo.grip_estimate=1.0", "algo.grip_hidden=[8]",
                         "algo.grip_inputs=history", "algo.actor_readings=2",
                         "demos.frames=120", "algo.bc_steps=10", "logger.every_frames=5", "demos.dagger_rounds=1",
                         "demos.dagger_frames=40", f"run_dir={tmp_path / 'run'}")
    res = train(cfg)
    assert res["updates"] == 20
    log = tmp_path / "run" / "logs" / "dagger" / "scalars" / "loss" / "grip.csv"
    assert log.is_file() and len(log.read_text().strip().splitlines()) >= 2
    pol = CheckpointPolicy(latest_checkpoint(tmp_path / "run" / "checkpoints"))
    assert pol.actor.grip_head is not None and pol.actor.grip_head[0].out_features == 8
    assert pol.actor.grip_head[0].in_features == 44 and pol.actor.net[0].in_features == 19 + 22 + 1  # 4 readings / the newest 2
    assert_policy_history_matches_training_env(pol, cfg, 7)
    from _bench import load_benchmark

    ck = str(latest_checkpoint(tmp_path / "run" / "checkpoints"))  # benchmarks/teacher_gap.py shows the estimate beside mu
    assert load_benchmark("teacher_gap").main([ck, "--track", "oval", "--surface", "dirt", "--teacher", "racer_bold", "--steps", "30"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"grip estimate: mean -?[0-9.]+ for the road's mu 0\.[0-9]+ \(RMSE [0-9.]+", out) and "| mu_hat | mu |" in out, out


@pytest.mark.parametrize("over,msg", [
    (["algo=td3", "algo.grip_estimate=1.0"], r"algo.grip_estimate=1.0: .*only algo=bc / dagger fit \(algo=td3\)"),
    (["algo=dagger", "algo.grip_estimate=-1"], r"algo.grip_estimate"),
    (["algo=dagger", "algo.grip_estimate=1.0", "algo.grip_hidden=[0]"], r"algo.grip_hidden=\[0\]: expected a list"),
    (["algo=dagger", "algo.grip_estimate=1.0", "algo.grip_inputs=road"], r"algo.grip_inputs='road'; allowed: all .*history"),
    (["algo=dagger", "algo.grip_estimate=1.0", "state_history=4", "algo.actor_readings=5"],
     r"algo.actor_readings=5: .* state_history=4 holds; allowed: 1..4"),
    (["algo=dagger", "state_history=4", "algo.actor_readings=2"], r"shape a grip head, which algo.grip_estimate=0.0 does not build"),
])
def test_a_grip_head_that_cannot_learn_is_one_line(over, msg):
    from torcsrl.config import problems

    found = [p for p in problems(compose_config(*RACE, *over)) if "grip" in p or "actor_readings" in p]
    assert len(found) == 1 and "\n" not in found[0], found
    assert re.search(msg, found[0]), found


def test_demonstrations_without_privileged_mu_are_refused_in_one_line(tmp_path):
    import json

    from torcsrl.training.demos import DemoError, write_demos
    from torcsrl.training import train

    base = compose_config(*RACE, "algo=dagger")
    write_demos(base, tmp_path / "d", frames=30, seed=1)
    meta_path = next((tmp_path / "d").rglob("meta.json"))
    meta = json.loads(meta_path.read_text())
    meta["extra_keys"] = ["expert_action"]  # as demonstrations written before the privileged rows were
    meta["checksums"] = {k: v for k, v in (meta.get("checksums") or {}).items() if "privileged" not in k}
    meta_path.write_text(json.dumps(meta))
    for f in (tmp_path / "d").rglob("privileged*"):
        f.unlink()
    cfg = compose_config(*RACE, "algo=dagger", "algo.grip_estimate=1.0", f"demos.path={tmp_path / 'd'}", "demos.frames=0",
                         "demos.dagger_rounds=0", "algo.bc_steps=2", f"run_dir={tmp_path / 'run'}")
    with pytest.raises(DemoError, match=r"algo.grip_estimate=1.0 regresses the rows' privileged mu") as err:
        train(cfg)
    assert "\n" not in str(err.value)
