"""Long-run memory check: RSS over 10^3 resets and 10^5 steps of the gymnasium RaceEnv.

    python benchmarks/soak.py [--resets 1000] [--steps 100000]

Prints RSS [MiB] after warm-up and at the end, and the growth. Reset must not reload the world:
its cost is printed beside the step's.
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resets", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=100_000)
    a = ap.parse_args(argv)
    r = soak(a.resets, a.steps)
    print(f"resets {a.resets}, steps {a.steps} (random actions, episodes reset when done)")
    print(f"RSS after warm-up {r['rss_start_mib']:.1f} MiB, at the end {r['rss_end_mib']:.1f} MiB, "
          f"growth {r['growth_mib']:+.1f} MiB")
    print(f"reset {r['reset_us']:.0f} us, step {r['step_us']:.0f} us (reset / step = {r['reset_us'] / r['step_us']:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
