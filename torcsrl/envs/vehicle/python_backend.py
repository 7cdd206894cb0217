"""The python backend of :class:`~torcsrl.envs.vehicle.fleet.CarFleet`: the equations of the numpy backend
(:mod:`~torcsrl.envs.vehicle.numpy_backend`), one for one, car by car in Python floats.

For a few cars this beats numpy, whose per-call overhead (~1 us) then dominates. :class:`PythonBackend` is a mixin
of the fleet (its methods read and write the fleet's state); tests check that the backends agree.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from torcsrl.envs.vehicle.ground import GROUND_GROUP
from torcsrl.envs.vehicle.params import RPM_PER_RAD_S
from torcsrl.utils.bullet import pybullet as p

__all__ = ["PythonBackend"]

_MISS = (-1, -1, 9.0)  # a suspension ray that meets no ground (read as far below)


class PythonBackend:
    """The python backend's methods of :class:`~torcsrl.envs.vehicle.fleet.CarFleet`."""

    # ---- python backend: the same equations, car by car, in floats -----------------------------
    def _read_frames(self) -> None:
        """python backend: read every car's state once; keep per-car frames and ray ends as floats."""
        cid, ray_len, hard = self.client, self._ray_len, self._hard_list
        gp, gv, gm, hypot = p.getBasePositionAndOrientation, p.getBaseVelocity, p.getMatrixFromQuaternion, math.hypot
        raws, frames, frm, to = [], [], [], []
        for b in self.bodies:
            pos, quat = gp(b, physicsClientId=cid)
            vel, angvel = gv(b, physicsClientId=cid)
            (vx, vy, vz), (wx, wy, wz) = vel, angvel
            m = gm(quat)  # row-major body -> world
            twist = (m[0] * vx + m[3] * vy + m[6] * vz, m[1] * vx + m[4] * vy + m[7] * vz,
                     m[2] * vx + m[5] * vy + m[8] * vz, m[0] * wx + m[3] * wy + m[6] * wz,
                     m[1] * wx + m[4] * wy + m[7] * wz, m[2] * wx + m[5] * wy + m[8] * wz)
            # ground frame in body coordinates: x_g (heading on the ground), y_g (its left)
            h = max(hypot(m[0], m[3]), 1e-12)
            ch, sh = m[0] / h, m[3] / h
            xg = (ch * m[0] + sh * m[3], ch * m[1] + sh * m[4], ch * m[2] + sh * m[5])
            yg = (ch * m[3] - sh * m[0], ch * m[4] - sh * m[1], ch * m[5] - sh * m[2])
            raws.append(pos + quat + vel + angvel)
            frames.append((pos, m, twist, xg, yg))
            px, py, pz = pos
            ux, uy, uz = m[2] * ray_len, m[5] * ray_len, m[8] * ray_len
            for hx, hy, hz in hard:
                ax = px + m[0] * hx + m[1] * hy + m[2] * hz
                ay = py + m[3] * hx + m[4] * hy + m[5] * hz
                az = pz + m[6] * hx + m[7] * hy + m[8] * hz
                frm.append((ax, ay, az))
                to.append((ax - ux, ay - uy, az - uz))
        self._frames, self._raws, self._frm, self._to = frames, raws, frm, to

    def _publish_frames(self) -> None:
        """python backend: the cached frames as the public numpy state arrays."""
        n = self.n
        self._raw = np.array(self._raws)
        self._rot = np.array([f[1] for f in self._frames]).reshape(n, 3, 3)
        self._twist_b = np.array([f[2] for f in self._frames])
        if n == 1:  # one array call instead of three (the same numbers)
            self._ray_pts = np.array(self._frm + self._to).reshape(1, 8, 3)
        else:
            self._ray_pts = np.concatenate([np.reshape(self._frm, (n, 4, 3)), np.reshape(self._to, (n, 4, 3))], axis=1)

    def _step_python(self, controls: np.ndarray) -> None:
        """One control step car by car in floats: the equations of :meth:`_step_numpy` and
        :meth:`_substep_numpy`, one for one (tests check that both backends agree). For a few
        cars this beats numpy, whose per-call overhead (~1 us) then dominates."""
        prm, n, cid = self.params, self.n, self.client
        r, low, c_mf, b_mf = prm.wheel_radius, prm.low_speed, prm.shape_c, self._mf_b
        ikp, iap, ra, kp = self._inv_kp, self._inv_ap, r * self._wheel_a, prm.peak_slip_ratio
        fz_max, wheel_a = prm.max_wheel_load, self._wheel_a
        k_a, k_l, damp = self._k_a_list, self._k_l_list, self._damp_list
        bump_a, bump_l = self._bump_a, self._bump_l
        contact = self._contact_list
        split, brake_split, driven = self._drive_split_list, self._brake_split_list, self._driven_list
        mu_all, crr_all = self._mu.tolist(), self._crr_a.tolist()
        omega_all, fz_all = self._omega.tolist(), self._fz.tolist()
        steer_l, throttle_l, brake_l = controls.tolist()
        delta_l, gear_l, rpm_l = self._delta.tolist(), self._gear.tolist(), self._rpm.tolist()
        ratios, n_gears = self._ratios_list, len(self._ratios_list)
        wb, ht, ack = prm.wheelbase, prm.track_front / 2.0, prm.ackermann
        max_d = prm.max_steer_rate * self.dt_control
        atan, sin, cos, tan, hypot, sqrt = math.atan, math.sin, math.cos, math.tan, math.hypot, math.sqrt

        # Per control step, per car: steering, powertrain, aero (held over the substeps).
        cars = []
        for i in range(n):
            steer, throttle, brake = steer_l[i], throttle_l[i], brake_l[i]
            delta = delta_l[i] + min(max(steer * prm.max_steer - delta_l[i], -max_d), max_d)
            delta_l[i] = delta
            tan_d = tan(delta)
            fl = atan(wb * tan_d / (wb - ht * tan_d))
            fr = atan(wb * tan_d / (wb + ht * tan_d))
            if ack != 1.0:
                fl, fr = ack * fl + (1.0 - ack) * delta, ack * fr + (1.0 - ack) * delta
            cw = (cos(fl), cos(fr), 1.0, 1.0)
            sw = (sin(fl), sin(fr), 0.0, 0.0)
            om = omega_all[i]
            drive_speed = om[0] * split[0] + om[1] * split[1] + om[2] * split[2] + om[3] * split[3]
            gear = gear_l[i]
            wheel_rpm = drive_speed * ratios[gear - 1] * RPM_PER_RAD_S
            shift = int(wheel_rpm > prm.shift_up_rpm and gear < n_gears) - int(wheel_rpm < prm.shift_down_rpm and gear > 1)
            if shift:
                gear += shift
                wheel_rpm = drive_speed * ratios[gear - 1] * RPM_PER_RAD_S
            gear_l[i] = gear
            ratio = ratios[gear - 1]
            rpm = max(wheel_rpm, prm.idle_rpm + (prm.clutch_rpm - prm.idle_rpm) * throttle)
            rpm_l[i] = rpm
            torque = self._torque_at(rpm) * throttle * (rpm < prm.redline_rpm) \
                - (wheel_rpm > prm.clutch_rpm) * (1.0 - throttle) * (prm.engine_brake_nm / prm.redline_rpm) * rpm
            t_a = torque * ratio * (prm.drivetrain_efficiency * wheel_a)
            drive = (t_a * split[0], t_a * split[1], t_a * split[2], t_a * split[3])
            b_a = brake * wheel_a
            brk = (b_a * brake_split[0], b_a * brake_split[1], b_a * brake_split[2], b_a * brake_split[3])
            abs_i = prm.abs and brake > 0.0
            tcs_i = (prm.traction_control and throttle > 0.0, driven)
            bvx, bvy, bvz = self._frames[i][2][0:3]
            dk = -self._drag_k * sqrt(bvx * bvx + bvy * bvy + bvz * bvz)
            down = self._down_k * bvx * bvx
            aero = (dk * bvx, dk * bvy, dk * bvz - down, 0.0, self._down_wrench[4] * down, 0.0)
            cars.append((cw, sw, drive, brk, abs_i, tcs_i, aero))

        apply_f, apply_t, world = p.applyExternalForce, p.applyExternalTorque, p.WORLD_FRAME
        bodies = self.bodies
        plane = self.ground == "plane"
        for _ in range(self.substeps):
            if plane:
                hits = [(0, -1, fz_ / (fz_ - tz_)) if fz_ * tz_ <= 0.0 and fz_ != tz_ else _MISS
                        for (_, _, fz_), (_, _, tz_) in zip(self._frm, self._to)]
            else:
                hits = p.rayTestBatch(self._frm, self._to, numThreads=1, collisionFilterMask=GROUND_GROUP,
                                      physicsClientId=cid)
            for i, b in enumerate(bodies):
                pos, m, (bvx, bvy, bvz, bwx, bwy, bwz), (xx, xy, xz), (yx, yy, yz) = self._frames[i]
                zx, zy, zz = m[6], m[7], m[8]
                cw, sw, drive, brk, abs_i, (tcs_i, tcs_w), aero = cars[i]
                fx_t, fy_t, fz_t, tx_t, ty_t, tz_t = aero
                om, fzs, mu, crr = omega_all[i], fz_all[i], mu_all[i], crr_all[i]
                for j in range(4):
                    h = hits[4 * i + j]
                    frac = h[2] if h[0] >= 0 else 9.0
                    cx, cy, cz = contact[j]
                    # contact-point velocity (body frame): v + w x r
                    pvx = bvx + (bwy * cz - bwz * cy)
                    pvy = bvy + (bwz * cx - bwx * cz)
                    pvz = bvz + (bwx * cy - bwy * cx)
                    fz = k_a[j] - k_l[j] * frac - damp[j] * pvz + max(bump_a - bump_l * frac, 0.0)
                    fz = min(max(fz, 0.0), fz_max)
                    gvx = pvx * xx + pvy * xy + pvz * xz  # ground frame
                    gvy = pvx * yx + pvy * yy + pvz * yz
                    c, s_ = cw[j], sw[j]
                    vxw = c * gvx + s_ * gvy  # wheel frame
                    vyw = c * gvy - s_ * gvx
                    big_v = max(abs(vxw), low)
                    inv_kp = ikp / big_v
                    w0 = om[j]
                    sx = (w0 * r - vxw) * inv_kp
                    sy = vyw * (-iap / big_v)
                    sn = hypot(sx, sy) + 1e-9
                    g = (mu[j] * fz) * sin(c_mf * atan(b_mf * sn)) / sn
                    k_r = g * inv_kp * ra
                    denom = 1.0 + k_r * r
                    w_free = (w0 + drive[j] + k_r * vxw) / denom
                    dw = (brk[j] + crr[j] * fz) / denom
                    w_new = max(w_free - dw, min(w_free + dw, 0.0))
                    if abs_i:
                        w_new = max(w_new, (vxw - kp * big_v) * (1.0 / r))
                    if tcs_i and tcs_w[j]:
                        w_new = min(w_new, (vxw + kp * big_v) * (1.0 / r))
                    om[j] = w_new
                    fzs[j] = fz
                    fxw, fyw = g * sx, g * sy
                    gfx = c * fxw - s_ * fyw  # ground frame
                    gfy = s_ * fxw + c * fyw
                    bfx = gfx * xx + gfy * yx + fz * zx  # body frame
                    bfy = gfx * xy + gfy * yy + fz * zy
                    bfz = gfx * xz + gfy * yz + fz * zz
                    fx_t += bfx
                    fy_t += bfy
                    fz_t += bfz
                    tx_t += cy * bfz - cz * bfy  # r x F
                    ty_t += cz * bfx - cx * bfz
                    tz_t += cx * bfy - cy * bfx
                force = (m[0] * fx_t + m[1] * fy_t + m[2] * fz_t, m[3] * fx_t + m[4] * fy_t + m[5] * fz_t,
                         m[6] * fx_t + m[7] * fy_t + m[8] * fz_t)
                torque = (m[0] * tx_t + m[1] * ty_t + m[2] * tz_t, m[3] * tx_t + m[4] * ty_t + m[5] * tz_t,
                          m[6] * tx_t + m[7] * ty_t + m[8] * tz_t)
                apply_f(b, -1, force, pos, world, physicsClientId=cid)
                apply_t(b, -1, torque, world, physicsClientId=cid)
            p.stepSimulation(physicsClientId=cid)
            if self.contact_impulse is not None:
                self._collect_contacts()
            self._read_frames()
        self._omega = np.array(omega_all)
        self._fz = np.array(fz_all)
        self._delta = np.array(delta_l)
        self._gear = np.array(gear_l, dtype=np.int64)
        self._rpm = np.array(rpm_l)
        self._publish_frames()

    def _torque_at(self, rpm: float) -> float:
        """Full-throttle engine torque [N m] at ``rpm`` (linear interpolation, clamped like np.interp)."""
        xs, ys = self._curve_rpm_list, self._curve_nm_list
        if rpm <= xs[0]:
            return ys[0]
        if rpm >= xs[-1]:
            return ys[-1]
        k = bisect.bisect_right(xs, rpm)
        t = (rpm - xs[k - 1]) / (xs[k] - xs[k - 1])
        return ys[k - 1] + t * (ys[k] - ys[k - 1])
