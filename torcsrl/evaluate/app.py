"""The evaluate app: time trials of a policy over tracks x surfaces, written as JSON, CSV, Markdown and PNG."""


from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from torcsrl.evaluate.plots import plot_trajectory, write_gif
from torcsrl.evaluate.protocol import (PROTOCOL_VERSION, Degradation, EvalError, check_policy_env, env_sensors, expert_reference,
                                       parse_degradation, run_cell, validate_grid)
from torcsrl.evaluate.results import _f, markdown_table, summarise_track, summary_table, write_csv, write_json
from torcsrl.policies import BUILTIN_POLICIES, Policy, PolicyError, load_policy
from torcsrl.utils.faults import OutputError, ignore_signals_in_worker, stop_pool, writable_folder

# --------------------------------------------------------------------------------------------
# evaluate()
# --------------------------------------------------------------------------------------------
def evaluate(
    policy: str | Policy,
    tracks: str | Sequence[str],
    surfaces: str | Sequence[str | None] | None = None,
    laps: int = 10,
    seed: int = 0,
    out_dir: str | Path | None = None,
    degradation: Any = None,
    *,
    episodes: int = 1,
    max_steps: int | None = None,
    env_kwargs: Mapping[str, Any] | None = None,
    expert_laps: int | None = 2,
    plots: bool = True,
    video_frames: int = 120,
    workers: int = 1,
    verbose: bool = True,
) -> dict[str, Any]:
    """Time trials of ``policy`` on ``tracks`` × ``surfaces``; returns (and writes to ``out_dir``)
    ``{"config", "policy", "summary": [per track], "episodes": [per episode], "files"}``.

    Args:
        policy: a policy spec (see :func:`torcsrl.policies.load_policy`) or a Policy.
        tracks: track names and/or sets (``"set:heldout"``).
        surfaces: road surfaces to drive each track on (None: each track's own).
        laps: laps per episode (N); success = all N without termination.
        seed: evaluation seed (starts, degradation draws, the random policy).
        out_dir: where to write the artefacts (None: nothing written).
        degradation: None (clean), ``"name@severity"``, ``(name, severity)`` or a mapping.
        episodes: episodes per track.
        max_steps: step cap per episode (default: N laps at 10 m/s, at least 60 s a lap).
        env_kwargs: more :func:`torcsrl.envs.make_env` keywords (start, spawn_jitter, ...).
        expert_laps: laps the expert drives for its reference time (None/0: no expert reference).
        plots: write the trajectory PNGs (and the camera GIF when pixels are observed).
        video_frames: frames in the camera GIF.
        workers: processes driving tracks in parallel (1: in this process).
    """
    t0 = time.perf_counter()
    if int(laps) < 1 or int(episodes) < 1:
        raise EvalError(f"laps and episodes must be >= 1, got laps={laps}, episodes={episodes}")
    if max_steps is not None and (isinstance(max_steps, bool) or int(max_steps) != max_steps or max_steps < 1):
        raise EvalError(f"--max-steps (max_steps) must be an integer >= 1, got {max_steps!r}; allowed: 1, 2, ... or "
                        "none (N laps at 10 m/s)")
    names, surfs = validate_grid(tracks, surfaces)
    deg = parse_degradation(degradation)
    pol = load_policy(policy)
    check_policy_env(pol, names[0], env_kwargs)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        try:
            writable_folder(out, "--out")
        except OutputError as err:
            raise EvalError(str(err)) from None
    config = {"policy": pol.describe(), "tracks": names, "surfaces": surfs, "laps": int(laps), "episodes": int(episodes),
              "seed": int(seed), "degradation": {"name": deg.name, "severity": deg.severity, "params": dict(deg.params)},
              "max_steps": max_steps, "env_kwargs": dict(env_kwargs or {}), "protocol": PROTOCOL_VERSION}
    if deg.keys() and not set(deg.keys()) & set(env_sensors(pol)):
        print(f"[torcsrl.evaluate] note: {deg.name} degrades {list(deg.keys())}, which {pol.name} does not observe", file=sys.stderr)
    all_rows, summaries, files, notes = [], [], [], []
    from torcsrl.envs import tracks as _tracks

    want_trace = plots and out is not None
    tasks = [(worker_spec(pol), pol.name, name, surface, deg,
              dict(episodes=episodes, laps=laps, seed=seed, max_steps=max_steps, env_kwargs=env_kwargs, trace=want_trace,
                   frames=video_frames if want_trace else 0), int(expert_laps or 0))
             for name in names for surface in surfs]
    for (_, _, name, surface, _, _, _), (rows, traces, ref) in zip(tasks, map_tasks(_track_task, tasks, workers)):
        if ref.get("note"):
            notes.append(ref["note"])
        summ = summarise_track(rows, ref)
        summaries.append(summ)
        all_rows += rows
        if verbose:
            print(f"[torcsrl.evaluate] {pol.name} on {name}/{summ['surface']} {deg.label()}: laps {summ['laps']:.0f}/{laps}, "
                  f"fastest {_f(summ['fastest_lap'])} s, success {summ['success_rate']:.0%}", file=sys.stderr)
        if out is not None and plots and traces and traces[0]:
            geom = _tracks.load(name, surface=surface)
            tr = dict(traces[0], terminated=rows[0]["terminated"])
            tag = f"{name}_{summ['surface']}" + ("" if deg.clean else f"_{deg.name}{deg.severity}")
            r0 = rows[0]
            how = f"fastest {_f(r0['fastest_lap'])} s" if r0["lap_times"] else "no timed lap"
            if r0["termination"]:
                how += f", ended: {r0['termination']}"
            title = f"{pol.name} on {name} ({summ['surface']}{'' if deg.clean else ', ' + deg.label()}): {r0['laps']}/{laps} laps, {how}"
            files.append(str(plot_trajectory(geom, tr, out / f"trajectory_{tag}.png", title)))
            if "frames" in tr:
                g = write_gif(tr["frames"], out / f"camera_{tag}.gif")
                if g:
                    files.append(str(g))
    result = {"config": config, "policy": pol.describe(), "summary": summaries, "episodes": all_rows, "notes": notes,
              "wall_s": time.perf_counter() - t0}
    if out is not None:
        header, body = summary_table(summaries)
        md = [f"# Time trials: {pol.name}", "",
              f"{len(names)} track(s) × {len(surfs)} surface(s), {laps} laps, {episodes} episode(s) each, seed {seed}"
              + ("" if deg.clean else f", degradation {deg.label()}") + ".", "",
              markdown_table(header, body), "",
              "Fastest lap: the best timed lap; mean lap: mean of laps 2..N (lap 1 starts from rest). vs expert / vs limit: "
              "fastest lap over the scripted expert's fastest lap / over the physical-limit lap time (point mass on the "
              "minimum-curvature line). Flips/km: steering sign changes per km.", ""]
        md += [f"- note: {n}" for n in notes]
        (out / "evaluation.md").write_text("\n".join(md) + "\n")
        write_csv(summaries, out / "evaluation.csv")
        write_csv(all_rows, out / "episodes.csv")
        files = [str(out / "evaluation.json"), str(out / "evaluation.csv"), str(out / "episodes.csv"), str(out / "evaluation.md"), *files]
        result["files"] = files
        write_json(result, out / "evaluation.json")
        if verbose:
            print(f"[torcsrl.evaluate] wrote {out} ({len(files)} files)", file=sys.stderr)
    return result


