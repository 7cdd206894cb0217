"""Procedural circuits (generate_circuit): validity, determinism, features, difficulty, knob errors, proc-<seed>."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torcsrl.envs import tracks
from torcsrl.envs.tracks.generator import (CIRCUIT_KNOB_RANGES, CURVATURE_RATE_MAX, LONG_STRAIGHT_M, circuit_plan,
                                           generate_circuit)
from torcsrl.envs.tracks.sources import SAMPLE_SPACING_M

SEEDS = range(60)


# ---------------------------------------------------------------- helpers: read the features off a track
def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Cyclic runs of True (index arrays), a run across the start line kept whole."""
    if mask.all():
        return [np.arange(len(mask))]
    first = int(np.argmin(mask))  # a False index
    order = (first + 1 + np.arange(len(mask))) % len(mask)
    out, cur = [], []
    for i in order:
        if mask[i]:
            cur.append(i)
        elif cur:
            out.append(np.array(cur))
            cur = []
    if cur:
        out.append(np.array(cur))
    return out


def _bends(t) -> list[tuple[np.ndarray, float, float]]:
    """Runs of one-signed curvature: (samples, turn [rad], tightest radius [m]), in driving order."""
    out = []
    for sign in (1.0, -1.0):
        for r in _runs(sign * t.kappa > 0.0):
            out.append((r, float(t.kappa[r].sum() * t.ds), float(1.0 / np.abs(t.kappa[r]).max())))
    return sorted(out, key=lambda b: b[0][0])


def _features(t) -> dict:
    r_min = 1.0 / np.abs(t.kappa).max()
    bends = _bends(t)
    hairpins = sum(abs(turn) >= math.radians(160.0) and r <= 1.3 * r_min + 1e-6 for _, turn, r in bends)
    groups, cur = [], [bends[0]]  # bends with under 12 m of straight between them
    for b in bends[1:]:
        if (b[0][0] - cur[-1][0][-1]) * t.ds < 12.0:
            cur.append(b)
        else:
            groups.append(cur)
            cur = [b]
    groups.append(cur)
    chicanes = sum(len(g) >= 2 and abs(sum(b[1] for b in g)) < math.radians(0.5)
                   and {np.sign(b[1]) for b in g} == {1.0, -1.0} for g in groups)
    decreasing = 0
    for idx, _, _ in bends:
        a = np.abs(t.kappa[idx])
        if len(a) > 10 and int(np.argmax(a)) > len(a) // 2 and a[: len(a) // 2].mean() < 0.6 * a.max():
            decreasing += 1
    starts = {int(b[0][0]): b for b in bends}
    long_into_tight = 0
    for r in _runs(t.kappa == 0.0):
        if len(r) * t.ds >= LONG_STRAIGHT_M - 2.0 * t.ds:
            nxt = starts[int((r[-1] + 1) % len(t))]
            long_into_tight += nxt[2] <= 2.0 * r_min + 1e-6
    return {"hairpins": hairpins, "chicanes": chicanes, "decreasing_radius": decreasing,
            "long_straights": long_into_tight, "min_radius_m": r_min,
            "longest_straight_m": max(len(r) for r in _runs(t.kappa == 0.0)) * t.ds}


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


# ---------------------------------------------------------------- validity
@pytest.mark.parametrize("difficulty", [0.0, 0.33, 0.66, 1.0, None])
def test_every_seed_gives_a_valid_drivable_circuit(difficulty):
    for seed in SEEDS:
        t = generate_circuit(seed, difficulty)  # validate() ran inside: closure, overlap, folding
        where = f"seed {seed}, difficulty {difficulty}"
        assert t.name == f"proc-{seed}" and t.character == "procedural circuit"
        assert _signed_area(t.xy) > 0.0, where  # anticlockwise, like generate()
        seg = np.hypot(*(np.roll(t.xy, -1, axis=0) - t.xy).T)  # closed and evenly sampled
        assert np.abs(seg - SAMPLE_SPACING_M).max() < 0.01, where
        assert 1500.0 - 1.0 <= t.length <= 5000.0 + 1.0, where
        # the curvature is exact and smooth: it matches the samples' turning and never jumps
        chord = np.roll(t.xy, -1, axis=0) - t.xy
        turn = np.diff(np.unwrap(np.arctan2(chord[:, 1], chord[:, 0])))  # at samples 1 … M-1
        assert np.abs(turn / seg[1:] - t.kappa[1:]).max() < 5e-3, where
        assert np.abs(np.diff(t.kappa)).max() / t.ds <= CURVATURE_RATE_MAX * 1.01, where
        assert 1.0 / np.abs(t.kappa).max() >= 12.0 - 1e-6, where  # a full-size car turns at 12 m
        width = t.w_left + t.w_right
        assert width.min() >= 8.0 - 1e-9 and np.array_equal(t.w_left, t.w_right), where


def test_same_seed_same_circuit_bit_for_bit():
    a, b = generate_circuit(11), generate_circuit(11)
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.kappa, b.kappa) and np.array_equal(a.w_left, b.w_left)
    a, b = generate_circuit(11, 0.7, hairpins=2, width_m=11.0), generate_circuit(11, 0.7, hairpins=2, width_m=11.0)
    assert np.array_equal(a.xy, b.xy) and a.description == b.description
    assert not np.array_equal(generate_circuit(12).xy[:100], generate_circuit(11).xy[:100])
    assert len(generate_circuit(11, 0.0)) != len(generate_circuit(11, 1.0))


