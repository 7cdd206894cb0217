"""The episode protocol: drive a deterministic policy for N laps from the grid, one implementation.

Everything that decides what an episode *is* lives here and in :mod:`torcsrl.evaluate.spec` (the inputs,
checked before anything heavy loads) and nowhere else: the seeds (:func:`~torcsrl.evaluate.spec.seed_for`: env
starts, degradation draws and the policy's own randomness, per (track, surface, episode) and per (degradation,
severity, episode), the same for every policy: common random numbers), the step cap
(:func:`~torcsrl.evaluate.spec.default_max_steps`), lap accounting and termination reasons (:class:`EpisodeBook`:
per car, from the env's ``info`` and the clean ``state``, never a degraded reading), and the env of a cell
(:func:`make_cell_env`).

:func:`run_episode` drives one car; :func:`torcsrl.evaluate.batched.run_batch` drives many
episodes as cars of one batched env with the same :class:`EpisodeBook` (tested equal, episode for
episode); ``torcsrl.train.validate`` and the report use them too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torchrl.envs import Compose
from torchrl.envs.utils import step_mdp

from torcsrl import metrics
from torcsrl.envs import expert, make_env
from torcsrl.envs import tracks as _tracks
from torcsrl.envs.race import TERMINATION_REASONS
from torcsrl.envs.sensors import STATE_SLOTS
from torcsrl.evaluate.spec import Degradation, default_max_steps, parse_degradation, seed_for
from torcsrl.policies import EpisodeContext, Policy
from torcsrl.transforms import KeepClean, LeanTransformedEnv, seed_degradations

#: Sensor keys in the env's canonical order.
_SENSOR_ORDER = ("rangefinder", "state", "telemetry", "opponents", "pixels", "depth")


# --------------------------------------------------------------------------------------------
# One episode, one cell
# --------------------------------------------------------------------------------------------
def base_env(env):
    """The race env under a transformed env (``env`` itself when it is not one)."""
    return getattr(env, "base_env", env)


def env_sensors(policy: Policy, extra: Sequence[str] = ()) -> tuple[str, ...]:
    """The sensors the evaluation env needs: the policy's, ``state`` for the bookkeeping, ``extra``."""
    want = set(policy.env_overrides.get("sensors", ())) | {"state"} | set(extra)
    return tuple(k for k in _SENSOR_ORDER if k in want)


def make_cell_env(policy: Policy, track: str, surface: str | None, deg: Degradation, laps: int, max_steps: int,
                  env_kwargs: Mapping[str, Any] | None = None):
    """(env, transform or None): the race env for ``policy`` on ``track``, ``lap_limit=laps``,
    with the clean ``state`` kept as ``state_clean`` and ``deg`` on top when not clean."""
    kw = dict(env_kwargs or {})
    kw.update({k: v for k, v in policy.env_overrides.items() if k != "sensors"})
    kw["sensors"] = env_sensors(policy)
    env = make_env(track=track, surface=surface, lap_limit=int(laps), max_steps=int(max_steps), **kw)
    if deg.clean:
        return env, None
    transform = Compose(KeepClean(["state"]), deg.build())
    return LeanTransformedEnv(env, transform), transform


