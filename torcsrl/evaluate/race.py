"""Race mode of the evaluate command: N laps against K opponents, the same episode protocol as the time trials.

Each race is one episode of :func:`torcsrl.evaluate.protocol.drive_episode` on a race env (``traffic``,
:mod:`torcsrl.envs.traffic`): the policy drives the learner (car 0), the opponents drive themselves; the race ends
when the learner has driven N laps from the line (it is then classified at its position), leaves the track, or the
step cap runs out (a DNF). Seeds are the time trials' (:func:`seed_for`): the same grid order and paces for every
policy (common random numbers).

Per race (``episodes.csv``): the time-trial numbers (laps, success, fastest lap, ...) plus ``position`` (1 = won;
``None`` when the learner did not finish), ``win`` (finished first), ``overtakes`` (net cars passed), ``collisions``
(contacts begun with another car; ``contacts_ahead`` / ``_alongside`` / ``_behind``: by where the other car's centre
was, more than half a car length in front, within it, or behind — ran into it or was cut across, rubbed side by side,
was hit from behind or cut back in too soon), ``damage`` (summed contact impulse [kN s]), ``gap_ahead_m`` (along-track gap to
the car ahead at the end; 0 when leading), ``lead_m`` (how far ahead of the next car a winner finished, or how far
behind the leader [m, negative] another finished), ``start_position`` (the learner's place at the start, 1 = front),
``start_xy_m`` (where it started, track frame [m]) and ``opponent_paces`` (each opponent's drawn pace).

The table's ``scenarios`` column counts the distinct starts raced (start position and point, opponent paces): the physics is
deterministic, so against identical opponents at one pace a track has at most K + 1 distinct starts whatever the number
of races, and the same start gives the same race (tested with one opponent) — ``pace=[lo,hi]`` (a pace drawn per race
and car) or ``start=random`` make more.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torcsrl.envs import tracks as _tracks
from torcsrl.envs.traffic import Traffic, TrafficError, TrafficSpec
from torcsrl.evaluate.plots import plot_race
from torcsrl.evaluate.protocol import base_env, drive_episode, make_cell_env
from torcsrl.evaluate.results import fmt_value, markdown_table, write_csv, write_json
from torcsrl.evaluate.spec import Degradation, EvalError, default_max_steps, seed_for, validate_grid
from torcsrl.evaluate.workers import map_tasks, worker_policy, worker_spec
from torcsrl.policies import EpisodeContext, Policy, load_policy

__all__ = ["race_traffic", "run_race_cell", "race_summary", "race_table", "evaluate_race"]


def race_traffic(opponents: int = 3, pace: float | Sequence[float] = 0.85, start: str = "grid",
                 traffic: Mapping[str, Any] | None = None, side_gap_m: float | None = None) -> dict[str, Any]:
    """The ``traffic`` setting of a race: ``opponents`` scripted experts at ``pace`` (or a full mapping), giving
    ``side_gap_m`` [m] of room to a car alongside (None: the traffic default, 3.2; 0: blind to it)."""
    if traffic is not None:
        return dict(traffic)
    out = {"opponents": int(opponents), "driver": {"kind": "expert", "pace": pace}, "start": start, "order": "random"}
    if side_gap_m is not None:
        out["side_gap_m"] = side_gap_m
    return out


def run_race_cell(policy: Policy, track: str, surface: str | None, traffic: Mapping[str, Any], *, laps: int = 5,
                  episodes: int = 1, seed: int = 0, max_steps: int | None = None,
                  env_kwargs: Mapping[str, Any] | None = None, trace: bool = False) -> tuple[list[dict[str, Any]], list[dict]]:
    """``episodes`` races of ``policy`` on ``track``; one row per race (see the module docstring), and per race a trace
    of every car's world position ``xy [steps, cars, 2]`` (track frame) and the contact steps (when ``trace``)."""
    geom = _tracks.load(track, surface=surface)
    surface_name = surface or geom.default_surface
    hz = {**dict(env_kwargs or {}), **policy.env_overrides}.get("control_hz", 50.0)
    steps = int(max_steps) if max_steps else default_max_steps(geom.length, laps, 1.0 / float(hz))
    kw = {**dict(env_kwargs or {}), "traffic": dict(traffic), "policy_loader": load_policy}  # opponents of kind policy
    env, _ = make_cell_env(policy, track, surface, Degradation(), laps, steps, kw)
    core = base_env(env).core
    tr = core.traffic
    rows, traces = [], []
    try:
        for e in range(int(episodes)):
            env_seed = seed_for(seed, "env", track, surface_name, e)
            base_env(env).set_seed(env_seed)
            ctx = EpisodeContext(track=core.car_tracks[0], seed=seed_for(seed, "policy", track, surface_name, e), episode=e,
                                 dt=float(core.dt))
            xy: list[np.ndarray] = []
            hits: list[tuple[int, int, str]] = []
            seen = np.zeros(core.n, dtype=np.int64)
            seen_sides = np.zeros((core.n, len(CONTACT_SIDES)), dtype=np.int64)

            start_xy: list[float] = []

            def observer(t: int, td: Any) -> None:
                if t == 0:  # where the learner starts (its track frame): with the paces, what makes a race its own
                    start_xy[:] = [round(float(v), 2) for v in core.fleet.pos[0, :2] - core.car_origins()[0]]
                if trace:
                    xy.append(core.fleet.pos[:, :2] - core.car_origins())
                    if t == 0:
                        seen[:], seen_sides[:] = tr.collisions, tr.contact_sides
                    for i in np.flatnonzero(tr.collisions > seen).tolist():  # a contact begun, by where the other car was
                        for k, d in enumerate((tr.contact_sides[i] - seen_sides[i]).tolist()):
                            hits.extend([(t, i, CONTACT_SIDES[k])] * d)
                    seen[:], seen_sides[:] = tr.collisions, tr.contact_sides

            book, _ = drive_episode(env, policy, laps, steps, observer=observer, on_reset=lambda: policy.reset(ctx))
            row = book.row(0, float(core.dt))
            members = tr.members[0]
            prog = core.dist_raced[members] - tr.start_back[members]
            pos = int(tr.race_pos[0])
            others = np.delete(prog, 0)
            if pos == 1:
                lead = float(prog[0] - others.max()) if len(others) else 0.0
            else:
                lead = float(prog[0] - prog.max())
            finished = bool(row["success"])
            rows.append({"policy": policy.name, "track": track, "surface": surface_name, "episode": e, "env_seed": env_seed,
                         "max_steps": steps, "opponents": int(tr.K), **row,
                         "position": pos if finished else None, "win": finished and pos == 1,
                         "overtakes": int(tr.overtakes[0]), "collisions": int(tr.collisions[0]),
                         **{f"contacts_{k}": int(v) for k, v in zip(CONTACT_SIDES, tr.contact_sides[0])},
                         "damage": float(tr.damage[0]), "gap_ahead_m": 0.0 if pos == 1 else float(tr.gap_ahead[0]),
                         "lead_m": lead, "start_position": 1 + int((tr.start_back[members][1:] < tr.start_back[members][0]).sum()),
                         "opponent_paces": [round(float(v), 4) for v in np.asarray(tr.pace)[: int(tr.K)]], "start_xy_m": start_xy})
            traces.append({"xy": np.asarray(xy), "hits": hits, "learner": 0} if trace else {})
    finally:
        env.close()
    return rows, traces


