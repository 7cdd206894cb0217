"""The visible track world: visual-only pybullet bodies built from the track geometry.

:func:`build_world` turns a :class:`~torcsrl.envs.track.Track` into coloured meshes in a pybullet
client, for the camera (:mod:`torcsrl.envs.camera`) to render:

* the road, coloured by surface (``surfaces.COLORS``: asphalt grey, wet dark, dirt brown, ice
  pale …), with white edge lines and a white start/finish line;
* red/white kerbs on both sides of every bend tighter than ``kerb_radius_m``;
* marker posts every ``post_spacing_m`` on both sides, alternating white and red (speed cue);
* a start/finish gantry and scattered trees (parallax cues for speed and heading).

Grass, sky and the distant mountain skyline are **not** geometry: the camera paints them per
pixel where the renderer drew nothing (an exact ground plane, so grass depth is exact too). That
keeps the renderer's pixel fill — its main cost on a CPU — to the road and the roadside objects.

Every body is visual only (``baseCollisionShapeIndex = -1``): suspension rays and contacts only
ever meet the vehicle module's ground plane at z = 0. The road lies ``road_z`` (5 mm) above it.

Performance
-----------
TinyRenderer (pybullet's CPU renderer) does not cull: every triangle of every visible body is
transformed and clipped on every frame (~0.3 µs each even off screen), and each covered pixel
costs ~0.2 µs. So the world is lean — a straight is two triangles per chunk, bends are split only
where the heading turns more than ``max_turn_deg`` — and it is cut into chunks of about
``chunk_m`` of track, each chunk one body per material. :meth:`World.cull` hides (alpha 0, which
both renderers skip) the chunks that lie beyond the draw distance or outside the camera's
horizontal field of view; the camera calls it before every frame.

Several worlds may share one client: place each at its own ``origin_xy`` (e.g. 10 km apart, well
beyond the camera's far plane) so a car on one track never sees another track. Cars on the SAME
track see each other (their chassis are ordinary visible bodies).

Meshes are written as small OBJ files into a temporary folder that is deleted once the bodies are
made: pybullet's EGL renderer plugin cannot take in-memory vertex arrays.
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pybullet as p

from torcsrl.envs import surfaces as _surf
from torcsrl.envs.track import Track

__all__ = ["World", "WorldStyle", "build_world", "PALETTE"]

log = logging.getLogger(__name__)

#: Colours (RGB 0..1) of everything that is not a road surface. Road colours are ``surfaces.COLORS``.
PALETTE: dict[str, tuple[float, float, float]] = {
    "line": (0.93, 0.93, 0.93),
    "kerb_red": (0.80, 0.12, 0.10),
    "kerb_white": (0.93, 0.93, 0.93),
    "post_white": (0.96, 0.96, 0.96),
    "post_red": (0.85, 0.15, 0.10),
    "gantry": (0.20, 0.22, 0.26),
    "tree_dark": (0.10, 0.30, 0.13),
    "tree_light": (0.17, 0.40, 0.15),
    # painted by the camera (not geometry)
    "grass": tuple(float(c) for c in _surf.COLORS[_surf.GRASS_ID]),
    "sky_horizon": (0.80, 0.86, 0.92),
    "sky_zenith": (0.33, 0.53, 0.85),
    "mountain": (0.47, 0.54, 0.62),
}


@dataclass(frozen=True)
class WorldStyle:
    """Knobs of the visual world (sizes in metres).

    Attributes:
        chunk_m: track length per chunk (the unit of culling).
        max_turn_deg: road decimation: a new vertex once the heading has turned this much.
        max_segment_m: road decimation: longest straight piece inside a chunk.
        road_z: height of the road meshes above the ground plane.
        line_width_m: white edge lines, painted inside the road edges.
        start_line_m: length (along s) of the white start/finish line.
        kerb_radius_m: kerbs where the bend radius is below this.
        kerb_width_m, kerb_block_m: kerb width beyond the edge, and length of each red/white block.
        post_spacing_m, post_offset_m, post_size_m, post_height_m: marker posts, alternating
            white/red, ``post_offset_m`` beyond each edge.
        tree_spacing_m: mean spacing of trees along each side (0: no trees).
        tree_min_offset_m, tree_band_m: trees lie between ``min_offset`` and ``min_offset + band``
            beyond the edge (and never closer than ``min_offset`` to any other part of the track).
        gantry: a start/finish gantry.
    """

    chunk_m: float = 100.0
    max_turn_deg: float = 6.0
    max_segment_m: float = 100.0
    road_z: float = 0.005
    line_width_m: float = 0.2
    start_line_m: float = 0.8
    kerb_radius_m: float = 150.0
    kerb_width_m: float = 1.0
    kerb_block_m: float = 3.0
    post_spacing_m: float = 25.0
    post_offset_m: float = 2.0
    post_size_m: float = 0.25
    post_height_m: float = 1.2
    tree_spacing_m: float = 20.0
    tree_min_offset_m: float = 10.0
    tree_band_m: float = 30.0
    gantry: bool = True


@dataclass
class _Chunk:
    bodies: list[int]
    colors: list[tuple[float, float, float]]
    center: np.ndarray  # [2] world
    radius: float  # [m] horizontal bounding radius
    visible: bool = True


@dataclass
class World:
    """A track's visual bodies in one pybullet client (see :func:`build_world`).

    Attributes:
        client_id: pybullet client.
        track: the track (in its own frame).
        origin_xy: world position of the track frame's origin ``[2]`` [m].
        chunks: culling units (bodies per material).
        num_triangles: triangles in the whole world.
    """

    client_id: int
    track: Track
    origin_xy: np.ndarray
    style: WorldStyle
    chunks: list[_Chunk] = field(default_factory=list)
    num_triangles: int = 0
    _centers: np.ndarray | None = field(default=None, repr=False)
    _radii: np.ndarray | None = field(default=None, repr=False)
    _visible: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.origin_xy = np.asarray(self.origin_xy, dtype=np.float64).reshape(2)

    def _finalize(self) -> None:
        self._centers = np.array([c.center for c in self.chunks]).reshape(-1, 2)
        self._radii = np.array([c.radius for c in self.chunks])
        self._visible = np.ones(len(self.chunks), dtype=bool)

    @property
    def bodies(self) -> list[int]:
        """All body ids of this world."""
        return [b for c in self.chunks for b in c.bodies]

    def to_world(self, s, d) -> np.ndarray:
        """World position ``[..., 2]`` of track coordinates (the track frame shifted by ``origin_xy``)."""
        return self.track.to_world(s, d) + self.origin_xy

    def set_visible(self, mask: np.ndarray) -> int:
        """Show the chunks where ``mask [K]`` is True, hide the others; returns how many changed."""
        mask = np.asarray(mask, dtype=bool)
        changed = np.flatnonzero(mask != self._visible)
        cid = self.client_id
        for k in changed.tolist():
            ch = self.chunks[k]
            alpha = 1.0 if mask[k] else 0.0
            for b, col in zip(ch.bodies, ch.colors):
                p.changeVisualShape(b, -1, rgbaColor=[col[0], col[1], col[2], alpha], physicsClientId=cid)
            ch.visible = bool(mask[k])
        self._visible = mask.copy()
        return len(changed)

    def show_all(self) -> None:
        """Make every chunk visible (no culling)."""
        self.set_visible(np.ones(len(self.chunks), dtype=bool))

    def visible_mask(self, eye_xy, forward_xy=None, half_angle: float = math.pi, distance: float = 250.0) -> np.ndarray:
        """Chunks that can appear in a camera's view: within ``distance`` [m] of ``eye_xy`` and,
        when ``forward_xy`` (a horizontal unit vector) is given, inside the horizontal cone of
        ``half_angle`` [rad] around it. Conservative (bounding circles)."""
        v = self._centers - np.asarray(eye_xy, dtype=np.float64)[None, :]
        dist = np.hypot(v[:, 0], v[:, 1])
        mask = dist - self._radii < distance
        if forward_xy is not None and half_angle < math.pi * 0.5:
            f = np.asarray(forward_xy, dtype=np.float64)
            along = v @ f
            lateral = np.abs(v[:, 0] * f[1] - v[:, 1] * f[0])
            # circle vs cone: signed distance of the centre from the cone's side plane
            ca, sa = math.cos(half_angle), math.sin(half_angle)
            mask &= (lateral * ca - along * sa) < self._radii
            mask &= along > -self._radii
        return mask

    def cull(self, eye_xy, forward_xy=None, half_angle: float = math.pi, distance: float = 250.0) -> int:
        """Hide the chunks a camera at ``eye_xy`` cannot see (see :meth:`visible_mask`)."""
        return self.set_visible(self.visible_mask(eye_xy, forward_xy, half_angle, distance))

    def remove(self) -> None:
        """Remove this world's bodies from the client."""
        for b in self.bodies:
            try:
                p.removeBody(b, physicsClientId=self.client_id)
            except p.error:  # client already gone
                pass
        self.chunks = []
        self._finalize()


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------
class _Mesh:
    """Triangles of one material, collected before they become an OBJ file."""

    __slots__ = ("v", "n", "f", "nv")

    def __init__(self) -> None:
        self.v: list[np.ndarray] = []
        self.n: list[np.ndarray] = []
        self.f: list[np.ndarray] = []
        self.nv = 0

    def add(self, verts: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
        verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
        self.v.append(verts)
        self.n.append(np.broadcast_to(np.asarray(normals, dtype=np.float64).reshape(-1, 3), verts.shape))
        self.f.append(np.asarray(faces, dtype=np.int64).reshape(-1, 3) + self.nv)
        self.nv += len(verts)

    @property
    def num_triangles(self) -> int:
        return int(sum(len(f) for f in self.f))

    def write_obj(self, path: Path, offset: np.ndarray) -> None:
        v = np.concatenate(self.v) - offset[None, :]
        n = np.concatenate(self.n)
        f = np.concatenate(self.f) + 1
        lines = ["v %.4f %.4f %.4f" % tuple(r) for r in v]
        lines += ["vn %.4f %.4f %.4f" % tuple(r) for r in n]
        lines += ["f %d//%d %d//%d %d//%d" % (a, a, b, b, c, c) for a, b, c in f]
        path.write_text("\n".join(lines) + "\n")


def _strip(left: np.ndarray, right: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and up-facing (counter-clockwise from above) triangles of a strip between two
    polylines ``[k, 2]`` that run in the direction of travel (``left`` on the left)."""
    k = len(left)
    verts = np.concatenate([np.column_stack([right, np.full(k, z)]), np.column_stack([left, np.full(k, z)])])
    i = np.arange(k - 1)
    r0, r1, l0, l1 = i, i + 1, k + i, k + i + 1
    faces = np.concatenate([np.stack([r0, r1, l1], 1), np.stack([r0, l1, l0], 1)])
    return verts, faces


_BOX_FACES = np.array([  # outward, counter-clockwise; vertex index = 4*ix + 2*iy + iz
    (0, 1, 3), (0, 3, 2),  # -x
    (4, 6, 7), (4, 7, 5),  # +x
    (0, 4, 5), (0, 5, 1),  # -y
    (2, 3, 7), (2, 7, 6),  # +y
    (1, 5, 7), (1, 7, 3),  # +z (no bottom face: never seen)
])


def _boxes(center_xy: np.ndarray, yaw: np.ndarray, half: np.ndarray, z0: float, z1: float):
    """Upright boxes ``[k]`` (flat-shaded: 4 vertices per face)."""
    k = len(center_xy)
    sx = np.array([-1, -1, -1, -1, 1, 1, 1, 1], dtype=np.float64)
    sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1], dtype=np.float64)
    sz = np.array([0, 1, 0, 1, 0, 1, 0, 1], dtype=np.float64)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx, ly = sx[None, :] * half[:, 0:1], sy[None, :] * half[:, 1:2]
    corners = np.stack([center_xy[:, 0:1] + c * lx - s * ly, center_xy[:, 1:2] + s * lx + c * ly,
                        np.broadcast_to(z0 + sz * (z1 - z0), (k, 8))], axis=-1)  # [k, 8, 3]
    # per face: its own 3 vertices per triangle with the face normal (flat shading)
    tri = corners[:, _BOX_FACES.reshape(-1)]  # [k, 30, 3]
    e1 = tri[:, 1::3] - tri[:, 0::3]
    e2 = tri[:, 2::3] - tri[:, 0::3]
    nrm = np.cross(e1, e2)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    normals = np.repeat(nrm, 3, axis=1)
    verts = tri.reshape(-1, 3)
    faces = np.arange(len(verts)).reshape(-1, 3)
    return verts, normals.reshape(-1, 3), faces


def _pyramids(center_xy: np.ndarray, radius: np.ndarray, height: np.ndarray, yaw: np.ndarray):
    """Four-sided pyramids (conifers) standing on the ground, flat-shaded."""
    k = len(center_xy)
    ang = yaw[:, None] + np.arange(4)[None, :] * (np.pi / 2)
    base = np.stack([center_xy[:, 0:1] + radius[:, None] * np.cos(ang), center_xy[:, 1:2] + radius[:, None] * np.sin(ang),
                     np.zeros((k, 4))], axis=-1)  # [k, 4, 3]
    apex = np.column_stack([center_xy, height])[:, None, :]  # [k, 1, 3]
    nxt = np.roll(base, -1, axis=1)
    tri = np.stack([base, nxt, np.broadcast_to(apex, base.shape)], axis=2)  # [k, 4, 3, 3]
    nrm = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    verts = tri.reshape(-1, 3)
    normals = np.repeat(nrm.reshape(-1, 3), 3, axis=0)
    return verts, normals, np.arange(len(verts)).reshape(-1, 3)


def _decimate(track: Track, forced: np.ndarray, max_turn: float, max_seg: float) -> np.ndarray:
    """Arc lengths of the road vertices: every forced break, plus a vertex whenever the heading
    has turned ``max_turn`` [rad], a width changed by 5 cm, or ``max_seg`` [m] passed."""
    s, wl, wr = track.s, track.w_left, track.w_right
    dh = np.abs(_wrap(np.diff(track.heading_samples)))
    keep = [0.0]
    acc, last = 0.0, 0
    for i in range(1, len(s)):
        acc += dh[i - 1]
        if (acc >= max_turn or s[i] - s[last] >= max_seg or abs(wl[i] - wl[last]) > 0.05
                or abs(wr[i] - wr[last]) > 0.05):
            keep.append(s[i])
            acc, last = 0.0, i
    return np.unique(np.concatenate([np.asarray(keep), np.mod(forced, track.length)]))


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _side_offsets_ok(track: Track, s: np.ndarray, side: float, offset: np.ndarray, clearance: float) -> np.ndarray:
    """Points ``offset [k]`` beyond the ``side`` (+1 left, -1 right) edge at ``s [k]``: True where the
    offset curve does not fold on the inside of a bend and the point lies outside every other
    stretch of road by at least ``clearance`` [m]."""
    wl, wr = track.width(s)
    d = side * ((wl if side > 0 else wr) + offset)
    kappa = track.curvature(s)
    fold = (np.sign(kappa) == side) & (np.abs(d * kappa) > 0.8)
    s_p, d_p = track.project(track.to_world(s, d))
    wl_p, wr_p = track.width(s_p)
    beyond = np.where(d_p >= 0, d_p - wl_p, -d_p - wr_p)  # distance beyond the nearest road edge
    own = np.abs(track.wrap_delta(s_p, s)) < 1.0  # projects back onto its own stretch
    return ~fold & (own | (beyond > clearance))


def build_world(client_id: int, track: Track, origin_xy=(0.0, 0.0), style: WorldStyle | None = None,
                ground_body: int | None = None) -> World:
    """Build the visible world of ``track`` in pybullet client ``client_id``.

    Args:
        client_id: pybullet physics client (each env owns its own).
        track: the track, in its own frame.
        origin_xy: where the track frame's origin lies in the world [m]. Give each track of a
            shared client its own origin, far apart (e.g. 10 km): a camera sees everything within
            its far plane.
        style: sizes and densities (:class:`WorldStyle`).
        ground_body: the physics ground plane (``vehicle.make_ground``). If given, its visual is
            hidden: the camera paints the grass itself, and pybullet would otherwise draw the
            collision plane (slow, and not our colours). The plane keeps colliding.

    Returns:
        the :class:`World`; every body is visual only (no collision shape).
    """
    st = style or WorldStyle()
    cid = int(client_id)
    origin = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    world = World(cid, track, origin, st)
    if ground_body is not None:
        p.changeVisualShape(ground_body, -1, rgbaColor=[1.0, 1.0, 1.0, 0.0], physicsClientId=cid)
    L = track.length
    n_chunks = max(1, int(round(L / st.chunk_m)))
    bounds = np.linspace(0.0, L, n_chunks + 1)
    rng = np.random.default_rng(zlib.crc32(track.name.encode()) & 0xFFFFFFFF)

    # ---- road vertices (decimated), forced breaks at chunk bounds, surface changes, start line
    stretch_starts = np.array([a for a, _, _ in track.surface_stretches]) if len(track.surface_stretches) > 1 else np.zeros(0)
    forced = np.concatenate([bounds[:-1], stretch_starts, [st.start_line_m]])
    s_road = _decimate(track, forced, math.radians(st.max_turn_deg), st.max_segment_m)
    meshes: list[dict[str, _Mesh]] = [dict() for _ in range(n_chunks)]

    def mesh(k: int, name: str) -> _Mesh:
        return meshes[k].setdefault(name, _Mesh())

    up = np.array([0.0, 0.0, 1.0])
    chunk_of = lambda s: np.clip(np.searchsorted(bounds, np.mod(s, L), side="right") - 1, 0, n_chunks - 1)  # noqa: E731
    lw = st.line_width_m
    for k in range(n_chunks):
        a, b = bounds[k], bounds[k + 1]
        ss = s_road[(s_road >= a - 1e-9) & (s_road < b - 1e-9)]
        ss = np.append(ss, b)  # close the gap to the next chunk
        wl, wr = track.width(ss)
        sid = track.surface(ss[:-1] + 1e-6)
        rl = track.to_world(ss, wl - lw) + origin
        rr = track.to_world(ss, -(wr - lw)) + origin
        el = track.to_world(ss, wl) + origin
        er = track.to_world(ss, -wr) + origin
        # road quads grouped by material (surface id, or the start line)
        mat = np.array([f"road{int(i)}" for i in sid], dtype=object)
        mat[ss[:-1] < st.start_line_m - 1e-9] = "line"
        for name in dict.fromkeys(mat.tolist()):
            sel = np.flatnonzero(mat == name)
            # contiguous runs of the same material
            runs = np.split(sel, np.flatnonzero(np.diff(sel) > 1) + 1)
            for run in runs:
                idx = np.append(run, run[-1] + 1)
                v, f = _strip(rl[idx], rr[idx], st.road_z)
                mesh(k, name).add(v, up, f)
        v, f = _strip(el, rl, st.road_z)
        mesh(k, "line").add(v, up, f)
        v, f = _strip(rr, er, st.road_z)
        mesh(k, "line").add(v, up, f)

    # ---- kerbs: blocks along bends tighter than kerb_radius_m
    radius = 1.0 / np.maximum(np.abs(track.kappa), 1e-9)
    tight = radius < st.kerb_radius_m
    if tight.any():
        nblk = int(L // st.kerb_block_m)
        s0 = np.arange(nblk) * (L / nblk)
        blk = L / nblk
        # a block is kerbed where the bend is tight anywhere within ±10 m (smooth ends)
        win = np.convolve(np.concatenate([tight[-20:], tight, tight[:20]]).astype(float), np.ones(21), "same")[20:-20] > 0
        is_kerb = np.interp(np.mod(s0 + blk / 2, L), track.s, win.astype(float)) > 0.5
        for side in (1.0, -1.0):
            ok = is_kerb & _side_offsets_ok(track, s0 + blk / 2, side, np.full(nblk, st.kerb_width_m), 1.0)
            for j in np.flatnonzero(ok):
                ss = np.array([s0[j], s0[j] + blk])
                wl, wr = track.width(ss)
                w = wl if side > 0 else wr
                inner = track.to_world(ss, side * w) + origin
                outer = track.to_world(ss, side * (w + st.kerb_width_m)) + origin
                v, f = (_strip(outer, inner, st.road_z) if side > 0 else _strip(inner, outer, st.road_z))
                name = "kerb_red" if j % 2 == 0 else "kerb_white"
                mesh(int(chunk_of(s0[j] + blk / 2)), name).add(v, up, f)

    # ---- marker posts
    if st.post_spacing_m > 0:
        npost = max(1, int(round(L / st.post_spacing_m)))
        sp = np.arange(npost) * (L / npost)
        for side in (1.0, -1.0):
            ok = _side_offsets_ok(track, sp, side, np.full(npost, st.post_offset_m), 1.0)
            wl, wr = track.width(sp)
            d = side * ((wl if side > 0 else wr) + st.post_offset_m + st.post_size_m / 2)
            xy = track.to_world(sp, d) + origin
            yaw = track.heading(sp)
            half = np.full((npost, 2), st.post_size_m / 2)
            for j in np.flatnonzero(ok):
                v, nrm, f = _boxes(xy[j:j + 1], yaw[j:j + 1], half[j:j + 1], 0.0, st.post_height_m)
                name = "post_white" if j % 2 == 0 else "post_red"
                mesh(int(chunk_of(sp[j])), name).add(v, nrm, f)

    # ---- start/finish gantry
    if st.gantry:
        wl, wr = track.width(0.0)
        yaw0 = float(track.heading(0.0))
        legs = np.stack([track.to_world(0.0, wl + 1.5), track.to_world(0.0, -(wr + 1.5))]) + origin
        v, nrm, f = _boxes(legs, np.full(2, yaw0), np.full((2, 2), 0.25), 0.0, 5.5)
        mesh(0, "gantry").add(v, nrm, f)
        mid = track.to_world(0.0, 0.5 * (wl - wr)) + origin
        half = np.array([[0.3, 0.5 * (wl + wr) + 1.75]])
        v, nrm, f = _boxes(mid[None, :], np.array([yaw0]), half, 4.5, 5.5)
        mesh(0, "gantry").add(v, nrm, f)

    # ---- trees: seeded by the track name
    if st.tree_spacing_m > 0:
        for side in (1.0, -1.0):
            ntree = int(L / st.tree_spacing_m)
            s_t = np.sort(rng.uniform(0.0, L, ntree))
            off = st.tree_min_offset_m + rng.uniform(0.0, st.tree_band_m, ntree)
            ok = _side_offsets_ok(track, s_t, side, off, st.tree_min_offset_m)
            wl, wr = track.width(s_t)
            xy = track.to_world(s_t, side * ((wl if side > 0 else wr) + off)) + origin
            r = rng.uniform(1.2, 2.2, ntree)
            h = r * rng.uniform(2.5, 3.5, ntree)
            yaw = rng.uniform(0, np.pi / 2, ntree)
            shade = rng.integers(0, 2, ntree)
            for j in np.flatnonzero(ok):
                v, nrm, f = _pyramids(xy[j:j + 1], r[j:j + 1], h[j:j + 1], yaw[j:j + 1])
                mesh(int(chunk_of(s_t[j])), "tree_dark" if shade[j] else "tree_light").add(v, nrm, f)

    # ---- bodies: one per (chunk, material), meshes in chunk-local coordinates
    tmp = Path(tempfile.mkdtemp(prefix="torcsrl_world_"))
    try:
        for k in range(n_chunks):
            all_v = np.concatenate([m for ms in meshes[k].values() for m in ms.v])
            center = 0.5 * (all_v[:, :2].min(0) + all_v[:, :2].max(0))
            radius = float(np.max(np.hypot(*(all_v[:, :2] - center).T))) + 0.5
            offset = np.array([center[0], center[1], 0.0])
            ch = _Chunk([], [], center, radius)
            for name, m in meshes[k].items():
                color = (tuple(float(c) for c in _surf.COLORS[int(name[4:])]) if name.startswith("road")
                         else PALETTE[name])
                path = tmp / f"c{k}_{name}.obj"
                m.write_obj(path, offset)
                vs = p.createVisualShape(p.GEOM_MESH, fileName=str(path), rgbaColor=[*color, 1.0],
                                         specularColor=[0.0, 0.0, 0.0], physicsClientId=cid)
                if vs < 0:
                    raise RuntimeError(f"pybullet could not create the visual shape {name!r} of chunk {k}")
                body = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vs,
                                         basePosition=offset.tolist(), physicsClientId=cid)
                ch.bodies.append(body)
                ch.colors.append(color)
                world.num_triangles += m.num_triangles
            world.chunks.append(ch)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    world._finalize()
    log.info("world %r at origin (%.0f, %.0f): %d chunks, %d bodies, %d triangles", track.name, origin[0], origin[1],
             len(world.chunks), len(world.bodies), world.num_triangles)
    return world
