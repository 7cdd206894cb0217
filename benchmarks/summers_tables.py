"""The seeds' experiment (Summers 2022, Tables 7.1 and 7.2): agents trained on ONE track, driven on tracks they never saw.

Each agent is trained by ``python -m torcsrl.train`` on one track — ``experiment=summers_road`` (fast_straights on
asphalt, the analogue of wheel-2) or ``experiment=summers_dirt`` (hairpins on dirt, the analogue of dirt-6) — then its
newest checkpoint (the end of its budget; nothing is chosen on a held-out track) drives 10-lap time trials on
``set:heldout`` on asphalt and on dirt. Per agent the table has the columns of Summers's tables (track, laps
completed, fastest lap, success) beside the scripted expert's fastest lap; one summary row per agent, and one per
(algorithm, training track) over its seeds, give the held-out tracks completed and the median lap over the expert's.

    python benchmarks/summers_tables.py --train --frames 100000 --jobs 2              # the default grid, then tables
    python benchmarks/summers_tables.py --train --algos td3 --seeds 0 1 2 --presets summers_road summers_dirt
    python benchmarks/summers_tables.py --runs outputs/benchmarks/summers/runs/*       # tables of finished runs

``--train`` trains every (preset, algorithm, seed) of the grid into ``<out>/runs/<preset>_<algo>_s<seed>`` — the
default grid is TD3 with seeds 0, 1, 2 and DDPG and D4PG with seed 0, on both presets — ``--jobs`` at a time,
each with one torch thread. A folder that already holds a run is resumed exactly from its newest checkpoint, to
``--frames`` in all; its recorded config must be the one asked for (apart from ``total_frames``), else the
script stops before training, naming the keys that differ. Summers trained for 10^6 frames; the budget used is
printed in every table.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

PRESETS = {"summers_road": ("fast_straights", "asphalt"), "summers_dirt": ("hairpins", "dirt")}
ALGOS = ("ddpg", "td3", "d4pg")
#: Config keys a resumed table run may change: its frame budget (and where it prints).
MAY_DIFFER = ("total_frames", "progress", "run_dir", "threads", "checkpoint.resume", "overwrite")


class TableError(ValueError):
    """A bad argument or a run folder that cannot be resumed as asked (one line)."""


def grid(presets: list[str], algos: list[str] | None, seeds: list[int] | None) -> list[tuple[str, str, int]]:
    """(preset, algo, seed) to train. Default: TD3 x seeds 0, 1, 2 and DDPG, D4PG x seed 0, on every preset."""
    for p in presets:
        if p not in PRESETS:
            raise TableError(f"preset {p!r} is not a table preset; allowed: {', '.join(PRESETS)}")
    for a in algos or []:
        if a not in ALGOS:
            raise TableError(f"algorithm {a!r} is not in the tables; allowed: {', '.join(ALGOS)}")
    if algos is None and seeds is None:
        order = (("td3", 0), ("ddpg", 0), ("d4pg", 0), ("td3", 1), ("td3", 2))  # every algorithm once before the seeds
        return [(p, a, s) for a, s in order for p in presets]
    return [(p, a, s) for p in presets for a in (algos or ["td3"]) for s in (seeds if seeds is not None else [0])]


def overrides(preset: str, algo: str, seed: int, frames: int, run_dir: Path, extra: tuple[str, ...] = ()) -> list[str]:
    return [f"experiment={preset}", f"algo={algo}", f"seed={seed}", f"total_frames={frames}", f"run_dir={run_dir}",
            "progress=false", "threads=1", *extra]


def _flat(x, pre: str = "") -> dict:
    if isinstance(x, dict):
        out: dict = {}
        for k, v in x.items():
            out.update(_flat(v, f"{pre}.{k}" if pre else str(k)))
        return out
    return {pre: x}


def config_diffs(run_dir: Path, args: list[str]) -> list[str]:
    """Keys whose value in ``run_dir``'s recorded config differs from the config ``args`` compose to (``MAY_DIFFER``
    left out)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        new = OmegaConf.to_container(compose("train", overrides=args), resolve=True)
    old = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"), resolve=False)
    a, b = _flat(old), _flat(new)
    keep = lambda k: not any(k == m or k.startswith(m + ".") for m in MAY_DIFFER)  # noqa: E731
    return [f"{k}={a.get(k)!r} in the run, {b.get(k)!r} asked" for k in sorted(set(a) | set(b)) if keep(k) and a.get(k) != b.get(k)]


