"""Time trials: a deterministic policy drives N laps per track; tables, JSON, CSV and pictures.

``python -m torcsrl.evaluate --policy SPEC --track set:heldout [--surface asphalt dirt] [--laps 10]``

For every track (and surface) the policy (:func:`torcsrl.policies.load_policy`: a checkpoint,
``reference``, ``expert``, ``sensor``, ``heuristic`` or ``random``) drives ``episodes`` episodes of ``laps``
laps (the env's ``lap_limit``: the episode ends, truncated, after the last lap; leaving the track,
driving backwards, stalling or flipping terminates it). Starts are seeded: episode ``e`` of
track ``t`` on surface ``u`` resets the env with ``seed_for(seed, "env", t, u, e)`` (the grid
start is the same every time; ``--start random`` draws the arc length from that seed). With a
degradation, its draws come from ``seed_for(seed, "degradation", name, severity, e)``, the same
for every policy (common random numbers).

Per track it reports (Summers 2022, Tables 7.1/7.2): laps completed of N, success (all N laps
without termination), fastest and mean lap [s] (mean over the flying laps 2..N), mean speed
[km/h] (distance / time), off-track events, steering oscillation (mean |delta steer| per step and
sign flips per km), the return, and the fastest lap relative to the scripted expert's fastest
lap and to the physical-limit lap time (:func:`torcsrl.envs.expert.limit_lap_time`).

Outputs (``out_dir``): ``evaluation.json`` (config, per-track summary, every episode),
``evaluation.csv`` (per track), ``episodes.csv``, ``evaluation.md`` (the table), one
``trajectory_<track>_<surface>.png`` per track (top-down path coloured by speed), and
``camera_<track>_<surface>.gif`` when the policy observes pixels.

Bookkeeping reads only the env's outputs: ``info`` (lap, lap times, distances) and the clean
``state`` (kept aside as ``state_clean`` before any degradation), never a degraded reading.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torcsrl import metrics
from torcsrl.policies import BUILTIN_POLICIES, EpisodeContext, Policy, PolicyError, load_policy
from torcsrl.utils.faults import OutputError, ignore_signals_in_worker, stop_pool, writable_folder

__all__ = [
    "Degradation",
    "EvalError",
    "evaluate",
    "run_cell",
    "run_episode",
    "seed_for",
    "parse_degradation",
    "validate_grid",
    "expert_reference",
    "plot_trajectory",
    "summary_table",
    "main",
]

#: Version of the episode protocol (part of every cache key: bump it when a metric's meaning changes).
PROTOCOL_VERSION = 1
#: Sensor keys in the env's canonical order.
_SENSOR_ORDER = ("rangefinder", "state", "telemetry", "pixels", "depth")


class EvalError(ValueError):
    """Bad evaluation input (unknown track, surface or degradation, empty grid): one line."""


# --------------------------------------------------------------------------------------------
# Seeds and degradations
# --------------------------------------------------------------------------------------------
def seed_for(seed: int, *parts: Any) -> int:
    """A 63-bit seed derived from ``seed`` and ``parts`` (stable across runs and processes)."""
    h = hashlib.sha256(repr((int(seed),) + tuple(str(p) for p in parts)).encode()).digest()
    return int.from_bytes(h[:8], "little") & ((1 << 63) - 1)


@dataclass(frozen=True)
class Degradation:
    """A degradation by registry name at a severity (0 = clean) with optional parameter overrides."""

    name: str = metrics.CLEAN
    severity: int = 0
    params: tuple[tuple[str, Any], ...] = ()

    @property
    def clean(self) -> bool:
        return self.name == metrics.CLEAN or self.severity == 0

    def label(self) -> str:
        return "clean" if self.clean else f"{self.name}@{self.severity}"

    def keys(self) -> tuple[str, ...]:
        """Observation keys the degradation can touch."""
        if self.clean:
            return ()
        from torcsrl.transforms import registry

        if self.name.startswith("weather."):
            comps = registry.PRESETS[self.name.split(".", 1)[1]]
            return tuple(sorted({k for q, _, _ in comps for k in registry.applies_to(q)}))
        return tuple(registry.applies_to(self.name))

    def build(self):
        """The TorchRL transform (keys the env lacks are skipped)."""
        from torcsrl.transforms import make_degradation

        if self.name.startswith("weather."):
            return make_degradation(self.name, severity=self.severity)
        return make_degradation(self.name, severity=self.severity, optional=True, **dict(self.params))


def _severity(v: Any, spec: Any) -> int:
    """An integer severity from ``v`` (of the degradation ``spec``), or EvalError."""
    try:
        if isinstance(v, bool) or (isinstance(v, float) and not v.is_integer()):
            raise ValueError
        return int(v)
    except (TypeError, ValueError):
        raise EvalError(f"degradation {spec!r}: severity {v!r} is not an integer; allowed: name or name@severity with "
                        "severity in 0..5 (0 = clean)") from None


def parse_degradation(d: Any, severity: int | None = None) -> Degradation:
    """A :class:`Degradation` from None, ``"name"``, ``"name@s"``, ``(name, s)``, a mapping
    ``{name, severity, **params}`` or a Degradation; checks the name and severity (EvalError)."""
    if d is None:
        return Degradation()
    if isinstance(d, Degradation):
        deg = d
    elif isinstance(d, str):
        name, _, s = d.partition("@")
        deg = Degradation(name, _severity(s if s else (severity if severity is not None else 3), d))
    elif isinstance(d, Mapping):
        m = dict(d)
        if "name" not in m:
            raise EvalError(f"a degradation mapping needs a name, got {d!r}; allowed: {{name, severity, **params}}")
        name = m.pop("name")
        s = _severity(m.pop("severity", severity if severity is not None else 3), d)
        deg = Degradation(name, s, tuple(sorted(m.items())))
    elif isinstance(d, (tuple, list)) and len(d) == 2:
        deg = Degradation(str(d[0]), _severity(d[1], d))
    else:
        raise EvalError(f"cannot read a degradation from {d!r}; use 'name', 'name@severity' or {{name, severity}}")
    if deg.name in (metrics.CLEAN, "clean"):
        return Degradation()
    if not 0 <= deg.severity <= 5:
        raise EvalError(f"severity must be in 0..5 (0 = clean), got {deg.severity} for {deg.name}")
    if deg.severity == 0:
        return Degradation()
    try:
        from torcsrl.transforms import registry
    except ImportError as err:
        raise EvalError(f"degradations need torcsrl.transforms, which cannot be imported ({err})") from None
    if deg.name.startswith("weather."):
        if deg.name.split(".", 1)[1] not in registry.PRESETS:
            raise EvalError(f"unknown weather preset {deg.name!r}; known: {', '.join('weather.' + p for p in registry.PRESETS)}")
    else:
        try:
            registry.degradation_class(deg.name)
        except ValueError as err:
            raise EvalError(str(err)) from None
    return deg


# --------------------------------------------------------------------------------------------
# One episode, one cell
# --------------------------------------------------------------------------------------------
def _base(env):
    return getattr(env, "base_env", env)


def env_sensors(policy: Policy, extra: Sequence[str] = ()) -> tuple[str, ...]:
    """The sensors the evaluation env needs: the policy's, ``state`` for the bookkeeping, ``extra``."""
    want = set(policy.env_overrides.get("sensors", ())) | {"state"} | set(extra)
    return tuple(k for k in _SENSOR_ORDER if k in want)