# ---------------------------------------------------------------- difficulty and features
def test_difficulty_scales_radius_width_and_features():
    easy = [generate_circuit(s, 0.0) for s in range(12)]
    hard = [generate_circuit(s, 1.0) for s in range(12)]
    for t in easy:
        f = _features(t)
        assert f["min_radius_m"] >= 55.0 and (t.w_left + t.w_right).max() >= 14.0 - 1e-9
    for t in hard:
        f = _features(t)
        assert 12.0 - 1e-6 <= f["min_radius_m"] <= 15.0
        assert f["longest_straight_m"] > 300.0
        assert (t.w_left + t.w_right).max() <= 12.0 + 1e-9
        assert f["hairpins"] >= 1 and f["long_straights"] >= 1
    count = lambda ts: sum(sum(_features(t)[k] for k in ("hairpins", "chicanes", "decreasing_radius")) for t in ts)
    assert count(hard) > 2 * count(easy)


@pytest.mark.parametrize("seed", [3, 8, 21])
def test_given_features_are_all_there(seed):
    knobs = {"hairpins": 2, "chicanes": 3, "long_straights": 3, "decreasing_radius": 2, "narrow_sections": 2}
    t = generate_circuit(seed, 0.8, **knobs)
    f = _features(t)
    for key in ("hairpins", "chicanes", "long_straights", "decreasing_radius"):
        assert f[key] >= knobs[key], (key, f)
    width = t.w_left + t.w_right
    narrow = _runs(width < width.max() - 0.5)
    assert 1 <= len(narrow) <= 2 and all(len(r) * t.ds >= 100.0 for r in narrow)
    assert "2 hairpins, 3 chicanes, 3 long straights" in t.description


def test_given_knobs_are_kept_and_others_still_drawn():
    t = generate_circuit(5, 0.5, length_m=3200.0, width_m=13.0, min_radius_m=20.0, hairpins=0, chicanes=0,
                         decreasing_radius=0, narrow_sections=0, long_straights=1, surface="dirt", name="mine")
    assert abs(t.length - 3200.0) < 2.0
    assert np.allclose(t.w_left + t.w_right, 13.0)
    assert abs(1.0 / np.abs(t.kappa).max() - 20.0) < 1e-6
    assert _features(t)["hairpins"] == 0 and t.name == "mine" and t.default_surface == "dirt"
    # one knob given: the other seed-drawn values stay as they were
    knobs = dict.fromkeys(CIRCUIT_KNOB_RANGES)
    base = circuit_plan(5, {**knobs, "difficulty": 0.5})
    given = circuit_plan(5, {**knobs, "difficulty": 0.5, "chicanes": 4})
    assert given["chicanes"] == 4 and {k: v for k, v in given.items() if k not in ("chicanes", "plain", "length_m")} == {
        k: v for k, v in base.items() if k not in ("chicanes", "plain", "length_m")}


# ---------------------------------------------------------------- bad knobs: one line naming the knob and its range
@pytest.mark.parametrize("knob,value", [
    ("difficulty", 1.5), ("difficulty", -0.1), ("difficulty", float("nan")), ("difficulty", "hard"),
    ("length_m", 500.0), ("length_m", 9000.0), ("width_m", 30.0), ("min_radius_m", 5.0),
    ("hairpins", 7), ("hairpins", -1), ("hairpins", 2.5), ("hairpins", True), ("chicanes", 9),
    ("long_straights", 5), ("decreasing_radius", 7), ("narrow_sections", 99),
])
def test_knob_out_of_range_is_one_line_naming_it_and_its_range(knob, value):
    lo, hi = CIRCUIT_KNOB_RANGES[knob]
    with pytest.raises(ValueError) as err:
        generate_circuit(1, **{knob: value})
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"generate_circuit: {knob}=")
    assert f"[{lo:g}, {hi:g}]" in msg, msg


def test_difficulty_message_reads_well():
    with pytest.raises(ValueError, match=r"^generate_circuit: difficulty=1\.5 is outside the allowed range \[0, 1\]$"):
        generate_circuit(1, 1.5)


@pytest.mark.parametrize("kwargs,needle", [
    ({"seed": -1}, "seed=-1"), ({"seed": 1.5}, "seed=1.5"), ({"seed": True}, "seed=True"),
    ({"seed": 1, "width_m": 25.0, "min_radius_m": 12.0}, "min_radius_m=12.0"),
    ({"seed": 1, "surface": "lava"}, "unknown surface 'lava'"),
    ({"seed": 1, "length_m": 1000.0, "hairpins": 6, "long_straights": 4}, "they need about"),
])
def test_bad_seed_and_impossible_knobs_are_one_line(kwargs, needle):
    with pytest.raises(ValueError) as err:
        generate_circuit(**kwargs)
    assert "\n" not in str(err.value) and needle in str(err.value)


# ---------------------------------------------------------------- the library name
def test_proc_seed_loads_through_the_library():
    t = tracks.load("proc-7")
    assert np.array_equal(t.xy, generate_circuit(7).xy) and t.name == "proc-7"
    assert tracks.load("proc-7", surface="ice").default_surface == "ice"
    assert tracks.load("proc-7").default_surface == "asphalt"  # the cached copy is untouched
    assert tracks.resolve(["proc-3", "gen-3"]) == ["proc-3", "gen-3"]
    with pytest.raises(ValueError, match="proc-<seed>"):
        tracks.load("proc-x")


def test_cli_plots_a_procedural_circuit(tmp_path):
    from torcsrl.envs.tracks.__main__ import main

    assert main(["plot", "--procedural", "7", "--difficulty", "0.9", "--out", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").stat().st_size > 10_000
