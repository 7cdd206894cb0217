"""Generalisation benchmark: drivers' 10-lap time trials on tracks and surfaces they never trained on.

For each driver (a checkpoint, a run folder, ``reference``, ``expert`` or ``heuristic``) it drives the
time trials of :mod:`torcsrl.evaluate` (deterministic policy, from the grid) on

* ``set:heldout`` (six bundled tracks) on asphalt and on dirt, and
* ``--generated N`` procedural tracks from the held-out seed range (``gen-0 … gen-<N-1>``, or ``proc-…``
  with ``--generator proc``; :data:`torcsrl.envs.tracks.procedural.HELDOUT_SEEDS`), on both surfaces,

and prints per driver and surface: completion rate (all N laps, no termination) on the bundled and on
the generated tracks, the median of (fastest lap / the expert's fastest lap at the driver's control
rate) over the completed tracks, and the median steering sign flips per km. The scripted expert's lap
on each track is driven once (2 laps) at the same control rate as the driver.

    python benchmarks/generalisation.py --policy torcsrl/assets/reference_td3.pt RUN_DIR ... [--laps 10] [--generated 20] [--workers 2]
    python benchmarks/generalisation.py --policy RUN_DIR --curve       # held-out completion against training frames -> PNG

``--screen`` drives the training tracks instead (``set:train`` and ``gen-10001 … gen-10008`` from the training
seed range; ``--generated N`` for ``10001 … 10000+N``, ``--generator proc --no-bundled`` for circuits only,
``--generator both`` for gen tracks and circuits: a screen that sees the hairpin circuits): the
selection screen a shipped driver is chosen on (``--laps 1``). ``--starts K`` drives every trial
from K starts — the grid, then K-1 seeded random points of the lap (the same for every driver) — so one unlucky
braking point weighs 1/K of a track instead of the whole track (the counts are then trials, K per track). ``--curve`` drives every checkpoint of each run folder (``--curve-laps`` laps, default 1) on the same tracks
and plots completion against frames (``--out``/curve.png). ``--train SEEDS`` first trains the recipe
(``experiment=generalise`` and any ``-- overrides``) once per seed, then benchmarks the runs. Held-out tracks
are only ever driven here, never trained or selected on.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def track_lists(screen: bool, generator: str = "gen", generated: int | None = None) -> tuple[list[str], list[str]]:
    """(bundled, generated) track names: with ``screen`` what a shipped driver is chosen on — ``set:train`` and the
    training-range seeds 10001 .. 10000+N (N default 8) — never a held-out one; else ``set:heldout`` and the held-out
    seeds 0 .. N-1 (N default 20). ``generator``: ``gen``, ``proc`` (hairpin circuits), or ``both`` (N of each: the
    gen tracks, then the proc circuits)."""
    from torcsrl.envs import tracks as _tracks
    from torcsrl.envs.tracks.procedural import heldout_names

    if generator == "both":
        bundled, gen = track_lists(screen, "gen", generated)
        return bundled, gen + track_lists(screen, "proc", generated)[1]
    if screen:
        n = 8 if generated is None else int(generated)
        return _tracks.resolve("set:train"), [f"{'proc' if generator == 'proc' else 'gen'}-{s}" for s in range(10001, 10001 + n)]
    n = 20 if generated is None else int(generated)
    return _tracks.resolve("set:heldout"), heldout_names(n, generator) if n else []


def _cell(args):
    spec, track, surface, laps, hz, start = args
    import torch

    torch.set_num_threads(1)
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import load_policy

    pol = load_policy(spec)
    kw = {} if "control_hz" in pol.env_overrides else {"control_hz": hz, "substeps": int(round(200 / hz))}
    if start > 0:  # start k > 0: a random point of the lap, seeded by k (run_cell's common random numbers)
        kw["start"] = "random"
    rows, _ = run_cell(pol, track, surface, laps=laps, env_kwargs=kw, seed=start)
    r = rows[0]
    return {"policy": spec, "track": track, "surface": surface, "start": start, "success": bool(r["success"]), "laps": int(r["laps"]),
            "fastest_lap": float(r["fastest_lap"]), "flips_per_km": float(r["steer_flips_per_km"]), "termination": r["termination"],
            "mean_speed_kmh": float(r["mean_speed_kmh"])}


def _hz(spec: str) -> float:
    from torcsrl.policies import load_policy

    return float(load_policy(spec).env_overrides.get("control_hz", 10.0))


def _worker_init() -> None:
    """A forked trial worker: SIGTERM kills it (not the parent's stop handler), it ignores Ctrl-C (the parent stops
    the pool) and dies with its parent, even a SIGKILLed one."""
    import signal

    from torcsrl.utils.faults import ignore_signals_in_worker

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    ignore_signals_in_worker()


def run_grid(specs: list[str], tracks: list[str], surfaces: list[str], laps: int, workers: int, hz: dict[str, float],
             starts: int = 1) -> list[dict]:
    """One trial per (driver, track, surface, start); start 0 is the grid, start k > 0 a seeded random point."""
    jobs = [(s, t, u, laps, hz[s], k) for s in specs for t in tracks for u in surfaces for k in range(starts)]
    if workers <= 1:
        return [_cell(j) for j in jobs]
    from torcsrl.utils.faults import stop_pool

    with ProcessPoolExecutor(workers, initializer=_worker_init) as ex:
        try:
            return list(ex.map(_cell, jobs))
        except BaseException:  # SIGTERM / Ctrl-C (main's graceful_termination) or a failed trial: no worker outlives it
            stop_pool(ex)
            raise


def summarise(rows: list[dict], expert: dict[tuple[str, str], float], generated: set[str]) -> list[dict]:
    out = []
    for spec in dict.fromkeys(r["policy"] for r in rows):
        for surface in dict.fromkeys(r["surface"] for r in rows):
            mine = [r for r in rows if r["policy"] == spec and r["surface"] == surface]
            bundled = [r for r in mine if r["track"] not in generated]
            gen = [r for r in mine if r["track"] in generated]
            ratios = [r["fastest_lap"] / expert[(r["track"], surface)] for r in mine
                      if r["success"] and math.isfinite(expert.get((r["track"], surface), math.nan))]
            out.append({"policy": spec, "surface": surface,
                        "heldout_completed": sum(r["success"] for r in bundled), "heldout_total": len(bundled),
                        "generated_completed": sum(r["success"] for r in gen), "generated_total": len(gen),
                        "median_lap_vs_expert": statistics.median(ratios) if ratios else math.nan,
                        "median_flips_per_km": statistics.median([r["flips_per_km"] for r in mine]) if mine else math.nan})
    return out


def table(summary: list[dict], bundled: str = "set:heldout") -> str:
    """The summary as markdown; ``bundled``: the name of the bundled track set driven (``set:train`` in a --screen)."""
    lines = [f"| driver | surface | {bundled} completed | generated completed | median lap / expert | median flips/km |",
             "|---|---|---|---|---|---|"]
    for s in summary:
        gen = f"{s['generated_completed']}/{s['generated_total']} ({100 * s['generated_completed'] / max(s['generated_total'], 1):.0f} %)"
        lines.append(f"| {s['policy']} | {s['surface']} | {s['heldout_completed']}/{s['heldout_total']} | {gen} | "
                     f"{s['median_lap_vs_expert']:.3f} | {s['median_flips_per_km']:.1f} |")
    return "\n".join(lines)


def curve(run_dirs: list[str], tracks: list[str], surfaces: list[str], laps: int, workers: int, out: Path,
          screen: bool = False) -> Path:
    """Completion rate of every checkpoint of each run, against its training frames -> curve.png: on the held-out
    tracks, or with ``screen`` on the training tracks (the selection screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for rd in run_dirs:
        cks = sorted((Path(rd) / "checkpoints").glob("ckpt_*.pt"))
        specs = [str(c) for c in cks]
        hz = {s: _hz(s) for s in specs}
        rows = run_grid(specs, tracks, surfaces, laps, workers, hz)
        xs, ys = [], []
        for c in cks:
            mine = [r for r in rows if r["policy"] == str(c)]
            xs.append(int(c.stem.split("_")[1]))
            ys.append(sum(r["success"] for r in mine) / max(len(mine), 1))
        ax.plot(xs, ys, marker="o", label=Path(rd).name)
        print(f"{Path(rd).name}: " + ", ".join(f"{x}: {y:.2f}" for x, y in zip(xs, ys)))
    ax.set_xlabel("training frames")
    which = "training-track" if screen else "held-out"
    ax.set_ylabel(f"{which} completion ({laps} lap{'s' if laps > 1 else ''})")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "curve.png"
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def main(argv: list[str] | None = None) -> int:
    """The command line; SIGTERM or Ctrl-C stops it with one line and exit status 128 + the signal, its pool shut."""
    from torcsrl.policies import PolicyError
    from torcsrl.utils.faults import cli_error, graceful_termination

    try:
        with graceful_termination():
            return _main(argv)
    except KeyboardInterrupt as err:  # Interrupted (SIGTERM) is one
        return cli_error("generalisation", err, stopped="no table written")
    except PolicyError as err:  # a --policy that is neither a file nor a built-in driver: one line, no traceback
        return cli_error("generalisation", err, stopped="no table written")


def _main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", nargs="+", default=[], help="checkpoints, run folders, reference, expert, heuristic")
    ap.add_argument("--train", nargs="*", type=int, default=None, help="train experiment=generalise with these seeds first")
    ap.add_argument("--laps", type=int, default=10)
    ap.add_argument("--generated", type=int, default=None,
                    help="generated tracks: held-out seeds 0..N-1 (default 20); with --screen training-range seeds 10001..10000+N (default 8)")
    ap.add_argument("--generator", choices=("gen", "proc", "both"), default="gen",
                    help="generated tracks: gen, proc (hairpin circuits: where dirt drivers fail most) or both (N of each)")
    ap.add_argument("--no-bundled", action="store_true",
                    help="drive only the generated tracks (e.g. 2-lap trials of them beside a 10-lap run of set:heldout)")
    ap.add_argument("--surfaces", nargs="+", default=["asphalt", "dirt"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--curve", action="store_true", help="plot held-out completion against frames for each run folder")
    ap.add_argument("--curve-laps", type=int, default=1)
    ap.add_argument("--screen", action="store_true",
                    help="selection screen on TRAINING tracks only (set:train + gen-10001..10008) instead of the held-out ones")
    ap.add_argument("--starts", type=int, default=1,
                    help="trials per track and surface: the grid, then seeded random points of the lap (the counts are trials)")
    ap.add_argument("--out", default="outputs/benchmarks/generalisation")
    ap.add_argument("--expert-json", default=None,
                    help="reuse the expert's reference laps of an earlier run's generalisation.json (same control rate); "
                         "the (track, surface) pairs it lacks are driven")
    args = ap.parse_args(argv)
    if args.generated is not None and args.generated < 0:
        ap.error(f"--generated {args.generated}: expected a whole number >= 0 (generated tracks to drive)")
    if args.starts < 1:
        ap.error(f"--starts {args.starts}: expected a whole number >= 1 (1 = from the grid only)")

    specs = list(args.policy)
    if args.train:
        from hydra import compose, initialize_config_dir

        from torcsrl.training import train

        for seed in args.train:
            run_dir = Path(args.out) / f"generalise_seed{seed}"
            with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
                cfg = compose("train", overrides=["experiment=generalise", f"seed={seed}", f"run_dir={run_dir}", "progress=false", *extra])
            train(cfg)
            specs.append(str(run_dir))
    if not specs:
        ap.error("give --policy and/or --train")
    heldout, generated = track_lists(args.screen, args.generator, args.generated)
    tracks = (generated if args.no_bundled else heldout + generated)
    if not tracks:
        ap.error("no tracks to drive: --no-bundled needs --generated N > 0")
    out = Path(args.out)
    t0 = time.perf_counter()
    if args.curve:
        path = curve([s for s in specs if Path(s).is_dir()], tracks, args.surfaces, args.curve_laps, args.workers, out,
                     screen=args.screen)
        print(f"wrote {path}")
        return 0
    hz = {s: _hz(s) for s in specs}
    exp_specs = sorted(set(hz.values()))
    expert: dict[tuple[str, str], float] = {}
    if args.expert_json:
        try:
            old = json.loads(Path(args.expert_json).read_text())
            old["expert"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            ap.error(f"--expert-json {args.expert_json}: not a generalisation.json with expert laps ({type(err).__name__}: {err})")
        rates = old.get("expert_hz", exp_specs)
        if sorted(rates) != exp_specs:
            ap.error(f"--expert-json {args.expert_json}: its reference laps were driven at {rates} Hz, these drivers run at {exp_specs} Hz")
        expert = {tuple(k.split("|")): float(v) for k, v in old["expert"].items()
                  if k.split("|")[0] in tracks and k.split("|")[1] in args.surfaces}
    rows = run_grid(specs, tracks, args.surfaces, args.laps, args.workers, hz, args.starts)
    for rate in exp_specs:  # the expert at each driver's control rate (2 laps: its fastest is a flying lap)
        todo = [t for t in tracks if any((t, u) not in expert for u in args.surfaces)]
        for r in run_grid(["expert"], todo, args.surfaces, 2, args.workers, {"expert": rate}) if todo else []:
            expert[(r["track"], r["surface"])] = r["fastest_lap"] if r["laps"] >= 2 else math.nan
    summary = summarise(rows, expert, set(generated))
    print(f"\n{len(rows)} trials of {args.laps} laps in {time.perf_counter() - t0:.0f} s"
          + (f"; generated: {generated[0]}..{generated[-1]}" if generated else "")
          + (f"; {args.starts} starts per track (the grid + {args.starts - 1} random): counts are trials" if args.starts > 1 else ""))
    bundled = "set:train" if args.screen else "set:heldout"
    print(table(summary, bundled))
    out.mkdir(parents=True, exist_ok=True)
    (out / "generalisation.json").write_text(json.dumps({"rows": rows, "summary": summary, "expert_hz": exp_specs,
                                                         "expert": {f"{k[0]}|{k[1]}": v for k, v in expert.items()}}, indent=1))
    (out / "generalisation.md").write_text(table(summary, bundled) + "\n")
    print(f"wrote {out / 'generalisation.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
