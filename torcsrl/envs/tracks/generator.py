"""Seeded procedural tracks.

``generate(seed, length_m=…, corners=…, min_radius_m=…, width_m=…)`` returns a valid
:class:`~torcsrl.envs.track.Track`: closed, not self-intersecting, edges that never overlap and
no bend tighter than ``min_radius_m``. The same seed and knobs always give the same track.

``generate_circuit(seed, difficulty=…, …)`` returns a valid race circuit with the features real
circuits have (hairpins, chicanes, long straights into tight bends, decreasing-radius bends,
narrow sections), built from straights, arcs and clothoids; see its docstring. The rest of this
note is about ``generate``.

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
    # deferred: scipy.interpolate only when a track is generated
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


# ====================================================================== circuits
#: Allowed range of every :func:`generate_circuit` knob (inclusive); counts are integers.
CIRCUIT_KNOB_RANGES = {
    "difficulty": (0.0, 1.0),
    "length_m": (1000.0, 8000.0),
    "width_m": (8.0, 25.0),
    "hairpins": (0, 6),
    "chicanes": (0, 8),
    "long_straights": (0, 4),
    "decreasing_radius": (0, 6),
    "narrow_sections": (0, 6),
    "min_radius_m": (12.0, 150.0),
}
_COUNT_KNOBS = ("hairpins", "chicanes", "long_straights", "decreasing_radius", "narrow_sections")
#: Layouts tried per circuit; the seed-drawn features are thinned after half and three quarters.
CIRCUIT_MAX_ATTEMPTS = 40
_RELAX_AT = (CIRCUIT_MAX_ATTEMPTS // 2, 3 * CIRCUIT_MAX_ATTEMPTS // 4)
#: Steepest change of curvature along a circuit [1/m²]: a bend of radius R is entered over at
#: least 1 / (R · this) metres of clothoid (8.3 m for 12 m), so the curvature never jumps.
CURVATURE_RATE_MAX = 0.01
#: Shortest long straight [m] (its straight part: the clothoids of the bends are not counted).
LONG_STRAIGHT_M = 320.0
_MIN_STRAIGHT_M = 15.0  # shortest straight between two bends [m]
_LONG_LEG_M = (330.0, 480.0)  # straight part of a hairpin finger's way out [m], long straight or not
_SHORT_LEG_M = (60.0, 200.0)
_FINGER_SHARE = 0.55  # largest share of the lap in hairpin fingers
_DRAWN_LENGTH_M = (1500.0, 5000.0)  # range of a seed-drawn lap length [m]
_PROC_TAG = 0x70726F63  # "proc": keeps these random streams apart from generate()'s


def _fmt(value) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def _check_circuit_knobs(knobs: dict, surface: str) -> None:
    for name, value in knobs.items():
        if value is None:
            continue
        lo, hi = CIRCUIT_KNOB_RANGES[name]
        if name in _COUNT_KNOBS:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"generate_circuit: {name}={_fmt(value)} must be an integer in the allowed range "
                                 f"[{lo}, {hi}]")
        elif isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"generate_circuit: {name}={_fmt(value)} must be a number in the allowed range "
                             f"[{lo:g}, {hi:g}]")
        if not (lo <= value <= hi):
            raise ValueError(f"generate_circuit: {name}={_fmt(value)} is outside the allowed range [{lo:g}, {hi:g}]")
    w, r = knobs["width_m"], knobs["min_radius_m"]
    if w is not None and r is not None and 0.5 * w > 0.9 * r:
        raise ValueError(f"generate_circuit: min_radius_m={_fmt(r)} must be at least {0.5 * w / 0.9:.1f} m with "
                         f"width_m={_fmt(w)} (the inner edge of the tightest bend would fold)")
    if surface not in _surf.ROAD_SURFACES:
        raise ValueError(f"generate_circuit: unknown surface {surface!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")


def _lerp(a: float, b: float, t: float) -> float:
    return a + (b - a) * t


def seed_difficulty(seed: int) -> float:
    """The difficulty in [0, 1) that ``generate_circuit(seed)`` draws from its seed when none is given."""
    return float(np.random.default_rng([int(seed), _PROC_TAG, 0]).uniform(0.0, 1.0))


def circuit_plan(seed: int, knobs: dict) -> dict:
    """The circuit's numbers: every value is drawn from the seed in a fixed order, then a given knob
    replaces its own draw (so giving one knob leaves the other draws as they were)."""
    rng = np.random.default_rng([int(seed), _PROC_TAG, 0])
    d = float(rng.uniform(0.0, 1.0))  # = seed_difficulty(seed)
    if knobs["difficulty"] is not None:
        d = float(knobs["difficulty"])
    u = rng.uniform(0.0, 1.0, 8)
    drawn = {
        "min_radius_m": _lerp(60.0, 12.0, d) * (1.0 + 0.2 * u[0]),
        "width_m": _lerp(15.0, 11.0, d) + 2.0 * u[1] - 1.0,
        "hairpins": int(_lerp(0.0, 2.0, d) + 1.99 * u[2]),
        "chicanes": int(_lerp(0.0, 2.5, d) + 1.99 * u[3]),
        "long_straights": int(_lerp(1.0, 2.0, d) + 1.99 * u[4]),
        "decreasing_radius": int(_lerp(0.0, 1.5, d) + 1.99 * u[5]),
        "narrow_sections": int(_lerp(0.0, 2.0, d) + 1.5 * u[6]),
    }
    plan = {"difficulty": d}
    for key, value in drawn.items():
        plan[key] = knobs[key] if knobs[key] is not None else value
    if knobs["min_radius_m"] is None:  # the tightest bend must not fold the inner edge
        plan["min_radius_m"] = max(plan["min_radius_m"], 0.5 * plan["width_m"] / 0.85)
    plan["plain"] = int(_lerp(4.0, 6.0, d) + 3.99 * rng.uniform())  # polygon corners besides the fingers
    plan["plain"] = max(plan["plain"], _plain_needed(plan))
    # drawn features that do not fit the lap are dropped (a given knob never is)
    cap = float(knobs["length_m"]) if knobs["length_m"] is not None else _DRAWN_LENGTH_M[1]
    for key, keep in (("long_straights", 1), ("hairpins", 1), ("chicanes", 0), ("plain", None), ("long_straights", 0),
                      ("hairpins", 0), ("decreasing_radius", 0)):
        while (_circuit_need_m(plan) > cap and knobs.get(key) is None
               and plan[key] > (max(4, _plain_needed(plan)) if keep is None else keep)):
            plan[key] -= 1
    if knobs["length_m"] is not None:
        plan["length_m"] = float(knobs["length_m"])
    else:  # uniform up to 5 km from what the features need (more only for given features)
        lo = max(_DRAWN_LENGTH_M[0], _circuit_need_m(plan))
        hi = max(_DRAWN_LENGTH_M[1], min(lo, CIRCUIT_KNOB_RANGES["length_m"][1]))
        plan["length_m"] = min(lo, hi) + u[7] * (hi - min(lo, hi))
    return plan


def _plain_needed(plan: dict) -> int:
    """Polygon corners the plan needs besides the fingers: edges for its chicanes, corners to tighten."""
    extra_long = max(0, plan["long_straights"] - plan["hairpins"])
    return max(plan["chicanes"] + 2 - plan["hairpins"], plan["decreasing_radius"] + extra_long + 1)


def _circuit_need_m(plan: dict) -> float:
    """A lap length [m] that fits the plan's features: fingers within their share, the rest a polygon."""
    r = plan["min_radius_m"]
    n_long = min(plan["long_straights"], plan["hairpins"])
    leg = 2.2 * r + 10.0  # a finger's leg beyond its straight: the base bend's tangent
    fingers = (2.0 * n_long * (np.mean(_LONG_LEG_M) + leg) + plan["hairpins"] * np.pi * 1.15 * r
               + 2.0 * (plan["hairpins"] - n_long) * (np.mean(_SHORT_LEG_M) + leg))
    corners = plan["plain"] + 3 * plan["hairpins"]
    polygon = (corners * (60.0 + 2.0 * r) + (plan["long_straights"] - n_long) * 400.0
               + plan["chicanes"] * (90.0 + 3.0 * r))
    return max(fingers / _FINGER_SHARE, fingers + polygon)


