"""Track model: Frenet frame, sources, generator, library and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from torcsrl.envs import surfaces, tracks
from torcsrl.envs.track import Track, TrackError
from torcsrl.envs.tracks.sources import load_file

ALL = tracks.names()


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


# ---------------------------------------------------------------- library
def test_library_has_the_characters_the_studies_used():
    assert len(ALL) >= 10
    chars = {tracks.load(n).character for n in ALL}
    for needed in ("oval", "flowing road course", "fast course", "technical", "long complex course",
                   "narrow twisty alpine road", "long straight into a hairpin", "rallycross dirt loop"):
        assert needed in chars, needed


@pytest.mark.parametrize("name", ALL)
def test_every_bundled_track_loads_and_validates(name):
    t = tracks.load(name)
    assert 1000.0 <= t.length <= 6000.0
    width = t.w_left + t.w_right
    assert 10.0 - 1e-9 <= width.min() and width.max() <= 15.0 + 1e-9
    assert t.default_surface in surfaces.ROAD_SURFACES
    t.validate()
    assert np.isclose(t.s[-1] + np.hypot(*(t.xy[0] - t.xy[-1])), t.length)


def test_long_complex_course_is_at_least_5_km():
    assert tracks.load("grand_tour").length >= 5000.0


def test_track_sets_are_data_and_disjoint():
    sets = tracks.track_sets()
    assert set(sets["train"]).isdisjoint(sets["heldout"])
    assert tracks.resolve("set:heldout") == sets["heldout"]
    assert tracks.resolve(["oval", "set:dirt"]) == ["oval", "rallycross"]


def test_surface_override_and_mixed_surfaces():
    rx = tracks.load("rallycross")
    names = {n for _, _, n in rx.surface_stretches}
    assert names == {"asphalt", "dirt"}
    ice = tracks.load("rallycross", surface="ice")
    assert {n for _, _, n in ice.surface_stretches} == {"ice"}
    # the bundled copy is untouched
    assert {n for _, _, n in tracks.load("rallycross").surface_stretches} == {"asphalt", "dirt"}


# ---------------------------------------------------------------- Frenet frame
@pytest.mark.parametrize("name", ALL)
def test_frenet_round_trip_under_1cm(name):
    t = tracks.load(name)
    rng = np.random.default_rng(0)
    s = rng.uniform(0, t.length, 3000)
    wl, wr = t.width(s)
    d = rng.uniform(-0.999, 0.999, 3000) * np.where(rng.random(3000) < 0.5, wl, wr)
    xy = t.to_world(s, d)
    s2, d2 = t.project(xy)
    assert np.abs(t.wrap_delta(s2, s)).max() < 0.01
    assert np.abs(d2 - d).max() < 0.01
    assert np.linalg.norm(t.to_world(s2, d2) - xy, axis=-1).max() < 0.01
    # the windowed search near a hint finds the same answer
    s3, d3 = t.project(xy, s_hint=s + rng.uniform(-20, 20, 3000))
    assert np.abs(t.wrap_delta(s3, s2)).max() < 1e-6 and np.abs(d3 - d2).max() < 1e-6


def test_round_trip_from_world_points_on_hairpins():
    """World → (s, d) → world around the 20 m hairpins, where both legs are close."""
    t = tracks.load("hairpins")
    rng = np.random.default_rng(1)
    tight = np.flatnonzero(np.abs(t.kappa) > 0.04)
    assert len(tight) > 50
    s0 = t.s[rng.choice(tight, 4000)]
    xy = t.to_world(s0, 0.0) + rng.uniform(-5.9, 5.9, (4000, 2))
    s, d = t.project(xy)
    back = t.to_world(s, d)
    assert np.linalg.norm(back - xy, axis=-1).max() < 0.01
    wl, wr = t.width(s)
    assert (np.abs(d) <= np.maximum(wl, wr) + 6.0).all()


def test_projection_is_continuous_across_the_start_line():
    t = tracks.load("oval")
    s = np.linspace(-30.0, 30.0, 601)
    xy = t.to_world(s, 3.0)
    s2, d2 = t.project(xy)
    ds = t.wrap_delta(s2[1:], s2[:-1])
    assert np.allclose(ds, 0.1, atol=1e-6)
    assert np.allclose(d2, 3.0, atol=1e-6)
    raw = np.diff(s2)
    assert (np.abs(raw) > 0.2).sum() == 1  # exactly one jump: the lap wrap
    assert np.isclose(np.abs(raw).max(), t.length - 0.1, atol=1e-6)


def test_projection_is_continuous_along_a_path_through_a_hairpin():
    t = tracks.load("hairpins")
    s = np.linspace(150, 300, 3001)
    xy = t.to_world(s, 4.0)
    s2, d2 = t.project(xy)
    assert np.abs(np.diff(s2)).max() < 0.06 and np.allclose(d2, 4.0, atol=1e-6)


@pytest.mark.parametrize("name", ["kidney", "rallycross", "hairpins", "oval", "gen-7"])
def test_vectorised_walk_equals_the_scalar_walk_bit_for_bit(name):
    """Track.track_points gives, point by point, the bits of Track.track_point (None <-> not ok): on and off the
    road, on the start line (s = 0 and just before L), from nearby and from far chords (walks that fail)."""
    t = tracks.load(name)
    rng = np.random.default_rng(5)
    n = 1500
    s = rng.uniform(0.0, t.length, n)
    s[:6] = [0.0, t.length - 1e-9, 1e-12, t.s[3], t.s[-1], 0.5 * t.length]
    d = rng.uniform(-1.0, 1.0, n) * np.repeat([0.0, 2.0, 6.0, 20.0, 60.0], n // 5)
    xy = t.to_world(s, d) + rng.normal(0.0, 0.3, (n, 2)) * (np.arange(n) % 3 == 0)[:, None]
    chord = (t._locate(s)[0] + rng.integers(-8, 9, n)) % len(t)
    chord[::7] = rng.integers(0, len(t), len(chord[::7]))  # far from the point
    vs, vd, vc, vt, ok = t.track_points(xy[:, 0], xy[:, 1], chord)
    failed = 0
    for k in range(n):
        r = t.track_point(float(xy[k, 0]), float(xy[k, 1]), int(chord[k]))
        assert (r is not None) == bool(ok[k]), k
        if r is None:
            failed += 1
            continue
        got = (float(vs[k]), float(vd[k]), int(vc[k]), float(vt[k]))
        assert np.array(got[:2] + got[3:]).tobytes() == np.array(r[:2] + r[3:]).tobytes() and got[2] == r[2], (k, got, r)
    assert 0 < failed < n // 3  # both kinds of walks were compared


def test_arc_curvature_is_one_over_radius():
    t = tracks.load("oval")  # two 120 m-radius, 180-degree left bends after 500 m straights
    mid_arc = 500.0 + 0.5 * np.pi * 120.0
    assert np.isclose(t.curvature(mid_arc), 1.0 / 120.0, rtol=1e-9)
    assert t.curvature(250.0) == 0.0
    # and the geometry agrees: heading turns at 1/R per metre
    h = np.unwrap(t.heading(np.linspace(mid_arc - 50, mid_arc + 50, 101)))
    assert np.allclose(np.diff(h) / 1.0, 1.0 / 120.0, rtol=1e-3)
    hp = tracks.load("hairpins")
    right = hp.curvature(180.0 + 20.0 * np.pi + 250.0 + 11.0 * np.pi)
    assert np.isclose(right, -1.0 / 22.0)


def test_width_surface_and_track_pos():
    t = tracks.load("rallycross")
    s = 5.0
    wl, wr = t.width(s)
    assert np.isclose(t.track_pos(s, wl), 1.0) and np.isclose(t.track_pos(s, -wr), -1.0)
    assert surfaces.SURFACE_NAMES[int(t.surface(s))] == "asphalt"
    assert t.surface_name(t.length * 0.6) == "dirt"
    off = t.to_world(s, wl + 3.0)
    assert t.surface_at(off) == surfaces.GRASS_ID
    assert t.surface_at(t.to_world(s, 0.0)) == surfaces.surface_id("asphalt")


def test_wrap_delta_removes_the_lap_wrap():
    t = tracks.load("oval")
    assert np.isclose(t.wrap_delta(1.0, t.length - 1.0), 2.0)
    assert np.isclose(t.wrap_delta(t.length - 1.0, 1.0), -2.0)


# ---------------------------------------------------------------- generator
def test_generator_is_valid_over_200_seeds():
    lengths = []
    for seed in range(200):
        t = tracks.generate(seed)  # validate() runs inside: closure, overlap, folding
        assert np.isclose(t.length, 3000.0, rtol=0.01)
        assert 1.0 / np.abs(t.kappa).max() >= 25.0
        lengths.append(t.length)


def test_generator_is_deterministic_per_seed_and_differs_across_seeds():
    a, b, c = tracks.generate(11), tracks.generate(11), tracks.generate(12)
    assert np.array_equal(a.xy, b.xy)
    assert not np.array_equal(a.xy[:50], c.xy[:50])
    assert tracks.load("gen-11").length == a.length


def test_generator_knobs_are_respected():
    t = tracks.generate(3, length_m=5000, corners=20, min_radius_m=30, width_m=10, surface="dirt")
    assert np.isclose(t.length, 5000, rtol=0.01)
    assert 1.0 / np.abs(t.kappa).max() >= 30
    assert np.allclose(t.w_left + t.w_right, 10.0)
    assert t.default_surface == "dirt"


@pytest.mark.parametrize("kwargs, msg", [
    (dict(length_m=50), "length_m"),
    (dict(min_radius_m=4, width_m=12), "min_radius_m"),
    (dict(surface="lava"), "unknown surface 'lava'"),
])
def test_generator_bad_knobs(kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        tracks.generate(1, **kwargs)


# ---------------------------------------------------------------- sources and bad input
SQUARE = """
name: square
width: 12
segments:
  - {{type: straight, length: {a}}}
  - {{type: arc, radius: 30, angle: 90, turn: left}}
  - {{type: straight, length: 200}}
  - {{type: arc, radius: 30, angle: 90, turn: left}}
  - {{type: straight, length: 200}}
  - {{type: arc, radius: 30, angle: 90, turn: left}}
  - {{type: straight, length: 200}}
  - {{type: arc, radius: 30, angle: 90, turn: left, surface: ice}}
