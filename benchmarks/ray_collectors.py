"""Collector throughput: the local multiprocess workers against the same workers as Ray actors, side by side.

    python benchmarks/ray_collectors.py [--workers 1 2] [--cars 8] [--rollout 64] [--batches 6] [--rounds 3]

What the PPO loop collects (``make_rollout_collector``): batches of ``--rollout`` steps of ``--cars`` cars on the oval
(the training config's 10 Hz race env), split over W workers, with the learner's weights pushed to every worker after
each batch, as the loop does after each update (here without an update in between: what is measured is the collector's
own cost). Contenders per W: ``local`` (TorchRL ``MultiSyncCollector``, worker processes) and ``ray`` (TorchRL
``RayCollector``, Ray actors on a local Ray instance of W CPUs, weights through the object store). Frames/s are env
frames per wall second over ``--batches`` batches after one warm-up batch (worker start-up excluded, reported apart).
Each round runs every contender once, in alternating order; the table gives the median over rounds and Ray's cost:
1 - ray / local at the same W (goal: <= 15 %). One torch thread per process; run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

torch.set_num_threads(1)


def _parts(cars: int, rollout: int, workers: int, ray: str | None):
    from hydra import compose, initialize_config_dir

    from torcsrl import agents
    from torcsrl.pipeline import actor_obs_keys, make_train_env
    from torcsrl.training.common import make_networks
    from torcsrl.training.onpolicy import worker_config
    from torcsrl.utils.hydra_app import CONF_DIR

    ov = ["algo=ppo", "env.track=oval", f"env.num_cars={cars}", f"algo.rollout_steps={rollout}", f"collector.num_workers={workers}",
          "threads=1", "progress=false"]
    if ray:
        ov.append(f"collector.ray={ray}")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", overrides=ov)
    torch.manual_seed(0)
    env = make_train_env(worker_config(cfg, workers))
    agent, keys = agents.get("ppo"), actor_obs_keys(cfg)
    actor, _, _ = make_networks(cfg, agent, env, keys, torch.device("cpu"))
    return cfg, env, agent.make_exploration(cfg.algo, actor, env, keys)


def measure(kind: str, workers: int, cars: int, rollout: int, batches: int) -> dict:
    from torcsrl.training.onpolicy import make_rollout_collector

    cfg, env, policy = _parts(cars, rollout, workers, "local" if kind == "ray" else None)
    t0 = time.perf_counter()
    collector = make_rollout_collector(cfg, env, policy, workers, 1)
    try:
        it = iter(collector)
        next(it)  # warm-up: the workers start and build their envs
        start_s = time.perf_counter() - t0
        frames, t = 0, time.perf_counter()
        for _ in range(batches):
            frames += next(it).numel()
            collector.update_policy_weights_()
        wall = time.perf_counter() - t
    finally:
        collector.shutdown()
        env.close()
    return {"kind": kind, "workers": workers, "fps": frames / wall, "start_s": start_s}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--cars", type=int, default=8)
    p.add_argument("--rollout", type=int, default=64)
    p.add_argument("--batches", type=int, default=6)
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args(argv)
    try:
        import ray  # noqa: F401
    except ImportError:
        print("benchmarks/ray_collectors.py: needs ray (pip install -e '.[distributed]')", file=sys.stderr)
        return 2
    for w in a.workers:
        if w < 1 or a.cars % w:
            print(f"--workers {w}: the {a.cars} cars are split evenly over the workers; allowed: divisors of {a.cars}", file=sys.stderr)
            return 2
    results: dict[tuple[str, int], list[dict]] = {}
    for r in range(a.rounds):
        order = [("local", w) for w in a.workers] + [("ray", w) for w in a.workers]
        for kind, w in (order if r % 2 == 0 else order[::-1]):
            res = measure(kind, w, a.cars, a.rollout, a.batches)
            results.setdefault((kind, w), []).append(res)
            print(f"round {r}: {kind} W={w}: {res['fps']:,.0f} frames/s (start {res['start_s']:.1f} s)", file=sys.stderr, flush=True)
    print(f"\nPPO rollouts on the oval, {a.cars} cars x {a.rollout} steps a batch, weights pushed after each batch; "
          f"median of {a.rounds} rounds ({time.strftime('%Y-%m-%d')}, {os.cpu_count()} CPUs)\n")
    print("| workers | local frames/s | Ray frames/s | Ray's cost | local start [s] | Ray start [s] |")
    print("|---|---|---|---|---|---|")
    for w in a.workers:
        loc = statistics.median(x["fps"] for x in results[("local", w)])
        ray_ = statistics.median(x["fps"] for x in results[("ray", w)])
        ls = statistics.median(x["start_s"] for x in results[("local", w)])
        rs = statistics.median(x["start_s"] for x in results[("ray", w)])
        print(f"| {w} | {loc:,.0f} | {ray_:,.0f} | {100 * (1 - ray_ / loc):+.1f} % | {ls:.1f} | {rs:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
