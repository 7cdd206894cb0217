"""The visible track world: a ground raster and visual-only pybullet bodies built from a track.

:func:`build_world` turns a :class:`~torcsrl.envs.track.Track` into what the camera
(:mod:`torcsrl.envs.camera`) draws:

* **flat ground** — the road coloured by surface (``surfaces.COLORS``: asphalt grey, wet dark,
  dirt brown, ice pale …), white edge lines, a white start/finish line, red/white kerbs on both
  sides of every bend tighter than ``kerb_radius_m`` — rasterised into a sparse tiled map
  (:class:`GroundRaster`, 0.2 m cells plus a 2 × 2 majority level for distant pixels). The camera
  paints it per pixel with an exact ray / ground-plane intersection, together with the grass
  (a distance-faded chequer that shows speed), the sky and a mountain skyline;
* **3-D objects** — marker posts every ``post_spacing_m`` on both sides (alternating white and
  red), a start/finish gantry and scattered trees (parallax cues for speed and heading) — as
  visual-only pybullet bodies that the renderer draws, in chunks along the track.

Why a raster: pybullet's CPU TinyRenderer pays for every pixel of a triangle's bounding box
(~0.1–0.2 µs each); the road alone covers half a hood camera's frame and cost more than everything
else together. The ground is a plane, so painting it from a map in numpy is exact, several times
cheaper, and has exact depth. ``WorldStyle(road_meshes=True)`` also builds the flat ground as
meshes (for other viewers, e.g. a GUI); where a mesh is drawn it wins over the painted ground.

Every body is visual only (``baseCollisionShapeIndex = -1``): suspension rays and contacts only ever
meet the vehicle module's ground plane at z = 0. Meshes lie ``road_z`` (5 mm) above it.

TinyRenderer does not cull: every triangle of every visible body costs ~0.3 µs per frame even off
screen. So the 3-D objects are cut into chunks of about ``chunk_m`` of track, one body per chunk
and colour, and :meth:`World.cull` hides (alpha 0, which both renderers skip) the chunks beyond the
draw distance or outside the camera's horizontal field of view; the camera calls it every frame.

Several worlds may share one client: give each its own ``origin_xy`` (e.g. 10 km apart, well beyond
the camera's far plane) so a car on one track never sees another. Cars on the SAME track see each
other (their chassis are ordinary visible bodies).

Meshes are written as small OBJ files into a temporary folder, deleted once the bodies exist:
pybullet's EGL renderer plugin cannot take in-memory vertex arrays.
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
from torcsrl.utils.bullet import pybullet as p

from torcsrl.envs import surfaces as _surf
from torcsrl.envs.track import Track

__all__ = ["World", "WorldStyle", "GroundRaster", "build_world", "hide_ground_planes", "track_origin", "PALETTE",
           "FLAT_MATERIALS", "flat_colors", "TRACK_SPACING_M"]

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

#: Distance between the origins of tracks sharing one client [m] (far beyond any camera's far plane).
TRACK_SPACING_M: float = 10_000.0


def track_origin(slot: int, spacing_m: float = TRACK_SPACING_M) -> np.ndarray:
    """World origin ``[2]`` [m] of the ``slot``-th track of a client: ``(slot * spacing_m, 0)``."""
    return np.array([float(slot) * spacing_m, 0.0])


def hide_ground_planes(client_id: int) -> list[int]:
    """Hide the visual of every body whose collision shape is a plane (the physics ground): the
    camera paints the ground itself, and pybullet would draw such planes slowly and in its own
    colours. They keep colliding. Returns the body ids hidden."""
    out = []
    for i in range(p.getNumBodies(physicsClientId=client_id)):
        b = p.getBodyUniqueId(i, physicsClientId=client_id)
        shapes = p.getCollisionShapeData(b, -1, physicsClientId=client_id)
        if any(s[2] == p.GEOM_PLANE for s in shapes):
            p.changeVisualShape(b, -1, rgbaColor=[1.0, 1.0, 1.0, 0.0], physicsClientId=client_id)
            out.append(b)
    return out


#: Materials of the ground raster, by id: 0 is grass (off the track), then one per surface name
#: (``1 + surface id``), then the painted marks.
FLAT_MATERIALS: tuple[str, ...] = ("grass", *(f"road:{n}" for n in _surf.SURFACE_NAMES),
                                   "line", "kerb_red", "kerb_white")
_MAT = {name: i for i, name in enumerate(FLAT_MATERIALS)}


def flat_colors() -> np.ndarray:
    """RGB (0..1) of each ground material ``[len(FLAT_MATERIALS), 3]``."""
    out = []
    for name in FLAT_MATERIALS:
        if name.startswith("road:"):
            out.append(_surf.COLORS[_surf.surface_id(name[5:])])
        else:
            out.append(PALETTE[name])
    return np.asarray(out, dtype=np.float64)


@dataclass(frozen=True)
class WorldStyle:
    """Knobs of the visual world (sizes in metres).

    Attributes:
        chunk_m: track length per chunk of 3-D objects (the unit of culling).
        max_turn_deg, max_segment_m: road polygons: a new vertex once the heading has turned
            ``max_turn_deg`` (or after ``max_segment_m``); a straight is one quad.
        raster_cell_m: ground raster cell (fine level); the coarse level has 2 × 2 of them.
        tile_shift: ground raster tiles are ``2**tile_shift`` cells square.
        raster_border_m: grass border of the raster grid around the track (cheap: one shared tile).
        road_meshes: also build the flat ground as visual meshes (slower on a CPU renderer).
        road_z: height of meshes lying on the ground.
        line_width_m: white edge lines, painted inside the road edges.
        start_line_m: length (along s) of the white start/finish line.
        kerb_radius_m: kerbs where the bend radius is below this.
        kerb_width_m, kerb_block_m: kerb width beyond the edge; length of each red/white block.
        post_spacing_m, post_offset_m, post_size_m, post_height_m: marker posts, alternating
            white/red, ``post_offset_m`` beyond each edge (0 spacing: none).
        tree_spacing_m: mean spacing of trees along each side (0: none).
        tree_min_offset_m, tree_band_m: trees stand between ``min_offset`` and ``min_offset + band``
            beyond the edge, and never closer than ``min_offset`` to any other stretch of road.
        gantry: a start/finish gantry.
        seed: extra seed for the scenery (trees); the track's name seeds it too.
    """

    chunk_m: float = 100.0
    max_turn_deg: float = 6.0
    max_segment_m: float = 100.0
    raster_cell_m: float = 0.2
    tile_shift: int = 5
    raster_border_m: float = 200.0
    road_meshes: bool = False
    road_z: float = 0.005
    line_width_m: float = 0.2
    start_line_m: float = 0.8
    kerb_radius_m: float = 150.0
    kerb_width_m: float = 1.0
    kerb_block_m: float = 3.0
    post_spacing_m: float = 25.0
    post_offset_m: float = 2.0
    post_size_m: float = 0.35
    post_height_m: float = 1.5
    tree_spacing_m: float = 20.0
    tree_min_offset_m: float = 10.0
    tree_band_m: float = 30.0
    gantry: bool = True
    seed: int = 0


# ---------------------------------------------------------------------------------------------
# Ground raster
# ---------------------------------------------------------------------------------------------
@dataclass
class GroundRaster:
    """A sparse tiled map of ground material ids (see :data:`FLAT_MATERIALS`) in the world frame.

    The grid of ``2**tile_shift`` × ``2**tile_shift``-cell tiles starts at ``(x0, y0)``; tile 0 is
    all grass and ``tile_index [TY, TX]`` maps every tile of the grid (a wide grass border all
    round) to a row of ``fine [T, C, C]`` (``cell`` metres). ``coarse`` has the same layout with
    every 2 × 2 block of cells set to its majority material: far away, where a pixel spans several
    cells, thin marks vanish instead of flickering.
    """

    x0: float
    y0: float
    cell: float
    tile_shift: int
    tile_index: np.ndarray
    fine: np.ndarray
    coarse: np.ndarray

    def __post_init__(self) -> None:
        # one flat table, fine cells then coarse cells: the coarse id of a cell is at index + offset
        self._flat = np.concatenate([self.fine.reshape(-1), self.coarse.reshape(-1)])
        self.coarse_offset = self.fine.size
        self._index_flat = np.ascontiguousarray(self.tile_index.reshape(-1), dtype=np.int64)
        ty, tx = self.tile_index.shape
        c = 1 << self.tile_shift
        self.max_cell = (float(tx * c - 1), float(ty * c - 1))

    @property
    def tile_cells(self) -> int:
        return 1 << self.tile_shift

    @property
    def nbytes(self) -> int:
        return int(self._flat.nbytes + self.tile_index.nbytes)

    def cell_index(self, cx: np.ndarray, cy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat table index of (fractional) cell coordinates ``cx, cy`` (clamped onto the grid's
        grass border), and the tile coordinates ``tx, ty``."""
        sh = self.tile_shift
        m = (1 << sh) - 1
        ix = np.minimum(np.maximum(cx, 0.0), self.max_cell[0]).astype(np.int64)
        iy = np.minimum(np.maximum(cy, 0.0), self.max_cell[1]).astype(np.int64)
        tx = ix >> sh
        ty = iy >> sh
        tid = self._index_flat.take(ty * self.tile_index.shape[1] + tx)
        return (tid << (2 * sh)) | ((iy & m) << sh) | (ix & m), tx, ty

    def lookup(self, x, y, coarse: np.ndarray | None = None) -> np.ndarray:
        """Material ids at world points ``x, y [k]`` (the coarse level where ``coarse [k]``)."""
        inv = 1.0 / self.cell
        lin, _, _ = self.cell_index((np.asarray(x, dtype=np.float64) - self.x0) * inv,
                                    (np.asarray(y, dtype=np.float64) - self.y0) * inv)
        if coarse is not None:
            np.add(lin, self.coarse_offset, out=lin, where=np.asarray(coarse, dtype=bool))
        return self._flat.take(lin)

    def take(self, index: np.ndarray) -> np.ndarray:
        """Material ids at flat table indices (from :meth:`cell_index`)."""
        return self._flat.take(index)


