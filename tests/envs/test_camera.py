"""Camera sensor and visual world: shapes, depth geometry, determinism, surfaces, world separation,
renderer choice, mounts, frame holding, visual-only bodies."""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import textwrap

import numpy as np
import pybullet as p
import pytest

from torcsrl.envs import tracks
from torcsrl.envs.camera import (
    MOUNTS,
    Camera,
    Mount,
    RendererUnavailable,
    euler_to_matrix,
    gpu_available,
    setup_renderer,
)
from torcsrl.envs.world import FLAT_MATERIALS, WorldStyle, build_world

Z_COM = 0.45  # [m] chassis centre-of-mass height of the default car at rest


@pytest.fixture
def client():
    cid = p.connect(p.DIRECT)
    yield cid
    p.disconnect(cid)


@pytest.fixture(scope="module")
def oval_scene():
    """One client with the oval's world and a tiny-renderer camera (shared: building is the slow part)."""
    cid = p.connect(p.DIRECT)
    track = tracks.load("oval")
    world = build_world(cid, track)
    yield cid, track, world
    p.disconnect(cid)


def _pose(track, s, d=0.0):
    xy = track.to_world(s, d)
    return [float(xy[0]), float(xy[1]), Z_COM], float(track.heading(s))


def _lower_middle_mean(rgb: np.ndarray) -> np.ndarray:
    h, w = rgb.shape[1:]
    return rgb[:, int(0.8 * h):, int(0.35 * w):int(0.65 * w)].reshape(3, -1).mean(1)