def _track_task(policy: Any, name: str, track: str, surface: str | None, deg: Degradation, kw: dict[str, Any],
                expert_laps: int) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, Any]]:
    """One track of :func:`evaluate` (runs in a worker process when ``workers > 1``)."""
    pol = worker_policy(policy)
    pol.name = name
    rows, traces = run_cell(pol, track, surface, deg, **kw)
    ref = expert_reference(track, surface, expert_laps) if expert_laps else {}
    return rows, traces, ref


_POLICIES: dict[str, Policy] = {}


def worker_policy(policy: str | Policy) -> Policy:
    """The policy a task names: loaded once per process from its spec (see :func:`worker_spec`), or the object."""
    if isinstance(policy, str):
        if policy not in _POLICIES:
            _POLICIES[policy] = load_policy(policy)
        return _POLICIES[policy]
    return policy


def worker_spec(pol: Policy) -> str | Policy:
    """What a worker process gets for ``pol``: its spec where the spec loads it again (a built-in name or a file),
    else the policy object itself."""
    return pol.spec if pol.spec in BUILTIN_POLICIES or Path(pol.spec).is_file() else pol


def _worker_init() -> None:
    torch.set_num_threads(1)
    ignore_signals_in_worker()


def map_tasks(fn: Callable[..., Any], tasks: Sequence[tuple], workers: int = 1):
    """``fn(*task)`` for every task, in order: in this process (workers <= 1) or in a pool of
    ``workers`` spawned processes (one torch thread each)."""
    workers = max(1, min(int(workers), len(tasks)))
    if workers == 1:
        for t in tasks:
            yield fn(*t)
        return
    import concurrent.futures as cf
    import multiprocessing as mp

    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_worker_init) as ex:
        futs = [ex.submit(fn, *t) for t in tasks]
        try:
            for f in futs:
                yield f.result()
        except BaseException:  # a signal (Interrupted), a failed task, or the consumer stopped early (GeneratorExit)
            stop_pool(ex)
            raise


# --------------------------------------------------------------------------------------------
#: The flags of earlier versions, aliases of the config's keys (conf/evaluate.yaml).
FLAGS = {"--policy": ("policy", "one"), "--track": ("tracks", "many"), "--tracks": ("tracks", "many"),
         "--surface": ("surfaces", "many"), "--surfaces": ("surfaces", "many"), "--laps": ("laps", "one"),
         "--episodes": ("episodes", "one"), "--seed": ("seed", "one"), "--degradation": ("corruption", "one"),
         "--severity": ("severity", "one"), "--max-steps": ("max_steps", "one"), "--start": ("start", "one"),
         "--expert-laps": ("expert_laps", "one"), "--no-plots": ("plots", "false"), "--workers": ("workers", "one"),
         "--out": ("out", "one"), "--mode": ("mode", "one"), "--opponents": ("opponents", "one"), "--pace": ("pace", "one"),
         "--side-gap": ("side_gap_m", "one")}
