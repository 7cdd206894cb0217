"""The numpy backend of :class:`~torcsrl.envs.vehicle.fleet.CarFleet`: every substep vectorised over all wheels
of all cars, a fixed number of array operations whatever N.

:class:`NumpyBackend` is a mixin of the fleet (its methods read and write the fleet's state). Its per-control-step
part (:meth:`NumpyBackend._step_numpy`: steering, powertrain, aero) and its pybullet calls
(:meth:`NumpyBackend._read_state`, :meth:`NumpyBackend._apply_and_step`) serve the numba backend too, whose
per-substep arithmetic is :mod:`~torcsrl.envs.vehicle.numba_backend`'s compiled kernels instead of
:meth:`NumpyBackend._substep_numpy`. The same equations car by car in floats:
:mod:`~torcsrl.envs.vehicle.python_backend`.
"""

from __future__ import annotations

from collections import deque
from itertools import chain

import numpy as np

from torcsrl.envs.vehicle.ground import GROUND_GROUP
from torcsrl.envs.vehicle.params import RPM_PER_RAD_S
from torcsrl.utils.bullet import pybullet as p

__all__ = ["NumpyBackend"]

_flat = chain.from_iterable


def _consume(calls) -> None:
    """Run an iterator of calls for their effects (``map`` over a C function: no Python frame per call)."""
    deque(calls, maxlen=0)


def _plane_hits(z_from: np.ndarray, z_to: np.ndarray) -> np.ndarray:
    """Hit fractions of rays from height ``z_from`` to ``z_to`` [m] with the plane z = 0 (either
    face, as bullet's ray test); 9.0 (far below: no spring force) where a ray does not reach it."""
    dz = z_from - z_to
    hit = (z_from * z_to <= 0.0) & (dz != 0.0)
    return np.where(hit, z_from / np.where(hit, dz, 1.0), 9.0)


def _quat_to_matrix_table() -> tuple[np.ndarray, np.ndarray]:
    """``R.flat = (q q^T).flat @ M + c`` for a unit quaternion q = (x, y, z, w) (pybullet order)."""
    x, y, z, w = range(4)
    terms = {  # R[i, j] = c_ij + sum(coef * q_a * q_b)
        (0, 0): [(-2, y, y), (-2, z, z)], (0, 1): [(2, x, y), (-2, z, w)], (0, 2): [(2, x, z), (2, y, w)],
        (1, 0): [(2, x, y), (2, z, w)], (1, 1): [(-2, x, x), (-2, z, z)], (1, 2): [(2, y, z), (-2, x, w)],
        (2, 0): [(2, x, z), (-2, y, w)], (2, 1): [(2, y, z), (2, x, w)], (2, 2): [(-2, x, x), (-2, y, y)],
    }
    m = np.zeros((16, 9))
    for (i, j), items in terms.items():
        for coef, a, b in items:
            m[4 * a + b, 3 * i + j] += coef
    return m, np.eye(3).reshape(9)


_QM, _QC = _quat_to_matrix_table()


