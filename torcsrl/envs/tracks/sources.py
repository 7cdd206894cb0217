"""Track sources: TORCS-style segment lists and centreline point files, both read from data.

**Segment lists** (YAML)::

    name: oval
    description: A simple oval: two straights and two constant-radius bends.
    character: oval
    surface: asphalt          # default surface of every stretch
    width: 14                 # total width [m]; or w_left / w_right [m]
    segments:
      - {type: straight, length: 500}
      - {type: arc, radius: 120, angle: 180, turn: left}          # angle in degrees
      - {type: straight, length: 200, surface: dirt, width: 12}   # per-segment overrides

The loop starts at the origin heading along +x and must close: the end of the last segment must
land within 1 m of the start with the heading turned by ±360°. The closing error is reported, and
a residual below 1 m is spread linearly along the lap.

**Centreline point files** (CSV, the common public format for real circuits): columns x, y and
the two widths, named in a ``#`` header line (``x_m, y_m, w_tr_right_m, w_tr_left_m`` as in the
TUM racetrack database, or ``x, y, w_left, w_right``). A sidecar YAML names the file
(``points: circuit.csv``) with the same metadata keys as a segment list plus ``smoothing`` (the
periodic spline's smoothing factor per point [m²]). The points are smoothed by a periodic cubic
spline and resampled every metre.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from torcsrl.envs import surfaces as _surf
from torcsrl.envs.track import Track, TrackError

#: Sample spacing of the centreline [m].
SAMPLE_SPACING_M = 1.0
#: Largest closing error a segment list may have [m].
MAX_CLOSING_ERROR_M = 1.0
#: Longest lap a track file may describe [m] (the longest bundled track is 5.6 km); checked before sampling,
#: so an absurd length fails at once instead of allocating one sample per metre.
MAX_TRACK_LENGTH_M = 100_000.0
#: Widest a road may be [m], either side of the centreline.
MAX_HALF_WIDTH_M = 100.0

_META_KEYS = {"name", "description", "character", "surface", "width", "w_left", "w_right"}
_SEGMENT_KEYS = {"type", "length", "radius", "angle", "turn", "width", "w_left", "w_right", "surface"}


def _widths(spec: dict, default: tuple[float, float], where: str) -> tuple[float, float]:
    if "w_left" in spec or "w_right" in spec:
        try:
            w = float(spec.get("w_left", default[0])), float(spec.get("w_right", default[1]))
        except (TypeError, ValueError):
            raise TrackError(f"{where}: w_left / w_right must be numbers [m]") from None
    elif "width" in spec:
        try:
            full = float(spec["width"])
        except (TypeError, ValueError):
            raise TrackError(f"{where}: width must be a number [m], got {spec['width']!r}") from None
        w = 0.5 * full, 0.5 * full
    else:
        return default
    if not all(math.isfinite(x) and 0 < x <= MAX_HALF_WIDTH_M for x in w):
        raise TrackError(f"{where}: widths must be finite and positive, at most {2 * MAX_HALF_WIDTH_M:g} m in all; got "
                         f"w_left {w[0]:g} m, w_right {w[1]:g} m")
    return w


def _surface(spec: dict, default: int, where: str) -> int:
    if "surface" not in spec:
        return default
    name = spec["surface"]
    if name not in _surf.ROAD_SURFACES:
        raise TrackError(f"{where}: unknown surface {name!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
    return _surf.surface_id(name)


def read_yaml(path: Path) -> dict:
    """Read a track's YAML file into a dict, naming the file on any problem."""
    try:
        raw = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        raise TrackError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
    except UnicodeDecodeError:
        raise TrackError(f"{path}: not a text file (binary content); a track file is YAML with 'segments' or 'points'") from None
    except OSError as err:
        raise TrackError(f"{path}: cannot read ({err.strerror})") from None
    if not isinstance(raw, dict):
        raise TrackError(f"{path}: expected a mapping with 'segments' or 'points', got {type(raw).__name__}")
    return raw


