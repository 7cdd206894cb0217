"""Clean sensors: the TORCS-style rangefinder and the named state vector.

Sensors return ideal readings. Everything that corrupts them (noise, dropouts, latency, weather)
is a transform in :mod:`torcsrl.transforms`.

**rangefinder** ``[B]`` float32 [m]: distance from the car to the track edge along each beam, at
angles :data:`RANGEFINDER_ANGLES_DEG` relative to the car's heading (positive = left), capped at
:data:`RANGE_M`. While the car is off the track every beam reads ``-1`` (TORCS/SCR semantics).
The beams are cast against the exact edge polylines (as vertical walls) in a pybullet client of
their own, so they never interact with the cars' physics.

**state** ``[S]`` float32, slots :data:`STATE_SLOTS` (TORCS names, units in the suffix).

**opponents** ``[36]`` float32 [m]: TORCS SCR's opponent sensor — per 10° sector around the car (sector 0 straight
back, clockwise: 9 left, 17/18 ahead, 27 right), the centre distance to the nearest other car of its race, capped at
200 m; a free sector reads 200 m (:func:`torcsrl.envs.traffic.opponent_sectors`). Normalised: / 200 m. Only cars of a
race (``traffic``) are seen; without traffic every sector reads 200.

**telemetry** ``[T]`` float32, slots :data:`TELEMETRY_SLOTS`: the state slots a real car measures on
board (speeds, wheel spin, rpm, gear) — without ``angle_rad`` and ``trackPos``, which need a map of the
track. With ``pixels`` it makes the camera-only observation set (``sensors=camera``).

Normalised versions (as the studies fed their networks) divide each key by the scales here (:data:`RANGE_M`,
:data:`STATE_SCALE`) — rangefinder / 200 m (so [0, 1], −1/200 off track), angle / π, trackPos as is,
speeds / 300 km/h, wheel spin / 150 rad/s, rpm / 10,000, gear / 6 — which maps a lap at racing
speed into about [−1, 1]. The transform that does it is :func:`torcsrl.transforms.normalize_transform`.

**road** ``[6]`` float32, slots :data:`ROAD_SLOTS`: what the track map and the tyres know and no on-board sensor
reads — the friction coefficient under the wheels (``surfaceMu``, their mean) and the mean curvature of the centreline
over five stretches ahead of the car (0–20, 20–50, 50–100, 100–150, 150–200 m along the track) [1/m], > 0 a bend to
the left: the heading change over the stretch divided by its length. A privileged sensor: for an asymmetric critic
(``critic_obs_keys``), not for a driver. Normalised: mu as is, curvature x 20 m (a 20 m radius reads 1).

**privileged** ``[22]`` (demonstration rows only, :data:`PRIVILEGED_SLOTS`): a teacher's clean view of the road.
"""

from __future__ import annotations

import math
from operator import itemgetter

import numpy as np
from torcsrl.utils.bullet import pybullet as p

#: TORCS/SCR default beam angles [deg], relative to the car's heading (positive = left).
RANGEFINDER_ANGLES_DEG: tuple[float, ...] = (-90, -75, -60, -45, -30, -20, -15, -10, -5, 0,
                                             5, 10, 15, 20, 30, 45, 60, 75, 90)
#: Rangefinder range [m].
RANGE_M = 200.0
#: Value of every beam while the car is off the track.
OFF_TRACK_READING = -1.0
_hit_fraction = itemgetter(2)  # of a rayTestBatch hit

