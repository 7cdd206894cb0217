"""Camera sensor: off-screen RGB and depth images from a camera mounted on a car.

A :class:`Camera` renders what a camera fixed to a car's chassis sees of the visual world built by
:func:`torcsrl.envs.world.build_world` (and of every other visible body in the client: other cars on
the same track included). It returns clean readings — degradations are transforms:

* ``rgb``: ``uint8 [3, H, W]``;
* ``depth``: ``float32 [1, H, W]`` [m], the distance along the camera's optical axis (z-depth, not
  the ray length), linearised from the renderer's z-buffer with the near/far planes. Sky and
  anything beyond the far plane read ``far``.

Typical use (one pybullet client per env)::

    cid = p.connect(p.DIRECT)
    cam = Camera(cid, 84, 84, mount="hood")            # first, if EGL may be used (see below)
    ground = vehicle.make_ground(cid); fleet = vehicle.CarFleet(cid, n)
    world = build_world(cid, track, origin_xy=(0, 0), ground_body=ground)
    cam.add_world(world)
    rgb, depth = cam.observe(fleet.pos, rot=fleet.rotation, reset=done_mask)   # [N,3,H,W], [N,1,H,W]

How a frame is made: the renderer draws the 3-D objects (posts, trees, gantry, cars); then, where
it drew nothing, the flat ground (road map by surface, lines, kerbs; grass with a chequer that
fades out before it aliases), the sky and a mountain skyline are painted per pixel in numpy with an
exact ray / ground-plane intersection — so the ground has exact depth and costs a few dozen numpy
calls instead of the renderer's slow fill. Before each frame the camera hides the worlds' object
chunks it cannot see (and whole worlds far away).

Mounts (:data:`MOUNTS`; offsets in the chassis frame, x forward, y left, z up, from the centre of
mass): ``hood`` (default: on the bonnet, 1.07 m above the ground, pitched 8° down, rigidly following
the chassis' roll and pitch; the bonnet itself stays out of view), ``chase`` (behind and above, yaw
only) and ``top`` (60 m up, looking straight down, the car's heading pointing up the image). With a
``vehicle`` (``VehicleParams``) the hood and chase positions are derived from the chassis box.

Renderers: ``"tiny"`` is pybullet's TinyRenderer on the CPU (always available); ``"egl"`` is
pybullet's EGL plugin with hardware OpenGL (needs a GPU); ``"auto"`` picks EGL when a GPU device is
present and no body exists yet in the client, else tiny. The choice is logged. No display is ever
opened. **EGL caveats**: the plugin only draws bodies created after it is loaded, so create the
Camera (or call :func:`setup_renderer`) right after ``p.connect`` — before the ground, the cars and
the world; and with the plugin loaded pybullet crashes (segfault, pybullet 3.2.7) on a body whose
collision shape is a ``GEOM_PLANE`` without a visual shape — give the ground plane a visual shape.
Asking for ``"egl"`` without a GPU raises :class:`RendererUnavailable`. EGL frames match tiny ones in
geometry but not exactly in shading. Measured on an H200 (2026-11-26, ``benchmarks/gpu/``, hood camera on
hairpins): mean |tiny − egl| 2.3–4.0 grey levels, most of it thin objects on the horizon shifted by about a
pixel; depth differs by a median 1.2–1.6 % per pixel (half-pixel sampling: tiny samples pixel corners,
OpenGL centres); EGL adds a specular highlight on cars (it ignores ``lightSpecularCoeff=0``). At these
sizes EGL is slower than tiny (96x64: 615 vs 1160 frames/s on one thread): its fixed cost per frame wins.

Frame rate: :meth:`Camera.observe` renders each car every ``every`` calls and holds its last frame
in between; :meth:`Camera.render` / :meth:`Camera.render_batch` always render.

Pose conventions: ``render(pos, yaw, pitch, roll)`` takes the chassis pose (centre of mass, world
frame) with pybullet's Euler convention (``p.getEulerFromQuaternion``: R = Rz(yaw)·Ry(pitch)·Rx(roll);
since y points left, positive pitch is nose DOWN). ``rot`` (``[3, 3]`` body→world, e.g.
``CarFleet.rotation[i]``) can be given instead.
"""

from __future__ import annotations

import glob
import logging
import math
import pkgutil
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from torcsrl.utils.bullet import pybullet as p

from torcsrl.envs import surfaces as _surf
from torcsrl.envs.world import (
    FLAT_MATERIALS,
    PALETTE,
    GroundRaster,
    World,
    WorldStyle,
    build_world,
    flat_colors,
    hide_ground_planes,
    track_origin,
)

__all__ = [
    "Camera",
    "CarCameras",
    "Mount",
    "MOUNTS",
    "RENDERERS",
    "Renderer",
    "RendererUnavailable",
    "setup_renderer",
    "gpu_available",
    "mount_for",
    "build_world",
    "World",
    "WorldStyle",
]

log = logging.getLogger(__name__)

#: Accepted ``renderer`` names.
RENDERERS: tuple[str, ...] = ("auto", "tiny", "egl")


class RendererUnavailable(RuntimeError):
    """The requested renderer cannot run here (e.g. ``"egl"`` without a GPU)."""


