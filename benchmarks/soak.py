"""Long-run memory check: RSS over 10^3 resets and 10^5 steps of the gymnasium RaceEnv, and over env
create/close cycles and report cells.

    python benchmarks/soak.py [--resets 1000] [--steps 100000] [--cycles 200] [--cells 50]

Prints RSS [MiB] after warm-up and at the end, and the growth. Reset must not reload the world:
its cost is printed beside the step's. ``--cycles``: build a TorchRL race env (two tracks, rangefinder +
state), drive 5 steps, close it, N times; RSS must stay flat (pybullet keeps the lists handed to
createCollisionShape, so the rangefinder's walls are handed over as the same lists each time).
``--cells``: N report cells (a degraded one-episode time trial, capped at 200 steps), as a report runs them.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def soak(resets: int, steps: int, track: str = "hairpins") -> dict:
    import torcsrl.envs  # noqa: F401
    from torcsrl.envs.race import RaceEnv

    env = RaceEnv(track=["oval", track], start="random")
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    for _ in range(2000):  # warm-up: caches, allocator
        _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        if te or tr:
            env.reset()
    for _ in range(50):
        env.reset()
    base = rss_mib()
    t0 = time.perf_counter()
    for _ in range(resets):
        env.reset()
    t_reset = (time.perf_counter() - t0) / max(resets, 1)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        if te or tr:
            env.reset()
    t_step = (time.perf_counter() - t0) / max(steps, 1)
    end = rss_mib()
    env.close()
    return {"rss_start_mib": base, "rss_end_mib": end, "growth_mib": end - base,
            "reset_us": t_reset * 1e6, "step_us": t_step * 1e6}


def cycles(n: int, every: int = 50) -> dict:
    """RSS [MiB] every ``every`` cycles of build env -> 5 steps -> close (after 5 warm-up cycles)."""
    import gc

    from torcsrl.envs import make_env

    def cycle() -> None:
        env = make_env(track=["hairpins", "oval"], seed=0)
        env.rollout(5)
        env.close()

    for _ in range(5):
        cycle()
    gc.collect()
    trace = [(0, rss_mib())]
    t0 = time.perf_counter()
    for i in range(1, n + 1):
        cycle()
        if i % every == 0 or i == n:
            gc.collect()
            trace.append((i, rss_mib()))
    return {"trace": trace, "per_cycle_mib": (trace[-1][1] - trace[0][1]) / max(n, 1), "cycle_ms": 1e3 * (time.perf_counter() - t0) / max(n, 1)}


def cells(n: int) -> dict:
    """RSS [MiB] over ``n`` report cells (evaluate.run_cell, rangefinder noise at severity 3, 200 steps)."""
    import gc

    from torcsrl.evaluate import parse_degradation, run_cell
    from torcsrl.policies import load_policy

    pol = load_policy("heuristic")
    deg = parse_degradation("rangefinder.noise@3")
    for i in range(3):
        run_cell(pol, "oval", None, deg, episodes=1, laps=1, seed=i, max_steps=200)
    gc.collect()
    r0 = rss_mib()
    for i in range(n):
        run_cell(pol, "oval", None, deg, episodes=1, laps=1, seed=i, max_steps=200)
    gc.collect()
    r1 = rss_mib()
    return {"rss_start_mib": r0, "rss_end_mib": r1, "per_cell_mib": (r1 - r0) / max(n, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resets", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--cycles", type=int, default=200, help="env create/close cycles (0: skip)")
    ap.add_argument("--cells", type=int, default=50, help="report cells (0: skip)")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    if a.resets or a.steps:
        r = soak(a.resets, a.steps)
        print(f"resets {a.resets}, steps {a.steps} (random actions, episodes reset when done)")
        print(f"RSS after warm-up {r['rss_start_mib']:.1f} MiB, at the end {r['rss_end_mib']:.1f} MiB, "
              f"growth {r['growth_mib']:+.1f} MiB")
        print(f"reset {r['reset_us']:.0f} us, step {r['step_us']:.0f} us (reset / step = {r['reset_us'] / r['step_us']:.2f})")
    if a.cycles:
        c = cycles(a.cycles)
        print(f"env create/close cycles {a.cycles}: RSS " + ", ".join(f"{m:.1f}" for _, m in c["trace"]) + " MiB "
              f"(every 50 cycles), {c['per_cycle_mib']:+.3f} MiB per cycle, {c['cycle_ms']:.0f} ms per cycle")
    if a.cells:
        c = cells(a.cells)
        print(f"report cells {a.cells}: RSS {c['rss_start_mib']:.1f} -> {c['rss_end_mib']:.1f} MiB, {c['per_cell_mib']:+.3f} MiB per cell")
    return 0


if __name__ == "__main__":
    sys.exit(main())
