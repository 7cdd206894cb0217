"""The track model: a closed centreline with widths and surfaces, and its Frenet frame.

A :class:`Track` is a closed centreline sampled about every metre, left/right widths and a
surface per stretch, in the track's own frame (metres, z = 0 ground). ``s = 0`` is the
start/finish line and the car drives towards increasing ``s``; the lateral offset ``d`` is
positive to the **left** of the direction of travel.

The Frenet frame is exact and continuous. Between two samples the centreline is the straight
chord and the normal is the normalised linear blend of the two vertex normals (each vertex normal
bisects its two chords), so ``to_world(s, d) = c(s) + d·n(s)`` is continuous in ``s`` everywhere,
and :meth:`Track.project` inverts it exactly by solving, per chord, the quadratic
``cross(p − c(t), n(t)) = 0`` for the chord parameter ``t``. A round trip world → (s, d) → world
is exact to float precision wherever the frame does not fold, i.e. wherever |d| is smaller than
the local radius — which :meth:`Track.validate` guarantees on the whole track surface. Hairpins
whose two legs come close are handled because the projection keeps the candidate with the
smallest |d| (and, given ``s_hint``, searches only near the previous position).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from torcsrl.envs import surfaces as _surf

#: No track may be narrower than this [m]: a full-size car is about 1.8 m wide.
MIN_TRACK_WIDTH_M = 2.0


class TrackError(ValueError):
    """A track that cannot be used: malformed data, not closing, self-intersecting, too narrow."""


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


@dataclass
class Track:
    """A closed track. Build it with the loaders in :mod:`torcsrl.envs.tracks`.

    Args:
        name: track name.
        xy: centreline samples ``[M, 2]`` [m], closed (the first sample is not repeated).
        w_left: width from the centreline to the left edge at each sample ``[M]`` [m].
        w_right: width from the centreline to the right edge at each sample ``[M]`` [m].
        surface_ids: surface of the stretch that starts at each sample ``[M]`` (ids into
            :data:`torcsrl.envs.surfaces.SURFACE_NAMES`).
        kappa: signed curvature at each sample ``[M]`` [1/m], > 0 turning left. Estimated from
            the samples when not given.
        default_surface: the track's usual surface (what config overrides).
        description: one line on the track's character.
        source: where it came from (file path, or ``generator(seed=…)``).
    """

    name: str
    xy: np.ndarray
    w_left: np.ndarray
    w_right: np.ndarray
    surface_ids: np.ndarray
    kappa: np.ndarray | None = None
    default_surface: str = "asphalt"
    description: str = ""
    source: str = ""
    character: str = ""
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.xy = np.asarray(self.xy, dtype=np.float64)
        m = len(self.xy)
        if self.xy.ndim != 2 or self.xy.shape[1] != 2 or m < 8:
            raise TrackError(f"{self._where()}: the centreline needs at least 8 (x, y) points, got shape {self.xy.shape}")
        self.w_left = np.broadcast_to(np.asarray(self.w_left, dtype=np.float64), (m,)).copy()
        self.w_right = np.broadcast_to(np.asarray(self.w_right, dtype=np.float64), (m,)).copy()
        self.surface_ids = np.broadcast_to(np.asarray(self.surface_ids, dtype=np.int64), (m,)).copy()
        if not (np.isfinite(self.xy).all() and np.isfinite(self.w_left).all() and np.isfinite(self.w_right).all()):
            raise TrackError(f"{self._where()}: non-finite coordinates or widths")
        nxt = np.roll(self.xy, -1, axis=0)
        self._e = nxt - self.xy  # chord vectors [M, 2]
        self._seg_len = np.hypot(self._e[:, 0], self._e[:, 1])
        self._inv_len = 1.0 / np.maximum(self._seg_len, 1e-12)
        if (self._seg_len < 1e-6).any():
            i = int(np.argmin(self._seg_len))
            raise TrackError(f"{self._where()}: repeated centreline point at index {i}")
        self.s = np.concatenate([[0.0], np.cumsum(self._seg_len)[:-1]])
        self.length = float(self._seg_len.sum())
        self.ds = self.length / m
        t = self._e / self._seg_len[:, None]
        seg_n = np.stack([-t[:, 1], t[:, 0]], axis=1)  # left normal of each chord
        vn = seg_n + np.roll(seg_n, 1, axis=0)  # vertex normal bisects chords i-1 and i
        norm = np.hypot(vn[:, 0], vn[:, 1])
        if (norm < 1e-9).any():
            raise TrackError(f"{self._where()}: the centreline reverses on itself at index {int(np.argmin(norm))}")
        self._n = vn / norm[:, None]
        self._n_next = np.roll(self._n, -1, axis=0)
        self._seg_heading = np.arctan2(t[:, 1], t[:, 0])
        if self.kappa is None:
            turn = _wrap_angle(self._seg_heading - np.roll(self._seg_heading, 1))
            self.kappa = turn / (0.5 * (self._seg_len + np.roll(self._seg_len, 1)))
        self.kappa = np.broadcast_to(np.asarray(self.kappa, dtype=np.float64), (m,)).copy()
        self.heading_samples = np.arctan2(-self._n[:, 0], self._n[:, 1])
        self.left_edge = self.xy + self.w_left[:, None] * self._n
        self.right_edge = self.xy - self.w_right[:, None] * self._n

    # ------------------------------------------------------------------ helpers
    def _where(self) -> str:
        return f"track {self.name!r}" + (f" ({self.source})" if self.source else "")

    def __len__(self) -> int:
        return len(self.xy)

    def _locate(self, s) -> tuple[np.ndarray, np.ndarray]:
        """Chord index and chord parameter t ∈ [0, 1) for arc lengths ``s`` (wrapped)."""
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        i = np.searchsorted(self.s, s, side="right") - 1  # s[0] = 0 and s < length: i in [0, M-1]
        return i, (s - self.s[i]) * self._inv_len[i]

    def _interp(self, arr: np.ndarray, s) -> np.ndarray:
        i, t = self._locate(s)
        return arr[i] + t * self._delta(arr)[i]

    def _delta(self, arr: np.ndarray) -> np.ndarray:
        key = ("delta", id(arr))
        d = self._cache.get(key)
        if d is None:
            d = self._cache[key] = np.roll(arr, -1) - arr
        return d

    def lookup(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(w_left [m], w_right [m], heading [rad], surface id) at ``s`` in one pass (the env's hot path)."""
        i, t = self._locate(s)
        wl = self.w_left[i] + t * self._delta(self.w_left)[i]
        wr = self.w_right[i] + t * self._delta(self.w_right)[i]
        n = self._n[i] + t[..., None] * (self._n_next[i] - self._n[i])
        return wl, wr, np.arctan2(-n[..., 0], n[..., 1]), self.surface_ids[i]

    # ------------------------------------------------------------------ geometry
    def normal(self, s) -> np.ndarray:
        """Unit left normal of the Frenet frame at ``s`` ``[..., 2]``."""
        i, t = self._locate(s)
        n = (1.0 - t)[..., None] * self._n[i] + t[..., None] * self._n_next[i]
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def to_world(self, s, d) -> np.ndarray:
        """World position ``[..., 2]`` [m] of arc length ``s`` [m] and lateral offset ``d`` [m]."""
        s, d = np.broadcast_arrays(np.asarray(s, dtype=np.float64), np.asarray(d, dtype=np.float64))
        i, t = self._locate(s)
        c = self.xy[i] + t[..., None] * self._e[i]
        return c + d[..., None] * self.normal(s)

    def heading(self, s) -> np.ndarray:
        """Direction of travel of the Frenet frame at ``s`` [rad], in (−π, π]."""
        n = self.normal(s)
        return np.arctan2(-n[..., 0], n[..., 1])

    def curvature(self, s) -> np.ndarray:
        """Signed centreline curvature at ``s`` [1/m] (> 0 turns left)."""
        return self._interp(self.kappa, s)

    def width(self, s) -> tuple[np.ndarray, np.ndarray]:
        """(w_left, w_right) at ``s`` [m]: distances from the centreline to each edge."""
        return self._interp(self.w_left, s), self._interp(self.w_right, s)

    def surface(self, s) -> np.ndarray:
        """Surface id of the road at ``s`` (ids into ``SURFACE_NAMES``)."""
        i, _ = self._locate(s)
        return self.surface_ids[i]

    def surface_name(self, s: float) -> str:
        """Surface name of the road at a scalar ``s``."""
        return _surf.SURFACE_NAMES[int(self.surface(s))]

    def surface_at(self, xy, s_hint=None) -> np.ndarray:
        """Surface id under world points ``xy [..., 2]``: the road's surface, or grass off the track."""
        s, d = self.project(xy, s_hint=s_hint)
        wl, wr = self.width(s)
        on = (d <= wl) & (d >= -wr)
        return np.where(on, self.surface(s), _surf.GRASS_ID)

    def start_pose(self) -> tuple[np.ndarray, float]:
        """Position ``[2]`` [m] and yaw [rad] of the start/finish line's centre."""
        return self.xy[0].copy(), float(self.heading(0.0))

    def wrap_delta(self, s_new, s_old) -> np.ndarray:
        """Signed progress ``s_new − s_old`` [m] with the lap wrap removed (|Δ| < length/2)."""
        return np.mod(np.asarray(s_new) - np.asarray(s_old) + 0.5 * self.length, self.length) - 0.5 * self.length

    def track_pos(self, s, d) -> np.ndarray:
        """TORCS trackPos: 0 on the centreline, +1 at the left edge, −1 at the right edge."""
        wl, wr = self.width(s)
        d = np.asarray(d, dtype=np.float64)
        return np.where(d >= 0.0, d / wl, d / wr)

    # ------------------------------------------------------------------ projection
    def project(self, xy, s_hint=None, window_m: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
        """Frenet projection of world points ``xy [..., 2]`` → ``(s, d)`` [m], exact.

        Args:
            xy: world points ``[..., 2]`` [m].
            s_hint: optional previous arc length of each point ``[...]``: only chords within
                ``±window_m`` of it are searched (faster, and it can never jump to the other leg
                of a hairpin). Without a hint the search starts from the nearest centreline sample
                (±30 m). Points with no solution in the window fall back to a search of all chords.
            window_m: half-width of the hint's search window [m].
        """
        p = np.asarray(xy, dtype=np.float64)
        shape = p.shape[:-1]
        p = p.reshape(-1, 2)
        m = len(self.xy)
        if s_hint is not None:
            hint = np.broadcast_to(np.asarray(s_hint, dtype=np.float64), shape).reshape(-1)
            i0, _ = self._locate(hint)
        else:  # start from the nearest centreline sample (a k-d tree query)
            if "kdtree" not in self._cache:
                # deferred: scipy.spatial (~1 s to import) only when a track is projected or checked
                from scipy.spatial import cKDTree

                self._cache["kdtree"] = cKDTree(self.xy)
            i0 = self._cache["kdtree"].query(p)[1]
            window_m = min(window_m, 30.0)
        # search the chords in a window around the start chord; fall back to all chords
        k = int(min(m, 2 * int(np.ceil(window_m / self.ds)) + 1))
        idx = (i0[:, None] + np.arange(k)[None, :] - k // 2) % m
        s, d, ok = self._project_candidates(p, idx)
        if not ok.all():
            bad = ~ok
            s[bad], d[bad], _ = self._project_candidates(p[bad], None)
        return s.reshape(shape), d.reshape(shape)

    def _project_candidates(self, p: np.ndarray, idx: np.ndarray | None):
        """Solve the chord quadratic on candidate chords ``idx [P, K]`` (all chords if None)."""
        if idx is None:
            idx = np.broadcast_to(np.arange(len(self.xy)), (len(p), len(self.xy)))
        c = self.xy[idx]  # [P, K, 2]
        e = self._e[idx]
        a = self._n[idx]
        b = self._n_next[idx] - a
        qx = p[:, None, 0] - c[..., 0]
        qy = p[:, None, 1] - c[..., 1]
        ex, ey, ax, ay, bx, by = e[..., 0], e[..., 1], a[..., 0], a[..., 1], b[..., 0], b[..., 1]
        qa = -_cross(ex, ey, bx, by)
        qb = _cross(qx, qy, bx, by) - _cross(ex, ey, ax, ay)
        qc = _cross(qx, qy, ax, ay)
        disc = qb * qb - 4.0 * qa * qc
        sq = np.sqrt(np.maximum(disc, 0.0))
        # Numerically stable roots; the first is the one that survives qa → 0 (straight chords).
        qq = -0.5 * (qb + np.where(qb >= 0.0, sq, -sq))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = np.where(qq != 0.0, qc / qq, np.inf)
            r2 = np.where(qa != 0.0, qq / qa, np.inf)
        t = np.stack([r1, r2], axis=-1)  # [P, K, 2] both roots of every chord
        valid = (disc >= 0.0)[..., None] & (t >= -1e-9) & (t <= 1.0 + 1e-9)
        t = np.minimum(np.maximum(np.where(valid, t, 0.0), 0.0), 1.0)
        nx = ax[..., None] + t * bx[..., None]
        ny = ay[..., None] + t * by[..., None]
        dd = ((qx[..., None] - t * ex[..., None]) * nx + (qy[..., None] - t * ey[..., None]) * ny) / np.sqrt(nx * nx + ny * ny)
        dd = np.where(valid, dd, np.inf).reshape(len(p), -1)
        j = np.argmin(np.abs(dd), axis=1)
        rows = np.arange(len(p))
        best_d = dd[rows, j]
        chord = idx[rows, j // 2]
        best_s = self.s[chord] + t.reshape(len(p), -1)[rows, j] * self._seg_len[chord]
        ok = np.isfinite(best_d)
        best_s = np.mod(best_s, self.length)
        return best_s, np.where(ok, best_d, 0.0), ok

    # ------------------------------------------------------------------ scalar fast path
    def _py(self) -> tuple:
        """The frame's arrays as Python lists (scalar indexing is ~10x cheaper than numpy's)."""
        py = self._cache.get("py")
        if py is None:
            py = self._cache["py"] = (
                self.xy[:, 0].tolist(), self.xy[:, 1].tolist(), self._e[:, 0].tolist(), self._e[:, 1].tolist(),
                self._n[:, 0].tolist(), self._n[:, 1].tolist(), self._n_next[:, 0].tolist(), self._n_next[:, 1].tolist(),
                self.s.tolist(), self._seg_len.tolist(), self.w_left.tolist(), self._delta(self.w_left).tolist(),
                self.w_right.tolist(), self._delta(self.w_right).tolist(), self.surface_ids.tolist())
        return py

    def track_point(self, x: float, y: float, chord: int, max_steps: int = 64) -> tuple[float, float, int, float] | None:
        """Exact projection of one point by walking chords from ``chord`` (a scalar fast path).

        The point must be near ``chord`` (it is meant for following a car from one control step to
        the next). Returns ``(s, d, chord, t)``, or ``None`` if the walk does not settle (then use
        :meth:`project`). Solves the same chord quadratic as :meth:`project`, keeping the root that
        is continuous with straight chords.
        """
        X, Y, EX, EY, NX, NY, MX, MY, S, L = self._py()[:10]
        m = len(X)
        i = chord % m
        last = -1
        for _ in range(max_steps):
            qx, qy = x - X[i], y - Y[i]
            ex, ey, ax, ay = EX[i], EY[i], NX[i], NY[i]
            bx, by = MX[i] - ax, MY[i] - ay
            qa = -(ex * by - ey * bx)
            qb = (qx * by - qy * bx) - (ex * ay - ey * ax)
            qc = qx * ay - qy * ax
            disc = qb * qb - 4.0 * qa * qc
            if disc < 0.0:
                return None
            sq = math.sqrt(disc)
            qq = -0.5 * (qb + (sq if qb >= 0.0 else -sq))
            if qq == 0.0:
                return None
            t = qc / qq
            if t < 0.0 and last != (i - 1) % m:
                last, i = i, (i - 1) % m
                continue
            if t > 1.0 and last != (i + 1) % m:
                last, i = i, (i + 1) % m
                continue
            t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
            nx, ny = ax + t * bx, ay + t * by
            d = ((qx - t * ex) * nx + (qy - t * ey) * ny) / math.sqrt(nx * nx + ny * ny)
            s = S[i] + t * L[i]
            return (s - self.length if s >= self.length else s), d, i, t
        return None

    def _walk_table(self) -> np.ndarray:
        """``[M, 8]``: per chord X, Y, EX, EY, NX, NY, MX - NX, MY - NY (what :meth:`track_point` reads)."""
        tab = self._cache.get("walk")
        if tab is None:
            b = self._n_next - self._n  # the same subtractions track_point does per call
            tab = self._cache["walk"] = np.ascontiguousarray(np.concatenate([self.xy, self._e, self._n, b], axis=1))
        return tab

    def track_points(self, x: np.ndarray, y: np.ndarray, chord: np.ndarray,
                     max_steps: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`track_point` for arrays of points ``x, y [P]`` walking from chords ``chord [P]``.

        Returns ``(s, d, chord, t, ok) [P]``; where ``ok`` each point's ``(s, d, chord, t)`` has the bits
        :meth:`track_point` returns for it (the same IEEE operations in the same order, elementwise, each
        point walking as many chords as its own walk does); where not ``ok`` the walk returned ``None``
        (the other values are then meaningless).
        """
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        m = len(self.xy)
        n_pts = len(x)
        tab = self._walk_table()
        s_out = np.zeros(n_pts)
        d_out = np.zeros(n_pts)
        c_out = np.zeros(n_pts, dtype=np.int64)
        t_out = np.zeros(n_pts)
        ok = np.zeros(n_pts, dtype=bool)
        rows = np.arange(n_pts)
        i = np.asarray(chord, dtype=np.int64).reshape(-1) % m
        last = np.full(n_pts, -1, dtype=np.int64)
        length = self.length
        with np.errstate(divide="ignore", invalid="ignore"):
            for _ in range(max_steps):
                if len(rows) == 0:
                    break
                r = tab[i]
                qx, qy = x - r[:, 0], y - r[:, 1]
                ex, ey, ax, ay, bx, by = r[:, 2], r[:, 3], r[:, 4], r[:, 5], r[:, 6], r[:, 7]
                qa = -(ex * by - ey * bx)
                qb = (qx * by - qy * bx) - (ex * ay - ey * ax)
                qc = qx * ay - qy * ax
                disc = qb * qb - 4.0 * qa * qc
                sq = np.sqrt(disc)
                qq = -0.5 * (qb + np.where(qb >= 0.0, sq, -sq))
                t = qc / qq
                live = ~((disc < 0.0) | (qq == 0.0))  # a failed walk stops (None)
                prev, nxt = (i - 1) % m, (i + 1) % m
                back = live & (t < 0.0) & (last != prev)
                fwd = live & ~back & (t > 1.0) & (last != nxt)
                done = live & ~back & ~fwd
                if done.any():
                    k = rows[done]
                    td = t[done]
                    td = np.where(td < 0.0, 0.0, np.where(td > 1.0, 1.0, td))
                    axd, ayd, bxd, byd = ax[done], ay[done], bx[done], by[done]
                    nx, ny = axd + td * bxd, ayd + td * byd
                    d = ((qx[done] - td * ex[done]) * nx + (qy[done] - td * ey[done]) * ny) / np.sqrt(nx * nx + ny * ny)
                    cd = i[done]
                    s = self.s[cd] + td * self._seg_len[cd]
                    s_out[k] = np.where(s >= length, s - length, s)
                    d_out[k] = d
                    c_out[k] = cd
                    t_out[k] = td
                    ok[k] = True
                move = back | fwd
                if not move.any():
                    break
                new_i = np.where(back, prev, nxt)[move]
                last, i = i[move], new_i
                rows, x, y = rows[move], x[move], y[move]
        return s_out, d_out, c_out, t_out, ok

    def frame_at(self, chord: int, t: float) -> tuple[float, float, float, int]:
        """(w_left [m], w_right [m], heading [rad], surface id) at a point of chord ``chord``."""
        _, _, _, _, NX, NY, MX, MY, _, _, WL, DWL, WR, DWR, SID = self._py()
        nx = NX[chord] + t * (MX[chord] - NX[chord])
        ny = NY[chord] + t * (MY[chord] - NY[chord])
        return WL[chord] + t * DWL[chord], WR[chord] + t * DWR[chord], math.atan2(-nx, ny), SID[chord]

    def surfaces_at(self, points: list, chord: int) -> list[int] | None:
        """Surface id under each ``(x, y)`` of ``points`` (grass off the track), each walked from ``chord`` by
        :meth:`track_point` and tested against :meth:`frame_at`'s widths (the same operations); ``None`` if a walk
        does not settle."""
        py = self._py()
        WL, DWL, WR, DWR, SID = py[10:15]
        grass = _surf.GRASS_ID
        out = []
        for x, y in points:
            r = self.track_point(x, y, chord)
            if r is None:
                return None
            _, d, c, t = r
            out.append(SID[c] if -(WR[c] + t * DWR[c]) <= d <= WL[c] + t * DWL[c] else grass)
        return out

    # ------------------------------------------------------------------ variants and checks
    def with_surface(self, name: str) -> "Track":
        """The same layout with every road stretch on surface ``name``."""
        sid = _surf.surface_id(name)
        if sid == _surf.GRASS_ID:
            raise ValueError(f"grass is what lies off the track; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
        return Track(self.name, self.xy, self.w_left, self.w_right, np.full(len(self.xy), sid), self.kappa,
                     default_surface=name, description=self.description, source=self.source, character=self.character)

    @property
    def surface_stretches(self) -> list[tuple[float, float, str]]:
        """Stretches of one surface as ``(s_start, s_end, name)`` [m]."""
        ids = self.surface_ids
        starts = np.flatnonzero(ids != np.roll(ids, 1))
        if len(starts) == 0:
            return [(0.0, self.length, _surf.SURFACE_NAMES[int(ids[0])])]
        out = []
        for k, i in enumerate(starts):
            j = starts[(k + 1) % len(starts)]
            out.append((float(self.s[i]), float(self.s[j]) if j > i else float(self.s[j]) + self.length,
                        _surf.SURFACE_NAMES[int(ids[i])]))
        return out

    def validate(self, min_width_m: float = MIN_TRACK_WIDTH_M) -> "Track":
        """Check the track can be driven; raise :class:`TrackError` naming the problem.

        Checks: widths positive and at least ``min_width_m`` in total; every surface a road
        surface; the inner edge never folds (half-width below the local radius on the inside of
        every bend); the centreline does not cross itself and the edges of distant stretches never
        overlap (neither does any point come closer than the sum of the two half-widths).
        """
        where = self._where()
        if (self.w_left <= 0).any() or (self.w_right <= 0).any():
            raise TrackError(f"{where}: widths must be positive")
        total = self.w_left + self.w_right
        if total.min() < min_width_m:
            i = int(np.argmin(total))
            raise TrackError(f"{where}: width {total[i]:.2f} m at s = {self.s[i]:.0f} m is below the car's minimum "
                             f"track width of {min_width_m} m")
        bad_surf = set(np.unique(self.surface_ids)) - {_surf.surface_id(n) for n in _surf.ROAD_SURFACES}
        if bad_surf:
            raise TrackError(f"{where}: surface ids {sorted(bad_surf)} are not road surfaces ({', '.join(_surf.ROAD_SURFACES)})")
        inner = np.where(self.kappa > 0, self.w_left, self.w_right)
        fold = inner * np.abs(self.kappa)
        if fold.max() >= 0.98:
            i = int(np.argmax(fold))
            raise TrackError(f"{where}: the inner edge folds at s = {self.s[i]:.0f} m (radius {1 / abs(self.kappa[i]):.1f} m "
                             f"is below the half-width {inner[i]:.1f} m)")
        self._check_overlap(where)
        return self

    def _check_overlap(self, where: str) -> None:
        # deferred: scipy.spatial (~1 s to import) only when a track is projected or checked
        from scipy.spatial import cKDTree

        half = np.maximum(self.w_left, self.w_right)
        reach = 2.0 * half.max() + 1.0
        pairs = cKDTree(self.xy).query_pairs(r=reach, output_type="ndarray")
        if len(pairs) == 0:
            return
        i, j = pairs[:, 0], pairs[:, 1]
        along = np.abs(self.wrap_delta(self.s[j], self.s[i]))
        # Stretches closer along the track than ~π·half-width are the same bend, not a crossing.
        far = along > np.pi * (half[i] + half[j]) + 2.0 * self.ds
        dist = np.hypot(*(self.xy[i] - self.xy[j]).T)
        clash = far & (dist < half[i] + half[j] + 0.5)
        if clash.any():
            k = int(np.flatnonzero(clash)[np.argmin(dist[clash])])
            what = "crosses itself" if dist[k] < 1.0 else "has overlapping edges"
            raise TrackError(f"{where}: the track {what} near s = {self.s[i[k]]:.0f} m and s = {self.s[j[k]]:.0f} m "
                             f"(centrelines {dist[k]:.1f} m apart)")

    def summary(self) -> dict:
        """A few numbers that characterise the track (for tables and plots)."""
        r = 1.0 / np.maximum(np.abs(self.kappa), 1e-9)
        return {
            "name": self.name,
            "length_m": round(self.length, 1),
            "width_m": round(float(np.mean(self.w_left + self.w_right)), 1),
            "min_radius_m": round(float(r.min()), 1),
            "surface": self.default_surface,
            "surfaces": sorted({st[2] for st in self.surface_stretches}),
            "character": self.character,
        }
