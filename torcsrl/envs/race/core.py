"""The race simulation core and its gymnasium face.

:class:`RaceCore` is the one simulation every face shares: N cars in one pybullet client (cars
never collide; each has its own track, progress and episode), TORCS-style sensors, named reward
terms, lap bookkeeping and the episode rules. :class:`RaceEnv` is its gymnasium face (one car);
:class:`torcsrl.envs.batched.TorchRaceEnv` its TorchRL face (one car or a batch).

One control step (the template method, :meth:`RaceCore.step`):
act (sanitise) → physics substeps → locate (Frenet projection, surfaces under the wheels) →
bookkeeping (progress, laps) → observe (sensors) → reward terms → terminated → truncated → info.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from torcsrl.utils.bullet import pybullet as p
from gymnasium import spaces
from gymnasium.utils import EzPickle

from torcsrl.envs import surfaces as _surf
from torcsrl.envs import tracks as _tracks
from torcsrl.envs.tracks.procedural import ProceduralSpec
from torcsrl.envs.rewards import REWARD_TERMS, Reward
from torcsrl.envs.sensors import (MS_TO_KMH, RANGEFINDER_ANGLES_DEG, RANGE_M, STATE_BOUNDS, STATE_SLOTS, TELEMETRY_SLOTS,
                                  Rangefinder, check_sensors)
from torcsrl.envs.traffic import (OPPONENT_RANGE_M, OPPONENT_RGBA, OPPONENT_SECTORS, RACE_INFO_KEYS, Traffic, TrafficSpec,
                                  opponent_sectors)
from torcsrl.envs.vehicle import BACKENDS, CarFleet, VehicleParams, make_ground
from torcsrl.envs.world import TRACK_SPACING_M
from torcsrl.utils.seq import as_list

ACTION_MODES = ("combined", "separate")
START_MODES = ("grid", "random")
#: Up to this many cars, cars are followed along their tracks chord by chord (the exact walk of
#: :meth:`Track.track_point`); beyond, located by the windowed vectorised projection.
SCALAR_LOCATE_MAX_CARS = 8
#: Up to this many cars the walk runs car by car in plain Python; beyond, vectorised over the cars
#: (:meth:`Track.track_points`, the same numbers).
PYTHON_WALK_MAX_CARS = 4
#: Keys of the per-car bookkeeping reported in ``info`` (TORCS names; SI units).
#: ``surfaceMu`` [-] is the mean friction coefficient under the car's four wheels (surface x tyre): privileged
#: knowledge for teachers (a camera sees the surface, no TORCS sensor does); no observation carries it.
INFO_KEYS: tuple[str, ...] = ("distFromStart", "distRaced", "lap", "curLapTime", "lastLapTime", "bestLapTime", "surfaceMu")
TERMINATION_REASONS: tuple[str, ...] = ("", "off_track", "backwards", "no_progress", "flipped")


def wrap_deltas(s_new: np.ndarray, s_old: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """:meth:`Track.wrap_delta` of each car on its own track (lap lengths ``lengths``), vectorised: the same
    operations elementwise, so each entry has the bits ``car_tracks[i].wrap_delta(s_new[i], s_old[i])`` has."""
    half = 0.5 * lengths
    return np.mod(s_new - s_old + half, lengths) - half


def episode_setting_problems(**settings: Any) -> list[tuple[str, str]]:
    """``(key, message)`` for each of ``spawn_jitter``, ``offtrack_grace_s``, ``no_progress_s``,
    ``backwards_m`` given in ``settings`` that :class:`RaceCore` cannot use (also run by torcsrl.config)."""
    out: list[tuple[str, str]] = []

    def number(v: Any) -> float | None:
        try:
            x = float(v)
        except (TypeError, ValueError):
            return None
        return x if math.isfinite(x) else None

    if "spawn_jitter" in settings and settings["spawn_jitter"] is not None:
        sj = settings["spawn_jitter"]
        vals = [number(v) for v in sj] if isinstance(sj, (list, tuple)) else []
        if len(vals) != 2 or any(v is None or v < 0 for v in vals):
            out.append(("spawn_jitter", f"must be two finite half-ranges [d_m, yaw_rad] >= 0, got {sj!r}; allowed: e.g. [1.0, 0.1]"))
    for key, none_ok in (("offtrack_grace_s", False), ("no_progress_s", True), ("backwards_m", False)):
        if key not in settings or (settings[key] is None and none_ok):
            continue
        v = number(settings[key])
        if v is None or v < 0:
            out.append((key, f"must be a finite number >= 0, got {settings[key]!r}; allowed: [0, inf)"
                             + (" or None (never)" if none_ok else "")))
    return out


class RaceCore:
    """N cars racing on their own tracks in one pybullet world.

    Args:
        track: a track name, ``set:<name>``, ``gen-<seed>``, or a list of those. With several,
            each car draws its track for every episode from the env's seed.
        surface: road surface for every track (``None``: each track's own), or a list to draw one
            per episode (domain randomisation).
        num_cars: number of cars N.
        sensors: observation keys, from ``rangefinder``, ``state``, ``telemetry``, ``pixels``, ``depth``.
        reward: a reward preset name or term weights (see :mod:`torcsrl.envs.rewards`).
        reward_scale: factor on the summed reward.
        max_steps: episode step limit (truncation) [control steps].
        lap_limit: end the episode (truncated, ``finished``) after this many laps; ``None``: off.
        start: ``grid`` (on the start line) or ``random`` (uniform s along the lap).
        spawn_jitter: ``(d_m, yaw_rad)`` uniform half-ranges added to the spawn pose.
        offtrack_grace_s: time the car may spend off the track before the episode terminates [s].
        no_progress_s: terminate when the car has not set a new furthest distance for this long
            [s]; ``None`` disables.
        backwards_m: terminate after driving this far backwards from the furthest point [m].
        action_mode: ``combined`` (steer, throttle_brake) or ``separate`` (steer, throttle, brake).
        vehicle: vehicle parameter file name; ``vehicle_overrides``: parameter overrides.
        control_hz, substeps: control rate [Hz] and physics substeps per control step.
        rangefinder_angles_deg: beam angles [deg]; ``rangefinder_range_m``: beam range [m].
        camera: keyword arguments for :class:`torcsrl.envs.camera.Camera` (pixels/depth).
        traffic: ``None`` (every car alone), or a race (:mod:`torcsrl.envs.traffic`, conf/traffic/*.yaml): each of the
            ``num_cars`` learners races ``traffic.opponents`` opponents on its own copy of the track; the core then
            holds ``num_cars x (1 + opponents)`` cars, learners first (``n_learners`` of ``n``).
        procedural: ``{seeds: [lo, hi], pool: N, share: p, generator: proc|gen|[gen, proc]}``: add a pool of N
            generated tracks (seeds drawn from ``[lo, hi)`` by a stream seeded with ``seed``); each
            episode drives a pool track with probability ``share``, else a named track
            (:mod:`torcsrl.envs.tracks.procedural`). ``None``: named tracks only.
        cars_per_world: ``None`` (default): every car in one pybullet world; a number: the cars dealt over
            ``ceil(n / cars_per_world)`` worlds (:class:`~torcsrl.envs.vehicle.CarFleet`; each car moves as it
            would in one world, and a world's collision broadphase sorts through its own cars only: many cars
            on one line are cheaper). Not with traffic or a camera.
        vehicle_backend: how :class:`~torcsrl.envs.vehicle.CarFleet` integrates the cars: ``auto`` (python for one
            car, numba for more where it is installed), ``numba``, ``numpy`` or ``python`` (the same equations, to rounding).
        seed: seed of the env's random generator (tracks, surfaces, spawn).
    """

    #: Cars followed one by one in plain Python up to this many (an instance may raise it: the batched
    #: evaluation does, so that each car is located exactly as a one-car env locates it).
    scalar_locate_max_cars: int = SCALAR_LOCATE_MAX_CARS

    def __init__(
        self,
        track: str | Sequence[str] = "road_flow",
        surface: str | Sequence[str] | None = None,
        num_cars: int = 1,
        sensors: Sequence[str] = ("rangefinder", "state"),
        reward: str | Mapping[str, float] = "summers_final",
        reward_scale: float = 1.0,
        max_steps: int = 2500,
        lap_limit: int | None = None,
        start: str = "grid",
        spawn_jitter: Sequence[float] = (0.0, 0.0),
        offtrack_grace_s: float = 0.0,
        no_progress_s: float | None = 5.0,
        backwards_m: float = 10.0,
        action_mode: str = "combined",
        vehicle: str = "default",
        vehicle_overrides: Mapping[str, Any] | None = None,
        control_hz: float = 50.0,
        substeps: int = 4,
        rangefinder_angles_deg: Sequence[float] = RANGEFINDER_ANGLES_DEG,
        rangefinder_range_m: float = RANGE_M,
        camera: Mapping[str, Any] | None = None,
        procedural: Mapping[str, Any] | None = None,
        traffic: Mapping[str, Any] | None = None,
        cars_per_world: int | None = None,
        vehicle_backend: str = "auto",
        seed: int | None = None,
    ) -> None:
        self.sensors = check_sensors(sensors)
        if int(num_cars) != num_cars or num_cars < 1:
            raise ValueError(f"num_cars must be a positive integer, got {num_cars!r}")
        if action_mode not in ACTION_MODES:
            raise ValueError(f"unknown action_mode {action_mode!r}; allowed: {', '.join(ACTION_MODES)}")
        if start not in START_MODES:
            raise ValueError(f"unknown start {start!r}; allowed: {', '.join(START_MODES)}")
        if vehicle_backend not in BACKENDS:
            raise ValueError(f"unknown vehicle_backend {vehicle_backend!r}; allowed: {', '.join(BACKENDS)}")
        if int(max_steps) != max_steps or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        if lap_limit is not None and (int(lap_limit) != lap_limit or lap_limit < 1):
            raise ValueError(f"lap_limit must be a positive integer or None, got {lap_limit!r}")
        #: the cars the agent drives (the env's batch); ``n`` counts every car of the world (opponents too)
        self.n_learners = int(num_cars)
        self.traffic_spec = TrafficSpec.from_config(traffic)
        k_opp = self.traffic_spec.opponents if self.traffic_spec is not None else 0
        self.n = self.n_learners * (1 + k_opp)
        self.track_names = _tracks.resolve(as_list(track))
        #: Named tracks first, then the procedural pool (slots n_named ...).
        self.n_named = len(self.track_names)
        self.procedural = ProceduralSpec.from_config(procedural)
        if self.procedural is not None:
            self.track_names = self.track_names + self.procedural.names(seed)
        self.surfaces = as_list(surface)
        for s in self.surfaces:
            if s is not None and s not in _surf.ROAD_SURFACES:
                raise ValueError(f"unknown surface {s!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
        for key, msg in episode_setting_problems(spawn_jitter=spawn_jitter, offtrack_grace_s=offtrack_grace_s,
                                                 no_progress_s=no_progress_s, backwards_m=backwards_m):
            raise ValueError(f"{key} {msg}")
        self.reward = Reward(reward, reward_scale)
        self.max_steps = int(max_steps)
        self.lap_limit = None if lap_limit is None else int(lap_limit)
        self.start = start
        self.spawn_jitter = (float(spawn_jitter[0]), float(spawn_jitter[1]))
        self.offtrack_grace_s = float(offtrack_grace_s)
        self.no_progress_s = None if no_progress_s is None else float(no_progress_s)
        self.backwards_m = float(backwards_m)
        self.action_mode = action_mode
        self.action_dim = 2 if action_mode == "combined" else 3

        worlds = 1
        if cars_per_world is not None:
            if isinstance(cars_per_world, bool) or int(cars_per_world) != cars_per_world or cars_per_world < 1:
                raise ValueError(f"cars_per_world must be a positive integer or None, got {cars_per_world!r}")
            worlds = -(-self.n // int(cars_per_world))
            if worlds > 1 and (self.traffic_spec is not None or "pixels" in self.sensors or "depth" in self.sensors):
                raise ValueError("cars_per_world: a race (traffic) and the camera need every car in one world")
        self.client = p.connect(p.DIRECT)
        #: the other pybullet worlds of the cars (cars_per_world), each with its ground
        self._more_clients = [p.connect(p.DIRECT) for _ in range(worlds - 1)]
        for c in (self.client, *self._more_clients):
            make_ground(c)
        params = VehicleParams.load(vehicle, overrides=dict(vehicle_overrides) if vehicle_overrides else None)
        self.fleet = CarFleet([self.client, *self._more_clients] if worlds > 1 else self.client, self.n, params,
                              control_hz=control_hz, substeps=substeps, backend=vehicle_backend)
        self.dt = self.fleet.dt_control
        self.traffic: Traffic | None = None
        self._group_offset = np.zeros((self.n, 2))
        if self.traffic_spec is not None:
            self.traffic = Traffic(self.traffic_spec, self.n_learners, params)
            self._group_offset[:, 1] = self.traffic.group * TRACK_SPACING_M  # group g: its own track copy, g x 10 km north
            if self.traffic_spec.collide:
                self.fleet.set_collide(True)
                self.fleet.track_contacts(True)
            for b in self.fleet.bodies[self.n_learners:]:
                p.changeVisualShape(b, -1, rgbaColor=list(OPPONENT_RGBA), physicsClientId=self.client)
        #: observation keys computed for every car (the learners' sensors and what frozen-policy opponents read)
        self._all_keys = tuple(k for k in self.sensors if k not in ("pixels", "depth"))
        if self.traffic is not None:
            self._all_keys += tuple(k for k in self.traffic.obs_keys if k not in self._all_keys)
        self._obs_all: dict[str, np.ndarray] = {}
        self.start_back = np.zeros(self.n)  # how far behind its race's start point each car started [m] (laps count from there)
        self.rangefinder = Rangefinder(rangefinder_angles_deg, rangefinder_range_m) if "rangefinder" in self._all_keys else None
        #: one slot per distinct entry: the named tracks loaded now (a bad one fails here), a procedural pool's on first use
        self._geometry = _TrackSlots(self.track_names, loaded=self.n_named)
        #: World origin [m] of each track slot: tracks lie 10 km apart, so that cameras never see
        #: another slot's track, and each car drives at its own track's origin.
        self.track_origins = np.array([[k * TRACK_SPACING_M, 0.0] for k in range(len(self._geometry))])
        self._variants: dict[tuple[int, str | None], Any] = {}  # a slot's walls are built on its first use (_variant)
        self.camera = None
        self._camera_cfg = dict(camera) if camera else {}
        if "pixels" in self.sensors or "depth" in self.sensors:
            self._make_camera()

        n = self.n
        self.rng = np.random.default_rng(seed)
        self.slot = np.zeros(n, dtype=np.int64)
        self.car_tracks = [self._variant(0, self.surfaces[0])] * n
        self.surface_pick: list[str | None] = [self.surfaces[0]] * n  # surface override drawn per car
        self.s = np.zeros(n)
        self.d = np.zeros(n)
        self.chord = np.zeros(n, dtype=np.int64)  # centreline chord the car was last on
        self.s0 = np.zeros(n)  # spawn arc length
        self.dist_raced = np.zeros(n)
        self.best_dist = np.zeros(n)
        self.best_dist_time = np.zeros(n)
        self.lap = np.zeros(n, dtype=np.int64)  # full laps driven (distRaced // length)
        self.crossings = np.zeros(n, dtype=np.int64)  # start-line crossings (they time the laps)
        self.time = np.zeros(n)
        self.lap_start_time = np.zeros(n)
        self.lap_timed = np.zeros(n, dtype=bool)  # the running lap started on the line
        self.last_lap_time = np.zeros(n)
        self.best_lap_time = np.zeros(n)
        self.steps = np.zeros(n, dtype=np.int64)
        self.offtrack_time = np.zeros(n)
        self.angle = np.zeros(n)
        self.track_pos = np.zeros(n)
        self.finished = np.zeros(n, dtype=bool)
        self.reason = np.zeros(n, dtype=np.int64)
        self.terms = np.zeros((len(REWARD_TERMS), n))
        self.last_steer = np.zeros(n)  # the steering command of the previous step (the steer_change reward term)
        self.rewards = np.zeros(n)
        self.terminated = np.zeros(n, dtype=bool)
        self.truncated = np.zeros(n, dtype=bool)
        self.obs: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ setup helpers
    def _variant(self, slot: int, surface: str | None):
        """Track ``slot`` on ``surface`` (the slot's own when None), cached; the first use of a slot builds its edge walls
        in the rangefinder's world: every car gets its track here, so a procedural pool of 100 tracks builds only the
        walls of the tracks drawn (4-7 s an env before; the beams read the same either way)."""
        key = (slot, surface)
        if key not in self._variants:
            t = self._geometry[slot]
            if self.rangefinder is not None:
                self.rangefinder.add_track(slot, t)
            self._variants[key] = t.with_surface(surface) if surface else t
        return self._variants[key]

    def _make_camera(self) -> None:
        from torcsrl.envs import camera as _camera  # optional: pixels and depth

        self.camera = _camera.CarCameras(self.client, self if self.traffic is None else _LearnerView(self), **self._camera_cfg)

    def car_origins(self) -> np.ndarray:
        """World origin ``[n, 2]`` [m] of each car's track copy (its track slot's origin, plus its race group's offset)."""
        if self.traffic is None:
            return self.track_origins[self.slot]
        return self.track_origins[self.slot] + self._group_offset

    @property
    def observation_shapes(self) -> dict[str, tuple[int, ...]]:
        out = {}
        if "rangefinder" in self.sensors:
            out["rangefinder"] = (self.rangefinder.n_beams,)
        if "state" in self.sensors:
            out["state"] = (len(STATE_SLOTS),)
        if "opponents" in self.sensors:
            out["opponents"] = (OPPONENT_SECTORS,)
        if "telemetry" in self.sensors:
            out["telemetry"] = (len(TELEMETRY_SLOTS),)
        if self.camera is not None:
            out.update(self.camera.shapes)
        return {k: out[k] for k in self.sensors}

    def seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(seed)

    # ------------------------------------------------------------------ reset
    def reset(self, idx: np.ndarray | None = None) -> None:
        """Start a new episode for cars ``idx`` (all when None); the others are untouched."""
        idx = np.arange(self.n_learners) if idx is None else np.flatnonzero(idx) if np.asarray(idx).dtype == bool else np.asarray(idx)
        if len(idx) == 0:
            return
        if self.traffic is not None:
            return self._reset_race(idx)
        k = len(idx)
        rng = self.rng
        if self.procedural is not None:  # named tracks or the pool, then a track within
            pick = rng.random(k) < self.procedural.share
            slots = np.where(pick, self.n_named + rng.integers(self.procedural.pool, size=k), rng.integers(self.n_named, size=k))
        else:
            slots = rng.integers(len(self._geometry), size=k) if len(self._geometry) > 1 else np.zeros(k, dtype=np.int64)
        surf = [self.surfaces[j] for j in (rng.integers(len(self.surfaces), size=k) if len(self.surfaces) > 1 else np.zeros(k, dtype=int))]
        xy = np.zeros((k, 2))
        yaw = np.zeros(k)
        for j, i in enumerate(idx):
            t = self._variant(int(slots[j]), surf[j])
            self.slot[i] = slots[j]
            self.car_tracks[i] = t
            self.surface_pick[i] = surf[j]
            s0 = rng.uniform(0.0, t.length) if self.start == "random" else 0.0
            dj = rng.uniform(-1.0, 1.0) * self.spawn_jitter[0] if self.spawn_jitter[0] else 0.0
            yj = rng.uniform(-1.0, 1.0) * self.spawn_jitter[1] if self.spawn_jitter[1] else 0.0
            xy[j] = t.to_world(s0, dj)
            yaw[j] = float(t.heading(s0)) + yj
            self.s0[i] = s0
            self.s[i] = s0
            self.chord[i] = int(t._locate(s0)[0])
        self.fleet.reset(idx, xy + self.car_origins()[idx], yaw, 0.0)
        self._clear_books(idx, lap_timed=self.start == "grid")
        self._observe()

    def park(self, idx: Any) -> None:
        """Take cars ``idx`` out of the physics until their next reset (:meth:`CarFleet.park`, numpy backend):
        for a batch whose cars end their episodes at different times. A parked car's state, books and
        observation rows are left as they are (its rangefinder reads off-track); the others are untouched."""
        self.fleet.park(idx)

    @property
    def parked(self) -> np.ndarray:
        """``[n]`` bool: the cars out of the physics until their next reset (:meth:`park`)."""
        return self.fleet.parked

    def _clear_books(self, idx: np.ndarray, lap_timed: bool) -> None:
        """Zero the lap books, counters, termination and reward terms of the cars ``idx`` just placed, and locate
        them; ``lap_timed``: whether their first lap counts from now (a grid start) or from the first crossing."""
        for name in ("dist_raced", "best_dist", "best_dist_time", "time", "lap_start_time", "last_lap_time",
                     "best_lap_time", "offtrack_time"):
            getattr(self, name)[idx] = 0.0
        self.lap[idx] = 0
        self.crossings[idx] = 0
        self.steps[idx] = 0
        self.lap_timed[idx] = lap_timed
        self.finished[idx] = False
        self.reason[idx] = 0
        self.terms[:, idx] = 0.0
        self.last_steer[idx] = 0.0
        self._locate(idx_reset=idx)

    def _draw_tracks(self, k: int) -> tuple[np.ndarray, list]:
        rng = self.rng
        if self.procedural is not None:
            pick = rng.random(k) < self.procedural.share
            slots = np.where(pick, self.n_named + rng.integers(self.procedural.pool, size=k), rng.integers(self.n_named, size=k))
        else:
            slots = rng.integers(len(self._geometry), size=k) if len(self._geometry) > 1 else np.zeros(k, dtype=np.int64)
        surf = [self.surfaces[j] for j in (rng.integers(len(self.surfaces), size=k) if len(self.surfaces) > 1 else np.zeros(k, dtype=int))]
        return slots, surf

    def _reset_race(self, groups: np.ndarray) -> None:
        """New races for learners ``groups``: each learner's group (it and its opponents) drawn onto a track, laid
        out on the grid (or rolling), with the grid order and the opponents' paces drawn from the env's generator."""
        tr = self.traffic
        slots, surf = self._draw_tracks(len(groups))
        cars, xy, yaw, speed = [], [], [], []
        for j, g in enumerate(groups.tolist()):
            t = self._variant(int(slots[j]), surf[j])
            anchor = float(self.rng.uniform(0.0, t.length)) if self.start == "random" else 0.0
            s_start, dd, v0, back = tr.layout(g, t, self.rng, anchor)
            for c, i in enumerate(tr.members[g].tolist()):
                self.slot[i] = slots[j]
                self.car_tracks[i] = t
                self.surface_pick[i] = surf[j]
                s0 = float(s_start[c])
                cars.append(i)
                xy.append(t.to_world(s0, float(dd[c])))
                yaw.append(float(t.heading(s0)))
                speed.append(float(v0[c]))
                self.s0[i] = s0
                self.s[i] = s0
                self.chord[i] = int(t._locate(s0)[0])
                self.start_back[i] = back[c]
            tr.reset_books(g, back)
        idx = np.asarray(cars, dtype=np.int64)
        self.fleet.reset(idx, np.asarray(xy) + self.car_origins()[idx], np.asarray(yaw), np.asarray(speed))
        self._clear_books(idx, lap_timed=False)  # the first lap is timed from the first crossing of the line
        tr._d_prev = self.d.copy()
        self._observe()

    # ------------------------------------------------------------------ exact resume
    def get_state(self) -> dict[str, Any]:
        """Every piece of dynamic state, for an exact resume on CPU: the pybullet world(s) (bodies'
        poses and velocities, as ``saveBullet`` bytes), the cars' drivetrain state, each car's
        track and surface, the episode books, the last observation, the camera's held frames and
        the generator.
        :meth:`set_state` on a core built with the same arguments continues bit for bit."""
        worlds = []
        with tempfile.TemporaryDirectory() as tmp:
            f = os.path.join(tmp, "world.bullet")
            for c in (self.client, *self._more_clients):
                p.saveBullet(f, physicsClientId=c)
                worlds.append(np.fromfile(f, dtype=np.uint8))
        world = worlds[0]
        extra: dict[str, Any] = {"more_worlds": worlds[1:]} if self._more_clients else {}
        books = {k: np.array(getattr(self, k), copy=True) for k in _BOOK_FIELDS}
        if self.traffic is not None:
            extra = {**extra, "traffic": self.traffic.get_state(), "start_back": self.start_back.copy(),
                     "obs_all": {k: v.copy() for k, v in self._obs_all.items()}}
        return {**extra, "world": world, "fleet": self.fleet.get_state(), "books": books,
                "surface_pick": list(self.surface_pick), "obs": {k: v.copy() for k, v in self.obs.items()},
                "camera_slots": list(getattr(self.camera, "_worlds", {}) or {}), "rng": self.rng.bit_generator.state,
                "camera": None if self.camera is None else self.camera.get_state()}

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`get_state` returned (same track list, cars, sensors and settings)."""
        books = state["books"]
        if len(books["s"]) != self.n:
            raise ValueError(f"saved state holds {len(books['s'])} cars; this env has {self.n}")
        if self.camera is not None:  # build the visual worlds the saved client had, in its order
            for k in state.get("camera_slots", []):
                self.camera.world(int(k))
        more = state.get("more_worlds", [])
        if len(more) != len(self._more_clients):
            raise ValueError(f"saved state holds {1 + len(more)} pybullet worlds; this env has {1 + len(self._more_clients)}")
        with tempfile.TemporaryDirectory() as tmp:
            f = os.path.join(tmp, "world.bullet")
            for c, w in zip((self.client, *self._more_clients), (state["world"], *more)):
                np.asarray(w, dtype=np.uint8).tofile(f)
                p.restoreState(fileName=f, physicsClientId=c)
        for k in _BOOK_FIELDS:
            if k == "last_steer" and k not in books:  # a state saved before the steer_change term
                self.last_steer = np.zeros(self.n)
                continue
            if k == "terms" and np.shape(books[k])[0] < len(REWARD_TERMS):  # the same, its terms without steer_change
                pad = np.zeros((len(REWARD_TERMS) - np.shape(books[k])[0], self.n))
                self.terms = np.concatenate([np.asarray(books[k], dtype=np.float64), pad])
                continue
            setattr(self, k, np.array(books[k], copy=True))
        self.surface_pick = list(state["surface_pick"])
        self.car_tracks = [self._variant(int(self.slot[i]), self.surface_pick[i]) for i in range(self.n)]
        self.obs = {k: np.array(v, copy=True) for k, v in state["obs"].items()}
        self.rng.bit_generator.state = state["rng"]
        self.fleet.set_state(state["fleet"])
        if self.traffic is not None:
            self.start_back = np.array(state["start_back"], copy=True)
            self._obs_all = {k: np.array(v, copy=True) for k, v in state["obs_all"].items()}
            self.obs = self._learner_obs(self._obs_all, self.obs)
            self.traffic.set_state(state["traffic"], self)
        if self.camera is not None and "camera" in state:  # held frames (camera every > 1); absent in older checkpoints
            self.camera.set_state(state["camera"])

    # ------------------------------------------------------------------ step
    def sanitize(self, action) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(steer, throttle, brake) ``[N]`` from an action ``[N, A]``; see :class:`RaceEnv`."""
        a = np.asarray(action, dtype=np.float64)
        nl = self.n_learners
        if nl == 1 and self.action_dim == 2 and a.size == 2:  # the common case, in floats
            st, tb = a.ravel().tolist()
            if math.isfinite(st) and math.isfinite(tb):
                st, tb = min(max(st, -1.0), 1.0), min(max(tb, -1.0), 1.0)
                return np.array([st]), np.array([max(tb, 0.0)]), np.array([max(-tb, 0.0)])
        if a.shape != (nl, self.action_dim):
            if a.size == nl * self.action_dim:
                a = a.reshape(nl, self.action_dim)
            else:
                want = (self.action_dim,) if nl == 1 else (nl, self.action_dim)
                raise ValueError(f"action has shape {a.shape}; expected {want} ({self.action_mode}: "
                                 f"{'steer, throttle_brake' if self.action_dim == 2 else 'steer, throttle, brake'})")
        if not np.isfinite(a).all():
            raise ValueError(f"action contains NaN or inf: {a.tolist()}; actions must be finite numbers in [-1, 1]")
        a = np.clip(a, -1.0, 1.0)
        if self.action_dim == 2:
            tb = a[:, 1]
            return a[:, 0], np.maximum(tb, 0.0), np.maximum(-tb, 0.0)
        return a[:, 0], (a[:, 1] + 1.0) * 0.5, (a[:, 2] + 1.0) * 0.5

    def step(self, action) -> None:
        """One control step for every car (call :meth:`reset` for the cars that are done)."""
        steer, throttle, brake = self.sanitize(action)
        if self.traffic is not None:
            steer, throttle, brake = self.traffic.actions(self, (steer, throttle, brake))
        steer_change = np.abs(steer - self.last_steer)
        self.last_steer = np.array(steer, dtype=np.float64)
        self.fleet.step(steer, throttle, brake)
        s_old = self.s.copy()
        self._locate()
        if self.n == 1 and self.traffic is None:
            self._book_one(float(s_old[0]), float(steer_change[0]))
            self._observe()
            return
        progress = wrap_deltas(self.s, s_old, np.array([t.length for t in self.car_tracks])) if self.n > 1 \
            else self.car_tracks[0].wrap_delta(self.s, s_old)
        self.time += self.dt
        self.steps += 1
        self.dist_raced += progress
        self._laps()
        better = self.dist_raced > self.best_dist
        self.best_dist = np.where(better, self.dist_raced, self.best_dist)
        self.best_dist_time = np.where(better, self.time, self.best_dist_time)
        off = np.abs(self.track_pos) > 1.0
        self.offtrack_time = np.where(off, self.offtrack_time + self.dt, 0.0)
        reason = np.zeros(self.n, dtype=np.int64)
        reason[off & (self.offtrack_time > self.offtrack_grace_s)] = 1
        reason[(reason == 0) & (self.dist_raced < self.best_dist - self.backwards_m)] = 2
        if self.no_progress_s is not None:
            reason[(reason == 0) & (self.time - self.best_dist_time > self.no_progress_s)] = 3
        reason[(reason == 0) & self.fleet.flipped] = 4
        self.reason = reason
        terminated = reason > 0
        self.finished = (self.lap >= self.lap_limit) & ~terminated if self.lap_limit is not None else np.zeros(self.n, bool)
        vx = self.fleet.vel_body[:, 0]
        race = None
        if self.traffic is not None:
            imp = self.fleet.contact_impulse
            self.traffic.update(self, imp if imp is not None else np.zeros((self.n, self.n)))
            race = self.traffic.terms
        self.terms = Reward.terms(vx, self.angle, self.track_pos, progress, terminated, race, steer_change)
        self.rewards = self.reward(self.terms)
        self.terminated = terminated
        self.truncated = ~terminated & ((self.steps >= self.max_steps) | self.finished)
        self._observe()

    def _book_one(self, s_old: float, steer_change: float = 0.0) -> None:
        """One car: the bookkeeping of :meth:`step` in plain floats (the same rules, in the same
        order; numpy's per-call overhead dominates arrays of one). Fields that :meth:`step`
        replaces by new arrays are replaced here too, so no caller's reference is overwritten."""
        t = self.car_tracks[0]
        dt = self.dt
        half = 0.5 * t.length
        progress = (float(self.s[0]) - s_old + half) % t.length - half
        now = float(self.time[0]) + dt
        self.time[0] = now
        self.steps[0] += 1
        dist = float(self.dist_raced[0]) + progress
        self.dist_raced[0] = dist
        self._laps()
        best, best_t = float(self.best_dist[0]), float(self.best_dist_time[0])
        if dist > best:
            best, best_t = dist, now
        self.best_dist, self.best_dist_time = np.array([best]), np.array([best_t])
        tp, ang = float(self.track_pos[0]), float(self.angle[0])
        off = abs(tp) > 1.0
        off_t = float(self.offtrack_time[0]) + dt if off else 0.0
        self.offtrack_time = np.array([off_t])
        if off and off_t > self.offtrack_grace_s:
            reason = 1
        elif dist < best - self.backwards_m:
            reason = 2
        elif self.no_progress_s is not None and now - best_t > self.no_progress_s:
            reason = 3
        elif bool(self.fleet.flipped[0]):
            reason = 4
        else:
            reason = 0
        self.reason = np.array([reason], dtype=np.int64)
        term = reason > 0
        fin = self.lap_limit is not None and int(self.lap[0]) >= self.lap_limit and not term
        self.finished = np.array([fin])
        vx = float(self.fleet.vel_body[0, 0])
        terms = (vx * math.cos(ang), -vx * abs(math.sin(ang)), -vx * abs(tp), progress, float(term), 0.0, 0.0, 0.0, 0.0,
                 steer_change)
        self.terms = np.array(terms).reshape(len(REWARD_TERMS), 1)
        w = self.reward._w
        total = sum(w[k] * terms[k] for k in range(len(self.reward._w_core)))
        for row, wk in self.reward.extra:
            total = total + wk * terms[row]
        self.rewards = np.array([self.reward.scale * total])
        self.terminated = np.array([term])
        self.truncated = np.array([not term and (int(self.steps[0]) >= self.max_steps or fin)])

    # ------------------------------------------------------------------ internals
    def _locate(self, idx_reset: np.ndarray | None = None) -> None:
        """Frenet position of every car and the surface under each wheel (exact projection).

        Few cars: each point is followed chord by chord from the car's previous chord in plain
        Python (a few µs). Many cars: one vectorised projection per track, windowed around the
        previous arc length.
        """
        fleet = self.fleet
        origin = self.car_origins()  # [N, 2]
        pos = fleet.pos[:, :2] - origin  # in each car's track frame
        wheels = fleet.wheel_xy - origin[:, None, :]  # [N, 4, 2]
        if self.n <= self.scalar_locate_max_cars:
            walk = self._locate_scalar if self.n <= PYTHON_WALK_MAX_CARS else self._locate_walk
            ids = walk(pos, wheels, fleet.yaw)
            if ids is not None:
                fleet.set_wheel_surfaces(ids)
                return
        pts = np.concatenate([pos[:, None, :], wheels], axis=1)  # [N, 5, 2]
        hint = self.s
        ids = np.empty((self.n, 4), dtype=np.int64)
        groups = [np.arange(self.n)] if self.n == 1 else [np.flatnonzero([t is u for t in self.car_tracks])
                                                            for u in {id(t): t for t in self.car_tracks}.values()]
        for g in groups:
            t = self.car_tracks[g[0]]
            s, d = t.project(pts[g], s_hint=np.repeat(hint[g, None], 5, axis=1), window_m=8.0)
            wl, wr, heading, sid = t.lookup(s)
            on = (d[:, 1:] <= wl[:, 1:]) & (d[:, 1:] >= -wr[:, 1:])
            ids[g] = np.where(on, sid[:, 1:], _surf.GRASS_ID)
            self.s[g] = s[:, 0]
            self.d[g] = d[:, 0]
            self.track_pos[g] = np.where(d[:, 0] >= 0.0, d[:, 0] / wl[:, 0], d[:, 0] / wr[:, 0])
            self.angle[g] = (fleet.yaw[g] - heading[:, 0] + math.pi) % (2.0 * math.pi) - math.pi
            self.chord[g] = t._locate(s[:, 0])[0]
        fleet.set_wheel_surfaces(ids)

    def _locate_scalar(self, pos: np.ndarray, wheels: np.ndarray, yaw: np.ndarray) -> np.ndarray | None:
        ids = np.empty((self.n, 4), dtype=np.int64)
        grass = _surf.GRASS_ID
        wl_ = wheels.tolist()
        for i in range(self.n):
            t = self.car_tracks[i]
            r = t.track_point(float(pos[i, 0]), float(pos[i, 1]), int(self.chord[i]))
            if r is None:
                return None
            s, d, chord, u = r
            wl, wr, heading, _ = t.frame_at(chord, u)
            self.s[i], self.d[i], self.chord[i] = s, d, chord
            self.track_pos[i] = d / wl if d >= 0.0 else d / wr
            self.angle[i] = (float(yaw[i]) - heading + math.pi) % (2.0 * math.pi) - math.pi
            for k, (x, y) in enumerate(wl_[i]):
                rw = t.track_point(x, y, chord)
                if rw is None:
                    return None
                w_l, w_r, _, sid = t.frame_at(rw[2], rw[3])
                ids[i, k] = sid if -w_r <= rw[1] <= w_l else grass
        return ids

    def _locate_walk(self, pos: np.ndarray, wheels: np.ndarray, yaw: np.ndarray) -> np.ndarray | None:
        """:meth:`_locate_scalar` vectorised over the cars (:meth:`Track.track_points`): the same numbers, bit for
        bit, and the same side effects when a walk fails (the cars before the first failing one, and that car's own
        point if it settled, are written; then ``None``)."""
        n = self.n
        s_new, d_new, tp_new, ang_new = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        ch_new = np.zeros(n, dtype=np.int64)
        car_ok = np.zeros(n, dtype=bool)
        all_ok = np.zeros(n, dtype=bool)
        ids = np.empty((n, 4), dtype=np.int64)
        tracks = self.car_tracks
        first = tracks[0]
        groups = [np.arange(n)] if all(t is first for t in tracks) else \
            [np.flatnonzero([t is u for t in tracks]) for u in {id(t): t for t in tracks}.values()]
        pi, two_pi = math.pi, 2.0 * math.pi
        for g in groups:
            t = tracks[g[0]]
            tab = t._walk_table()
            wl_, dwl = t.w_left, t._delta(t.w_left)
            wr_, dwr = t.w_right, t._delta(t.w_right)
            s, d, ch, u, ok = t.track_points(pos[g, 0], pos[g, 1], self.chord[g])
            row = tab[ch]
            nx = row[:, 4] + u * row[:, 6]
            ny = row[:, 5] + u * row[:, 7]
            heading = np.fromiter(map(math.atan2, (-nx).tolist(), ny.tolist()), dtype=np.float64, count=len(g))
            wl = wl_[ch] + u * dwl[ch]
            wr = wr_[ch] + u * dwr[ch]
            with np.errstate(divide="ignore", invalid="ignore"):
                tp = np.where(d >= 0.0, d / wl, d / wr)
            s_new[g], d_new[g], ch_new[g], tp_new[g] = s, d, ch, tp
            ang_new[g] = (yaw[g] - heading + pi) % two_pi - pi
            car_ok[g] = ok
            # the wheels walk from their car's chord
            rs, rd, rc, ru, rok = t.track_points(wheels[g, :, 0], wheels[g, :, 1], np.repeat(ch, 4))
            w_l = wl_[rc] + ru * dwl[rc]
            w_r = wr_[rc] + ru * dwr[rc]
            ids[g] = np.where((-w_r <= rd) & (rd <= w_l), t.surface_ids[rc], _surf.GRASS_ID).reshape(-1, 4)
            all_ok[g] = ok & rok.reshape(-1, 4).all(axis=1)
        if all_ok.all():
            self.s[:], self.d[:], self.chord[:], self.track_pos[:], self.angle[:] = s_new, d_new, ch_new, tp_new, ang_new
            return ids
        f = int(np.argmin(all_ok))  # the first car whose walk failed: the scalar loop wrote the cars before it
        w = np.arange(n) < f
        w[f] = car_ok[f]
        for a, v in ((self.s, s_new), (self.d, d_new), (self.chord, ch_new), (self.track_pos, tp_new), (self.angle, ang_new)):
            a[w] = v[w]
        return None

    def _laps(self) -> None:
        """``lap``: full laps driven since the start (``distRaced // length``; from the grid, the
        line crossings). Lap *times* run from one start-line crossing to the next, so after a
        random start the first, partial lap is never timed."""
        lengths = np.array([t.length for t in self.car_tracks]) if self.n > 1 else self.car_tracks[0].length
        cross = np.floor((self.s0 + self.dist_raced) / lengths).astype(np.int64)
        done = cross > self.crossings
        if done.any():
            i = np.flatnonzero(done)
            lap_time = self.time[i] - self.lap_start_time[i]
            timed = self.lap_timed[i]
            self.last_lap_time[i] = np.where(timed, lap_time, self.last_lap_time[i])
            best = self.best_lap_time[i]
            self.best_lap_time[i] = np.where(timed & ((best == 0) | (lap_time < best)), lap_time, best)
            self.lap_start_time[i] = self.time[i]
            self.lap_timed[i] = True
            self.crossings = np.maximum(self.crossings, cross)
        self.lap = np.maximum(self.lap, np.floor((self.dist_raced - self.start_back) / lengths).astype(np.int64))

    def _observe(self) -> None:
        obs = {}
        fleet = self.fleet
        keys = self._all_keys
        if "rangefinder" in keys:
            on = np.abs(self.track_pos) <= 1.0
            if self.fleet._live is not None:  # parked cars cast no beams
                on &= ~self.fleet.parked
            xy = fleet.pos[:, :2] - self.car_origins()
            obs["rangefinder"] = self.rangefinder.read(self.slot, xy, fleet.yaw, on)
        if "opponents" in keys:
            groups = self.traffic.group if self.traffic is not None else np.arange(self.n)
            obs["opponents"] = opponent_sectors(fleet.pos[:, :2], fleet.yaw, groups, range_m=OPPONENT_RANGE_M)
        if "state" in keys or "telemetry" in keys:
            v = fleet.vel_body * MS_TO_KMH
            st = np.empty((self.n, len(STATE_SLOTS)), dtype=np.float32)
            st[:, 0] = self.angle
            st[:, 1] = self.track_pos
            st[:, 2:5] = v
            st[:, 5:9] = fleet.wheel_omega
            st[:, 9] = fleet.rpm
            st[:, 10] = fleet.gear
            if "state" in keys:
                obs["state"] = st
            if "telemetry" in keys:
                obs["telemetry"] = np.ascontiguousarray(st[:, 2:])
        if self.traffic is not None:
            self._obs_all = obs
            obs = self._learner_obs(obs)
        if self.camera is not None:
            obs.update(self.camera.render())
        self.obs = obs

    def _learner_obs(self, obs_all: Mapping[str, np.ndarray], held: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """The learners' rows of the sensors they asked for (race mode), and ``held``'s camera frames."""
        nl = self.n_learners
        out = {k: np.ascontiguousarray(v[:nl]) for k, v in obs_all.items() if k in self.sensors}
        if held is not None:
            out.update({k: v for k, v in held.items() if k in ("pixels", "depth")})
        return out

    def info(self) -> dict[str, np.ndarray]:
        """Per-car bookkeeping ``[N]`` (TORCS names, SI units) and the reward terms."""
        cur = np.where(self.lap_timed, self.time - self.lap_start_time, 0.0)
        out = {
            "distFromStart": self.s.copy(), "distRaced": self.dist_raced.copy(), "lap": self.lap.copy(),
            "curLapTime": cur, "lastLapTime": self.last_lap_time.copy(), "bestLapTime": self.best_lap_time.copy(),
            "surfaceMu": self.fleet.wheel_mu.mean(axis=1),
        }
        if self.traffic is not None:
            out.update(self.traffic.info())
        for k, name in enumerate(REWARD_TERMS):
            out[f"reward_{name}"] = self.terms[k].copy()
        return out

    def close(self) -> None:
        if self.rangefinder is not None:
            self.rangefinder.close()
        if self.camera is not None and hasattr(self.camera, "close"):
            self.camera.close()
        if self.client is not None:
            for c in (self.client, *self._more_clients):
                try:
                    p.disconnect(physicsClientId=c)
                except p.error:
                    pass
            self.client = None
            self._more_clients = []


#: RaceCore's per-car episode books, saved by :meth:`RaceCore.get_state`.
_BOOK_FIELDS = ("slot", "s", "d", "chord", "s0", "dist_raced", "best_dist", "best_dist_time", "lap", "crossings", "time",
                "lap_start_time", "lap_timed", "last_lap_time", "best_lap_time", "steps", "offtrack_time", "angle",
                "track_pos", "finished", "reason", "terms", "rewards", "terminated", "truncated", "last_steer")


class RaceEnv(gym.Env, EzPickle):
    """Race a full-size car round a track, seen through TORCS-style sensors.

    ## Description
    A raycast car (pybullet; ~1,100 kg, 2.6 m wheelbase, tyre forces from slip scaled by the grip
    of the surface under each wheel) drives on a bundled or generated track. The task is to drive
    fast without leaving the track, as in the TORCS studies (Summers 2022, Andersson et al.).

    ## Action Space
    ``Box(-1, 1, (2,), float32)`` with ``action_mode="combined"`` (default):

    | index | action         | range   | meaning                                                  |
    |-------|----------------|---------|----------------------------------------------------------|
    | 0     | steer          | [-1, 1] | road-wheel angle as a fraction of full lock; +1 = left    |
    | 1     | throttle_brake | [-1, 1] | > 0: throttle fraction; < 0: brake fraction (pedal)       |

    ``action_mode="separate"``: ``Box(-1, 1, (3,))`` = steer, throttle, brake, with pedals mapped
    from [-1, 1] to [0, 1]. Finite out-of-range values are clipped; a NaN or infinite action, or
    one of the wrong shape, raises ``ValueError`` and the physics is not touched. The gearbox is
    automatic.

    ## Observation Space
    ``Dict`` with the keys chosen by ``sensors`` (default ``("rangefinder", "state")``):

    - ``rangefinder``: ``Box(-1, 200, (19,), float32)`` [m] — distance to the track edge along beams at
      −90, −75, −60, −45, −30, −20, −15, −10, −5, 0, 5, 10, 15, 20, 30, 45, 60, 75, 90° from the car's
      heading (positive = left); all −1 while off the track.
    - ``state``: ``Box((11,), float32)``, slots (:data:`torcsrl.envs.sensors.STATE_SLOTS`):
      angle_rad [rad] (car vs track axis), trackPos [-] (0 centre, ±1 edges, > 0 left),
      speedX/Y/Z_kmh [km/h] (car frame: forward, left, up), wheelSpinVel fl/fr/rl/rr [rad/s],
      rpm [1/min], gear [-]. Bounds: angle ±π, rpm [0, 20000], gear [0, 10], the rest ±1000.
    - ``telemetry``: ``Box((9,), float32)``, the on-board slots of ``state`` (speeds, wheel spin, rpm, gear;
      :data:`torcsrl.envs.sensors.TELEMETRY_SLOTS`): no angle to the axis or trackPos, which need a map.
    - ``pixels`` ``Box(0, 255, (3, H, W), uint8)`` and ``depth`` ``Box(0, far, (1, H, W), float32)`` [m]
      from the car-mounted camera, when requested.

    Normalised versions (divide by :func:`torcsrl.envs.sensors.obs_scale`) are in [−1, 1].

    ## Rewards
    ``reward_scale · Σ weight · term`` over the named terms of :mod:`torcsrl.envs.rewards`
    (speed_cos, speed_sin, track_pos, progress, termination); the default preset is Summers 2022's
    final reward v_x (cos θ − |sin θ|) [m/s] with −1 on termination. Each term is in ``info``.

    ## Starting State
    At rest on the start/finish line (``start="grid"``) or at a uniformly drawn arc length
    (``start="random"``), optionally jittered laterally and in yaw (``spawn_jitter``). With several
    tracks (or surfaces) one is drawn per episode from the env's seed.

    ## Episode End
    *Terminated*: off the track (|trackPos| > 1) for longer than ``offtrack_grace_s``; driving
    ``backwards_m`` backwards from the furthest point reached; no new furthest point for
    ``no_progress_s``; the car flipped. *Truncated*: ``max_steps`` control steps, or
    ``lap_limit`` laps completed (``info["finished"]`` is then True). Never both.

    ## Info
    distFromStart [m], distRaced [m], lap (completed laps), curLapTime, lastLapTime, bestLapTime [s]
    (0 until set, as in TORCS), ``reward_<term>`` for every reward term, ``termination``
    (the reason, "" if none), ``finished``, ``track``, ``surface``.

    ## Arguments
    See :class:`RaceCore` (every keyword is passed through), plus ``render_mode`` (``"rgb_array"``:
    a top-down 400×400 frame of the track and the car).

    ## Version History
    - v0: initial version.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, render_mode: str | None = None, **kwargs: Any) -> None:
        EzPickle.__init__(self, render_mode=render_mode, **kwargs)
        if kwargs.get("num_cars", 1) != 1:
            raise ValueError("the gymnasium RaceEnv drives one car; use torcsrl.envs.make_env(num_cars=N) for a batch")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unknown render_mode {render_mode!r}; allowed: rgb_array")
        self.render_mode = render_mode
        self.core = RaceCore(**kwargs)
        self.metadata = dict(self.metadata, render_fps=int(round(1.0 / self.core.dt)))
        self.action_space = spaces.Box(-1.0, 1.0, (self.core.action_dim,), np.float32)
        obs_spaces = {}
        for key, shape in self.core.observation_shapes.items():
            if key == "rangefinder":
                obs_spaces[key] = spaces.Box(-1.0, self.core.rangefinder.range_m, shape, np.float32)
            elif key in ("state", "telemetry"):
                lo, hi = np.array([STATE_BOUNDS[s] for s in (STATE_SLOTS if key == "state" else TELEMETRY_SLOTS)], dtype=np.float32).T
                obs_spaces[key] = spaces.Box(lo, hi, dtype=np.float32)
            elif key == "opponents":
                obs_spaces[key] = spaces.Box(0.0, OPPONENT_RANGE_M, shape, np.float32)
            elif key == "pixels":
                obs_spaces[key] = spaces.Box(0, 255, shape, np.uint8)
            elif key == "depth":
                obs_spaces[key] = spaces.Box(0.0, np.inf, shape, np.float32)
        self.observation_space = spaces.Dict(obs_spaces)
        self._seeded = False

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {k: v[0] for k, v in self.core.obs.items()}
        for k in ("state", "telemetry"):  # keep the observation inside its (very wide) physical bounds
            if k in obs:
                np.clip(obs[k], self.observation_space[k].low, self.observation_space[k].high, out=obs[k])
        return obs

    def _info(self) -> dict[str, Any]:
        c = self.core
        info = {k: (int(v[0]) if k in ("lap", "racePos", "overtakes", "collisions") else float(v[0])) for k, v in c.info().items()}
        info["termination"] = TERMINATION_REASONS[int(c.reason[0])]
        info["finished"] = bool(c.finished[0])
        info["track"] = c.car_tracks[0].name
        info["surface"] = c.car_tracks[0].default_surface
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or not self._seeded:
            self.core.seed(seed if seed is not None else int(self.np_random.integers(2**31)))
            self._seeded = True
        self.core.reset()
        return self._obs(), self._info()

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.action_space.shape:
            names = "steer, throttle_brake" if self.core.action_dim == 2 else "steer, throttle, brake"
            raise ValueError(f"action has shape {a.shape}; expected {self.action_space.shape} ({names})")
        self.core.step(a[None])
        c = self.core
        return self._obs(), float(c.rewards[0]), bool(c.terminated[0]), bool(c.truncated[0]), self._info()

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        c = self.core
        return render_top_down(c.car_tracks[0], c.fleet.pos[0, :2] - c.car_origins()[0], float(c.fleet.yaw[0]))

    def close(self) -> None:
        if getattr(self, "core", None) is not None:
            self.core.close()
            self.core = None


_BACKGROUNDS: dict = {}


def render_top_down(track, xy: np.ndarray, yaw: float, size: int = 400) -> np.ndarray:
    """A top-down RGB frame ``[size, size, 3]`` uint8 of ``track`` with the car at ``xy``, ``yaw``."""
    import cv2

    lo = np.minimum(track.left_edge.min(0), track.right_edge.min(0)) - 10.0
    hi = np.maximum(track.left_edge.max(0), track.right_edge.max(0)) + 10.0
    scale = (size - 1) / float(np.max(hi - lo))

    def px(pts):
        q = (np.asarray(pts) - lo) * scale
        return np.stack([q[..., 0], size - 1 - q[..., 1]], -1).astype(np.int32)

    key = (id(track), size)
    if key not in _BACKGROUNDS:
        bg = np.empty((size, size, 3), dtype=np.uint8)
        bg[:] = (_surf.COLORS[_surf.GRASS_ID] * 255).astype(np.uint8)
        m = len(track)
        for i in range(m):
            j = (i + 1) % m
            quad = px(np.stack([track.left_edge[i], track.left_edge[j], track.right_edge[j], track.right_edge[i]]))
            cv2.fillConvexPoly(bg, quad, tuple(int(c) for c in _surf.COLORS[track.surface_ids[i]] * 255))
        cv2.polylines(bg, [px(track.left_edge)], True, (255, 255, 255), 1)
        cv2.polylines(bg, [px(track.right_edge)], True, (255, 255, 255), 1)
        _BACKGROUNDS[key] = bg
    img = _BACKGROUNDS[key].copy()
    line = px(np.stack([track.to_world(0.0, track.w_left[0]), track.to_world(0.0, -track.w_right[0])]))
    cv2.line(img, tuple(line[0]), tuple(line[1]), (220, 30, 30), 2)
    c = px(xy)
    tip = px(np.asarray(xy) + 12.0 / scale * np.array([math.cos(yaw), math.sin(yaw)]))
    cv2.circle(img, tuple(c), 5, (230, 20, 20), -1)
    cv2.line(img, tuple(c), tuple(tip), (255, 255, 0), 2)
    return img


class _LearnerView:
    """The learners of a race core as the camera sees them (:class:`torcsrl.envs.camera.CarCameras` reads ``fleet``,
    ``slot``, ``car_tracks``, ``_geometry``, ``steps``, ``sensors``, ``track_origins``): frames are rendered for the
    learners only, and race group g's copy of a track is a visual world of its own (virtual slot
    ``slot + n_slots x g``, at the group's origin), so each learner sees its own opponents."""

    def __init__(self, core: RaceCore) -> None:
        self._core = core
        self.sensors = core.sensors
        self.fleet = _LearnerFleet(core)
        self._geometry = _Cycle(core._geometry)

    @property
    def slot(self) -> np.ndarray:
        c = self._core
        nl = c.n_learners
        return c.slot[:nl] + len(c._geometry) * np.arange(nl)

    @property
    def car_tracks(self) -> list:
        return self._core.car_tracks[: self._core.n_learners]

    @property
    def steps(self) -> np.ndarray:
        return self._core.steps[: self._core.n_learners]

    @property
    def track_origins(self) -> np.ndarray:
        c = self._core
        k = len(c._geometry)
        g = np.arange(k * c.n_learners) // k
        return c.track_origins[np.arange(k * c.n_learners) % k] + np.stack([np.zeros(len(g)), g * TRACK_SPACING_M], 1)


class _TrackSlots(Sequence):
    """The base :class:`~torcsrl.envs.track.Track` of each slot, by name, loaded on first access: the first ``loaded``
    at once, the rest (a procedural pool of ~100 generated tracks, ~10 ms each) when a car first draws them. A
    generated track is a function of its name, so the order of loading changes nothing."""

    def __init__(self, names: Sequence[str], loaded: int = 0) -> None:
        self._names = list(names)
        self._tracks: list[Any] = [None] * len(self._names)
        for i in range(min(int(loaded), len(self._names))):
            self[i]

    def __len__(self) -> int:
        return len(self._names)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        t = self._tracks[i]
        if t is None:
            t = self._tracks[i] = _tracks.load(self._names[i])
        return t


class _Cycle:
    def __init__(self, items: list) -> None:
        self._items = items

    def __getitem__(self, i: int):
        return self._items[int(i) % len(self._items)]


class _LearnerFleet:
    def __init__(self, core: RaceCore) -> None:
        self._core = core
        self.params = core.fleet.params

    @property
    def pos(self) -> np.ndarray:
        return self._core.fleet.pos[: self._core.n_learners]

    @property
    def rotation(self) -> np.ndarray:
        return self._core.fleet.rotation[: self._core.n_learners]
