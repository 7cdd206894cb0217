"""Training collectors on Ray (``collector.ray=<address> collector.num_workers=W``): the batch the loops get, the weights
and observation statistics the actors act with after a sync, PPO and TD3 smoke runs through train(cfg), workers placed
on both nodes of a two-node cluster on this machine, a node lost mid-run as one line (not a hang), and the bad input
that fails before any worker starts."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import pytest
import torch

ray = pytest.importorskip("ray")

from torcsrl import agents  # noqa: E402
from torcsrl.config import ConfigError, validate  # noqa: E402
from torcsrl.pipeline import make_train_env  # noqa: E402
from torcsrl.training import train  # noqa: E402
from torcsrl.training.common import make_networks  # noqa: E402
from torcsrl.training.onpolicy import make_rollout_collector, worker_config  # noqa: E402
from torcsrl.training.ray_collectors import RayRollouts, RayWorkerLost  # noqa: E402
from torcsrl.utils.ray_session import RayError  # noqa: E402
from _compose import compose_config  # noqa: E402

PPO = ["env=toy", "debug=smoke", "algo=ppo", "algo.rollout_steps=20", "algo.epochs=2", "algo.batch_size=32"]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def cluster():
    """A Ray cluster of two nodes of one CPU each, as separate processes on this machine (Ray's ``cluster_utils``)."""
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    c.add_node(num_cpus=1)
    ray.init(address=c.address, logging_level="ERROR", log_to_driver=False)
    c.wait_for_nodes()
    yield c
    ray.shutdown()
    c.shutdown()


def _ppo_parts(cfg, workers: int):
    env = make_train_env(worker_config(cfg, workers))
    agent, keys = agents.get("ppo"), list(cfg.env.sensors)
    actor, _, _ = make_networks(cfg, agent, env, keys, torch.device("cpu"))
    return env, actor, agent.make_exploration(cfg.algo, actor, env, keys), keys


def test_an_unreachable_address_and_a_bad_one_fail_in_one_line_before_any_worker():
    """With no Ray in this process: the CLI refuses a malformed address at validation and an address nobody
    answers within seconds, in one line each."""
    if ray.is_initialized():  # another test file's Ray in this process would be used as it is, whatever the address
        ray.shutdown()
    with pytest.raises(ConfigError) as err:
        validate(compose_config(*PPO, "env.num_cars=2", "collector.num_workers=2", "collector.ray=nowhere"))
    assert str(err.value).count("\n") == 0 and "collector.ray: 'nowhere' is not a Ray address; allowed: null (no Ray), local" in str(err.value)
    with pytest.raises(ConfigError, match="collector.ray=local: the Ray actors are the env workers; allowed: collector.num_workers>=1"):
        validate(compose_config(*PPO, "collector.ray=local"))
    with pytest.raises(ConfigError, match="collector.ray=local: algo=bc collects its demonstrations and DAgger rounds in this process"):
        validate(compose_config("env=toy", "debug=smoke", "algo=bc", "collector.num_workers=1", "collector.ray=local"))
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "torcsrl.train", *PPO, "env.num_cars=2", "collector.num_workers=2",
                        "collector.ray=127.0.0.1:9", "total_frames=40", "progress=false"], capture_output=True, text=True, timeout=120)
    assert p.returncode != 0 and time.perf_counter() - t < 60
    last = p.stderr.strip().splitlines()[-1]
    assert "cannot reach the Ray cluster at 127.0.0.1:9" in last and "Traceback" not in p.stderr, p.stderr[-2000:]


def test_workers_on_both_nodes_act_with_the_learners_weights_and_statistics(cluster, tmp_path):
    cfg = compose_config(*PPO, "env.num_cars=4", "collector.num_workers=2", f"collector.ray={cluster.address}", f"run_dir={tmp_path}")
    torch.manual_seed(0)
    env, actor, policy, keys = _ppo_parts(cfg, 2)
    collector = make_rollout_collector(cfg, env, policy, 2, 1)
    assert isinstance(collector, RayRollouts)
    try:
        batches = iter(collector)
        data = next(batches)
        assert tuple(data.batch_size) == (4, 20)  # [cars, time], worker 0's cars first, as with local workers
        obs = data.get("rangefinder")
        assert not torch.equal(obs[:2], obs[2:])  # the workers' envs have their own seeds
        nodes = collector.worker_nodes()
        assert len(set(nodes)) == 2 and all(nodes), nodes  # one actor on each node
        actor.encoder.update_norm(*[data.get(k) for k in keys])
        with torch.no_grad():
            for p in actor.parameters():
                p.add_(0.01)
        mine = policy.state_dict()
        assert float(mine["actor.encoder.norm.count"]) == 80
        collector.update_policy_weights_()
        for state in collector.worker_policy_states():
            assert set(state) == set(mine)
            for k, v in mine.items():
                torch.testing.assert_close(state[k], v, rtol=0, atol=0, msg=k)
        assert tuple(next(batches).batch_size) == (4, 20)
    finally:
        collector.shutdown()
        env.close()


