"""Training-loop throughput: our TD3 / DDPG / D4PG loops vs Stable-Baselines3 TD3, on Pendulum-v1.

Same settings for all: 256x256 actor and critic, batch 256, one gradient step per env step
(TD3: actor every 2), one env, after a warm-up of random steps. Steps/s are env steps per
wall-clock second of the whole loop (collect + store + sample + update), measured after the
warm-up, for each torch thread count asked for.

A contender ``<algo>+bf16`` runs ``<algo>`` with ``algo.precision=bfloat16`` (mixed-precision
updates; fast only where the CPU has bfloat16 units, which the header line reports).

The box is shared, so absolute figures drift with the load. What counts is the RATIO to SB3
measured side by side: each round runs every contender once (SB3 first on even rounds, last
on odd ones), a round's ratios compare runs seconds apart, and the table gives the median
over rounds. SB3 is used when importable (``pip install stable-baselines3``, the ``[bench]``
extra; a ``--target /tmp/peers`` install is picked up too).

    python benchmarks/train_throughput.py [--steps 1500] [--warmup 500] [--threads 1 2] [--rounds 3] [--algos td3 d4pg td3+bf16]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
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

TARGETS = {"td3": 1.25, "d4pg": 1.0}


def cpu_bf16() -> str:
    """Which bfloat16 units this CPU has (from /proc/cpuinfo), e.g. ``avx512_bf16``; ``none`` if none."""
    try:
        flags = set(open("/proc/cpuinfo").read().split())
    except OSError:
        return "unknown"
    found = sorted(f for f in flags if f in ("avx512_bf16", "amx_bf16", "avx_ne_convert"))
    return ", ".join(found) or "none"


def ours(name: str, threads: int, steps: int, warmup: int, extra: list[str]) -> tuple[float, float]:
    """(steps per wall second, steps per CPU second) of ``torcsrl.train.train`` after the warm-up (from its log).

    ``name``: an algorithm, or ``<algo>+bf16`` for its mixed-precision updates."""
    algo, _, variant = name.partition("+")
    if variant not in ("", "bf16"):
        raise SystemExit(f"unknown contender {name!r}; allowed: <algo> or <algo>+bf16")
    if variant == "bf16":
        extra = [*extra, "algo.precision=bfloat16"]
    run = tempfile.mkdtemp(prefix=f"tp_{algo}_")
    every = max(50, steps // 5)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[
            f"algo={algo}", "env.name=gym", "+env.id=Pendulum-v1", "env.sensors=[observation]", f"run_dir={run}",
            f"threads={threads}", f"total_frames={warmup + steps}", f"collector.init_random_frames={warmup}",
            f"learner.warmup_frames={warmup}", "collector.frames_per_batch=1", "algo.batch_size=256",
            "algo.actor_hidden=[256,256]", "algo.critic_hidden=[256,256]", "eval.every_episodes=1000000",
            "checkpoint.every_frames=0", "checkpoint.buffer=false", f"logger.every_frames={every}", "progress=false",
            "buffer.size=100000",
            *(["algo.exploration.sigma=0.2", "algo.exploration.theta=0.15", "algo.exploration.mu=0.0"] if algo == "ddpg" else []),
            *extra,
        ])
    train(cfg)
    wall = [(s, v) for s, v in read_csv_metric(Path(run), "time/elapsed_s") if s >= warmup + every]
    cpu = [(s, v) for s, v in read_csv_metric(Path(run), "time/cpu_s") if s >= warmup + every]
    shutil.rmtree(run, ignore_errors=True)
    return (wall[-1][0] - wall[0][0]) / (wall[-1][1] - wall[0][1]), (cpu[-1][0] - cpu[0][0]) / (cpu[-1][1] - cpu[0][1])


class SB3:
    """One SB3 TD3 model per thread count, learning ``steps`` more steps per call."""

    def __init__(self, threads: int, warmup: int):
        import gymnasium as gym
        from stable_baselines3 import TD3

        torch.set_num_threads(threads)
        self.m = TD3("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=warmup, batch_size=256, buffer_size=100000,
                     policy_kwargs=dict(net_arch=[256, 256]), seed=0, device="cpu")
        self.m.learn(warmup + 50)
        self.threads = threads

    def __call__(self, steps: int) -> tuple[float, float]:
        torch.set_num_threads(self.threads)
        t, c = time.perf_counter(), time.process_time()
        self.m.learn(steps, reset_num_timesteps=False)
        return steps / (time.perf_counter() - t), steps / (time.process_time() - c)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1500, help="measured env steps per run")
    ap.add_argument("--warmup", type=int, default=500, help="random steps before updates start")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--rounds", type=int, default=3, help="rounds of side-by-side runs (median reported)")
    ap.add_argument("--algos", nargs="+", default=["td3", "ddpg", "d4pg"])
    ap.add_argument("overrides", nargs="*", help="extra Hydra overrides for our runs (after --)")
    a = ap.parse_args()
    try:
        import stable_baselines3  # noqa: F401

        have_sb3 = True
    except ImportError:
        have_sb3 = False
        print("stable-baselines3 is not installed (pip install stable-baselines3): ratios are left out", file=sys.stderr)
    table = []
    for th in a.threads:
        load0 = os.getloadavg()[0]
        peer = SB3(th, a.warmup) if have_sb3 else None
        runs: dict[str, list[float]] = {k: [] for k in ["sb3", *a.algos]}
        ratios: dict[str, list[float]] = {k: [] for k in a.algos}
        cpu_ratios: dict[str, list[float]] = {k: [] for k in a.algos}
        for r in range(a.rounds):
            order = ["sb3", *a.algos] if r % 2 == 0 else [*a.algos, "sb3"]
            got = {}
            for name in order:
                if name == "sb3":
                    if peer is not None:
                        got[name] = peer(a.steps)
                else:
                    got[name] = ours(name, th, a.steps, a.warmup, a.overrides)
            for k, v in got.items():
                runs[k].append(v[0])
            if "sb3" in got:
                for k in a.algos:
                    ratios[k].append(got[k][0] / got["sb3"][0])
                    cpu_ratios[k].append(got[k][1] / got["sb3"][1])
            print(f"[threads {th} round {r}] " + ", ".join(f"{k} {v[0]:.1f} steps/s ({v[1]:.1f} per CPU-s)" for k, v in got.items())
                  + f"; load {os.getloadavg()[0]:.2f}", file=sys.stderr)
        table.append((th, load0, os.getloadavg()[0], runs, ratios, cpu_ratios))

    print(f"\nPendulum-v1, 256x256, batch 256, UTD 1, {a.steps} steps after {a.warmup} warm-up; steps/s and ratio to SB3 TD3, "
          f"median of {a.rounds} side-by-side rounds (cpu: ratio of steps per CPU-second, meaningful at 1 thread); "
          f"CPU bfloat16 units: {cpu_bf16()}")
    head = f"{'threads':>7} | {'load':>9} | {'SB3 TD3':>8} | " + " | ".join(f"{k.upper():>8} {'ratio':>6} {'cpu':>5}" for k in a.algos)
    print(head)
    for th, l0, l1, runs, ratios, cpu_ratios in table:
        sb = f"{statistics.median(runs['sb3']):8.1f}" if runs["sb3"] else f"{'n/a':>8}"
        cells = []
        for k in a.algos:
            rt = f"{statistics.median(ratios[k]):6.2f} {statistics.median(cpu_ratios[k]):5.2f}" if ratios[k] else f"{'-':>6} {'-':>5}"
            cells.append(f"{statistics.median(runs[k]):8.1f} {rt}")
        print(f"{th:>7} | {l0:4.1f}-{l1:<4.1f} | {sb} | " + " | ".join(cells))
    print("targets: " + ", ".join(f"{k.upper()} >= {v} x SB3 TD3" for k, v in TARGETS.items()) + " (steps/s, float32)")


if __name__ == "__main__":
    main()
