"""Every RL agent has the same factories, and every one of them builds a working agent: one matrix over all five.

The matrix is the shared base's contract: the factories build from the env's specs, the behaviour policy acts inside
the action bounds, validation's action is deterministic and equals ``actor(*obs)`` (what evaluation and export call),
one ``update`` moves the actor and the critic and returns finite losses, and an update's own state round-trips
through ``state_dict`` (what checkpoints hold)."""

import inspect
import math

import pytest
import torch
from omegaconf import OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torcsrl import agents
from torcsrl.envs.toy import make_toy_env

FACTORIES = ["make_actor", "make_critic", "make_loss", "make_target_updater", "make_exploration", "make_optimizers", "update"]


def _cfg(algo: str):
    base = OmegaConf.load("conf/algo/base.yaml")
    own = OmegaConf.load(f"conf/algo/{algo}.yaml")
    own.pop("defaults", None)
    return OmegaConf.merge(base, own, {"actor_hidden": [16, 16], "critic_hidden": [16, 16], "batch_size": 16, "v_min": -10.0, "v_max": 10.0,
                                       "encoder": {"cnn_channels": [4], "feature_dim": 8}, "policy_delay": 1})


@pytest.mark.parametrize("name", agents.RL_ALGOS)
def test_identical_factories(name):
    mod = agents.get(name)
    for f in FACTORIES:
        assert callable(getattr(mod, f, None)), (name, f)
        ref = inspect.signature(getattr(agents.get("td3"), f))
        sig = inspect.signature(getattr(mod, f))
        assert list(sig.parameters) == list(ref.parameters), (name, f)


def test_siblings_write_only_what_differs():
    """DDPG, TD3 and D4PG take actor, target updater, exploration and optimisers from one place, as they are."""
    from torcsrl.agents import _build

    for name in ("ddpg", "td3", "d4pg"):
        mod = agents.get(name)
        for f in ("make_actor", "make_target_updater", "make_exploration", "make_optimizers"):
            assert getattr(mod, f) is getattr(_build, f), (name, f)


def test_imitation_agents_build_the_rl_actor():
    for name in agents.IMITATION:
        mod = agents.get(name)
        assert mod.make_actor.__code__ is agents.get("bc").make_actor.__code__
        assert list(inspect.signature(mod.make_actor).parameters) == list(inspect.signature(agents.get("td3").make_actor).parameters)


def test_unknown_algo_is_one_clear_line():
    with pytest.raises(ValueError, match="unknown algorithm 'a2c'; known: ddpg, td3, d4pg, sac, ppo, bc, dagger"):
        agents.get("a2c")


@pytest.mark.parametrize("name", agents.RL_ALGOS)
@pytest.mark.parametrize("pixels", [False, True], ids=["vector", "pixels"])
def test_every_agent_builds_acts_and_updates(name, pixels):
    torch.manual_seed(0)
    keys = ["rangefinder", "state", "pixels"] if pixels else ["rangefinder", "state"]
    env = make_toy_env(sensors=keys, camera={"height": 16, "width": 16} if pixels else None, seed=0)
    cfg = _cfg(name)
    ag = agents.get(name)
    actor, critic = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
    loss = ag.make_loss(cfg, actor, critic, env, keys)
    updater = ag.make_target_updater(cfg, loss)
    policy = ag.make_exploration(cfg, actor, env, keys)
    optim = ag.make_optimizers(cfg, loss)

    # acting: inside the bounds while exploring; deterministic (= actor(*obs)) under DETERMINISTIC exploration
    with torch.no_grad():
        data = env.rollout(24, policy, break_when_any_done=False)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    assert ((data["action"] >= low) & (data["action"] <= high)).all()
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        a1, a2 = policy(td.clone())["action"], policy(td.clone())["action"]
        torch.testing.assert_close(a1, a2)
        torch.testing.assert_close(a1, actor(*[td[k] for k in keys]))

    # one update moves the actor and the critic; finite losses
    if name in agents.ON_POLICY:
        with torch.no_grad():
            loss.value_estimator(data)
    batch = data[:16]
    before = {n: [p.detach().clone() for p in m.parameters()] for n, m in (("actor", actor), ("critic", critic))}
    out = ag.update(cfg, loss, optim, updater, batch, 0)
    assert out and all(math.isfinite(float(v)) for v in out.values()), out
    for n, m in (("actor", actor), ("critic", critic)):
        assert any(not torch.equal(p, q) for p, q in zip(m.parameters(), before[n])), f"{name}: the {n} did not move"

    # what a checkpoint holds comes back: a fresh agent loading it acts the same
    torch.manual_seed(1)
    actor2, critic2 = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
    loss2 = ag.make_loss(cfg, actor2, critic2, env, keys)
    loss2.load_state_dict(loss.state_dict())
    actor2.load_state_dict(actor.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(actor2(*[td[k] for k in keys]), actor(*[td[k] for k in keys]))
