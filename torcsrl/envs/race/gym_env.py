"""The gymnasium face of the race core: :class:`RaceEnv` (``gymnasium.make("torcsrl/Race-v0")``), one car, and
:func:`render_top_down`, its ``rgb_array`` frame.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import EzPickle

from torcsrl.envs import surfaces as _surf
from torcsrl.envs.race.core import RaceCore
from torcsrl.envs.race.rules import TERMINATION_REASONS
from torcsrl.envs.rewards import REWARD_TERMS
from torcsrl.envs.sensors import STATE_BOUNDS, STATE_SLOTS, TELEMETRY_SLOTS
from torcsrl.envs.traffic import OPPONENT_RANGE_M

_REWARD_INFO_KEYS = tuple(f"reward_{name}" for name in REWARD_TERMS)

__all__ = ["RaceEnv", "render_top_down"]


class RaceEnv(gym.Env, EzPickle):
    """Race a full-size car round a track, seen through TORCS-style sensors.

    ## Description
    A raycast car (pybullet; ~1,100 kg, 2.6 m wheelbase, tyre forces from slip scaled by the grip
    of the surface under each wheel) drives on a bundled or generated track. The task is to drive
    fast without leaving the track, as in the TORCS studies (Summers 2022, Andersson et al.).
    ``gymnasium.make("torcsrl/Race-v0", ...)`` observes a ``Dict``; ``gymnasium.make("torcsrl/RaceFlat-v0", ...)``
    takes the same arguments and observes the vector keys as one ``Box`` (:mod:`torcsrl.envs.flat`).

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
    ``Dict`` with the keys chosen by ``sensors`` (default ``("rangefinder", "state")``), float32 unless said:

    - ``rangefinder``: ``Box(-1, 200, (19,))`` [m] — distance to the track edge along beams at
      −90, −75, −60, −45, −30, −20, −15, −10, −5, 0, 5, 10, 15, 20, 30, 45, 60, 75, 90° from the car's
      heading (positive = left; ``rangefinder_angles_deg``, ``rangefinder_range_m`` change them); all −1
      while off the track.
    - ``state``: ``Box((11,))``, slots (:data:`torcsrl.envs.sensors.STATE_SLOTS`):

      | slot | name                           | unit  | meaning                                             |
      |------|--------------------------------|-------|-----------------------------------------------------|
      | 0    | angle_rad                      | rad   | heading vs the track axis, > 0 = pointing left      |
      | 1    | trackPos                       | –     | 0 centreline, +1 left edge, −1 right edge           |
      | 2    | speedX_kmh                     | km/h  | forward speed, car frame                            |
      | 3    | speedY_kmh                     | km/h  | leftward speed, car frame                           |
      | 4    | speedZ_kmh                     | km/h  | upward speed                                        |
      | 5–8  | wheelSpinVel_fl, fr, rl, rr    | rad/s | wheel spin, > 0 rolling forward                     |
      | 9    | rpm                            | 1/min | engine speed                                        |
      | 10   | gear                           | –     | engaged gear                                        |

      Bounds: angle_rad ±π, rpm [0, 20000], gear [0, 10], the rest ±1000 (trackPos beyond ±1: off the track).

    - ``telemetry``: ``Box((9,))``, slots 2–10 of ``state`` (speeds, wheel spin, rpm, gear;
      :data:`torcsrl.envs.sensors.TELEMETRY_SLOTS`): what the car measures on board, without angle_rad and
      trackPos, which need a map.
    - ``opponents``: ``Box(0, 200, (36,))`` [m] — TORCS SCR's opponent sensor: per 10° sector around the car
      (sector 0 straight back, clockwise), the distance to the nearest other car of its race; 200 = free
      (always, without ``traffic``).
    - ``pixels``: ``Box(0, 255, (3, H, W), uint8)`` — RGB from the car-mounted camera (``camera`` settings:
      width, height, field of view, mount).
    - ``depth``: ``Box(0, inf, (1, H, W))`` [m] — the camera's z-depth, capped at its far plane (300 m by default).

    Normalised versions (divide by :func:`torcsrl.envs.sensors.obs_scale`) are in about [−1, 1].

    ## Rewards
    ``reward_scale · Σ weight · term`` over the named terms of :mod:`torcsrl.envs.rewards` (θ: the car's
    angle to the track axis; v_x: its forward speed [m/s]):

    - ``speed_cos`` v_x cos θ [m/s]; ``speed_sin`` −v_x |sin θ| [m/s]; ``track_pos`` −v_x |trackPos| [m/s];
    - ``progress`` Δs along the centreline this step [m]; ``termination`` 1 on the step that terminates;
    - ``steer_change`` |steering command − the previous step's| [action units];
    - with ``traffic``: ``collision`` contact impulse with other cars [kN s], ``positions`` race positions
      gained (− lost), ``gap`` the safe-distance shortfall to the car ahead [-], ``blocking`` lateral moves
      towards the line of a car close behind [m] (0 without traffic).

    ``reward`` takes a preset (``summers_initial``, ``summers_final`` (default: Summers 2022's
    v_x (cos θ − |sin θ|) with −1 on termination), ``lau``, ``progress``, ``race``) or weights by term.
    Each term is in ``info`` as ``reward_<term>``.

    ## Starting State
    At rest on the start/finish line (``start="grid"``) or at a uniformly drawn arc length
    (``start="random"``), optionally jittered laterally and in yaw (``spawn_jitter``). With several
    tracks (or surfaces) one is drawn per episode from the env's seed.

    ## Episode End
    *Terminated* (``info["termination"]`` names why): ``off_track``, |trackPos| > 1 for longer than
    ``offtrack_grace_s``; ``backwards``, ``backwards_m`` behind the furthest point reached; ``no_progress``,
    no new furthest point for ``no_progress_s``; ``flipped``, the car on its side or roof. *Truncated*:
    ``max_steps`` control steps, or ``lap_limit`` laps completed (``info["finished"]`` is then True).
    Never both.

    ## Info
    distFromStart [m], distRaced [m], lap (completed laps), curLapTime, lastLapTime, bestLapTime [s]
    (0 until set, as in TORCS), surfaceMu [-] (mean friction under the wheels), ``reward_<term>`` for every
    reward term, ``termination`` (the reason, "" if none), ``finished``, ``track``, ``surface``; with
    ``traffic`` also racePos, overtakes, collisions, damage, impulse, gapAhead.

    ## Arguments
    Every keyword of :class:`~torcsrl.envs.race.core.RaceCore` (defaults in brackets), among them:
    ``track`` (a name, ``set:<name>``, ``gen-<seed>`` or a list) [``"road_flow"``]; ``surface`` [the track's];
    ``sensors`` [``("rangefinder", "state")``]; ``reward`` [``"summers_final"``]; ``reward_scale`` [1.0];
    ``max_steps`` [2500]; ``lap_limit`` [None]; ``start`` [``"grid"``]; ``spawn_jitter`` [(0, 0)];
    ``offtrack_grace_s`` [0.0]; ``no_progress_s`` [5.0]; ``backwards_m`` [10.0];
    ``action_mode`` [``"combined"``]; ``vehicle`` [``"default"``]; ``control_hz`` [50] and ``substeps`` [4];
    ``camera``; ``traffic``; ``procedural``; ``seed``. Plus ``render_mode``: ``"rgb_array"`` gives a top-down 400×400
    frame of the track and the car. One car only (``num_cars=1``).

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
            elif key == "road":  # mu in [0, 2]; a stretch's mean curvature at most pi over its 20 m
                lim = np.float32(np.pi / 20.0)
                obs_spaces[key] = spaces.Box(np.array([0.0] + [-lim] * (shape[0] - 1), np.float32),
                                             np.array([2.0] + [lim] * (shape[0] - 1), np.float32), dtype=np.float32)
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
                box = self.observation_space[k]  # np.clip's result, in two plain ufunc calls (a third of its time)
                np.minimum(np.maximum(obs[k], box.low, out=obs[k]), box.high, out=obs[k])
        return obs

    def _info(self) -> dict[str, Any]:
        c = self.core
        if c.traffic is None:  # RaceCore.info()'s values for the one car, read as floats without its [N] copies
            mu = c.fleet.wheel_mu[0].tolist()
            info = {"distFromStart": float(c.s[0]), "distRaced": float(c.dist_raced[0]), "lap": int(c.lap[0]),
                    "curLapTime": float(c.time[0] - c.lap_start_time[0]) if c.lap_timed[0] else 0.0,
                    "lastLapTime": float(c.last_lap_time[0]), "bestLapTime": float(c.best_lap_time[0]),
                    "surfaceMu": (mu[0] + mu[1] + mu[2] + mu[3]) / 4.0}
            info.update(zip(_REWARD_INFO_KEYS, c.terms[:, 0].tolist()))
        else:
            info = {k: (int(v[0]) if k in ("lap", "racePos", "overtakes", "collisions") else float(v[0]))
                    for k, v in c.info().items()}
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
    import cv2  # deferred: OpenCV (~0.1 s) only draws the rgb_array frame

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
