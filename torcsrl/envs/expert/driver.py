"""Scripted reference driver and the physical lap-time limit.

* :func:`racing_line`: a minimum-curvature line inside the track (squared curvature linearised in
  the centreline's Frenet frame: a bound-constrained quadratic programme, solved by projected
  Newton steps), optionally traded against length, or the centreline.
* :func:`speed_profile`: quasi-steady-state point-mass speed along a line: the cornering limit
  ``v^2 |kappa| m = mu (m g + downforce)``, then a forward pass (acceleration limited by the
  friction circle, the engine's peak wheel power, drag and rolling resistance) and a backward pass
  (braking limited by the friction circle, helped by drag and rolling resistance), both around
  the closed loop.
* :func:`limit_lap_time`: the "physical limit" — the flying-lap time of that point mass (same
  mass, mu, power, drag, downforce as the car; all four tyres' grip available for driving and
  braking) on the fastest of the centreline and a few lines between minimum curvature and
  minimum length. Quasi-steady state, so a reference rather than a strict bound (the true
  minimum-time line differs a little, and transients are ignored).
* :class:`ExpertDriver`: Stanley-style path tracking (curvature feed-forward, heading and
  cross-track feedback, the heading measured against the front axle's filtered slip angle) on the
  minimum-curvature line plus a speed controller that feeds the profile's acceleration forward
  through a model of the engine and brakes, on a derated profile (``mu_margin`` of the grip,
  driven-axle traction that also holds the speed in bends, gentle braking in bends), with a
  TORCS-robot-style traction-control throttle filter. It reads only what the car exposes (pose,
  velocities, wheel spin) and works at any control rate (the training env's 10 Hz or 50 Hz).
* CLI: ``python -m torcsrl.envs.expert --track NAME --surface dirt --laps 10 [--control-hz 10]
  [--plot out.png]`` drives a fleet of one on a ground plane, with the surface under each wheel
  from the track, and prints lap times beside the limit and the rate they were driven at;
  ``--all`` prints the table for every bundled track on asphalt and dirt.
  ``benchmarks/expert_sweep.py`` drives it on hundreds of generated tracks.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np
from torcsrl.utils.bullet import pybullet as p
from scipy import sparse
from scipy.sparse.linalg import spsolve

from torcsrl.envs import surfaces as surf
from torcsrl.envs.track import Track
from torcsrl.envs.vehicle import CarFleet, VehicleParams, make_ground

__all__ = [
    "RacingLine",
    "racing_line",
    "speed_profile",
    "limit_lap_time",
    "ExpertDriver",
    "DriveResult",
    "drive",
    "default_substeps",
    "main",
]

G = 9.81  # [m/s^2]
#: The lines the expert can follow: the racing line, or the centre of the road.
LINES = ("racing", "centre")
#: Half-width [m] of the band about the middle of the road the racing line may use where the road
#: is narrower than twice its edge margin.
_MIN_BAND_M = 0.05
#: Length weights [1/m^2] of the candidate lines the "best" physical limit tries (0 = minimum curvature).
LIMIT_LENGTH_WEIGHTS: tuple[float, ...] = (0.0, 3e-5, 1e-4, 3e-4)
#: Solved line offsets by (geometry hash, margin, length weight): a line costs ~1 s to solve.
_LINE_CACHE: dict[tuple[str, float, float], np.ndarray] = {}


# --------------------------------------------------------------------------------------------
# Lines and speed profiles
# --------------------------------------------------------------------------------------------
@dataclass
class RacingLine:
    """A closed driving line, one point per centreline sample of its track.

    Attributes:
        track_s: track arc length of each point ``[M]`` [m] (the track's samples).
        d: lateral offset from the centreline ``[M]`` [m] (> 0 left).
        xy: world points ``[M, 2]`` [m].
        ds: line length from each point to the next ``[M]`` [m].
        kappa: signed line curvature ``[M]`` [1/m] (> 0 turning left).
        mu: friction coefficient of the road under each point ``[M]`` [-].
        crr: rolling-resistance coefficient under each point ``[M]`` [-].
    """

    track_s: np.ndarray
    d: np.ndarray
    xy: np.ndarray
    ds: np.ndarray
    kappa: np.ndarray
    mu: np.ndarray
    crr: np.ndarray

    @property
    def length(self) -> float:
        """Line length [m]."""
        return float(self.ds.sum())


def _line_geometry(xy: np.ndarray, smooth: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Segment lengths and signed curvature (heading change per length, lightly smoothed) of a closed polyline."""
    seg = np.roll(xy, -1, axis=0) - xy
    ds = np.hypot(seg[:, 0], seg[:, 1])
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    turn = (heading - np.roll(heading, 1) + np.pi) % (2 * np.pi) - np.pi
    kappa = turn / np.maximum(0.5 * (ds + np.roll(ds, 1)), 1e-9)
    if smooth > 0:
        k = 2 * smooth + 1
        kappa = np.convolve(np.concatenate([kappa[-smooth:], kappa, kappa[:smooth]]), np.ones(k) / k, mode="valid")
    return ds, kappa


def _min_curvature_offsets(kappa_c: np.ndarray, ds: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                           length_weight: float = 0.0, relinearise: int = 3, max_iter: int = 60) -> np.ndarray:
    """Lateral offsets ``d [M]`` of the closed line minimising ``0.5 * sum kappa^2 ds + w * length``,
    ``lo <= d <= hi``, with ``w = length_weight`` [1/m^2] (0: the minimum-curvature line).

    In the centreline's Frenet frame (curvature ``kappa_c``, spacing ``ds``) a line of offset
    ``d(s)`` has curvature ``kappa ~= kappa_c / (1 - kappa_c d) + d''`` (small d'). Linearised
    about the previous solution this is affine in d, so ``sum kappa^2 ds`` is a bound-constrained
    convex quadratic with a cyclic banded Hessian, solved by projected Newton steps (sparse
    direct solves on the free variables, Armijo search along the projection arc), and
    re-linearised a few times. The line's length ``sum (1 - kappa_c d) ds`` is affine in d too.
    """
    m = len(kappa_c)
    h = float(np.mean(ds))
    idx = np.arange(m)
    rows = np.concatenate([idx, idx, idx])
    cols = np.concatenate([(idx - 1) % m, idx, (idx + 1) % m])
    d2 = sparse.csr_matrix((np.concatenate([np.ones(m), -2.0 * np.ones(m), np.ones(m)]) / h**2, (rows, cols)),
                           shape=(m, m))
    w = sparse.diags(np.sqrt(ds))
    d = np.clip(np.zeros(m), lo, hi)
    for _ in range(relinearise):
        denom = np.maximum(1.0 - kappa_c * d, 0.05)
        slope = kappa_c**2 / denom**2  # d kappa / d d at the linearisation point
        const = kappa_c / denom - slope * d
        a = (w @ (sparse.diags(slope) + d2)).tocsr()
        b = w @ const
        hess = (a.T @ a).tocsc() + 1e-12 * sparse.identity(m, format="csc")
        length_grad = -length_weight * kappa_c * ds
        lin = a.T @ b + length_grad

        def cost(x: np.ndarray) -> float:
            r = a @ x + b
            return 0.5 * float(r @ r) + float(length_grad @ x)

        # Projected Newton with an Armijo search along the projection arc (Bertsekas 1982).
        x = d
        fx = cost(x)
        for _ in range(max_iter):
            grad = hess @ x + lin
            eps = min(1e-3, float(np.abs(x - np.clip(x - grad, lo, hi)).max()))
            fixed = ((x <= lo + eps) & (grad > 0)) | ((x >= hi - eps) & (grad < 0))
            free = ~fixed
            step = np.zeros(m)
            step[free] = spsolve(hess[free][:, free].tocsc(), -grad[free])
            alpha = 1.0
            while True:
                new = np.clip(x + alpha * step, lo, hi)
                f_new = cost(new)
                if f_new <= fx + 1e-4 * float(grad @ (new - x)) or alpha < 1e-6:
                    break
                alpha *= 0.5
            moved = float(np.abs(new - x).max())
            if f_new <= fx:
                x, fx = new, f_new
            if moved < 1e-7:
                break
        d = x
    return d


def racing_line(track: Track, kind: str = "racing", margin_m: float = 2.2, mu: float | None = None,
                length_weight: float = 0.0) -> RacingLine:
    """A closed line on ``track``: ``"racing"`` (minimum curvature) or ``"centre"``.

    The minimum-curvature line minimises the integral of its squared curvature over offsets
    ``d`` from the centreline with ``-w_right + margin <= d <= w_left - margin`` (where the road
    is narrower than ``2 * margin_m``: within 5 cm of the middle of the road; see
    :func:`_min_curvature_offsets`), where ``margin_m`` [m] keeps the car's centre that far
    from the edges; ``length_weight`` [1/m^2] > 0 trades curvature for a shorter line (see
    :func:`_min_curvature_offsets`). ``mu`` overrides the friction of the track's surfaces (else each stretch's own surface).
    """
    if kind not in LINES:
        raise ValueError(f"line must be one of {', '.join(LINES)}, got {kind!r}")
    c = track.xy
    m = len(c)
    normal = track.normal(track.s)
    if kind == "centre":
        d = np.zeros(m)
    else:
        # Where the road is narrower than twice the margin, the line keeps to a narrow band about
        # the middle of the road instead (a 4 m road leaves ~1.2 m either side of a car's wheels).
        mid = 0.5 * (track.w_left - track.w_right)
        lo = np.minimum(-track.w_right + margin_m, mid - _MIN_BAND_M)
        hi = np.maximum(track.w_left - margin_m, mid + _MIN_BAND_M)
        key = (hashlib.sha1(np.ascontiguousarray(np.stack([c[:, 0], c[:, 1], track.w_left, track.w_right,
                                                             track.kappa])).tobytes()).hexdigest(),
               float(margin_m), float(length_weight))
        d = _LINE_CACHE.get(key)
        if d is None:
            ds = np.roll(track.s, -1) - track.s + np.where(np.arange(m) == m - 1, track.length, 0.0)
            d = _min_curvature_offsets(track.kappa, ds, lo, hi, length_weight)
            if len(_LINE_CACHE) >= 128:
                _LINE_CACHE.pop(next(iter(_LINE_CACHE)))
            _LINE_CACHE[key] = d
        d = d.copy()
    xy = c + d[:, None] * normal
    ds, kappa = _line_geometry(xy)
    ids = track.surface_ids
    mu_arr = np.full(m, float(mu)) if mu is not None else surf.MU[ids].astype(float)
    return RacingLine(track.s.copy(), d, xy, ds, kappa, mu_arr, surf.ROLLING_RESISTANCE[ids].astype(float))


def speed_profile(
    line: RacingLine,
    params: VehicleParams,
    mu_scale: float = 1.0,
    drive_share: float = 1.0,
    brake_share: float = 1.0,
    brake_exponent: float = 2.0,
    hold_speed: bool = False,
    brake_memory_s: float = 0.0,
) -> np.ndarray:
    """Quasi-steady-state point-mass speed ``[M]`` [m/s] at each point of a closed ``line``.

    Args:
        line: the line (curvature, mu and rolling resistance per point).
        params: mass, peak power x drivetrain efficiency, drag and downforce areas, top-gear speed.
        mu_scale: fraction of the road's mu the profile may use [-] (1 = the physical limit).
        drive_share: fraction of the normal load whose grip can drive the car [-] (1 = all
            wheels, a point mass; ~0.5 for a rear-wheel-drive car).
        brake_share: fraction of the normal load whose grip can brake the car [-].
        brake_exponent: braking in a bend that uses a fraction ``f`` of the grip sideways may use
            ``(1 - f^p)^(1/p)`` of it lengthways: 2 the friction circle, 1 a "diamond" (``1 - f``,
            gentler braking in bends, for a car that gets loose when braked while cornering).
        hold_speed: the cornering limit also leaves the driven wheels (``drive_share``) the grip
            to hold the speed against drag and rolling resistance:
            ``(m v^2 kappa)^2 + (resistance / drive_share)^2 <= (mu N)^2``.
        brake_memory_s: braking grip is what the sharpest bend within this many seconds of
            travel (at the cornering-limit speed) before each point leaves: a car leaving a bend
            is still loaded sideways, and braked then it gets loose.
    """
    m = params.mass
    q_drag = 0.5 * params.air_density * params.drag_area  # [kg/m]
    q_down = 0.5 * params.air_density * params.lift_area  # [kg/m]
    power = params.max_wheel_power_w()
    mu = line.mu * mu_scale
    kappa = np.abs(line.kappa)
    # cornering limit: m v^2 |kappa| = mu (m g + q_down v^2)
    denom = m * kappa - mu * q_down
    v2 = np.where(denom > 1e-9, mu * m * G / np.maximum(denom, 1e-9), np.inf)
    v_top = params.top_gear_speed()
    v = np.minimum(np.sqrt(v2), v_top)
    if hold_speed:  # ... with the driven wheels also holding the speed (bisection on v)
        def feasible(vv: np.ndarray) -> np.ndarray:
            normal = m * G + q_down * vv * vv
            resist = q_drag * vv * vv + line.crr * normal
            return (mu * normal) ** 2 - (resist / drive_share) ** 2 - (m * vv * vv * kappa) ** 2 >= 0.0
        lo_v, hi_v = np.zeros_like(v), v.copy()
        ok = feasible(hi_v)
        for _ in range(40):
            mid_v = 0.5 * (lo_v + hi_v)
            f = feasible(mid_v)
            lo_v = np.where(f, mid_v, lo_v)
            hi_v = np.where(f, hi_v, mid_v)
        v = np.where(ok, v, lo_v)
    ds = line.ds
    n = len(v)
    kappa_brake = kappa
    if brake_memory_s > 0.0:  # braking grip: the sharpest bend within brake_memory_s of travel before
        cum = np.concatenate([[0.0], np.cumsum(ds)])
        total_len = cum[-1]
        back = np.minimum(v * brake_memory_s, 0.5 * total_len)
        ext = np.concatenate([kappa, kappa])  # two laps: windows may reach back across the start
        s_ext = np.concatenate([cum[:-1], cum[:-1] + total_len])
        start = np.searchsorted(s_ext, cum[:-1] + total_len - back, side="left")
        stop = np.arange(n) + n + 1
        kappa_brake = np.array([ext[a:b].max() for a, b in zip(start, stop)])

    def grip_left(vi: float, i: int, share: float, p: float = 2.0, k: np.ndarray = kappa) -> float:
        """Longitudinal acceleration the tyres can still give after cornering at vi [m/s^2]."""
        normal = m * G + q_down * vi * vi
        total = mu[i] * normal * share
        lateral = m * vi * vi * k[i] * share
        if p == 2.0:
            return math.sqrt(max(total * total - lateral * lateral, 0.0)) / m
        if p == 1.0:
            return max(total - lateral, 0.0) / m
        used = min(lateral / total, 1.0) if total > 0.0 else 1.0
        return total * (1.0 - used**p) ** (1.0 / p) / m

    v = v.tolist()
    for _ in range(2):  # forward (acceleration) pass, twice around the loop
        for k in range(n):
            i, j = k, (k + 1) % n
            vi = v[i]
            a = min(grip_left(vi, i, drive_share), power / (m * max(vi, 1.0)))
            a -= (q_drag * vi * vi) / m + line.crr[i] * (G + q_down * vi * vi / m)
            v[j] = min(v[j], math.sqrt(max(vi * vi + 2.0 * a * ds[i], 0.0)))
    for _ in range(2):  # backward (braking) pass
        for k in range(n - 1, -1, -1):
            i, j = k, (k + 1) % n
            vj = v[j]
            a = grip_left(vj, j, brake_share, brake_exponent, kappa_brake) + (q_drag * vj * vj) / m + line.crr[j] * (G + q_down * vj * vj / m)
            v[i] = min(v[i], math.sqrt(vj * vj + 2.0 * a * ds[i]))
    return np.asarray(v)


def _lap_time(line: RacingLine, v: np.ndarray) -> float:
    """Time [s] to drive the closed ``line`` at speeds ``v`` (trapezoid in 1/v per segment)."""
    v_next = np.roll(v, -1)
    return float(np.sum(2.0 * line.ds / np.maximum(v + v_next, 1e-6)))


def limit_lap_time(
    track: Track,
    surface: str | None = None,
    params: VehicleParams | None = None,
    mu: float | None = None,
    line: str = "best",
) -> float:
    """Physical-limit flying-lap time [s]: a point mass with the car's mass, power, drag and
    downforce and the road's mu (all four tyres' grip for cornering, driving and braking) on the
    minimum-curvature line (``line="racing"``), the centreline (``"centre"``), or the fastest of
    the centreline and the lines trading curvature for length with the weights
    :data:`LIMIT_LENGTH_WEIGHTS` (``"best"``, the default: minimum curvature is close to, not
    exactly, minimum time).

    Args:
        track: the track.
        surface: road surface name for the whole track (default: the track's own surfaces).
        params: vehicle parameters (default: ``VehicleParams.load("default")``).
        mu: a friction coefficient for the whole track, instead of the surfaces' [-].
        line: ``"best"``, ``"racing"`` or ``"centre"``.
    """
    if line not in ("best",) + LINES:
        raise ValueError(f"line must be one of best, {', '.join(LINES)}, got {line!r}")
    params = params or VehicleParams.load("default")
    if surface is not None:
        track = track.with_surface(surface)
    if line == "best":
        candidates = [("centre", 0.0)] + [("racing", w) for w in LIMIT_LENGTH_WEIGHTS]
    else:
        candidates = [(line, 0.0)]
    times = []
    for kind, weight in candidates:
        rl = racing_line(track, kind=kind, mu=mu, length_weight=weight)
        times.append(_lap_time(rl, speed_profile(rl, params)))
    return min(times)


# --------------------------------------------------------------------------------------------
# The driver
# --------------------------------------------------------------------------------------------
def _engine_forces(params: VehicleParams, dv: float = 1.0) -> tuple[list[float], list[float]]:
    """Full-throttle drive force and closed-throttle engine-braking force at the wheels [N], per
    ``dv`` m/s of speed up to top speed, in the gear the automatic gearbox holds when accelerating
    (the lowest whose engine speed is below the upshift point)."""
    rpm_per_rad_s = 60.0 / (2.0 * math.pi)
    ratios = np.asarray(params.gear_ratios, dtype=float) * params.final_drive
    drive, brake = [], []
    for v in np.arange(0.0, params.top_gear_speed() + 2.0 * dv, dv):
        wheel_rpm = v / params.wheel_radius * ratios * rpm_per_rad_s
        ok = np.flatnonzero(wheel_rpm <= params.shift_up_rpm)
        g = int(ok[0]) if len(ok) else len(ratios) - 1
        rpm = max(float(wheel_rpm[g]), params.clutch_rpm)
        torque = float(np.interp(rpm, params.torque_curve_rpm, params.torque_curve_nm)) if rpm < params.redline_rpm else 0.0
        to_force = ratios[g] * params.drivetrain_efficiency / params.wheel_radius
        drive.append(torque * to_force)
        eb = params.engine_brake_nm * float(wheel_rpm[g]) / params.redline_rpm if wheel_rpm[g] > params.clutch_rpm else 0.0
        brake.append(eb * to_force)
    return drive, brake


class ExpertDriver:
    """Path tracking on a racing line + a speed-profile tracker, for one car.

    Steering (evaluated at the front axle, projected on the track): curvature feed-forward
    ``atan(L kappa_line)`` + the heading error to the line + a Stanley cross-track term
    ``atan(k e / (v + v0))`` + yaw-rate damping. The heading error is the line's heading minus the
    body's yaw minus a slowly filtered estimate of the front axle's slip angle (the angle between
    its velocity and the body): in a steady bend the tyres run at a slip angle, and a heading term
    on the bare yaw then holds the car off the line by ``~ v * slip / k`` (over a metre at 200
    km/h), while fast yaw motions (a rear stepping out) still meet the full heading gain.

    Speed: the line's point-mass profile derated to ``mu_margin`` of the grip, to the driven
    axle's traction (which must also hold the speed against drag and rolling resistance in a
    steady bend) and, when braking in a bend (or within ``brake_memory_s`` of leaving one), to a
    friction "diamond" (``brake_exponent`` 1: the braking left after cornering at a fraction ``f``
    of the grip is ``1 - f`` of it, not ``sqrt(1 - f^2)``: braking hard while cornering hard
    unloads the inner rear wheel, which the fixed brake balance and the open differential's engine
    braking then lock, and the rear steps out). The pedals are the
    profile's acceleration a little ahead turned into force (mass, drag, rolling resistance, the
    engine's full-throttle and closed-throttle forces in the gear it will be in, the brakes'
    force), plus speed feedback; below the profile the car catches up no harder than its driven
    tyres allow there. A TORCS-robot-style traction-control filter eases the throttle when the
    driven wheels spin (the car has ABS but no traction control).

    It reads only what the car exposes (pose, velocities, wheel spin) and the control period
    ``dt_control``, and is rate-independent (its filters are in seconds).

    Args:
        track: the track (with the surfaces the car will meet).
        params: the car's parameters.
        mu_margin: fraction of the road's mu the speed profile uses [-].
        line: ``"racing"`` (minimum curvature, ``edge_margin_m`` from the edges) or ``"centre"``.
        edge_margin_m: how far the racing line keeps the car's centre from the edges [m].
        cross_track_gain: Stanley gain k [1/s].
        heading_gain: gain on the heading error [-].
        yaw_damping: gain on the yaw-rate error [s].
        slip_filter_s: time constant of the front axle's slip-angle estimate [s].
        speed_gain: speed feedback [1/s] (acceleration per m/s of speed error).
        speed_lead_s: how far ahead the profile's speed and acceleration are read [s of travel].
        brake_exponent: exponent of the friction "ellipse" the profile brakes on in bends
            (2: the friction circle; 1: a diamond, see above).
        hold_speed: the profile's cornering limit leaves the driven wheels the grip to hold the
            speed against drag and rolling resistance.
        brake_memory_s: the profile brakes on the grip the sharpest bend of the last this many
            seconds leaves (see :func:`speed_profile`): out of a fast bend into the next one the
            car is still loaded sideways.
    """

    def __init__(self, track: Track, params: VehicleParams, mu_margin: float = 0.85, line: str = "racing",
                 edge_margin_m: float = 2.2, cross_track_gain: float = 1.5, heading_gain: float = 1.0,
                 yaw_damping: float = 0.05, slip_filter_s: float = 1.0, speed_gain: float = 2.0,
                 speed_lead_s: float = 0.2, brake_exponent: float = 1.0, hold_speed: bool = True,
                 brake_memory_s: float = 0.5) -> None:
        self.track = track
        self.params = params
        self.line = racing_line(track, kind=line, margin_m=edge_margin_m)
        rear_load = params.cg_to_front_axle / params.wheelbase  # static share of weight on the rear axle
        self.drive_share = {"rear": rear_load, "front": 1.0 - rear_load, "all": 1.0}[params.drive]
        self.mu_margin = mu_margin
        self.v_ref = speed_profile(self.line, params, mu_scale=mu_margin, drive_share=self.drive_share,
                                   brake_exponent=brake_exponent, hold_speed=hold_speed, brake_memory_s=brake_memory_s)
        self.k_e = cross_track_gain
        self.k_head = heading_gain
        self.k_yaw = yaw_damping
        self.slip_filter_s = slip_filter_s
        self.k_v = speed_gain
        self.speed_lead_s = speed_lead_s
        self.brake_exponent = brake_exponent
        v = self.v_ref
        accel = (np.roll(v, -1) ** 2 - v**2) / (2.0 * np.maximum(self.line.ds, 1e-6))  # profile dv/dt [m/s^2]
        self._k_drag = 0.5 * params.air_density * params.drag_area  # [kg/m]
        self._k_down = 0.5 * params.air_density * params.lift_area  # [kg/m]
        self._f_brake = params.brake_torque / params.wheel_radius  # full-pedal brake force [N]
        self._f_drive, self._f_engine_brake = _engine_forces(params)
        seg = np.roll(self.line.xy, -1, axis=0) - np.roll(self.line.xy, 1, axis=0)
        heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
        self._s = self.line.track_s.tolist()
        self._d = self.line.d.tolist()
        self._v = self.v_ref.tolist()
        self._a = accel.tolist()
        self._kappa = self.line.kappa.tolist()
        self._heading = heading.tolist()
        self._mu = self.line.mu.tolist()
        self._crr = self.line.crr.tolist()
        self._chord = 0
        self._chord_front = 0
        self._slip = 0.0  # filtered slip angle of the front axle [rad]

    def reset(self, s: float = 0.0) -> None:
        """Forget the tracking state; the car is near arc length ``s`` [m]."""
        self._slip = 0.0
        self._chord = self._chord_front = int(np.searchsorted(self.line.track_s, s % self.track.length,
                                                              side="right") - 1)

    def _index(self, s: float) -> tuple[int, int, float]:
        """Samples around track arc length ``s`` (wrapped) and the blend factor between them."""
        length, n = self.track.length, len(self._s)
        s %= length
        i = min(max(int(s / length * n), 0), n - 1)  # samples are ~uniform: start near, then walk
        while i > 0 and self._s[i] > s:
            i -= 1
        while i + 1 < n and self._s[i + 1] <= s:
            i += 1
        j = (i + 1) % n
        s_next = self._s[j] if j else length
        return i, j, (s - self._s[i]) / max(s_next - self._s[i], 1e-9)

    def _at(self, s: float, table: list[float]) -> float:
        i, j, t = self._index(s)
        return table[i] + t * (table[j] - table[i])

    def _heading_at(self, s: float) -> float:
        i, j, t = self._index(s)
        hj = self._heading[j] if j else self._heading[-1] + (self._heading[1] - self._heading[0])  # across the wrap
        return self._heading[i] + t * (hj - self._heading[i])

    def _locate(self, x: float, y: float, front: bool) -> tuple[float, float]:
        chord = self._chord_front if front else self._chord
        hit = self.track.track_point(x, y, chord)
        if hit is None:
            s_arr, d_arr = self.track.project(np.array([x, y]))
            s, d = float(s_arr), float(d_arr)
            chord = int(np.searchsorted(self.line.track_s, s, side="right") - 1)
        else:
            s, d, chord, _ = hit
        if front:
            self._chord_front = chord
        else:
            self._chord = chord
        return s, d

    def locate(self, x: float, y: float) -> tuple[float, float]:
        """Track ``(s, d)`` [m] of the car's centre (a point near its last position)."""
        return self._locate(x, y, front=False)

    def act(self, fleet: CarFleet, car: int = 0, d_range: tuple[float, float] | None = None) -> tuple[float, float, float]:
        """``(steer, throttle, brake)`` for car ``car`` of ``fleet`` (anything with the fleet's
        pose, velocity, wheel-spin and ``dt_control`` attributes). ``d_range`` [m] (lo, hi): the lateral offsets
        the car may track this step — the line's offset is clipped into it (a race opponent giving room to a car
        beside it); None: the line."""
        prm = self.params
        x, y = float(fleet.pos[car, 0]), float(fleet.pos[car, 1])
        yaw = float(fleet.yaw[car])
        vx, vy = float(fleet.vel_body[car, 0]), float(fleet.vel_body[car, 1])
        yaw_rate = float(fleet.yaw_rate[car])
        speed = float(fleet.speed[car])
        dt = float(fleet.dt_control)
        s, _ = self.locate(x, y)
        # Steering at the front axle.
        a = prm.cg_to_front_axle
        s_f, d_f = self._locate(x + a * math.cos(yaw), y + a * math.sin(yaw), front=True)
        d_line = self._at(s_f, self._d)
        if d_range is not None:
            d_line = min(max(d_line, d_range[0]), d_range[1])
        err = d_f - d_line
        kappa = self._at(s_f + 0.15 * speed, self._kappa)
        slip = math.atan2(vy + a * yaw_rate, max(vx, 5.0))  # front axle's velocity vs the body [rad]
        self._slip += (slip - self._slip) * min(dt / self.slip_filter_s, 1.0)
        psi_err = (self._heading_at(s_f) - yaw - self._slip + math.pi) % (2.0 * math.pi) - math.pi
        delta = math.atan(prm.wheelbase * kappa) + self.k_head * psi_err - math.atan(self.k_e * err / (speed + 2.0)) \
            - self.k_yaw * (yaw_rate - speed * kappa)
        steer = max(-1.0, min(1.0, delta / prm.max_steer))
        throttle, brake = self._pedals(s, speed, yaw_rate)
        # Traction-control filter (as TORCS robots do): ease off when the driven wheels spin.
        if throttle > 0.0:
            omega = fleet.wheel_omega[car]
            pair = (2, 3) if prm.drive == "rear" else (0, 1)
            wheel_v = float(omega[pair[0]] + omega[pair[1]]) * 0.5 * prm.wheel_radius
            slip_ratio = (wheel_v - vx) / max(abs(vx), 3.0)
            limit = 0.5 * prm.peak_slip_ratio
            if slip_ratio > limit:
                throttle = max(0.0, throttle * (1.0 - 6.0 * (slip_ratio - limit) / prm.peak_slip_ratio))
        return steer, throttle, brake

    def _pedals(self, s: float, speed: float, yaw_rate: float) -> tuple[float, float]:
        """``(throttle, brake)``: the profile's acceleration ``speed_lead_s`` ahead as force, plus speed feedback."""
        m = self.params.mass
        ahead = s + speed * self.speed_lead_s + 1.0
        v_ref, a_ref = self._at(ahead, self._v), self._at(ahead, self._a)
        a_fb = self.k_v * (v_ref - speed)
        normal = m * G + self._k_down * speed * speed
        grip = self._at(s, self._mu) * self.mu_margin * normal  # [N]
        # sideways force: the line's bend here, or what the car is doing if more (it lags the line)
        lateral = m * speed * max(speed * abs(self._at(s, self._kappa)), abs(yaw_rate))
        if a_fb > 0.0:  # below the profile: catch up, but no harder than the driven tyres allow here
            total, side = grip * self.drive_share, lateral * self.drive_share
            a_grip = math.sqrt(max(total * total - side * side, 0.0)) / m
            a_cmd = max(min(a_ref + a_fb, a_grip), min(a_ref, a_grip))
        else:
            a_cmd = a_ref + a_fb
        resist = self._k_drag * speed * speed + self._at(s, self._crr) * normal
        force = m * a_cmd + resist
        k = min(int(speed), len(self._f_drive) - 1)
        f_max, f_engine_brake = self._f_drive[k], self._f_engine_brake[k]
        if force >= -f_engine_brake:  # throttle: -f_engine_brake closed .. f_max open
            return min((force + f_engine_brake) / max(f_max + f_engine_brake, 1.0), 1.0), 0.0
        return 0.0, min((-force - f_engine_brake) / self._f_brake, 1.0)


# --------------------------------------------------------------------------------------------
# Driving loop
# --------------------------------------------------------------------------------------------
@dataclass
class DriveResult:
    """Outcome of :func:`drive`.

    Attributes:
        track, surface: what was driven.
        lap_times: completed laps [s] (the first from a standing start).
        limit: physical-limit flying-lap time [s] (:func:`limit_lap_time`).
        max_offset_ratio: largest |d| of the car's centre over the local half-width [-] (> 1 = off).
        wheels_off: control steps with at least one wheel on grass (the surface the physics used
            under each wheel's hardpoint: the track's, or grass beyond an edge).
        completed: all requested laps done without the centre leaving the track.
        xy, speed: trajectory [m] and speed [m/s] per control step (for plots).
        wall_s: wall-clock time of the run [s].
        control_hz, substeps: the control rate it was driven at [Hz] and physics substeps per control step.
        min_wheel_margin_m: smallest distance of any wheel's hardpoint inside its nearer track edge over
            the run [m] (< 0: that wheel was on the grass).
    """

    track: str
    surface: str
    lap_times: list[float]
    limit: float
    max_offset_ratio: float
    wheels_off: int
    completed: bool
    xy: np.ndarray = field(repr=False)
    speed: np.ndarray = field(repr=False)
    wall_s: float = 0.0
    control_hz: float = 50.0
    substeps: int = 4
    min_wheel_margin_m: float = float("nan")

    @property
    def best_lap(self) -> float:
        """Best lap [s] (nan if none)."""
        return min(self.lap_times) if self.lap_times else float("nan")

    @property
    def clean(self) -> bool:
        """All laps completed with no wheel ever on the grass."""
        return self.completed and self.wheels_off == 0


class _WheelSurfaces:
    """surface_fn for the fleet: the track's surface under each wheel, grass off the track (scalar fast path).

    Each call also records ``margin``: the smallest distance [m] of a wheel inside its nearer edge
    (negative: that wheel is on the grass).
    """

    def __init__(self, track: Track) -> None:
        self.track = track
        self.chords = [0, 0, 0, 0]
        self.grass = surf.GRASS_ID
        self.margin = math.inf

    def __call__(self, wheel_xy: np.ndarray) -> np.ndarray:
        ids = np.empty((1, 4), dtype=np.int64)
        margin = math.inf
        for j, (x, y) in enumerate(wheel_xy[0].tolist()):
            hit = self.track.track_point(x, y, self.chords[j])
            if hit is None:
                s_arr, d_arr = self.track.project(np.array([x, y]))
                wl, wr = (float(w) for w in self.track.width(float(s_arr)))
                d = float(d_arr)
                sid = int(self.track.surface(float(s_arr)))
            else:
                _, d, chord, t = hit
                self.chords[j] = chord
                wl, wr, _, sid = self.track.frame_at(chord, t)
            inside = min(wl - d, d + wr)
            margin = min(margin, inside)
            ids[0, j] = sid if inside >= 0.0 else self.grass
        self.margin = margin
        return ids


def default_substeps(control_hz: float) -> int:
    """Physics substeps per control step for a physics rate of at least 200 Hz (50 Hz: 4, 10 Hz: 20)."""
    return max(1, math.ceil(200.0 / float(control_hz) - 1e-9))


def drive(
    track: Track,
    laps: int = 10,
    params: VehicleParams | None = None,
    mu_margin: float = 0.85,
    line: str = "racing",
    max_time_s: float | None = None,
    control_hz: float = 50.0,
    substeps: int | None = None,
    expert_kwargs: dict | None = None,
) -> DriveResult:
    """Drive ``laps`` laps of ``track`` with the :class:`ExpertDriver` (fleet of one, ground plane).

    The car is driven at ``control_hz`` [Hz] (one :meth:`ExpertDriver.act` per control step, the
    controls held over ``substeps`` physics steps; default: :func:`default_substeps`, 200 Hz
    physics), as :class:`~torcsrl.envs.race.RaceEnv` does with the same settings (training:
    ``control_hz=10, substeps=20``). Stops early when the car's centre leaves the track (|d|
    beyond the half-width) or after ``max_time_s`` simulated seconds (default: three times the
    physical limit per lap + 60 s). ``expert_kwargs``: more :class:`ExpertDriver` arguments.
    A wheel on the grass (``DriveResult.wheels_off``) does not stop the run; ``DriveResult.clean``
    says whether the run stayed on the road with every wheel.
    """
    params = params or VehicleParams.load("default")
    substeps = default_substeps(control_hz) if substeps is None else int(substeps)
    t_wall = time.perf_counter()
    limit = limit_lap_time(track, params=params)
    cid = p.connect(p.DIRECT)
    try:
        make_ground(cid)
        surface_fn = _WheelSurfaces(track)
        fleet = CarFleet(cid, 1, params, surface_fn=surface_fn, control_hz=control_hz, substeps=substeps)
        expert = ExpertDriver(track, params, mu_margin=mu_margin, line=line, **(expert_kwargs or {}))
        xy0, yaw0 = track.start_pose()
        fleet.reset([0], xy0[None], [yaw0], [0.0])
        expert.reset(0.0)
        dt = fleet.dt_control
        max_steps = int((max_time_s if max_time_s is not None else 3.0 * limit * laps + 60.0) / dt)
        s_prev, progress, lap_start = 0.0, 0.0, 0.0
        lap_times: list[float] = []
        worst, wheels_off, margin = 0.0, 0, math.inf
        xs, speeds = [], []
        for k in range(max_steps):
            steer, throttle, brake = expert.act(fleet)
            fleet.step(steer, throttle, brake)  # reads the surfaces under the wheels where this step starts
            wheels_off += int((fleet.wheel_surfaces == surf.GRASS_ID).any())
            margin = min(margin, surface_fn.margin)
            x, y = float(fleet.pos[0, 0]), float(fleet.pos[0, 1])
            s, d = expert.locate(x, y)
            wl, wr = track.width(s)
            worst = max(worst, d / float(wl) if d >= 0 else -d / float(wr))
            xs.append((x, y))
            speeds.append(float(fleet.speed[0]))
            progress += float(track.wrap_delta(s, s_prev))
            s_prev = s
            if progress >= track.length * (len(lap_times) + 1):
                t_now = (k + 1) * dt
                lap_times.append(t_now - lap_start)
                lap_start = t_now
                if len(lap_times) >= laps:
                    break
            if worst > 1.0:
                break
        # the wheels where the last step ended
        wheels_off += int((surface_fn(fleet.wheel_xy) == surf.GRASS_ID).any())
        margin = min(margin, surface_fn.margin)
        completed = len(lap_times) >= laps and worst <= 1.0
        return DriveResult(track.name, track.default_surface, lap_times, limit, worst, wheels_off, completed,
                           np.asarray(xs), np.asarray(speeds), time.perf_counter() - t_wall,
                           float(control_hz), substeps, float(margin))
    finally:
        p.disconnect(cid)


def plot_run(result: DriveResult, track: Track, path: str) -> None:
    """Top-down trajectory coloured by speed [km/h], with the track edges, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    fig, ax = plt.subplots(figsize=(8, 8))
    for edge in (track.left_edge, track.right_edge):
        closed = np.vstack([edge, edge[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.3", lw=0.8)
    pts = result.xy
    segs = np.stack([pts[:-1], pts[1:]], axis=1)
    lc = LineCollection(segs, cmap="viridis", linewidths=1.5)
    lc.set_array(result.speed[:-1] * 3.6)
    ax.add_collection(lc)
    fig.colorbar(lc, ax=ax, label="speed [km/h]", shrink=0.8)
    best = f"best lap {result.best_lap:.2f} s" if result.lap_times else "no lap"
    ax.set_title(f"{track.name} on {result.surface}: {best} (limit {result.limit:.2f} s)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _row(r: DriveResult) -> str:
    flying = r.lap_times[1:] or r.lap_times
    mean = float(np.mean(flying)) if flying else float("nan")
    return (f"{r.track:15s} {r.surface:8s} {len(r.lap_times):>4d} {r.lap_times[0] if r.lap_times else float('nan'):>8.2f} "
            f"{r.best_lap:>8.2f} {mean:>8.2f} {r.limit:>8.2f} {r.best_lap / r.limit:>6.3f} {r.max_offset_ratio:>7.2f} "
            f"{r.wheels_off:>6d} {'yes' if r.completed else 'NO':>5s} {r.wall_s:>6.0f}")


_HEADER = (f"{'track':15s} {'surface':8s} {'laps':>4s} {'lap1 s':>8s} {'best s':>8s} {'mean s':>8s} {'limit s':>8s} "
           f"{'ratio':>6s} {'max|d|/w':>7s} {'wheels':>6s} {'done':>5s} {'wall s':>6s}")


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns a process exit status (1 if a run left the track or fell short)."""
    from torcsrl.envs import tracks

    parser = argparse.ArgumentParser(prog="python -m torcsrl.envs.expert",
                                     description="Drive the scripted expert and compare with the physical-limit lap time.")
    parser.add_argument("--track", default="road_flow", help=f"track name ({', '.join(tracks.names())})")
    parser.add_argument("--surface", default=None, help=f"road surface for the whole track ({', '.join(surf.ROAD_SURFACES)}); "
                                                        "default: the track's own")
    parser.add_argument("--laps", type=int, default=10)
    parser.add_argument("--vehicle", default="default", help="vehicle parameter file")
    parser.add_argument("--mu-margin", type=float, default=0.85, help="fraction of mu the expert's speed profile uses")
    parser.add_argument("--line", default="racing", choices=LINES)
    parser.add_argument("--control-hz", type=float, default=50.0,
                        help="control rate [Hz] the expert drives at (the training env: 10); physics at >= 200 Hz")
    parser.add_argument("--substeps", type=int, default=None,
                        help="physics substeps per control step (default: 200 Hz physics, e.g. 4 at 50 Hz, 20 at 10 Hz)")
    parser.add_argument("--plot", default=None, help="write a top-down trajectory PNG coloured by speed")
    parser.add_argument("--all", action="store_true", help="every bundled track on asphalt and dirt: print a table")
    args = parser.parse_args(argv)
    if args.laps < 1:
        parser.error("--laps must be >= 1")
    if args.control_hz <= 0:
        parser.error("--control-hz must be > 0")
    params = VehicleParams.load(args.vehicle)
    substeps = default_substeps(args.control_hz) if args.substeps is None else args.substeps
    rate = f"{args.control_hz:g} Hz control, {substeps} substeps ({args.control_hz * substeps:g} Hz physics)"

    if args.all:
        print(f"expert at {rate}, {args.laps} laps from a standing start")
        print(_HEADER)
        ok = True
        for name in tracks.names():
            for surface in ("asphalt", "dirt"):
                r = drive(tracks.load(name, surface=surface), args.laps, params, args.mu_margin, args.line,
                          control_hz=args.control_hz, substeps=substeps)
                ok &= r.clean
                print(_row(r), flush=True)
        return 0 if ok else 1

    track = tracks.load(args.track, surface=args.surface)
    r = drive(track, args.laps, params, args.mu_margin, args.line, control_hz=args.control_hz, substeps=substeps)
    print(f"{track.name} on {r.surface} ({track.length:.0f} m), {len(r.lap_times)}/{args.laps} laps at {rate}, "
          f"physical limit {r.limit:.2f} s (point mass, quasi-steady state)")
    for i, t in enumerate(r.lap_times, 1):
        print(f"  lap {i:2d}: {t:7.2f} s   ({t / r.limit:.3f} x limit){'  standing start' if i == 1 else ''}")
    print(f"max |d| / half-width {r.max_offset_ratio:.2f}; steps with a wheel on grass: {r.wheels_off} "
          f"(closest wheel to an edge {r.min_wheel_margin_m:+.2f} m); "
          f"{'completed' if r.completed else 'NOT completed'}; wall {r.wall_s:.1f} s")
    if r.lap_times:
        print(f"reference lap (best): {r.best_lap:.2f} s at {args.control_hz:g} Hz control")
    if args.plot:
        plot_run(r, track, args.plot)
        print(f"wrote {args.plot}")
    return 0 if r.clean else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except ValueError as exc:  # bad track / surface / vehicle name: one clear line
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