# ---------------------------------------------------------------------------------------------
# Mounts
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mount:
    """Where a camera sits on the car.

    Attributes:
        name: mount name.
        offset: camera position in the chassis frame (x forward, y left, z up) [m], from the
            centre of mass.
        pitch_deg: camera tilt below the chassis' x axis [deg] (90 looks straight down).
        follow_attitude: True: the camera follows the chassis' roll and pitch (rigid mount);
            False: yaw only (a stabilised chase or map camera).
    """

    name: str
    offset: tuple[float, float, float]
    pitch_deg: float = 0.0
    follow_attitude: bool = True


#: Mounts for the default car (4.5 m box, front 2.15 m ahead of the centre of mass, top 0.12 m above it).
MOUNTS: dict[str, Mount] = {
    "hood": Mount("hood", (1.55, 0.0, 0.62), pitch_deg=8.0, follow_attitude=True),
    "chase": Mount("chase", (-6.85, 0.0, 2.12), pitch_deg=11.0, follow_attitude=False),
    "top": Mount("top", (15.0, 0.0, 60.0), pitch_deg=90.0, follow_attitude=False),
}


def mount_for(mount: str | Mount, vehicle: Any = None) -> Mount:
    """The :class:`Mount` called ``mount`` (or ``mount`` itself), fitted to ``vehicle``'s chassis box
    when given (any object with ``VehicleParams``' ``cg_to_front_axle``, ``front_overhang``,
    ``length``, ``ground_clearance``, ``height`` and ``cg_height``).

    Raises:
        ValueError: unknown mount name (the message lists the allowed mounts).
    """
    if isinstance(mount, Mount):
        return mount
    if mount not in MOUNTS:
        raise ValueError(f"unknown camera mount {mount!r}; allowed mounts: {', '.join(MOUNTS)}")
    m = MOUNTS[mount]
    if vehicle is None:
        return m
    front = vehicle.cg_to_front_axle + vehicle.front_overhang  # [m] box front ahead of the COM
    top = vehicle.ground_clearance + vehicle.height - vehicle.cg_height  # [m] box top above the COM
    if mount == "hood":
        return replace(m, offset=(front - 0.6, 0.0, top + 0.5))
    if mount == "chase":
        return replace(m, offset=(front - vehicle.length - 4.5, 0.0, top + 2.0))
    return m


# ---------------------------------------------------------------------------------------------
# Renderers
# ---------------------------------------------------------------------------------------------
def gpu_available() -> bool:
    """True when a GPU device node is present (NVIDIA, or a DRM render node)."""
    return bool(glob.glob("/dev/nvidia[0-9]*") or glob.glob("/dev/dri/renderD*"))


@dataclass
class Renderer:
    """A renderer set up on one pybullet client (see :func:`setup_renderer`).

    Attributes:
        name: ``"tiny"`` or ``"egl"``.
        flag: the ``renderer=`` argument of ``p.getCameraImage``.
        client_id: the pybullet client.
        plugin_id: the EGL plugin's id (-1 for tiny).
    """

    name: str
    flag: int
    client_id: int
    plugin_id: int = -1

    def close(self) -> None:
        """Unload the EGL plugin (no-op for tiny or when the client is gone)."""
        if self.plugin_id >= 0:
            try:
                p.unloadPlugin(self.plugin_id, physicsClientId=self.client_id)
            except p.error:
                pass
            self.plugin_id = -1


def setup_renderer(client_id: int, renderer: str = "auto", allow_software_egl: bool = False) -> Renderer:
    """Choose and set up the renderer of client ``client_id``; the choice is logged.

    Args:
        client_id: pybullet client (``p.DIRECT``; no display is used).
        renderer: ``"auto"`` (EGL when a GPU is present and the client has no bodies yet, else
            tiny), ``"tiny"`` (CPU TinyRenderer) or ``"egl"`` (EGL plugin, hardware OpenGL).
        allow_software_egl: let ``"egl"`` run without a GPU (Mesa's llvmpipe: slow; for tests).

    Raises:
        ValueError: unknown renderer name.
        RendererUnavailable: ``"egl"`` without a GPU, with bodies already in the client (the plugin
            would not draw them), or when the plugin fails to load.
    """
    if renderer not in RENDERERS:
        raise ValueError(f"unknown renderer {renderer!r}; allowed: {', '.join(RENDERERS)}")
    cid = int(client_id)
    tiny = Renderer("tiny", p.ER_TINY_RENDERER, cid)
    if renderer == "tiny":
        log.info("camera renderer: tiny (pybullet TinyRenderer on the CPU; requested)")
        return tiny
    gpu = gpu_available()
    n_bodies = p.getNumBodies(physicsClientId=cid)
    problem = None
    if not gpu and not (renderer == "egl" and allow_software_egl):
        problem = "no GPU device found (/dev/nvidia*, /dev/dri/renderD*)"
    elif n_bodies > 0:
        problem = (f"the client already has {n_bodies} bodies, which the EGL plugin would not draw; "
                   "create the Camera (or call setup_renderer) right after p.connect")
    loader = pkgutil.get_loader("eglRenderer") if problem is None else None
    if problem is None and loader is None:
        problem = "pybullet's eglRenderer plugin is not installed"
    plugin = -1
    if problem is None:
        plugin = p.loadPlugin(loader.get_filename(), "_eglRendererPlugin", physicsClientId=cid)
        if plugin < 0:
            problem = "loading pybullet's eglRenderer plugin failed"
    if problem is not None:
        if renderer == "egl":
            raise RendererUnavailable(f"renderer='egl' is not available: {problem}. "
                                      "Use renderer='tiny' (CPU) or 'auto' (picks EGL only where it works).")
        log.info("camera renderer: tiny (pybullet TinyRenderer on the CPU; auto: %s)", problem)
        return tiny
    log.info("camera renderer: egl (pybullet EGL plugin, hardware OpenGL; %s)", renderer)
    return Renderer("egl", p.ER_BULLET_HARDWARE_OPENGL, cid, plugin)


