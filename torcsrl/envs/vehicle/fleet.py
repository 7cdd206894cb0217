"""The fleet: N raycast cars in pybullet (see :mod:`torcsrl.envs.vehicle` for the model).

:class:`CarFleet` owns the cars' pybullet bodies and their dynamic state (wheel spin, steer angle, gear, rpm, wheel
loads, surfaces), places, parks and restores them, exposes the state as arrays, and steps them through one of the
integration backends it mixes in: :class:`~torcsrl.envs.vehicle.numpy_backend.NumpyBackend` (numpy, and numba with
the compiled kernels of :mod:`~torcsrl.envs.vehicle.numba_backend`) or
:class:`~torcsrl.envs.vehicle.python_backend.PythonBackend`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from torcsrl.envs.surfaces import MU, ROLLING_RESISTANCE, SURFACE_NAMES, surface_id
from torcsrl.envs.vehicle.ground import CAR_GROUP, GROUND_GROUP, GROUND_MODELS
from torcsrl.envs.vehicle.numpy_backend import NumpyBackend
from torcsrl.envs.vehicle.params import DRIVES, GRAVITY, RPM_PER_RAD_S, VehicleParams, sanitize_controls
from torcsrl.envs.vehicle.python_backend import PythonBackend
from torcsrl.utils.bullet import pybullet as p

__all__ = ["CarFleet", "BACKENDS", "MIN_PHYSICS_HZ", "PYTHON_BACKEND_MAX_CARS"]

#: Lowest physics rate the fleet accepts [Hz].
MIN_PHYSICS_HZ: float = 200.0
#: The integration backends (:class:`CarFleet`'s ``backend``).
BACKENDS: tuple[str, ...] = ("auto", "numpy", "numba", "python")
#: Without numba, fleets up to this many cars use the per-car Python backend by default (faster there than numpy).
PYTHON_BACKEND_MAX_CARS: int = 4
_CTRL_LOW = np.array([[-1.0], [0.0], [0.0]])
_CTRL_HIGH = np.array([[1.0], [1.0], [1.0]])


class _Live(NamedTuple):
    """The cars of a fleet still in the physics while some are parked, and their pybullet call columns."""

    idx: np.ndarray
    bodies: list
    cids: list
    links: list
    frames: list


def _jit():
    """The compiled kernels of the numba backend (:mod:`~torcsrl.envs.vehicle.numba_backend`), or None without numba."""
    global _JIT
    if _JIT is False:
        try:
            from torcsrl.envs.vehicle import numba_backend as mod  # deferred: numba is optional, ~1.7 s to import
        except ImportError:  # no numba
            mod = None
        except (RuntimeError, OSError) as err:  # numba present but unusable here (e.g. no writable cache location)
            warnings.warn(f"the numba vehicle backend is unavailable ({type(err).__name__}: {err}); using numpy / python", stacklevel=2)
            mod = None
        _JIT = mod
    return _JIT


_JIT: Any = False


def _auto_backend(n_cars: int, several_worlds: bool) -> str:
    """``backend="auto"``: python for one car; numba for more (numpy without numba, or python up to
    :data:`PYTHON_BACKEND_MAX_CARS` cars in one world)."""
    if (n_cars > 1 or several_worlds) and _jit() is not None:  # one car never imports numba (~1.7 s)
        return "numba"
    return "python" if n_cars <= PYTHON_BACKEND_MAX_CARS and not several_worlds else "numpy"


def _skew(r: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


# --------------------------------------------------------------------------------------------
# The fleet
# --------------------------------------------------------------------------------------------
class CarFleet(NumpyBackend, PythonBackend):
    """N raycast cars in one pybullet client, or dealt over several (see :mod:`torcsrl.envs.vehicle` for the model).

    Args:
        client_id: pybullet physics client. The fleet sets gravity and the fixed time step on it
            and calls ``stepSimulation``: it owns the stepping of that client. A sequence of clients
            (worlds, each with its own :func:`make_ground`) deals the cars over them in contiguous
            blocks (car i in world ``i // ceil(N / worlds)``): a car moves in its world exactly as it
            would in one shared world (the cars never touch each other), while each world's collision
            broadphase only sorts through its own cars (cars that drive the same line overlap; in one
            world the cost of the overlapping pairs grows with N^2). Several worlds need the numpy
            backend, the plane ground and ``collide=False``.
        n_cars: number of cars N (>= 1).
        params: vehicle parameters (default: ``VehicleParams.load("default")``).
        collide: if False (default) cars pass through each other; if True their chassis collide.
        surface_fn: optional ``wheel_xy [N,4,2] -> surface ids [N,4]``, called once at the start of
            every :meth:`step`. Without it, the ids set by :meth:`set_wheel_surfaces` persist.
        control_hz: control rate [Hz] (one :meth:`step`).
        substeps: physics steps per control step; ``control_hz * substeps`` must be >= 200 Hz.
        surface: initial surface name under every wheel.
        backend: ``"numpy"`` (vectorised over all wheels of all cars), ``"python"`` (the same
            equations car by car in floats: faster for a few cars) or ``"auto"`` (python for
            N <= :data:`PYTHON_BACKEND_MAX_CARS`). Both give the same trajectories.
        ground: ``"plane"`` (default): the ground is the z = 0 plane of :func:`make_ground` and
            each suspension ray is intersected with it in closed form (the same hit fraction as
            pybullet's ray test, ~10x cheaper, and independent of how many car bodies overlap);
            ``"raycast"``: one pybullet ``rayTestBatch`` per substep against every body in
            :data:`GROUND_GROUP`, for a custom ground (bumps, banking, meshes).

    The cars are created at ``(0, 0)`` facing +x, at rest; call :meth:`reset` to place them.
    Per control step the engine torque, gear, steering angles and aerodynamic forces are
    computed once and held over the substeps; suspension, tyres and wheel spin run every substep.
    """

    def __init__(
        self,
        client_id: int | Sequence[int],
        n_cars: int,
        params: VehicleParams | None = None,
        collide: bool = False,
        surface_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        control_hz: float = 50.0,
        substeps: int = 4,
        surface: str = "asphalt",
        backend: str = "auto",
        ground: str = "plane",
    ) -> None:
        if isinstance(n_cars, bool) or int(n_cars) != n_cars or n_cars < 1:
            raise ValueError(f"n_cars must be a positive integer, got {n_cars!r}")
        if not (control_hz > 0 and int(substeps) == substeps and substeps >= 1):
            raise ValueError(f"control_hz must be > 0 and substeps a positive integer, got {control_hz}, {substeps}")
        if control_hz * substeps < MIN_PHYSICS_HZ:
            raise ValueError(f"physics rate control_hz * substeps = {control_hz * substeps:g} Hz; "
                             f"must be >= {MIN_PHYSICS_HZ:g} Hz")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
        if backend == "numba" and _jit() is None:
            raise ValueError("backend numba needs the numba package (pip install numba); allowed without it: auto, numpy, python")
        if ground not in GROUND_MODELS:
            raise ValueError(f"ground must be one of {', '.join(GROUND_MODELS)}; got {ground!r}")
        #: "plane": suspension rays meet the z = 0 plane of make_ground, solved in closed form;
        #: "raycast": pybullet rayTestBatch against every body in GROUND_GROUP (custom terrain).
        self.ground = ground
        #: "numpy" vectorises each substep over all wheels of all cars; "numba" is the numpy backend with its
        #: per-substep arithmetic compiled (numba kernels: :mod:`~torcsrl.envs.vehicle.numba_backend`); "python"
        #: runs the same equations car by car in floats ("auto": python for one car; numba for more where numba is
        #: installed, else python for N <= 4 and numpy above).
        clients = [int(c) for c in client_id] if isinstance(client_id, Sequence) else [int(client_id)]
        if not 1 <= len(clients) <= n_cars:
            raise ValueError(f"a fleet of {n_cars} cars needs 1 to {n_cars} clients, got {len(clients)}")
        several = len(clients) > 1
        if several and (backend == "python" or ground != "plane" or collide):
            raise ValueError("cars in several worlds need backend numpy or numba (or auto), ground plane and collide=False")
        self.backend = backend if backend != "auto" else _auto_backend(n_cars, several)
        self._kernels = _jit() if self.backend == "numba" else None
        #: the fleet's worlds (pybullet clients); ``client`` is the first
        self.clients = clients
        self.client = clients[0]
        self.n = int(n_cars)
        self.params = params if params is not None else VehicleParams.load("default")
        self.collide = bool(collide)
        self.surface_fn = surface_fn
        self.control_hz = float(control_hz)
        self.substeps = int(substeps)
        self.dt_control = 1.0 / self.control_hz  # [s]
        self.dt = self.dt_control / self.substeps  # [s] physics step
        for cid in clients:
            p.setGravity(0.0, 0.0, -GRAVITY, physicsClientId=cid)
            p.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSubSteps=0, physicsClientId=cid)
        per = -(-self.n // len(clients))
        # per-car argument columns of the batched pybullet calls (map over C functions): world, base link, frame
        self._cids, self._links, self._world_frames = [clients[i // per] for i in range(self.n)], [-1] * self.n, \
            [p.WORLD_FRAME] * self.n
        self._build_constants()
        self.bodies: list[int] = [self._create_body(cid) for cid in self._cids]
        self.set_collide(self.collide)
        #: car-car contact impulses of the last control step [N s], ``[N, N]`` (see :meth:`track_contacts`); None: off
        self.contact_impulse: np.ndarray | None = None
        self._body_index = {b: i for i, b in enumerate(self.bodies)}
        #: cars taken out of the physics until their next reset (:meth:`park`)
        self.parked = np.zeros(self.n, dtype=bool)
        self._live: _Live | None = None  # the cars still in the physics while some are parked (None: every car)
        n = self.n
        # per-car dynamic state; after a step these are new arrays (never modified in place)
        self._omega = np.zeros((n, 4))  # [rad/s] wheel spin
        self._delta = np.zeros(n)  # [rad] road-wheel steer angle (bicycle equivalent)
        self._gear = np.ones(n, dtype=np.int64)
        self._rpm = np.full(n, self.params.idle_rpm)
        self._fz = np.tile(self.params.static_wheel_loads, (n, 1))  # [N] last normal loads
        self.set_wheel_surfaces(np.full((n, 4), surface_id(surface)))
        self.reset(np.arange(n), np.zeros((n, 2)), np.zeros(n), np.zeros(n))

    # ---- construction -----------------------------------------------------------------------
    def _build_constants(self) -> None:
        prm = self.params
        a, b = prm.cg_to_front_axle, prm.cg_to_rear_axle
        xs = np.array([a, a, -b, -b])
        ys = np.array([prm.track_front, -prm.track_front, prm.track_rear, -prm.track_rear]) / 2.0
        k = np.array([prm.stiffness_front] * 2 + [prm.stiffness_rear] * 2)  # [N/m]
        self._damp = np.array([prm.damping_front] * 2 + [prm.damping_rear] * 2)  # [N s/m]
        # Hardpoint heights (body frame) chosen so that the body is level at static ride height.
        z_hp = prm.wheel_radius + prm.rest_length - prm.static_wheel_loads / k - prm.cg_height
        ray_len = prm.rest_length + prm.wheel_radius  # [m]
        self._ray_len = ray_len
        hard = np.stack([xs, ys, z_hp], axis=1)
        self._ray_pts_local = np.concatenate([hard, hard - np.array([0.0, 0.0, ray_len])], axis=0)  # [8, 3]
        # Normal load = k * compression (+ bump stop) - c * vz, compression = ray_len - frac * ray_len.
        self._k_a, self._k_l = k * ray_len, k * ray_len
        self._bump_a = prm.bump_stop_stiffness * (ray_len - prm.travel)
        self._bump_l = prm.bump_stop_stiffness * ray_len
        # Contact points (body frame, ground level at static ride height) and the 12x6 wheel
        # Jacobian: v_point = v + w x r = [I | -[r]x] (v, w); its transpose sums the wheel forces
        # into a body wrench at the COM.
        contact = np.stack([xs, ys, np.full(4, -prm.cg_height)], axis=1)
        self._contact_local = contact
        jac = np.zeros((12, 6))
        for i in range(4):
            jac[3 * i:3 * i + 3, 0:3] = np.eye(3)
            jac[3 * i:3 * i + 3, 3:6] = -_skew(contact[i])
        self._jac = jac  # wrench [N, 6] = wheel forces [N, 12] @ jac
        self._jac_t = np.ascontiguousarray(jac.T)  # contact-point velocities [N, 12] = twist [N, 6] @ jac_t
        # Tyre constants.
        self._mf_b = math.tan(math.pi / (2.0 * prm.shape_c))  # puts the peak of sin(C atan(B s)) at s = 1
        self._inv_kp = 1.0 / prm.peak_slip_ratio
        self._inv_ap = 1.0 / prm.peak_slip_angle
        self._wheel_a = self.dt / prm.wheel_inertia  # [rad/s per N m]
        self._drive_split = np.array(DRIVES[prm.drive])
        self._driven = self._drive_split > 0
        share = prm.brake_front_share
        self._brake_split = prm.brake_torque * np.array([share / 2, share / 2, (1 - share) / 2, (1 - share) / 2])
        self._ratios = np.asarray(prm.gear_ratios) * prm.final_drive  # overall ratios per gear
        self._curve_rpm = np.asarray(prm.torque_curve_rpm)
        self._curve_nm = np.asarray(prm.torque_curve_nm)
        self._ack_half_tracks = np.array([prm.track_front / 2.0, -prm.track_front / 2.0])
        self._ride_z = prm.cg_height  # [m] COM height at static ride height
        # Aero: drag coefficient and the body wrench of unit downforce (at the axles).
        self._drag_k = 0.5 * prm.air_density * prm.drag_area  # [kg/m]
        self._down_k = 0.5 * prm.air_density * prm.lift_area  # [kg/m]
        arm = prm.downforce_front_share * a - (1.0 - prm.downforce_front_share) * b
        self._down_wrench = np.array([0.0, 0.0, -1.0, 0.0, arm, 0.0])  # tau_y = x_f F_f + x_r F_r
        # The same constants as Python floats for the python backend.
        self._k_a_list, self._k_l_list, self._damp_list = self._k_a.tolist(), self._k_l.tolist(), self._damp.tolist()
        self._hard_list = [tuple(h) for h in hard.tolist()]
        self._contact_list = [tuple(c) for c in contact.tolist()]
        self._drive_split_list = self._drive_split.tolist()
        self._brake_split_list = self._brake_split.tolist()
        self._driven_list = tuple(bool(d) for d in self._driven)
        self._ratios_list = self._ratios.tolist()
        self._curve_rpm_list, self._curve_nm_list = self._curve_rpm.tolist(), self._curve_nm.tolist()

    def _create_body(self, cid: int) -> int:
        prm = self.params
        half = [prm.length / 2.0, prm.width / 2.0, prm.height / 2.0]
        box_center = [prm.cg_to_front_axle + prm.front_overhang - prm.length / 2.0, 0.0,
                      prm.ground_clearance + prm.height / 2.0 - prm.cg_height]
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, collisionFramePosition=box_center,
                                     physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, visualFramePosition=box_center,
                                  rgbaColor=[0.8, 0.1, 0.1, 1.0], physicsClientId=cid)
        body = p.createMultiBody(prm.mass, col, vis, basePosition=[0.0, 0.0, self._ride_z], physicsClientId=cid)
        p.changeDynamics(body, -1, localInertiaDiagonal=list(prm.inertia), linearDamping=0.0, angularDamping=0.0,
                         lateralFriction=0.5, restitution=0.0,
                         activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=cid)
        return body

    def set_collide(self, collide: bool) -> None:
        """Switch car-car chassis collisions on or off (the ground always collides)."""
        self.collide = bool(collide)
        if collide and len(self.clients) > 1:
            raise ValueError("cars in different worlds cannot collide")
        mask = GROUND_GROUP | (CAR_GROUP if self.collide else 0)
        for b, cid in zip(self.bodies, self._cids):
            if b is not None:
                p.setCollisionFilterGroupMask(b, -1, CAR_GROUP, mask, physicsClientId=cid)

    def track_contacts(self, on: bool = True) -> None:
        """Record car-car contacts: after every :meth:`step`, ``contact_impulse [N, N]`` holds the impulse [N s]
        each pair of chassis exchanged over the step's physics substeps (symmetric; 0: no contact)."""
        if on and len(self.clients) > 1:
            raise ValueError("car-car contacts need the cars in one world")
        self.contact_impulse = np.zeros((self.n, self.n)) if on else None

    def _collect_contacts(self) -> None:
        out, index, dt = self.contact_impulse, self._body_index, self.dt
        for c in p.getContactPoints(physicsClientId=self.client):
            a, b = index.get(c[1]), index.get(c[2])
            if a is None or b is None or a == b or c[9] <= 0.0:
                continue
            out[a, b] += c[9] * dt
            out[b, a] += c[9] * dt

    # ---- surfaces ---------------------------------------------------------------------------
    def get_state(self) -> dict[str, np.ndarray]:
        """The fleet's own dynamic state (wheel spin, steer angle, gear, rpm, wheel loads, surfaces);
        the bodies' poses and velocities live in the pybullet client (``saveBullet``)."""
        if self.parked.any():
            raise ValueError("a fleet with parked cars cannot be saved: reset them first")
        return {k: np.array(getattr(self, k), copy=True) for k in ("_omega", "_delta", "_gear", "_rpm", "_fz", "_surface")}

    def set_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore :meth:`get_state` after the client's bodies were restored; re-reads the poses."""
        for k in ("_omega", "_delta", "_gear", "_rpm", "_fz"):
            v = np.array(state[k], copy=True)
            if v.shape != getattr(self, k).shape:
                raise ValueError(f"fleet state {k} has shape {v.shape}; this fleet needs {getattr(self, k).shape}")
            setattr(self, k, v)
        self.set_wheel_surfaces(np.asarray(state["_surface"]))
        if self.backend == "python":
            self._read_frames()
            self._publish_frames()
        else:
            self._read_state()

    def set_wheel_surfaces(self, surface_ids: Any) -> None:
        """Surface id under each wheel, ``[N, 4]`` ints indexing ``surfaces.SURFACE_NAMES`` (or a scalar)."""
        ids = np.asarray(surface_ids)
        if ids.shape != (self.n, 4):
            try:
                ids = np.broadcast_to(ids, (self.n, 4))
            except ValueError:
                raise ValueError(f"surface ids must have shape ({self.n}, 4), got {ids.shape}") from None
        if ids.dtype.kind not in "iu" or ids.min() < 0 or ids.max() >= len(SURFACE_NAMES):
            raise ValueError(f"surface ids must be integers in [0, {len(SURFACE_NAMES) - 1}] "
                             f"({', '.join(SURFACE_NAMES)}), got {np.unique(ids)}")
        self._apply_wheel_surfaces(ids)

    def _apply_wheel_surfaces(self, ids: np.ndarray) -> None:
        """Keep valid ``[N, 4]`` ids and the grip and rolling resistance they give each wheel."""
        self._surface = ids.copy()
        self._mu = MU[ids] * self.params.tyre_mu_scale
        self._crr_a = ROLLING_RESISTANCE[ids] * (self.params.wheel_radius * self._wheel_a)

    def _update_wheel_surfaces(self, ids: np.ndarray) -> None:
        """:meth:`set_wheel_surfaces` for the env's own ``[N, 4]`` int64 ids (valid by construction, so not
        checked again), and nothing to do when the wheels are on the surfaces they were on."""
        if self.n == 1:
            if ids.tolist() == self._surface.tolist():
                return
        elif np.array_equal(ids, self._surface):
            return
        self._apply_wheel_surfaces(ids)

    @property
    def wheel_surfaces(self) -> np.ndarray:
        """Surface id under each wheel ``[N, 4]`` for the current control step."""
        return self._surface

    @property
    def wheel_mu(self) -> np.ndarray:
        """Friction coefficient under each wheel ``[N, 4]`` [-] (surface mu x tyre_mu_scale)."""
        return self._mu

    # ---- reset ------------------------------------------------------------------------------
    def reset(self, idx: Any, xy: Any, yaw: Any, speed: Any = 0.0) -> None:
        """Place cars ``idx`` (``[k]``) upright at ``xy`` [m] ``[k,2]``, heading ``yaw`` [rad] ``[k]``,
        rolling straight ahead at ``speed`` [m/s] ``[k]`` (>= 0), at static ride height.

        Cheap: moves the existing bodies (no re-creation); also rights flipped cars.
        """
        idx = np.atleast_1d(np.asarray(idx, dtype=np.int64))
        k = idx.size
        if k and (idx.min() < 0 or idx.max() >= self.n):
            raise ValueError(f"car indices must lie in [0, {self.n - 1}], got {idx}")
        try:
            xy = np.asarray(xy, dtype=np.float64).reshape(k, 2)
            yaw = np.broadcast_to(np.asarray(yaw, dtype=np.float64), (k,))
            speed = np.broadcast_to(np.asarray(speed, dtype=np.float64), (k,))
        except ValueError:
            raise ValueError(f"reset needs xy [{k},2], yaw [{k}] and speed [{k}] (or scalars)") from None
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(yaw)) and np.all(np.isfinite(speed))):
            raise ValueError("reset xy, yaw and speed must be finite")
        if np.any(speed < 0):
            raise ValueError("reset speed must be >= 0 (cars drive forward)")
        if self.parked[idx].any():
            self._unpark(idx[self.parked[idx]])
        cids = self._cids
        for j, i in enumerate(idx.tolist()):
            cid = cids[i]
            c, s = math.cos(yaw[j] / 2.0), math.sin(yaw[j] / 2.0)
            p.resetBasePositionAndOrientation(self.bodies[i], [xy[j, 0], xy[j, 1], self._ride_z], [0.0, 0.0, s, c],
                                              physicsClientId=cid)
            p.resetBaseVelocity(self.bodies[i], [speed[j] * math.cos(yaw[j]), speed[j] * math.sin(yaw[j]), 0.0],
                                [0.0, 0.0, 0.0], physicsClientId=cid)
        prm = self.params
        self._omega = self._omega.copy()
        self._omega[idx] = (speed / prm.wheel_radius)[:, None]
        self._delta = self._delta.copy()
        self._delta[idx] = 0.0
        self._fz = self._fz.copy()
        self._fz[idx] = prm.static_wheel_loads
        # the lowest gear that is not above the upshift speed
        wheel_rpm = (speed / prm.wheel_radius * RPM_PER_RAD_S)[:, None] * self._ratios[None, :]  # [k, gears]
        gear = 1 + np.minimum(np.sum(wheel_rpm > prm.shift_up_rpm, axis=1), len(self._ratios) - 1)
        self._gear = self._gear.copy()
        self._gear[idx] = gear
        self._rpm = self._rpm.copy()
        self._rpm[idx] = np.maximum(wheel_rpm[np.arange(k), gear - 1], prm.idle_rpm)
        if self.backend == "python":
            self._read_frames()
            self._publish_frames()
        else:
            self._read_state()

    # ---- parking ----------------------------------------------------------------------------
    def park(self, idx: Any) -> None:
        """Take cars ``idx`` out of the physics until their next :meth:`reset` (numpy backend): their bodies
        leave their worlds, so they cost no state reads, force calls or integration; their state arrays
        keep their last values, and their rows of the per-substep arithmetic are computed and dropped.
        The other cars move as they would have (cars never touch each other), and :meth:`reset` puts a
        parked car back as a new body (the same numbers as a body reset in place). For evaluations whose
        cars end their episodes at different times (:func:`torcsrl.evaluate.batched.run_batch`)."""
        idx = np.atleast_1d(np.asarray(idx, dtype=np.int64))
        idx = idx[~self.parked[idx]]
        if not len(idx):
            return
        if self.backend == "python":
            raise ValueError("park needs the numpy or numba backend")
        for i in idx.tolist():
            p.removeBody(self.bodies[i], physicsClientId=self._cids[i])
            self._body_index.pop(self.bodies[i], None)  # (body ids are per world: the index serves one world)
            self.bodies[i] = None
        self.parked[idx] = True
        self._relive()

    def _unpark(self, idx: np.ndarray) -> None:
        mask = GROUND_GROUP | (CAR_GROUP if self.collide else 0)
        for i in idx.tolist():
            cid = self._cids[i]
            b = self._create_body(cid)
            p.setCollisionFilterGroupMask(b, -1, CAR_GROUP, mask, physicsClientId=cid)
            self.bodies[i] = b
            self._body_index[b] = i
        self.parked[idx] = False
        self._relive()

    def _relive(self) -> None:
        if not self.parked.any():
            self._live = None
            return
        live = np.flatnonzero(~self.parked)
        pick = live.tolist()
        self._live = _Live(live, [self.bodies[i] for i in pick], [self._cids[i] for i in pick], [-1] * len(pick),
                           [p.WORLD_FRAME] * len(pick))


    @property
    def pos(self) -> np.ndarray:
        """Centre-of-mass position ``[N, 3]`` [m] (world)."""
        return self._raw[:, 0:3]

    @property
    def quat(self) -> np.ndarray:
        """Body orientation quaternion ``[N, 4]`` (x, y, z, w; pybullet order)."""
        return self._raw[:, 3:7]

    @property
    def yaw(self) -> np.ndarray:
        """Heading of the body x axis in the world xy plane ``[N]`` [rad], in (-pi, pi]."""
        return np.arctan2(self._rot[:, 1, 0], self._rot[:, 0, 0])

    @property
    def vel_world(self) -> np.ndarray:
        """COM velocity ``[N, 3]`` [m/s] (world)."""
        return self._raw[:, 7:10]

    @property
    def vel_body(self) -> np.ndarray:
        """COM velocity in the body frame ``[N, 3]`` [m/s] (x forward, y left, z up)."""
        return self._twist_b[:, 0:3]

    @property
    def angvel_body(self) -> np.ndarray:
        """Angular velocity in the body frame ``[N, 3]`` [rad/s] (roll, pitch, yaw rates)."""
        return self._twist_b[:, 3:6]

    @property
    def yaw_rate(self) -> np.ndarray:
        """Yaw rate ``[N]`` [rad/s] (world z component of the angular velocity; > 0 turning left)."""
        return self._raw[:, 12]

    @property
    def speed(self) -> np.ndarray:
        """Ground speed ``[N]`` [m/s] (norm of the horizontal COM velocity)."""
        return np.hypot(self._raw[:, 7], self._raw[:, 8])

    @property
    def slip_angle(self) -> np.ndarray:
        """Body slip angle ``[N]`` [rad]: ``atan2(vy, vx)`` of the body-frame velocity (0 below 1 m/s)."""
        vb = self._twist_b
        return np.where(np.hypot(vb[:, 0], vb[:, 1]) > 1.0, np.arctan2(vb[:, 1], vb[:, 0]), 0.0)

    @property
    def rotation(self) -> np.ndarray:
        """Body-to-world rotation matrices ``[N, 3, 3]``."""
        return self._rot

    @property
    def flipped(self) -> np.ndarray:
        """``[N]`` bool: the body z axis is tilted more than 60 deg from world up (on its side or roof)."""
        return self._rot[:, 2, 2] < 0.5

    @property
    def wheel_omega(self) -> np.ndarray:
        """Wheel spin ``[N, 4]`` [rad/s] (FL, FR, RL, RR; > 0 rolling forward)."""
        return self._omega

    @property
    def wheel_xy(self) -> np.ndarray:
        """World xy of each wheel's suspension hardpoint ``[N, 4, 2]`` [m] (above the contact patch)."""
        return self._ray_pts[:, 0:4, 0:2]

    @property
    def wheel_load(self) -> np.ndarray:
        """Normal load of each wheel in the last substep ``[N, 4]`` [N] (0 when airborne)."""
        return self._fz

    @property
    def wheel_contact(self) -> np.ndarray:
        """``[N, 4]`` bool: the wheel carried load in the last substep."""
        return self._fz > 0.0

    @property
    def rpm(self) -> np.ndarray:
        """Engine speed ``[N]`` [rpm]."""
        return self._rpm

    @property
    def gear(self) -> np.ndarray:
        """Engaged forward gear ``[N]`` (1 .. number of gears)."""
        return self._gear

    @property
    def steer_angle(self) -> np.ndarray:
        """Road-wheel steer angle ``[N]`` [rad] (bicycle-model equivalent; > 0 = left)."""
        return self._delta

    # ---- stepping ---------------------------------------------------------------------------
    def _controls(self, steer: Any, throttle: Any, brake: Any) -> np.ndarray:
        """Sanitised controls ``[3, N]``: NaN -> 0, then clipped to the ranges (+-inf -> bounds)."""
        try:
            c = np.array((steer, throttle, brake), dtype=np.float64)
        except (ValueError, TypeError):  # mixed scalars and arrays
            c = None
        if c is not None and c.shape == (3,):
            c = np.repeat(c[:, None], self.n, axis=1)
        elif c is None or c.shape != (3, self.n):
            c = np.stack([sanitize_controls(x, self.n, -9.0, 9.0, w)
                          for x, w in ((steer, "steer"), (throttle, "throttle"), (brake, "brake"))])
        return np.minimum(np.maximum(np.where(c == c, c, 0.0), _CTRL_LOW), _CTRL_HIGH)

    def step(self, steer: Any, throttle: Any, brake: Any) -> None:
        """Advance one control step (``1 / control_hz`` s).

        Args:
            steer: [-1, 1] ``[N]`` or scalar; +1 = full left lock.
            throttle: [0, 1] ``[N]`` or scalar.
            brake: [0, 1] ``[N]`` or scalar.
        Non-finite values never reach the physics: NaN -> 0, +-inf -> the bounds (then clipped).

        Per control step: steering (rate limit, Ackermann), gearbox, engine torque and aero forces
        are computed once and held; suspension, tyres and wheel spin run every substep.
        """
        controls = self._controls(steer, throttle, brake)
        if self.surface_fn is not None:
            self.set_wheel_surfaces(self.surface_fn(self.wheel_xy))
        if self.contact_impulse is not None:
            self.contact_impulse = np.zeros((self.n, self.n))
        if self.backend == "python":
            self._step_python(controls)
        else:
            self._step_numpy(controls)