#: Named slots of the "state" observation, with their units.
STATE_SLOTS: tuple[str, ...] = (
    "angle_rad",          # angle between the car's heading and the track axis, (−π, π], > 0 = car points left of the axis
    "trackPos",           # 0 on the centreline, +1 at the left edge, −1 at the right edge, |.| > 1 off the track
    "speedX_kmh",         # forward speed in the car's frame [km/h]
    "speedY_kmh",         # leftward speed in the car's frame [km/h]
    "speedZ_kmh",         # upward speed [km/h]
    "wheelSpinVel_fl",    # front-left wheel spin [rad/s]
    "wheelSpinVel_fr",    # front-right wheel spin [rad/s]
    "wheelSpinVel_rl",    # rear-left wheel spin [rad/s]
    "wheelSpinVel_rr",    # rear-right wheel spin [rad/s]
    "rpm",                # engine speed [1/min]
    "gear",               # engaged gear [-]
)
#: Slots of the "telemetry" observation: what the car measures on board, no map (a subset of STATE_SLOTS, same order).
TELEMETRY_SLOTS: tuple[str, ...] = STATE_SLOTS[2:]
#: Divisors that bring each state slot to about [−1, 1].
STATE_SCALE: dict[str, float] = {
    "angle_rad": np.pi, "trackPos": 1.0, "speedX_kmh": 300.0, "speedY_kmh": 300.0, "speedZ_kmh": 300.0,
    "wheelSpinVel_fl": 150.0, "wheelSpinVel_fr": 150.0, "wheelSpinVel_rl": 150.0, "wheelSpinVel_rr": 150.0,
    "rpm": 10000.0, "gear": 6.0,
}
#: Physical bounds of each state slot (the observation space's low/high).
STATE_BOUNDS: dict[str, tuple[float, float]] = {
    "angle_rad": (-np.pi, np.pi), "trackPos": (-1e3, 1e3), "speedX_kmh": (-1e3, 1e3), "speedY_kmh": (-1e3, 1e3),
    "speedZ_kmh": (-1e3, 1e3), "wheelSpinVel_fl": (-1e3, 1e3), "wheelSpinVel_fr": (-1e3, 1e3),
    "wheelSpinVel_rl": (-1e3, 1e3), "wheelSpinVel_rr": (-1e3, 1e3), "rpm": (0.0, 2e4), "gear": (0.0, 10.0),
}
MS_TO_KMH = 3.6
SENSOR_NAMES: tuple[str, ...] = ("rangefinder", "state", "telemetry", "pixels", "depth", "opponents", "road")
#: Stretches ahead of the car [m, m] whose mean centreline curvature the ``road`` sensor reads.
ROAD_AHEAD_M: tuple[tuple[float, float], ...] = ((0.0, 20.0), (20.0, 50.0), (50.0, 100.0), (100.0, 150.0), (150.0, 200.0))
#: Named slots of the privileged ``road`` observation (an asymmetric critic's): grip under the wheels, bends ahead [1/m].
ROAD_SLOTS: tuple[str, ...] = ("surfaceMu",) + tuple(f"curv_{int(a)}_{int(b)}m" for a, b in ROAD_AHEAD_M)
#: Divisors that bring each road slot to about [-1, 1]: mu as is, curvature x 20 m.
ROAD_SCALE: tuple[float, ...] = (1.0,) + (0.05,) * len(ROAD_AHEAD_M)
#: What ``privileged`` holds per demonstration row: the teacher's clean view of the road, normalised to ~[-1, 1] —
#: the 19 rangefinder beams / 200 m (-1/200 off track), the angle to the track axis / pi, trackPos, and the friction
#: under the wheels ``info/surfaceMu``. A camera student regresses it as an auxiliary target (``algo.aux_privileged``).
PRIVILEGED_SLOTS: tuple[str, ...] = tuple(f"track_{i}" for i in range(19)) + ("angle", "trackPos", "surfaceMu")


def check_sensors(sensors) -> tuple[str, ...]:
    """Validate a list of sensor names; ``ValueError`` names the allowed ones."""
    if isinstance(sensors, str):
        sensors = (sensors,)
    sensors = tuple(sensors)
    unknown = [s for s in sensors if s not in SENSOR_NAMES]
    if unknown or not sensors:
        raise ValueError(f"unknown sensors {unknown or '(none given)'}; allowed: {', '.join(SENSOR_NAMES)}")
    if len(set(sensors)) != len(sensors):
        raise ValueError(f"sensors listed twice: {sensors}")
    return sensors