def _relaxed(plan: dict, knobs: dict, level: int) -> dict:
    """``plan`` with fewer seed-drawn features: one fewer of each (level 1), or none but one long straight (2)."""
    out = dict(plan)
    for key in ("hairpins", "chicanes", "decreasing_radius", "long_straights"):
        if knobs[key] is None:
            out[key] = max(0, plan[key] - 1) if level == 1 else (min(1, plan[key]) if key == "long_straights" else 0)
    return out


# ---------------------------------------------------------------- curvature profiles
# A profile is an array of pieces [P, 3]: (length [m], curvature at its start [1/m], at its end
# [1/m]), linear in between: straights, arcs, clothoids and spirals. Heading and position follow
# by integration, so the curvature of a circuit is exact and continuous by construction.
def _bend(angle: float, radius: float, f: float) -> list:
    """A constant-radius bend turning ``angle`` [rad] (> 0 left), a share ``f`` of it in each clothoid."""
    a = abs(angle) * radius
    k = np.sign(angle) / radius
    return [(f * a, 0.0, k), ((1.0 - f) * a, k, k), (f * a, k, 0.0)]


def _decreasing(angle: float, r_in: float, r_out: float, rel: np.ndarray) -> list:
    """A bend turning ``angle`` [rad] that tightens from ``r_in`` to ``r_out`` [m]: clothoid in, spiral,
    arc, clothoid out, their lengths in the ratios ``rel``."""
    k1, k2 = np.sign(angle) / r_in, np.sign(angle) / r_out
    l1, l2, l3, l4 = rel
    c = angle / (0.5 * k1 * l1 + 0.5 * (k1 + k2) * l2 + k2 * l3 + 0.5 * k2 * l4)
    return [(c * l1, 0.0, k1), (c * l2, k1, k2), (c * l3, k2, k2), (c * l4, k2, 0.0)]


