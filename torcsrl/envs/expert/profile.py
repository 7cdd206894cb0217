"""Speed along a line and the physical lap-time limit.

* :func:`speed_profile`: quasi-steady-state point-mass speed along a line: the cornering limit
  ``v^2 |kappa| m = mu (m g + downforce)``, then a forward pass (acceleration limited by the
  friction circle, the engine's peak wheel power, drag and rolling resistance) and a backward pass
  (braking limited by the friction circle, helped by drag and rolling resistance), both around
  the closed loop.
* :func:`limit_lap_time`: the "physical limit" — the flying-lap time of that point mass on the fastest of the
  centreline and a few lines between minimum curvature and minimum length.
"""

from __future__ import annotations

import math

import numpy as np

from torcsrl.envs.expert.line import LINES, RacingLine, racing_line
from torcsrl.envs.track import Track
from torcsrl.envs.vehicle import VehicleParams

__all__ = ["G", "LIMIT_LENGTH_WEIGHTS", "speed_profile", "limit_lap_time"]

G = 9.81  # [m/s^2]
#: Length weights [1/m^2] of the candidate lines the "best" physical limit tries (0 = minimum curvature).
LIMIT_LENGTH_WEIGHTS: tuple[float, ...] = (0.0, 3e-5, 1e-4, 3e-4)


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
