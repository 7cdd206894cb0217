"""The sensor teachers: :class:`SensorDriver` (a stateless rangefinder + state driver whose every choice the
observation explains: the imitation teacher) and :class:`SensorRacer` (the race teacher: it passes, lifts for and
brakes for the cars its ``opponents`` sensor shows), with their named gains (``SensorDriver.FAST``,
``SensorRacer.BOLD`` / ``CLEAN`` / ``KEEP`` / ``YIELD``). The specs that name them (``sensor_fast``,
``racer_safe:<gamma>...``, ``racer_safe(gamma=...)``) are read by :mod:`torcsrl.policies.registry`."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from torcsrl.envs.traffic import sector_directions
from torcsrl.policies.base import Policy

# A built-in driver's fingerprint is the hash of its class's source (report caches and result rows are keyed by it):
# the driver classes below are kept to the byte, so they keep the local names they were written with
# (_code_fingerprint, _state_slot) and their imports of the env modules inside their methods.
from torcsrl.policies.base import code_fingerprint as _code_fingerprint
from torcsrl.policies.base import state_slot as _state_slot

__all__ = ["SensorDriver", "SensorRacer"]


class SensorDriver(Policy):
    """A teacher whose every choice the observation explains: a TORCS-SCR-style driver on the rangefinder
    and ``state`` alone, stateless (the action is a function of the current observation), so a network
    can imitate it exactly and DAgger can label any state a learner reaches.

    * **Steering** [rad, then / ``max_steer``]: towards the free space ahead — the beam-length-weighted
      mean direction of the front beams (|angle| <= 60 deg, weights ``(r / 200 m)^p``), pulled less on
      long straights (``* min(1, 60 m / d)``) — minus ``k_axis`` x the course angle to the track axis
      (heading angle + ``k_beta`` x the slip angle ``atan(v_y / v_x)``) minus ``k_pos`` x trackPos.
      Each of the three terms is scaled by ``min(1, v_gain / v)`` with its own ``v_gain_*`` [m/s]: the
      heading a steering command turns in one control step grows as ``v dt / wheelbase``, so a gain that
      is right at 10 m/s makes the loop ring at 25 m/s and 10 Hz (the steering then flips sign every step
      or two: 40-70 flips/km). Only the free-space term needs it (``v_gain_free`` 5 m/s).
    * **Speed target** [m/s]: what can still stop within the free distance ``d`` straight ahead (the
      longest of the three central beams): ``sqrt(2 decel (d - d0))``, clipped to [``v_min``, ``v_max``];
      at (near) full lock (|steer| > ``sat``) a tenth below the current speed.
    * **Pedal**: proportional on the speed error (``k_v``) plus a 0.1 cruise offset that fades in over the
      last ``pedal_ramp_ms`` [m/s] below the target (a step there makes the pedal chatter); traction
      control on the driven (rear) wheels (throttle faded out as their slip exceeds ``slip_max``) and a
      throttle cap while sliding (``max(u_slide, 1 - k_slide |beta|)``).
    * Off the track (beams read -1): back towards the axis at walking pace.

    ``decel`` (4.5 m/s^2) is below the grip of dirt (mu 0.6) and gravel (0.5), so the same driver is safe on asphalt, wet, dirt and
    gravel (and slower than it could be on asphalt: it cannot see the surface). Tuned on the training tracks
    and training-range generated tracks only (``set:train``, ``gen-10001…10008``), at 10 Hz. The first
    version (the teacher of ``reference_dagger.pt``) is ``SensorDriver(**SensorDriver.V1)``.
    """

    #: Braking the grip-aware teacher plans with per unit of friction [m/s^2] (``decel_per_mu``): 7.5 on asphalt,
    #: 5.25 wet, 4.5 dirt (the surface-blind teacher's decel), 3.75 gravel. Screened on training tracks only
    #: (set:train's fast_straights, hairpins, esses + gen-10001/2/4, 2 laps at 10 Hz): 24/24 laps on asphalt, wet,
    #: dirt and gravel at 1.17-1.19x the expert (the surface-blind teacher: 1.45x on asphalt).
    GRIP_DECEL_PER_MU = 7.5
    #: The sight distance [m] of the camera student's teacher (``sensor_sight``): it plans its speed as if it saw no
    #: further than this straight ahead. In the 96x64 hood camera a bend shows only a few tens of metres ahead (a point
    #: 100 m ahead on the road is within one pixel row of the horizon); a teacher that sees 200 m brakes for bends the
    #: student cannot see yet. An observability-matched teacher: its choices are ones the student can infer. Chosen on
    #: the training screen (2026-11-26, set:train + gen-10001..8, one lap, asphalt and dirt): the BC students of
    #: teachers with sight 80 / 100 m lapped 24/26 / 18/26 (the sight-200 teacher's: 17/26), with regression losses
    #: 0.0099 / 0.0107 / 0.0148; the teachers themselves lap 26/26 at 1.40x / 1.33x / 1.26x the expert.
    CAMERA_SIGHT_M = 80.0
    #: The fast teacher (``sensor_fast``): grip-aware braking at 9 m/s^2 per unit mu, a corner speed from the circle
    #: through the farthest free point (``k_corner``), braking towards 8 m/s rather than to a stop at the wall ahead
    #: (``v_corner_ms``), and a 3x stiffer speed loop (``k_v``). Screened on training tracks only (set:train +
    #: gen-10001..4, asphalt, 2 laps at 10 Hz, 2026-11-27): 9/9 laps at a median 1.076x the expert's lap (sensor_grip:
    #: 9/9 at 1.165x) — faster than experts at 85 % pace (1.176x), the pace a racer must beat.
    FAST = {"decel_per_mu": 9.0, "v_corner_ms": 8.0, "k_corner": 0.7, "k_v": 0.3}
    #: The fast camera teacher (``sensor_fast_sight``): the fast gains limited to the camera's sight
    #: (:data:`CAMERA_SIGHT_M`) with a gentler corner speed (``k_corner`` 0.6: at 0.7 it left hairpins on dirt and
    #: gravel). Screened on training tracks only (set:train + gen-10001..4, 2 laps at 10 Hz, 2026-11-27): 36/36 laps on
    #: asphalt, wet, dirt and gravel at a median 1.18-1.20x the expert (``sensor_sight``: 36/36 at 1.31-1.33x; FAST's
    #: k_corner 0.7 at 80 m: 32/36; decel 8 per mu: 36/36 at 1.20-1.24x).
    CAMERA_FAST = {"decel_per_mu": 9.0, "v_corner_ms": 8.0, "k_corner": 0.6, "k_v": 0.3}
    #: The first teacher's gains (no speed scaling, a pedal step, softer traction control, decel 3.5).
    V1 = {"decel": 3.5, "k_v": 0.3, "slip_max": 0.12, "v_gain_free": math.inf, "v_gain_axis": math.inf,
          "v_gain_pos": math.inf, "pedal_ramp_ms": 0.0}

    name = "sensor"

    def __init__(self, decel: float = 4.5, d0: float = 8.0, v_min: float = 4.0, v_max: float = 75.0, k_axis: float = 0.5,
                 k_pos: float = 0.15, k_free: float = 0.8, p: float = 6.0, k_beta: float = -1.0, slip_max: float = 0.05,
                 tc_width: float = 3.0, u_slide: float = 0.3, k_slide: float = 5.0, k_v: float = 0.1, sat: float = 0.9,
                 v_gain_free: float = 5.0, v_gain_axis: float = math.inf, v_gain_pos: float = 15.0,
                 pedal_ramp_ms: float = 1.0, decel_per_mu: float | None = None, sight_m: float | None = None,
                 v_corner_ms: float = 0.0, k_corner: float | None = None, grip_exponent: float = 1.0,
                 vehicle: str = "default", rangefinder_key: str = "rangefinder", state_key: str = "state") -> None:
        from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG
        from torcsrl.envs.vehicle import VehicleParams

        prm = VehicleParams.load(vehicle)
        self.spec = "sensor"
        self.obs_keys = ("rangefinder", "state")
        self.env_overrides = {"sensors": ("rangefinder", "state")}
        self.k = SimpleNamespace(decel=decel, d0=d0, v_min=v_min, v_max=v_max, k_axis=k_axis, k_pos=k_pos, k_free=k_free, p=p,
                                 k_beta=k_beta, slip_max=slip_max, tc_width=tc_width, u_slide=u_slide, k_slide=k_slide, k_v=k_v, sat=sat,
                                 v_gain=(float(v_gain_free), float(v_gain_axis), float(v_gain_pos)), pedal_ramp_ms=float(pedal_ramp_ms),
                                 decel_per_mu=None if decel_per_mu is None else float(decel_per_mu),
                                 sight_m=math.inf if sight_m is None else float(sight_m), v_corner=float(v_corner_ms),
                                 k_corner=None if k_corner is None else float(k_corner), grip_exponent=float(grip_exponent))
        if not math.isfinite(float(grip_exponent)) or float(grip_exponent) < 1.0:
            raise ValueError(f"SensorDriver grip_exponent must be a finite number >= 1 (1: braking in proportion to the grip), got {grip_exponent}")
        self.fingerprint = _code_fingerprint(SensorDriver, repr(sorted(vars(self.k).items())))  # code and gains
        if decel_per_mu is not None:
            if not math.isfinite(float(decel_per_mu)) or float(decel_per_mu) <= 0.0:
                raise ValueError(f"SensorDriver decel_per_mu must be a finite braking rate > 0 [m/s^2 per unit mu], got {decel_per_mu}")
            self.spec = f"sensor-grip{float(decel_per_mu):g}"
        if sight_m is not None:
            if not math.isfinite(float(sight_m)) or float(sight_m) <= d0:
                raise ValueError(f"SensorDriver sight_m must be a finite distance > d0 = {d0} m, got {sight_m}")
            self.spec += f"-sight{float(sight_m):g}"
        self.max_steer, self.wheel_r = float(prm.max_steer), float(prm.wheel_radius)
        self.keys = (rangefinder_key, state_key)
        self.ang = np.radians(np.asarray(RANGEFINDER_ANGLES_DEG, dtype=float))
        self.front = np.flatnonzero(np.abs(self.ang) <= np.radians(60.0) + 1e-9)
        self.centre = np.argsort(np.abs(self.ang))[:3]
        self.obs_shapes = {"rangefinder": (len(self.ang),)}
        self._i = {n: _state_slot(n) for n in ("angle_rad", "trackPos", "speedX_kmh", "speedY_kmh", "wheelSpinVel_rl", "wheelSpinVel_rr")}

    def act(self, r: np.ndarray, st: np.ndarray, mu: float | None = None, tp_target: float = 0.0,
            decel_per_mu: float | None = None) -> tuple[float, float]:
        """(steer, throttle_brake) in [-1, 1] from one car's beams [m] and state (raw units); ``mu`` [-], the
        friction under the car, sets the braking it plans with when the driver is grip-aware (``decel_per_mu``, or
        the argument in its place [m/s^2 at mu 1]); ``tp_target`` [trackPos units] is where across the road the
        centring term pulls (0: the axis)."""
        k, i = self.k, self._i
        per_mu = k.decel_per_mu if decel_per_mu is None else decel_per_mu
        decel = k.decel if per_mu is None or mu is None else per_mu * float(mu) ** k.grip_exponent
        v = float(st[i["speedX_kmh"]]) / 3.6
        beta = math.atan2(float(st[i["speedY_kmh"]]) / 3.6, max(v, 5.0))  # slip angle [rad]
        angle, tp = float(st[i["angle_rad"]]) + k.k_beta * beta, float(st[i["trackPos"]])
        if (r < 0).all():  # off the track
            steer_rad, v_t = -(k.k_axis * angle + 0.5 * tp), 0.5 * k.v_min
        else:
            f = np.maximum(r[self.front], 0.0)
            w = (f / 200.0) ** k.p + 1e-9
            theta = float((w * self.ang[self.front]).sum() / w.sum())
            d = min(float(np.max(r[self.centre])), k.sight_m)
            g_free, g_axis, g_pos = (min(1.0, vg / max(v, 1.0)) for vg in k.v_gain)
            steer_rad = (g_free * k.k_free * theta * min(1.0, 60.0 / max(d, 1.0)) - g_axis * k.k_axis * angle
                         - g_pos * k.k_pos * (tp - tp_target))
            v_t = min(k.v_max, max(k.v_min, math.sqrt(k.v_corner ** 2 + 2.0 * decel * max(d - k.d0, 0.0))))
            if k.k_corner is not None:  # the bend it is in: the circle along the heading through the farthest point
                j = int(np.argmax(f))
                sin_t = abs(math.sin(float(self.ang[self.front][j])))
                if sin_t > 1e-3:
                    radius = min(float(f[j]), k.sight_m) / (2.0 * sin_t)
                    v_t = min(v_t, max(k.v_min, math.sqrt(k.k_corner * decel * radius)))
        steer = max(-1.0, min(1.0, steer_rad / self.max_steer))
        if abs(steer) > k.sat:
            v_t = min(v_t, 0.9 * v)
        err = v_t - v
        if k.pedal_ramp_ms > 0.0:
            cruise = 0.1 * min(1.0, max(0.0, 1.0 + err / k.pedal_ramp_ms))
        else:
            cruise = 0.1 if err > 0 else 0.0
        u = max(-1.0, min(1.0, k.k_v * err + cruise))
        if u > 0:  # traction control on the driven wheels, throttle cap while sliding
            spin = 0.5 * (float(st[i["wheelSpinVel_rl"]]) + float(st[i["wheelSpinVel_rr"]])) * self.wheel_r
            slip = (spin - v) / max(v, 3.0)
            if slip > k.slip_max:
                u *= max(0.0, 1.0 - (slip - k.slip_max) / (k.tc_width * k.slip_max))
            u = min(u, max(k.u_slide, 1.0 - k.k_slide * abs(beta)))
        return steer, u

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        r = td.get(self.keys[0]).reshape(-1, len(self.ang)).numpy()
        st = td.get(self.keys[1]).reshape(r.shape[0], -1).numpy()
        if self.k.decel_per_mu is not None:
            mu = td.get(("info", "surfaceMu"), None)
            if mu is None:
                raise ValueError("a grip-aware SensorDriver (decel_per_mu) reads ('info', 'surfaceMu'), which this tensordict lacks")
            mu = mu.reshape(-1).tolist()
        else:
            mu = [None] * r.shape[0]
        out = torch.tensor([self.act(r[j], st[j], mu[j]) for j in range(r.shape[0])], dtype=torch.float32)
        td.set("action", out.reshape(*td.batch_size, 2))
        return td


class SensorRacer(SensorDriver):
    """The race teacher: :class:`SensorDriver` with the fast gains (``SensorDriver.FAST``) that passes the cars its
    ``opponents`` sensor shows (TORCS SCR's 36 sectors, 200 m = free) and lifts or brakes for one it cannot pass yet —
    from the current observation alone (stateless), so a student with the same sensors can imitate it.

    Each car a sector shows sits at ``x = r cos(phi)`` ahead and ``y = r sin(phi)`` left [m] (sector k's centre
    ``phi = 175 - 10 k`` degrees counter-clockwise from the heading). Its place relative to the road ahead is
    ``dy = y - kappa x^2 / 2``, with ``kappa`` the curvature of the circle along the heading through the farthest free
    point (the bend the rangefinder shows), and its trackPos ``tp + dy / w`` (``w`` the half-width the side beams
    read).

    * **Passing**: the car that matters is the nearest ahead (else alongside, to ``rear_m`` behind) with
      ``x < look_m`` and ``|dy| < 2 lane_m``. The racer passes on the side it is already on (from straight behind:
      the roomier side; the other side where a third car is near that line), aiming ``pass_gap_m`` beside it and at
      most ``tp_max`` out, through the centring term's target (``tp_target``), weighted from 0 at ``look_m`` ahead to
      1 at ``full_m`` and fading over ``rear_m`` once passed. It starts a pass only where the road ahead is
      straighter than ``pass_radius_m`` and no bend is near — the free distance straight ahead exceeds its braking
      distance ``v^2 / (2 decel)`` plus ``bend_m`` — and finishes one it is in (``|dy| > 1.5 m``).
    * **Following**: a car more than ``length_m`` ahead (centre to centre; one alongside it steers away from) within
      ``lane_m`` of its path or of the line it heads for makes it lift closer than ``lift_m + lift_s v`` and brake
      (``brake`` of the pedal) closer than ``brake_m + brake_s v`` (``v`` its speed [m/s]). Near a bend and while it
      brakes that corridor is ``bend_lanes`` x ``lane_m`` wide (a car ahead on the racing line turns in across the
      inside: the scripted opponents do not see a car beside them), and with ``yield_alongside`` a car alongside
      but a little ahead counts too (it lets it go first).

    * **Fighting**: with ``fight_decel_per_mu`` [m/s^2 at mu 1] it plans its braking (and corner speed) at that rate
      while a car is within ``fight_m`` [m] (any sector), at its own ``decel_per_mu`` otherwise — a margin when it
      drives alone, the limit in a fight (``racer_safe:<gamma>:<decel>:<fight decel>[:<fight m>]``).

    Without an ``opponents`` key it drives as ``sensor_fast``.
    """

    name = "racer"
    #: ``racer_bold``: never widens the following corridor near bends nor yields to a car alongside (races on the
    #: training tracks, 5 laps against 3 experts at 85 %, 2026-11-27: 11/16 wins, 1.81 collisions a race; the default,
    #: cautious racer: 3/16 wins, 0.81 collisions a race).
    BOLD = {"bend_lanes": 1.0, "yield_alongside": False, "bend_m": -1000.0}
    #: ``racer_safe[:<gamma>]``: ``racer_bold`` planning its braking with ``decel_per_mu * mu ** gamma`` — the same on
    #: asphalt (mu = 1), a margin on low grip that grows as the grip falls (dirt, mu 0.6: 3.2 m/s^2 at gamma 2 against
    #: 5.4 at gamma 1), so a student whose grip estimate runs high still brakes within the road's grip.
    SAFE_GRIP_EXPONENT = 2.0
    #: ``racer_clean[:<gamma>]``: ``racer_safe`` whose following corridor near a bend (and while it brakes) is 1.5 lanes
    #: wide: a car ahead on the racing line turns in across part of the inside. Races on the training tracks (5 laps,
    #: 3 experts at pace drawn from [0.83, 0.87], 3 races a track, seed 0; 2026-11-27): 22/24 finished, 17/24 wins,
    #: 0.75 collisions a race (racer_bold: 21/24, 16/24, 1.08; yielding to a car alongside: 23/24, 18/24, 1.17;
    #: holding its lane while a car is within 30 m, ``hold_lane``: 24/24, 19/24, 1.08).
    CLEAN = {**BOLD, "bend_lanes": 1.5}
    #: ``racer_keep[:<gamma>...]``: ``racer_safe`` that finishes a pass on the side it is on. Once beside the car it
    #: passes (``|dy| > 1.5 m``) it never takes the other side's line (across that car's path), and with no room on its
    #: own side (a third car near that line) it holds its trackPos — the following rules lift or brake for that car —
    #: where ``racer_safe`` aims at the road's centre.
    KEEP = {**BOLD, "keep_side": True}
    #: ``racer_yield[:<gamma>...]``: ``racer_safe`` that completes a pass before the braking zone or gives it up. Within
    #: ``abandon_m`` [m] of its braking point for the bend ahead (the free distance straight ahead less than its
    #: braking distance ``v^2 / (2 decel)`` plus ``abandon_m``) it starts no pass, and beside a car it has not yet
    #: cleared by a car length it holds its lane, braking to drop behind while that car's centre is ahead of its own
    #: (``racer_safe`` and ``racer_keep`` finish the pass into the bend, side by side).
    YIELD = {**BOLD, "abandon_m": 30.0}

    def __init__(self, look_m: float = 60.0, full_m: float = 30.0, rear_m: float = 15.0, pass_gap_m: float = 3.8,
                 tp_max: float = 0.7, lane_m: float = 2.4, length_m: float = 4.5, lift_m: float = 10.0, lift_s: float = 0.8,
                 brake_m: float = 6.0, brake_s: float = 0.5, brake: float = 1.0, pass_radius_m: float = 120.0,
                 bend_m: float = 50.0, bend_lanes: float = 2.5, yield_alongside: bool = True, hold_lane: bool = False,
                 fight_decel_per_mu: float | None = None, fight_m: float = 60.0, clear_m: float = 0.0,
                 keep_side: bool = False, abandon_m: float | None = None, opponents_key: str = "opponents", **kw: Any) -> None:
        from torcsrl.envs.traffic import OPPONENT_RANGE_M

        if fight_decel_per_mu is not None and not (math.isfinite(float(fight_decel_per_mu)) and float(fight_decel_per_mu) > 0.0):
            raise ValueError(f"SensorRacer fight_decel_per_mu must be a positive rate [m/s^2 at mu 1], got {fight_decel_per_mu}")
        if not (math.isfinite(float(fight_m)) and 0.0 < float(fight_m) <= OPPONENT_RANGE_M):
            raise ValueError(f"SensorRacer fight_m must be in (0, {OPPONENT_RANGE_M:g}] m (the opponents sensor's range), got {fight_m}")
        if not (math.isfinite(float(clear_m)) and 0.0 <= float(clear_m) <= 30.0):
            raise ValueError(f"SensorRacer clear_m must be in [0, 30] m, got {clear_m}")
        if abandon_m is not None and not (math.isfinite(float(abandon_m)) and 0.0 <= float(abandon_m) <= OPPONENT_RANGE_M):
            raise ValueError(f"SensorRacer abandon_m must be None (off) or in [0, {OPPONENT_RANGE_M:g}] m, got {abandon_m}")
        super().__init__(**{**SensorDriver.FAST, **kw})
        self.spec = "racer"
        self.obs_keys = ("rangefinder", "state", "opponents")
        # the rate its gains are tuned at (SensorDriver's: 10 Hz, 20 physics substeps), as the students it teaches drive
        self.env_overrides = {"sensors": ("rangefinder", "state", "opponents"), "control_hz": 10.0, "substeps": 20}
        self.opponents_key = opponents_key
        self.race = SimpleNamespace(look_m=look_m, full_m=full_m, rear_m=rear_m, pass_gap_m=pass_gap_m, tp_max=tp_max,
                                    lane_m=lane_m, length_m=length_m, lift_m=lift_m, lift_s=lift_s, brake_m=brake_m, brake_s=brake_s,
                                    brake=brake, pass_radius_m=pass_radius_m, bend_m=bend_m, bend_lanes=bend_lanes,
                                    yield_alongside=bool(yield_alongside), hold_lane=bool(hold_lane),
                                    fight_decel_per_mu=None if fight_decel_per_mu is None else float(fight_decel_per_mu),
                                    fight_m=float(fight_m), clear_m=float(clear_m), keep_side=bool(keep_side),
                                    abandon_m=None if abandon_m is None else float(abandon_m))
        self.fingerprint = _code_fingerprint(SensorDriver, SensorRacer, repr(sorted(vars(self.k).items())),
                                             repr(sorted(vars(self.race).items())))
        self._cos, self._sin = sector_directions()
        self._free = OPPONENT_RANGE_M - 1e-3
        self._side = (int(np.argmin(self.ang)), int(np.argmax(self.ang)))  # the -90 (right) and +90 (left) beams

    def traffic(self, r: np.ndarray, st: np.ndarray, opp: np.ndarray, braking: bool = False) -> tuple[float, float]:
        """``(tp_target, pedal_cap)`` from one car's beams [m], state and opponent sectors [m]: where across the road
        to drive (trackPos units) and the most pedal allowed (1 free, 0 lift, < 0 brake); ``braking``: the car brakes
        for a bend (the following corridor widens, as near a bend)."""
        q = self.race
        seen = np.flatnonzero(opp < self._free)
        if len(seen) == 0 or (r < 0).all():
            return 0.0, 1.0
        tp = float(st[self._i["trackPos"]])
        w = max(0.5 * (max(float(r[self._side[0]]), 0.0) + max(float(r[self._side[1]]), 0.0)), 2.0)  # half-width [m]
        f = np.maximum(r[self.front], 0.0)
        j = int(np.argmax(f))
        kappa = 2.0 * math.sin(float(self.ang[self.front][j])) / max(float(f[j]), 1.0)  # the bend ahead [1/m, + left]
        v = max(float(st[self._i["speedX_kmh"]]) / 3.6, 0.0)
        d_free = float(np.max(r[self.centre]))  # straight ahead [m]
        brake_dist = v * v / (2.0 * (self.k.decel_per_mu or self.k.decel))  # [m] (braking as on mu = 1)
        bend_near = d_free < brake_dist + q.bend_m
        zone = q.abandon_m is not None and d_free < brake_dist + q.abandon_m  # near the braking point: no pass unfinished
        x, y = opp[seen] * self._cos[seen], opp[seen] * self._sin[seen]
        dy = y - 0.5 * kappa * x * x
        tp_o = tp + dy / w
        near = (x > -(q.rear_m + q.clear_m)) & (x < q.look_m) & (np.abs(dy) < 2.0 * q.lane_m)
        target, drop = 0.0, False
        if near.any():
            ahead = near & (x > 0.0)
            pick = ahead if ahead.any() else near
            i = int(np.argmin(np.where(pick, np.abs(x), np.inf)))
            gap = q.pass_gap_m / w
            go_left = dy[i] < 0.0 if abs(dy[i]) > 0.5 else tp_o[i] < 0.0
            left, right = min(tp_o[i] + gap, q.tp_max), max(tp_o[i] - gap, -q.tp_max)
            sides = (left, right) if go_left else (right, left)
            others = (np.arange(len(x)) != i) & (x > -2.0 * q.length_m) & (x < q.full_m)

            def free(a: float) -> bool:  # room beside the car passed, and no other car near that line
                return abs(a - tp_o[i]) >= gap - 1e-6 and not (others & (np.abs(tp_o - a) * w < q.lane_m)).any()

            committed = abs(dy[i]) > 1.5  # already beside it: finish the pass; else start one only where the road is straight
            keep = q.keep_side and committed  # beside it, the other side's line crosses its path
            aim = next((a for a in (sides[:1] if keep else sides) if free(a)), None)
            if zone and committed and float(x[i]) > -q.length_m:  # not clear of it by a car length: give the pass up
                target = max(-q.tp_max, min(q.tp_max, tp))
                drop = float(x[i]) > 0.0  # its centre ahead of ours: brake, let it into the bend first
            elif aim is not None and (committed or (abs(kappa) * q.pass_radius_m < 1.0 and not bend_near and not zone)):
                xi = float(x[i])
                wt = (q.look_m - xi) / (q.look_m - q.full_m) if xi >= 0.0 else (xi + q.clear_m + q.rear_m) / q.rear_m
                target = min(1.0, max(0.0, wt)) * aim
            elif keep or (q.hold_lane and (np.abs(x[near]) < q.full_m).any()):  # no room: keep the lane it is in
                target = max(-q.tp_max, min(q.tp_max, tp))
        cap = -q.brake if drop else 1.0
        braking = braking or bend_near
        lift, brake = q.lift_m + q.lift_s * v, q.brake_m + q.brake_s * v  # [m]
        # near a bend a car ahead may turn in across the car's path: a wider corridor, and one alongside but a little
        # ahead is let go first; on a straight one alongside is steered away from, not braked for
        lane, x_min = (q.lane_m * q.bend_lanes, 0.0 if q.yield_alongside else q.length_m) if braking else (q.lane_m, q.length_m)
        for xa, da, ta in zip(x.tolist(), dy.tolist(), tp_o.tolist()):  # on its path now, or on the line it heads for
            if xa > x_min and (abs(da) < lane or abs(ta - target) * w < lane):
                cap = min(cap, -q.brake if xa < brake else 0.0 if xa < lift else 1.0)
        return target, cap

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        opp_t = td.get(self.opponents_key, None)
        if opp_t is None:
            return super().__call__(td)
        r = td.get(self.keys[0]).reshape(-1, len(self.ang)).numpy()
        st = td.get(self.keys[1]).reshape(r.shape[0], -1).numpy()
        opp = opp_t.reshape(r.shape[0], -1).numpy().astype(np.float64)
        mu = td.get(("info", "surfaceMu"), None)
        if mu is None:
            raise ValueError("the racer (a grip-aware SensorDriver) reads ('info', 'surfaceMu'), which this tensordict lacks")
        mu = mu.reshape(-1).tolist()
        out = []
        q = self.race
        for j in range(r.shape[0]):
            target, cap = self.traffic(r[j], st[j], opp[j])
            fight = q.fight_decel_per_mu is not None and bool((opp[j] < q.fight_m).any())
            steer, u = self.act(r[j], st[j], mu[j], tp_target=target, decel_per_mu=q.fight_decel_per_mu if fight else None)
            if u < 0.0:  # braking for a bend: a car ahead may turn in across its path
                cap = self.traffic(r[j], st[j], opp[j], braking=True)[1]
            out.append((steer, min(u, cap)))
        td.set("action", torch.tensor(out, dtype=torch.float32).reshape(*td.batch_size, 2))
        return td