def make_cell_env(policy: Policy, track: str, surface: str | None, deg: Degradation, laps: int, max_steps: int,
                  env_kwargs: Mapping[str, Any] | None = None):
    """(env, transform or None): the race env for ``policy`` on ``track``, ``lap_limit=laps``,
    with the clean ``state`` kept as ``state_clean`` and ``deg`` on top when not clean."""
    from torcsrl.envs import make_env

    kw = dict(env_kwargs or {})
    kw.update({k: v for k, v in policy.env_overrides.items() if k != "sensors"})
    kw["sensors"] = env_sensors(policy)
    env = make_env(track=track, surface=surface, lap_limit=int(laps), max_steps=int(max_steps), **kw)
    if deg.clean:
        return env, None
    from torchrl.envs import Compose

    from torcsrl.transforms import KeepClean, LeanTransformedEnv

    transform = Compose(KeepClean(["state"]), deg.build())
    return LeanTransformedEnv(env, transform), transform


def default_max_steps(track_length_m: float, laps: int, dt: float = 0.02, min_speed_ms: float = 10.0,
                      min_lap_s: float = 60.0) -> int:
    """Step cap of an episode: ``laps`` laps at ``min_speed_ms`` (at least ``min_lap_s`` each)."""
    return int(math.ceil(laps * max(min_lap_s, track_length_m / min_speed_ms) / dt))


