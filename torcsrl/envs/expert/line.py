"""The lines the expert drives: :func:`racing_line`, a minimum-curvature line inside the track (squared curvature
linearised in the centreline's Frenet frame: a bound-constrained quadratic programme, solved by projected Newton
steps), optionally traded against length, or the centreline; :class:`RacingLine` holds one.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from torcsrl.envs import surfaces as surf
from torcsrl.envs.track import Track

__all__ = ["LINES", "RacingLine", "racing_line"]

#: The lines the expert can follow: the racing line, or the centre of the road.
LINES = ("racing", "centre")
#: Half-width [m] of the band about the middle of the road the racing line may use where the road
#: is narrower than twice its edge margin.
_MIN_BAND_M = 0.05
#: Solved line offsets by (geometry hash, margin, length weight): a line costs ~1 s to solve.
_LINE_CACHE: dict[tuple[str, float, float], np.ndarray] = {}


# --------------------------------------------------------------------------------------------
# Lines and speed profiles
# --------------------------------------------------------------------------------------------
@dataclass
class RacingLine:
    """A closed driving line, one point per centreline sample of its track.

    Attributes:
        track_s: track arc length of each point ``[M]`` [m] (the track's samples).
        d: lateral offset from the centreline ``[M]`` [m] (> 0 left).
        xy: world points ``[M, 2]`` [m].
        ds: line length from each point to the next ``[M]`` [m].
        kappa: signed line curvature ``[M]`` [1/m] (> 0 turning left).
        mu: friction coefficient of the road under each point ``[M]`` [-].
        crr: rolling-resistance coefficient under each point ``[M]`` [-].
    """

    track_s: np.ndarray
    d: np.ndarray
    xy: np.ndarray
    ds: np.ndarray
    kappa: np.ndarray
    mu: np.ndarray
    crr: np.ndarray

    @property
    def length(self) -> float:
        """Line length [m]."""
        return float(self.ds.sum())


def _line_geometry(xy: np.ndarray, smooth: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Segment lengths and signed curvature (heading change per length, lightly smoothed) of a closed polyline."""
    seg = np.roll(xy, -1, axis=0) - xy
    ds = np.hypot(seg[:, 0], seg[:, 1])
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    turn = (heading - np.roll(heading, 1) + np.pi) % (2 * np.pi) - np.pi
    kappa = turn / np.maximum(0.5 * (ds + np.roll(ds, 1)), 1e-9)
    if smooth > 0:
        k = 2 * smooth + 1
        kappa = np.convolve(np.concatenate([kappa[-smooth:], kappa, kappa[:smooth]]), np.ones(k) / k, mode="valid")
    return ds, kappa


def _min_curvature_offsets(kappa_c: np.ndarray, ds: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                           length_weight: float = 0.0, relinearise: int = 3, max_iter: int = 60) -> np.ndarray:
    """Lateral offsets ``d [M]`` of the closed line minimising ``0.5 * sum kappa^2 ds + w * length``,
    ``lo <= d <= hi``, with ``w = length_weight`` [1/m^2] (0: the minimum-curvature line).

    In the centreline's Frenet frame (curvature ``kappa_c``, spacing ``ds``) a line of offset
    ``d(s)`` has curvature ``kappa ~= kappa_c / (1 - kappa_c d) + d''`` (small d'). Linearised
    about the previous solution this is affine in d, so ``sum kappa^2 ds`` is a bound-constrained
    convex quadratic with a cyclic banded Hessian, solved by projected Newton steps (sparse
    direct solves on the free variables, Armijo search along the projection arc), and
    re-linearised a few times. The line's length ``sum (1 - kappa_c d) ds`` is affine in d too.
    """
    m = len(kappa_c)
    h = float(np.mean(ds))
    idx = np.arange(m)
    rows = np.concatenate([idx, idx, idx])
    cols = np.concatenate([(idx - 1) % m, idx, (idx + 1) % m])
    d2 = sparse.csr_matrix((np.concatenate([np.ones(m), -2.0 * np.ones(m), np.ones(m)]) / h**2, (rows, cols)),
                           shape=(m, m))
    w = sparse.diags(np.sqrt(ds))
    d = np.clip(np.zeros(m), lo, hi)
    for _ in range(relinearise):
        denom = np.maximum(1.0 - kappa_c * d, 0.05)
        slope = kappa_c**2 / denom**2  # d kappa / d d at the linearisation point
        const = kappa_c / denom - slope * d
        a = (w @ (sparse.diags(slope) + d2)).tocsr()
        b = w @ const
        hess = (a.T @ a).tocsc() + 1e-12 * sparse.identity(m, format="csc")
        length_grad = -length_weight * kappa_c * ds
        lin = a.T @ b + length_grad

        def cost(x: np.ndarray) -> float:
            r = a @ x + b
            return 0.5 * float(r @ r) + float(length_grad @ x)

        # Projected Newton with an Armijo search along the projection arc (Bertsekas 1982).
        x = d
        fx = cost(x)
        for _ in range(max_iter):
            grad = hess @ x + lin
            eps = min(1e-3, float(np.abs(x - np.clip(x - grad, lo, hi)).max()))
            fixed = ((x <= lo + eps) & (grad > 0)) | ((x >= hi - eps) & (grad < 0))
            free = ~fixed
            step = np.zeros(m)
            step[free] = spsolve(hess[free][:, free].tocsc(), -grad[free])
            alpha = 1.0
            while True:
                new = np.clip(x + alpha * step, lo, hi)
                f_new = cost(new)
                if f_new <= fx + 1e-4 * float(grad @ (new - x)) or alpha < 1e-6:
                    break
                alpha *= 0.5
            moved = float(np.abs(new - x).max())
            if f_new <= fx:
                x, fx = new, f_new
            if moved < 1e-7:
                break
        d = x
    return d


def racing_line(track: Track, kind: str = "racing", margin_m: float = 2.2, mu: float | None = None,
                length_weight: float = 0.0) -> RacingLine:
    """A closed line on ``track``: ``"racing"`` (minimum curvature) or ``"centre"``.

    The minimum-curvature line minimises the integral of its squared curvature over offsets
    ``d`` from the centreline with ``-w_right + margin <= d <= w_left - margin`` (where the road
    is narrower than ``2 * margin_m``: within 5 cm of the middle of the road; see
    :func:`_min_curvature_offsets`), where ``margin_m`` [m] keeps the car's centre that far
    from the edges; ``length_weight`` [1/m^2] > 0 trades curvature for a shorter line (see
    :func:`_min_curvature_offsets`). ``mu`` overrides the friction of the track's surfaces (else each stretch's own surface).
    """
    if kind not in LINES:
        raise ValueError(f"line must be one of {', '.join(LINES)}, got {kind!r}")
    c = track.xy
    m = len(c)
    normal = track.normal(track.s)
    if kind == "centre":
        d = np.zeros(m)
    else:
        # Where the road is narrower than twice the margin, the line keeps to a narrow band about
        # the middle of the road instead (a 4 m road leaves ~1.2 m either side of a car's wheels).
        mid = 0.5 * (track.w_left - track.w_right)
        lo = np.minimum(-track.w_right + margin_m, mid - _MIN_BAND_M)
        hi = np.maximum(track.w_left - margin_m, mid + _MIN_BAND_M)
        key = (hashlib.sha1(np.ascontiguousarray(np.stack([c[:, 0], c[:, 1], track.w_left, track.w_right,
                                                             track.kappa])).tobytes()).hexdigest(),
               float(margin_m), float(length_weight))
        d = _LINE_CACHE.get(key)
        if d is None:
            ds = np.roll(track.s, -1) - track.s + np.where(np.arange(m) == m - 1, track.length, 0.0)
            d = _min_curvature_offsets(track.kappa, ds, lo, hi, length_weight)
            if len(_LINE_CACHE) >= 128:
                _LINE_CACHE.pop(next(iter(_LINE_CACHE)))
            _LINE_CACHE[key] = d
        d = d.copy()
    xy = c + d[:, None] * normal
    ds, kappa = _line_geometry(xy)
    ids = track.surface_ids
    mu_arr = np.full(m, float(mu)) if mu is not None else surf.MU[ids].astype(float)
    return RacingLine(track.s.copy(), d, xy, ds, kappa, mu_arr, surf.ROLLING_RESISTANCE[ids].astype(float))