#: pybullet 3.2.x never releases the sequences passed as ``vertices=`` / ``indices=`` to ``createCollisionShape``
#: (nor each vertex's row): a reference leak of ~4 MB per track's walls, which grew a DAgger run by ~0.4 GB for
#: every env it built (each env seed draws its own procedural pool of 100 tracks). So every mesh goes through the
#: SAME list objects, refilled in place: the leaked references then pin only these buffers (as large as the
#: largest mesh so far). pybullet copies the data during the call, so refilling them afterwards is safe.
_MESH_ROWS: list[list[float]] = []  # one [x, y, z] list per vertex, reused
_MESH_VERTS: list[list[float]] = []
_MESH_INDICES: list[int] = []


def _mesh_args(verts: np.ndarray, tris: np.ndarray) -> tuple[list, list]:
    """``(vertices, indices)`` for ``createCollisionShape``: the shared buffers above, refilled with ``verts [V, 3]``
    [m] and ``tris [3T]``; valid until the next call (hand them straight to pybullet)."""
    while len(_MESH_ROWS) < len(verts):
        _MESH_ROWS.append([0.0, 0.0, 0.0])
    for row, xyz in zip(_MESH_ROWS, verts.tolist()):
        row[:] = xyz
    _MESH_VERTS[:] = _MESH_ROWS[: len(verts)]
    _MESH_INDICES[:] = tris.tolist()
    return _MESH_VERTS, _MESH_INDICES


def _wall_mesh(left: np.ndarray, right: np.ndarray, x_offset_m: float, height_m: float) -> tuple[list, list]:
    """(vertices, indices) of the vertical walls along both track edges, shifted by ``x_offset_m`` [m] and
    ``height_m`` [m] above and below the beam plane, in the shared buffers of :func:`_mesh_args`."""
    offset = np.array([x_offset_m, 0.0])
    verts, tris, base = [], [], 0
    for edge in (left, right):
        m = len(edge)
        e = edge + offset
        verts.append(np.concatenate([np.c_[e, np.full(m, -height_m)], np.c_[e, np.full(m, height_m)]]))
        i = np.arange(m)
        j = (i + 1) % m
        tris.append(np.concatenate([np.stack([i, j, i + m], 1), np.stack([j, j + m, i + m], 1)]).ravel() + base)
        base += 2 * m
    return _mesh_args(np.concatenate(verts), np.concatenate(tris).astype(int))