def race_summary(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One track's races: how many, wins, finishes, mean position (finishers), collisions and how they spread
    (``contact_free``: races without one; ``most_collisions``: the most in one race — a mean of 1.04 a race can be 12
    in one race and 13 over the other 23), overtakes, damage, gaps."""
    n = len(rows)
    fin = [r for r in rows if r["position"] is not None]

    def mean(xs: list[float]) -> float:
        return float(np.mean(xs)) if xs else math.nan

    return {"track": rows[0]["track"], "surface": rows[0]["surface"], "races": n, "opponents": rows[0]["opponents"],
            "finished": len(fin), "wins": sum(bool(r["win"]) for r in rows), "win_rate": sum(bool(r["win"]) for r in rows) / n,
            "mean_position": mean([r["position"] for r in fin]),
            "collisions_per_race": mean([r["collisions"] for r in rows]),
            "contact_free": sum(int(r["collisions"]) == 0 for r in rows),
            "most_collisions": max((int(r["collisions"]) for r in rows), default=0),
            **{f"contacts_{k}": sum(int(r.get(f"contacts_{k}", 0)) for r in rows) for k in CONTACT_SIDES},
            "overtakes_per_race": mean([r["overtakes"] for r in rows]),
            "damage_per_race": mean([r["damage"] for r in rows]),
            "mean_gap_ahead_m": mean([r["gap_ahead_m"] for r in fin]), "mean_lead_m": mean([r["lead_m"] for r in fin]),
            "scenarios": len({(r["track"], r["surface"], r.get("start_position"), tuple(r.get("start_xy_m") or ()),
                               tuple(r.get("opponent_paces") or ())) for r in rows})}


#: Where the other car was when a contact began (the race books' order).
CONTACT_SIDES = Traffic.CONTACT_SIDES

RACE_COLUMNS = ("track", "surface", "races", "finished", "wins", "mean pos", "collisions/race", "contact-free", "most coll.",
                "coll. ahead·alongside·behind", "overtakes/race",
                "damage/race [kN s]", "gap ahead [m]", "lead [m]", "scenarios")


def race_table(summaries: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the race table (one row per track, then ``all``)."""
    body = []
    for s in summaries:
        body.append([s["track"], s["surface"], str(s["races"]), f"{s['finished']}/{s['races']}", f"{s['wins']}/{s['races']}",
                     fmt_value(s["mean_position"]), fmt_value(s["collisions_per_race"]), f"{s['contact_free']}/{s['races']}",
                     str(s["most_collisions"]), "·".join(str(s[f"contacts_{k}"]) for k in CONTACT_SIDES),
                     fmt_value(s["overtakes_per_race"]), fmt_value(s["damage_per_race"]), fmt_value(s["mean_gap_ahead_m"], "{:.1f}"),
                     fmt_value(s["mean_lead_m"], "{:.1f}"), str(s["scenarios"])])
    return list(RACE_COLUMNS), body


def _race_job(spec: str | Policy, name: str, surface: str | None, tr: Mapping[str, Any], kw: dict) -> tuple[list, list]:
    """One track's races (a worker's task: the policy is loaded once per process)."""
    return run_race_cell(worker_policy(spec), name, surface, tr, **kw)


def evaluate_race(policy: str | Policy, tracks: str | Sequence[str], surfaces: Any = None, laps: int = 5, seed: int = 0,
                  out_dir: str | Path | None = None, *, episodes: int = 1, opponents: int = 3,
                  pace: float | Sequence[float] = 0.85, start: str = "grid", traffic: Mapping[str, Any] | None = None,
                  max_steps: int | None = None, env_kwargs: Mapping[str, Any] | None = None, plots: bool = True,
                  verbose: bool = True, workers: int = 1, side_gap_m: float | None = None) -> dict[str, Any]:
    """Races of ``policy`` against ``opponents`` experts at ``pace`` (or ``traffic``) on ``tracks`` x ``surfaces``;
    returns ``{"config", "policy", "summary", "episodes", "files"}`` and writes race.md / .csv / .json (and a
    top-down plot of the first race per track) to ``out_dir``. ``workers`` > 1: the tracks' races in that many
    processes (the same races, seeded per track and race, as in one process)."""
    t0 = time.perf_counter()
    if int(laps) < 1 or int(episodes) < 1:
        raise EvalError(f"laps and episodes must be >= 1, got laps={laps}, episodes={episodes}")
    tr = race_traffic(opponents, pace, start, traffic, side_gap_m)
    try:
        TrafficSpec.from_config(tr)
    except TrafficError as err:
        raise EvalError(str(err)) from None
    names, surfs = validate_grid(tracks, surfaces)
    pol = policy if isinstance(policy, Policy) else load_policy(policy)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    all_rows, summaries, files = [], [], []
    kw = {"laps": laps, "episodes": episodes, "seed": seed, "max_steps": max_steps, "env_kwargs": env_kwargs,
          "trace": plots and out is not None}
    cells = [(name, surface) for name in names for surface in surfs]
    spec = worker_spec(pol) if int(workers) > 1 else pol
    results = map_tasks(_race_job, [(spec, name, surface, tr, kw) for name, surface in cells], workers=int(workers))
    for (name, surface), (rows, traces) in zip(cells, results):
        for r in rows:
            r["policy"] = pol.name
        s = race_summary(rows)
        summaries.append(s)
        all_rows += rows
        if verbose:
            print(f"[torcsrl.evaluate] race {pol.name} on {name}/{s['surface']}: won {s['wins']}/{s['races']}, "
                  f"finished {s['finished']}/{s['races']}, {s['collisions_per_race']:.2f} collisions/race", file=sys.stderr)
        if out is not None and plots and traces and traces[0]:
            r0 = rows[0]
            title = (f"{pol.name} vs {r0['opponents']} on {name}: "
                     + (f"P{r0['position']}" if r0["position"] else "DNF") + f", {r0['collisions']} learner collision(s)")
            files.append(str(plot_race(_tracks.load(name, surface=surface), traces[0], out / f"race_{name}_{s['surface']}.png", title)))
    if len(summaries) > 1:
        tot = race_summary(all_rows)
        tot.update(track="all", surface="")
        summaries.append(tot)
    result = {"config": {"policy": pol.describe(), "tracks": names, "surfaces": surfs, "laps": int(laps),
                         "episodes": int(episodes), "seed": int(seed), "traffic": tr},
              "policy": pol.describe(), "summary": summaries, "episodes": all_rows, "wall_s": time.perf_counter() - t0}
    if out is not None:
        header, body = race_table(summaries)
        room = TrafficSpec.from_config(tr).side_gap_m
        md = [f"# Races: {pol.name}", "", f"{laps} laps against {tr.get('opponents')} opponent(s) ({tr.get('driver')}), "
              f"{episodes} race(s) per track, seed {seed}; scripted opponents give {room:g} m of room to a car alongside "
              f"(side_gap_m{'; 0: blind to it' if room == 0 else ''}).", "", markdown_table(header, body), "",
              "finished: races completed without leaving the track; wins: finished first; mean pos: over finished races; "
              "collisions: contacts begun with another car; contact-free: races without one; most coll.: the most in one race; coll. ahead·alongside·behind: the contacts by where the other car was; damage: summed contact impulse; gap ahead: along-track gap to "
              "the car ahead at the end; lead: margin over the next car (winners) or behind the leader (negative); scenarios: "
              "distinct starts raced (the learner's start position and the opponents' paces) — the physics is deterministic, "
              "so races from the same start are the same race.", ""]
        (out / "race.md").write_text("\n".join(md))
        write_csv(summaries, out / "race.csv")
        write_csv(all_rows, out / "race_episodes.csv")
        write_json(result, out / "race.json")
        result["files"] = [str(out / "race.md"), str(out / "race.csv"), str(out / "race_episodes.csv"), str(out / "race.json"), *files]
        if verbose:
            print(f"[torcsrl.evaluate] wrote {out} ({len(result['files'])} files)", file=sys.stderr)
    return result
