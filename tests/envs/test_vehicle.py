"""Vehicle physics against closed-form physics (flat ground, real pybullet, numpy only).

Each physical test drives a protocol and compares with a closed form:

* braking from 100 km/h:            d = v0^2 / (2 mu g)          within +-25 %, ordered by mu
* steady-state skidpad (R = 40 m):  max a_lat = mu g             within +-25 %
* top speed:                        200 .. 320 km/h (and converged: dv/dt ~ 0)
* 0-100 km/h at full throttle:      3 .. 8 s
* exceeding grip on ice:            body slip angle > 10 deg; the same input on asphalt < 10 deg

``python tests/envs/test_vehicle.py`` prints the measured figures.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pybullet as p
import pytest

from torcsrl.envs.surfaces import MU, SURFACE_NAMES, surface_id
from torcsrl.envs.vehicle import (
    CarFleet,
    VehicleParams,
    available_vehicles,
    make_ground,
    sanitize_controls,
    split_throttle_brake,
)

G = 9.81  # [m/s^2]
DT = 1.0 / 50.0  # [s] control step


# ------------------------------------------------------------------------------ helpers
class World:
    """A pybullet DIRECT client with a ground plane, closed by :meth:`close`."""

    def __init__(self) -> None:
        self.client = p.connect(p.DIRECT)
        self.ground = make_ground(self.client)

    def fleet(self, n: int = 1, **kw) -> CarFleet:
        return CarFleet(self.client, n, **kw)

    def close(self) -> None:
        p.disconnect(self.client)


@pytest.fixture
def world() -> Iterator[World]:
    w = World()
    yield w
    w.close()


def braking_distance(surface: str) -> tuple[float, float]:
    """Full brake, wheel straight, from 100 km/h to rest: (distance [m], time [s])."""
    w = World()
    try:
        f = w.fleet(surface=surface)
        f.reset([0], [[0.0, 0.0]], [0.0], 100.0 / 3.6)
        steps = 0
        while f.speed[0] > 0.05 and steps < 5000:
            f.step(0.0, 0.0, 1.0)
            steps += 1
        return float(np.hypot(*f.pos[0, :2])), steps * DT
    finally:
        w.close()


def skidpad_max_lateral_accel(surface: str, radius: float = 40.0, ramp: float = 0.2) -> float:
    """Max steady lateral acceleration [m/s^2] on a circle of ``radius`` [m].

    Pure pursuit holds the circle while a PI throttle/brake loop raises the speed slowly (``ramp``
    [m/s^2]) from 0.6 to 1.2 times the closed-form limit sqrt(mu g R). The lateral acceleration is
    the component of the COM's acceleration (finite differences of the world velocity) normal to
    its velocity, averaged over 1 s windows in which the car stays within 1 m of the circle with a
    body slip angle under 12 deg (steady cornering, not a spin).
    """
    w = World()
    try:
        f = w.fleet(surface=surface)
        prm = f.params
        v_lim = math.sqrt(MU[surface_id(surface)] * G * radius)
        v_target = 0.6 * v_lim
        f.reset([0], [[0.0, 0.0]], [0.0], v_target)  # on the circle centred at (0, radius)
        integ, v_prev = 0.0, f.vel_world[0, :2].copy()
        a_lat, steady = [], []
        for _ in range(int(0.6 * v_lim / ramp / DT)):
            v_target += ramp * DT
            x, y = f.pos[0, :2]
            lookahead = max(8.0, 0.6 * f.speed[0])
            phi = math.atan2(y - radius, x) + lookahead / radius
            tx, ty = radius * math.cos(phi), radius + radius * math.sin(phi)
            alpha = (math.atan2(ty - y, tx - x) - f.yaw[0] + math.pi) % (2 * math.pi) - math.pi
            delta = math.atan(2.0 * prm.wheelbase * math.sin(alpha) / lookahead)
            err = v_target - f.speed[0]
            integ += err * DT
            u = float(np.clip(0.5 * err + 0.3 * integ, -1.0, 1.0))
            f.step(delta / prm.max_steer, max(u, 0.0), max(-u, 0.0))
            v = f.vel_world[0, :2].copy()
            acc = (v - v_prev) / DT
            v_prev = v
            a_lat.append((v[0] * acc[1] - v[1] * acc[0]) / max(float(np.hypot(*v)), 1e-3))
            on_circle = abs(math.hypot(x, y - radius) - radius) < 1.0
            steady.append(on_circle and abs(f.slip_angle[0]) < math.radians(12.0))
        win = int(1.0 / DT)
        mean = np.convolve(a_lat, np.ones(win) / win, mode="valid")
        ok = np.convolve(np.asarray(steady, dtype=float), np.ones(win), mode="valid") == win
        assert ok.any(), "the car never cornered steadily"
        return float(mean[ok].max())
    finally:
        w.close()


def full_throttle_run(seconds: float = 150.0, **overrides) -> np.ndarray:
    """Speed trace [m/s] at full throttle, straight ahead on asphalt, from rest."""
    w = World()
    try:
        params = VehicleParams.load("default", overrides=overrides or None)
        f = w.fleet(params=params)
        out = np.empty(int(seconds / DT))
        for k in range(out.size):
            f.step(0.0, 1.0, 0.0)
            out[k] = f.speed[0]
        return out
    finally:
        w.close()


def max_slip_angle(surface: str, steer: float = 0.15, throttle: float = 0.3, speed: float = 12.0) -> float:
    """Largest |body slip angle| [deg] over 4 s of a fixed steer + throttle from ``speed`` [m/s]."""
    w = World()
    try:
        f = w.fleet(surface=surface)
        f.reset([0], [[0.0, 0.0]], [0.0], speed)
        worst = 0.0
        for _ in range(200):
            f.step(steer, throttle, 0.0)
            worst = max(worst, abs(float(f.slip_angle[0])))
        return math.degrees(worst)
    finally:
        w.close()


# ------------------------------------------------------------------------------ parameters
def test_params_load_and_reject_unknown_names():
    prm = VehicleParams.load("default")
    assert "default" in available_vehicles()
    assert 1000.0 <= prm.mass <= 1200.0 and prm.length == pytest.approx(4.5) and prm.wheelbase == pytest.approx(2.6)
    with pytest.raises(ValueError, match="available: .*default"):
        VehicleParams.load("no_such_car")
    with pytest.raises(ValueError, match="drive must be one of"):
        VehicleParams.load("default", overrides={"drive": "sideways"})
    with pytest.raises(ValueError, match="unknown vehicle parameter"):
        VehicleParams.load("default", overrides={"warp_drive": 1.0})
    with pytest.raises(ValueError, match="must be finite and > 0"):
        prm.replace(mass=-1.0)


def test_physics_rate_must_be_at_least_200_hz(world):
    with pytest.raises(ValueError, match=">= 200 Hz"):
        world.fleet(control_hz=50.0, substeps=3)
    f = world.fleet(control_hz=50.0, substeps=4)
    assert f.dt == pytest.approx(1.0 / 200.0)
    with pytest.raises(ValueError, match="backend must be one of"):
        world.fleet(backend="cuda")


# ------------------------------------------------------------------------------ closed-form physics
def test_braking_distance_matches_v2_over_2mug_and_orders_by_mu():
    measured = {}
    for surface in ("asphalt", "dirt", "ice"):
        d, t = braking_distance(surface)
        ideal = (100.0 / 3.6) ** 2 / (2.0 * MU[surface_id(surface)] * G)
        assert 0.75 * ideal <= d <= 1.25 * ideal, f"{surface}: braked in {d:.1f} m, closed form {ideal:.1f} m"
        measured[surface] = d
    assert measured["asphalt"] < measured["dirt"] < measured["ice"]


@pytest.mark.parametrize("surface", ["asphalt", "dirt", "ice"])
def test_skidpad_lateral_acceleration_matches_mu_g(surface):
    a = skidpad_max_lateral_accel(surface)
    mu_g = MU[surface_id(surface)] * G
    assert 0.75 * mu_g <= a <= 1.25 * mu_g, f"{surface}: {a:.2f} m/s^2 vs mu g = {mu_g:.2f} m/s^2"


@pytest.fixture(scope="module")
def flat_out() -> np.ndarray:
    return full_throttle_run()


def test_top_speed_is_200_to_320_kmh(flat_out):
    top = flat_out[-1] * 3.6
    accel_end = (flat_out[-1] - flat_out[-int(5 / DT)]) / 5.0
    assert abs(accel_end) < 0.05, f"still accelerating at {accel_end:.3f} m/s^2: not a top speed"
    assert 200.0 <= top <= 320.0, f"top speed {top:.0f} km/h"


def test_zero_to_hundred_in_3_to_8_s(flat_out):
    reached = np.flatnonzero(flat_out >= 100.0 / 3.6)
    assert reached.size, "never reached 100 km/h"
    t = (reached[0] + 1) * DT
    assert 3.0 <= t <= 8.0, f"0-100 km/h in {t:.2f} s"


def test_exceeding_grip_on_ice_slides_where_asphalt_grips():
    ice, asphalt = max_slip_angle("ice"), max_slip_angle("asphalt")
    assert ice > 10.0, f"ice slip angle {ice:.1f} deg"
    assert asphalt < 10.0, f"asphalt slip angle {asphalt:.1f} deg"


# ------------------------------------------------------------------------------ robustness
def test_random_actions_1e5_car_steps_stay_finite_and_above_ground(world):
    """20 cars x 5,000 control steps of random inputs on random surfaces (10^5 car-steps)."""
    rng = np.random.default_rng(1234)
    n, steps = 20, 5000
    f = world.fleet(n)
    f.reset(np.arange(n), np.stack([np.arange(n) * 20.0, np.zeros(n)], axis=1), rng.uniform(-3, 3, n),
            rng.uniform(0.0, 40.0, n))
    prm = f.params
    # collision-box corners in the body frame (relative to the COM)
    hx, hy, hz = prm.length / 2, prm.width / 2, prm.height / 2
    cx = prm.cg_to_front_axle + prm.front_overhang - hx
    cz = prm.ground_clearance + hz - prm.cg_height
    corners = np.array([[cx + sx * hx, sy * hy, cz + sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    action = rng.uniform(-1, 1, size=(3, n))
    lowest, fastest, spin = np.inf, 0.0, 0.0
    for k in range(steps):
        if k % 250 == 0:
            f.set_wheel_surfaces(rng.integers(0, len(SURFACE_NAMES), size=(n, 4)))
        change = rng.random(n) < 0.2  # hold each car's input ~5 steps
        action[:, change] = rng.uniform(-1, 1, size=(3, int(change.sum())))
        throttle, brake = split_throttle_brake(action[1])
        f.step(action[0], throttle, brake)
        if k % 1000 == 999:  # partial resets under way
            idx = rng.choice(n, size=3, replace=False)
            f.reset(idx, f.pos[idx, :2], rng.uniform(-3, 3, 3), rng.uniform(0, 30, 3))
        if k % 10 == 0 or k == steps - 1:
            state = np.concatenate([f.pos.ravel(), f.vel_world.ravel(), f.angvel_body.ravel(), f.wheel_omega.ravel(),
                                    f.rpm, f.steer_angle, f.wheel_load.ravel()])
            assert np.isfinite(state).all(), f"non-finite state at step {k}"
            z = (f.rotation[:, 2, :] @ corners.T) + f.pos[:, 2:3]  # corner heights [N, 8]
            lowest = min(lowest, float(z.min()))
            fastest = max(fastest, float(np.abs(f.vel_world).max()))
            spin = max(spin, float(np.abs(f.angvel_body).max()))
    assert lowest > -0.05, f"a chassis corner went {-lowest:.3f} m into the ground"
    assert (f.pos[:, 2] > 0.05).all()
    assert fastest < 100.0, f"blow-up: {fastest:.1f} m/s"
    assert spin < 30.0, f"blow-up: {spin:.1f} rad/s"


def test_flipped_car_is_detected_and_reset_upright(world):
    f = world.fleet(2)
    f.reset([0, 1], [[0.0, 0.0], [30.0, 0.0]], [0.0, 0.0])
    upside_down = p.getQuaternionFromEuler([math.pi, 0.0, 0.3])
    p.resetBasePositionAndOrientation(f.bodies[0], [0.0, 0.0, 1.5], upside_down, physicsClientId=world.client)
    for _ in range(100):
        f.step(0.0, 1.0, 0.0)
    assert f.flipped[0] and not f.flipped[1]
    assert f.pos[0, 2] < 0.4 and not f.wheel_contact[0].any()  # lying on its roof, wheels in the air
    bodies_before = p.getNumBodies(physicsClientId=world.client)
    f.reset([0], [[5.0, 5.0]], [1.0], [0.0])
    assert p.getNumBodies(physicsClientId=world.client) == bodies_before  # no body re-created
    for _ in range(100):
        f.step(0.0, 0.0, 1.0)
    assert not f.flipped.any()
    assert f.pos[0, 2] == pytest.approx(f.params.cg_height, abs=0.03)
    assert f.speed[0] < 0.05 and f.wheel_contact[0].all()
    assert f.yaw[0] == pytest.approx(1.0, abs=0.02)


def test_reset_sets_pose_speed_wheel_spin_and_gear(world):
    f = world.fleet(3)
    f.reset([2, 0], [[10.0, -5.0], [0.0, 0.0]], [0.5, -2.0], [25.0, 0.0])
    assert f.pos[2, :2] == pytest.approx([10.0, -5.0])
    assert f.yaw[2] == pytest.approx(0.5) and f.yaw[0] == pytest.approx(-2.0)
    assert f.vel_body[2, 0] == pytest.approx(25.0) and abs(f.vel_body[2, 1]) < 1e-9
    assert f.wheel_omega[2] == pytest.approx(np.full(4, 25.0 / f.params.wheel_radius))
    assert f.gear[2] > 1 and f.gear[0] == 1
    assert f.params.shift_down_rpm <= f.rpm[2] <= f.params.shift_up_rpm
    for bad in ([5], [-1]):
        with pytest.raises(ValueError, match="car indices"):
            f.reset(bad, [[0.0, 0.0]], [0.0])
    with pytest.raises(ValueError, match="finite"):
        f.reset([0], [[np.nan, 0.0]], [0.0])


def test_state_arrays_have_documented_shapes(world):
    n = 3
    f = world.fleet(n)
    f.step(np.zeros(n), np.ones(n), np.zeros(n))
    shapes = {"pos": (n, 3), "yaw": (n,), "vel_world": (n, 3), "vel_body": (n, 3), "yaw_rate": (n,),
              "wheel_omega": (n, 4), "wheel_xy": (n, 4, 2), "rpm": (n,), "gear": (n,), "steer_angle": (n,)}
    for name, shape in shapes.items():
        assert getattr(f, name).shape == shape, name
    # wheel_xy: the four hardpoints around the car, front wheels ahead
    xy = f.wheel_xy[0] - f.pos[0, :2]
    assert xy[0, 0] > 1.0 and xy[2, 0] < -1.0 and xy[0, 1] > 0.5 and xy[1, 1] < -0.5


# ------------------------------------------------------------------------------ controls
def test_non_finite_controls_never_reach_the_physics():
    """NaN -> 0 and +-inf -> the bounds: the same trajectory as the clean inputs."""
    traces = []
    for controls in (([np.nan, np.inf], [np.inf, np.nan], [np.nan, -np.inf]), ([0.0, 1.0], [1.0, 0.0], [0.0, 0.0])):
        w = World()
        try:
            f = w.fleet(2)
            f.reset([0, 1], [[0.0, 0.0], [0.0, 50.0]], [0.0, 0.0], [20.0, 20.0])
            for _ in range(50):
                f.step(*controls)
            traces.append(np.concatenate([f.pos.ravel(), f.wheel_omega.ravel(), f.steer_angle]))
        finally:
            w.close()
    assert np.isfinite(traces[0]).all()
    assert np.array_equal(traces[0], traces[1])
    assert traces[0][-1] == pytest.approx(VehicleParams.load().max_steer)  # +inf steer = full left lock


def test_control_helpers():
    t, b = split_throttle_brake(np.array([-2.0, -0.5, 0.0, 0.3, np.nan, np.inf, -np.inf]))
    assert t == pytest.approx([0.0, 0.0, 0.0, 0.3, 0.0, 1.0, 0.0])
    assert b == pytest.approx([1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 1.0])
    assert sanitize_controls(np.nan, 3, -1.0, 1.0) == pytest.approx([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        sanitize_controls(np.zeros(2), 3, -1.0, 1.0, "steer")


def test_bad_control_shapes_and_surface_ids_raise(world):
    f = world.fleet(3)
    with pytest.raises(ValueError, match="steer must be a scalar or have shape"):
        f.step(np.zeros(2), 0.0, 0.0)
    with pytest.raises(ValueError, match="surface ids must be integers"):
        f.set_wheel_surfaces(np.full((3, 4), 99))
    with pytest.raises(ValueError, match=r"shape \(3, 4\)"):
        f.set_wheel_surfaces(np.zeros((2, 4), dtype=int))


def test_steering_is_rate_limited_and_locks_at_max(world):
    f = world.fleet()
    prm = f.params
    f.step(1.0, 0.0, 0.0)
    assert f.steer_angle[0] == pytest.approx(prm.max_steer_rate * DT)
    for _ in range(50):
        f.step(1.0, 0.0, 0.0)
    assert f.steer_angle[0] == pytest.approx(prm.max_steer)


# ------------------------------------------------------------------------------ surfaces, fleets
def test_surface_fn_is_called_with_wheel_xy_each_step(world):
    calls = []

    def ice_beyond_20m(wheel_xy: np.ndarray) -> np.ndarray:
        calls.append(wheel_xy.shape)
        return np.where(wheel_xy[..., 0] > 20.0, surface_id("ice"), surface_id("asphalt"))

    f = world.fleet(surface_fn=ice_beyond_20m)
    f.reset([0], [[0.0, 0.0]], [0.0], 20.0)
    for _ in range(100):
        f.step(0.0, 0.5, 0.0)
    assert calls == [(1, 4, 2)] * 100
    assert f.pos[0, 0] > 30.0 and (f.wheel_mu[0] == MU[surface_id("ice")]).all()


def test_cars_pass_through_each_other_unless_collide():
    for collide in (False, True):
        w = World()
        try:
            f = w.fleet(2, collide=collide)
            f.reset([0, 1], [[10.0, 0.0], [0.0, 0.0]], [0.0, 0.0], [0.0, 12.0])  # car 1 runs into car 0
            for _ in range(100):
                f.step(0.0, 0.0, [1.0, 0.0])
            passed = f.pos[1, 0] > f.pos[0, 0]
            assert passed == (not collide), f"collide={collide}: x = {f.pos[:, 0]}"
        finally:
            w.close()


def run_backend(backend: str, overrides: dict, actions: np.ndarray, surfaces: np.ndarray) -> np.ndarray:
    """A 3-car trajectory (positions, body velocities, wheel spin, rpm, gear) in a fresh world."""
    w = World()
    try:
        n = actions.shape[2]
        f = w.fleet(n, backend=backend, params=VehicleParams.load("default", overrides=overrides or None))
        f.reset(np.arange(n), np.stack([np.arange(n) * 30.0, np.zeros(n)], axis=1), np.arange(n, dtype=float),
                np.linspace(0.0, 40.0, n))
        f.set_wheel_surfaces(surfaces)
        out = []
        for a in actions:
            f.step(a[0], np.abs(a[1]), np.maximum(a[2], 0.0))
            out.append(np.concatenate([f.pos.ravel(), f.vel_body.ravel(), f.wheel_omega.ravel(), f.rpm, f.gear]))
        return np.array(out)
    finally:
        w.close()


@pytest.mark.parametrize("other", ["python", "numba"])
def test_backends_agree_and_are_deterministic(other):
    """The numpy, numba and python backends integrate the same equations (to rounding)."""
    rng = np.random.default_rng(7)
    actions = rng.uniform(-1, 1, size=(200, 3, 3))
    surfaces = rng.integers(0, len(SURFACE_NAMES), size=(3, 4))
    options = {"traction_control": True, "abs": False, "drive": "all", "ackermann": 0.5}
    a = run_backend("numpy", {}, actions, surfaces)
    o = run_backend(other, {}, actions, surfaces)
    assert np.array_equal(o, run_backend(other, {}, actions, surfaces)), "not deterministic"
    assert np.abs(a - o).max() < 1e-6
    b = run_backend("numpy", options, actions, surfaces)
    assert np.abs(b - run_backend(other, options, actions, surfaces)).max() < 1e-6
    assert np.abs(a - b).max() > 1.0  # the options do change the dynamics


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_cars_dealt_over_several_worlds_move_as_in_one_world(backend):
    """A fleet over several pybullet clients gives the bits of the same fleet in one client: each car's body is
    integrated alone (no contacts between cars), only the collision broadphase is split."""
    n = 12

    def run(k: int) -> np.ndarray:
        worlds = [World() for _ in range(k)]
        try:
            f = CarFleet([w.client for w in worlds] if k > 1 else worlds[0].client, n, backend=backend,
                         control_hz=10.0, substeps=20)
            assert f.clients == [w.client for w in worlds]
            rng = np.random.default_rng(0)
            f.reset(np.arange(n), rng.normal(0.0, 0.5, (n, 2)), rng.normal(0.0, 0.1, n), rng.uniform(5.0, 30.0, n))
            out = []
            for k_ in range(25):
                f.step(rng.uniform(-1, 1, n), rng.uniform(0, 1, n), rng.uniform(0, 1, n) * (k_ % 5 == 0))
                out.append(np.concatenate([f._raw.ravel(), f.wheel_omega.ravel(), f.wheel_load.ravel(), f.rpm]))
            return np.array(out)
        finally:
            for w in worlds:
                w.close()

    one = run(1)
    for k in (2, 5):
        assert run(k).tobytes() == one.tobytes(), k


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("worlds", [1, 3])
def test_parked_cars_leave_the_physics_and_come_back_as_if_reset_in_place(worlds, backend):
    """park() takes cars out of the physics: the others move as they would have, a parked car's state stays
    frozen, and reset() brings it back as a new body with the bits of a body reset in place."""
    n = 9

    def run(park: bool) -> tuple[np.ndarray, CarFleet]:
        ws = [World() for _ in range(worlds)]
        try:
            f = CarFleet([w.client for w in ws] if worlds > 1 else ws[0].client, n, backend=backend,
                         control_hz=10.0, substeps=20)
            rng = np.random.default_rng(0)
            f.reset(np.arange(n), rng.normal(0.0, 3.0, (n, 2)), rng.normal(0.0, 0.1, n), 20.0)
            out = []
            for k in range(30):
                if park and k == 5:
                    f.park([2, 6, 7])
                    f.park([6])  # again: nothing happens
                    assert f.parked.tolist() == [i in (2, 6, 7) for i in range(n)]
                if k == 12:
                    f.reset([2, 7], [[1.0, 2.0], [3.0, -1.0]], [0.4, -0.2], 12.0)
                f.step(np.linspace(-0.5, 0.5, n), 0.7, float(k % 7 == 0))
                out.append(np.concatenate([f._raw, f.wheel_omega, f.wheel_load], axis=1))
            return np.array(out), f
        finally:
            for w in ws:
                w.close()

    a, _ = run(False)
    b, f = run(True)
    never = [0, 1, 3, 4, 5, 8]
    assert a[:, never].tobytes() == b[:, never].tobytes()
    assert a[12:, [2, 7]].tobytes() == b[12:, [2, 7]].tobytes()  # parked, then reset: as if reset in place
    assert np.array_equal(b[5, 6, :13], b[-1, 6, :13])  # still parked: its pose and velocity frozen
    assert f.parked.tolist() == [i == 6 for i in range(n)]
    with pytest.raises(ValueError, match="parked"):
        f.get_state()


def test_numba_backend_without_numba_fails_in_one_line(world, monkeypatch):
    from torcsrl.envs.vehicle import fleet

    monkeypatch.setattr(fleet, "_JIT", None)  # as on a machine without numba
    with pytest.raises(ValueError, match="backend numba needs the numba package"):
        world.fleet(2, backend="numba")
    assert world.fleet(2).backend == "python" and world.fleet(6).backend == "numpy"  # auto falls back


def test_park_needs_the_numpy_or_numba_backend(world):
    f = world.fleet(2, backend="python")
    with pytest.raises(ValueError, match="numpy or numba backend"):
        f.park([0])


def test_several_worlds_refuse_what_needs_one():
    worlds = [World() for _ in range(2)]
    try:
        ids = [w.client for w in worlds]
        for kw, n in (({"backend": "python"}, 4), ({"collide": True}, 4), ({"ground": "raycast"}, 4), ({}, 1)):
            with pytest.raises(ValueError):
                CarFleet(ids, n, **kw)
        f = CarFleet(ids, 3)
        assert f.backend == "numba" and f._cids == [ids[0], ids[0], ids[1]]
        with pytest.raises(ValueError, match="cannot collide"):
            f.set_collide(True)
        with pytest.raises(ValueError, match="one world"):
            f.track_contacts(True)
    finally:
        for w in worlds:
            w.close()


@pytest.mark.parametrize("backend", ["numpy", "numba", "python"])
def test_closed_form_ground_matches_pybullet_ray_test(backend):
    """ground="plane" (closed-form suspension rays) gives pybullet's ray-test trajectory, also for
    cars that overlap on one spot (where pybullet's ray test gets ~10x dearer)."""
    pos = {}
    for ground in ("plane", "raycast"):
        cid = p.connect(p.DIRECT)
        try:
            make_ground(cid)
            fleet = CarFleet(cid, 3, ground=ground, backend=backend)
            fleet.reset(np.arange(3), np.array([[0.0, 0.0], [0.0, 0.0], [30.0, 5.0]]), np.zeros(3), 20.0)
            for t in range(300):
                fleet.step(np.array([math.sin(t / 30), -0.5, 0.2]), np.array([0.8, 0.6, 1.0]),
                           np.array([0.0, 0.3 if t % 100 < 20 else 0.0, 0.0]))
            pos[ground] = fleet.pos.copy()
        finally:
            p.disconnect(cid)
    assert np.abs(pos["plane"] - pos["raycast"]).max() < 1e-6
    assert np.abs(pos["plane"][2, :2] - [30.0, 5.0]).max() > 10.0  # the cars did drive


def test_unknown_ground_model_is_rejected(world):
    with pytest.raises(ValueError, match="ground must be one of plane, raycast"):
        world.fleet(1, ground="terrain")


if __name__ == "__main__":  # print the validation figures
    print("braking from 100 km/h (ABS):")
    for s in ("asphalt", "wet", "dirt", "gravel", "ice", "grass"):
        d, t = braking_distance(s)
        ideal = (100 / 3.6) ** 2 / (2 * MU[surface_id(s)] * G)
        print(f"  {s:8s} {d:6.1f} m in {t:5.2f} s   closed form {ideal:6.1f} m   ratio {d / ideal:.3f}")
    print("skidpad R = 40 m, max steady lateral acceleration:")
    for s in ("asphalt", "wet", "dirt", "gravel", "ice", "grass"):
        a = skidpad_max_lateral_accel(s)
        mu_g = MU[surface_id(s)] * G
        print(f"  {s:8s} {a:5.2f} m/s^2   mu g {mu_g:5.2f} m/s^2   ratio {a / mu_g:.3f}")
    for label, ov in (("no traction control (default)", {}), ("traction control on", {"traction_control": True})):
        v = full_throttle_run(**ov)
        t100 = (np.flatnonzero(v >= 100 / 3.6)[0] + 1) * DT
        print(f"full throttle, {label}: 0-100 km/h {t100:.2f} s, top speed {v[-1] * 3.6:.1f} km/h")
    print(f"slip angle, steer 0.15 + throttle 0.3 from 12 m/s: ice {max_slip_angle('ice'):.1f} deg, "
          f"asphalt {max_slip_angle('asphalt'):.1f} deg")


@pytest.mark.parametrize("n", [1, 3])
def test_update_wheel_surfaces_matches_set_wheel_surfaces(world, n):
    """The env's unchecked update gives the checked setter's grip and rolling resistance, and keeps the arrays
    when the wheels stay on the surfaces they were on."""
    f, ref = world.fleet(n), world.fleet(n)
    ids = np.tile(np.array([surface_id("asphalt"), surface_id("dirt"), surface_id("grass"), surface_id("ice")]), (n, 1))
    f._update_wheel_surfaces(ids)
    ref.set_wheel_surfaces(ids)
    assert np.array_equal(f.wheel_surfaces, ids) and np.array_equal(f.wheel_mu, ref.wheel_mu)
    assert np.array_equal(f._crr_a, ref._crr_a)
    mu = f.wheel_mu
    f._update_wheel_surfaces(ids.copy())
    assert f.wheel_mu is mu
    ids[-1, 0] = surface_id("wet")
    f._update_wheel_surfaces(ids)
    ref.set_wheel_surfaces(ids)
    assert f.wheel_mu is not mu and np.array_equal(f.wheel_mu, ref.wheel_mu)
