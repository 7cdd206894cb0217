"""The race simulation core: :class:`RaceCore`, the one simulation every face shares.

N cars in one pybullet client (cars never collide; each has its own track, progress and episode), TORCS-style
sensors, named reward terms, lap bookkeeping and the episode rules.

One control step (the template method, :meth:`RaceCore.step`):
act (sanitise) → physics substeps → locate (Frenet projection, surfaces under the wheels;
:mod:`~torcsrl.envs.race.locate`) → bookkeeping (progress, laps) → observe (sensors) → reward terms → terminated →
truncated → info.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from torcsrl.envs import surfaces as _surf
from torcsrl.envs import tracks as _tracks
from torcsrl.envs.race.locate import CarLocator
from torcsrl.envs.race.views import LearnerView, TrackSlots
from torcsrl.envs.race.rules import ACTION_MODES, START_MODES, episode_setting_problems, wrap_deltas
from torcsrl.envs.rewards import REWARD_TERMS, Reward
from torcsrl.envs.sensors import (MS_TO_KMH, RANGEFINDER_ANGLES_DEG, RANGE_M, ROAD_SLOTS, STATE_SLOTS, TELEMETRY_SLOTS,
                                  Rangefinder, check_sensors, road_readings)
from torcsrl.envs.tracks.procedural import ProceduralSpec
from torcsrl.envs.traffic import (OPPONENT_RANGE_M, OPPONENT_RGBA, OPPONENT_SECTORS, Traffic, TrafficSpec,
                                  opponent_sectors)
from torcsrl.envs.vehicle import BACKENDS, CarFleet, VehicleParams, make_ground
from torcsrl.envs.world import TRACK_SPACING_M
from torcsrl.utils.bullet import pybullet as p
from torcsrl.utils.seq import as_list

__all__ = ["RaceCore"]


class RaceCore(CarLocator):
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
        self._check_settings(sensors, num_cars, action_mode, start, vehicle_backend, max_steps, lap_limit)
        self._count_cars(num_cars, traffic)
        self._list_tracks(track, procedural, surface, seed)
        self._set_episode_rules(spawn_jitter, offtrack_grace_s, no_progress_s, backwards_m, reward, reward_scale,
                                max_steps, lap_limit, start, action_mode)
        params = self._build_worlds(cars_per_world, vehicle, vehicle_overrides, control_hz, substeps, vehicle_backend)
        self._build_traffic(params)
        self._build_sensors(rangefinder_angles_deg, rangefinder_range_m, camera)
        self._init_books(seed)

    # ------------------------------------------------------------------ construction (in this order)
    def _check_settings(self, sensors: Sequence[str], num_cars: int, action_mode: str, start: str, vehicle_backend: str,
                        max_steps: int, lap_limit: int | None) -> None:
        """The sensor keys, and the arguments checked before anything is built."""
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

    def _count_cars(self, num_cars: int, traffic: Mapping[str, Any] | None) -> None:
        """The learners, the race's opponents (if any) and the number of cars in the world."""
        #: the cars the agent drives (the env's batch); ``n`` counts every car of the world (opponents too)
        self.n_learners = int(num_cars)
        self.traffic_spec = TrafficSpec.from_config(traffic)
        k_opp = self.traffic_spec.opponents if self.traffic_spec is not None else 0
        self.n = self.n_learners * (1 + k_opp)

    def _list_tracks(self, track: str | Sequence[str], procedural: Mapping[str, Any] | None,
                     surface: str | Sequence[str] | None, seed: int | None) -> None:
        """The track slots' names (named tracks, then a procedural pool) and the road surfaces to draw from."""
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

    def _set_episode_rules(self, spawn_jitter: Sequence[float], offtrack_grace_s: float, no_progress_s: float | None,
                           backwards_m: float, reward: str | Mapping[str, float], reward_scale: float, max_steps: int,
                           lap_limit: int | None, start: str, action_mode: str) -> None:
        """The reward, the episode's limits and termination rules, the start and the action layout."""
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

    def _build_worlds(self, cars_per_world: int | None, vehicle: str, vehicle_overrides: Mapping[str, Any] | None,
                      control_hz: float, substeps: int, vehicle_backend: str) -> VehicleParams:
        """The pybullet world(s), each with its ground, and the fleet of every car; returns the vehicle parameters."""
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
        return params

    def _build_traffic(self, params: VehicleParams) -> None:
        """The race's opponents (None: every car alone): their track copies' offsets, collisions and colour."""
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

    def _build_sensors(self, rangefinder_angles_deg: Sequence[float], rangefinder_range_m: float,
                       camera: Mapping[str, Any] | None) -> None:
        """The observation keys of every car, the rangefinder, the track slots and their origins, the camera."""
        #: observation keys computed for every car (the learners' sensors and what frozen-policy opponents read)
        self._all_keys = tuple(k for k in self.sensors if k not in ("pixels", "depth"))
        if self.traffic is not None:
            self._all_keys += tuple(k for k in self.traffic.obs_keys if k not in self._all_keys)
        self._obs_all: dict[str, np.ndarray] = {}
        self.rangefinder = Rangefinder(rangefinder_angles_deg, rangefinder_range_m) if "rangefinder" in self._all_keys else None
        #: one slot per distinct entry: the named tracks loaded now (a bad one fails here), a procedural pool's on first use
        self._geometry = TrackSlots(self.track_names, loaded=self.n_named)
        #: World origin [m] of each track slot: tracks lie 10 km apart, so that cameras never see
        #: another slot's track, and each car drives at its own track's origin.
        self.track_origins = np.array([[k * TRACK_SPACING_M, 0.0] for k in range(len(self._geometry))])
        self._variants: dict[tuple[int, str | None], Any] = {}  # a slot's walls are built on its first use (_variant)
        self.camera = None
        self._camera_cfg = dict(camera) if camera else {}
        if "pixels" in self.sensors or "depth" in self.sensors:
            self._make_camera()

    def _init_books(self, seed: int | None) -> None:
        """The env's generator and every car's episode books, observation and step results (zeros until a reset)."""
        n = self.n
        self.start_back = np.zeros(n)  # how far behind its race's start point each car started [m] (laps count from there)
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
        from torcsrl.envs import camera as _camera  # deferred: the camera (renderer, OpenGL) only for pixels and depth

        self.camera = _camera.CarCameras(self.client, self if self.traffic is None else LearnerView(self), **self._camera_cfg)

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
        if "road" in self.sensors:
            out["road"] = (len(ROAD_SLOTS),)
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
        slots, surf = self._draw_tracks(k)
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
        """Track slots ``[k]`` and surface overrides of ``k`` cars from the env's generator: named tracks or the
        procedural pool, then a track within; then the surfaces."""
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
        self._laps_one(t.length, now, dist)
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
        total = sum(w[k] * terms[k] for k in range(len(self.reward.core_weights)))
        for row, wk in self.reward.extra:
            total = total + wk * terms[row]
        self.rewards = np.array([self.reward.scale * total])
        self.terminated = np.array([term])
        self.truncated = np.array([not term and (int(self.steps[0]) >= self.max_steps or fin)])

    def _laps_one(self, length: float, now: float, dist: float) -> None:
        """:meth:`_laps` for one car in plain floats (the same operations in the same order); ``crossings`` and
        ``lap`` are replaced by new arrays as :meth:`_laps` replaces them, the lap times are written in place."""
        cross = math.floor((float(self.s0[0]) + dist) / length)
        if cross > int(self.crossings[0]):
            lap_time = now - float(self.lap_start_time[0])
            if self.lap_timed[0]:
                self.last_lap_time[0] = lap_time
                best = float(self.best_lap_time[0])
                if best == 0 or lap_time < best:
                    self.best_lap_time[0] = lap_time
            self.lap_start_time[0] = now
            self.lap_timed[0] = True
            self.crossings = np.array([cross], dtype=np.int64)
        self.lap = np.array([max(int(self.lap[0]), math.floor((dist - float(self.start_back[0])) / length))],
                            dtype=np.int64)

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
            if self.n == 1:  # one car: one array from floats (the same float64 products, the same casts)
                vx, vy, vz = fleet.vel_body[0].tolist()
                st = np.array([[float(self.angle[0]), float(self.track_pos[0]), vx * MS_TO_KMH, vy * MS_TO_KMH,
                                vz * MS_TO_KMH, *fleet.wheel_omega[0].tolist(), float(fleet.rpm[0]),
                                float(fleet.gear[0])]], dtype=np.float32)
            else:
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
        if "road" in keys:  # privileged (an asymmetric critic's): the grip under the wheels and the bends ahead
            obs["road"] = road_readings(self.car_tracks, self.s, fleet.wheel_mu.mean(axis=1))
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
