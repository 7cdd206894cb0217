"""Time trials: a deterministic policy drives N laps per track x surface alone; written as JSON, CSV, Markdown and
PNG (see :mod:`torcsrl.evaluate`)."""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torcsrl.envs import tracks as _tracks
from torcsrl.evaluate.plots import plot_trajectory, write_gif
from torcsrl.evaluate.protocol import check_policy_env, env_sensors, expert_reference, run_cell
from torcsrl.evaluate.results import fmt_value, markdown_table, summarise_track, summary_table, write_csv, write_json
from torcsrl.evaluate.spec import PROTOCOL_VERSION, Degradation, EvalError, parse_degradation, validate_grid
from torcsrl.evaluate.workers import map_tasks, worker_policy, worker_spec
from torcsrl.policies import Policy, load_policy
from torcsrl.utils.faults import OutputError, writable_folder

__all__ = ["evaluate"]


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
                  f"fastest {fmt_value(summ['fastest_lap'])} s, success {summ['success_rate']:.0%}", file=sys.stderr)
        if out is not None and plots and traces and traces[0]:
            geom = _tracks.load(name, surface=surface)
            tr = dict(traces[0], terminated=rows[0]["terminated"])
            tag = f"{name}_{summ['surface']}" + ("" if deg.clean else f"_{deg.name}{deg.severity}")
            r0 = rows[0]
            how = f"fastest {fmt_value(r0['fastest_lap'])} s" if r0["lap_times"] else "no timed lap"
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