def _smooth_f(turn: float, r: float, f: float) -> float:
    """Clothoid share ``f`` of a bend of radius ``r`` [m], raised so dκ/ds stays within ``CURVATURE_RATE_MAX``."""
    return float(min(1.0, max(f, 1.0 / (abs(turn) * r * r * CURVATURE_RATE_MAX))))


def _rate_floor(turn: float, f: float) -> float:
    """Smallest radius [m] a bend with clothoid share ``f`` may have within ``CURVATURE_RATE_MAX``."""
    return 1.0 / np.sqrt(f * abs(turn) * CURVATURE_RATE_MAX)


def _max_rate(pieces: np.ndarray) -> float:
    """Largest |dκ/ds| of a profile [1/m²]."""
    p = pieces[pieces[:, 0] > 0.0]
    return float(np.max(np.abs(p[:, 2] - p[:, 1]) / p[:, 0]))


def _scaled(unit: np.ndarray, r: float) -> np.ndarray:
    """A profile built for radius 1 scaled to radius ``r`` [m] (lengths × r, curvatures ÷ r)."""
    return unit * np.array([r, 1.0 / r, 1.0 / r])


def _profile_eval(pieces: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Curvature [1/m] and heading [rad] (0 at s = 0) of a profile at arc lengths ``s`` [m]."""
    length, k0, k1 = pieces[:, 0], pieces[:, 1], pieces[:, 2]
    start = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    theta0 = np.concatenate([[0.0], np.cumsum(0.5 * (k0 + k1) * length)[:-1]])
    i = np.clip(np.searchsorted(start, s, side="right") - 1, 0, len(length) - 1)
    t = s - start[i]
    slope = np.divide(k1 - k0, length, out=np.zeros_like(length), where=length > 0.0)
    return k0[i] + slope[i] * t, theta0[i] + k0[i] * t + 0.5 * slope[i] * t * t


def _displacement(pieces: np.ndarray, step: float = 0.25) -> np.ndarray:
    """End point ``[2]`` [m] of a profile driven from the origin along +x (midpoint rule, ``step`` [m])."""
    total = float(pieces[:, 0].sum())
    n = max(1, int(np.ceil(total / step)))
    h = total / n
    _, th = _profile_eval(pieces, (np.arange(n) + 0.5) * h)
    return h * np.array([np.cos(th).sum(), np.sin(th).sum()])


def _rot(v: np.ndarray, th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _angle(v: np.ndarray) -> float:
    return float(np.arctan2(v[1], v[0]))


def _tangents(unit: np.ndarray, turn: float) -> tuple[float, float]:
    """Distances from a bend's start and end to its vertex, where its two lines meet [m per m of radius]."""
    dx, dy = _displacement(unit)
    t_out = dy / np.sin(turn)
    return dx - t_out * np.cos(turn), t_out


def _solve_straights(heading: np.ndarray, nominal: np.ndarray, lower: np.ndarray, gap: np.ndarray,
                     total: float) -> np.ndarray | None:
    """Straight lengths [m] that close the lap: sum L_i (cos, sin)(heading_i) = gap and sum L_i = total.

    The least change from ``nominal`` (weighted by it) with ``L >= lower`` (a small active set: the
    straights that come out too short are pinned to their bound and the rest solved again); None
    when there are no such lengths.
    """
    a = np.stack([np.cos(heading), np.sin(heading), np.ones_like(heading)])
    b = np.array([gap[0], gap[1], total])
    pinned = np.zeros(len(nominal), bool)
    for _ in range(len(nominal)):
        free = ~pinned
        if free.sum() < 3:
            return None
        af, nf = a[:, free], nominal[free]
        rhs = b - a[:, pinned] @ lower[pinned] - af @ nf
        g = (af * nf) @ af.T
        if np.linalg.cond(g) > 1e8:
            return None
        x = np.where(pinned, lower, 0.0)
        x[free] = nf + nf * (af.T @ np.linalg.solve(g, rhs))
        short = free & (x < lower - 1e-9)
        if not short.any():
            return x
        pinned |= short
    return None


# ---------------------------------------------------------------- layout
def _fingers(rng: np.random.Generator, plan: dict) -> list[dict] | None:
    """Hairpin fingers: out along a straight, a 165–179° hairpin, back (often with a dog-leg)."""
    r_min, n_h = plan["min_radius_m"], plan["hairpins"]
    long_h = set(rng.permutation(n_h)[: min(plan["long_straights"], n_h)].tolist())
    fingers = []
    for j in range(n_h):
        fingers.append({
            "r": r_min if j == 0 else r_min * rng.uniform(1.0, 1.3),
            "turn": np.radians(rng.uniform(165.0, 179.0)),
            "f": rng.uniform(0.25, 0.4),
            "straight": rng.uniform(*_LONG_LEG_M) if j in long_h else rng.uniform(*_SHORT_LEG_M),
            "r_base": r_min * rng.uniform(1.2, 2.2),
            "long": j in long_h,
            "inward": rng.random() < 0.3,
            "tilt": np.radians(rng.uniform(-20.0, 20.0)),
            "kink": (rng.uniform(0.3, 0.6), np.radians(rng.uniform(15.0, 40.0))) if rng.random() < 0.6 else None,
        })
    # the fingers take at most _FINGER_SHARE of the lap: shorten their straights if they must
    fixed = sum(2.0 * (1.3 * f["r_base"] + 10.0) + np.pi * f["r"] for f in fingers)
    free = sum(2.0 * f["straight"] for f in fingers)
    floor = sum(2.0 * (LONG_STRAIGHT_M + 10.0 if f["long"] else 60.0) for f in fingers)
    budget = _FINGER_SHARE * plan["length_m"] - fixed
    if free > budget:
        if floor > budget:
            return None
        c = (budget - floor) / (free - floor)
        for f in fingers:
            lo = LONG_STRAIGHT_M + 10.0 if f["long"] else 60.0
            f["straight"] = lo + c * (f["straight"] - lo)
    for f in fingers:
        f["leg"] = f["straight"] + 1.3 * f["r_base"] + 10.0  # base vertex to the hairpin's start [m]
    return fingers


def _skeleton(rng: np.random.Generator, plan: dict) -> list[dict] | None:
    """The circuit's polygon in driving order: vertices ``{"type": "v", "V": [2]}`` and hairpin tips
    ``{"type": "t", "P1", "P2", "pieces", "turn"}`` (where the hairpin starts and ends).

    Slots at sorted angles and random radii around a centre make a star-shaped, hence simple,
    polygon; a hairpin slot becomes a finger (base vertex, tip, optional dog-leg, base vertex).
    """
    n_h = plan["hairpins"]
    kinds = np.array(["v"] * plan["plain"] + ["h"] * n_h)[rng.permutation(plan["plain"] + n_h)]
    k = len(kinds)
    weight = rng.uniform(0.7, 1.3, k)  # angular gap before each slot
    weight[np.roll(kinds == "h", 1)] += 0.3  # room for a finger's way back
    weight[rng.choice(k, size=min(k, max(0, plan["long_straights"] - n_h)), replace=False)] *= 1.8
    phi = rng.uniform(0.0, 2.0 * np.pi) + 2.0 * np.pi * np.cumsum(weight) / weight.sum()
    rho = np.where(kinds == "h", rng.uniform(0.85, 1.0, k), rng.uniform(0.55, 1.0, k))
    unit = rho[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    fingers = _fingers(rng, plan)
    if fingers is None:
        return None
    perimeter = float(np.sum(np.hypot(*(np.roll(unit, -1, axis=0) - unit).T)))
    scale = (plan["length_m"] - sum(2.0 * f["leg"] + np.pi * f["r"] for f in fingers)) / perimeter
    nodes = []
    fingers = iter(fingers)
    for i in range(k):
        pos = scale * unit[i]
        if kinds[i] == "v":
            nodes.append({"type": "v", "V": pos})
            continue
        f = next(fingers)
        radial = pos / np.hypot(*pos)
        inward = f["inward"] and scale * rho[i] > f["leg"] + 150.0  # a right-hand hairpin into the middle
        u = _rot(-radial if inward else radial, f["tilt"])
        turn = -f["turn"] if inward else f["turn"]
        pieces = np.array(_bend(turn, f["r"], _smooth_f(turn, f["r"], f["f"])))
        p_in = pos + f["leg"] * u
        p_out = p_in + _rot(_displacement(pieces), _angle(u))
        u_out = _rot(u, turn)
        back = float(np.dot(p_out - pos, u) / -np.dot(u_out, u))  # way back to the base's level [m]
        kink = None
        if f["kink"] is not None:  # the way back bends away from the way out
            kink = p_out + f["kink"][0] * back * u_out
            u_out = _rot(u_out, -np.sign(turn) * f["kink"][1])
            back = float(np.dot(kink - pos, u) / -np.dot(u_out, u))
        b = (p_out if kink is None else kink) + back * u_out
        nxt = scale * unit[(i + 1) % k]
        if not 0.05 < (_angle(b) - _angle(pos)) % (2 * np.pi) < (_angle(nxt) - _angle(pos)) % (2 * np.pi) - 0.05:
            return None  # the finger would cross its neighbour
        nodes.append({"type": "v", "V": pos, "base": True, "r_des": f["r_base"]})
        nodes.append({"type": "t", "P1": p_in, "P2": p_out, "pieces": pieces, "turn": turn, "long_in": f["long"]})
        if kink is not None:
            nodes.append({"type": "v", "V": kink})
        nodes.append({"type": "v", "V": b, "base": True, "r_des": f["r_base"]})
    return nodes


def _circuit_layout(rng: np.random.Generator, plan: dict, ds: float) -> tuple[np.ndarray, np.ndarray] | None:
    """One candidate lap: centreline ``[M, 2]`` [m] and curvature ``[M]`` [1/m], or None.

    The skeleton polygon is rounded: every vertex gets a bend (clothoid, arc, clothoid; or a
    tightening spiral) that fits between its edges, chicanes go on edges with room, and the
    straights' lengths are then solved so that the lap closes at the planned length with every
    long straight at least ``LONG_STRAIGHT_M``. The lap starts 40 % into its longest straight,
    heading along +x, and is sampled every ``ds`` [m].
    """
    r_min, n_h = plan["min_radius_m"], plan["hairpins"]
    nodes = _skeleton(rng, plan)
    if nodes is None:
        return None
    n = len(nodes)
    exit_pt = [nd["V"] if nd["type"] == "v" else nd["P2"] for nd in nodes]
    entry_pt = [nd["V"] if nd["type"] == "v" else nd["P1"] for nd in nodes]
    edge = [entry_pt[(i + 1) % n] - exit_pt[i] for i in range(n)]  # edge i leaves node i
    edge_len = np.array([np.hypot(*e) for e in edge])
    edge_dir = np.array([_angle(e) for e in edge])
    if edge_len.min() < 1.0:
        return None
    verts = [i for i in range(n) if nodes[i]["type"] == "v"]
    for i in verts:
        nodes[i]["turn"] = float((edge_dir[i] - edge_dir[i - 1] + np.pi) % (2 * np.pi) - np.pi)
        if abs(nodes[i]["turn"]) > np.radians(170.0):
            return None
    # long straights: the fingers' ways out, then the longest edges into plain corners of 45° or more
    edge_long = np.array([bool(nodes[(i + 1) % n].get("long_in")) for i in range(n)])
    cand = [i for i in range(n) if nodes[(i + 1) % n]["type"] == "v" and not nodes[(i + 1) % n].get("base")
            and abs(nodes[(i + 1) % n]["turn"]) >= np.radians(45.0) and not edge_long[i]]
    cand.sort(key=lambda i: -edge_len[i] * rng.uniform(0.8, 1.2))
    for i in cand[: max(0, plan["long_straights"] - n_h)]:
        edge_long[i] = True
        nodes[(i + 1) % n]["tight"] = True
    # decreasing-radius bends at the corners after long straights first, then the biggest turns
    dec = [i for i in verts if abs(nodes[i]["turn"]) >= np.radians(45.0)]
    dec.sort(key=lambda i: (not nodes[i].get("tight"), bool(nodes[i].get("base")), -abs(nodes[i]["turn"])))
    if len(dec) < plan["decreasing_radius"]:
        return None
    dec = dec[: plan["decreasing_radius"]]
    tightest = None  # the bend at exactly min_radius_m when no hairpin has it
    if n_h == 0:
        tight = [i for i in verts if nodes[i].get("tight")]
        tightest = dec[0] if dec else tight[0] if tight else max(verts, key=lambda i: abs(nodes[i]["turn"]))
    for i in verts:
        nd = nodes[i]
        turn = nd["turn"]
        nd["fixed_r"] = i == tightest
        if abs(turn) < 1e-3:
            nd["unit"], nd["tau"], nd["r"] = None, (0.0, 0.0), 0.0
            continue
        if i == tightest:
            r = r_min
        elif nd.get("tight") or i in dec:
            r = r_min * rng.uniform(1.0, 1.6)
        elif nd.get("base"):
            r = nd["r_des"]
        else:
            r = float(np.exp(rng.uniform(np.log(1.3 * r_min), np.log(max(250.0, 2.0 * r_min)))))
        if i in dec:
            rel = np.array([rng.uniform(0.15, 0.3), 1.0, rng.uniform(0.1, 0.3), rng.uniform(0.15, 0.3)])
            ratio = rng.uniform(2.0, 3.5)
            for _ in range(6):  # longer clothoids until the bend may be as tight as r_min
                nd["unit"] = np.array(_decreasing(turn, ratio, 1.0, rel))
                floor = np.sqrt(_max_rate(nd["unit"]) / CURVATURE_RATE_MAX)
                if floor <= r_min:
                    break
                rel[[0, 3]] *= 1.4
        else:
            f = _smooth_f(turn, r_min, rng.uniform(0.2, 0.45))
            nd["unit"] = np.array(_bend(turn, 1.0, f))
            floor = _rate_floor(turn, f)
        nd["tau"] = _tangents(nd["unit"], turn)
        nd["r_floor"] = max(r_min, floor)
        nd["r"] = max(r, nd["r_floor"])

    def tangent_lengths():
        t_out = np.array([nd["r"] * nd["tau"][1] if nd["type"] == "v" else 0.0 for nd in nodes])
        t_in = np.array([nd["r"] * nd["tau"][0] if nd["type"] == "v" else 0.0 for nd in nodes])
        return t_out, np.roll(t_in, -1)  # at the start and at the end of each edge

    # fit the bends between their edges: shrink radii (never below their floor) where they overlap
    lower = np.where(edge_long, LONG_STRAIGHT_M, _MIN_STRAIGHT_M)
    t_start, t_end = tangent_lengths()
    factor = np.clip((edge_len - lower) / np.maximum(t_start + t_end, 1e-9), 0.0, 1.0)
    for i in verts:
        nd = nodes[i]
        if nd["unit"] is not None and not nd["fixed_r"]:
            nd["r"] = max(nd["r_floor"], nd["r"] * min(factor[i], factor[i - 1]))
    t_start, t_end = tangent_lengths()
    straight = edge_len - t_start - t_end
    # chicanes (left-right, or left-right-left back on the same line) on edges with room
    chicanes = {}
    for _ in range(plan["chicanes"]):
        sign = 1.0 if rng.random() < 0.5 else -1.0
        a = np.radians(rng.uniform(_lerp(15.0, 25.0, plan["difficulty"]), _lerp(30.0, 50.0, plan["difficulty"])))
        r = r_min * rng.uniform(1.3, 2.2)
        f = _smooth_f(a, r, rng.uniform(0.3, 0.45))
        r = max(r, _rate_floor(a, f))
        if rng.random() < 0.6:
            pieces = _bend(sign * a, r, f) + [(rng.uniform(0.0, 10.0), 0.0, 0.0)] + _bend(-sign * a, r, f)
        else:
            pieces = _bend(sign * a, r, f) + _bend(-2.0 * sign * a, r, f) + _bend(sign * a, r, f)
        pieces = np.array(pieces)
        pieces = pieces[pieces[:, 0] > 1e-9]
        need = _displacement(pieces)[0] + 60.0
        room = [i for i in range(n) if not edge_long[i] and i not in chicanes and straight[i] >= need]
        if not room:
            return None
        chicanes[room[int(rng.integers(len(room)))]] = pieces
    # the lap as elements in driving order: ("S", length, lower bound) or ("E", pieces, turn)
    elems = []
    for i in range(n):
        nd = nodes[i]
        if nd["type"] == "t":
            elems.append(("E", nd["pieces"], nd["turn"]))
        elif nd["unit"] is not None:
            elems.append(("E", _scaled(nd["unit"], nd["r"]), nd["turn"]))
        nominal = max(straight[i], lower[i])
        if i in chicanes:
            rest = max(nominal - _displacement(chicanes[i])[0], 2.0 * _MIN_STRAIGHT_M)
            x = rng.uniform(0.25, 0.75)
            elems += [("S", x * rest, _MIN_STRAIGHT_M), ("E", chicanes[i], 0.0), ("S", (1 - x) * rest, _MIN_STRAIGHT_M)]
        else:
            elems.append(("S", nominal, lower[i]))
    # close the lap: the straights keep their headings, their lengths absorb every mismatch
    theta = edge_dir[-1]
    heading, gap, bend_len, s_idx = [], np.zeros(2), 0.0, []
    for j, el in enumerate(elems):
        if el[0] == "S":
            heading.append(theta)
            s_idx.append(j)
        else:
            gap -= _rot(_displacement(el[1]), theta)
            bend_len += float(el[1][:, 0].sum())
            theta += el[2]
    if abs(theta - edge_dir[-1] - 2.0 * np.pi) > 1e-6:  # one anticlockwise turn, nothing else
        return None
    lengths = _solve_straights(np.array(heading), np.array([elems[j][1] for j in s_idx]),
                               np.array([elems[j][2] for j in s_idx]), gap, plan["length_m"] - bend_len)
    if lengths is None:
        return None
    for j, length in zip(s_idx, lengths):
        elems[j] = ("S", length, 0.0)
    # the profile from 40 % into the longest straight, integrated and sampled every ds
    j0 = s_idx[int(np.argmax(lengths))]
    prof = [(0.6 * elems[j0][1], 0.0, 0.0)]
    for jj in range(1, len(elems)):
        el = elems[(j0 + jj) % len(elems)]
        prof.extend([(el[1], 0.0, 0.0)] if el[0] == "S" else map(tuple, el[1]))
    prof.append((0.4 * elems[j0][1], 0.0, 0.0))
    prof = np.array(prof)
    prof = prof[prof[:, 0] > 1e-9]
    total = float(prof[:, 0].sum())
    m = int(round(total / ds))
    sub = 4  # midpoint-rule steps per sample
    h = total / (m * sub)
    _, th = _profile_eval(prof, (np.arange(m * sub) + 0.5) * h)
    fine = np.concatenate([np.zeros((1, 2)), np.cumsum(h * np.stack([np.cos(th), np.sin(th)], axis=1), axis=0)])
    xy = fine[::sub]
    xy = xy[:-1] - np.outer(np.arange(m) / m, xy[-1])  # spread the (sub-millimetre) closing error
    kappa, _ = _profile_eval(prof, np.arange(m) * (total / m))
    return xy, kappa


def _narrow_widths(rng: np.random.Generator, s: np.ndarray, length: float, width: float, count: int) -> np.ndarray:
    """Total width [m] at arc lengths ``s`` [m]: ``width`` with ``count`` narrow stretches of 120–400 m at
    60–80 % of it (never below min(8 m, 0.8 · width)), entered and left over 30 m cosine ramps."""
    w = np.full(len(s), float(width))
    floor = min(8.0, 0.8 * width)
    for _ in range(count):
        centre = rng.uniform(0.1, 0.9) * length
        half = 0.5 * rng.uniform(120.0, 400.0)
        narrow = max(floor, rng.uniform(0.6, 0.8) * width)
        dist = np.abs((s - centre + 0.5 * length) % length - 0.5 * length)
        ramp = np.clip((half + 30.0 - dist) / 30.0, 0.0, 1.0)
        w = np.minimum(w, width - (width - narrow) * (0.5 - 0.5 * np.cos(np.pi * ramp)))
    return w


def generate_circuit(seed: int, difficulty: float | None = None, *, length_m: float | None = None,
                     width_m: float | None = None, hairpins: int | None = None, chicanes: int | None = None,
                     long_straights: int | None = None, decreasing_radius: int | None = None,
                     narrow_sections: int | None = None, min_radius_m: float | None = None,
                     surface: str = "asphalt", name: str | None = None) -> Track:
    """A valid procedural race circuit with the features real circuits have, deterministic per seed.

    The lap is a rounded polygon: straights, and bends of clothoid–arc–clothoid (curvature is
    continuous and changes at most ``CURVATURE_RATE_MAX`` per metre: no spikes), with hairpins at
    the ends of fingers, chicanes, long straights into the tightest bends, bends that tighten
    towards their exit and narrow stretches. The straights' lengths are solved so the lap closes at
    the planned length. Driven anticlockwise, sampled every ``SAMPLE_SPACING_M``, ``kappa`` exact;
    ``validate()`` passes (a layout that fails it is redrawn from the next sub-seed; late redraws
    drop seed-drawn features, never given ones).

    Every knob left ``None`` is drawn from the seed, scaled by ``difficulty``; a given knob
    replaces only its own draw. Ranges: :data:`CIRCUIT_KNOB_RANGES`.

    Args:
        seed: non-negative integer seed (the same seed and knobs give the same track, bit for bit).
        difficulty: 0 (wide, gentle, few features) … 1 (tight hairpins, narrow, many features);
            ``None``: drawn uniformly from the seed.
        length_m: lap length [m] (drawn: 1.5–5 km, at least what the features need).
        width_m: total width [m] outside the narrow stretches (drawn: 14–16 m at difficulty 0,
            10–12 m at 1).
        hairpins: bends of 165–179° at the end of a finger, the first at ``min_radius_m`` (drawn:
            0–1 at difficulty 0, 2–3 at 1).
        chicanes: quick left-right (or left-right-left) bends on a straight (0–1 … 2–4).
        long_straights: straights of at least ``LONG_STRAIGHT_M`` (320 m), each into a tight bend:
            a hairpin first (1–2 … 2–3).
        decreasing_radius: bends that tighten 2–3.5× towards their exit (0–1 … 1–3).
        narrow_sections: stretches of 120–400 m narrowed to 60–80 % of the width, never below
            min(8 m, 0.8 · width_m) (0–1 … 2–3).
        min_radius_m: the tightest bend's radius [m]; none is tighter (drawn: 60–72 m at
            difficulty 0, 12–14.4 m at 1; at least 0.59 · width_m).
        surface: road surface of the whole lap.
        name: track name (default ``proc-<seed>``).

    Raises:
        ValueError: a bad seed or a knob outside its range (one line naming it and the range), or
            given knobs that no layout satisfies (e.g. many hairpins in a short lap).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"generate_circuit: seed={_fmt(seed)} must be a non-negative integer")
    knobs = {"difficulty": difficulty, "length_m": length_m, "width_m": width_m, "hairpins": hairpins,
             "chicanes": chicanes, "long_straights": long_straights, "decreasing_radius": decreasing_radius,
             "narrow_sections": narrow_sections, "min_radius_m": min_radius_m}
    _check_circuit_knobs(knobs, surface)
    plan = circuit_plan(int(seed), knobs)
    sid = _surf.surface_id(surface)
    given = [f"seed={seed}"] + [f"{k}={v}" for k, v in knobs.items() if v is not None]
    source = f"generate_circuit({', '.join(given)})"
    for attempt in range(CIRCUIT_MAX_ATTEMPTS):
        if attempt in _RELAX_AT:
            plan = _relaxed(plan, knobs, _RELAX_AT.index(attempt) + 1)
        rng = np.random.default_rng([int(seed), _PROC_TAG, 1 + attempt])
        out = _circuit_layout(rng, plan, SAMPLE_SPACING_M)
        if out is None:
            continue
        xy, kappa = out
        w = _narrow_widths(rng, np.arange(len(xy)) * (plan["length_m"] / len(xy)), plan["length_m"],
                           plan["width_m"], plan["narrow_sections"])
        desc = (f"procedural circuit (seed {seed}, difficulty {plan['difficulty']:.2f}): {plan['hairpins']} hairpins, "
                f"{plan['chicanes']} chicanes, {plan['long_straights']} long straights, "
                f"{plan['decreasing_radius']} decreasing-radius bends, {plan['narrow_sections']} narrow sections")
        track = Track(name or f"proc-{seed}", xy, 0.5 * w, 0.5 * w, np.full(len(xy), sid), kappa,
                      default_surface=surface, description=desc, source=source, character="procedural circuit")
        try:
            return track.validate()
        except TrackError:
            continue
    need = _circuit_need_m(plan)
    hint = f" (they need about {need:.0f} m, the lap is {plan['length_m']:.0f} m)" if need > plan["length_m"] else ""
    raise ValueError(f"generate_circuit: no valid circuit for seed {seed} with these knobs after {CIRCUIT_MAX_ATTEMPTS} "
                     f"layouts{hint}; try a larger length_m, a smaller min_radius_m or fewer features")
