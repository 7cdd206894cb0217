"""PPO's rollouts from worker processes (``algo=ppo collector.num_workers=W``): the batch the loop gets, the weights and
observation statistics the workers act with after a sync, a smoke run through train(cfg), the one-line refusal of a car
count the workers cannot share."""

from __future__ import annotations

import math

import pytest
import torch

from torcsrl import agents
from torcsrl.pipeline import make_train_env
from torcsrl.config import ConfigError, validate
from torcsrl.training import train
from torcsrl.training.common import make_networks
from torcsrl.training.onpolicy import WorkerRollouts, make_rollout_collector, worker_config
from torcsrl.utils.logging import read_csv_metric
from _compose import compose_config

PPO = ["env=toy", "debug=smoke", "algo=ppo", "algo.rollout_steps=20", "algo.epochs=2", "algo.batch_size=32"]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def cfg_for(*overrides: str):
    return compose_config(*PPO, *overrides)


def test_two_workers_give_one_batch_of_all_cars_and_act_with_the_learners_weights_and_statistics(tmp_path):
    cfg = cfg_for("env.num_cars=4", "collector.num_workers=2", f"run_dir={tmp_path}")
    torch.manual_seed(0)
    env = make_train_env(worker_config(cfg, 2))  # one worker's env: 2 cars
    assert tuple(env.batch_size) == (2,)
    agent, keys = agents.get("ppo"), list(cfg.env.sensors)
    actor, critic, _ = make_networks(cfg, agent, env, keys, torch.device("cpu"))
    policy = agent.make_exploration(cfg.algo, actor, env, keys)
    rng = torch.get_rng_state()
    collector = make_rollout_collector(cfg, env, policy, 2, 1)
    assert isinstance(collector, WorkerRollouts)
    assert torch.equal(torch.get_rng_state(), rng)  # the workers seed their own generators, not the learner's
    try:
        batches = iter(collector)
        data = next(batches)
        assert tuple(data.batch_size) == (4, 20)  # [cars, time], worker 0's cars first: GAE runs along time per car
        assert data.get("action_log_prob").shape == (4, 20) and data.get(("next", "episode_reward")).shape == (4, 20, 1)
        obs = data.get("rangefinder")
        assert not torch.equal(obs[:2], obs[2:])  # the workers' envs have their own seeds
        # the learner moves its weights and its observation statistics; the workers see both after the sync
        actor.encoder.update_norm(*[data.get(k) for k in keys])
        with torch.no_grad():
            for p in actor.parameters():
                p.add_(0.01)
        mine = policy.state_dict()
        norm = [k for k in mine if k.endswith("norm.count")]
        assert norm and float(mine[norm[0]]) == 80
        collector.update_policy_weights_()
        for state in collector.worker_policy_states():
            assert set(state) == set(mine)
            for k, v in mine.items():
                torch.testing.assert_close(state[k], v, rtol=0, atol=0, msg=k)
        assert tuple(next(batches).batch_size) == (4, 20)  # and collect again
    finally:
        collector.shutdown()
        env.close()


def test_ppo_smoke_run_with_two_workers_and_its_resume(tmp_path):
    """One car a worker (each worker's env has no batch dim): the loop still gets [cars, T]. A resumed run carries on
    from the checkpoint (networks, statistics, counters; the workers' episodes restart)."""
    ov = ["env.num_cars=2", "collector.num_workers=2", "logger.every_frames=40", "checkpoint.every_frames=40", f"run_dir={tmp_path}"]
    r = train(cfg_for(*ov, "total_frames=80"))
    assert r["frames"] == 80 and r["updates"] == 2 * 2 * 2  # 2 batches of 2 cars x 20 steps, 2 epochs of 40 / 32 -> 2
    ck = torch.load(r["checkpoint"], weights_only=False)
    assert float(ck["actor"]["encoder.norm.count"]) == 80 and ck["collector"] == {}
    r = train(cfg_for(*ov, "total_frames=160", "checkpoint.resume=latest"))
    assert r["frames"] == 160 and r["updates"] == 4 * 2 * 2
    rows = read_csv_metric(tmp_path, "loss/critic")
    assert [s for s, _ in rows] == [40, 80, 120, 160] and all(math.isfinite(v) for _, v in rows)
    assert float(torch.load(r["checkpoint"], weights_only=False)["actor"]["encoder.norm.count"]) == 160


