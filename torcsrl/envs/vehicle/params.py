"""Vehicle parameters and the conventions every backend shares.

:class:`VehicleParams` is loaded from the bundled ``torcsrl/envs/vehicles/<name>.yaml`` (documented per key there),
optionally with flat key overrides, and validated. The wheel order of every ``[N, 4]`` array, gravity, the rpm
conversion and the drive layouts' torque shares are defined here once; :func:`sanitize_controls` and
:func:`split_throttle_brake` keep non-finite controls out of the physics.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np
import yaml

__all__ = [
    "VehicleParams",
    "available_vehicles",
    "sanitize_controls",
    "split_throttle_brake",
    "WHEEL_NAMES",
    "GRAVITY",
    "RPM_PER_RAD_S",
    "DRIVES",
]

#: Wheel order used by every ``[N, 4]`` array.
WHEEL_NAMES: tuple[str, ...] = ("front_left", "front_right", "rear_left", "rear_right")
#: [m/s^2] gravity (the fleet sets it on its clients; the static wheel loads use it)
GRAVITY = 9.81
#: engine or wheel speed [rpm] per [rad/s]
RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
#: torque share of each wheel (FL, FR, RL, RR) per drive layout
DRIVES: dict[str, tuple[float, float, float, float]] = {
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
        if self.drive not in DRIVES:
            raise ValueError(f"drive must be one of {', '.join(DRIVES)}, got {self.drive!r}")
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
        front = self.mass * GRAVITY * self.cg_to_rear_axle / self.wheelbase / 2.0
        rear = self.mass * GRAVITY * self.cg_to_front_axle / self.wheelbase / 2.0
        return np.array([front, front, rear, rear])

    @property
    def max_power_w(self) -> float:
        """[W] peak engine power at the crank (on the torque-curve samples)."""
        rpm = np.asarray(self.torque_curve_rpm)
        return float(np.max(np.asarray(self.torque_curve_nm) * rpm / RPM_PER_RAD_S))

    def max_wheel_power_w(self) -> float:
        """[W] peak power at the wheels (crank power x drivetrain efficiency)."""
        return self.max_power_w * self.drivetrain_efficiency

    def top_gear_speed(self) -> float:
        """[m/s] speed at the rev limiter in top gear."""
        return self.redline_rpm / RPM_PER_RAD_S / (self.gear_ratios[-1] * self.final_drive) * self.wheel_radius


def available_vehicles() -> list[str]:
    """Names of the bundled vehicle parameter files."""
    folder = resources.files("torcsrl.envs").joinpath("vehicles")
    return sorted(f.name[:-5] for f in folder.iterdir() if f.name.endswith(".yaml"))


# --------------------------------------------------------------------------------------------
# Controls
# --------------------------------------------------------------------------------------------
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
