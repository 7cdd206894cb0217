"""Report throughput: episodes/s of a robustness grid, one car at a time (today's path) vs batched as cars.

    PYTHONPATH=. python benchmarks/report_throughput.py [--episodes 8] [--max-steps N] [--tracks kidney rallycross]

The grid: the shipped driver (``reference``) × 2 held-out tracks × 6 rangefinder
degradations × severities 0..5 × 8 episodes of one lap = 2 × (8 + 6 × 5 × 8) = 496 episodes. Both
paths drive the SAME episodes (the same seeds; the benchmark checks that every row is equal):

* ``one car``: :func:`torcsrl.evaluate.run_cell` per cell, episode after episode (what
  ``report --batch-cars 1`` does, and what every report did before);
* ``batched``: :func:`torcsrl.evaluate.batched.run_batch`, every cell of a track as cars of one env
  (``report``'s default).

It then compares the rows: the paths give the same episodes bit for bit except where two or more cars
of the batch have a chassis-ground contact in the same physics substep (pybullet solves such contacts
together; see :mod:`torcsrl.evaluate.batched`), so it prints how many episodes differ, how many of them
in their outcome, and the largest relative difference of a return.

Side by side in one process, one torch thread, interleaved track by track (the order rotates), so
that other jobs on the machine slow both alike; the load average is printed before and after. Each path
is timed by the wall clock and by the process's CPU time (``time.process_time``: what a loaded machine
does not distort; the ratio is given for both). ``--max-cars 64 128 256`` runs the batched path once per
batch size, each compared with the same one-car rows. ``--max-steps`` caps every episode (a shorter run;
every path gets the same cap).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torcsrl.evaluate import run_cell  # noqa: E402
from torcsrl.evaluate.batched import run_batch  # noqa: E402
from torcsrl.policies import load_policy  # noqa: E402
from torcsrl.report import ReportConfig  # noqa: E402

DEGRADATIONS = ("rangefinder.noise", "rangefinder.dropout", "rangefinder.dead_beams", "rangefinder.fog", "rangefinder.rain",
                "rangefinder.latency")
GOAL = 5.0


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and a != a and b != b)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", default="reference")
    ap.add_argument("--tracks", nargs="+", default=["kidney", "rallycross"])
    ap.add_argument("--degradations", nargs="+", default=list(DEGRADATIONS))
    ap.add_argument("--severities", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--laps", type=int, default=1)
    ap.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default: the protocol's, a full lap)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-cars", type=int, nargs="+", default=[ReportConfig.batch_cars],
                    help="cars of the batched env, one batched run per value (default: the report's batch_cars default)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    pol = load_policy(a.policy)
    cells = [None] + [f"{d}@{s}" for d in a.degradations for s in a.severities if s > 0]
    n_ep = len(cells) * a.episodes
    kw = dict(episodes=a.episodes, laps=a.laps, seed=a.seed, max_steps=a.max_steps)
    paths = ["one car"] + [f"batched {m}" for m in a.max_cars]
    load0 = os.getloadavg()
    print(f"torch {torch.__version__}, 1 thread, {os.cpu_count()} CPUs; load average before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}")
    print(f"grid: {a.policy} x {len(a.tracks)} tracks x {len(a.degradations)} degradations x severities "
          f"{','.join(map(str, a.severities))} x {a.episodes} episodes = {n_ep * len(a.tracks)} episodes of {a.laps} lap(s)"
          + (f", at most {a.max_steps} steps each" if a.max_steps else ""))
    print("\n| track | path | episodes | car-steps | wall [s] | CPU [s] | episodes/s (wall) | episodes/s (CPU) | car-steps/s (CPU) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    tot = {path: [0, 0, 0.0, 0.0] for path in paths}
    diff = {path: [0, 0, 0, 0.0] for path in paths[1:]}  # fields, episodes, outcomes, largest relative return difference
    for k, track in enumerate(a.tracks):
        order = paths[k % len(paths):] + paths[:k % len(paths)]
        res = {}
        for path in order:
            t0, c0 = time.perf_counter(), time.process_time()
            if path == "one car":
                rows = [run_cell(pol, track, None, c, **kw)[0] for c in cells]
            else:
                rows = run_batch(pol, track, None, cells, max_cars=int(path.split()[1]), **kw)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            steps = sum(r["steps"] for cell in rows for r in cell)
            res[path] = rows
            for j, v in enumerate((n_ep, steps, wall, cpu)):
                tot[path][j] += v
            print(f"| {track} | {path} | {n_ep} | {steps} | {wall:.1f} | {cpu:.1f} | {n_ep / wall:.2f} | {n_ep / cpu:.2f} | "
                  f"{steps / cpu:.0f} |", flush=True)
        for path in paths[1:]:
            dd = diff[path]
            for ca, cb in zip(res["one car"], res[path]):
                for ra, rb in zip(ca, cb):
                    m = sum(not _same(ra[x], rb[x]) for x in ra)
                    dd[0] += m
                    dd[1] += m > 0
                    dd[2] += (ra["success"], ra["laps"], ra["termination"]) != (rb["success"], rb["laps"], rb["termination"])
                    dd[3] = max(dd[3], abs(ra["return"] - rb["return"]) / max(abs(ra["return"]), 1.0))
    for path in paths:
        e, st, wall, cpu = tot[path]
        print(f"| all | {path} | {e} | {st} | {wall:.1f} | {cpu:.1f} | {e / wall:.2f} | {e / cpu:.2f} | {st / cpu:.0f} |")
    load1 = os.getloadavg()
    one = tot["one car"]
    print()
    for path in paths[1:]:
        bat, dd = tot[path], diff[path]
        r_wall = (bat[0] / bat[2]) / (one[0] / one[2])
        r_cpu = (bat[0] / bat[3]) / (one[0] / one[3])
        print(f"{path} / one car: {r_wall:.2f}x episodes/s by wall clock, {r_cpu:.2f}x by CPU time (goal >= {GOAL:.0f}x: "
              f"{'ok' if min(r_wall, r_cpu) >= GOAL else 'MISS'}); rows equal: {'yes' if dd[0] == 0 else 'NO'}: "
              f"{dd[1]} of {one[0]} episodes differ in some field, {dd[2]} in success / laps / termination; "
              f"largest relative return difference {dd[3]:.2e}")
    print(f"load average after {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
