"""The scripted expert and its driving loop.

* :class:`ExpertDriver`: Stanley-style path tracking (curvature feed-forward, heading and cross-track feedback, the
  heading measured against the front axle's filtered slip angle) on the minimum-curvature line plus a speed
  controller that feeds the profile's acceleration forward through a model of the engine and brakes, on a derated
  profile, with a TORCS-robot-style traction-control throttle filter. It reads only what the car exposes (pose,
  velocities, wheel spin) and works at any control rate.
* :func:`drive`: a fleet of one on a ground plane, the surface under each wheel from the track, driven by the
  expert for some laps (:class:`DriveResult`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from torcsrl.envs import surfaces as surf
from torcsrl.envs.expert.line import racing_line
from torcsrl.envs.expert.profile import G, limit_lap_time, speed_profile
from torcsrl.envs.track import Track
from torcsrl.envs.vehicle import CarFleet, VehicleParams, make_ground
from torcsrl.utils.bullet import pybullet as p

__all__ = ["ExpertDriver", "DriveResult", "drive", "default_substeps"]


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