def test_a_car_count_the_workers_cannot_share_is_refused_in_one_line():
    with pytest.raises(ConfigError) as err:
        validate(cfg_for("env.num_cars=6", "collector.num_workers=4"))
    msg = str(err.value)
    assert msg.count("\n") == 0
    assert "collector.num_workers=4: algo=ppo splits env.num_cars=6 cars evenly over the worker processes; allowed: a divisor of 6 " \
           "(1, 2, 3, 6), or 0" in msg
    validate(cfg_for("env.num_cars=6", "collector.num_workers=3"))  # a divisor passes


def test_policy_lag_collects_while_the_learner_updates_and_gives_the_same_batches(tmp_path):
    """collector.policy_lag=1: TorchRL's MultiAsyncCollector. The loop still gets [cars, T] batches of all cars (two
    workers' batches joined along the cars), every row one car's contiguous steps, each step with the log-probability
    of its action as drawn. (That the worker collects during the update is a matter of timing: measured by
    benchmarks/train_throughput.py's ppo+w1+lag, not asserted here.)"""
    from torchrl.collectors import MultiAsyncCollector

    cfg = cfg_for("env.num_cars=4", "collector.num_workers=2", "collector.policy_lag=1", f"run_dir={tmp_path}")
    torch.manual_seed(0)
    env = make_train_env(worker_config(cfg, 2))
    agent, keys = agents.get("ppo"), list(cfg.env.sensors)
    actor, critic, _ = make_networks(cfg, agent, env, keys, torch.device("cpu"))
    policy = agent.make_exploration(cfg.algo, actor, env, keys)
    collector = make_rollout_collector(cfg, env, policy, 2, 1)
    assert isinstance(collector.collector, MultiAsyncCollector) and collector.lag == 1
    try:
        batches = iter(collector)
        for _ in range(2):
            data = next(batches)
            assert tuple(data.batch_size) == (4, 20)
            # every row is one car's contiguous steps: a step starts where the one before ended, unless an episode ended
            obs, nxt = data.get(keys[0]), data.get(("next", keys[0]))
            done = data.get(("next", "done")).squeeze(-1)
            joined = (nxt[:, :-1] == obs[:, 1:]).flatten(2).all(-1)
            assert bool((joined | done[:, :-1]).all()) and bool(joined.any())
            # the log-probabilities are those of the acting weights (the learner's have not moved yet)
            with torch.no_grad():
                loc, scale = actor.dist(*[data.get(k) for k in keys])
                again = policy.squash.log_prob(loc, scale, data.get("action"))
            torch.testing.assert_close(again.reshape(4, 20), data.get("action_log_prob"), rtol=1e-3, atol=1e-3)
    finally:
        collector.shutdown()
        env.close()


def test_ppo_smoke_run_with_policy_lag(tmp_path):
    ov = ["env.num_cars=2", "collector.num_workers=1", "collector.policy_lag=1", "logger.every_frames=40",
          "checkpoint.every_frames=40", f"run_dir={tmp_path}"]
    r = train(cfg_for(*ov, "total_frames=120"))
    assert r["frames"] == 120 and r["updates"] == 3 * 2 * 2
    rows = read_csv_metric(tmp_path, "loss/critic")
    assert [s for s, _ in rows] == [40, 80, 120] and all(math.isfinite(v) for _, v in rows)


@pytest.mark.parametrize("overrides, message", [
    (["collector.num_workers=1", "collector.policy_lag=2"], "collector.policy_lag=2: rollouts of policy lag while the learner updates; "
                                                            "allowed: 0 (collect, then update) or 1"),
    (["collector.policy_lag=1"], "collector.policy_lag=1 needs worker processes to collect while this one updates; allowed: "
                                 "collector.num_workers>=1 (got 0), or policy_lag=0"),
    (["algo=td3", "collector.num_workers=1", "collector.policy_lag=1"], "collector.policy_lag=1: the workers collect the next rollout "
                                                                       "during the update only for algo=ppo (algo=td3"),
])
def test_a_policy_lag_that_cannot_apply_is_refused_in_one_line(overrides, message):
    with pytest.raises(ConfigError) as err:
        validate(cfg_for("env.num_cars=2", *overrides))
    assert str(err.value).count("\n") == 0 and message in str(err.value), str(err.value)