#: Types of the config's values (checked before anything runs).
TYPES = {"policy": (str,), "tracks": (str, list), "surfaces": (str, list, type(None)), "laps": (int,), "episodes": (int,),
         "seed": (int,), "corruption": (str, type(None)), "severity": (int, type(None)), "max_steps": (int, type(None)),
         "start": (str,), "expert_laps": (int,), "plots": (bool,), "workers": (int,), "out": (str, type(None)),
         "mode": (str,), "opponents": (int,), "pace": (float, int, list), "side_gap_m": (float, int)}


def run_config(cfg: Any, out: str | Path | None = None, verbose: bool = True) -> dict[str, Any]:
    """:func:`evaluate` from a composed ``conf/evaluate.yaml`` (checked first: unknown keys, types, names);
    ``out`` (a multirun's job folder) wins over ``cfg.out``."""
    from torcsrl.utils.hydra_app import AppError, check_keys

    try:
        c = check_keys(cfg, "evaluate", TYPES)
    except AppError as err:
        raise EvalError(str(err)) from None
    if c["start"] not in ("grid", "random"):
        raise EvalError(f"start must be grid or random, got {c['start']!r}")
    deg = parse_degradation(c["corruption"], c["severity"]) if c["corruption"] else None
    if not c["corruption"] and c["severity"] not in (None, 0):
        raise EvalError(f"severity={c['severity']} needs a degradation (corruption=<name>, --degradation <name>)")
    from torcsrl.policies import is_ensemble_spec

    spec = str(c["policy"])  # an ensemble spec (a.pt+b.pt@reduce) is named after its member count, as EnsemblePolicy
    name = f"ensemble{spec.count('+') + 1}" if is_ensemble_spec(spec) else Path(spec).stem
    out = out or c["out"] or str(Path("outputs") / "evaluate" / name / time.strftime("%Y-%m-%d_%H-%M-%S"))
    if c["mode"] not in ("trial", "race"):
        raise EvalError(f"mode must be trial or race, got {c['mode']!r}")
    if c["mode"] == "race":
        from torcsrl.evaluate.race import evaluate_race

        if deg is not None:
            raise EvalError("mode=race drives clean sensors; allowed: corruption=null with mode=race")
        return evaluate_race(c["policy"], c["tracks"], c["surfaces"], laps=c["laps"], seed=c["seed"], out_dir=out,
                             episodes=c["episodes"], opponents=c["opponents"], pace=c["pace"], env_kwargs={"start": c["start"]},
                             max_steps=c["max_steps"], plots=c["plots"], verbose=verbose, workers=c["workers"],
                             side_gap_m=c["side_gap_m"])
    return evaluate(c["policy"], c["tracks"], c["surfaces"], laps=c["laps"], seed=c["seed"], out_dir=out, degradation=deg,
                    episodes=c["episodes"], max_steps=c["max_steps"], env_kwargs={"start": c["start"]},
                    expert_laps=c["expert_laps"], plots=c["plots"], workers=c["workers"], verbose=verbose)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torcsrl.evaluate [key=value ...] [--flag value ...] [-m]`` (see conf/evaluate.yaml)."""
    from torcsrl.utils.faults import cli_error, graceful_termination
    from torcsrl.utils.hydra_app import AppError, compose, flags_to_overrides, is_multirun, run_multirun

    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__.split("\n\n")[0] + "\n\nusage: python -m torcsrl.evaluate [key=value ...] [-m]; keys and defaults: "
              "conf/evaluate.yaml; flags: " + " ".join(FLAGS))
        return 0
    torch.set_num_threads(1)
    try:
        overrides = flags_to_overrides(argv, FLAGS)
        if is_multirun(overrides):
            return run_multirun("evaluate", overrides, _multirun_job, "torcsrl.evaluate")
        cfg = compose("evaluate", overrides)
        with graceful_termination():
            res = run_config(cfg)
    except (EvalError, PolicyError, AppError, OSError, KeyboardInterrupt) as err:
        return cli_error("torcsrl.evaluate", err, stopped="its worker processes were stopped (run it again for the full evaluation)")
    out = Path(res["files"][0]).parent
    print((out / ("race.md" if (out / "race.md").exists() and not (out / "evaluation.md").exists() else "evaluation.md")).read_text())
    print(f"evaluation: {out}")
    return 0


def _multirun_job(cfg: Any, job_dir: Path) -> None:
    """One job of ``python -m torcsrl.evaluate -m ...``: its outputs in its own Hydra job folder."""
    from torcsrl.utils.faults import cli_error, graceful_termination

    torch.set_num_threads(1)
    try:
        with graceful_termination():
            run_config(cfg, out=job_dir)
    except (EvalError, PolicyError, OSError) as err:
        sys.exit(cli_error("torcsrl.evaluate", err))


if __name__ == "__main__":
    sys.exit(main())
