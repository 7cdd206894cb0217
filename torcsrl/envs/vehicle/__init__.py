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
backend with that arithmetic in two compiled kernels (:mod:`~torcsrl.envs.vehicle.numba_backend`) and is the
fastest from two cars on (this CPU, 20 substeps a step: 0.40 / 0.64 / 1.74 / 3.17 ms a step for 1 / 4 / 16 / 32
cars, against numpy's 1.47 / 1.85 / 3.04 / 4.73 and python's 0.41 / 1.49 / 5.72 / 11.5; for one car in the env at
50 Hz x 4 substeps python is ~6 % faster: 3,417 against 3,213 steps/s). ``backend="auto"`` picks python for one car,
numba for more where it is installed, else python for N <= 4 and numpy above. The public state arrays are new arrays after
every step (never modified in place), so callers may keep them. A fleet owns the stepping of its
pybullet clients: use one fleet per client.

Modules
-------
* :mod:`~torcsrl.envs.vehicle.params`: :class:`VehicleParams` (the bundled ``vehicles/*.yaml``, validation,
  derived quantities), the wheel order, the control sanitising helpers.
* :mod:`~torcsrl.envs.vehicle.ground`: the collision groups, the ground models and :func:`make_ground`.
* :mod:`~torcsrl.envs.vehicle.fleet`: :class:`CarFleet`: the pybullet bodies, their state, reset and park, and
  the step that dispatches to a backend.
* The integration backends, side by side (a change of the model is made in each):
  :mod:`~torcsrl.envs.vehicle.numpy_backend` (vectorised over every wheel of every car; also the numba backend's
  per-control-step part and pybullet calls), :mod:`~torcsrl.envs.vehicle.numba_backend` (its per-substep arithmetic
  in two compiled kernels) and :mod:`~torcsrl.envs.vehicle.python_backend` (car by car in floats).
"""

from __future__ import annotations

from torcsrl.envs.vehicle.fleet import BACKENDS, MIN_PHYSICS_HZ, PYTHON_BACKEND_MAX_CARS, CarFleet
from torcsrl.envs.vehicle.ground import CAR_GROUP, GROUND_GROUP, GROUND_MODELS, make_ground
from torcsrl.envs.vehicle.params import (WHEEL_NAMES, VehicleParams, available_vehicles, sanitize_controls,
                                         split_throttle_brake)

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
    "BACKENDS",
    "PYTHON_BACKEND_MAX_CARS",
]