# ---------------------------------------------------------------------------------------------
# Rotations
# ---------------------------------------------------------------------------------------------
def euler_to_matrix(yaw, pitch=0.0, roll=0.0) -> np.ndarray:
    """Body→world rotation(s) ``[..., 3, 3]`` from pybullet Euler angles: Rz(yaw)·Ry(pitch)·Rx(roll)."""
    yaw, pitch, roll = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (yaw, pitch, roll)))
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def _euler(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Scalar :func:`euler_to_matrix` (plain floats: much faster for one pose)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


# ---------------------------------------------------------------------------------------------
# The camera
# ---------------------------------------------------------------------------------------------
class Camera:
    """Off-screen RGB + depth camera on a car (see the module docstring).

    Args:
        client_id: pybullet client the car and the world live in.
        width, height: image size [px].
        fov_deg: vertical field of view [deg].
        mount: ``"hood"`` | ``"chase"`` | ``"top"`` or a :class:`Mount`.
        hfov_deg: horizontal field of view [deg]; None: square pixels (``width / height`` times the vertical
            field's tangent). With a horizontal field wider than the pixels' aspect, each row covers fewer degrees:
            e.g. 96x64 at ``fov_deg=30, hfov_deg=81`` resolves the far road with twice the rows of ``fov_deg=60``.
        pitch_deg: camera tilt below the chassis' x axis [deg], replacing the mount's (hood: 8).
        renderer: ``"auto"`` | ``"tiny"`` | ``"egl"``, or a :class:`Renderer` already set up on
            this client (cameras of one client can share it).
        near, far: clip planes [m]; depth readings lie in [near, far].
        every: :meth:`observe` renders every ``every``-th call per car and holds the frame between.
        worlds: the worlds (:func:`build_world`) in this client: culled before each frame, and the
            nearest one's ground map painted. More can be added with :meth:`add_world`. A world
            not attached is drawn whole (slower) and its ground is not painted (grass only).
        draw_distance: 3-D objects (posts, trees) farther than this [m] are hidden (default:
            150 m or ``far``; at 84 px a post 150 m away is a fifth of a pixel). The painted
            ground is not affected: it reaches the far plane.
        vehicle: ``VehicleParams`` to fit the hood and chase mounts to the chassis box.
        background: paint the ground map, grass, sky and skyline where nothing was drawn (else
            the renderer's own background colour stays).
        cull: hide the worlds' chunks the camera cannot see before each frame (same image, faster).

    Raises:
        ValueError: unknown mount or renderer, or a bad size / field of view / clip plane.
        RendererUnavailable: see :func:`setup_renderer`.
    """

    def __init__(self, client_id: int, width: int = 84, height: int = 84, fov_deg: float = 60.0,
                 mount: str | Mount = "hood", renderer: str | Renderer = "auto", near: float = 0.1,
                 far: float = 300.0, every: int = 1, worlds: Sequence[World] = (), draw_distance: float | None = None,
                 vehicle: Any = None, background: bool = True, cull: bool = True, hfov_deg: float | None = None,
                 pitch_deg: float | None = None) -> None:
        self.mount = mount_for(mount, vehicle)  # validates the name first
        if pitch_deg is not None:
            if not -30.0 <= pitch_deg <= 90.0:
                raise ValueError(f"pitch_deg must lie in [-30, 90] (tilt below the chassis' x axis), got {pitch_deg}")
            self.mount = replace(self.mount, pitch_deg=float(pitch_deg))
        if hfov_deg is not None and not 1.0 <= hfov_deg <= 170.0:
            raise ValueError(f"hfov_deg must lie in [1, 170] or be null (square pixels), got {hfov_deg}")
        if int(width) != width or int(height) != height or width < 1 or height < 1:
            raise ValueError(f"width and height must be positive integers, got {width}x{height}")
        if not 1.0 <= fov_deg <= 170.0:
            raise ValueError(f"fov_deg must lie in [1, 170], got {fov_deg}")
        if not 0.0 < near < far:
            raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
        if int(every) != every or every < 1:
            raise ValueError(f"every must be a positive integer, got {every}")
        self.client = int(client_id)
        self.width, self.height = int(width), int(height)
        self.fov_deg, self.near, self.far = float(fov_deg), float(near), float(far)
        self.every = int(every)
        self.draw_distance = float(draw_distance) if draw_distance is not None else min(self.far, 150.0)
        self.background = bool(background)
        self.cull = bool(cull)
        if isinstance(renderer, Renderer):
            self._renderer, self._owns_renderer = renderer, False
        else:
            self._renderer, self._owns_renderer = setup_renderer(self.client, renderer), True
        self.worlds: list[World] = list(worlds)
        # square pixels unless a horizontal field is given (then a pixel spans more degrees across than down: the
        # rows go to the distance, where the road narrows into few of them, while both road edges stay in view)
        aspect = self.width / self.height if hfov_deg is None else \
            math.tan(math.radians(hfov_deg) / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)
        self.square_pixels = hfov_deg is None
        self.hfov_deg = math.degrees(2.0 * math.atan(math.tan(math.radians(self.fov_deg) / 2.0) * aspect))
        self._proj = p.computeProjectionMatrixFOV(self.fov_deg, aspect, self.near, self.far)
        tan_v = math.tan(math.radians(self.fov_deg) / 2.0)
        tan_h = tan_v * aspect
        # culling cone: the image diagonal (covers any roll) plus a margin
        self._cull_half_angle = math.atan(math.hypot(tan_h, tan_v)) + math.radians(5.0)
        # pixel rays in the camera's (forward, left, up) frame, forward component 1 (so the ray
        # parameter at a hit is its z-depth)
        # where each renderer samples pixel (row i, column j): TinyRenderer at the integer corner
        # (x = j, y = H - 1 - i from the bottom; measured), OpenGL at pixel centres
        jx, iy = (0.0, 1.0) if self._renderer.name == "tiny" else (0.5, 0.5)
        xs = (2.0 * (np.arange(self.width) + jx) / self.width - 1.0) * tan_h
        ys = (1.0 - 2.0 * (np.arange(self.height) + iy) / self.height) * tan_v
        left = np.broadcast_to(-xs[None, :], (self.height, self.width))
        up = np.broadcast_to(ys[:, None], (self.height, self.width))
        self._rays = np.stack([np.ones((self.height, self.width)), left, up]).reshape(3, -1)  # [3, HW]
        pitch = math.radians(self.mount.pitch_deg)
        self._mount_rot = _euler(0.0, pitch, 0.0)
        self._mount_off = np.asarray(self.mount.offset, dtype=np.float64)
        self._light = dict(shadow=0, lightDirection=[-0.4, -0.3, 1.0], lightAmbientCoeff=0.6, lightDiffuseCoeff=0.4,
                           lightSpecularCoeff=0.0)
        self._painter = _Painter(self)
        self._remap_cache: dict[str, np.ndarray] = {}
        self._held: tuple[np.ndarray, np.ndarray] | None = None
        self._count: np.ndarray | None = None
        log.info("camera: %dx%d, fov %.0f x %.0f deg, mount %s (pitch %.0f deg), renderer %s, near %.2f m, far %.0f m, every %d",
                 self.width, self.height, self.hfov_deg, self.fov_deg, self.mount.name, self.mount.pitch_deg, self.renderer, self.near,
                 self.far, self.every)

    # ---- info ----------------------------------------------------------------------------------
    @property
    def renderer(self) -> str:
        """The renderer in use: ``"tiny"`` or ``"egl"``."""
        return self._renderer.name

    @property
    def shape_rgb(self) -> tuple[int, int, int]:
        """``(3, H, W)``."""
        return (3, self.height, self.width)

    @property
    def shape_depth(self) -> tuple[int, int, int]:
        """``(1, H, W)``."""
        return (1, self.height, self.width)

    def add_world(self, world: World) -> None:
        """Cull ``world`` before every frame from now on."""
        if world.client_id != self.client:
            raise ValueError(f"world lives in client {world.client_id}, the camera in client {self.client}")
        self.worlds.append(world)

    # ---- poses ---------------------------------------------------------------------------------
    def camera_pose(self, pos, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0,
                    rot: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Eye position ``[3]`` and camera rotation ``[3, 3]`` (columns: forward, left, up; world
        frame) for a chassis pose (see :meth:`render`)."""
        pos = np.asarray(pos, dtype=np.float64).reshape(3)
        if rot is None:
            r = _euler(float(yaw), float(pitch), float(roll))
        else:
            r = np.asarray(rot, dtype=np.float64).reshape(3, 3)
        if not self.mount.follow_attitude:
            r = _euler(math.atan2(r[1, 0], r[0, 0]), 0.0, 0.0)
        return pos + r @ self._mount_off, r @ self._mount_rot

    @staticmethod
    def _view_matrix(eye: np.ndarray, rc: np.ndarray) -> list[float]:
        """OpenGL view matrix (column-major) of an eye with axes ``rc`` (forward, left, up)."""
        # eye axes: x right (= -left), y up, z backwards (= -forward)
        (fx, lx, ux), (fy, ly, uy), (fz, lz, uz) = rc.tolist()
        ex, ey, ez = eye.tolist()
        return [-lx, ux, -fx, 0.0,
                -ly, uy, -fy, 0.0,
                -lz, uz, -fz, 0.0,
                lx * ex + ly * ey + lz * ez, -(ux * ex + uy * ey + uz * ez), fx * ex + fy * ey + fz * ez, 1.0]

    # ---- rendering -----------------------------------------------------------------------------
    def render(self, pos, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0,
               rot: np.ndarray | None = None, surface: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render one frame from the chassis pose ``pos [3]`` (centre of mass, world) and
        ``yaw/pitch/roll`` [rad] (or ``rot [3, 3]`` body→world). ``surface``: paint every road
        of the ground map as this surface (a track's ``with_surface`` variant; None: as built).

        Returns:
            ``(rgb uint8 [3, H, W], depth float32 [1, H, W] [m])``, new arrays.
        """
        eye, rc = self.camera_pose(pos, yaw, pitch, roll, rot)
        return self._render_eye(eye, rc, self._remap(surface))

    def render_batch(self, pos, yaw=None, rot=None, pitch=None, roll=None,
                     surface: str | Sequence[str | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render one frame per car: ``pos [N, 3]`` with ``yaw [N]`` (optionally ``pitch, roll [N]``)
        or ``rot [N, 3, 3]``; ``surface`` one for all or one per car (see :meth:`render`).
        Returns ``(rgb uint8 [N, 3, H, W], depth float32 [N, 1, H, W])``."""
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        n = len(pos)
        rots = self._rotations(n, yaw, rot, pitch, roll)
        remaps = self._remaps(n, surface)
        rgb = np.empty((n, 3, self.height, self.width), dtype=np.uint8)
        depth = np.empty((n, 1, self.height, self.width), dtype=np.float32)
        for i in range(n):
            eye, rc = self.camera_pose(pos[i], rot=rots[i])
            rgb[i], depth[i] = self._render_eye(eye, rc, remaps[i])
        return rgb, depth

    def get_state(self) -> dict | None:
        """The frame-rate state of :meth:`observe` (held frames and per-car call counts), or None before
        the first call: with ``every > 1`` an exact resume needs it (the held frame is what the car sees)."""
        if self._held is None:
            return None
        return {"rgb": self._held[0].copy(), "depth": self._held[1].copy(), "count": self._count.copy()}

    def set_state(self, state: dict | None) -> None:
        """Restore :meth:`get_state`."""
        if state is None:
            self._held = None
            return
        self._held = (np.array(state["rgb"], dtype=np.uint8, copy=True), np.array(state["depth"], dtype=np.float32, copy=True))
        self._count = np.array(state["count"], dtype=np.int64, copy=True)

    def observe(self, pos, yaw=None, rot=None, reset=None, pitch=None, roll=None,
                surface: str | Sequence[str | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`render_batch`, at the camera's frame rate: each car is rendered on every
        ``every``-th call (counted per car) and its last frame is held in between. ``reset [N]``
        (bool) restarts the count of those cars and renders them now (use it on env reset). The
        first call, or a change in N, renders every car.

        Returns:
            ``(rgb uint8 [N, 3, H, W], depth float32 [N, 1, H, W])``, new arrays.
        """
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        n = len(pos)
        if self._held is None or len(self._held[0]) != n:
            self._held = (np.zeros((n, 3, self.height, self.width), np.uint8),
                          np.zeros((n, 1, self.height, self.width), np.float32))
            self._count = np.zeros(n, dtype=np.int64)
        due = self._count % self.every == 0
        if reset is not None:
            r = np.broadcast_to(np.asarray(reset, dtype=bool).reshape(-1), (n,))
            due = due | r
            self._count[r] = 0
        if due.any():
            rots = self._rotations(n, yaw, rot, pitch, roll)
            remaps = self._remaps(n, surface)
            for i in np.flatnonzero(due).tolist():
                eye, rc = self.camera_pose(pos[i], rot=rots[i])
                self._held[0][i], self._held[1][i] = self._render_eye(eye, rc, remaps[i])
        self._count += 1
        return self._held[0].copy(), self._held[1].copy()

    def _remap(self, surface: str | None) -> np.ndarray | None:
        """Ground material map that paints every road as ``surface`` (None: identity)."""
        if surface is None:
            return None
        if surface not in self._remap_cache:
            sid = _surf.surface_id(surface)  # ValueError listing the surfaces
            if sid == _surf.GRASS_ID:
                raise ValueError(f"grass is what lies off the track; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
            m = np.arange(len(FLAT_MATERIALS), dtype=np.uint8)
            m[1:1 + len(_surf.SURFACE_NAMES)] = 1 + sid
            self._remap_cache[surface] = m
        return self._remap_cache[surface]

    def _remaps(self, n: int, surface) -> list[np.ndarray | None]:
        if surface is None or isinstance(surface, str):
            return [self._remap(surface)] * n
        surface = list(surface)
        if len(surface) != n:
            raise ValueError(f"give one surface for all cars or one per car ({n}), got {len(surface)}")
        return [self._remap(s) for s in surface]

    def _rotations(self, n: int, yaw, rot, pitch, roll) -> np.ndarray:
        if rot is not None:
            return np.asarray(rot, dtype=np.float64).reshape(n, 3, 3)
        if yaw is None:
            raise ValueError("give the cars' yaw [N] (optionally pitch, roll) or rot [N, 3, 3]")
        z = np.zeros(n)
        return euler_to_matrix(np.broadcast_to(yaw, (n,)), z if pitch is None else pitch, z if roll is None else roll)

    def _render_eye(self, eye: np.ndarray, rc: np.ndarray,
                    remap: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        ground = None
        if self.worlds:
            fx, fy = rc[0, 0], rc[1, 0]
            nf = math.hypot(fx, fy)
            if nf > 0.5:  # looking roughly horizontally: cull by distance and cone
                fwd, half = (fx / nf, fy / nf), self._cull_half_angle
            else:  # looking down: distance only
                fwd, half = None, math.pi
            dist = self.draw_distance + max(0.0, float(eye[2]))
            best = math.inf
            for w in self.worlds:
                gap = w.distance_to(eye)
                if not self.cull:
                    w.show_all()
                elif gap > dist:  # a track far away (another car's): all hidden, cheaply
                    w.hide_all()
                else:
                    w.cull(eye[:2], fwd, half, dist)
                if gap < best:  # the ground map painted is the nearest world's
                    best, ground = gap, w.ground
        out = p.getCameraImage(self.width, self.height, self._view_matrix(eye, rc), self._proj,
                               renderer=self._renderer.flag, flags=p.ER_NO_SEGMENTATION_MASK,
                               physicsClientId=self.client, **self._light)
        rgba = np.ascontiguousarray(out[2], dtype=np.uint8).reshape(-1, 4)
        zbuf = np.asarray(out[3], dtype=np.float64).reshape(-1)  # float64: exact far where zbuf is 1
        n, f = self.near, self.far
        depth = (n * f) / (f - (f - n) * zbuf)  # z-depth; zbuf 1 (nothing drawn) gives far
        if self.background:
            empty = zbuf >= 1.0 - 1e-7
            self._painter.paint(eye, rc, empty, rgba.view(np.uint32).reshape(-1), depth, ground, remap)
        rgb = rgba[:, :3].T.reshape(3, self.height, self.width).copy()
        return rgb, depth.astype(np.float32).reshape(1, self.height, self.width)

    def close(self) -> None:
        """Release the renderer if this camera set it up (unloads the EGL plugin)."""
        if self._owns_renderer:
            self._renderer.close()


class CarCameras:
    """The env's camera sensor: one :class:`Camera` looking from every car of a race simulation.

    Made by :class:`torcsrl.envs.race.RaceCore` as ``CarCameras(client, core, **camera_cfg)``; reads
    from the core, at :meth:`render` time: ``fleet`` (``pos``, ``rotation``, ``params``),
    ``sensors``, ``slot`` (track slot per car), ``car_tracks`` (each car's track, maybe a
    ``with_surface`` variant), ``_geometry`` (the base track per slot) and ``steps`` (0 right after
    a reset: forces a fresh frame). Optional ``track_origins [slots, 2]``: where the core placed each
    slot's track in the physics world.

    Worlds are built lazily, one per track slot, at ``track_origins[slot]`` or else at
    :func:`~torcsrl.envs.world.track_origin` (slot × 10 km). Without ``track_origins`` the core is
    taken to drive every car in its track's own frame; a car on slot k is then *rendered* at its
    pose shifted by slot k's origin. Slot 0's origin is (0, 0), so with one track everything is
    consistent (cars on it see each other). With several slots and no ``track_origins``, cars on
    slot 0 would also see the other slots' cars as ghosts, and cars on other slots see no car
    (their own included, in chase/top views): give the core ``track_origins`` and drive each car
    at its track's origin to fix that.

    Args:
        client_id: the core's pybullet client.
        sim: the race core (see above).
        width, height, fov_deg, mount, renderer, near, far, every, draw_distance, hfov_deg, pitch_deg: see :class:`Camera`.
        style: :class:`~torcsrl.envs.world.WorldStyle` or a mapping of its fields.
        max_worlds: visual worlds kept built besides those a car is on (least recently used removed first). Each
            world's decor costs every physics step (pybullet steps every body of the client: 313 control steps/s
            with one world, 180 with two, 15 with nine, on this CPU), so the default keeps only the worlds in use
            and rebuilds a track's world (0.3-0.7 s) when a car comes back to it.
    """

    def __init__(self, client_id: int, sim: Any, width: int = 84, height: int = 84, fov_deg: float = 60.0,
                 mount: str | Mount = "hood", renderer: str | Renderer = "auto", near: float = 0.1, far: float = 300.0,
                 every: int = 1, draw_distance: float | None = None, style: WorldStyle | dict | None = None,
                 max_worlds: int = 1, hfov_deg: float | None = None, pitch_deg: float | None = None) -> None:
        self.client = int(client_id)
        self.sim = sim
        if int(max_worlds) < 1:
            raise ValueError(f"camera max_worlds must be >= 1, got {max_worlds}")
        self.max_worlds = int(max_worlds)
        self.keys = tuple(k for k in ("pixels", "depth") if k in sim.sensors)
        hide_ground_planes(self.client)
        fleet = getattr(sim, "fleet", None)
        self.camera = Camera(self.client, width, height, fov_deg=fov_deg, mount=mount, renderer=renderer, near=near,
                             far=far, every=every, draw_distance=draw_distance,
                             vehicle=getattr(fleet, "params", None), hfov_deg=hfov_deg, pitch_deg=pitch_deg)
        self.style = style if isinstance(style, WorldStyle) or style is None else WorldStyle(**dict(style))
        self._worlds: dict[int, World] = {}
        self._surface_of: dict[int, str | None] = {}  # id(track variant) -> surface override

    @property
    def shapes(self) -> dict[str, tuple[int, int, int]]:
        """Observation shapes: ``{"pixels": (3, H, W), "depth": (1, H, W)}`` (the requested keys)."""
        out = {"pixels": self.camera.shape_rgb, "depth": self.camera.shape_depth}
        return {k: out[k] for k in self.keys}

    @property
    def far(self) -> float:
        """Largest depth reading [m]."""
        return self.camera.far

    @property
    def near(self) -> float:
        """Smallest depth reading [m]."""
        return self.camera.near

    def origin(self, slot: int) -> np.ndarray:
        """World origin ``[2]`` of track slot ``slot``."""
        origins = getattr(self.sim, "track_origins", None)
        return np.asarray(origins[slot], dtype=np.float64) if origins is not None else track_origin(slot)

    def world(self, slot: int, keep: Sequence[int] = ()) -> World:
        """The visual world of track slot ``slot``, built on first use. At most ``max_worlds`` are kept: the least
        recently used world no car drives (``keep``: the slots in use) is removed first. Decor bodies are visual
        only, but pybullet's ``stepSimulation`` still walks every body in the client, so a procedural pool of
        100 tracks with all its worlds built made each physics step ~4x slower."""
        w = self._worlds.pop(slot, None)
        if w is None:
            w = build_world(self.client, self.sim._geometry[slot], origin_xy=self.origin(slot), style=self.style)
            self.camera.add_world(w)
            for old in list(self._worlds):
                if len(self._worlds) < self.max_worlds:
                    break
                if old not in keep and old != slot:
                    gone = self._worlds.pop(old)
                    self.camera.worlds.remove(gone)
                    gone.remove()
        self._worlds[slot] = w  # most recently used last
        return w

    def _surface(self, i: int, slot: int) -> str | None:
        t = self.sim.car_tracks[i]
        key = id(t)
        if key not in self._surface_of:
            self._surface_of[key] = None if t is self.sim._geometry[slot] else t.default_surface
        return self._surface_of[key]

    def render(self) -> dict[str, np.ndarray]:
        """``{"pixels": uint8 [N, 3, H, W], "depth": float32 [N, 1, H, W]}`` (the requested keys)
        for the cars' current poses (held frames between renders when ``every`` > 1)."""
        sim = self.sim
        fleet = sim.fleet
        slots = np.asarray(sim.slot, dtype=np.int64).reshape(-1)
        pos = np.array(fleet.pos, dtype=np.float64)
        used = [int(k) for k in np.unique(slots).tolist()]
        for k in used:
            self.world(k, keep=used)
        if getattr(sim, "track_origins", None) is None:  # cars drive in their track's own frame
            pos[:, :2] += np.array([self.origin(int(k)) for k in slots.tolist()])
        surface = [self._surface(i, int(k)) for i, k in enumerate(slots.tolist())]
        steps = getattr(sim, "steps", None)
        reset = None if steps is None else (np.asarray(steps) == 0)
        rgb, depth = self.camera.observe(pos, rot=fleet.rotation, reset=reset, surface=surface)
        out = {"pixels": rgb, "depth": depth}
        return {k: out[k] for k in self.keys}

    def get_state(self) -> dict | None:
        """The camera's frame-rate state (:meth:`Camera.get_state`), for an exact resume."""
        return self.camera.get_state()

    def set_state(self, state: dict | None) -> None:
        self.camera.set_state(state)

    def close(self) -> None:
        """Release the renderer (the worlds go with the client)."""
        self.camera.close()


class _Painter:
    """Paints the ground map, grass, sky and skyline per pixel where the renderer drew nothing.

    Colours come from look-up tables of packed RGBA (``uint32``) indexed by material and distance
    bin (haze, chequer fade) or by elevation bin (sky), so a frame costs a few dozen numpy calls.
    """

    N_BINS = 64  # distance / elevation bins of the colour tables
    N_T = 1024  # linear distance steps (0 .. far) mapped onto the distance bins
    CHEQUER_M = 6.4  # [m] grass chequer tile (one raster tile at the default raster settings)
    N_FADE = 4  # chequer contrast levels
    FADE_PX = (1.0, 4.0)  # the chequer fades out as its tiles shrink from 4 to 1 pixel (no aliasing)
    CHEQUER = 0.09  # relative brightness step of the grass chequer
    ROAD_CHEQUER = 0.035  # the same on the road (faint slabs: a speed cue on the road itself)
    HAZE = 0.7  # haze fraction at the far plane
    SKY_EL_MAX = 0.6  # [rad] elevation where the sky reaches its zenith colour

    def __init__(self, cam: Camera) -> None:
        self.cam = cam
        far, nb = cam.far, self.N_BINS
        t = ((np.arange(nb) + 0.5) / nb) ** 2 * far  # distance bin centres: sqrt spacing (fine near the car)
        haze = (np.minimum(t / far, 1.0) ** 0.7 * self.HAZE)[:, None]
        horizon = np.asarray(PALETTE["sky_horizon"])
        # chequer contrast levels: the chequer fades out as its tiles shrink towards a pixel
        fade = (np.arange(self.N_FADE) / (self.N_FADE - 1))[None, :, None]
        rows = []  # two rows per material (chequer dark, light): row = 2 * material + parity
        for name, color in zip(FLAT_MATERIALS, flat_colors()):
            step = self.CHEQUER if name == "grass" else (self.ROAD_CHEQUER if name.startswith("road:") else 0.0)
            for sign in (-1.0, 1.0):
                c = color[None, None, :] * (1.0 + sign * step * fade)  # [1, fade, 3]
                rows.append(c * (1.0 - haze[:, :, None]) + horizon * haze[:, :, None])  # [nb, fade, 3]
        self.ground_lut = _pack(np.stack(rows)).reshape(-1)  # index (row * nb + distance bin) * N_FADE + fade
        # sky and mountains by elevation: bins of sin(elevation)
        el = np.arcsin((np.arange(nb) + 0.5) / nb)
        a = np.clip(el / self.SKY_EL_MAX, 0.0, 1.0)[:, None]
        self.sky_lut = _pack(horizon * (1.0 - a) + np.asarray(PALETTE["sky_zenith"]) * a)
        self.hill_lut = _pack(np.asarray(PALETTE["mountain"]) * (1.0 + 1.5 * el)[:, None])
        # skyline: mountain height above the horizon by world azimuth, as sin(elevation)
        rng = np.random.default_rng(7)
        k = np.arange(1, 9)
        amp = (0.035 / k ** 0.9) * rng.uniform(0.5, 1.0, len(k))
        phase = rng.uniform(0, 2 * np.pi, len(k))
        self.n_az = 1024
        az = np.arange(self.n_az) * (2 * np.pi / self.n_az)
        self.skyline_sin = np.sin(np.maximum(0.03 + np.sin(k[None, :] * az[:, None] + phase[None, :]) @ amp, 0.004))
        self.skyline_max = float(self.skyline_sin.max())
        self.inv_norm = 1.0 / np.sqrt((cam._rays ** 2).sum(0))  # rotation keeps ray lengths
        # a pixel's lateral ground footprint [m] is t * pix_angle; beyond 2 fine cells use the coarse level
        self.pix_angle = math.radians(cam.fov_deg) / cam.height
        if not cam.square_pixels:  # a pixel spans more degrees across than down: the wider side sets the footprint
            self.pix_angle = max(self.pix_angle, math.radians(cam.hfov_deg) / cam.width)
        # chequer tile size in pixels along the ray ~ CHEQUER_M * eye_z / (t^2 * pix_angle)
        p0, p1 = self.FADE_PX
        self._row_stride = nb * self.N_FADE
        self._cached_z = -math.inf
        self._fade_a = (self.N_FADE - 1) / (p1 - p0) * self.CHEQUER_M / self.pix_angle
        self._fade_b = (self.N_FADE - 1) / (p1 - p0) * p0

    def _distance_index(self, eye_z: float) -> np.ndarray:
        """``[N_T]`` LUT column (distance bin × fade level) per linear distance step, for an eye
        height (the chequer's fade depends on it); cached while the height stays within 1 cm."""
        if abs(eye_z - self._cached_z) > 0.01:
            t = (np.arange(self.N_T) + 0.5) * (self.cam.far / self.N_T)
            tb = np.minimum((np.sqrt(t / self.cam.far) * self.N_BINS).astype(np.int64), self.N_BINS - 1)
            # chequer tile size along the ray [px] (taking |ray| = 1) → fade level
            fb = np.minimum(np.maximum(self._fade_a * max(eye_z, 0.0) / (t * t) - self._fade_b, 0.0), self.N_FADE - 1)
            self._dist_index = tb * self.N_FADE + fb.astype(np.int64)
            self._cached_z = eye_z
        return self._dist_index

    def paint(self, eye: np.ndarray, rc: np.ndarray, empty: np.ndarray, rgba32: np.ndarray, depth: np.ndarray,
              ground: GroundRaster | None, remap: np.ndarray | None = None) -> None:
        cam, nb = self.cam, self.N_BINS
        rays = cam._rays
        ex, ey, ez = float(eye[0]), float(eye[1]), max(float(eye[2]), 0.01)  # (an eye under the ground: keep t > 0)
        dz = rc[2] @ rays
        below = dz < -1e-6
        gi = np.flatnonzero(empty & below)
        si = np.flatnonzero(empty & ~below)
        if len(gi):
            t = ez / -dz.take(gi)  # ray parameter = z-depth (the rays' forward component is 1)
            if ground is not None:
                inv = 1.0 / ground.cell
                dg = (rc[:2] * inv) @ rays.take(gi, axis=1)  # in cells per unit of t
                lin, tx, ty = ground.cell_index((ex - ground.x0) * inv + t * dg[0], (ey - ground.y0) * inv + t * dg[1])
                np.add(lin, ground.coarse_offset, out=lin, where=t > self.coarse_from(ground))
                mat = ground.take(lin) if remap is None else remap.take(ground.take(lin))
                row = (mat.astype(np.int64) << 1) | ((tx + ty) & 1)  # 2 * material + chequer parity
            else:
                inv = 1.0 / self.CHEQUER_M
                dg = (rc[:2] * inv) @ rays.take(gi, axis=1)
                row = (np.floor(ex * inv + t * dg[0]) + np.floor(ey * inv + t * dg[1])).astype(np.int64) & 1
            tq = np.minimum((t * (self.N_T / cam.far)).astype(np.int64), self.N_T - 1)
            rgba32[gi] = self.ground_lut.take(row * self._row_stride + self._distance_index(ez).take(tq))
            depth[gi] = np.minimum(t, cam.far)
        if len(si):
            sin_el = dz.take(si) * self.inv_norm.take(si)
            eb = np.minimum((sin_el * nb).astype(np.int64), nb - 1)
            col = self.sky_lut.take(eb)
            low = np.flatnonzero(sin_el < self.skyline_max)
            if len(low):
                dl = rc[:2] @ rays.take(si.take(low), axis=1)
                ab = (np.arctan2(dl[1], dl[0]) * (self.n_az / (2 * np.pi))).astype(np.int64) & (self.n_az - 1)
                hill = low[sin_el.take(low) < self.skyline_sin.take(ab)]
                col[hill] = self.hill_lut.take(eb.take(hill))
            rgba32[si] = col
            # depth there is already far (the z-buffer read 1)

    def coarse_from(self, ground: GroundRaster) -> float:
        """Distance [m] beyond which a pixel's ground footprint exceeds two fine cells."""
        return 2.0 * ground.cell / self.pix_angle


def _pack(rgb: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] ``[..., 3]`` → packed little-endian RGBA ``uint32 [...]`` (alpha 255)."""
    c = np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint32)
    return (c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16) | np.uint32(255 << 24)).astype(np.uint32)