class Rangefinder:
    """Beams from each car to the edges of its track, cast in a private pybullet client.

    Args:
        angles_deg: beam angles relative to the car's heading [deg] (positive = left).
        range_m: maximum range [m].
        height_m: height of the edge walls above and below the beam plane [m].
    """

    def __init__(self, angles_deg=RANGEFINDER_ANGLES_DEG, range_m: float = RANGE_M, height_m: float = 2.0) -> None:
        a = np.radians(np.asarray(angles_deg, dtype=np.float64))
        if a.ndim != 1 or len(a) < 1 or np.abs(a).max() > np.pi:
            raise ValueError(f"rangefinder angles must be a list of degrees in [-180, 180], got {angles_deg}")
        if not range_m > 0:
            raise ValueError(f"rangefinder range must be positive [m], got {range_m}")
        self.angles = a
        self._angle_list = a.tolist()
        self.range_m = float(range_m)
        self.height_m = float(height_m)
        self.client = p.connect(p.DIRECT)
        self._bodies: dict[int, int] = {}  # track slot -> body
        self._offsets: dict[int, tuple[float, float]] = {}  # slot -> wall offset [m]

    @property
    def n_beams(self) -> int:
        return len(self.angles)

    def add_track(self, slot: int, track) -> None:
        """Build the edge walls of ``track`` under ``slot``; each slot sits at its own offset."""
        if slot in self._bodies:
            return
        offset = np.array([slot * 50_000.0, 0.0])
        verts, indices = _wall_mesh(track.left_edge, track.right_edge, float(offset[0]), self.height_m)
        shape = p.createCollisionShape(p.GEOM_MESH, vertices=verts, indices=indices,
                                       flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=self.client)
        self._bodies[slot] = p.createMultiBody(0, shape, physicsClientId=self.client)
        self._offsets[slot] = (float(offset[0]), float(offset[1]))

    def read(self, slots: np.ndarray, xy: np.ndarray, yaw: np.ndarray, on_track: np.ndarray) -> np.ndarray:
        """Beam distances ``[N, B]`` float32 [m] for cars at ``xy [N,2]`` (track frame), ``yaw [N]``."""
        n, b = len(xy), self.n_beams
        if n == 1:  # one car: plain floats (numpy's per-call overhead dominates at this size)
            if not on_track[0]:
                return np.full((1, b), OFF_TRACK_READING, dtype=np.float32)
            ox, oy = self._offsets[int(slots[0])]
            x0, y0, psi, r = float(xy[0, 0]) + ox, float(xy[0, 1]) + oy, float(yaw[0]), self.range_m
            start = [(x0, y0, 0.0)] * b
            end = [(x0 + r * math.cos(psi + a), y0 + r * math.sin(psi + a), 0.0) for a in self._angle_list]
            hits = p.rayTestBatch(start, end, physicsClientId=self.client)
            frac = np.fromiter(map(_hit_fraction, hits), dtype=np.float64, count=b)
            return (frac * r).astype(np.float32).reshape(1, b)
        out = np.full((n, b), OFF_TRACK_READING, dtype=np.float32)
        idx = np.flatnonzero(on_track)
        if len(idx) == 0:
            return out
        origin = xy[idx] + np.stack([self._offsets[int(s)] for s in slots[idx]])
        ang = yaw[idx, None] + self.angles[None, :]
        k = len(idx) * b
        start = np.zeros((k, 3))
        start[:, :2] = np.repeat(origin, b, axis=0)
        end = start.copy()
        end[:, 0] += self.range_m * np.cos(ang).ravel()
        end[:, 1] += self.range_m * np.sin(ang).ravel()
        hits = p.rayTestBatch(start, end, physicsClientId=self.client)
        frac = np.fromiter(map(_hit_fraction, hits), dtype=np.float64, count=len(idx) * b)
        out[idx] = (frac * self.range_m).reshape(len(idx), b)
        return out

    def close(self) -> None:
        if self.client is not None:
            try:
                p.disconnect(physicsClientId=self.client)
            except p.error:
                pass
            self.client = None



#: Arc lengths ahead of the car [m] whose centreline headings the ``road`` sensor compares (the stretches' ends).
_ROAD_EDGES = np.array(sorted({x for ab in ROAD_AHEAD_M for x in ab}), dtype=np.float64)
_ROAD_FROM = np.searchsorted(_ROAD_EDGES, [a for a, _ in ROAD_AHEAD_M])
_ROAD_TO = np.searchsorted(_ROAD_EDGES, [b for _, b in ROAD_AHEAD_M])
_ROAD_LEN = np.array([b - a for a, b in ROAD_AHEAD_M])


def road_readings(tracks, s: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """The ``road`` readings ``[n, 6]`` float32 (:data:`ROAD_SLOTS`) of ``n`` cars: each car's ``mu`` and the mean
    curvature [1/m] of its track's centreline over each stretch of :data:`ROAD_AHEAD_M` ahead of its arc length ``s``
    [m] (heading change / stretch length). ``tracks``: each car's track; cars on the same track are read at once."""
    s = np.asarray(s, dtype=np.float64)
    heading = np.empty((len(s), len(_ROAD_EDGES)))
    groups: dict[int, list[int]] = {}
    for i, t in enumerate(tracks):
        groups.setdefault(id(t), []).append(i)
    for rows in groups.values():
        heading[rows] = tracks[rows[0]].heading(s[rows, None] + _ROAD_EDGES)
    dh = (heading[:, _ROAD_TO] - heading[:, _ROAD_FROM] + math.pi) % (2 * math.pi) - math.pi
    return np.concatenate([np.asarray(mu, dtype=np.float64).reshape(-1, 1), dh / _ROAD_LEN], 1).astype(np.float32)
