"""Camera drivers: the camera-only observation set, the grip-aware teacher, privileged distillation into a camera
student (experiment=camera_distill), and the one-line errors when a policy is fed another observation set."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.envs.sensors import STATE_SLOTS, TELEMETRY_SLOTS
from torcsrl.envs.surfaces import SURFACES
from _compose import compose_config
from _history import assert_policy_history_matches_training_env

torch.set_num_threads(1)


def _drive(env, steps, act=(0.05, 0.7)):
    td = env.reset()
    out = [td]
    for _ in range(steps):
        td = env.step(td.set("action", torch.tensor(act)))["next"]
        out.append(td)
    return out


def test_camera_set_is_pixels_and_telemetry_without_map_quantities():
    cam = make_env(track="hairpins", sensors=("pixels", "telemetry"), camera={"height": 32, "width": 32}, seed=3)
    full = make_env(track="hairpins", sensors=("state",), seed=3)
    try:
        keys = set(cam.observation_spec.keys()) - {"info"}
        assert keys == {"pixels", "telemetry"}  # no rangefinder, no state (trackPos, angle to the axis)
        assert cam.observation_spec["pixels"].dtype == torch.uint8 and tuple(cam.observation_spec["pixels"].shape) == (3, 32, 32)
        assert TELEMETRY_SLOTS == STATE_SLOTS[2:] and "trackPos" not in TELEMETRY_SLOTS and "angle_rad" not in TELEMETRY_SLOTS
        a, b = _drive(cam, 40), _drive(full, 40)
        for x, y in zip(a, b):  # same seed, same actions: telemetry is exactly the on-board slots of state
            torch.testing.assert_close(x["telemetry"], y["state"][2:], rtol=0, atol=0)
        assert a[-1]["telemetry"][TELEMETRY_SLOTS.index("speedX_kmh")] > 5.0  # 0.8 s of throttle at 50 Hz
        assert a[-1]["pixels"].float().std() > 5.0  # a picture, not a blank frame
    finally:
        cam.close()
        full.close()


@pytest.mark.parametrize("surface", ["asphalt", "dirt"])
def test_info_reports_the_friction_under_the_car(surface):
    env = make_env(track="oval", surface=surface, sensors=("state",), seed=0)
    try:
        td = _drive(env, 5, act=(0.0, 0.3))[-1]
        from torcsrl.envs.vehicle import VehicleParams

        want = SURFACES[surface].mu * VehicleParams.load("default").tyre_mu_scale
        assert float(td["info", "surfaceMu"]) == pytest.approx(want, rel=1e-6)
    finally:
        env.close()


def test_grip_aware_teacher_plans_its_braking_with_the_surface():
    from torcsrl.policies import SensorDriver, load_policy

    blind, grip = SensorDriver(), load_policy("sensor_grip")
    r = np.full(19, 60.0)  # a bend 60 m ahead, car at 100 km/h on the centreline
    st = np.zeros(len(STATE_SLOTS))
    st[STATE_SLOTS.index("speedX_kmh")] = 100.0
    asphalt, dirt = grip.act(r, st, mu=1.0)[1], grip.act(r, st, mu=0.6)[1]
    assert dirt == pytest.approx(blind.act(r, st)[1])  # 7.5 x 0.6 = the blind driver's 4.5 m/s^2
    assert asphalt > dirt  # more grip: brakes less (or later) for the same view
    from tensordict import TensorDict

    td = TensorDict({"rangefinder": torch.tensor(r, dtype=torch.float32), "state": torch.tensor(st, dtype=torch.float32)}, [])
    with pytest.raises(ValueError, match="surfaceMu"):
        grip(td)
    for bad in (0.0, -2.0, float("nan")):
        with pytest.raises(ValueError, match="decel_per_mu"):
            SensorDriver(decel_per_mu=bad)


def test_sight_limited_teacher_plans_its_speed_on_what_the_camera_can_see():
    from torcsrl.training.demos import DemoError, make_teacher
    from torcsrl.policies import PolicyError, SensorDriver, load_policy

    grip, sight = load_policy("sensor_grip"), load_policy("sensor_sight")
    assert sight.k.sight_m == SensorDriver.CAMERA_SIGHT_M and load_policy("sensor_sight:90").k.sight_m == 90.0
    st = np.zeros(len(STATE_SLOTS))
    st[STATE_SLOTS.index("speedX_kmh")] = 150.0  # 41.7 m/s on a long straight, asphalt
    straight = np.full(19, 200.0)
    assert grip.act(straight, st, mu=1.0)[1] > 0 > sight.act(straight, st, mu=1.0)[1]  # it cannot stop within 80 m: it brakes
    near = np.full(19, 40.0)  # a bend nearer than the sight distance: both see the same
    assert grip.act(near, st, mu=1.0) == sight.act(near, st, mu=1.0)
    with pytest.raises(PolicyError, match="number of metres"):
        load_policy("sensor_sight:far")
    with pytest.raises(DemoError, match="number of metres"):
        make_teacher("sensor_sight:far")
    with pytest.raises(ValueError, match="sight_m"):
        SensorDriver(sight_m=5.0)


def test_fast_camera_teacher_laps_faster_within_the_same_sight():
    """sensor_fast_sight: the fast gains under the camera's 80 m of sight — faster laps than sensor_sight on asphalt
    and dirt, never planning on road it cannot see, and a bad sight fails in one line."""
    from torcsrl.training.demos import DemoError, make_teacher
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import PolicyError, SensorDriver, load_policy

    fast = load_policy("sensor_fast_sight")
    assert fast.k.sight_m == SensorDriver.CAMERA_SIGHT_M and load_policy("sensor_fast_sight:90").k.sight_m == 90.0
    assert fast.fingerprint != load_policy("sensor_sight").fingerprint != load_policy("sensor_fast").fingerprint
    assert make_teacher("sensor_fast_sight").keys == ("rangefinder_clean", "state_clean")
    st = np.zeros(len(STATE_SLOTS))
    st[STATE_SLOTS.index("speedX_kmh")] = 160.0  # 44 m/s: more than 80 m of road stops
    from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG

    sin = np.abs(np.sin(np.radians(RANGEFINDER_ANGLES_DEG)))
    straight = np.minimum(200.0, 6.0 / np.maximum(sin, 1e-9))  # the beams on a straight 12 m wide road
    assert fast.act(straight, st, mu=1.0)[1] < 0 < load_policy("sensor_fast").act(straight, st, mu=1.0)[1]
    kw = {"control_hz": 10, "substeps": 20}
    for surface in ("asphalt", "dirt"):
        f, _ = run_cell(fast, "oval", surface, laps=2, env_kwargs=kw)
        s, _ = run_cell(load_policy("sensor_sight"), "oval", surface, laps=2, env_kwargs=kw)
        assert f[0]["success"] and s[0]["success"] and f[0]["off_track_events"] == 0, (surface, f[0], s[0])
        assert f[0]["fastest_lap"] < 0.95 * s[0]["fastest_lap"], (surface, f[0]["fastest_lap"], s[0]["fastest_lap"])
    with pytest.raises(PolicyError, match="sensor_fast_sight:.*number of metres"):
        load_policy("sensor_fast_sight:far")
    with pytest.raises(DemoError, match="number of metres"):
        make_teacher("sensor_fast_sight:far")


# ------------------------------------------------------------------ privileged distillation, end to end (tiny)
@pytest.fixture(scope="module")
def distilled(tmp_path_factory):
    from torcsrl.training import train

    out = tmp_path_factory.mktemp("cam") / "run"
    cfg = compose_config("experiment=camera_distill", "env.camera.height=32", "env.camera.width=32",
                         "algo.encoder.cnn_kernels=[4,3,3]", "algo.encoder.cnn_strides=[2,2,1]", "algo.batch_size=16",
                         "algo.actor_hidden=[32,32]", "demos.frames=120", "algo.bc_steps=10", "demos.dagger_rounds=1",
                         "demos.dagger_frames=60", "eval.per_track=false", "eval.env.track=oval", "eval.max_steps=20",
                         "env.procedural.pool=2", "algo.aux_privileged=1.0", "logger.every_frames=5", f"run_dir={out}")
    res = train(cfg)
    return cfg, res, out


def test_distillation_trains_a_camera_student_from_a_privileged_teacher(distilled):
    import json

    from torcsrl.policies import CheckpointPolicy
    from torcsrl.utils.checkpoint import latest_checkpoint

    cfg, res, out = distilled
    assert res["updates"] == 20 and res["frames"] == 60
    meta = json.loads((out / "demos" / "demos.json").read_text())
    assert meta["teacher"] == "sensor_sight" and meta["frames"] == 120
    stored = {p.name.split(".")[0] for p in (out / "demos" / "rows").glob("*.memmap")}
    assert (out / "logs" / "dagger" / "scalars" / "loss" / "aux.csv").is_file()  # algo.aux_privileged > 0 logs its loss
    assert {"pixels", "telemetry", "expert_action", "privileged"} <= stored and not stored & {"rangefinder", "state"}  # only what the student sees
    pol = CheckpointPolicy(latest_checkpoint(out / "checkpoints"))
    assert list(pol.obs_keys) == ["pixels", "telemetry"] and pol.env_overrides["sensors"] == ("pixels", "telemetry")
    assert pol.obs_shapes["pixels"] == (3, 32, 32) and set(pol.pipeline["scales"]) == {"telemetry"}


def test_camera_student_sees_exactly_its_training_observations(distilled):
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.pipeline import env_kwargs, make_train_env
    from torcsrl.utils.checkpoint import latest_checkpoint

    cfg, _, out = distilled
    pol = CheckpointPolicy(latest_checkpoint(out / "checkpoints"))
    train_env = make_train_env(cfg)
    kw = env_kwargs(cfg.env, seed=int(cfg.seed), device="cpu")  # the single training env's seed
    raw = make_env(**kw)
    try:
        a, b = train_env.reset(), raw.reset()
        for _ in range(4):
            act = torch.tensor([0.0, 0.5])
            a = train_env.step(a.set("action", act))["next"]
            b = raw.step(b.set("action", act))["next"]
        assert torch.equal(a["pixels"], b["pixels"]) and not torch.equal(a["telemetry"], b["telemetry"])  # telemetry scaled
        with torch.no_grad():
            torch.testing.assert_close(pol._act(*(b.get(k) for k in pol.obs_keys)), pol.actor(*(a.get(k) for k in pol.obs_keys)))
    finally:
        train_env.close()
        raw.close()


def test_mismatched_observations_fail_in_one_line(distilled):
    from torcsrl.policies import CheckpointPolicy, PolicyError, load_policy
    from torcsrl.utils.checkpoint import latest_checkpoint

    _, _, out = distilled
    cam = CheckpointPolicy(latest_checkpoint(out / "checkpoints"))
    envs = {"rangefinder": make_env(track="oval", sensors=("rangefinder", "state")),
            "big": make_env(track="oval", sensors=("pixels", "telemetry"), camera={"height": 48, "width": 48}),
            "camera": make_env(track="oval", sensors=("pixels", "telemetry"), camera={"height": 32, "width": 32})}
    try:
        with pytest.raises(PolicyError, match=r"pixels.*3x32x32") as err:  # camera policy on an env without pixels
            cam.check_env(envs["rangefinder"])
        assert "\n" not in str(err.value) and "telemetry:9" in str(err.value)
        with pytest.raises(PolicyError, match=r"\(3, 32, 32\).*\(3, 48, 48\)") as err:  # another resolution
            cam.check_env(envs["big"])
        assert "\n" not in str(err.value)
        cam.check_env(envs["camera"])  # the right one passes
        with pytest.raises(PolicyError, match="rangefinder") as err:  # a rangefinder policy on a camera-only env
            load_policy("reference").check_env(envs["camera"])
        assert "\n" not in str(err.value)
    finally:
        for e in envs.values():
            e.close()


def test_the_shipped_camera_driver_loads_and_sees_only_the_camera_set():
    from torcsrl.policies import REFERENCE_CAMERA_POLICY, load_policy

    assert REFERENCE_CAMERA_POLICY.is_file() and REFERENCE_CAMERA_POLICY.with_suffix(".md").is_file()
    pol = load_policy("reference_camera")
    assert list(pol.obs_keys) == ["pixels", "telemetry"] and pol.obs_shapes["pixels"] == (3, 64, 96)
    env = make_env(track="oval", sensors=pol.env_overrides["sensors"], camera=pol.env_overrides["camera"],
                   control_hz=pol.env_overrides.get("control_hz"), substeps=pol.env_overrides.get("substeps"))
    try:
        pol.check_env(env)
        td = env.reset()
        for _ in range(20):
            td = env.step(pol(td))["next"]
        assert float(td["telemetry"][TELEMETRY_SLOTS.index("speedX_kmh")]) > 10.0  # it drives off the grid
    finally:
        env.close()


def test_a_frame_stacked_student_trains_on_one_frame_demonstrations_and_drives_one_frame_envs(distilled, tmp_path):
    """frame_stack=3: the same demonstration folder (written at one frame) trains it, DAgger included; its checkpoint
    keeps K, reads one-frame envs (check_env) and stacks them itself exactly as the training env did."""
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.training import train
    from torcsrl.utils.checkpoint import latest_checkpoint

    cfg0, _, out0 = distilled
    over = [f"run_dir={tmp_path / 'fs'}", "frame_stack=3", f"demos.path={out0 / 'demos'}", "demos.frames=0"]
    cfg = compose_config("experiment=camera_distill", "env.camera.height=32", "env.camera.width=32",
                         "algo.encoder.cnn_kernels=[4,3,3]", "algo.encoder.cnn_strides=[2,2,1]", "algo.batch_size=16",
                         "algo.actor_hidden=[32,32]", "algo.bc_steps=10", "demos.dagger_rounds=1", "demos.dagger_frames=30",
                         "eval.per_track=false", "eval.env.track=oval", "eval.max_steps=20", "env.procedural.pool=2", *over)
    res = train(cfg)
    assert res["updates"] == 20 and res["frames"] == 30
    pol = CheckpointPolicy(latest_checkpoint(tmp_path / "fs" / "checkpoints"))
    assert pol.frame_stack == 3 and pol.obs_shapes["pixels"] == (3, 32, 32)  # what the env gives: one frame
    assert pol.meta["obs_layout"].startswith("pixels:9x32x32")  # what the actor sees: 3 frames of 3 channels
    cam = make_env(track="oval", sensors=("pixels", "telemetry"), camera={"height": 32, "width": 32})
    try:
        pol.check_env(cam)
    finally:
        cam.close()
    # the evaluation protocol drives it on one-frame envs, its history reset at every episode's start
    from torcsrl.evaluate import run_cell

    resets, reset = [], pol.reset
    pol.reset = lambda ctx=None: (resets.append(dict(pol._history)), reset(ctx))[1]
    rows, _ = run_cell(pol, "oval", "asphalt", episodes=2, max_steps=6)
    assert len(rows) == 2 and len(resets) == 2 and resets[0] == {} and resets[1]["pixels"].shape == (9, 32, 32)  # episode 1 filled it
    pol.reset = reset
    assert_policy_history_matches_training_env(pol, cfg, 8)


def test_dagger_continues_from_a_distilled_student(distilled, tmp_path):
    """init.actor with algo=dagger: round 0 validates the given student unchanged, round 1 drives it, relabels and refits."""
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.training import train
    from torcsrl.utils.checkpoint import checkpoint_path, latest_checkpoint

    _, _, out0 = distilled
    start = latest_checkpoint(out0 / "checkpoints")
    cfg = compose_config("experiment=camera_distill", "env.camera.height=32", "env.camera.width=32",
                         "algo.encoder.cnn_kernels=[4,3,3]", "algo.encoder.cnn_strides=[2,2,1]", "algo.batch_size=16",
                         "algo.actor_hidden=[32,32]", "algo.bc_steps=7", "demos.dagger_rounds=1", "demos.dagger_frames=30",
                         f"demos.path={out0 / 'demos'}", "demos.frames=0", f"init.actor={start}", "eval.per_track=false",
                         "eval.env.track=oval", "eval.max_steps=20", "env.procedural.pool=2", f"run_dir={tmp_path / 'dg'}")
    res = train(cfg)
    assert res["updates"] == 7 and res["frames"] == 30  # one fit: round 1's
    ck = tmp_path / "dg" / "checkpoints"
    a, b = CheckpointPolicy(start).actor.state_dict(), CheckpointPolicy(checkpoint_path(ck, 0)).actor.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)  # round 0: the start itself
    c = CheckpointPolicy(latest_checkpoint(ck)).actor.state_dict()
    assert any(not torch.equal(a[k], c[k]) for k in a)  # round 1 refitted it


def test_demonstrations_load_at_any_stack_of_their_frame_size_only(distilled):
    import json

    from torcsrl.training.demos import DemoError, load_demos

    _, _, out0 = distilled
    rec = json.loads((out0 / "demos" / "demos.json").read_text())["record"]
    one = rec["obs_layout"]  # pixels:3x32x32,telemetry:9
    assert one.startswith("pixels:3x32x32")
    stacked = {**rec, "obs_layout": one.replace("pixels:3x", "pixels:12x"), "frame_stack": 4}
    buf = load_demos(out0 / "demos", stacked, 8, history={"pixels": 4})
    assert buf.sample(8)["pixels"].shape == (8, 12, 32, 32)
    other = {**stacked, "obs_layout": one.replace("pixels:3x32x32", "pixels:12x48x48")}
    with pytest.raises(DemoError, match=r"frames of 'pixels:3x32x32.*this run's frames are 'pixels:3x48x48") as err:
        load_demos(out0 / "demos", other, 8, history={"pixels": 4})
    assert "\n" not in str(err.value)