"""


def test_segment_list_closing_error_is_reported_and_spread(tmp_path):
    t = load_file(_write(tmp_path, "sq.yaml", SQUARE.format(a=200.5)))
    assert np.isclose(t.closing_error_m, 0.5, atol=1e-6)
    assert {n for *_, n in t.surface_stretches} == {"asphalt", "ice"}
    s = np.linspace(0, t.length, 500, endpoint=False)
    assert np.linalg.norm(t.to_world(*t.project(t.to_world(s, 2.0))) - t.to_world(s, 2.0), axis=-1).max() < 0.01


def test_segment_list_that_does_not_close_is_rejected(tmp_path):
    with pytest.raises(TrackError, match=r"sq.yaml: the loop does not close: its end is 5.00 m from its start"):
        load_file(_write(tmp_path, "sq.yaml", SQUARE.format(a=205)))


def test_segment_list_that_does_not_turn_360_is_rejected(tmp_path):
    bad = SQUARE.format(a=200).replace("angle: 90, turn: left, surface", "angle: 80, turn: left, surface")
    with pytest.raises(TrackError, match="turn 350.0° in total"):
        load_file(_write(tmp_path, "sq.yaml", bad))


def test_self_intersecting_track_is_rejected():
    th = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    xy = np.stack([400 * np.sin(th), 400 * np.sin(th) * np.cos(th)], axis=1)  # a figure of eight
    with pytest.raises(TrackError, match="track 'eight' .*: the track crosses itself near s = "):
        Track("eight", xy, 5.0, 5.0, 0, source="eight.csv").validate()


def test_overlapping_edges_are_rejected():
    # two parallel straights 8 m apart on a 12 m wide track: the edges overlap
    s = np.linspace(0, 2 * np.pi, 800, endpoint=False)
    xy = np.stack([300 * np.cos(s), 4 * np.sin(s)], axis=1)
    with pytest.raises(TrackError, match="inner edge folds|overlapping edges|crosses itself"):
        Track("thin", xy, 6.0, 6.0, 0).validate()


def test_too_narrow_track_is_rejected(tmp_path):
    with pytest.raises(TrackError, match=r"width 1.50 m .* below the car's minimum track width"):
        load_file(_write(tmp_path, "sq.yaml", SQUARE.format(a=200).replace("width: 12", "width: 1.5")))


@pytest.mark.parametrize("text, msg", [
    ("name: x\nwidth: 12\nsegments: [{type: loop, length: 5}]", "segment 1: type must be 'straight' or 'arc'"),
    ("name: x\nwidth: 12\nsegments: [{type: arc, radius: 5, angle: 90}]", "needs turn: left or right"),
    ("name: x\nwidth: 12\nsegments: [{type: straight}]", "a straight needs 'length'"),
    ("name: x\nwidth: 12\nsegments: [{type: straight, length: 10, surface: lava}]", "unknown surface 'lava'"),
    ("name: x\nwidth: 12\nsegments: [{type: straight, lenght: 10}]", r"unknown keys \['lenght'\]"),
    ("name: x\nsegments: [{type: straight, length: 10}]", "give the track's width"),
    ("name: x\nwidth: 12\n", "needs 'segments'"),
    ("name: [x\n", "not valid YAML"),
])
def test_malformed_files_name_the_file_and_the_problem(tmp_path, text, msg):
    with pytest.raises(TrackError, match=msg) as err:
        load_file(_write(tmp_path, "bad.yaml", text))
    assert "bad.yaml" in str(err.value)
    assert "\n" not in str(err.value)


def test_point_file_loads_and_is_smoothed(tmp_path):
    th = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    rng = np.random.default_rng(0)
    x, y = 300 * np.cos(th) + rng.normal(0, 0.2, 120), 200 * np.sin(th) + rng.normal(0, 0.2, 120)
    rows = "\n".join(f"{a:.3f},{b:.3f},6.0,5.0" for a, b in zip(x, y))
    _write(tmp_path, "e.csv", "# x_m,y_m,w_tr_right_m,w_tr_left_m\n" + rows + "\n")
    t = load_file(_write(tmp_path, "e.yaml", "name: ellipse\npoints: e.csv\nsurface: wet\n"))
    assert np.allclose(t.w_right, 6.0) and np.allclose(t.w_left, 5.0)
    assert t.default_surface == "wet"
    assert 1500 < t.length < 1700  # Ramanujan: ~1585 m
    assert np.abs(np.diff(t.kappa)).max() < 1e-3  # smooth curvature


def test_point_file_that_does_not_close_is_rejected(tmp_path):
    th = np.linspace(0, 1.5 * np.pi, 100)
    rows = "\n".join(f"{300 * np.cos(a):.3f},{300 * np.sin(a):.3f},6,6" for a in th)
    _write(tmp_path, "open.csv", "# x,y,w_left,w_right\n" + rows)
    with pytest.raises(TrackError, match="open.csv: the centreline does not close"):
        load_file(_write(tmp_path, "open.yaml", "name: open\npoints: open.csv\n"))


def test_point_file_with_bad_rows_is_rejected(tmp_path):
    _write(tmp_path, "bad.csv", "# x,y,w_left,w_right\n1,2,3\n")
    with pytest.raises(TrackError, match="bad.csv: every row needs 4 columns"):
        load_file(_write(tmp_path, "b.yaml", "name: b\npoints: bad.csv\n"))


def test_unknown_track_name_lists_the_available_ones():
    with pytest.raises(ValueError) as err:
        tracks.load("monza")
    msg = str(err.value)
    assert "unknown track 'monza'" in msg and all(n in msg for n in ALL)
    with pytest.raises(ValueError, match="unknown track set 'nope'; available sets: "):
        tracks.resolve("set:nope")
    with pytest.raises(ValueError, match="unknown surface 'lava'"):
        tracks.load("oval", surface="lava")


def test_plot_command_writes_pngs(tmp_path):
    from torcsrl.envs.tracks.__main__ import main

    assert main(["plot", "hairpins", "--out", str(tmp_path / "h.png")]) == 0
    assert main(["plot", "--generated", "7", "--out", str(tmp_path / "g.png")]) == 0
    assert main(["plot", "nope", "--out", str(tmp_path / "n.png")]) == 2
    for f in ("h.png", "g.png"):
        data = (tmp_path / f).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_the_parsed_track_cache_is_bounded():
    """Every env seed draws its own procedural pool, so a long run loads many generated tracks: the cache keeps the
    newest TRACK_CACHE_SIZE, and an evicted track loads again the same."""
    import numpy as np

    from torcsrl.envs import tracks

    first = tracks.load("gen-40000")
    for i in range(tracks.TRACK_CACHE_SIZE + 10):
        tracks.load(f"gen-{40001 + i}")
    info = tracks.cache_info()
    assert info.currsize == tracks.TRACK_CACHE_SIZE == info.maxsize
    again = tracks.load("gen-40000")  # evicted, generated again
    assert again is not first and np.array_equal(again.xy, first.xy)


def test_surfaces_at_is_track_point_then_frame_at():
    """Track.surfaces_at (the wheels' surfaces in one call) gives what a walk and frame_at give point by point."""
    rng = np.random.default_rng(0)
    for t, chord in [(t, c) for t in (tracks.load("hairpins"), tracks.load("rallycross")) for c in range(0, len(t.xy), 7)]:
        x0, y0 = t.xy[chord]
        pts = [(float(x0 + dx), float(y0 + dy)) for dx, dy in rng.uniform(-12.0, 12.0, size=(4, 2))]
        want = []
        for x, y in pts:
            r = t.track_point(x, y, chord)
            if r is None:
                want = None
                break
            w_l, w_r, _, sid = t.frame_at(r[2], r[3])
            want.append(sid if -w_r <= r[1] <= w_l else surfaces.GRASS_ID)
        assert t.surfaces_at(pts, chord) == want