def _meta(raw: dict, path: Path) -> tuple[str, tuple[float, float], int]:
    surface = raw.get("surface", "asphalt")
    if surface not in _surf.ROAD_SURFACES:
        raise TrackError(f"{path}: unknown surface {surface!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
    if not any(k in raw for k in ("width", "w_left", "w_right")) and "points" not in raw:
        raise TrackError(f"{path}: give the track's width [m] (width, or w_left and w_right)")
    w = _widths(raw, (6.0, 6.0), str(path))
    return surface, w, _surf.surface_id(surface)


def segments_to_track(raw: dict, path: Path | str = "<segments>", ds: float = SAMPLE_SPACING_M) -> Track:
    """Build a :class:`Track` from a parsed segment list (see the module docstring)."""
    path = Path(path) if not isinstance(path, Path) else path
    segs = raw.get("segments")
    if not isinstance(segs, list) or not segs:
        raise TrackError(f"{path}: 'segments' must be a non-empty list of straights and arcs")
    surface, w_default, sid_default = _meta(raw, path)
    pts, kap, wl, wr, sid = [], [], [], [], []
    x = y = heading = 0.0
    total_turn = 0.0
    lap_m = 0.0  # length so far [m]
    prev_k = None
    for n, seg in enumerate(segs, start=1):
        where = f"{path}: segment {n}"
        if not isinstance(seg, dict):
            raise TrackError(f"{where}: expected a mapping like {{type: straight, length: 100}}, got {seg!r}")
        unknown = set(seg) - _SEGMENT_KEYS
        if unknown:
            raise TrackError(f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(_SEGMENT_KEYS)}")
        kind = seg.get("type")
        w = _widths(seg, w_default, where)
        s_id = _surface(seg, sid_default, where)
        try:
            if kind == "straight":
                length = float(seg["length"])
                k = 0.0
            elif kind == "arc":
                radius = float(seg["radius"])
                angle = np.radians(float(seg["angle"]))
                turn = seg.get("turn")
                if turn not in ("left", "right"):
                    raise TrackError(f"{where}: an arc needs turn: left or right, got {turn!r}")
                if radius <= 0 or angle <= 0:
                    raise TrackError(f"{where}: an arc needs a positive radius [m] and angle [deg]")
                length = radius * angle
                k = (1.0 if turn == "left" else -1.0) / radius
            else:
                raise TrackError(f"{where}: type must be 'straight' or 'arc', got {kind!r}")
        except KeyError as err:
            raise TrackError(f"{where}: a {kind} needs {err.args[0]!r}") from None
        except (TypeError, ValueError) as err:
            if isinstance(err, TrackError):
                raise
            raise TrackError(f"{where}: length, radius and angle must be numbers") from None
        if not math.isfinite(length) or length <= 0 or (kind == "arc" and not math.isfinite(radius)):
            raise TrackError(f"{where}: length, radius and angle must be finite and positive, got "
                             + ", ".join(f"{k} {seg[k]!r}" for k in ("length", "radius", "angle") if k in seg))
        lap_m += length
        if lap_m > MAX_TRACK_LENGTH_M:
            raise TrackError(f"{where}: the segments add up to {lap_m:.4g} m; allowed: a lap of at most {MAX_TRACK_LENGTH_M:g} m")
        count = max(1, int(np.ceil(length / ds)))
        u = np.arange(count) * (length / count)  # arc length into the segment of each sample
        if k == 0.0:
            px = x + u * np.cos(heading)
            py = y + u * np.sin(heading)
        else:
            r = 1.0 / k
            px = x + r * (np.sin(heading + k * u) - np.sin(heading))
            py = y - r * (np.cos(heading + k * u) - np.cos(heading))
        ks = np.full(count, k)
        if prev_k is not None:
            ks[0] = 0.5 * (k + prev_k)
        pts.append(np.stack([px, py], axis=1))
        kap.append(ks)
        wl.append(np.full(count, w[0]))
        wr.append(np.full(count, w[1]))
        sid.append(np.full(count, s_id))
        if k == 0.0:
            x, y = x + length * np.cos(heading), y + length * np.sin(heading)
        else:
            r = 1.0 / k
            x, y = x + r * (np.sin(heading + k * length) - np.sin(heading)), y - r * (np.cos(heading + k * length) - np.cos(heading))
        heading += k * length
        total_turn += k * length
        prev_k = k
    kap[0][0] = 0.5 * (kap[0][0] + prev_k)
    xy = np.concatenate(pts)
    turn_deg = np.degrees(total_turn)
    if abs(abs(turn_deg) - 360.0) > 0.5:
        raise TrackError(f"{path}: the segments turn {turn_deg:.1f}° in total; a closed loop turns ±360°")
    gap = np.hypot(x, y)
    if gap > MAX_CLOSING_ERROR_M:
        raise TrackError(f"{path}: the loop does not close: its end is {gap:.2f} m from its start "
                         f"(({x:.2f}, {y:.2f}) m); at most {MAX_CLOSING_ERROR_M} m is allowed")
    seg_len = np.hypot(*np.diff(np.vstack([xy, xy[:1]]), axis=0).T)
    frac = np.concatenate([[0.0], np.cumsum(seg_len)[:-1]]) / seg_len.sum()
    xy = xy - frac[:, None] * np.array([x, y])[None, :]
    wl_a, wr_a = _smooth_widths(np.concatenate(wl), ds), _smooth_widths(np.concatenate(wr), ds)
    track = Track(str(raw.get("name", Path(path).stem)), xy, wl_a, wr_a, np.concatenate(sid), np.concatenate(kap),
                  default_surface=surface, description=str(raw.get("description", "")), source=str(path),
                  character=str(raw.get("character", "")))
    track.closing_error_m = float(gap)
    return track


def _smooth_widths(w: np.ndarray, ds: float, span_m: float = 20.0) -> np.ndarray:
    """Taper width changes over ``span_m`` so the edges have no steps (a circular moving average)."""
    if np.ptp(w) == 0:
        return w
    k = max(1, int(round(span_m / ds)))
    kernel = np.ones(k) / k
    padded = np.concatenate([w[-k:], w, w[:k]])
    return np.convolve(padded, kernel, mode="same")[k:-k]


def _read_points(path: Path) -> np.ndarray:
    """Read a centreline CSV into columns (x, y, w_left, w_right) [m]."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise TrackError(f"{path}: not a text file (binary content); expected CSV rows x_m, y_m, w_tr_right_m, w_tr_left_m") from None
    except OSError as err:
        raise TrackError(f"{path}: cannot read ({err.strerror})") from None
    header = None
    rows = []
    for ln, line in enumerate(lines, start=1):
        text = line.strip()
        if not text:
            continue
        if text.startswith("#"):
            if header is None and "," in text:
                header = [h.strip().lower() for h in text.lstrip("#").split(",")]
            continue
        try:
            rows.append([float(v) for v in text.split(",")])
        except ValueError:
            raise TrackError(f"{path}: line {ln} is not a row of numbers: {text[:60]!r}") from None
    if not rows:
        raise TrackError(f"{path}: no points")
    width = {len(r) for r in rows}
    if width != {4}:
        raise TrackError(f"{path}: every row needs 4 columns (x, y and two widths), found {sorted(width)}")
    data = np.array(rows)
    order = ["x_m", "y_m", "w_tr_right_m", "w_tr_left_m"]  # the TUM racetrack-database layout
    if header is not None:
        names = {"x": "x_m", "y": "y_m", "w_left": "w_tr_left_m", "w_right": "w_tr_right_m"}
        header = [names.get(h, h) for h in header]
        if sorted(header) != sorted(order):
            raise TrackError(f"{path}: header {header} must name x, y, w_left, w_right "
                             f"(or x_m, y_m, w_tr_right_m, w_tr_left_m)")
        order = header
    col = {name: data[:, i] for i, name in enumerate(order)}
    if not np.isfinite(data).all():
        raise TrackError(f"{path}: non-finite values")
    return np.stack([col["x_m"], col["y_m"], col["w_tr_left_m"], col["w_tr_right_m"]], axis=1)


def points_to_track(raw: dict, path: Path, ds: float = SAMPLE_SPACING_M) -> Track:
    """Build a :class:`Track` from a sidecar YAML naming a centreline point file."""
    # deferred: scipy.interpolate only when a track is fitted
    from scipy.interpolate import splev, splprep

    csv = Path(path).parent / str(raw["points"])
    pts = _read_points(csv)
    if np.allclose(pts[0, :2], pts[-1, :2], atol=1e-6):
        pts = pts[:-1]
    if len(pts) < 8:
        raise TrackError(f"{csv}: a closed centreline needs at least 8 points, got {len(pts)}")
    step = np.hypot(*np.diff(pts[:, :2], axis=0).T)
    gap = float(np.hypot(*(pts[0, :2] - pts[-1, :2])))
    spacing = float(np.median(step))
    if gap > 3.0 * spacing + 1.0:
        raise TrackError(f"{csv}: the centreline does not close: the last point is {gap:.1f} m from the first "
                         f"(points are {spacing:.1f} m apart)")
    if (pts[:, 2:] <= 0).any() or (pts[:, 2:] > MAX_HALF_WIDTH_M).any():
        raise TrackError(f"{csv}: widths must be positive and at most {MAX_HALF_WIDTH_M:g} m each side")
    perimeter = float(step.sum() + gap)
    if perimeter > MAX_TRACK_LENGTH_M:
        raise TrackError(f"{csv}: the centreline is {perimeter:.4g} m long; allowed: a lap of at most {MAX_TRACK_LENGTH_M:g} m")
    surface, _, sid = _meta(raw, path)
    smoothing = float(raw.get("smoothing", 0.5)) * len(pts)
    closed = np.vstack([pts, pts[:1]])
    try:
        tck, _ = splprep(closed.T, s=smoothing, per=True, k=3)
    except Exception as err:  # scipy raises several types for degenerate input
        raise TrackError(f"{csv}: cannot fit a periodic spline to the points ({err})") from None
    dense = np.linspace(0.0, 1.0, 20 * len(pts), endpoint=False)
    x, y = splev(dense, tck)[:2]
    seg = np.hypot(np.diff(np.append(x, x[0])), np.diff(np.append(y, y[0])))
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    length = cum[-1]
    count = int(round(length / ds))
    u = np.interp(np.arange(count) * (length / count), cum, np.append(dense, 1.0))
    x, y, wl, wr = splev(u, tck)
    dx, dy, *_ = splev(u, tck, der=1)
    ddx, ddy, *_ = splev(u, tck, der=2)
    kappa = (dx * ddy - dy * ddx) / np.power(dx * dx + dy * dy, 1.5)
    track = Track(str(raw.get("name", Path(path).stem)), np.stack([x, y], axis=1), wl, wr, np.full(count, sid), kappa,
                  default_surface=surface, description=str(raw.get("description", "")), source=str(csv),
                  character=str(raw.get("character", "")))
    if np.degrees(abs(np.sum(np.diff(np.unwrap(np.append(track.heading_samples, track.heading_samples[0])))))) < 359:
        raise TrackError(f"{csv}: the centreline does not make one loop")
    return track


def load_file(path: Path | str) -> Track:
    """Load and validate a track file: a segment list, or a sidecar naming a point file."""
    path = Path(path)
    raw = read_yaml(path)
    unknown = set(raw) - _META_KEYS - {"segments", "points", "smoothing"}
    if unknown:
        raise TrackError(f"{path}: unknown keys {sorted(unknown)}; allowed: {sorted(_META_KEYS | {'segments', 'points', 'smoothing'})}")
    if "segments" in raw:
        track = segments_to_track(raw, path)
    elif "points" in raw:
        track = points_to_track(raw, path)
    else:
        raise TrackError(f"{path}: a track file needs 'segments' (a segment list) or 'points' (a CSV file name)")
    return track.validate()