class EpisodeBook:
    """The bookkeeping of N episodes driven side by side (N = 1: one car), one control step at a time.

    Per car: the return (float64 sum of the float32 rewards, in step order), the steering
    actually applied (clipped to [-1, 1]), trackPos and speed from the clean ``state``, the
    distance along the lap (``trace``), laps completed and the timed laps (a lap counts when
    ``info/lap`` rises; its time is ``info/lastLapTime``, 0 = untimed, e.g. a random start's first
    lap), and, once the car is done, its final numbers (:meth:`rows`). A car's books stop at its
    first ``done``; later steps of the batch do not touch them.
    """

    def __init__(self, n: int, laps: int, trace: bool = False) -> None:
        self.n, self.laps, self.trace = int(n), int(laps), bool(trace)
        self._i_tp, self._i_v = STATE_SLOTS.index("trackPos"), STATE_SLOTS.index("speedX_kmh")
        self.steer: list[list[float]] = [[] for _ in range(self.n)]
        self.tpos: list[list[float]] = [[] for _ in range(self.n)]
        self.speed: list[list[float]] = [[] for _ in range(self.n)]
        self.s_hist: list[list[float]] = [[] for _ in range(self.n)]
        self.lap_times: list[list[float]] = [[] for _ in range(self.n)]
        self.ret = [0.0] * self.n
        self.prev_lap = [0] * self.n
        self.steps = [0] * self.n
        self.end: list[dict[str, Any] | None] = [None] * self.n
        self.active = np.ones(self.n, dtype=bool)

    def record(self, action: Any, nxt: Any, reason: Sequence[int] | np.ndarray | None, rows: slice | None = None) -> np.ndarray:
        """Book one step of every car still running from the step's ``action [N, A]`` and its
        ``"next"`` tensordict (reward, clean or plain ``state``, lap keys, done flags);
        ``reason [N]``: the env's termination reason codes (None: not known). Returns the cars
        done at this step. Envs without a ``state`` or lap keys (the toy env) book what they have.
        ``rows``: the batch rows of this book's cars (a slice of a bigger batch; None: all of it)."""
        return self.record_lists(self.step_lists(action, nxt, self.trace), nxt, reason, rows)

    @staticmethod
    def step_lists(action: Any, nxt: Any, trace: bool = False) -> tuple:
        """What :meth:`record_lists` reads from one step, as Python lists over the whole batch
        (extracted once per step, then shared by the books of every group of cars)."""
        total = nxt.get("done").numel()
        a = action.reshape(total, -1)[:, 0].tolist()
        rew = nxt.get("reward").reshape(total).tolist()
        st = nxt.get("state_clean", None)
        st = st if st is not None else nxt.get("state", None)
        if st is not None:
            st = st.reshape(total, -1)
            tp, v = st[:, STATE_SLOTS.index("trackPos")].tolist(), st[:, STATE_SLOTS.index("speedX_kmh")].tolist()
        else:
            tp = v = [math.nan] * total
        lap_key, time_key = lap_keys(nxt)
        lap = nxt.get(lap_key).reshape(total).tolist() if lap_key is not None else [0] * total
        last = nxt.get(time_key).reshape(total).tolist() if time_key is not None else [0.0] * total
        dfs = nxt.get(("info", "distFromStart")).reshape(total).tolist() if trace else None
        done = nxt.get("done").reshape(total).tolist()
        return total, a, rew, tp, v, lap, last, dfs, done

    def record_lists(self, lists: tuple, nxt: Any, reason: Sequence[int] | np.ndarray | None,
                     rows: slice | None = None) -> np.ndarray:
        """:meth:`record` from :meth:`step_lists` (this book's cars are ``rows`` of the batch)."""
        total, a, rew, tp, v, lap, last, dfs, done = lists
        off = 0 if rows is None else rows.start
        newly = []
        for i in np.flatnonzero(self.active).tolist():
            j = off + i
            self.steer[i].append(min(1.0, max(-1.0, a[j])))  # the env clips actions to [-1, 1]
            self.ret[i] += rew[j]
            self.tpos[i].append(tp[j])
            self.speed[i].append(v[j])
            if dfs is not None:
                self.s_hist[i].append(dfs[j])
            self.steps[i] += 1
            if lap[j] > self.prev_lap[i]:
                if last[j] > 0:  # 0: the lap was not timed (a random start's first, partial lap)
                    self.lap_times[i].append(last[j])
                self.prev_lap[i] = lap[j]
            if done[j]:
                newly.append(i)
        if newly:
            self._end(nxt, reason, newly, rows, total)
        return np.asarray(newly, dtype=np.int64)

    def _end(self, nxt: Any, reason: Sequence[int] | np.ndarray | None, cars: Sequence[int], rows: slice | None = None,
             total: int | None = None) -> None:
        n = self.n
        total = n if total is None else total
        rows = slice(0, total) if rows is None else rows

        def col(t: torch.Tensor) -> list:
            return t.reshape(total)[rows].tolist()

        info = nxt.get("info", None)
        term = col(nxt.get("terminated"))
        trunc = col(nxt.get("truncated"))
        fin = col(info.get("finished")) if info is not None else [False] * n
        dist = col(info.get("distRaced")) if info is not None else [math.nan] * n
        why_rows = list(np.asarray(reason).reshape(-1)[rows]) if reason is not None else None
        for i in cars:
            why = TERMINATION_REASONS[int(why_rows[i])] if why_rows is not None else "terminated"
            self.end[i] = {"terminated": bool(term[i]), "truncated": bool(trunc[i]), "finished": bool(fin[i]),
                           "distance_m": dist[i], "termination": why if term[i] else ""}
            self.active[i] = False

    def close(self, nxt: Any, reason: Sequence[int] | np.ndarray | None, rows: slice | None = None) -> None:
        """End the books of the cars still running (the step cap ran out) at the last step."""
        if self.active.any():
            total = nxt.get("done").numel()
            self._end(nxt, reason, np.flatnonzero(self.active).tolist(), rows, total)

    def row(self, i: int, dt: float) -> dict[str, Any]:
        """Car ``i``'s episode numbers (see :func:`run_cell`)."""
        e = self.end[i]
        if e is None:
            raise RuntimeError(f"episode of car {i} has not ended")
        steps = self.steps[i]
        time_s = steps * float(dt)
        dist = e["distance_m"]
        flips = metrics.steering_oscillation(self.steer[i], dist)
        lt = metrics.lap_time_stats(self.lap_times[i])
        laps = self.prev_lap[i]
        return {
            "laps_target": self.laps,
            "laps": int(laps),
            "success": bool(laps >= self.laps and not e["terminated"]),
            "completed_lap": bool(laps >= 1),
            "terminated": e["terminated"],
            "termination": e["termination"],
            "truncated": e["truncated"],
            "finished": e["finished"],
            "steps": steps,
            "time_s": time_s,
            "distance_m": dist,
            "return": self.ret[i],
            "lap_times": list(self.lap_times[i]),
            "fastest_lap": lt["fastest_lap"],
            "mean_lap": lt["mean_lap"],
            "mean_speed_kmh": dist / time_s * 3.6 if time_s > 0 else math.nan,
            "off_track_events": metrics.off_track_events(self.tpos[i]),
            "steer_abs_delta": flips[0],
            "steer_flips_per_km": flips[1],
        }

    def trace_of(self, i: int) -> dict[str, np.ndarray]:
        return {"s": np.asarray(self.s_hist[i]), "track_pos": np.asarray(self.tpos[i]), "speed_kmh": np.asarray(self.speed[i])}