# ---------------------------------------------------------------- shapes and values
@pytest.mark.parametrize("size", [(84, 84), (64, 48)])
def test_shapes_dtypes_and_depth_range(oval_scene, size):
    cid, track, world = oval_scene
    w, h = size
    cam = Camera(cid, w, h, worlds=[world], renderer="tiny")
    rgb, depth = cam.render(*_pose(track, 100.0))
    assert rgb.shape == (3, h, w) and rgb.dtype == np.uint8
    assert depth.shape == (1, h, w) and depth.dtype == np.float32
    assert cam.shape_rgb == rgb.shape and cam.shape_depth == depth.shape
    assert np.isfinite(depth).all() and depth.min() >= cam.near - 1e-4 and depth.max() <= cam.far + 1e-3
    # sky at the top reads far, road at the bottom is a few metres ahead
    assert np.allclose(depth[0, 0], cam.far)
    assert 0.5 < depth[0, -1, w // 2] < 5.0
    assert rgb.std() > 10  # not a blank frame


def test_depth_of_a_box_ahead_matches_geometry(oval_scene):
    """A visual box straight ahead on the camera's optical axis: centre-pixel depth within 5 %."""
    cid, track, world = oval_scene
    cam = Camera(cid, 84, 84, worlds=[world], renderer="tiny")
    pos, yaw = _pose(track, 120.0)
    eye, rc = cam.camera_pose(pos, yaw)
    axis = rc[:, 0]  # optical axis (pitched down by the hood mount)
    dist = 12.0  # [m] along the axis to the box's near face
    half = 0.75
    center = eye + axis * (dist + half)
    vs = p.createVisualShape(p.GEOM_BOX, halfExtents=[half] * 3, rgbaColor=[0.1, 0.2, 0.9, 1], physicsClientId=cid)
    quat = p.getQuaternionFromEuler([0.0, math.radians(cam.mount.pitch_deg), yaw])  # face square to the axis
    box = p.createMultiBody(0, -1, vs, basePosition=center.tolist(), baseOrientation=quat, physicsClientId=cid)
    try:
        rgb, depth = cam.render(pos, yaw)
        c = depth[0, 41:43, 41:43]
        assert np.all(np.abs(c - dist) < 0.05 * dist), c
        assert rgb[2, 42, 42] > 150 and rgb[0, 42, 42] < 100  # the box's blue
    finally:
        p.removeBody(box, physicsClientId=cid)


def test_painted_ground_depth_is_exact(oval_scene):
    """Ground pixels (painted, not rendered) read the exact ray / ground-plane z-depth."""
    cid, track, world = oval_scene
    cam = Camera(cid, 84, 84, worlds=[world], renderer="tiny")
    pos, yaw = _pose(track, 120.0)
    eye, rc = cam.camera_pose(pos, yaw)
    _, depth = cam.render(pos, yaw)
    rays = rc @ cam._rays  # forward component 1: the ray parameter at the ground is the z-depth
    t = eye[2] / -rays[2]
    rows = np.arange(60, 84)
    expected = t.reshape(84, 84)[rows, 42]
    assert np.allclose(depth[0, rows, 42], expected, rtol=1e-4)


@pytest.mark.parametrize("geometry", [{}, {"fov_deg": 30.0, "hfov_deg": 81.0, "pitch_deg": 2.0}], ids=["square", "far-seeing"])
def test_painted_ground_lines_up_with_rendered_meshes(geometry):
    """The same road drawn as meshes by the renderer and painted from the map: depths agree (also with non-square
    pixels and another tilt: the renderer's projection and the painter's rays are the same camera)."""
    track = tracks.load("hairpins")
    pos, yaw = _pose(track, 150.0, 2.0)
    depths = []
    for meshes in (True, False):
        cid = p.connect(p.DIRECT)
        try:
            style = WorldStyle(road_meshes=meshes, post_spacing_m=0, tree_spacing_m=0, gantry=False)
            world = build_world(cid, track, style=style)
            cam = Camera(cid, 84, 84, worlds=[world], renderer="tiny", background=not meshes, **geometry)
            depths.append(cam.render(pos, yaw + 0.1)[1])
        finally:
            p.disconnect(cid)
    d_mesh, d_paint = depths
    ground = d_mesh < 0.9 * 300.0  # where the renderer drew the road mesh
    rel = np.abs(d_mesh[ground] - d_paint[ground]) / d_mesh[ground]
    assert ground.mean() > 0.3 and rel.max() < 0.02


# ---------------------------------------------------------------- determinism and motion
def test_same_pose_same_frame_and_motion_changes_it(oval_scene):
    cid, track, world = oval_scene
    cam = Camera(cid, 84, 84, worlds=[world], renderer="tiny")
    pose = _pose(track, 300.0, 1.0)
    a_rgb, a_d = cam.render(*pose)
    cam.render(*_pose(track, 900.0))  # elsewhere in between (other chunks visible)
    b_rgb, b_d = cam.render(*pose)
    np.testing.assert_array_equal(a_rgb, b_rgb)
    np.testing.assert_array_equal(a_d, b_d)
    c_rgb, _ = cam.render(*_pose(track, 301.0, 1.0))  # one metre on
    assert np.abs(c_rgb.astype(int) - a_rgb).sum() > 0
    d_rgb, _ = cam.render(pose[0], pose[1] + 0.05)  # a small turn
    assert np.abs(d_rgb.astype(int) - a_rgb).sum() > 0


def test_culling_does_not_change_the_frame(oval_scene):
    cid, track, world = oval_scene
    # draw distance = far plane: only the view cone culls (a shorter draw distance drops far objects)
    culled = Camera(cid, 84, 84, worlds=[world], renderer="tiny", cull=True, draw_distance=300.0)
    whole = Camera(cid, 84, 84, worlds=[world], renderer="tiny", cull=False)
    for s in (0.0, 480.0, 620.0, 1300.0):
        pose = _pose(track, s, -2.0)
        a = culled.render(*pose)
        assert world._visible.sum() < len(world.chunks)
        b = whole.render(*pose)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


def test_render_batch_and_rotation_input_match_render(oval_scene):
    cid, track, world = oval_scene
    cam = Camera(cid, 32, 32, worlds=[world], renderer="tiny")
    poses = [_pose(track, s) for s in (50.0, 700.0)]
    pos = np.array([q[0] for q in poses])
    yaw = np.array([q[1] for q in poses])
    rgb, depth = cam.render_batch(pos, yaw=yaw)
    rgb_r, depth_r = cam.render_batch(pos, rot=euler_to_matrix(yaw))
    assert rgb.shape == (2, 3, 32, 32) and depth.shape == (2, 1, 32, 32)
    np.testing.assert_array_equal(rgb, rgb_r)
    for i, (q, y) in enumerate(poses):
        one = cam.render(q, y)
        np.testing.assert_array_equal(rgb[i], one[0])
        np.testing.assert_array_equal(depth[i], one[1])


def test_observe_holds_frames_between_renders(oval_scene):
    cid, track, world = oval_scene
    cam = Camera(cid, 32, 32, worlds=[world], renderer="tiny", every=3)
    frames = []
    for k in range(6):
        q, y = _pose(track, 100.0 + 2.0 * k)
        frames.append(cam.observe(np.array([q]), yaw=np.array([y]))[0])
    assert frames[0].shape == (1, 3, 32, 32)
    np.testing.assert_array_equal(frames[0], frames[1])
    np.testing.assert_array_equal(frames[0], frames[2])
    assert not np.array_equal(frames[2], frames[3])
    np.testing.assert_array_equal(frames[3], frames[5])
    q, y = _pose(track, 400.0)
    fresh = cam.observe(np.array([q]), yaw=np.array([y]), reset=np.array([True]))[0]
    np.testing.assert_array_equal(fresh[0], cam.render(q, y)[0])


# ---------------------------------------------------------------- surfaces
def test_surfaces_render_distinguishably(client):
    track = tracks.load("oval")
    means = {}
    for k, surface in enumerate(("asphalt", "dirt", "wet", "ice")):
        world = build_world(client, track.with_surface(surface), origin_xy=(k * 10_000.0, 0.0),
                            style=WorldStyle(tree_spacing_m=0))
        cam = Camera(client, 84, 84, worlds=[world], renderer="tiny")
        xy = world.to_world(200.0, 0.0)
        rgb, _ = cam.render([xy[0], xy[1], Z_COM], float(track.heading(200.0)))
        means[surface] = _lower_middle_mean(rgb)
    assert np.abs(means["asphalt"] - means["dirt"]).sum() > 60, means
    assert np.abs(means["ice"] - means["wet"]).sum() > 200, means
    assert means["dirt"][0] > means["dirt"][2] + 40  # brown
    assert means["ice"].mean() > 180 > 60 > means["wet"].mean()  # pale vs dark


# ---------------------------------------------------------------- several worlds in one client
def test_origin_offsets_keep_worlds_apart(client):
    a_track, b_track = tracks.load("oval"), tracks.load("hairpins", surface="dirt")
    world_a = build_world(client, a_track)
    cam = Camera(client, 84, 84, worlds=[world_a], renderer="tiny")
    pose = _pose(a_track, 250.0)
    alone = cam.render(*pose)
    world_b = build_world(client, b_track, origin_xy=(10_000.0, 0.0))
    cam.add_world(world_b)
    together = cam.render(*pose)
    np.testing.assert_array_equal(alone[0], together[0])  # world A's camera sees nothing of B
    np.testing.assert_array_equal(alone[1], together[1])
    # the other way round: at B the road under the car is B's dirt, not A's asphalt
    xy = world_b.to_world(100.0, 0.0)
    rgb, _ = cam.render([xy[0], xy[1], Z_COM], float(b_track.heading(100.0)))
    m = _lower_middle_mean(rgb)
    assert m[0] > m[2] + 40
    assert world_a._visible.sum() == 0  # every chunk of A hidden while looking at B


# ---------------------------------------------------------------- renderers and mounts
def test_egl_request_without_gpu_fails_clearly_and_auto_falls_back(client, caplog):
    if gpu_available():
        pytest.skip("a GPU is present: EGL may legitimately work here")
    with pytest.raises(RendererUnavailable, match="GPU"):
        Camera(client, 84, 84, renderer="egl")
    with caplog.at_level(logging.INFO, logger="torcsrl.envs.camera"):
        cam = Camera(client, 84, 84, renderer="auto")
    assert cam.renderer == "tiny"
    assert "camera renderer: tiny" in caplog.text


def test_egl_needs_to_come_before_bodies(client):
    vs = p.createVisualShape(p.GEOM_BOX, halfExtents=[1, 1, 1], physicsClientId=client)
    p.createMultiBody(0, -1, vs, physicsClientId=client)
    with pytest.raises(RendererUnavailable):
        setup_renderer(client, "egl", allow_software_egl=True)
    assert setup_renderer(client, "auto").name == "tiny"


_EGL_SCRIPT = textwrap.dedent("""
    import numpy as np, pybullet as p
    from torcsrl.envs import tracks
    from torcsrl.envs.camera import Camera, RendererUnavailable, setup_renderer
    from torcsrl.envs.world import build_world
    cid = p.connect(p.DIRECT)
    try:
        rend = setup_renderer(cid, "egl", allow_software_egl=True)
    except RendererUnavailable as err:
        print("UNAVAILABLE", err); raise SystemExit(0)
    track = tracks.load("oval")
    world = build_world(cid, track)
    cam = Camera(cid, 32, 32, renderer=rend, worlds=[world])
    xy = track.to_world(100.0, 0.0)
    rgb, depth = cam.render([xy[0], xy[1], 0.45], float(track.heading(100.0)))
    assert rgb.shape == (3, 32, 32) and depth.shape == (1, 32, 32)
    print("OK", cam.renderer, int(rgb.std() > 10), float(depth.min()), float(depth.max()))
    rend.close()
""")


def test_egl_path_renders_in_a_subprocess():
    """The EGL code path (Mesa's software EGL where no GPU is present), isolated in a subprocess:
    pybullet's EGL plugin can crash the whole process on a broken driver setup."""
    try:
        out = subprocess.run([sys.executable, "-c", _EGL_SCRIPT], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.skip("software EGL too slow here")
    if out.returncode != 0 or "UNAVAILABLE" in out.stdout:
        pytest.skip(f"no working EGL here (exit {out.returncode})")
    line = next(ln for ln in out.stdout.splitlines() if ln.startswith("OK"))
    _, name, textured, dmin, dmax = line.split()
    assert name == "egl" and textured == "1"
    assert 0.1 <= float(dmin) < 5.0 and float(dmax) == pytest.approx(300.0)


def test_a_horizontal_field_spreads_the_rows_over_less_angle(oval_scene):
    """hfov_deg: a box 30 deg left of the axis lands in the column the horizontal field predicts; with the vertical field
    halved (60 -> 30 deg) at the same horizontal field, the ground 20 m ahead sits ~2x as many rows below the horizon.
    pitch_deg replaces the mount's tilt. Out-of-range fields or tilts fail with one line."""
    cid, track, world = oval_scene
    cam = Camera(cid, 96, 64, fov_deg=30.0, hfov_deg=81.0, pitch_deg=0.0, worlds=[world], renderer="tiny")
    assert cam.hfov_deg == pytest.approx(81.0) and cam.mount.pitch_deg == 0.0
    pos, yaw = _pose(track, 120.0)
    eye, rc = cam.camera_pose(pos, yaw)
    ang = math.radians(30.0)
    center = eye + 15.0 * (rc[:, 0] * math.cos(ang) + rc[:, 1] * math.sin(ang))  # 15 m away, 30 deg to the left, eye height
    vs = p.createVisualShape(p.GEOM_BOX, halfExtents=[0.3] * 3, rgbaColor=[0.1, 0.2, 0.9, 1], physicsClientId=cid)
    box = p.createMultiBody(0, -1, vs, basePosition=center.tolist(), physicsClientId=cid)
    try:
        rgb, _ = cam.render(pos, yaw)
    finally:
        p.removeBody(box, physicsClientId=cid)
    blue = (rgb[2] > 150) & (rgb[0] < 100)
    col = 0.5 * 96 * (1.0 - math.tan(ang) / math.tan(math.radians(40.5)))
    assert blue.any() and abs(np.nonzero(blue)[1].mean() - col) < 1.5
    # the ground 20 m ahead: its row below the horizon (pitch 0: the middle row) with 60 and 30 deg down, 81 across
    dip = eye[2] / 20.0  # tangent of the angle below the horizon
    for vfov in (60.0, 30.0):
        c = Camera(cid, 96, 64, fov_deg=vfov, hfov_deg=81.0, pitch_deg=0.0, worlds=[world], renderer="tiny")
        depth = c.render(pos, yaw)[1][0, :, 48]
        measured = int(np.argmax(depth < 20.0)) - 32  # first row nearer than 20 m, counted from the horizon
        assert abs(measured - 32 * dip / math.tan(math.radians(vfov / 2.0))) <= 1.0, (vfov, measured)
    assert Camera(cid, 96, 64, fov_deg=60.0, renderer="tiny").hfov_deg == pytest.approx(81.8, abs=0.1)  # square pixels
    with pytest.raises(ValueError, match=r"hfov_deg must lie in \[1, 170\] or be null"):
        Camera(cid, 96, 64, hfov_deg=180.0, renderer="tiny")
    with pytest.raises(ValueError, match=r"pitch_deg must lie in \[-30, 90\]"):
        Camera(cid, 96, 64, pitch_deg=-45.0, renderer="tiny")


def test_bad_names_raise_listing_the_choices(client):
    with pytest.raises(ValueError, match="hood, chase, top"):
        Camera(client, 84, 84, mount="roof")
    with pytest.raises(ValueError, match="auto, tiny, egl"):
        Camera(client, 84, 84, renderer="opengl")
    with pytest.raises(ValueError):
        Camera(client, 84, 84, near=10.0, far=1.0)


def test_mounts_see_the_car_only_from_outside(client):
    """Chase and top views show the (red) chassis; the hood view does not."""
    vehicle = pytest.importorskip("torcsrl.envs.vehicle")
    ground = vehicle.make_ground(client)
    fleet = vehicle.CarFleet(client, 1)
    track = tracks.load("oval")
    world = build_world(client, track, ground_body=ground, style=WorldStyle(post_spacing_m=0, tree_spacing_m=0))
    xy = track.to_world(150.0, 0.0)
    yaw = float(track.heading(150.0))
    fleet.reset([0], xy[None], [yaw])
    red = {}
    for mount in MOUNTS:
        cam = Camera(client, 64, 64, mount=mount, worlds=[world], renderer="tiny", vehicle=fleet.params)
        rgb, _ = cam.render(fleet.pos[0], rot=fleet.rotation[0])
        r, g, b = rgb.astype(int)
        red[mount] = float(((r > 150) & (g < 60) & (b < 60)).mean())
    assert red["hood"] < 0.005
    assert red["chase"] > 0.03 and red["top"] > 0.001


def test_custom_mount_and_vehicle_fit(client):
    cam = Camera(client, 16, 16, mount=Mount("roof", (0.0, 0.0, 1.0), 5.0), renderer="tiny")
    assert cam.mount.name == "roof"
    eye, rc = cam.camera_pose([1.0, 2.0, 0.5], 0.0)
    np.testing.assert_allclose(eye, [1.0, 2.0, 1.5])
    assert rc[2, 0] < 0  # pitched down


# ---------------------------------------------------------------- the world's bodies
def test_world_bodies_are_visual_only(client):
    track = tracks.load("oval")
    world = build_world(client, track, style=WorldStyle(road_meshes=True))
    assert world.num_triangles > 0 and len(world.bodies) > 0
    for b in world.bodies:
        assert p.getCollisionShapeData(b, -1, physicsClientId=client) == ()
    xy = track.to_world(np.array([10.0, 400.0, 800.0]), 0.0)
    hits = p.rayTestBatch([[x, y, 5.0] for x, y in xy], [[x, y, -1.0] for x, y in xy], physicsClientId=client)
    assert all(h[0] == -1 for h in hits)  # nothing to hit: the road is not a collider


def test_ground_raster_matches_the_track(oval_scene):
    _, track, world = oval_scene
    s = np.linspace(0, track.length, 200, endpoint=False)
    on = world.to_world(s, 0.0)
    off = world.to_world(s, track.width(s)[0] + 5.0)
    mat_on = world.ground.lookup(on[:, 0], on[:, 1])
    mat_off = world.ground.lookup(off[:, 0], off[:, 1])
    assert set(mat_on.tolist()) == {FLAT_MATERIALS.index("road:asphalt")} or \
        (mat_on == FLAT_MATERIALS.index("road:asphalt")).mean() > 0.99
    assert (mat_off == 0).all()


# ---------------------------------------------------------------- the env adapter
class _FakeFleet:
    def __init__(self, pos, yaw):
        self.pos = np.asarray(pos, dtype=np.float64)
        self.rotation = euler_to_matrix(np.asarray(yaw, dtype=np.float64))
        self.params = None


class _FakeSim:
    """What CarCameras reads from the race core."""

    def __init__(self, geometry, car_tracks, slot, pos, yaw, sensors=("pixels", "depth")):
        self.sensors = sensors
        self._geometry = geometry
        self.car_tracks = car_tracks
        self.slot = np.asarray(slot)
        self.steps = np.zeros(len(slot), dtype=np.int64)
        self.fleet = _FakeFleet(pos, yaw)


def test_car_cameras_render_each_car_on_its_own_track_and_surface(client):
    from torcsrl.envs.camera import CarCameras

    oval, hairpins = tracks.load("oval"), tracks.load("hairpins")
    geometry = [oval, hairpins]
    iced = oval.with_surface("ice")
    s = 200.0
    xy_o, xy_h = oval.to_world(s, 0.0), hairpins.to_world(100.0, 0.0)  # each in its track's own frame
    pos = [[xy_o[0], xy_o[1], Z_COM], [xy_o[0], xy_o[1], Z_COM], [xy_h[0], xy_h[1], Z_COM]]
    yaw = [float(oval.heading(s)), float(oval.heading(s)), float(hairpins.heading(100.0))]
    sim = _FakeSim(geometry, [oval, iced, hairpins], [0, 0, 1], pos, yaw, sensors=("pixels",))
    cams = CarCameras(client, sim, width=48, height=48, renderer="tiny")
    assert cams.shapes == {"pixels": (3, 48, 48)}
    obs = cams.render()
    assert set(obs) == {"pixels"} and obs["pixels"].shape == (3, 3, 48, 48)
    asphalt, ice, other = (_lower_middle_mean(obs["pixels"][i]) for i in range(3))
    assert np.abs(ice - asphalt).sum() > 200  # same place, the ice variant painted pale
    np.testing.assert_allclose(cams.world(1).origin_xy, [10_000.0, 0.0])
    assert np.abs(other - asphalt).sum() < 30  # car 2 sees its own (asphalt) road 10 km away
    # the same frame as a plain camera placed at the shifted pose on world 1
    cam = Camera(client, 48, 48, renderer="tiny", worlds=list(cams._worlds.values()))
    ref, _ = cam.render([xy_h[0] + 10_000.0, xy_h[1], Z_COM], yaw[2])
    np.testing.assert_array_equal(obs["pixels"][2], ref)


def test_only_the_worlds_in_use_stay_built_so_physics_does_not_slow_down():
    """Every built world's decor costs each physics step (pybullet steps every body of the client), so a car
    that changes track leaves at most ``max_worlds`` worlds behind, and the body count stays bounded."""
    import torch

    from torcsrl.envs import make_env

    env = make_env(track=["oval", "hairpins", "kidney", "esses"], sensors=("pixels",), camera={"height": 24, "width": 32},
                   seed=0, max_steps=3)
    core = env.core
    try:
        counts, tracks = [], set()
        for _ in range(8):
            td = env.reset()
            td = env.step(td.set("action", torch.tensor([0.0, 0.3])))["next"]
            assert td["pixels"].float().std() > 1.0
            tracks.add(core.car_tracks[0].name)
            assert len(core.camera._worlds) == 1  # the default: only the world the car drives
            counts.append(p.getNumBodies(physicsClientId=core.client))
        assert len(tracks) >= 2 and max(counts) - min(counts) < 400  # a world is ~60-130 bodies; without eviction 4 worlds pile up
    finally:
        env.close()
    env = make_env(track=["oval", "hairpins"], sensors=("pixels",), camera={"height": 24, "width": 32, "max_worlds": 2}, seed=0, max_steps=3)
    try:
        for _ in range(6):
            env.reset()
            env.step(env.reset().set("action", torch.tensor([0.0, 0.3])))
        assert len(env.core.camera._worlds) == len({t.name for t in env.core._geometry}) == 2  # both kept when allowed
    finally:
        env.close()
    with pytest.raises(ValueError, match="max_worlds"):
        make_env(track="oval", sensors=("pixels",), camera={"max_worlds": 0})
