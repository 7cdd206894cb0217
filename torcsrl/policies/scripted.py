"""The scripted drivers that are no teachers: the expert driven from observations (:class:`ExpertPolicy`), a
sensor-only driver in the style of the TORCS SCR sample robot (:class:`HeuristicPolicy`) and random actions
(:class:`RandomPolicy`, the floor R_random of the report)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from torcsrl.policies.base import EpisodeContext, Policy, PolicyError

# A built-in driver's fingerprint is the hash of its class's source (report caches and result rows are keyed by it):
# the driver classes below are kept to the byte, so they keep the local names they were written with
# (_code_fingerprint, _state_slot) and their imports of the env modules inside their methods.
from torcsrl.policies.base import code_fingerprint as _code_fingerprint
from torcsrl.policies.base import state_slot as _state_slot

__all__ = ["ExpertPolicy", "HeuristicPolicy", "RandomPolicy"]


# --------------------------------------------------------------------------------------------
# The expert, driven from observations
# --------------------------------------------------------------------------------------------
class ExpertPolicy(Policy):
    """The scripted expert (:class:`torcsrl.envs.expert.ExpertDriver`) as a policy over observations.

    The driver needs the car's pose, velocities and wheel spin. They are rebuilt each step from
    the ``state`` observation (angle to the track axis, trackPos, speedX/Y [km/h], wheel spin)
    and the lap position ``info/distFromStart`` [m] with the track map: ``d`` = trackPos times
    the half-width on that side, ``(x, y) = to_world(s, d)``, ``yaw = heading(s) + angle``.
    So a degraded ``state`` degrades the expert; it never reads the rangefinder.

    Args:
        mu_margin: fraction of the road's grip the expert's speed profile uses.
        vehicle: vehicle parameter file (must be the env's).
        line: ``"racing"`` (minimum curvature: where it drives depends on the map beyond what the
            rangefinder shows) or ``"centre"`` (the track axis at the centre line's speed profile: a
            rangefinder student can see what it follows; ``expert_centre``).
        state_key: where the raw (un-normalised) ``state`` is read; ``"state_clean"`` under a
            :class:`~torcsrl.transforms.KeepClean` when the policy's ``state`` is scaled or degraded
            (the demonstration writer does this).
    """

    name = "expert"

    def __init__(self, mu_margin: float = 0.85, vehicle: str = "default", state_key: str = "state",
                 line: str = "racing") -> None:
        from torcsrl.envs import expert as _expert
        from torcsrl.envs.vehicle import VehicleParams

        if line not in _expert.LINES:
            raise PolicyError(f"ExpertPolicy line={line!r}; allowed: {', '.join(_expert.LINES)}")
        self.params = VehicleParams.load(vehicle)
        self.mu_margin = float(mu_margin)
        self.line = line
        self.spec = "expert" if line == "racing" else f"expert_{line}"
        self.obs_keys = ("state",)
        self.state_key = state_key
        self.env_overrides = {"sensors": ("state",)}
        self.fingerprint = _code_fingerprint(ExpertPolicy, _expert) + ("" if line == "racing" else f"-{line}")
        self._drivers: dict[tuple[str, str], Any] = {}
        self.driver = None
        self.track = None
        self._i = {n: _state_slot(n) for n in ("angle_rad", "trackPos", "speedX_kmh", "speedY_kmh", "wheelSpinVel_fl")}

    def reset(self, ctx: EpisodeContext) -> None:
        t = ctx.track
        key = (t.name, t.default_surface, round(float(t.length), 3))
        if key not in self._drivers:
            from torcsrl.envs import expert as _expert

            self._drivers[key] = _expert.ExpertDriver(t, self.params, mu_margin=self.mu_margin, line=self.line)
        self.driver = self._drivers[key]
        self.track = t
        self.driver.reset(0.0)
        self._first = True
        self._dt = float(ctx.dt)
        self._prev_yaw: float | None = None

    def _car(self, td: TensorDictBase) -> SimpleNamespace:
        st = td.get(self.state_key).reshape(-1).tolist()
        s = float(td.get(("info", "distFromStart")).reshape(-1)[0])
        t = self.track
        s = s % t.length
        angle, tp = st[self._i["angle_rad"]], st[self._i["trackPos"]]
        wl, wr = t.width(s)
        d = tp * float(wl) if tp >= 0 else tp * float(wr)
        x, y = (float(v) for v in t.to_world(s, d))
        yaw = float(t.heading(s)) + angle
        vx, vy = st[self._i["speedX_kmh"]] / 3.6, st[self._i["speedY_kmh"]] / 3.6
        w0 = self._i["wheelSpinVel_fl"]
        # the yaw rate is not observed: a finite difference of the rebuilt yaw
        yaw_rate = 0.0 if self._prev_yaw is None else ((yaw - self._prev_yaw + math.pi) % (2 * math.pi) - math.pi) / self._dt
        self._prev_yaw = yaw
        c, sn = math.cos(yaw), math.sin(yaw)
        return SimpleNamespace(pos=np.array([[x, y, 0.0]]), yaw=np.array([yaw]), vel_body=np.array([[vx, vy, 0.0]]),
                               vel_world=np.array([[vx * c - vy * sn, vx * sn + vy * c, 0.0]]), yaw_rate=np.array([yaw_rate]),
                               speed=np.array([math.hypot(vx, vy)]), wheel_omega=np.array([st[w0:w0 + 4]]),
                               dt_control=self._dt)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        if self.driver is None:
            raise RuntimeError("ExpertPolicy.reset(ctx) must be called with the episode's track first")
        car = self._car(td)
        if self._first:  # locate the car from scratch once per episode
            s, _ = self.driver.track.project(car.pos[0, :2])
            self.driver.reset(float(s))
            self._first = False
        steer, throttle, brake = self.driver.act(car, 0)
        td.set("action", torch.tensor([steer, throttle - brake], dtype=torch.float32).reshape(*td.batch_size, 2))
        return td


# --------------------------------------------------------------------------------------------
# A sensor-only driver
# --------------------------------------------------------------------------------------------
class HeuristicPolicy(Policy):
    """A rangefinder + state driver in the style of the TORCS SCR sample robot.

    Steering: towards the track axis (``-k_angle * angle - k_pos * trackPos``) plus a pull
    towards the beam that sees furthest ahead (front beams within +-45 deg). Speed: the target is
    ``sqrt(2 a d)`` for the free distance ``d`` straight ahead (median of the three front beams),
    capped; throttle/brake by a proportional controller. Off the track (beams read -1) it steers
    back to the axis slowly.
    """

    name = "heuristic"

    def __init__(self, k_angle: float = 1.6, k_pos: float = 0.35, k_beam: float = 0.9, decel: float = 6.0,
                 v_min_kmh: float = 45.0, v_max_kmh: float = 220.0, max_steer_rad: float | None = None) -> None:
        from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG
        from torcsrl.envs.vehicle import VehicleParams

        self.spec = "heuristic"
        self.obs_keys = ("rangefinder", "state")
        self.env_overrides = {"sensors": ("rangefinder", "state")}
        self.fingerprint = _code_fingerprint(HeuristicPolicy)
        self.k_angle, self.k_pos, self.k_beam = k_angle, k_pos, k_beam
        self.decel = decel
        self.v_min, self.v_max = v_min_kmh / 3.6, v_max_kmh / 3.6
        self.max_steer = max_steer_rad if max_steer_rad is not None else VehicleParams.load("default").max_steer
        self.angles = np.radians(np.asarray(RANGEFINDER_ANGLES_DEG, dtype=float))
        self.front = np.flatnonzero(np.abs(self.angles) <= np.radians(45.0) + 1e-9)
        self.ahead = np.argsort(np.abs(self.angles))[:3]
        self.obs_shapes = {"rangefinder": (len(self.angles),)}
        self._ia, self._ip, self._iv = _state_slot("angle_rad"), _state_slot("trackPos"), _state_slot("speedX_kmh")

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        r = td.get("rangefinder").reshape(-1).numpy()
        st = td.get("state").reshape(-1).numpy()
        angle, tp, v = float(st[self._ia]), float(st[self._ip]), float(st[self._iv]) / 3.6
        steer = -(self.k_angle * angle + self.k_pos * tp)
        if (r >= 0).any():
            f = r[self.front]
            j = int(np.argmax(f))
            steer += self.k_beam * float(self.angles[self.front][j]) * min(1.0, 60.0 / max(float(f[j]), 1.0))
            d = float(np.median(r[self.ahead]))
            v_target = min(self.v_max, max(self.v_min, math.sqrt(2.0 * self.decel * max(d - 10.0, 0.0))))
        else:
            v_target = self.v_min
        steer = max(-1.0, min(1.0, steer / max(self.max_steer, 1e-3) * 0.5))
        err = v_target - v
        tb = max(-1.0, min(1.0, 0.25 * err + (0.1 if err > 0 else 0.0)))
        td.set("action", torch.tensor([steer, tb], dtype=torch.float32).reshape(*td.batch_size, 2))
        return td


# --------------------------------------------------------------------------------------------
# Random actions
# --------------------------------------------------------------------------------------------
class RandomPolicy(Policy):
    """Uniform random actions in [-1, 1], from a generator seeded at every episode start."""

    name = "random"

    def __init__(self, action_dim: int = 2) -> None:
        self.spec = "random"
        self.obs_keys = ()
        self.env_overrides = {}
        self.action_dim = int(action_dim)
        self.fingerprint = _code_fingerprint(RandomPolicy)
        self.gen = torch.Generator().manual_seed(0)

    def reset(self, ctx: EpisodeContext) -> None:
        self.gen.manual_seed(int(ctx.seed) & ((1 << 63) - 1))

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        a = torch.rand(*td.batch_size, self.action_dim, generator=self.gen) * 2.0 - 1.0
        td.set("action", a)
        return td