def lap_keys(td: Any) -> tuple:
    """(completed-laps key, last-lap-time key) of an env's output: the race env's ``info`` entries or the
    toy env's ``laps`` / ``lap_time``; ``None`` where absent."""
    keys = td.keys(include_nested=True)
    if ("info", "lap") in keys:
        return ("info", "lap"), ("info", "lastLapTime")
    return ("laps" if "laps" in keys else None), ("lap_time" if "lap_time" in keys else None)


@torch.no_grad()
def drive_episode(env, act: Callable[[Any], Any], laps: int, max_steps: int, *, trace: bool = False, frames: int = 0,
                  observer: Callable[[int, Any], None] | None = None, on_reset: Callable[[], None] | None = None,
                  ) -> tuple[EpisodeBook, list[torch.Tensor]]:
    """THE episode: reset ``env`` (seeded already), then ``act(td)`` (writes ``"action"``) and step until
    the env says done or ``max_steps`` steps; every step booked by an :class:`EpisodeBook`. Returns the
    book and up to ``frames`` camera frames (every 5th step). ``on_reset()`` runs right after the reset
    (a policy's episode start); ``observer(step, td)`` sees what the policy sees. One implementation for
    :func:`run_episode` (evaluate, report) and ``torcsrl.train.validate``; the batched path
    (:func:`torcsrl.evaluate.batched.run_batch`) books its cars with the same :class:`EpisodeBook`."""
    td = env.reset()
    if on_reset is not None:
        on_reset()
    core = getattr(base_env(env), "core", None)
    book = EpisodeBook(1, laps, trace=trace)
    pix: list[torch.Tensor] = []
    nxt = td
    for t in range(int(max_steps)):
        if observer is not None:
            observer(t, td)
        if frames and len(pix) < frames and t % 5 == 0 and "pixels" in td.keys():  # 10 frames/s at 50 Hz
            pix.append(td.get("pixels").clone())
        td = act(td)
        td = env.step(td)
        nxt = td.get("next")
        if len(book.record(td.get("action"), nxt, core.reason if core is not None else None)):
            break
        td = step_mdp(td)
    book.close(nxt, core.reason if core is not None else None)
    return book, pix


def run_episode(env, policy: Policy, ctx: EpisodeContext, laps: int, max_steps: int, *, trace: bool = False,
                frames: int = 0, observer: Callable[[int, Any], None] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Drive one episode of ``policy`` (the env must be seeded already); returns (row, trace).

    ``row`` holds the episode's numbers (see :func:`run_cell`); ``trace`` (when asked) the
    per-step ``s`` [m], ``track_pos``, ``speed_kmh`` and up to ``frames`` camera frames.
    ``observer(step, td)`` sees every tensordict the policy sees (before it acts).
    """
    book, pix = drive_episode(env, policy, laps, max_steps, trace=trace, frames=frames, observer=observer,
                              on_reset=lambda: policy.reset(ctx))
    row = book.row(0, float(base_env(env).core.dt))
    tr = book.trace_of(0) if trace else {}
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
    deg = parse_degradation(degradation)
    geom = _tracks.load(track, surface=surface)
    surface_name = surface or geom.default_surface
    hz = {**dict(env_kwargs or {}), **policy.env_overrides}.get("control_hz", 50.0)
    dt = 1.0 / float(hz)
    steps = int(max_steps) if max_steps else default_max_steps(geom.length, laps, dt)
    env, transform = make_cell_env(policy, track, surface, deg, laps, steps, env_kwargs)
    core = base_env(env).core
    rows, traces = [], []
    try:
        for e in range(int(episodes)):
            env_seed = seed_for(seed, "env", track, surface_name, e)
            deg_seed = seed_for(seed, "degradation", deg.name, deg.severity, e) if not deg.clean else None
            base_env(env).set_seed(env_seed)
            if transform is not None:
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