def plan(cells: list[tuple[str, str, int]], frames: int, out: Path, extra: tuple[str, ...] = ()) -> list[tuple[Path, list[str]]]:
    """The train command of every cell; a folder already holding a run resumes it, after its config is checked."""
    jobs = []
    for preset, algo, seed in cells:
        rd = out / "runs" / f"{preset}_{algo}_s{seed}"
        args = overrides(preset, algo, seed, frames, rd, extra)
        if (rd / "config.yaml").exists():
            diffs = config_diffs(rd, args)
            if diffs:
                more = f" (and {len(diffs) - 3} more)" if len(diffs) > 3 else ""
                raise TableError(f"{rd} holds a run of another config: {'; '.join(diffs[:3])}{more}; allowed: the same "
                                 "preset, algorithm, seed and settings with a larger --frames, or another --out")
            if newest_checkpoint(rd) is not None:
                args.append("checkpoint.resume=latest")
            else:
                args.append("overwrite=true")
        jobs.append((rd, args))
    return jobs


def newest_checkpoint(run_dir: Path) -> Path | None:
    cks = sorted((run_dir / "checkpoints").glob("ckpt_*.pt"), key=lambda c: int(c.stem.split("_")[1]))
    return cks[-1] if cks else None


def train(jobs: list[tuple[Path, list[str]]], n_jobs: int) -> None:
    def one(job):
        rd, args = job
        frames = int(next(a for a in args if a.startswith("total_frames=")).split("=")[1])
        if (ck := newest_checkpoint(rd)) is not None and int(ck.stem.split("_")[1]) >= frames:
            return rd, 0, 0.0  # already at its budget
        rd.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        with open(rd.parent / f"{rd.name}.log", "a") as log:
            rc = subprocess.call([sys.executable, "-m", "torcsrl.train", *args], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        return rd, rc, time.perf_counter() - t0

    with ThreadPoolExecutor(max(1, n_jobs)) as ex:
        for rd, rc, dt in ex.map(one, jobs):
            print(f"[summers] {rd.name}: exit {rc} after {dt / 60:.1f} min (log {rd.parent / (rd.name + '.log')})", flush=True)
            if rc:
                raise TableError(f"training {rd.name} failed with exit status {rc}; see {rd.parent / (rd.name + '.log')}")


def describe(run_dir: Path) -> dict:
    """What a run folder trained: algorithm, track, surface, seed, frames of its newest checkpoint."""
    from omegaconf import OmegaConf

    if not (run_dir / "config.yaml").exists():
        raise TableError(f"{run_dir}: not a training run folder (no config.yaml); expected outputs/train/... or <out>/runs/...")
    ck = newest_checkpoint(run_dir)
    if ck is None:
        raise TableError(f"{run_dir}: no checkpoint yet (checkpoints/ckpt_*.pt); train it first")
    cfg = OmegaConf.load(run_dir / "config.yaml")
    track = cfg.env.track
    return {"run": str(run_dir), "checkpoint": str(ck), "algo": str(cfg.algo.name), "seed": int(cfg.seed),
            "track": track if isinstance(track, str) else "+".join(track), "surface": str(cfg.env.surface),
            "frames": int(ck.stem.split("_")[1])}


def agent_table(agent: dict, rows: list[dict], expert: dict) -> str:
    lines = [f"#### {agent['algo'].upper()} trained on {agent['track']} ({agent['surface']}), seed {agent['seed']}, "
             f"{agent['frames']:,} frames",
             "", "| track | surface | laps completed | fastest lap [s] | expert lap [s] | success |", "|---|---|---|---|---|---|"]
    for r in rows:
        fl = f"{r['fastest_lap']:.1f}" if math.isfinite(r["fastest_lap"]) else "-"
        ex = expert.get((r["track"], r["surface"]), math.nan)
        lines.append(f"| {r['track']} | {r['surface']} | {r['laps']} | {fl} | {ex:.1f} | {'yes' if r['success'] else 'no'} |")
    return "\n".join(lines)


def summary_rows(agents: list[dict], rows: list[dict], expert: dict) -> list[dict]:
    out = []
    for ag in agents:
        mine = [r for r in rows if r["policy"] == ag["checkpoint"]]
        row = dict(ag)
        for surface in dict.fromkeys(r["surface"] for r in mine):
            su = [r for r in mine if r["surface"] == surface]
            ratios = [r["fastest_lap"] / expert[(r["track"], surface)] for r in su
                      if r["success"] and math.isfinite(expert.get((r["track"], surface), math.nan))]
            row[f"{surface}_completed"] = sum(r["success"] for r in su)
            row[f"{surface}_total"] = len(su)
            row[f"{surface}_lap_vs_expert"] = statistics.median(ratios) if ratios else math.nan
        row["flips_per_km"] = statistics.median([r["flips_per_km"] for r in mine]) if mine else math.nan
        out.append(row)
    return out


def summary_table(summary: list[dict], surfaces: list[str]) -> str:
    head = "| algorithm | training track | seed | frames | " + " | ".join(
        f"completed ({s}) | median lap / expert ({s})" for s in surfaces) + " | flips/km |"
    lines = [head, "|" + "---|" * (5 + 2 * len(surfaces))]
    for s in summary:
        cells = []
        for u in surfaces:
            cells += [f"{s.get(u + '_completed', 0)}/{s.get(u + '_total', 0)}", _fmt(s.get(u + "_lap_vs_expert", math.nan))]
        lines.append(f"| {s['algo'].upper()} | {s['track']} ({s['surface']}) | {s['seed']} | {s['frames']:,} | "
                     + " | ".join(cells) + f" | {_fmt(s['flips_per_km'], 1)} |")
    return "\n".join(lines)


def pooled_table(summary: list[dict], surfaces: list[str]) -> str:
    """One row per (algorithm, training track): completions summed over seeds, the median of the seeds' ratios."""
    lines = ["| algorithm | training track | seeds | completed | median lap / expert |", "|---|---|---|---|---|"]
    keys = dict.fromkeys((s["algo"], s["track"], s["surface"]) for s in summary)
    for algo, track, surface in keys:
        mine = [s for s in summary if (s["algo"], s["track"], s["surface"]) == (algo, track, surface)]
        done = sum(s.get(u + "_completed", 0) for s in mine for u in surfaces)
        total = sum(s.get(u + "_total", 0) for s in mine for u in surfaces)
        ratios = [s[u + "_lap_vs_expert"] for s in mine for u in surfaces if math.isfinite(s.get(u + "_lap_vs_expert", math.nan))]
        lines.append(f"| {algo.upper()} | {track} ({surface}) | {len(mine)} | {done}/{total} | "
                     f"{_fmt(statistics.median(ratios)) if ratios else '-'} |")
    return "\n".join(lines)


def _fmt(x: float, nd: int = 3) -> str:
    return f"{x:.{nd}f}" if isinstance(x, (int, float)) and math.isfinite(x) else "-"


def main(argv: list[str] | None = None) -> int:
    """The command line; bad input and SIGTERM / Ctrl-C end it with one line."""
    from torcsrl.policies import PolicyError
    from torcsrl.utils.faults import cli_error, graceful_termination

    try:
        with graceful_termination():
            return _main(argv)
    except KeyboardInterrupt as err:
        return cli_error("summers_tables", err, stopped="no table written")
    except (TableError, PolicyError) as err:
        return cli_error("summers_tables", err, stopped="no table written")


def _main(argv: list[str] | None = None) -> int:
    from generalisation import _hz, run_grid, track_lists

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", action="store_true", help="train the grid first (resuming folders that hold a run)")
    ap.add_argument("--presets", nargs="+", default=list(PRESETS))
    ap.add_argument("--algos", nargs="+", default=None, help=f"of {', '.join(ALGOS)} (default: the grid in the docstring)")
    ap.add_argument("--seeds", nargs="+", type=int, default=None)
    ap.add_argument("--frames", type=int, default=1_000_000, help="training frames per agent (Summers: 10^6)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="further Hydra overrides for every training run (recorded, so a resume must repeat them)")
    ap.add_argument("--jobs", type=int, default=2, help="training runs at once (one torch thread each)")
    ap.add_argument("--runs", nargs="*", default=None, help="run folders to tabulate (default: those of the grid)")
    ap.add_argument("--laps", type=int, default=10)
    ap.add_argument("--surfaces", nargs="+", default=["asphalt", "dirt"])
    ap.add_argument("--tracks", nargs="+", default=None, help="a subset of set:heldout (default: all of it)")
    ap.add_argument("--workers", type=int, default=2, help="trial processes")
    ap.add_argument("--out", default="outputs/benchmarks/summers")
    args = ap.parse_args(argv)
    if args.frames < 1:
        ap.error(f"--frames {args.frames}: expected a whole number >= 1 (training frames per agent)")
    if args.laps < 1:
        ap.error(f"--laps {args.laps}: expected a whole number >= 1")
    out = Path(args.out)
    cells = grid(args.presets, args.algos, args.seeds)
    if args.train:
        jobs = plan(cells, args.frames, out, tuple(args.set))  # every config checked before anything trains
        train(jobs, args.jobs)
    from torcsrl.envs.surfaces import ROAD_SURFACES

    for u in args.surfaces:
        if u not in ROAD_SURFACES:
            raise TableError(f"--surfaces {u}: not a road surface; allowed: {', '.join(ROAD_SURFACES)}")
    run_dirs = [Path(r) for r in args.runs] if args.runs else [out / "runs" / f"{p}_{a}_s{s}" for p, a, s in cells]
    agents = [describe(rd) for rd in run_dirs]
    heldout, _ = track_lists(False, generated=0)
    if args.tracks:
        if bad := [t for t in args.tracks if t not in heldout]:
            raise TableError(f"--tracks {' '.join(bad)}: the tables drive held-out tracks only; allowed: {', '.join(heldout)}")
        heldout = list(args.tracks)
    specs = [a["checkpoint"] for a in agents]
    t0 = time.perf_counter()
    hz = {s: _hz(s) for s in specs}
    if len(set(hz.values())) > 1:
        raise TableError(f"the agents run at different control rates {sorted(set(hz.values()))} Hz; tabulate them apart")
    rows = run_grid(specs, heldout, args.surfaces, args.laps, args.workers, hz)
    rate = next(iter(hz.values()))  # the expert's reference lap at the agents' control rate (2 laps: a flying lap)
    expert = {(r["track"], r["surface"]): (r["fastest_lap"] if r["laps"] >= 2 else math.nan)
              for r in run_grid(["expert"], heldout, args.surfaces, 2, args.workers, {"expert": rate})}
    summary = summary_rows(agents, rows, expert)
    frames = sorted({a["frames"] for a in agents})
    head = (f"{len(agents)} agents, {len(rows)} trials of {args.laps} laps on set:heldout ({', '.join(heldout)}) x "
            f"{', '.join(args.surfaces)} in {time.perf_counter() - t0:.0f} s; training budget "
            f"{', '.join(f'{f:,}' for f in frames)} frames per agent (Summers: 1,000,000); the newest checkpoint of each run")
    parts = [head, "", "### Summary", "", summary_table(summary, args.surfaces), "", "### Per algorithm and training track",
             "", pooled_table(summary, args.surfaces), "", "### Per agent (Tables 7.1 / 7.2)"]
    for ag in agents:
        parts += ["", agent_table(ag, [r for r in rows if r["policy"] == ag["checkpoint"]], expert)]
    text = "\n".join(parts) + "\n"
    print(text)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summers_tables.md").write_text(text)
    (out / "summers_tables.json").write_text(json.dumps({"agents": agents, "rows": rows, "summary": summary,
                                                         "expert": {f"{k[0]}|{k[1]}": v for k, v in expert.items()}}, indent=1))
    print(f"wrote {out / 'summers_tables.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