def _rasterize(polys: list[tuple[int, np.ndarray, int]], st: WorldStyle) -> GroundRaster:
    """Fill ``(material id, polygon [k, 2] world, group)`` into tiles. Each group (a chunk of
    track) is filled in order (later polygons on top) into one dense patch, cut into tiles; where
    groups meet, the higher id wins (marks over road)."""
    import cv2  # deferred: OpenCV (~0.1 s) only rasterises a camera world's ground; envs.race imports this module

    sh = st.tile_shift
    c, cell = 1 << sh, st.raster_cell_m
    tile_m = c * cell
    allpts = np.concatenate([q for _, q, _ in polys])
    border = math.ceil(st.raster_border_m / tile_m) * tile_m
    lo = np.floor(allpts.min(0) / tile_m) * tile_m - border
    hi = np.ceil(allpts.max(0) / tile_m) * tile_m + border
    tx_n, ty_n = (np.round((hi - lo) / tile_m)).astype(int)
    tiles: dict[tuple[int, int], np.ndarray] = {}
    scale = 16.0 / cell  # cv2 fixed point, 4 fractional bits
    groups: dict[int, list[tuple[int, np.ndarray]]] = {}
    for mat, q, g in polys:
        groups.setdefault(g, []).append((mat, q))
    for items in groups.values():
        pts = np.concatenate([q for _, q in items])
        t0 = np.floor((pts.min(0) - lo) / tile_m).astype(int)  # patch corner tile
        t1 = np.floor((pts.max(0) - lo) / tile_m).astype(int)
        nx, ny = t1 - t0 + 1
        patch = np.zeros((ny * c, nx * c), dtype=np.uint8)
        origin = lo + t0 * tile_m
        for mat, q in items:
            cv2.fillConvexPoly(patch, np.round((q - origin) * scale - 8.0).astype(np.int32), int(mat),
                               lineType=cv2.LINE_8, shift=4)  # -8: cell centres
        cut = patch.reshape(ny, c, nx, c).transpose(0, 2, 1, 3)
        used = cut.any(axis=(2, 3))
        for j, i in zip(*np.nonzero(used)):
            key = (int(t0[1] + j), int(t0[0] + i))
            old = tiles.get(key)
            tiles[key] = cut[j, i].copy() if old is None else np.maximum(old, cut[j, i])
    keys = [k for k, t in tiles.items() if t.any()]
    index = np.zeros((ty_n, tx_n), dtype=np.int64)
    fine = np.zeros((len(keys) + 1, c, c), dtype=np.uint8)
    for i, k in enumerate(keys, start=1):
        index[k] = i
        fine[i] = tiles[k]
    nm = len(FLAT_MATERIALS)
    blocks = fine.reshape(len(fine), c // 2, 2, c // 2, 2).transpose(0, 1, 3, 2, 4).reshape(-1, 4)
    counts = np.bincount((np.arange(len(blocks))[:, None] * nm + blocks).reshape(-1), minlength=len(blocks) * nm)
    majority = np.argmax(counts.reshape(len(fine), c // 2, c // 2, nm), axis=-1).astype(np.uint8)  # ties: lower id
    coarse = np.repeat(np.repeat(majority, 2, axis=1), 2, axis=2)
    return GroundRaster(float(lo[0]), float(lo[1]), cell, sh, index, fine, coarse)


# ---------------------------------------------------------------------------------------------
# World
# ---------------------------------------------------------------------------------------------
@dataclass
class _Chunk:
    bodies: list[int]
    colors: list[tuple[float, float, float]]
    center: np.ndarray  # [2] world
    radius: float  # [m] horizontal bounding radius


@dataclass
class World:
    """A track's visible world in one pybullet client (see :func:`build_world`).

    Attributes:
        client_id: pybullet client.
        track: the track (in its own frame).
        origin_xy: world position of the track frame's origin ``[2]`` [m].
        style: the :class:`WorldStyle` it was built with.
        ground: the flat ground map the camera paints.
        chunks: culling units of the 3-D objects (one body per colour).
        num_triangles: triangles in all bodies.
    """

    client_id: int
    track: Track
    origin_xy: np.ndarray
    style: WorldStyle
    ground: GroundRaster | None = None
    chunks: list[_Chunk] = field(default_factory=list)
    num_triangles: int = 0
    bounds: np.ndarray | None = None  # [2, 2] world xy min / max of everything
    _centers: np.ndarray | None = field(default=None, repr=False)
    _radii: np.ndarray | None = field(default=None, repr=False)
    _visible: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.origin_xy = np.asarray(self.origin_xy, dtype=np.float64).reshape(2)
        self._finalize()

    def _finalize(self) -> None:
        self._centers = np.array([c.center for c in self.chunks], dtype=np.float64).reshape(-1, 2)
        self._radii = np.array([c.radius for c in self.chunks], dtype=np.float64)
        self._visible = np.ones(len(self.chunks), dtype=bool)

    @property
    def bodies(self) -> list[int]:
        """All body ids of this world."""
        return [b for c in self.chunks for b in c.bodies]

    def to_world(self, s, d) -> np.ndarray:
        """World position ``[..., 2]`` of track coordinates (the track frame shifted by ``origin_xy``)."""
        return self.track.to_world(s, d) + self.origin_xy

    def distance_to(self, xy) -> float:
        """Distance [m] from a world point to this world's bounding box (0 inside)."""
        xy = np.asarray(xy, dtype=np.float64)[:2]
        gap = np.maximum(np.maximum(self.bounds[0] - xy, xy - self.bounds[1]), 0.0)
        return float(math.hypot(gap[0], gap[1]))

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
        self._visible = mask.copy()
        return len(changed)

    def show_all(self) -> None:
        """Make every chunk visible (no culling)."""
        if not self._visible.all():
            self.set_visible(np.ones(len(self.chunks), dtype=bool))

    def hide_all(self) -> None:
        """Hide every chunk (a camera far from this world)."""
        if self._visible.any():
            self.set_visible(np.zeros(len(self.chunks), dtype=bool))

    def visible_mask(self, eye_xy, forward_xy=None, half_angle: float = math.pi, distance: float = 300.0) -> np.ndarray:
        """Chunks that may appear in a camera's view: within ``distance`` [m] of ``eye_xy`` and, when
        ``forward_xy`` (a horizontal unit vector) is given, inside the horizontal cone of
        ``half_angle`` [rad] around it. Conservative (bounding circles)."""
        v = self._centers - np.asarray(eye_xy, dtype=np.float64)[None, :]
        mask = np.hypot(v[:, 0], v[:, 1]) - self._radii < distance
        if forward_xy is not None and half_angle < 0.5 * math.pi:
            f = np.asarray(forward_xy, dtype=np.float64)
            along = v @ f
            lateral = np.abs(v[:, 0] * f[1] - v[:, 1] * f[0])
            # circle vs cone: distance of the centre outside the cone's side line
            mask &= (lateral * math.cos(half_angle) - along * math.sin(half_angle)) < self._radii
            mask &= along > -self._radii
        return mask

    def cull(self, eye_xy, forward_xy=None, half_angle: float = math.pi, distance: float = 300.0) -> int:
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
# Geometry helpers
# ---------------------------------------------------------------------------------------------
class _Mesh:
    """Triangles of one colour, collected before they become an OBJ file."""

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
        text = ("v %.4f %.4f %.4f\n" * len(v)) % tuple(v.ravel().tolist())
        text += ("vn %.4f %.4f %.4f\n" * len(n)) % tuple(n.ravel().tolist())
        text += ("f %d//%d %d//%d %d//%d\n" * len(f)) % tuple(np.repeat(f, 2, axis=1).ravel().tolist())
        path.write_text(text)


_BOX_FACES = np.array([  # outward, counter-clockwise; vertex index = 4*ix + 2*iy + iz
    (0, 1, 3), (0, 3, 2),  # -x
    (4, 6, 7), (4, 7, 5),  # +x
    (0, 4, 5), (0, 5, 1),  # -y
    (2, 3, 7), (2, 7, 6),  # +y
    (1, 5, 7), (1, 7, 3),  # +z (no bottom face: never seen)
])


def _flat_shaded(tri: np.ndarray):
    """Vertices, normals and faces of triangles ``[k, 3, 3]`` with one normal per face."""
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    verts = tri.reshape(-1, 3)
    return verts, np.repeat(nrm, 3, axis=0), np.arange(len(verts)).reshape(-1, 3)


def _boxes(center_xy: np.ndarray, yaw: np.ndarray, half: np.ndarray, z0: float, z1: float):
    """Upright boxes ``[k]`` with half sizes ``half [k, 2]`` from ``z0`` to ``z1`` (no bottom)."""
    k = len(center_xy)
    sx = np.array([-1, -1, -1, -1, 1, 1, 1, 1], dtype=np.float64)
    sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1], dtype=np.float64)
    sz = np.array([0, 1, 0, 1, 0, 1, 0, 1], dtype=np.float64)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx, ly = sx[None, :] * half[:, 0:1], sy[None, :] * half[:, 1:2]
    corners = np.stack([center_xy[:, 0:1] + c * lx - s * ly, center_xy[:, 1:2] + s * lx + c * ly,
                        np.broadcast_to(z0 + sz * (z1 - z0), (k, 8))], axis=-1)  # [k, 8, 3]
    return _flat_shaded(corners[:, _BOX_FACES.reshape(-1)].reshape(-1, 3, 3))


def _pyramids(center_xy: np.ndarray, radius: np.ndarray, height: np.ndarray, yaw: np.ndarray):
    """Four-sided pyramids (conifers) standing on the ground."""
    k = len(center_xy)
    ang = yaw[:, None] + np.arange(4)[None, :] * (np.pi / 2)
    base = np.stack([center_xy[:, 0:1] + radius[:, None] * np.cos(ang),
                     center_xy[:, 1:2] + radius[:, None] * np.sin(ang),
                     np.zeros((k, 4))], axis=-1)  # [k, 4, 3]
    apex = np.broadcast_to(np.column_stack([center_xy, height])[:, None, :], base.shape)
    tri = np.stack([base, np.roll(base, -1, axis=1), apex], axis=2)  # [k, 4, 3, 3]
    return _flat_shaded(tri.reshape(-1, 3, 3))


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _decimate(track: Track, forced: np.ndarray, max_turn: float, max_seg: float) -> np.ndarray:
    """Arc lengths of the road polygon vertices: every forced break, plus a vertex whenever the
    heading has turned ``max_turn`` [rad], a width changed by 5 cm, or ``max_seg`` [m] passed."""
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


def _beside_ok(track: Track, s: np.ndarray, side: float, offset: np.ndarray, clearance: float) -> np.ndarray:
    """Points ``offset [k]`` beyond the ``side`` (+1 left, -1 right) edge at ``s [k]``: True where the
    offset curve does not fold on the inside of a bend and the point lies outside every other
    stretch of road by at least ``clearance`` [m]."""
    if len(s) == 0:
        return np.zeros(0, dtype=bool)
    wl, wr = track.width(s)
    d = side * ((wl if side > 0 else wr) + offset)
    kappa = track.curvature(s)
    fold = (np.sign(kappa) == side) & (np.abs(d * kappa) > 0.8)
    s_p, d_p = track.project(track.to_world(s, d))
    wl_p, wr_p = track.width(s_p)
    beyond = np.where(d_p >= 0, d_p - wl_p, -d_p - wr_p)  # distance beyond the nearest road edge
    own = np.abs(track.wrap_delta(s_p, s)) < 1.0  # projects back onto its own stretch
    return ~fold & (own | (beyond > clearance))


def _band(track: Track, s: np.ndarray, d_in: np.ndarray, d_out: np.ndarray) -> np.ndarray:
    """Quads ``[k-1, 4, 2]`` (counter-clockwise from above) of the band between lateral offsets
    ``d_in`` and ``d_out`` (either order) along the arc lengths ``s [k]`` (track frame)."""
    a = track.to_world(s, d_in)
    b = track.to_world(s, d_out)
    left_is_a = np.mean(np.asarray(d_in) - np.asarray(d_out)) > 0
    lft, rgt = (a, b) if left_is_a else (b, a)
    return np.stack([rgt[:-1], rgt[1:], lft[1:], lft[:-1]], axis=1)


# ---------------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------------
def build_world(client_id: int, track: Track, origin_xy=(0.0, 0.0), style: WorldStyle | None = None,
                ground_body: int | None = None) -> World:
    """Build the visible world of ``track`` in pybullet client ``client_id``.

    Args:
        client_id: pybullet physics client (each env owns its own).
        track: the track, in its own frame.
        origin_xy: where the track frame's origin lies in the world [m]. Give each track in a
            shared client its own origin, far apart (e.g. 10 km): a camera sees what lies within
            its far plane.
        style: sizes and densities (:class:`WorldStyle`).
        ground_body: the physics ground plane (``vehicle.make_ground``). If given, its visual is
            hidden (the camera paints the ground; pybullet would otherwise draw the collision
            plane, slowly and in its own colours). It keeps colliding.

    Returns:
        the :class:`World`. Every body is visual only (no collision shape).
    """
    st = style or WorldStyle()
    cid = int(client_id)
    origin = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    if ground_body is not None:
        p.changeVisualShape(ground_body, -1, rgbaColor=[1.0, 1.0, 1.0, 0.0], physicsClientId=cid)
    L = track.length
    n_chunks = max(1, int(round(L / st.chunk_m)))
    bounds = np.linspace(0.0, L, n_chunks + 1)
    chunk_of = lambda s: np.clip(np.searchsorted(bounds, np.mod(s, L), side="right") - 1, 0, n_chunks - 1)  # noqa: E731

    # ---- flat ground polygons, in paint order: road, edge lines, kerbs, start line
    polys: list[tuple[int, np.ndarray, float]] = []  # (material, quad [4, 2] track frame, s of its middle)
    stretches = track.surface_stretches
    breaks = np.array([a for a, _, _ in stretches]) if len(stretches) > 1 else np.zeros(0)
    s_road = _decimate(track, np.concatenate([bounds[:-1], breaks]), math.radians(st.max_turn_deg), st.max_segment_m)
    s_all = np.append(s_road, L)
    wl, wr = track.width(s_all)
    mids = 0.5 * (s_all[:-1] + s_all[1:])
    mats = 1 + track.surface(mids)
    for q, m, sm in zip(_band(track, s_all, wl, -wr), mats, mids):
        polys.append((int(m), q, sm))
    lw = st.line_width_m
    for q, sm in zip(_band(track, s_all, wl, wl - lw), mids):
        polys.append((_MAT["line"], q, sm))
    for q, sm in zip(_band(track, s_all, -wr, -wr + lw), mids):
        polys.append((_MAT["line"], q, sm))
    radius = 1.0 / np.maximum(np.abs(track.kappa), 1e-9)
    tight = radius < st.kerb_radius_m
    if tight.any():
        nblk = max(1, int(L // st.kerb_block_m))
        blk = L / nblk
        s0 = np.arange(nblk) * blk
        # kerbed where the bend is tight within ±10 samples (the kerb runs a little past the bend)
        pad = np.concatenate([tight[-10:], tight, tight[:10]]).astype(float)
        near_tight = np.convolve(pad, np.ones(21), "same")[10:-10] > 0
        is_kerb = np.interp(np.mod(s0 + blk / 2, L), track.s, near_tight.astype(float)) > 0.5
        for side in (1.0, -1.0):
            ok = is_kerb & _beside_ok(track, s0 + blk / 2, side, np.full(nblk, st.kerb_width_m), 1.0)
            j = np.flatnonzero(ok)
            ss = np.stack([s0[j], s0[j] + blk], axis=1)  # [k, 2] block ends
            w = track.width(ss)[0 if side > 0 else 1]
            edge = track.to_world(ss, side * w)
            outer = track.to_world(ss, side * (w + st.kerb_width_m))
            lft, rgt = (outer, edge) if side > 0 else (edge, outer)
            quads = np.stack([rgt[:, 0], rgt[:, 1], lft[:, 1], lft[:, 0]], axis=1)
            for jj, q in zip(j.tolist(), quads):
                polys.append((_MAT["kerb_red"] if jj % 2 == 0 else _MAT["kerb_white"], q, s0[jj] + blk / 2))
    ss = np.array([0.0, st.start_line_m])
    w0l, w0r = track.width(ss)
    polys.append((_MAT["line"], _band(track, ss, w0l, -w0r)[0], 0.5 * st.start_line_m))

    world = World(cid, track, origin, st)
    world.ground = _rasterize([(m, q + origin, int(chunk_of(sm))) for m, q, sm in polys], st)

    # ---- 3-D objects, as meshes per (chunk, colour)
    meshes: list[dict[tuple[float, float, float], _Mesh]] = [dict() for _ in range(n_chunks)]

    def add(k: int, color, parts) -> None:
        meshes[k].setdefault(tuple(float(c) for c in color), _Mesh()).add(*parts)

    def add_objects(make, chunk: np.ndarray, names: np.ndarray, *arrays: np.ndarray) -> None:
        """Objects ``make(*arrays[sel])`` grouped into one mesh per (chunk, colour name)."""
        for k, name in sorted(set(zip(chunk.tolist(), names.tolist()))):
            sel = (chunk == k) & (names == name)
            add(k, PALETTE[name], make(*(a[sel] for a in arrays)))

    up = np.array([0.0, 0.0, 1.0])
    if st.road_meshes:
        cols = flat_colors()
        for m, q, sm in polys:
            z = st.road_z * (2.0 if m > len(_surf.SURFACE_NAMES) else 1.0)  # marks just above the road
            v = np.column_stack([q + origin, np.full(4, z)])
            add(int(chunk_of(sm)), cols[m], (v, up, np.array([[0, 1, 2], [0, 2, 3]])))
    if st.post_spacing_m > 0:
        npost = max(1, int(round(L / st.post_spacing_m)))
        sp = np.arange(npost) * (L / npost)
        yaw = track.heading(sp)
        for side in (1.0, -1.0):
            ok = _beside_ok(track, sp, side, np.full(npost, st.post_offset_m + st.post_size_m), 1.0)
            w = track.width(sp)[0 if side > 0 else 1]
            xy = track.to_world(sp, side * (w + st.post_offset_m + st.post_size_m / 2)) + origin
            names = np.where(np.arange(npost) % 2 == 0, "post_white", "post_red")
            half = np.full((npost, 2), st.post_size_m / 2)
            add_objects(lambda c, y, h: _boxes(c, y, h, 0.0, st.post_height_m), chunk_of(sp)[ok], names[ok],
                        xy[ok], yaw[ok], half[ok])
    if st.gantry:
        gl, gr = track.width(0.0)
        yaw0 = float(track.heading(0.0))
        legs = np.stack([track.to_world(0.0, gl + 1.5), track.to_world(0.0, -(gr + 1.5))]) + origin
        add(0, PALETTE["gantry"], _boxes(legs, np.full(2, yaw0), np.full((2, 2), 0.25), 0.0, 5.5))
        mid = track.to_world(0.0, 0.5 * (gl - gr)) + origin
        beam = np.array([[0.3, 0.5 * (gl + gr) + 1.75]])
        add(0, PALETTE["gantry"], _boxes(mid[None, :], np.array([yaw0]), beam, 4.5, 5.5))
    if st.tree_spacing_m > 0:
        rng = np.random.default_rng([zlib.crc32(track.name.encode()), st.seed])
        for side in (1.0, -1.0):
            n = int(L / st.tree_spacing_m)
            s_t = rng.uniform(0.0, L, n)
            off = st.tree_min_offset_m + rng.uniform(0.0, st.tree_band_m, n)
            r = rng.uniform(1.2, 2.2, n)
            h = r * rng.uniform(2.5, 3.5, n)
            yaw = rng.uniform(0, np.pi / 2, n)
            shade = rng.integers(0, 2, n)
            ok = _beside_ok(track, s_t, side, off, st.tree_min_offset_m)
            w = track.width(s_t)[0 if side > 0 else 1]
            xy = track.to_world(s_t, side * (w + off)) + origin
            names = np.where(shade == 1, "tree_dark", "tree_light")
            add_objects(_pyramids, chunk_of(s_t)[ok], names[ok], xy[ok], r[ok], h[ok], yaw[ok])

    # ---- bodies: one per (chunk, colour), each mesh in chunk-local coordinates
    tmp = Path(tempfile.mkdtemp(prefix="torcsrl_world_"))
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    try:
        for k in range(n_chunks):
            if not meshes[k]:
                continue
            all_v = np.concatenate([v for m in meshes[k].values() for v in m.v])[:, :2]
            center = 0.5 * (all_v.min(0) + all_v.max(0))
            lo, hi = np.minimum(lo, all_v.min(0)), np.maximum(hi, all_v.max(0))
            ch = _Chunk([], [], center, float(np.max(np.hypot(*(all_v - center).T))) + 0.5)
            offset = np.array([center[0], center[1], 0.0])
            for j, (color, m) in enumerate(meshes[k].items()):
                path = tmp / f"c{k}_{j}.obj"
                m.write_obj(path, offset)
                vs = p.createVisualShape(p.GEOM_MESH, fileName=str(path), rgbaColor=[*color, 1.0],
                                         specularColor=[0.0, 0.0, 0.0], physicsClientId=cid)
                if vs < 0:
                    raise RuntimeError(f"pybullet could not create a visual shape for chunk {k} of {track.name!r}")
                body = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vs,
                                         basePosition=offset.tolist(), physicsClientId=cid)
                ch.bodies.append(body)
                ch.colors.append(color)
                world.num_triangles += m.num_triangles
            world.chunks.append(ch)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    g = world.ground
    glo = np.array([g.x0, g.y0])
    ghi = glo + np.array(g.tile_index.shape[::-1]) * g.tile_cells * g.cell
    world.bounds = np.stack([np.minimum(lo, glo), np.maximum(hi, ghi)])
    world._finalize()
    log.info("world %r at origin (%.0f, %.0f): %d chunks, %d bodies, %d triangles, ground raster %d tiles (%.1f MB)",
             track.name, origin[0], origin[1], len(world.chunks), len(world.bodies), world.num_triangles,
             len(g.fine) - 1, g.nbytes / 1e6)
    return world
