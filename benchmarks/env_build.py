"""Env construction time: a training env with a procedural pool, as built now (lazily) and as built before (eagerly).

    python benchmarks/env_build.py [--repeats 3] [--experiment racer]

A run builds many envs (the demonstrations, each DAgger round, each validation), and each env seed draws its own
procedural pool of 100 generated tracks. Before 2026-11-28 the env generated every pool track and built its
rangefinder walls at construction (4-7 s an env); now a pool track is generated and walled when a car first draws it.
``eager`` rebuilds the old behaviour on the same env (every slot's track and walls right after construction) so both
are measured side by side in one process, one thread, on distinct env seeds (no cached pool tracks). It also checks
that the two read the same beams over a short drive.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def build(cfg, seed: int, eager: bool):
    from torcsrl.training.demos import make_demo_env

    t0 = time.perf_counter()
    env = make_demo_env(cfg, seed=seed)
    core = env.base_env.core
    if eager:  # what construction did before: every slot's geometry and rangefinder walls
        for slot, t in enumerate(core._geometry):
            core.rangefinder.add_track(slot, t)
    return env, time.perf_counter() - t0


def drive(env, steps: int = 30) -> np.ndarray:
    td = env.reset()
    act = env.action_spec.zero()
    act[..., 1] = 0.6
    beams = []
    for _ in range(steps):
        td = env.step(td.set("action", act.clone()))["next"]
        beams.append(td["rangefinder_clean"].numpy().copy())
    return np.stack(beams)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--experiment", default="racer", help="conf/experiment/<name>.yaml (its env and procedural pool)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from _compose import compose_config

    cfg = compose_config(f"experiment={a.experiment}")
    pool = cfg.env.get("procedural") or {}
    env, _ = build(cfg, seed=999, eager=False)  # imports and the named tracks' cache: not what is measured
    env.close()
    times: dict[str, list[float]] = {"lazy (now)": [], "eager (before)": []}
    same = True
    for r in range(a.repeats):
        lazy, t_lazy = build(cfg, seed=100 + r, eager=False)
        times["lazy (now)"].append(t_lazy)
        eager, t_eager = build(cfg, seed=200 + r, eager=True)
        times["eager (before)"].append(t_eager)
        lazy.close()
        eager.close()
        a_env, _ = build(cfg, seed=300 + r, eager=False)
        b_env, _ = build(cfg, seed=300 + r, eager=True)
        same &= bool(np.array_equal(drive(a_env), drive(b_env)))
        a_env.close()
        b_env.close()
    print(f"env build: experiment={a.experiment}, procedural pool {pool.get('pool', 0)} tracks, {a.repeats} builds each, one thread")
    print("| construction | median [s] | min [s] | max [s] |")
    print("|---|---:|---:|---:|")
    for k, v in times.items():
        print(f"| {k} | {statistics.median(v):.2f} | {min(v):.2f} | {max(v):.2f} |")
    ratio = statistics.median(times["eager (before)"]) / statistics.median(times["lazy (now)"])
    print(f"eager / lazy: {ratio:.1f}x; same beams over a 30-step drive: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
