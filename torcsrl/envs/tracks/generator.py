"""Seeded procedural tracks.

``generate(seed, length_m=…, corners=…, min_radius_m=…, width_m=…)`` returns a valid
:class:`~torcsrl.envs.track.Track`: closed, not self-intersecting, edges that never overlap and
no bend tighter than ``min_radius_m``. The same seed and knobs always give the same track.

Method: ``corners`` control points around a circle, at jittered angles and random radii, are
joined by a periodic cubic spline and scaled to the requested length. A layout that breaks a rule
is first relaxed (its radii pulled towards the circle, which opens its bends), and if that is not
enough a fresh layout is drawn from the next sub-seed. Everything is drawn from
``numpy.random.default_rng([seed, attempt])``.
"""

from __future__ import annotations

import numpy as np

from torcsrl.envs import surfaces as _surf
from torcsrl.envs.track import Track, TrackError
from torcsrl.envs.tracks.sources import SAMPLE_SPACING_M

KNOB_RANGES = {
    "length_m": (500.0, 8000.0),
    "corners": (3, 40),
    "min_radius_m": (8.0, 300.0),
    "width_m": (4.0, 30.0),
}
MAX_ATTEMPTS = 60


def _check_knobs(length_m, corners, min_radius_m, width_m, surface) -> None:
    for name, value in (("length_m", length_m), ("corners", corners), ("min_radius_m", min_radius_m), ("width_m", width_m)):
        lo, hi = KNOB_RANGES[name]
        if not (lo <= value <= hi):
            raise ValueError(f"generate: {name}={value!r} is outside the allowed range [{lo}, {hi}]")
    if 0.5 * width_m >= 0.98 * min_radius_m:
        raise ValueError(f"generate: min_radius_m={min_radius_m} must exceed half the width ({0.5 * width_m} m)")
    if surface not in _surf.ROAD_SURFACES:
        raise ValueError(f"generate: unknown surface {surface!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")


def _layout(rng: np.random.Generator, corners: int, relax: float, length_m: float, ds: float):
    from scipy.interpolate import splev, splprep

    base = np.linspace(0.0, 2.0 * np.pi, corners, endpoint=False)
    theta = base + rng.uniform(-0.4, 0.4, corners) * (2.0 * np.pi / corners)
    radius = 1.0 + relax * rng.uniform(-0.6, 0.6, corners)
    ctrl = np.stack([radius * np.cos(theta), radius * np.sin(theta)], axis=1)
    closed = np.vstack([ctrl, ctrl[:1]])
    tck, _ = splprep(closed.T, s=0.0, per=True, k=3)
    dense = np.linspace(0.0, 1.0, 400 * corners, endpoint=False)
    x, y = splev(dense, tck)
    seg = np.hypot(np.diff(np.append(x, x[0])), np.diff(np.append(y, y[0])))
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    scale = length_m / cum[-1]
    count = int(round(length_m / ds))
    u = np.interp(np.arange(count) * (cum[-1] / count), cum, np.append(dense, 1.0))
    x, y = splev(u, tck)
    dx, dy = splev(u, tck, der=1)
    ddx, ddy = splev(u, tck, der=2)
    kappa = (dx * ddy - dy * ddx) / np.power(dx * dx + dy * dy, 1.5) / scale
    return np.stack([x, y], axis=1) * scale, kappa


def generate(seed: int, length_m: float = 3000.0, corners: int = 10, min_radius_m: float = 25.0,
             width_m: float = 12.0, surface: str = "asphalt", name: str | None = None) -> Track:
    """A valid procedural track, deterministic per ``seed`` and knobs.

    Args:
        seed: integer seed (the same seed and knobs give the same track).
        length_m: lap length [m] (500–8000).
        corners: number of control points, roughly the number of bends (3–40).
        min_radius_m: no bend tighter than this radius [m] (8–300, above half the width).
        width_m: total track width [m] (4–30).
        surface: road surface of the whole lap.
        name: track name (default ``gen-<seed>``).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"generate: seed must be a non-negative integer, got {seed!r}")
    _check_knobs(length_m, corners, min_radius_m, width_m, surface)
    sid = _surf.surface_id(surface)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([int(seed), attempt])
        state = rng.bit_generator.state
        for relax in (1.0, 0.7, 0.5, 0.35):
            rng.bit_generator.state = state  # the same draw, progressively relaxed
            xy, kappa = _layout(rng, int(corners), relax, float(length_m), SAMPLE_SPACING_M)
            if 1.0 / np.abs(kappa).max() < min_radius_m:
                continue
            track = Track(name or f"gen-{seed}", xy, 0.5 * width_m, 0.5 * width_m, np.full(len(xy), sid), kappa,
                          default_surface=surface, description=f"procedural track (seed {seed})",
                          source=f"generator(seed={seed}, length_m={length_m}, corners={corners}, "
                                 f"min_radius_m={min_radius_m}, width_m={width_m})", character="procedural")
            if _signed_area(xy) < 0:  # always drive anticlockwise
                track = _reverse(track)
            try:
                return track.validate()
            except TrackError:
                break
    raise ValueError(f"generate: no valid track found for seed {seed} with these knobs after {MAX_ATTEMPTS} "
                     f"layouts; try a larger length_m or a smaller min_radius_m / width_m")


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _reverse(track: Track) -> Track:
    xy = np.roll(track.xy[::-1], 1, axis=0)
    k = -np.roll(track.kappa[::-1], 1)
    return Track(track.name, xy, np.roll(track.w_right[::-1], 1), np.roll(track.w_left[::-1], 1),
                 np.roll(track.surface_ids[::-1], 1), k, default_surface=track.default_surface,
                 description=track.description, source=track.source, character=track.character)