@torch.no_grad()
def run_episode(env, policy: Policy, ctx: EpisodeContext, laps: int, max_steps: int, *, trace: bool = False,
                frames: int = 0, observer: Callable[[int, Any], None] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Drive one episode (the env must be seeded already); returns (row, trace).

    ``row`` holds the episode's numbers (see :func:`run_cell`); ``trace`` (when asked) the
    per-step ``s`` [m], ``track_pos``, ``speed_kmh`` and up to ``frames`` camera frames.
    ``observer(step, td)`` sees every tensordict the policy sees (before it acts).
    """
    from torchrl.envs.utils import step_mdp

    from torcsrl.envs.race import TERMINATION_REASONS
    from torcsrl.envs.sensors import STATE_SLOTS

    i_tp, i_v = STATE_SLOTS.index("trackPos"), STATE_SLOTS.index("speedX_kmh")
    td = env.reset()
    policy.reset(ctx)
    steer, tpos, speed, s_hist, lap_times = [], [], [], [], []
    pix = []
    ret = 0.0
    prev_lap = 0
    nxt = td
    t = 0
    for t in range(int(max_steps)):
        if observer is not None:
            observer(t, td)
        if frames and len(pix) < frames and t % 5 == 0 and "pixels" in td.keys():  # 10 frames/s at 50 Hz
            pix.append(td.get("pixels").clone())
        td = policy(td)
        td = env.step(td)
        nxt = td.get("next")
        a = td.get("action").reshape(-1)
        steer.append(min(1.0, max(-1.0, float(a[0]))))  # the env clips actions to [-1, 1]
        ret += float(nxt.get("reward").reshape(-1)[0])
        st = nxt.get("state_clean", None)
        st = (st if st is not None else nxt.get("state")).reshape(-1)
        tpos.append(float(st[i_tp]))
        speed.append(float(st[i_v]))
        info = nxt.get("info")
        lap = int(info.get("lap").reshape(-1)[0])
        if trace:
            s_hist.append(float(info.get("distFromStart").reshape(-1)[0]))
        if lap > prev_lap:
            last = float(info.get("lastLapTime").reshape(-1)[0])
            if last > 0:  # 0: the lap was not timed (a random start's first, partial lap)
                lap_times.append(last)
            prev_lap = lap
        if bool(nxt.get("done").reshape(-1)[0]):
            break
        td = step_mdp(td)
    core = _base(env).core
    terminated = bool(nxt.get("terminated").reshape(-1)[0])
    truncated = bool(nxt.get("truncated").reshape(-1)[0])
    info = nxt.get("info")
    dist = float(info.get("distRaced").reshape(-1)[0])
    steps = t + 1
    time_s = steps * float(core.dt)
    flips = metrics.steering_oscillation(steer, dist)
    lt = metrics.lap_time_stats(lap_times)
    row = {
        "laps_target": int(laps),
        "laps": int(prev_lap),
        "success": bool(prev_lap >= laps and not terminated),
        "completed_lap": bool(prev_lap >= 1),
        "terminated": terminated,
        "termination": TERMINATION_REASONS[int(core.reason[0])] if terminated else "",
        "truncated": truncated,
        "finished": bool(info.get("finished").reshape(-1)[0]),
        "steps": steps,
        "time_s": time_s,
        "distance_m": dist,
        "return": ret,
        "lap_times": lap_times,
        "fastest_lap": lt["fastest_lap"],
        "mean_lap": lt["mean_lap"],
        "mean_speed_kmh": dist / time_s * 3.6 if time_s > 0 else math.nan,
        "off_track_events": metrics.off_track_events(tpos),
        "steer_abs_delta": flips[0],
        "steer_flips_per_km": flips[1],
    }
    tr = {}
    if trace:
        tr = {"s": np.asarray(s_hist), "track_pos": np.asarray(tpos), "speed_kmh": np.asarray(speed)}
    if pix:
        tr["frames"] = torch.stack(pix).numpy()
    return row, tr


def run_cell(policy: Policy, track: str, surface: str | None = None, degradation: Any = None, *, episodes: int = 1,
             laps: int = 1, seed: int = 0, max_steps: int | None = None, env_kwargs: Mapping[str, Any] | None = None,
             trace: bool = False, frames: int = 0, observer: Callable[[int, int, Any], None] | None = None,
             ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Run ``episodes`` episodes of ``policy`` on one (track, surface, degradation, severity) cell.

    Returns (rows, traces): one row per episode with ``policy``, ``track``, ``surface``,
    ``corruption``, ``severity``, ``episode``, the seeds and the numbers of :func:`run_episode`.
    ``observer(episode, step, td)`` sees what the policy sees.
    """
    from torcsrl.envs import tracks as _tracks

    deg = parse_degradation(degradation)
    geom = _tracks.load(track, surface=surface)
    surface_name = surface or geom.default_surface
    hz = {**dict(env_kwargs or {}), **policy.env_overrides}.get("control_hz", 50.0)
    dt = 1.0 / float(hz)
    steps = int(max_steps) if max_steps else default_max_steps(geom.length, laps, dt)
    env, transform = make_cell_env(policy, track, surface, deg, laps, steps, env_kwargs)
    core = _base(env).core
    rows, traces = [], []
    try:
        for e in range(int(episodes)):
            env_seed = seed_for(seed, "env", track, surface_name, e)
            deg_seed = seed_for(seed, "degradation", deg.name, deg.severity, e) if not deg.clean else None
            _base(env).set_seed(env_seed)
            if transform is not None:
                from torcsrl.transforms import seed_degradations

                seed_degradations(transform, deg_seed)
            ctx = EpisodeContext(track=core.car_tracks[0], seed=seed_for(seed, "policy", track, surface_name, e), episode=e,
                                 dt=float(core.dt))
            obs = (lambda t, td, _e=e: observer(_e, t, td)) if observer is not None else None
            row, tr = run_episode(env, policy, ctx, laps, steps, trace=trace and e == 0, frames=frames if e == 0 else 0,
                                  observer=obs)
            rows.append({"policy": policy.name, "policy_fingerprint": policy.fingerprint, "track": track,
                         "surface": surface_name, "corruption": deg.name if not deg.clean else metrics.CLEAN,
                         "severity": 0 if deg.clean else deg.severity, "episode": e, "env_seed": env_seed,
                         "degradation_seed": deg_seed, "max_steps": steps, **row})
            traces.append(tr)
    finally:
        env.close()
    return rows, traces


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------
def validate_grid(tracks: Sequence[str] | str, surfaces: Sequence[str | None] | str | None) -> tuple[list[str], list[str | None]]:
    """Resolve track names and sets (``set:heldout``) and check surfaces; EvalError (one line)."""
    from torcsrl.envs import surfaces as _surf
    from torcsrl.envs import tracks as _tracks

    if isinstance(tracks, str):
        tracks = [tracks]
    if not tracks:
        raise EvalError("no track given (empty grid); name a track or a set such as set:heldout")
    try:
        names = _tracks.resolve(list(tracks))
        for n in names:
            _tracks.load(n)
    except ValueError as err:
        raise EvalError(str(err)) from None
    if not names:
        raise EvalError(f"the tracks {list(tracks)} resolve to no track (empty grid)")
    seen: list[str] = []
    for n in names:
        if n not in seen:
            seen.append(n)
    if surfaces is None or isinstance(surfaces, str):
        surfaces = [surfaces]
    surfaces = list(surfaces) or [None]
    for s in surfaces:
        if s is not None and s not in _surf.ROAD_SURFACES:
            raise EvalError(f"unknown surface {s!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
    return seen, surfaces


def check_policy_env(policy: Policy, track: str, env_kwargs: Mapping[str, Any] | None = None) -> None:
    """Build one env for ``policy`` and check it fits (PolicyError, one line) — before any work."""
    env, _ = make_cell_env(policy, track, None, Degradation(), 1, 10, env_kwargs)
    try:
        policy.check_env(env)
    finally:
        env.close()


# --------------------------------------------------------------------------------------------
# References: the expert and the physical limit
# --------------------------------------------------------------------------------------------
_EXPERT_CACHE: dict[tuple[str, str | None, int], dict[str, float]] = {}


def expert_reference(track: str, surface: str | None = None, laps: int = 2) -> dict[str, Any]:
    """``{"expert_lap": fastest expert lap [s], "limit_lap": physical limit [s], "note": ...}``.

    The expert drives ``laps`` laps through its own API (:func:`torcsrl.envs.expert.drive`);
    NaN (with a note) when the expert module is missing or the expert leaves the track.
    """
    key = (track, surface, laps)
    if key in _EXPERT_CACHE:
        return dict(_EXPERT_CACHE[key])
    out: dict[str, Any] = {"expert_lap": math.nan, "limit_lap": math.nan, "note": ""}
    try:
        from torcsrl.envs import expert
        from torcsrl.envs import tracks as _tracks

        t = _tracks.load(track, surface=surface)
        out["limit_lap"] = float(expert.limit_lap_time(t))
        r = expert.drive(t, laps=laps)
        if r.lap_times:
            out["expert_lap"] = float(min(r.lap_times))
        if not r.completed:
            out["note"] = f"expert did not complete {laps} laps of {track} ({len(r.lap_times)} done)"
    except Exception as err:  # noqa: BLE001 - references are optional; say why they are missing
        out["note"] = f"expert reference unavailable: {type(err).__name__}: {err}"
    _EXPERT_CACHE[key] = dict(out)
    return out


# --------------------------------------------------------------------------------------------
# Summaries, tables, pictures
# --------------------------------------------------------------------------------------------
def summarise_track(rows: Sequence[Mapping[str, Any]], ref: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Per-track numbers over its episodes (means, except fastest lap = the minimum)."""
    r0 = rows[0]
    lap_means = [r["mean_lap"] for r in rows if not math.isnan(r["mean_lap"])]
    fastest = min((r["fastest_lap"] for r in rows if not math.isnan(r["fastest_lap"])), default=math.nan)
    out = {
        "track": r0["track"], "surface": r0["surface"], "corruption": r0["corruption"], "severity": r0["severity"],
        "episodes": len(rows), "laps_target": r0["laps_target"],
        "laps": float(np.mean([r["laps"] for r in rows])),
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "fastest_lap": fastest,
        "mean_lap": float(np.mean(lap_means)) if lap_means else math.nan,
        "mean_speed_kmh": float(np.mean([r["mean_speed_kmh"] for r in rows])),
        "off_track_events": int(sum(r["off_track_events"] for r in rows)),
        "terminations": ", ".join(sorted({r["termination"] for r in rows if r["termination"]}
                                         | ({"step limit"} if any(r["truncated"] and not r["finished"] for r in rows) else set()))),
        "steer_abs_delta": float(np.mean([r["steer_abs_delta"] for r in rows])),
        "steer_flips_per_km": float(np.nanmean([r["steer_flips_per_km"] for r in rows])) if any(
            not math.isnan(r["steer_flips_per_km"]) for r in rows) else math.nan,
        "return": float(np.mean([r["return"] for r in rows])),
    }
    ref = ref or {}
    out["expert_lap"] = float(ref.get("expert_lap", math.nan))
    out["limit_lap"] = float(ref.get("limit_lap", math.nan))
    out["vs_expert"] = fastest / out["expert_lap"] if out["expert_lap"] > 0 else math.nan
    out["vs_limit"] = fastest / out["limit_lap"] if out["limit_lap"] > 0 else math.nan
    return out


def _f(x: Any, fmt: str = "{:.2f}", none: str = "–") -> str:
    if x is None:
        return none
    try:
        if isinstance(x, float) and math.isnan(x):
            return none
        if isinstance(x, float) and math.isinf(x):
            return "∞" if x > 0 else "−∞"
    except TypeError:
        pass
    return fmt.format(x)


def summary_table(summaries: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of the time-trial table (Summers's Tables 7.1/7.2 layout, plus ours)."""
    header = ["Track", "Surface", "Laps", "Fastest lap [s]", "Mean lap [s]", "Success", "Mean speed [km/h]",
              "vs expert", "vs limit", "Off-track", "|Δsteer|", "Flips/km", "Return"]
    body = []
    for s in summaries:
        laps = f"{s['laps']:.0f}/{s['laps_target']}" if s["episodes"] == 1 else f"{s['laps']:.1f}/{s['laps_target']}"
        succ = ("yes" if s["success_rate"] == 1 else "no") if s["episodes"] == 1 else f"{100 * s['success_rate']:.0f}%"
        if s.get("terminations"):
            succ += f" ({s['terminations']})"
        body.append([s["track"], s["surface"], laps, _f(s["fastest_lap"]), _f(s["mean_lap"]), succ, _f(s["mean_speed_kmh"], "{:.1f}"),
                     _f(s["vs_expert"], "{:.3f}"), _f(s["vs_limit"], "{:.3f}"), str(s["off_track_events"]),
                     _f(s["steer_abs_delta"], "{:.3f}"), _f(s["steer_flips_per_km"], "{:.1f}"), _f(s["return"], "{:.0f}")])
    return header, body


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-flavoured Markdown table."""
    esc = [[str(c).replace("|", "\\|") for c in r] for r in [header, *rows]]
    lines = ["| " + " | ".join(esc[0]) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in esc[1:]]
    return "\n".join(lines)


def plot_trajectory(track, trace: Mapping[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """Top-down PNG: track edges, the path coloured by speed [km/h] (colour bar), start line, and a
    red cross where the episode was terminated (if it was)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    s, tp, v = (np.asarray(trace[k], dtype=float) for k in ("s", "track_pos", "speed_kmh"))
    wl, wr = track.width(s)
    d = np.where(tp >= 0, tp * wl, tp * wr)
    xy = np.asarray(track.to_world(s, d), dtype=float).reshape(-1, 2)
    span = np.ptp(np.vstack([track.left_edge, track.right_edge]), axis=0)  # [m] x, y extent
    fig, ax = plt.subplots(figsize=(7.5, float(np.clip(6.5 * span[1] / max(span[0], 1.0) + 1.2, 3.0, 9.0))))
    for edge in (track.left_edge, track.right_edge):
        closed = np.vstack([edge, edge[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.35", lw=0.8)
    start = np.stack([track.to_world(0.0, float(track.w_left[0])), track.to_world(0.0, -float(track.w_right[0]))])
    ax.plot(start[:, 0], start[:, 1], color="k", lw=2.5)
    if len(xy) > 1:
        segs = np.stack([xy[:-1], xy[1:]], axis=1)
        lc = LineCollection(segs, cmap="plasma", linewidths=2.0)
        lc.set_array(v[1:])
        lc.set_clim(0, max(50.0, float(np.nanmax(v))))
        ax.add_collection(lc)
        from mpl_toolkits.axes_grid1 import make_axes_locatable

        ax.set_aspect("equal")
        ax.autoscale_view()
        cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.1)
        fig.colorbar(lc, cax=cax, label="speed [km/h]")
        if trace.get("terminated"):
            ax.plot(xy[-1, 0], xy[-1, 1], "x", color="red", ms=14, mew=3, label="terminated")
            ax.legend(loc="upper right")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or track.name, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def write_gif(frames: np.ndarray, path: str | Path, fps: int = 10) -> Path | None:
    """Animated GIF from frames ``[T, 3, H, W]`` uint8 (PIL); None when PIL is missing."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - PIL ships with matplotlib
        return None
    imgs = []
    for f in frames:
        a = np.transpose(np.asarray(f), (1, 2, 0)).astype(np.uint8)
        scale = max(1, 160 // max(a.shape[0], 1))
        img = Image.fromarray(a).resize((a.shape[1] * scale, a.shape[0] * scale), Image.NEAREST)
        imgs.append(img)
    if not imgs:
        return None
    path = Path(path)
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=int(1000 / fps), loop=0)
    return path


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        if math.isnan(x):
            return None
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return x
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    return x


def write_json(obj: Any, path: str | Path) -> Path:
    """Strict JSON (NaN -> null, inf -> "inf"), written atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_jsonable(obj), indent=1, allow_nan=False))
    tmp.replace(path)
    return path


def write_csv(rows: Sequence[Mapping[str, Any]], path: str | Path, columns: Sequence[str] | None = None) -> Path:
    cols = list(columns or (rows[0].keys() if rows else []))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (";".join(f"{v:.3f}" for v in r[k]) if isinstance(r.get(k), list) else _jsonable(r.get(k))) for k in cols})
    return Path(path)


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
    tasks = [(pol.spec if pol.spec in BUILTIN_POLICIES or Path(pol.spec).is_file() else pol, pol.name, name, surface, deg,
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
    if isinstance(policy, str):
        if policy not in _POLICIES:
            _POLICIES[policy] = load_policy(policy)
        pol = _POLICIES[policy]
    else:
        pol = policy
    pol.name = name
    rows, traces = run_cell(pol, track, surface, deg, **kw)
    ref = expert_reference(track, surface, expert_laps) if expert_laps else {}
    return rows, traces, ref


_POLICIES: dict[str, Policy] = {}


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


def read_evaluations(root: str | Path) -> list[dict[str, Any]]:
    """Every ``evaluation.json`` under ``root`` (e.g. a Hydra multirun folder: one per job), loaded."""
    out = []
    for p in sorted(Path(root).rglob("evaluation.json")):
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as err:
            print(f"[torcsrl] skipping unreadable {p} ({type(err).__name__})", file=sys.stderr)
            continue
        d["_path"] = str(p)
        out.append(d)
    return out


# --------------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    from torcsrl.utils.faults import exit_code, graceful_termination, os_error_line

    parser = argparse.ArgumentParser(prog="python -m torcsrl.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", default="expert", help="checkpoint path, 'reference', 'expert', 'sensor', 'heuristic' or 'random'")
    parser.add_argument("--track", "--tracks", dest="track", nargs="+", default=["set:heldout"], help="track names and/or sets (set:heldout)")
    parser.add_argument("--surface", "--surfaces", dest="surface", nargs="+", default=None, help="road surfaces (default: each track's own)")
    parser.add_argument("--laps", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--degradation", default=None, help="degradation name (e.g. rangefinder.fog) or name@severity")
    parser.add_argument("--severity", type=int, default=None, help="severity 1..5 of --degradation (default 3)")
    parser.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default: N laps at 10 m/s)")
    parser.add_argument("--start", choices=("grid", "random"), default="grid", help="start on the line or at a seeded random arc length")
    parser.add_argument("--expert-laps", type=int, default=2, help="laps for the expert's reference time (0: skip)")
    parser.add_argument("--no-plots", action="store_true")
    parser.add_argument("--workers", type=int, default=1, help="processes driving tracks in parallel")
    parser.add_argument("--out", default=None, help="output folder (default outputs/evaluate/<policy>/<time>)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        with graceful_termination():
            deg = parse_degradation(args.degradation, args.severity) if args.degradation else None
            out = args.out or str(Path("outputs") / "evaluate" / Path(str(args.policy)).stem / time.strftime("%Y-%m-%d_%H-%M-%S"))
            res = evaluate(args.policy, args.track, args.surface, laps=args.laps, seed=args.seed, out_dir=out, degradation=deg,
                           episodes=args.episodes, max_steps=args.max_steps, env_kwargs={"start": args.start},
                           expert_laps=args.expert_laps, plots=not args.no_plots, workers=args.workers)
    except (EvalError, PolicyError) as err:
        print(f"torcsrl.evaluate: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"torcsrl.evaluate: error: {os_error_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        print(f"torcsrl.evaluate: error: stopped by {getattr(err, 'name', 'SIGINT')}; its worker processes were stopped "
              "(run it again for the full evaluation)", file=sys.stderr)
        return exit_code(err)
    print((Path(out) / "evaluation.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
