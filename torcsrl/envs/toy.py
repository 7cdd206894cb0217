"""ToyRace-v0: a fast, pybullet-free race env with the real env's keys and specs.

A kinematic point-car drives counter-clockwise around an analytic *stadium* track (two
straights joined by two half circles). Everything is closed-form and vectorised over cars in
torch, so one step of N cars costs a few hundred microseconds: algorithm tests and smoke runs
use it instead of the pybullet world (STYLE §14). Same contract as
``torcsrl.envs.make_env``: :func:`make_toy_env` takes the same arguments.

Geometry (track frame, metres): the *spine* is the segment ``[-L/2, L/2] x {0}``; the centreline
lies at distance ``R`` from it, the road between distances ``R - W`` and ``R + W``. ``s = 0`` is
the start/finish line at ``(0, -R)``, the car drives towards ``+x`` there. ``d > 0`` is to the
LEFT of the direction of travel (towards the infield), ``|d| > W`` is off the track.

Observation keys (batch shape ``[]`` for one car, ``[N]`` for N cars):

* ``"rangefinder"`` float32 [19] [m]: distance from the car to the track edge along 19 beams at
  :data:`BEAM_ANGLES_DEG` (0 = straight ahead, > 0 = left), capped at 200 m; all -1 off track.
* ``"state"`` float32 [6]: :data:`STATE_SLOTS`:
  ``speed`` [m/s] >= 0 along the heading; ``angle`` [rad] heading minus track heading, wrapped to
  [-pi, pi]; ``track_pos`` [-] d / W (+1 = left edge, TORCS trackPos with the opposite sign
  convention kept as in INTERFACES: d > 0 left); ``yaw_rate`` [rad/s] (> 0 = turning left);
  ``steer`` [rad] the wheel angle applied; ``throttle_brake`` [-] the last command.
* ``"pixels"`` uint8 [3, H, W] (when ``"pixels"`` is in ``sensors``): an egocentric top-down
  view, the car at the bottom centre facing up, :data:`PIXEL_VIEW_M` metres ahead; road grey,
  edges white, grass green.
* info keys: ``"laps"`` int64 [1] completed laps, ``"lap_time"`` float32 [1] [s] time of the
  last completed lap (0 before the first), ``"distance"`` float32 [1] [m] signed progress along
  the centreline since the reset.

Action ``"action"`` float32 [2] in [-1, 1]: ``(steer, throttle_brake)``; steer +1 = full left
lock (:data:`MAX_STEER` rad); throttle_brake > 0 accelerates (up to ``ACCEL`` m/s^2), < 0 brakes
(up to ``BRAKE`` m/s^2). The yaw rate is capped by the grip limit ``v * yaw_rate <= mu * g``
(``mu`` from :mod:`torcsrl.envs.surfaces`), so entering a bend too fast runs wide.

Reward (``reward="summers_final"``, after Summers 2022): per step
``(v cos(angle) - v |sin(angle)| - v |d| / W) / V_REF`` (dimensionless, at most ~1), and
:data:`OFF_TRACK_PENALTY` when the car leaves the track. ``reward="progress"``: signed metres
along the centreline this step divided by ``V_REF * dt``.

Ends: ``terminated`` when the car leaves the track (|d| > W); ``truncated`` at ``max_steps``
control steps or when ``lap_limit`` laps are completed. ``done = terminated | truncated``.

Randomness comes only from the env's own ``numpy.random.Generator`` (``set_seed``): ``start="grid"``
places every car on the start line at rest (deterministic); ``start="random"`` draws s, d,
heading error and speed from the generator.

Version history: v0 — first version.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

#: Beam directions of the 19 rangefinders [deg], 0 = ahead, > 0 = left (TORCS default spread).
BEAM_ANGLES_DEG: tuple[float, ...] = (
    -90, -75, -60, -45, -30, -20, -15, -10, -5, 0, 5, 10, 15, 20, 30, 45, 60, 75, 90
)
RANGE_M = 200.0  #: rangefinder range [m]
STATE_SLOTS: tuple[str, ...] = ("speed", "angle", "track_pos", "yaw_rate", "steer", "throttle_brake")
#: (low, high) of each state slot, same order as STATE_SLOTS; readings are clamped into these.
STATE_BOUNDS: tuple[tuple[float, float], ...] = (
    (0.0, 60.0), (-math.pi, math.pi), (-2.0, 2.0), (-10.0, 10.0), (-0.5, 0.5), (-1.0, 1.0)
)
SUPPORTED_SENSORS = ("rangefinder", "state", "pixels")
MAX_STEER = 0.45  #: full lock wheel angle [rad]
WHEELBASE = 2.6  #: [m]
ACCEL = 5.0  #: full-throttle acceleration [m/s^2]
BRAKE = 10.0  #: full-brake deceleration [m/s^2]
DRAG = ACCEL / 45.0**2  #: quadratic drag [1/m] (top speed ~45 m/s)
G = 9.81  #: [m/s^2]
V_REF = 40.0  #: speed that scales the reward to ~1 per step [m/s]
OFF_TRACK_PENALTY = -1.0  #: reward on the step that leaves the track [-]
PIXEL_VIEW_M = 60.0  #: the pixel view covers PIXEL_VIEW_M x PIXEL_VIEW_M metres
ROAD_RGB, EDGE_RGB, GRASS_RGB, CAR_RGB = (110, 110, 110), (240, 240, 240), (40, 140, 40), (220, 30, 30)


@dataclass(frozen=True)
class StadiumTrack:
    """A stadium-shaped closed track.

    Attributes:
        name: track name.
        straight: length of each straight [m].
        radius: centreline radius of the two bends [m].
        half_width: half the road width W [m].
    """

    name: str
    straight: float
    radius: float
    half_width: float

    @property
    def length(self) -> float:
        """Centreline length [m]."""
        return 2 * self.straight + 2 * math.pi * self.radius

    def project(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frenet coordinates of points: ``(s [m] in [0, length), d [m] > 0 left, track heading [rad])``."""
        a, r = self.straight / 2, self.radius
        px = np.clip(x, -a, a)
        phi = np.arctan2(y, x - px)
        rho = np.hypot(x - px, y)
        d = r - rho
        # s along the centreline, piece by piece (bottom straight right half, right bend, top, left bend, bottom left half)
        s_bottom = np.where(x >= 0, x, self.length + x)
        s_top = a + math.pi * r + (a - x)
        s_right = a + r * (phi + math.pi / 2)
        s_left = a + math.pi * r + 2 * a + r * np.mod(phi - math.pi / 2, 2 * math.pi)
        on_straight = (x >= -a) & (x <= a)
        s = np.where(on_straight, np.where(y < 0, s_bottom, s_top), np.where(x > a, s_right, s_left))
        heading = np.where(on_straight, np.where(y < 0, np.zeros_like(x), np.full_like(x, math.pi)), phi + math.pi / 2)
        return np.mod(s, self.length), d, heading

    def to_world(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World ``(x, y, heading)`` of Frenet points (s [m], d [m] > 0 left)."""
        a, r, L = self.straight / 2, self.radius, self.length
        s = np.mod(s, L)
        rho = r - d
        b1, b2, b3 = a, a + math.pi * r, 3 * a + math.pi * r
        b4 = b3 + math.pi * r
        # bottom straight (s < b1 or s >= b4)
        xb = np.where(s < b1, s, s - L)
        # right bend
        phi_r = (s - b1) / r - math.pi / 2
        # top straight
        xt = a - (s - b2)
        # left bend
        phi_l = (s - b3) / r + math.pi / 2
        x = np.where(s < b1, xb, np.where(s < b2, a + rho * np.cos(phi_r), np.where(s < b3, xt, np.where(s < b4, -a + rho * np.cos(phi_l), xb))))
        y = np.where(s < b1, -rho, np.where(s < b2, rho * np.sin(phi_r), np.where(s < b3, rho, np.where(s < b4, rho * np.sin(phi_l), -rho))))
        h = np.where(s < b1, 0.0 * s, np.where(s < b2, phi_r + math.pi / 2, np.where(s < b3, 0.0 * s + math.pi, np.where(s < b4, phi_l + math.pi / 2, 0.0 * s))))
        return x, y, h

    def rangefinder(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, beams: np.ndarray) -> np.ndarray:
        """Exact distances [m] from points ``[N]`` along beams ``[B]`` (rad, relative to yaw) to the nearest edge, capped at RANGE_M."""
        ang = yaw[:, None] + beams[None, :]
        dx, dy = np.cos(ang), np.sin(ang)
        ox, oy = np.broadcast_to(x[:, None], dx.shape), np.broadcast_to(y[:, None], dy.shape)
        inf = np.full_like(dx, float("inf"))
        a = self.straight / 2
        r_out, r_in = self.radius + self.half_width, self.radius - self.half_width
        exit_out = np.full_like(dx, -float("inf"))
        enter_in = inf
        for cx in (-a, a):  # the two disks of each capsule
            for r, outer in ((r_out, True), (r_in, False)):
                bx, by = ox - cx, oy
                b = bx * dx + by * dy
                disc = b * b - (bx * bx + by * by - r * r)
                hit = disc >= 0
                sq = np.sqrt(np.maximum(disc, 0.0))
                if outer:
                    exit_out = np.where(hit, np.maximum(exit_out, -b + sq), exit_out)
                else:
                    t0 = -b - sq
                    enter_in = np.where(hit & (t0 >= 0), np.minimum(enter_in, t0), enter_in)
        # the rectangles [-a, a] x [-r, r] (slab method)
        sdx = np.where(np.abs(dx) < 1e-9, np.full_like(dx, 1e-9), dx)
        sdy = np.where(np.abs(dy) < 1e-9, np.full_like(dy, 1e-9), dy)
        tx1, tx2 = (-a - ox) / sdx, (a - ox) / sdx
        txmin, txmax = np.minimum(tx1, tx2), np.maximum(tx1, tx2)
        for r, outer in ((r_out, True), (r_in, False)):
            ty1, ty2 = (-r - oy) / sdy, (r - oy) / sdy
            t_in = np.maximum(txmin, np.minimum(ty1, ty2))
            t_out = np.minimum(txmax, np.maximum(ty1, ty2))
            hit = t_in <= t_out
            if outer:
                exit_out = np.where(hit, np.maximum(exit_out, t_out), exit_out)
            else:
                enter_in = np.where(hit & (t_in >= 0), np.minimum(enter_in, t_in), enter_in)
        return np.minimum(exit_out, enter_in).clip(0.0, RANGE_M)


#: Toy tracks by name (workers of a multi-process collector may each get one).
TRACKS: dict[str, StadiumTrack] = {
    t.name: t
    for t in (
        StadiumTrack("stadium", straight=100.0, radius=40.0, half_width=6.0),
        StadiumTrack("oval", straight=40.0, radius=60.0, half_width=7.0),
        StadiumTrack("hairpin", straight=160.0, radius=20.0, half_width=5.0),
    )
}


def _surface_mu(surface: str | None) -> float:
    from torcsrl.envs import surfaces  # noqa: PLC0415  (pure data module, no pybullet)

    return float(surfaces.get(surface or "asphalt").mu)


class ToyRaceEnv(EnvBase):
    """ToyRace-v0 (see the module docstring for every key, unit and rule)."""

    batch_locked = True

    def __init__(
        self,
        track: str = "stadium",
        surface: str | None = None,
        sensors: Sequence[str] = ("rangefinder", "state"),
        reward: str = "summers_final",
        num_cars: int = 1,
        max_steps: int = 1000,
        lap_limit: int | None = None,
        start: str = "grid",
        seed: int | None = None,
        device: str = "cpu",
        camera: dict | None = None,
        dt: float = 0.1,
    ):
        if track not in TRACKS:
            raise ValueError(f"unknown toy track {track!r}; known toy tracks: {', '.join(TRACKS)}")
        bad = [s for s in sensors if s not in SUPPORTED_SENSORS]
        if bad:
            raise ValueError(f"toy env has no sensor {bad[0]!r}; supported: {', '.join(SUPPORTED_SENSORS)}")
        if reward not in ("summers_final", "progress"):
            raise ValueError(f"unknown toy reward {reward!r}; known: summers_final, progress")
        if start not in ("grid", "random"):
            raise ValueError(f"unknown start {start!r}; known: grid, random")
        if num_cars < 1 or max_steps < 1:
            raise ValueError(f"num_cars and max_steps must be >= 1, got {num_cars}, {max_steps}")
        batch = torch.Size([num_cars]) if num_cars > 1 else torch.Size([])
        super().__init__(device=device, batch_size=batch)
        self.track = TRACKS[track]
        self.mu = _surface_mu(surface)
        self.sensors = tuple(sensors)
        self.reward_name, self.start, self.dt = reward, start, float(dt)
        self.max_steps, self.lap_limit, self.n = int(max_steps), lap_limit, num_cars
        cam = dict(camera or {})
        self.img_h, self.img_w = int(cam.get("height", 64)), int(cam.get("width", 64))
        self.beams = np.deg2rad(np.array(BEAM_ANGLES_DEG, dtype=np.float64))
        self._lo = np.array([b[0] for b in STATE_BOUNDS])
        self._hi = np.array([b[1] for b in STATE_BOUNDS])
        if "pixels" in self.sensors:  # pixel centres in the car frame (x forward, y left) [m]
            u = (np.arange(self.img_w) + 0.5) / self.img_w - 0.5
            v = 1.0 - (np.arange(self.img_h) + 0.5) / self.img_h
            gv, gu = np.meshgrid(v, u, indexing="ij")
            self._grid_fwd = (gv * PIXEL_VIEW_M - 5.0).reshape(-1)
            self._grid_left = (-gu * PIXEL_VIEW_M).reshape(-1)
        f32 = torch.float32
        lo, hi = torch.tensor(self._lo, dtype=f32), torch.tensor(self._hi, dtype=f32)
        obs = {}
        if "rangefinder" in self.sensors:
            obs["rangefinder"] = Bounded(-1.0, RANGE_M, shape=(*batch, 19), dtype=f32, device=device)
        if "state" in self.sensors:
            obs["state"] = Bounded(lo.expand(*batch, 6).clone(), hi.expand(*batch, 6).clone(), shape=(*batch, 6), dtype=f32, device=device)
        if "pixels" in self.sensors:
            obs["pixels"] = Bounded(0, 255, shape=(*batch, 3, self.img_h, self.img_w), dtype=torch.uint8, device=device)
        obs["laps"] = Unbounded(shape=(*batch, 1), dtype=torch.int64, device=device)
        obs["lap_time"] = Unbounded(shape=(*batch, 1), dtype=f32, device=device)
        obs["distance"] = Unbounded(shape=(*batch, 1), dtype=f32, device=device)
        self.observation_spec = Composite(obs, shape=batch, device=device)
        self.action_spec = Bounded(-1.0, 1.0, shape=(*batch, 2), dtype=f32, device=device)
        self.reward_spec = Unbounded(shape=(*batch, 1), dtype=f32, device=device)
        self.done_spec = Composite(
            {k: Categorical(2, shape=(*batch, 1), dtype=torch.bool, device=device) for k in ("done", "terminated", "truncated")},
            shape=batch,
            device=device,
        )
        self.rng = np.random.default_rng(0 if seed is None else int(seed))
        floats = ("x", "y", "yaw", "v", "yaw_rate", "steer", "throttle", "t", "lap_t0", "lap_time", "dist", "s")
        self._sim = {k: np.zeros(num_cars) for k in floats}
        self._sim["steps"] = np.zeros(num_cars, dtype=np.int64)
        self._sim["laps"] = np.zeros(num_cars, dtype=np.int64)

    # ---- seeding and exact-resume state -------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(0 if seed is None else int(seed))

    def get_sim_state(self) -> dict:
        """Every piece of dynamic state (cars, counters, the generator) as tensors and plain Python values."""
        out: dict = {k: torch.from_numpy(v.copy()) for k, v in self._sim.items()}
        out["rng"] = self.rng.bit_generator.state
        return out

    def set_sim_state(self, state: dict) -> None:
        """Restore what :meth:`get_sim_state` returned."""
        for k in self._sim:
            self._sim[k] = state[k].numpy().copy()
        self.rng.bit_generator.state = state["rng"]

    # ---- TorchRL hooks ------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.n).cpu().numpy()
        idx = np.arange(self.n) if mask is None else np.flatnonzero(mask)
        k = idx.size
        sim, trk = self._sim, self.track
        if self.start == "grid":
            s0, d0, dpsi, v0 = np.zeros(k), np.zeros(k), np.zeros(k), np.zeros(k)
        else:
            u = self.rng.random((k, 4))
            s0 = u[:, 0] * trk.length
            d0 = (u[:, 1] - 0.5) * trk.half_width
            dpsi = (u[:, 2] - 0.5) * 0.4
            v0 = u[:, 3] * 15.0
        x, y, h = trk.to_world(s0, d0)
        for name, val in (("x", x), ("y", y), ("yaw", h + dpsi), ("v", v0), ("s", s0)):
            sim[name][idx] = val
        for name in ("yaw_rate", "steer", "throttle", "t", "lap_t0", "lap_time", "dist", "steps", "laps"):
            sim[name][idx] = 0
        obs = self._observe()
        f = torch.zeros(*self.batch_size, 1, dtype=torch.bool, device=self.device)
        obs.update({"done": f, "terminated": f.clone(), "truncated": f.clone()})
        return obs

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        sim, trk, dt = self._sim, self.track, self.dt
        act = tensordict.get("action").detach().reshape(self.n, 2).cpu().numpy().astype(np.float64)
        act = np.clip(act, -1.0, 1.0)
        steer = act[:, 0] * MAX_STEER
        u = act[:, 1]
        v = sim["v"]
        acc = np.where(u > 0, u * ACCEL, u * BRAKE) - DRAG * v * v - 0.1
        v = np.maximum(v + acc * dt, 0.0)
        w_lim = self.mu * G / np.maximum(v, 1.0)
        yaw_rate = np.clip(v * np.tan(steer) / WHEELBASE, -w_lim, w_lim)
        yaw = sim["yaw"] + yaw_rate * dt
        x = sim["x"] + v * np.cos(yaw) * dt
        y = sim["y"] + v * np.sin(yaw) * dt
        s, d, heading = trk.project(x, y)
        ds = np.mod(s - sim["s"] + trk.length / 2, trk.length) - trk.length / 2
        dist = sim["dist"] + ds
        t = sim["t"] + dt
        laps = np.maximum(np.floor(dist / trk.length), 0).astype(np.int64)
        new_lap = laps > sim["laps"]
        sim["lap_time"] = np.where(new_lap, t - sim["lap_t0"], sim["lap_time"])
        sim["lap_t0"] = np.where(new_lap, t, sim["lap_t0"])
        sim.update(x=x, y=y, yaw=yaw, v=v, yaw_rate=yaw_rate, steer=steer, throttle=u, t=t, s=s, dist=dist)
        sim["laps"] = np.maximum(laps, sim["laps"])
        sim["steps"] = sim["steps"] + 1
        off = np.abs(d) > trk.half_width
        psi = np.mod(yaw - heading + math.pi, 2 * math.pi) - math.pi
        obs = self._observe(d=d, psi=psi)
        if self.reward_name == "summers_final":
            r = v * (np.cos(psi) - np.abs(np.sin(psi)) - np.abs(d) / trk.half_width) / V_REF
        else:
            r = ds / (V_REF * dt)
        r = np.where(off, OFF_TRACK_PENALTY, r)
        trunc = sim["steps"] >= self.max_steps
        if self.lap_limit is not None:
            trunc = trunc | (sim["laps"] >= self.lap_limit)
        trunc = trunc & ~off
        bs = (*self.batch_size, 1)
        obs.update(
            {
                "reward": torch.from_numpy(r.astype(np.float32)).reshape(bs),
                "terminated": torch.from_numpy(off).reshape(bs),
                "truncated": torch.from_numpy(trunc).reshape(bs),
                "done": torch.from_numpy(off | trunc).reshape(bs),
            }
        )
        return obs

    # ---- sensors ----------------------------------------------------------------------
    def _observe(self, d: np.ndarray | None = None, psi: np.ndarray | None = None) -> TensorDict:
        sim, trk = self._sim, self.track
        if d is None:
            _, d, heading = trk.project(sim["x"], sim["y"])
            psi = np.mod(sim["yaw"] - heading + math.pi, 2 * math.pi) - math.pi
        off = np.abs(d) > trk.half_width
        bs = self.batch_size
        out = {}
        if "rangefinder" in self.sensors:
            rf = trk.rangefinder(sim["x"], sim["y"], sim["yaw"], self.beams)
            out["rangefinder"] = torch.from_numpy(np.where(off[:, None], -1.0, rf).astype(np.float32)).reshape(*bs, 19)
        if "state" in self.sensors:
            st = np.stack([sim["v"], psi, d / trk.half_width, sim["yaw_rate"], sim["steer"], sim["throttle"]], -1)
            out["state"] = torch.from_numpy(np.clip(st, self._lo, self._hi).astype(np.float32)).reshape(*bs, 6)
        if "pixels" in self.sensors:
            out["pixels"] = self._render().reshape(*bs, 3, self.img_h, self.img_w)
        out["laps"] = torch.from_numpy(sim["laps"].copy()).reshape(*bs, 1)
        out["lap_time"] = torch.from_numpy(sim["lap_time"].astype(np.float32)).reshape(*bs, 1)
        out["distance"] = torch.from_numpy(sim["dist"].astype(np.float32)).reshape(*bs, 1)
        return TensorDict(out, batch_size=bs, device=self.device)

    def _render(self) -> torch.Tensor:
        sim, trk = self._sim, self.track
        c, s_ = np.cos(sim["yaw"])[:, None], np.sin(sim["yaw"])[:, None]
        gx = sim["x"][:, None] + c * self._grid_fwd - s_ * self._grid_left
        gy = sim["y"][:, None] + s_ * self._grid_fwd + c * self._grid_left
        _, d, _ = trk.project(gx, gy)
        ad = np.abs(d)
        road = ad <= trk.half_width
        cls = road.astype(np.int64) + (road & (ad > trk.half_width - 0.6))
        palette = np.array([GRASS_RGB, ROAD_RGB, EDGE_RGB], dtype=np.uint8)
        img = palette[cls].reshape(self.n, self.img_h, self.img_w, 3).transpose(0, 3, 1, 2).copy()
        # the car: a small red block at the bottom centre
        r0 = self.img_h - max(2, round(5.0 / PIXEL_VIEW_M * self.img_h)) - 1
        cw = max(1, self.img_w // 32)
        img[:, :, r0 : r0 + 2, self.img_w // 2 - cw : self.img_w // 2 + cw] = np.array(CAR_RGB, dtype=np.uint8)[:, None, None]
        return torch.from_numpy(img)


def make_toy_env(
    track: str = "stadium",
    surface: str | None = None,
    sensors: Sequence[str] = ("rangefinder", "state"),
    reward: str = "summers_final",
    num_cars: int = 1,
    max_steps: int = 1000,
    lap_limit: int | None = None,
    start: str = "grid",
    seed: int | None = None,
    device: str = "cpu",
    camera: dict | None = None,
    dt: float = 0.1,
) -> ToyRaceEnv:
    """Build ToyRace-v0 with ``torcsrl.envs.make_env``'s arguments (``dt``: control step [s])."""
    env = ToyRaceEnv(track, surface, sensors, reward, num_cars, max_steps, lap_limit, start, seed, device, camera, dt)
    if seed is not None:
        env.set_seed(int(seed))
    return env
