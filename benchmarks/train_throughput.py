"""Training-loop throughput: our TD3 / DDPG / D4PG loops vs Stable-Baselines3 TD3, on Pendulum-v1.

Same settings for all: 256x256 actor and critic, batch 256, one gradient step per env step
(TD3: actor every 2), one env, after a warm-up of random steps. Steps/s are env steps per
wall-clock second of the whole loop (collect + store + sample + update), measured after the
warm-up; 1 and 2 torch threads. SB3 is used only when importable (``pip install --target
/tmp/peers stable-baselines3`` is picked up from /tmp/peers).

    python benchmarks/train_throughput.py [--steps 1500] [--warmup 500] [--threads 1 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
if os.path.isdir("/tmp/peers"):
    sys.path.append("/tmp/peers")

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from torcsrl.train import train  # noqa: E402
from torcsrl.utils.logging import read_csv_metric  # noqa: E402


def ours(algo: str, threads: int, steps: int, warmup: int) -> float:
    run = tempfile.mkdtemp(prefix=f"tp_{algo}_")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[
            f"algo={algo}", "env.name=gym", "+env.id=Pendulum-v1", "env.sensors=[observation]", f"run_dir={run}",
            f"threads={threads}", f"total_frames={warmup + steps}", f"collector.init_random_frames={warmup}",
            f"learner.warmup_frames={warmup}", "collector.frames_per_batch=1", "algo.batch_size=256",
            "algo.actor_hidden=[256,256]", "algo.critic_hidden=[256,256]", "eval.every_episodes=1000000",
            "checkpoint.every_frames=0", "checkpoint.buffer=false", f"logger.every_frames={steps // 5}", "progress=false",
            "buffer.size=100000",
            *(["algo.exploration.sigma=0.2", "algo.exploration.theta=0.15", "algo.exploration.mu=0.0"] if algo == "ddpg" else []),
        ])
    train(cfg)
    rows = [v for s, v in read_csv_metric(Path(run), "time/steps_per_s") if s > warmup + steps // 5]
    return sum(rows) / len(rows)


def sb3(threads: int, steps: int, warmup: int) -> float | None:
    try:
        import gymnasium as gym
        from stable_baselines3 import TD3
    except ImportError:
        return None
    torch.set_num_threads(threads)
    m = TD3("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=warmup, batch_size=256, buffer_size=100000,
            policy_kwargs=dict(net_arch=[256, 256]), seed=0, device="cpu")
    m.learn(warmup + 50)
    t = time.perf_counter()
    m.learn(steps, reset_num_timesteps=False)
    return steps / (time.perf_counter() - t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1500, help="measured env steps per run")
    ap.add_argument("--warmup", type=int, default=500, help="random steps before updates start")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args()
    rows = []
    for th in a.threads:
        peer = sb3(th, a.steps, a.warmup)
        res = {algo: ours(algo, th, a.steps, a.warmup) for algo in ("td3", "ddpg", "d4pg")}
        rows.append((th, peer, res))
    print(f"\nPendulum-v1, 256x256, batch 256, UTD 1, {a.steps} steps after {a.warmup} warm-up; load avg {os.getloadavg()[0]:.2f}")
    print(f"{'threads':>7} | {'SB3 TD3':>8} | {'TD3':>7} {'ratio':>6} | {'DDPG':>7} {'ratio':>6} | {'D4PG':>7} {'ratio':>6}")
    for th, peer, res in rows:
        def cell(v):
            return f"{v:7.1f} {v / peer:6.2f}" if peer else f"{v:7.1f} {'-':>6}"
        p = f"{peer:8.1f}" if peer else f"{'n/a':>8}"
        print(f"{th:>7} | {p} | {cell(res['td3'])} | {cell(res['ddpg'])} | {cell(res['d4pg'])}")
    print("targets: TD3 >= 1.25 x SB3 TD3, D4PG >= 1.0 x SB3 TD3 (steps/s)")


if __name__ == "__main__":
    main()
