"""Physics throughput: torcsrl's raycast car against pybullet's racecar URDF, in the same run.

Usage::

    python benchmarks/physics_throughput.py [--rounds 7] [--seconds 0.4]
    python benchmarks/physics_throughput.py --backend numba numpy python --sizes 1 2 16 32 --control-hz 10 --substeps 20

Prints control steps per second (car-steps/s for a fleet) for :class:`torcsrl.envs.vehicle.CarFleet`
at 50 Hz control with 200 Hz physics (4 substeps), N = 1, 8, 32 cars in one pybullet client, and
pybullet's ``racecar/racecar.urdf`` from ``pybullet_data`` (6 joint motors set per control step,
5 substeps at 240 Hz, base pose and velocity read back), with the ratio ours / reference. ``--backend`` takes several
integration backends (``CarFleet(backend=...)``: auto, numba, numpy, python), timed side by side in the same rounds;
``--control-hz`` / ``--substeps`` set the control rate (the training config: 10 Hz x 20 substeps).

Single-threaded (one pybullet DIRECT client per measurement, ``numThreads=1`` ray batches). The
machine may be shared: every figure is the best of ``--rounds`` interleaved timing rounds, and
the ratio compares rounds run side by side, so it is the figure to trust.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable

import numpy as np
import pybullet as p
import pybullet_data

if "torch" in sys.modules:  # keep any torch import single-threaded
    sys.modules["torch"].set_num_threads(1)

from torcsrl.envs.vehicle import CarFleet, make_ground  # noqa: E402

CONTROL_HZ = 50.0


def make_fleet(n: int, backend: str = "auto", control_hz: float = CONTROL_HZ,
               substeps: int = 4) -> tuple[Callable[[], None], Callable[[], None]]:
    """A stepping closure for a fleet of ``n`` cars driving random-ish inputs on asphalt."""
    cid = p.connect(p.DIRECT)
    make_ground(cid)
    fleet = CarFleet(cid, n, control_hz=control_hz, substeps=substeps, backend=backend)
    fleet.reset(np.arange(n), np.stack([np.arange(n) * 10.0, np.zeros(n)], axis=1), np.zeros(n), 15.0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, size=(64, 3, n))
    state = {"k": 0}

    def step() -> None:
        a = actions[state["k"] % 64]
        state["k"] += 1
        fleet.step(0.3 * a[0], 0.5 + 0.5 * a[1], np.zeros(n))
        _ = fleet.pos, fleet.vel_body, fleet.yaw_rate, fleet.wheel_omega, fleet.rpm  # what an env reads

    return step, lambda: p.disconnect(cid)


#: How far from the origin the raw racecar may drive before it is carried back across the plane [m].
PLANE_KEEP_M = 80.0


def make_racecar(rays: int = 0, ray_len_m: float = 200.0) -> tuple[Callable[[], None], Callable[[], None]]:
    """pybullet_data's racecar URDF: 4 wheel velocity motors + 2 steering position motors, 5 x 240 Hz, driven by
    seeded random actions; with ``rays`` > 0 it also casts that many rays of ``ray_len_m`` in a fan over +-90 deg of
    its heading each step (``rayTestBatch``, as a TORCS rangefinder)."""
    cid = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setPhysicsEngineParameter(fixedTimeStep=1.0 / 240.0, numSubSteps=0, physicsClientId=cid)
    p.loadURDF("plane.urdf", physicsClientId=cid)
    car = p.loadURDF(os.path.join("racecar", "racecar.urdf"), [0, 0, 0.2], physicsClientId=cid)
    wheels, steering = [2, 3, 5, 7], [4, 6]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, size=(64, 2))
    angles = np.deg2rad(np.linspace(-90.0, 90.0, rays)).tolist() if rays else []
    state = {"k": 0}

    def step() -> None:
        a = actions[state["k"] % 64]
        state["k"] += 1
        for w in wheels:
            p.setJointMotorControl2(car, w, p.VELOCITY_CONTROL, targetVelocity=20.0 * (0.5 + 0.5 * a[0]), force=10.0,
                                    physicsClientId=cid)
        for s in steering:
            p.setJointMotorControl2(car, s, p.POSITION_CONTROL, targetPosition=0.3 * a[1], physicsClientId=cid)
        for _ in range(5):
            p.stepSimulation(physicsClientId=cid)
        (x, y, z), quat = p.getBasePositionAndOrientation(car, physicsClientId=cid)
        p.getBaseVelocity(car, physicsClientId=cid)
        if abs(x) > PLANE_KEEP_M or abs(y) > PLANE_KEEP_M:
            # pybullet_data's plane ends ~100 m out; a car that drives off it falls through empty space with no
            # contacts and steps ~2.5x faster, so the reference would stop being a car on the ground. Carry it back
            # across the plane (pose and velocities kept).
            x, y = x - math.copysign(2 * PLANE_KEEP_M, x) * (abs(x) > PLANE_KEEP_M), \
                y - math.copysign(2 * PLANE_KEEP_M, y) * (abs(y) > PLANE_KEEP_M)
            p.resetBasePositionAndOrientation(car, (x, y, z), quat, physicsClientId=cid)
        if angles:
            yaw = p.getEulerFromQuaternion(quat)[2]
            to = [(x + ray_len_m * math.cos(yaw + t), y + ray_len_m * math.sin(yaw + t), z + 0.3) for t in angles]
            p.rayTestBatch([(x, y, z + 0.3)] * len(angles), to, numThreads=1, physicsClientId=cid)

    step.client, step.car = cid, car  # for a check of where the car is
    return step, lambda: p.disconnect(cid)


def best_rate(step: Callable[[], None], seconds: float) -> float:
    """Calls per second over one timing window of about ``seconds``."""
    k = 0
    t0 = time.perf_counter()
    while True:
        for _ in range(10):
            step()
        k += 10
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return k / dt


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="interleaved timing rounds (best is kept)")
    parser.add_argument("--seconds", type=float, default=0.4, help="length of one timing window [s]")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 32], help="fleet sizes N")
    parser.add_argument("--backend", nargs="+", default=["auto"], choices=["auto", "numba", "numpy", "python"],
                        help="integration backends, timed side by side")
    parser.add_argument("--control-hz", type=float, default=CONTROL_HZ, help="control rate [Hz]")
    parser.add_argument("--substeps", type=int, default=4, help="physics substeps per control step")
    args = parser.parse_args(argv)

    ref_step, ref_close = make_racecar()
    keys = [(b, n) for b in args.backend for n in args.sizes]
    fleets = {k: make_fleet(k[1], k[0], args.control_hz, args.substeps) for k in keys}
    for _ in range(20):  # warm-up
        ref_step()
        for step, _close in fleets.values():
            step()
    ref_best = 0.0
    best = {k: 0.0 for k in keys}
    for _ in range(args.rounds):
        ref_best = max(ref_best, best_rate(ref_step, args.seconds))
        for k, (step, _close) in fleets.items():
            best[k] = max(best[k], best_rate(step, args.seconds))
    ref_close()
    for _step, close in fleets.values():
        close()

    print(f"physics throughput, single thread, best of {args.rounds} interleaved rounds (control {args.control_hz:g} Hz; "
          f"torcsrl physics {args.control_hz * args.substeps:g} Hz = {args.substeps} substeps; racecar URDF at 50 Hz x 5 "
          f"substeps of 240 Hz)")
    print(f"{'backend':>8} | {'N cars':>6} | {'torcsrl steps/s':>15} | {'car-steps/s':>11} | {'us/step':>8} | "
          f"{'racecar URDF steps/s':>20} | {'ratio (car-steps)':>17}")
    print("-" * 106)
    for b, n in keys:
        rate = best[(b, n)]
        print(f"{b:>8} | {n:>6} | {rate:>15.0f} | {rate * n:>11.0f} | {1e6 / rate:>8.0f} | {ref_best:>20.0f} | "
              f"{rate * n / ref_best:>17.2f}")


if __name__ == "__main__":
    main()
