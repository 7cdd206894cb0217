"""Raycast car physics in pybullet: N cars in one client, vectorised over cars with numpy.

Model (one car)
---------------
* **Chassis**: one rigid body with a box collision shape (``length x width x height``), mass and
  principal inertia from the parameters, centre of mass (COM) ``cg_height`` above the ground at
  static ride height. pybullet integrates it (gravity, contacts with the ground when the car
  bottoms out or rolls over). The box only touches the ground when something went wrong: in
  normal driving the car stands on its four suspension rays.
* **Suspension**: per wheel a ray from a chassis-fixed hardpoint along the chassis' -z axis, of
  length ``rest_length + wheel_radius``. The hit fraction gives the spring compression; the
  normal load is ``k * compression + c * compression_rate`` (>= 0, bump stop beyond ``travel``,
  capped at ``max_wheel_load``), applied along the ground normal (world up: the ground is the
  flat plane of :func:`make_ground`). All 4N rays of a fleet are one ``rayTestBatch`` call per
  physics substep; they only hit bodies in collision group :data:`GROUND_GROUP`.
* **Tyres**: combined-slip magic formula, as in TORCS' simuv2: with slip ratio
  ``kappa = (omega * r - vx) / V`` and lateral slip ``tan(alpha) = -vy / V`` (``vx, vy`` the
  contact-point velocity in the wheel's frame on the ground plane, ``V = max(|vx|, low_speed)``),
  the normalised slip
  ``s = |(kappa / peak_slip_ratio, tan(alpha) / peak_slip_angle)|`` gives the force magnitude
  ``mu * Fz * sin(C * atan(B * s))`` (peak ``mu * Fz`` at ``s = 1``: a friction circle), directed
  along the slip vector, in the ground plane. ``mu`` is the surface's friction
  (``surfaces.MU``) under that wheel, times ``tyre_mu_scale``. (Applying the forces in the
  ground plane rather than the rolled/pitched body plane matters: a 3 deg roll otherwise costs
  ~10 % of the cornering grip.)
* **Wheel spin**: each wheel has its own angular speed ``wheel_omega``, driven by engine torque,
  slowed by brake and rolling-resistance torque (``crr * Fz * r``, ``crr`` from the surface) and
  by the tyre's longitudinal force. The update is semi-implicit in the tyre's secant slip
  stiffness (unconditionally stable at any substep); brake and rolling-resistance torques can
  lock a wheel but never spin it backwards. ABS (on by default) keeps braked wheels at or above
  ``-peak_slip_ratio``; optional traction control keeps driven wheels at or below it.
* **Powertrain**: engine torque curve x throttle, automatic gearbox (6 forward gears, shifting on
  rpm thresholds once per control step; no reverse), slipping clutch below ``clutch_rpm``,
  engine braking with the throttle shut, rev limiter, open differential (equal torque to the
  driven wheels).
* **Brakes**: total brake torque split front/rear by ``brake_front_share``.
* **Aero**: drag ``0.5 rho CdA |v| v`` opposing the body velocity; downforce
  ``0.5 rho ClA vx^2`` split between the axles (so it loads the tyres through the suspension).
* **Steering**: the road-wheel angle follows ``steer * max_steer`` at most ``max_steer_rate``
  per second (Ackermann geometry on the two front wheels).

All wheel forces of a car are summed into one force and one torque at the COM and applied in the
WORLD frame (one ``applyExternalForce`` + one ``applyExternalTorque`` per car per substep). The
tyre and suspension forces act at chassis-fixed contact points (below the wheel hardpoints, at
ground level for the static ride height): the lever-arm error from suspension travel is a few
cm against the 0.45 m COM height.

Conventions
-----------
* Wheel order: front-left, front-right, rear-left, rear-right (index 0..3).
* Body frame: x forward, y left, z up; ``yaw`` is the heading of body x in the world xy plane.
* Controls: ``steer`` in [-1, 1] (+1 = full LEFT lock), ``throttle`` and ``brake`` in [0, 1].
  Non-finite inputs never reach the physics: NaN becomes 0 (straight, no throttle, no brake),
  +-inf become the nearest bound, then everything is clipped to its range.
* Time: one :meth:`CarFleet.step` is one control step of ``1 / control_hz`` s (default 50 Hz),
  made of ``substeps`` physics steps (default 4, i.e. 200 Hz; at least 200 Hz is required).

Performance: per physics substep the fleet makes 2N state reads, one ray batch, 2N force calls
and one ``stepSimulation`` per world; state is read once per substep and cached. Three backends integrate
the same equations (a test checks they agree to rounding): ``"numpy"`` runs a fixed number of
vectorised operations on ``[N, 4]`` arrays per substep, independent of N (~80 calls of ~1 us);
``"python"`` runs them car by car in floats and beats numpy for a few cars; ``"numba"`` is the numpy
backend with that arithmetic in two compiled kernels (:mod:`torcsrl.envs._vehicle_jit`) and is the
fastest from two cars on (this CPU, 20 substeps a step: 0.40 / 0.64 / 1.74 / 3.17 ms a step for 1 / 4 / 16 / 32
cars, against numpy's 1.47 / 1.85 / 3.04 / 4.73 and python's 0.41 / 1.49 / 5.72 / 11.5; for one car in the env at
50 Hz x 4 substeps python is ~6 % faster: 3,417 against 3,213 steps/s). ``backend="auto"`` picks python for one car,
numba for more where it is installed, else python for N <= 4 and numpy above. The public state arrays are new arrays after
every step (never modified in place), so callers may keep them. A fleet owns the stepping of its
pybullet clients: use one fleet per client.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from itertools import chain
from typing import Any, NamedTuple

import numpy as np
from torcsrl.utils.bullet import pybullet as p
import yaml

from torcsrl.envs.surfaces import MU, ROLLING_RESISTANCE, SURFACE_NAMES, surface_id

__all__ = [
    "VehicleParams",
    "CarFleet",
    "make_ground",
    "split_throttle_brake",
    "sanitize_controls",
    "available_vehicles",
    "GROUND_GROUP",
    "GROUND_MODELS",
    "CAR_GROUP",
    "WHEEL_NAMES",
    "MIN_PHYSICS_HZ",
]

#: Collision group of the ground (and anything the suspension rays should hit).
GROUND_GROUP: int = 1
#: Collision group of car chassis. Cars collide with the ground; with each other only if ``collide``.
CAR_GROUP: int = 2
#: Wheel order used by every ``[N, 4]`` array.
WHEEL_NAMES: tuple[str, ...] = ("front_left", "front_right", "rear_left", "rear_right")
#: Lowest physics rate the fleet accepts [Hz].
MIN_PHYSICS_HZ: float = 200.0
#: The integration backends (:class:`CarFleet`'s ``backend``).
BACKENDS: tuple[str, ...] = ("auto", "numpy", "numba", "python")
#: Without numba, fleets up to this many cars use the per-car Python backend by default (faster there than numpy).
PYTHON_BACKEND_MAX_CARS: int = 4
_G = 9.81  # [m/s^2] gravity set on the client by the fleet
_RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
_DRIVES: dict[str, tuple[float, float, float, float]] = {
    "rear": (0.0, 0.0, 0.5, 0.5),
    "front": (0.5, 0.5, 0.0, 0.0),
    "all": (0.25, 0.25, 0.25, 0.25),
}


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VehicleParams:
    """Vehicle parameters (SI units; engine speeds in rpm). Documented per key in ``vehicles/*.yaml``."""

    # chassis
    mass: float  # [kg]
    inertia: tuple[float, float, float]  # [kg m^2] roll, pitch, yaw
    length: float  # [m]
    width: float  # [m]
    height: float  # [m]
    ground_clearance: float  # [m]
    front_overhang: float  # [m]
    cg_height: float  # [m]
    cg_to_front_axle: float  # [m]
    # geometry
    wheelbase: float  # [m]
    track_front: float  # [m]
    track_rear: float  # [m]
    wheel_radius: float  # [m]
    wheel_inertia: float  # [kg m^2]
    # suspension
    rest_length: float  # [m]
    travel: float  # [m]
    stiffness_front: float  # [N/m]
    stiffness_rear: float  # [N/m]
    damping_front: float  # [N s/m]
    damping_rear: float  # [N s/m]
    bump_stop_stiffness: float  # [N/m]
    max_wheel_load: float  # [N]
    # tyre
    tyre_mu_scale: float  # [-]
    peak_slip_ratio: float  # [-]
    peak_slip_angle: float  # [rad]
    shape_c: float  # [-]
    low_speed: float  # [m/s]
    # engine
    torque_curve_rpm: tuple[float, ...]  # [rpm]
    torque_curve_nm: tuple[float, ...]  # [N m]
    idle_rpm: float  # [rpm]
    clutch_rpm: float  # [rpm]
    redline_rpm: float  # [rpm]
    engine_brake_nm: float  # [N m]
    drivetrain_efficiency: float  # [-]
    drive: str  # rear | front | all
    # gearbox
    gear_ratios: tuple[float, ...]  # [-]
    final_drive: float  # [-]
    shift_up_rpm: float  # [rpm]
    shift_down_rpm: float  # [rpm]
    # brakes
    brake_torque: float  # [N m]
    brake_front_share: float  # [-]
    abs: bool
    traction_control: bool
    # steering
    max_steer: float  # [rad]
    max_steer_rate: float  # [rad/s]
    ackermann: float  # [-]
    # aero
    air_density: float  # [kg/m^3]
    drag_area: float  # [m^2]
    lift_area: float  # [m^2]
    downforce_front_share: float  # [-]
    name: str = field(default="custom", compare=False)

    # ---- loading -----------------------------------------------------------------------------
    @classmethod
    def load(cls, name: str = "default", overrides: dict[str, Any] | None = None) -> VehicleParams:
        """Parameters from the bundled ``vehicles/<name>.yaml``, with optional flat key overrides.

        Raises:
            ValueError: unknown vehicle name (the message lists the available ones), or an
                unknown / missing / invalid parameter.
        """
        known = available_vehicles()
        if name not in known:
            raise ValueError(f"unknown vehicle {name!r}; available: {', '.join(known)}")
        text = resources.files("torcsrl.envs").joinpath("vehicles", f"{name}.yaml").read_text()
        raw = yaml.safe_load(text)
        flat: dict[str, Any] = {}
        for section, entries in raw.items():
            if not isinstance(entries, dict):
                raise ValueError(f"vehicle {name!r}: section {section!r} must be a mapping of parameters")
            for key, value in entries.items():
                if key in flat:
                    raise ValueError(f"vehicle {name!r}: parameter {key!r} given twice")
                flat[key] = value
        flat.update(overrides or {})
        return cls.from_dict(flat, name=name)

    @classmethod
    def from_dict(cls, values: dict[str, Any], name: str = "custom") -> VehicleParams:
        """Parameters from a flat mapping (every field once); validated."""
        names = [f.name for f in dataclasses.fields(cls) if f.name != "name"]
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise ValueError(f"unknown vehicle parameter(s) {unknown}; allowed: {', '.join(names)}")
        missing = [n for n in names if n not in values]
        if missing:
            raise ValueError(f"missing vehicle parameter(s) {missing}")
        kw: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name == "name":
                continue
            v = values[f.name]
            if f.name in ("inertia", "torque_curve_rpm", "torque_curve_nm", "gear_ratios"):
                kw[f.name] = tuple(float(x) for x in v)
            elif f.name == "drive":
                kw[f.name] = str(v)
            elif f.name in ("abs", "traction_control"):
                kw[f.name] = bool(v)
            else:
                kw[f.name] = float(v)
        out = cls(**kw, name=name)
        out.validate()
        return out

    def replace(self, **changes: Any) -> VehicleParams:
        """A validated copy with some fields changed."""
        out = dataclasses.replace(self, **changes)
        out.validate()
        return out

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first inconsistent parameter."""
        if self.drive not in _DRIVES:
            raise ValueError(f"drive must be one of {', '.join(_DRIVES)}, got {self.drive!r}")
        positive = ("mass", "length", "width", "height", "cg_height", "wheelbase", "track_front", "track_rear",
                    "wheel_radius", "wheel_inertia", "rest_length", "travel", "stiffness_front", "stiffness_rear",
                    "max_wheel_load", "tyre_mu_scale", "peak_slip_ratio", "peak_slip_angle", "low_speed",
                    "redline_rpm", "final_drive", "max_steer", "max_steer_rate")
        for k in positive:
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"vehicle parameter {k} must be finite and > 0, got {v}")
        if len(self.inertia) != 3 or min(self.inertia) <= 0:
            raise ValueError(f"inertia must be three positive moments [kg m^2], got {self.inertia}")
        if not 0.0 < self.cg_to_front_axle < self.wheelbase:
            raise ValueError(f"cg_to_front_axle must lie in (0, wheelbase={self.wheelbase}), got {self.cg_to_front_axle}")
        if not 1.0 < self.shape_c < 2.0:
            raise ValueError(f"shape_c must lie in (1, 2) so the force peaks, got {self.shape_c}")
        for k in ("brake_front_share", "downforce_front_share", "drivetrain_efficiency", "ackermann"):
            v = getattr(self, k)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"vehicle parameter {k} must lie in [0, 1], got {v}")
        if len(self.torque_curve_rpm) != len(self.torque_curve_nm) or len(self.torque_curve_rpm) < 2:
            raise ValueError("torque_curve_rpm and torque_curve_nm must have the same length (>= 2)")
        if np.any(np.diff(self.torque_curve_rpm) <= 0):
            raise ValueError("torque_curve_rpm must be strictly increasing")
        if not self.gear_ratios or min(self.gear_ratios) <= 0:
            raise ValueError(f"gear_ratios must be positive, got {self.gear_ratios}")
        if not self.idle_rpm <= self.clutch_rpm < self.shift_down_rpm < self.shift_up_rpm <= self.redline_rpm:
            raise ValueError("need idle_rpm <= clutch_rpm < shift_down_rpm < shift_up_rpm <= redline_rpm")
        ratios = self.gear_ratios
        for a, b in zip(ratios[:-1], ratios[1:]):
            if self.shift_up_rpm * b / a <= self.shift_down_rpm:
                raise ValueError(f"gears {a} -> {b}: an upshift at shift_up_rpm would land below shift_down_rpm")
        if self.ground_clearance + self.height <= self.cg_height * 0.5:
            raise ValueError("the collision box must reach above half the centre-of-mass height")

    # ---- derived quantities -----------------------------------------------------------------
    @property
    def cg_to_rear_axle(self) -> float:
        """[m] centre of mass ahead of the rear axle."""
        return self.wheelbase - self.cg_to_front_axle

    @property
    def static_wheel_loads(self) -> np.ndarray:
        """[N] static normal load of each wheel (FL, FR, RL, RR) on flat ground."""
        front = self.mass * _G * self.cg_to_rear_axle / self.wheelbase / 2.0
        rear = self.mass * _G * self.cg_to_front_axle / self.wheelbase / 2.0
        return np.array([front, front, rear, rear])

    @property
    def max_power_w(self) -> float:
        """[W] peak engine power at the crank (on the torque-curve samples)."""
        rpm = np.asarray(self.torque_curve_rpm)
        return float(np.max(np.asarray(self.torque_curve_nm) * rpm / _RPM_PER_RAD_S))

    def max_wheel_power_w(self) -> float:
        """[W] peak power at the wheels (crank power x drivetrain efficiency)."""
        return self.max_power_w * self.drivetrain_efficiency

    def top_gear_speed(self) -> float:
        """[m/s] speed at the rev limiter in top gear."""
        return self.redline_rpm / _RPM_PER_RAD_S / (self.gear_ratios[-1] * self.final_drive) * self.wheel_radius


def available_vehicles() -> list[str]:
    """Names of the bundled vehicle parameter files."""
    folder = resources.files("torcsrl.envs").joinpath("vehicles")
    return sorted(f.name[:-5] for f in folder.iterdir() if f.name.endswith(".yaml"))


# --------------------------------------------------------------------------------------------
# Controls
# --------------------------------------------------------------------------------------------
_CTRL_LOW = np.array([[-1.0], [0.0], [0.0]])
_CTRL_HIGH = np.array([[1.0], [1.0], [1.0]])


def sanitize_controls(x: Any, n: int, low: float, high: float, what: str = "control") -> np.ndarray:
    """``x`` as a float array ``[n]`` in ``[low, high]``: NaN -> 0 (then clipped), +-inf -> the bounds.

    Scalars broadcast to all cars. Raises ``ValueError`` if the shape does not broadcast to ``[n]``.
    """
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n,):
        try:
            a = np.broadcast_to(a, (n,))
        except ValueError:
            raise ValueError(f"{what} must be a scalar or have shape ({n},), got shape {a.shape}") from None
    return np.minimum(np.maximum(np.where(a == a, a, 0.0), low), high)


def split_throttle_brake(throttle_brake: Any) -> tuple[np.ndarray, np.ndarray]:
    """Map the combined pedal in [-1, 1] (negative brakes) to ``(throttle, brake)`` in [0, 1].

    NaN counts as 0 (coast); +inf as full throttle, -inf as full brake.
    """
    a = np.asarray(throttle_brake, dtype=np.float64)
    a = np.minimum(np.maximum(np.where(a == a, a, 0.0), -1.0), 1.0)
    return np.maximum(a, 0.0), np.maximum(-a, 0.0)


# --------------------------------------------------------------------------------------------
# World helpers
# --------------------------------------------------------------------------------------------
#: Ground models of :class:`CarFleet` (see its ``ground`` argument).
GROUND_MODELS = ("plane", "raycast")
_MISS = (-1, -1, 9.0)  # a suspension ray that meets no ground (read as far below)


_flat = chain.from_iterable


class _Live(NamedTuple):
    """The cars of a fleet still in the physics while some are parked, and their pybullet call columns."""

    idx: np.ndarray
    bodies: list
    cids: list
    links: list
    frames: list


def _jit():
    """The compiled kernels of the numba backend (:mod:`torcsrl.envs._vehicle_jit`), or None without numba."""
    global _JIT
    if _JIT is False:
        try:
            from torcsrl.envs import _vehicle_jit as mod
        except ImportError:  # no numba
            mod = None
        except (RuntimeError, OSError) as err:  # numba present but unusable here (e.g. no writable cache location)
            import warnings

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


def _consume(calls) -> None:
    """Run an iterator of calls for their effects (``map`` over a C function: no Python frame per call)."""
    deque(calls, maxlen=0)


def _plane_hits(z_from: np.ndarray, z_to: np.ndarray) -> np.ndarray:
    """Hit fractions of rays from height ``z_from`` to ``z_to`` [m] with the plane z = 0 (either
    face, as bullet's ray test); 9.0 (far below: no spring force) where a ray does not reach it."""
    dz = z_from - z_to
    hit = (z_from * z_to <= 0.0) & (dz != 0.0)
    return np.where(hit, z_from / np.where(hit, dz, 1.0), 9.0)


def make_ground(client_id: int, lateral_friction: float = 0.8) -> int:
    """A static infinite plane at z = 0 in collision group :data:`GROUND_GROUP`; returns its body id.

    ``lateral_friction`` [-] only matters for chassis-ground contact (tyre grip comes from the
    surface ids given to the fleet).
    """
    shape = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client_id)
    body = p.createMultiBody(0.0, shape, basePosition=[0.0, 0.0, 0.0], physicsClientId=client_id)
    p.setCollisionFilterGroupMask(body, -1, GROUND_GROUP, 0xFFFF, physicsClientId=client_id)
    p.changeDynamics(body, -1, lateralFriction=lateral_friction, physicsClientId=client_id)
    return body


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


def _skew(r: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


# --------------------------------------------------------------------------------------------
# The fleet
# --------------------------------------------------------------------------------------------
class CarFleet:
    """N raycast cars in one pybullet client, or dealt over several (see the module docstring for the model).

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
        #: per-substep arithmetic compiled (numba kernels: :mod:`torcsrl.envs._vehicle_jit`); "python" runs the
        #: same equations car by car in floats ("auto": python for one car; numba for more where numba is installed,
        #: else python for N <= 4 and numpy above).
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
            p.setGravity(0.0, 0.0, -_G, physicsClientId=cid)
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
        self._drive_split = np.array(_DRIVES[prm.drive])
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
        self._surface = ids.copy()
        self._mu = MU[ids] * self.params.tyre_mu_scale
        self._crr_a = ROLLING_RESISTANCE[ids] * (self.params.wheel_radius * self._wheel_a)

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
        wheel_rpm = (speed / prm.wheel_radius * _RPM_PER_RAD_S)[:, None] * self._ratios[None, :]  # [k, gears]
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
        wheel_rpm = drive_speed * self._ratios[gear - 1] * _RPM_PER_RAD_S
        shift = (wheel_rpm > prm.shift_up_rpm) & (gear < len(self._ratios))
        shift = shift.astype(np.int64) - ((wheel_rpm < prm.shift_down_rpm) & (gear > 1))
        if shift.any():
            gear = gear + shift
            wheel_rpm = drive_speed * self._ratios[gear - 1] * _RPM_PER_RAD_S
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
            wheel_rpm = drive_speed * ratios[gear - 1] * _RPM_PER_RAD_S
            shift = int(wheel_rpm > prm.shift_up_rpm and gear < n_gears) - int(wheel_rpm < prm.shift_down_rpm and gear > 1)
            if shift:
                gear += shift
                wheel_rpm = drive_speed * ratios[gear - 1] * _RPM_PER_RAD_S
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