class NumpyBackend:
    """The numpy (and numba) backend's methods of :class:`~torcsrl.envs.vehicle.fleet.CarFleet`."""

    # ---- state ------------------------------------------------------------------------------
    def _read_state(self) -> None:
        """numpy backend: read every car's pose and velocity once and derive the cached frames."""
        cid, n = self.client, self.n
        live = self._live
        bodies, cids = (self.bodies, self._cids) if live is None else (live.bodies, live.cids)
        # one row per car: position (3), quaternion xyzw (4), linear (3) and angular (3) velocity; read car by car
        # (pose, then velocity) and flattened in C (map, chain, fromiter: no Python frame per car)
        parts = zip(map(p.getBasePositionAndOrientation, bodies, cids), map(p.getBaseVelocity, bodies, cids))
        raw = np.fromiter(_flat(_flat(_flat(parts))), dtype=np.float64, count=13 * len(bodies)).reshape(-1, 13)
        if live is not None:  # parked cars keep their last rows
            raw, rows = self._raw.copy(), raw
            raw[live.idx] = rows
        self._raw = raw
        if self._kernels is not None:  # the same frames, compiled (and the plane's ray hits with them)
            self._rot, self._twist_b, self._ray_pts, self._ground_xy, self._plane_frac = \
                self._kernels.read_frames(raw, self._ray_pts_local, self.ground == "plane")
            return
        quat = raw[:, 3:7]
        rot = ((quat[:, :, None] * quat[:, None, :]).reshape(n, 16) @ _QM + _QC).reshape(n, 3, 3)  # body -> world
        self._rot = rot
        # body-frame twist: the rows (v, w) times R are (R^T v, R^T w)
        self._twist_b = np.matmul(raw[:, 7:13].reshape(n, 2, 3), rot).reshape(n, 6)
        # suspension ray start and end points in the world frame [N, 8, 3]
        self._ray_pts = np.matmul(self._ray_pts_local, rot.transpose(0, 2, 1)) + raw[:, None, 0:3]
        # Ground frame (x: heading projected on the ground, y: its left, z: world up) in body
        # coordinates: x_g + i y_g = exp(-i yaw) (R[0] + i R[1]) and z_g = R[2] (rows of R).
        rc = rot[:, 0, :] + 1j * rot[:, 1, :]
        heading = rc[:, 0].conj()
        self._ground_xy = (heading / np.maximum(np.abs(heading), 1e-12))[:, None] * rc  # [N, 3] complex

    # ---- numpy backend: every substep vectorised over all wheels of all cars ------------------
    def _step_numpy(self, controls: np.ndarray) -> None:
        prm, n = self.params, self.n
        steer, throttle, brake = controls
        # Steering: rate-limited road-wheel angle; Ackermann split over the front wheels.
        max_d = prm.max_steer_rate * self.dt_control
        delta = self._delta + np.minimum(np.maximum(steer * prm.max_steer - self._delta, -max_d), max_d)
        self._delta = delta
        tan_d = np.tan(delta)[:, None]
        front = np.arctan(prm.wheelbase * tan_d / (prm.wheelbase - self._ack_half_tracks * tan_d))
        if prm.ackermann != 1.0:
            front = prm.ackermann * front + (1.0 - prm.ackermann) * delta[:, None]
        rot = np.ones((n, 4), dtype=complex)  # exp(i * wheel angle): wheel frame -> ground frame
        rot[:, 0:2] = np.exp(1j * front)

        # Powertrain: automatic gearbox, engine speed and torque, drive and brake torques.
        drive_speed = self._omega @ self._drive_split  # [rad/s] mean driven-wheel speed
        gear = self._gear
        wheel_rpm = drive_speed * self._ratios[gear - 1] * RPM_PER_RAD_S
        shift = (wheel_rpm > prm.shift_up_rpm) & (gear < len(self._ratios))
        shift = shift.astype(np.int64) - ((wheel_rpm < prm.shift_down_rpm) & (gear > 1))
        if shift.any():
            gear = gear + shift
            wheel_rpm = drive_speed * self._ratios[gear - 1] * RPM_PER_RAD_S
        self._gear = gear
        ratio = self._ratios[gear - 1]
        rpm = np.maximum(wheel_rpm, prm.idle_rpm + (prm.clutch_rpm - prm.idle_rpm) * throttle)  # clutch slips
        self._rpm = rpm
        torque = np.interp(rpm, self._curve_rpm, self._curve_nm) * throttle * (rpm < prm.redline_rpm) \
            - (wheel_rpm > prm.clutch_rpm) * (1.0 - throttle) * (prm.engine_brake_nm / prm.redline_rpm) * rpm
        drive_a = (torque * ratio * (prm.drivetrain_efficiency * self._wheel_a))[:, None] * self._drive_split
        brake_a = (brake * self._wheel_a)[:, None] * self._brake_split  # [rad/s] per substep
        abs_on = (brake > 0.0)[:, None] if (prm.abs and brake.any()) else None
        tcs_on = (throttle > 0.0)[:, None] & self._driven if (prm.traction_control and throttle.any()) else None

        # Aero (held over the control step): drag against the body velocity, downforce at the axles.
        vb = self._twist_b[:, 0:3]
        aero = np.zeros((n, 6))
        aero[:, 0:3] = (-self._drag_k * np.sqrt(np.sum(vb * vb, axis=1)))[:, None] * vb
        aero += (self._down_k * vb[:, 0] * vb[:, 0])[:, None] * self._down_wrench

        if self._kernels is not None:
            abs_k = np.zeros(n, dtype=bool) if abs_on is None else abs_on[:, 0]
            tcs_k = np.zeros((n, 4), dtype=bool) if tcs_on is None else tcs_on
            for _ in range(self.substeps):
                self._substep_numba(rot, drive_a, brake_a, aero, abs_k, tcs_k)
            return
        for _ in range(self.substeps):
            self._substep_numpy(rot, drive_a, brake_a, aero, abs_on, tcs_on)

    def _substep_numpy(self, rot: np.ndarray, drive_a: np.ndarray, brake_a: np.ndarray, aero: np.ndarray,
                       abs_on: np.ndarray | None, tcs_on: np.ndarray | None) -> None:
        prm, n = self.params, self.n
        r = prm.wheel_radius
        # Suspension: one ray batch for every wheel of every car; a miss counts as far below.
        if self.ground == "plane":
            frac = _plane_hits(self._ray_pts[:, 0:4, 2], self._ray_pts[:, 4:8, 2])
        else:
            frac = self._ray_fracs()
        vp = (self._twist_b @ self._jac_t).reshape(n, 4, 3)  # contact-point velocities (body frame)
        fz = self._k_a - self._k_l * frac - self._damp * vp[:, :, 2] \
            + np.maximum(self._bump_a - self._bump_l * frac, 0.0)
        fz = np.minimum(np.maximum(fz, 0.0), prm.max_wheel_load)
        # Tyres: slip in the wheel frame (ground plane), combined-slip magic formula (friction circle).
        ground_xy = self._ground_xy
        w = (vp @ ground_xy[:, :, None])[:, :, 0] * rot.conj()
        vx, vy = w.real, w.imag
        big_v = np.maximum(np.abs(vx), prm.low_speed)
        inv_kp = self._inv_kp / big_v
        omega = self._omega
        sx = (omega * r - vx) * inv_kp
        sy = vy * (-self._inv_ap / big_v)
        s = np.hypot(sx, sy) + 1e-9
        g = (self._mu * fz) * np.sin(prm.shape_c * np.arctan(self._mf_b * s)) / s  # force per unit slip [N]
        # Wheel spin, semi-implicit in the tyre's secant stiffness k = g * inv_kp / r per (m/s):
        # w' = (w + a (T_drive + r k vx)) / (1 + a r^2 k); brake and rolling-resistance torques
        # then reduce |w'| but never reverse it.
        k_r = g * inv_kp * (r * self._wheel_a)
        denom = 1.0 + k_r * r
        w_free = (omega + drive_a + k_r * vx) / denom
        dw = (brake_a + self._crr_a * fz) / denom
        w_new = np.maximum(w_free - dw, np.minimum(w_free + dw, 0.0))
        if abs_on is not None:  # ABS: braked wheels stay at or above -peak slip
            w_new = np.where(abs_on, np.maximum(w_new, (vx - prm.peak_slip_ratio * big_v) * (1.0 / r)), w_new)
        if tcs_on is not None:  # traction control: driven wheels stay at or below +peak slip
            w_new = np.where(tcs_on, np.minimum(w_new, (vx + prm.peak_slip_ratio * big_v) * (1.0 / r)), w_new)
        self._omega = w_new
        self._fz = fz
        # Wheel forces: tyre force in the ground plane, normal load along world up; to the body
        # frame, then summed with aero into one body wrench at the COM.
        f_ground = ((g * sx + 1j * (g * sy)) * rot).conj()  # (fx - i fy) in the ground frame
        forces = (f_ground[:, :, None] * ground_xy[:, None, :]).real + fz[:, :, None] * self._rot[:, None, 2, :]
        wrench = forces.reshape(n, 12) @ self._jac + aero
        world = np.matmul(wrench.reshape(n, 2, 3), self._rot.transpose(0, 2, 1))  # (R f, R tau)
        self._apply_and_step(world)

    def _substep_numba(self, rot: np.ndarray, drive_a: np.ndarray, brake_a: np.ndarray, aero: np.ndarray,
                       abs_on: np.ndarray, tcs_on: np.ndarray) -> None:
        """numba backend: :meth:`_substep_numpy`'s arithmetic in one compiled kernel; the same pybullet calls."""
        prm = self.params
        frac = self._plane_frac if self.ground == "plane" else self._ray_fracs()
        self._omega, self._fz, world = self._kernels.substep(
            frac, self._twist_b, self._rot, self._ground_xy, rot, self._omega, self._mu, self._crr_a, drive_a, brake_a,
            abs_on, tcs_on, aero, self._contact_local, self._k_a, self._k_l, self._damp, float(self._bump_a),
            float(self._bump_l), float(prm.max_wheel_load), float(prm.low_speed), self._inv_kp, self._inv_ap,
            float(prm.wheel_radius), self._wheel_a, float(prm.shape_c), self._mf_b, float(prm.peak_slip_ratio))
        self._apply_and_step(world)

    def _ray_fracs(self) -> np.ndarray:
        """Suspension ray hit fractions ``[N, 4]`` from pybullet's ray test (ground="raycast"); 9.0 for a miss."""
        pts = self._ray_pts.tolist()
        frm = [w for car in pts for w in car[0:4]]
        to = [w for car in pts for w in car[4:8]]
        hits = p.rayTestBatch(frm, to, numThreads=1, collisionFilterMask=GROUND_GROUP, physicsClientId=self.client)
        return np.array([h[2] if h[0] >= 0 else 9.0 for h in hits]).reshape(self.n, 4)

    def _apply_and_step(self, world: np.ndarray) -> None:
        """numpy and numba backends: apply every live car's world-frame force and torque ``[N, 2, 3]`` at its COM (every
        car's force, then every car's torque: each body accumulates its own, the same sums as car by car), step every
        world, book contacts, read the new state."""
        live, pos = self._live, self._raw[:, 0:3]
        if live is None:
            bodies, links, frames, cids = self.bodies, self._links, self._world_frames, self._cids
        else:  # parked cars: no forces
            bodies, links, frames, cids = live.bodies, live.links, live.frames, live.cids
            world, pos = world[live.idx], pos[live.idx]
        _consume(map(p.applyExternalForce, bodies, links, world[:, 0].tolist(), pos.tolist(), frames, cids))
        _consume(map(p.applyExternalTorque, bodies, links, world[:, 1].tolist(), frames, cids))
        for c in self.clients:
            p.stepSimulation(physicsClientId=c)
        if self.contact_impulse is not None:
            self._collect_contacts()
        self._read_state()