def test_more_workers_than_the_cluster_has_cpus_is_one_line(cluster, tmp_path):
    cfg = compose_config(*PPO, "env.num_cars=3", "collector.num_workers=3", f"collector.ray={cluster.address}", f"run_dir={tmp_path}")
    env, _, policy, _ = _ppo_parts(cfg, 3)
    try:
        with pytest.raises(RayError) as err:
            make_rollout_collector(cfg, env, policy, 3, 1)
        assert str(err.value).count("\n") == 0
        assert "collector.num_workers=3: the Ray instance this process had initialised, 2 CPU(s) cannot hold 3 workers" in str(err.value)
    finally:
        env.close()


@pytest.mark.parametrize("algo,extra", [("ppo", PPO[2:]), ("td3", ["algo=td3", "total_frames=300", "collector.init_random_frames=100",
                                                                       "learner.warmup_frames=100"])], ids=["ppo", "td3"])
def test_smoke_runs_through_train_on_ray(cluster, tmp_path, algo, extra):
    ov = ["env=toy", "debug=smoke", *extra, "env.num_cars=2" if algo == "ppo" else "env.num_cars=1", "collector.num_workers=2",
          f"collector.ray={cluster.address}", "logger.every_frames=40", "checkpoint.every_frames=40", f"run_dir={tmp_path}"]
    if algo == "ppo":
        ov.append("total_frames=80")
    r = train(compose_config(*ov))
    assert r["frames"] >= 80 and r["updates"] > 0 and r["checkpoint"]
    key = "loss/critic" if algo == "ppo" else "loss/qvalue"
    assert math.isfinite(r[key])


def test_a_node_lost_mid_run_is_one_line_not_a_hang(cluster, tmp_path):
    """The second node goes away between two batches: the next batch raises RayWorkerLost naming the cluster, within
    Ray's failure detection, instead of waiting forever."""
    node = cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    cfg = compose_config(*PPO, "env.num_cars=3", "collector.num_workers=3", f"collector.ray={cluster.address}", f"run_dir={tmp_path}")
    env, _, policy, _ = _ppo_parts(cfg, 3)
    collector = make_rollout_collector(cfg, env, policy, 3, 1)  # 3 CPUs, 3 actors: one of them on the node that goes
    try:
        batches = iter(collector)
        next(batches)
        cluster.remove_node(node)
        t = time.perf_counter()
        with pytest.raises(RayWorkerLost) as err:
            next(batches)
        assert time.perf_counter() - t < 120
        assert str(err.value).count("\n") == 0 and "a Ray collector worker on" in str(err.value)
        assert "resume: checkpoint.resume=latest" in str(err.value)
    finally:
        collector.shutdown()
        env.close()


def test_a_node_lost_in_a_training_run_ends_it_with_a_checkpoint_it_resumes_from(cluster, tmp_path):
    """A whole ``train(cfg)`` on the two-node cluster plus a third node that goes away once the run has written a
    checkpoint: the run ends with RayWorkerLost in one line (no hang), and resuming on a cluster that has the CPUs
    again continues from that checkpoint to the end."""
    node = cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    ckpts = tmp_path / "checkpoints"
    ov = [*PPO, "env.num_cars=3", "collector.num_workers=3", f"collector.ray={cluster.address}", "logger.every_frames=60",
          "checkpoint.every_frames=60", f"run_dir={tmp_path}"]

    def remove_node_after_a_checkpoint():
        deadline = time.monotonic() + 400  # the actors start slowly on a loaded machine (a first checkpoint took > 120 s)
        while time.monotonic() < deadline and not list(ckpts.glob("ckpt_*.pt")):
            time.sleep(0.1)
        cluster.remove_node(node)

    killer = threading.Thread(target=remove_node_after_a_checkpoint, daemon=True)
    killer.start()
    t = time.perf_counter()
    with pytest.raises(RayWorkerLost) as err:
        train(compose_config(*ov, "total_frames=1000000"))
    killer.join()
    assert time.perf_counter() - t < 480
    assert str(err.value).count("\n") == 0 and "resume: checkpoint.resume=latest" in str(err.value)
    saved = sorted(ckpts.glob("ckpt_*.pt"))
    assert saved
    frames = int(saved[-1].stem.split("_")[1])
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    r = train(compose_config(*ov, f"total_frames={frames + 120}", "checkpoint.resume=latest"))
    assert r["frames"] >= frames + 120 and r["updates"] > 0
