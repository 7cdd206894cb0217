"""benchmarks/race_screen.py: the racer selection screen refuses held-out tracks in one line, and a real (tiny) screen
prints its table with the eligibility computed from the races."""

from __future__ import annotations

import json

import pytest
from _bench import load_benchmark


def _bench():
    return load_benchmark("race_screen")


@pytest.mark.parametrize("tracks", [["set:heldout"], ["oval", "kidney"], ["gen-17"], ["proc-999@0.5"]])
def test_held_out_tracks_are_refused_in_one_line(tracks, capsys):
    with pytest.raises(SystemExit) as err:
        _bench().main(["--policy", "racer_bold", "--tracks", *tracks])
    msg = str(err.value)
    assert "held-out" in msg and "training tracks only" in msg and "\n" not in msg


def test_training_range_tracks_are_not_held_out():
    assert _bench().heldout_tracks(["oval", "gen-10001", "proc-20000", "road_flow"]) == []


def test_a_tiny_screen_prints_the_races_and_the_eligibility(capsys):
    b = _bench()
    assert b.main(["--policy", "racer_bold", "--tracks", "oval", "--episodes", "2", "--laps", "1", "--opponents", "1",
                   "--min-finished", "0", "--min-wins", "0", "--max-collisions", "99"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| racer_bold |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "2" and 0 <= int(cells[2]) <= 2 and 0 <= int(cells[3]) <= int(cells[2])
    assert 0 <= int(cells[5]) <= 2 and int(cells[6]) >= 0  # contact-free races, the most in one race
    assert (int(cells[6]) == 0) == (int(cells[5]) == 2) and (float(cells[4]) == 0) == (int(cells[5]) == 2)
    sides = [int(x) for x in cells[7].split("·")]  # where the other car was: the contacts, each counted once
    assert len(sides) == 3 and sum(sides) == round(float(cells[4]) * 2)
    assert cells[8] == "2" and cells[9] == "yes"  # paces drawn per race: 2 races, 2 scenarios; thresholds at 0
    rows = b.screen(["racer_bold"], ["oval"], episodes=2, laps=1, opponents=1)
    assert not b.eligible(rows[0], 0.0, 0.0, -1.0)  # no driver has fewer than 0 collisions a race
    assert b.eligible(rows[0], 0.0, 0.0, 99.0)


@pytest.mark.parametrize("argv,match", [(["--tracks", "oval", "--surfaces", "grass"], "unknown surface 'grass'"),
                                        (["--tracks", "no_such_track"], "no_such_track")])
def test_an_off_road_surface_or_an_unknown_track_is_refused_in_one_line(argv, match):
    with pytest.raises(SystemExit) as err:
        _bench().main(["--policy", "racer_bold", *argv])
    assert match in str(err.value) and str(err.value).startswith("race_screen: ") and "\n" not in str(err.value)


def test_surfaces_race_every_track_on_each_and_an_unknown_surface_is_refused_in_one_line(capsys, tmp_path):
    b = _bench()
    assert b.main(["--policy", "racer_bold", "--tracks", "oval", "--surfaces", "asphalt", "dirt", "--episodes", "1",
                   "--laps", "1", "--opponents", "1", "--surface-weights", "asphalt=5", "dirt=1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "oval on asphalt dirt" in out
    row = next(line for line in out.splitlines() if line.startswith("| racer_bold |"))
    assert [c.strip() for c in row.strip("|").split("|")][1] == "2"  # one race a track and surface
    per = [[c.strip() for c in line.strip("|").split("|")] for line in out.split("per surface:")[1].split("surface-weighted")[0].splitlines()
           if line.startswith("| racer_bold |")]
    assert [p[1] for p in per] == ["asphalt", "dirt"] and all(p[2] == "1" for p in per)  # one race on each
    total = [c.strip() for c in row.strip("|").split("|")]
    assert sum(int(p[3]) for p in per) == int(total[2]) and sum(int(p[4]) for p in per) == int(total[3])  # finished, wins
    (w,) = [[c.strip() for c in line.strip("|").split("|")] for line in out.split("surface-weighted (asphalt 5, dirt 1):")[1].splitlines()
            if line.startswith("| racer_bold |")]
    asp, dirt = per  # one race each: the weighted shares are 5/6 of asphalt's and 1/6 of dirt's
    assert float(w[1]) == pytest.approx(5 / 6 * int(asp[3]) + 1 / 6 * int(dirt[3]), abs=1e-3)
    assert float(w[2]) == pytest.approx(5 / 6 * int(asp[4]) + 1 / 6 * int(dirt[4]), abs=1e-3)
    assert float(w[3]) == pytest.approx(5 / 6 * float(asp[5]) + 1 / 6 * float(dirt[5]), abs=0.01)
    summary = json.loads((tmp_path / "screen.json").read_text())  # the same numbers, machine-readable
    assert summary["protocol"]["surface_weights"] == {"asphalt": 5.0, "dirt": 1.0}
    (pol,) = summary["policies"]
    assert pol["weighted"]["wins"] == pytest.approx(float(w[2]), abs=1e-3) and set(pol["by_surface"]) == {"asphalt", "dirt"}
    with pytest.raises(SystemExit) as err:
        b.main(["--policy", "racer_bold", "--tracks", "oval", "--surfaces", "lava"])
    assert "unknown surface 'lava'" in str(err.value) and "asphalt" in str(err.value) and "\n" not in str(err.value)


def test_surface_weights_reweigh_the_eligibility_to_the_held_out_mix():
    b = _bench()
    row = {"races": 48, "finished": 36, "wins": 20, "collisions_per_race": 0.955,  # R15's training screen (2026-11-28)
           "by_surface": {"asphalt": {"races": 24, "finished": 20, "wins": 17, "collisions_per_race": 0.79},
                          "dirt": {"races": 24, "finished": 16, "wins": 3, "collisions_per_race": 1.12}}}
    w = b.weighted_rates(row, {"asphalt": 5, "dirt": 1})
    assert w["finished"] == pytest.approx(5 / 6 * 20 / 24 + 1 / 6 * 16 / 24)
    assert w["wins"] == pytest.approx(5 / 6 * 17 / 24 + 1 / 6 * 3 / 24)  # 0.611
    assert w["collisions_per_race"] == pytest.approx(5 / 6 * 0.79 + 1 / 6 * 1.12)
    assert not b.eligible(row, 0.75, 0.5, 1.0)  # pooled: 20 of 48 wins
    assert b.eligible(row, 0.75, 0.5, 1.0, {"asphalt": 5, "dirt": 1})  # weighted: 0.61 of the races
    assert not b.eligible(row, 0.75, 0.5, 1.0, {"asphalt": 0, "dirt": 1})  # dirt only: 3 of 24 wins
    assert b.weighted_rates(row, {"asphalt": 1, "dirt": 1})["wins"] == pytest.approx(20 / 48)  # equal weights: pooled


@pytest.mark.parametrize("argv,match", [
    (["--surface-weights", "asphalt=5"], "needs --surfaces"),
    (["--surfaces", "asphalt", "dirt", "--surface-weights", "asphalt=5"], "missing: dirt"),
    (["--surfaces", "asphalt", "dirt", "--surface-weights", "asphalt=5", "dirt=1", "wet=2"], "not raced"),
    (["--surfaces", "asphalt", "dirt", "--surface-weights", "asphalt=-1", "dirt=1"], "W >= 0"),
    (["--surfaces", "asphalt", "dirt", "--surface-weights", "asphalt", "dirt=1"], "SURFACE=W"),
    (["--surfaces", "asphalt", "dirt", "--surface-weights", "asphalt=0", "dirt=0"], "all weights are 0"),
])
def test_bad_surface_weights_are_refused_in_one_line_before_any_race(argv, match):
    with pytest.raises(SystemExit) as err:
        _bench().main(["--policy", "racer_bold", "--tracks", "oval", *argv])
    assert match in str(err.value) and str(err.value).startswith("race_screen: ") and "\n" not in str(err.value)


def _races(wins: list[int], surface: str = "asphalt", coll: float = 0.0) -> list[dict]:
    return [{"track": "oval", "surface": surface, "episode": e, "env_seed": 100 + e, "finished": True, "win": bool(w),
             "collisions": coll} for e, w in enumerate(wins)]


def test_paired_delta_is_race_by_race_with_a_bootstrap_interval():
    b = _bench()
    base = _races([0] * 10) + _races([0] * 10, "dirt", coll=1.0)
    same = b.paired_delta(base, base)
    assert all(v == (0.0, 0.0, 0.0) for v in same.values())  # a policy against itself: no difference, no spread
    better = _races([1] * 8 + [0] * 2) + _races([0] * 10, "dirt", coll=1.0)
    d = b.paired_delta(better, base)
    assert d["wins"][0] == pytest.approx(8 / 20) and d["wins"][1] <= d["wins"][0] <= d["wins"][2]
    assert d["wins"][1] > 0  # 8 of 10 asphalt races won more: beyond the draw of races
    dw = b.paired_delta(better, base, {"asphalt": 5, "dirt": 1})
    assert dw["wins"][0] == pytest.approx(5 / 6 * 0.8)  # weighted to the held-out mix
    one = _races([1] + [0] * 9) + _races([0] * 10, "dirt", coll=1.0)
    assert b.paired_delta(one, base)["wins"][1] == 0.0  # one race's difference: the interval reaches 0
    assert b.paired_delta(one, base, seed=3) == b.paired_delta(one, base, seed=3)  # seeded
    with pytest.raises(SystemExit) as err:
        b.paired_delta(_races([1] * 9), _races([1] * 10))
    assert "other races" in str(err.value) and "\n" not in str(err.value)
    moved = [dict(r, env_seed=r["env_seed"] + 1) for r in _races([1] * 10)]
    with pytest.raises(SystemExit):
        b.paired_delta(moved, _races([1] * 10))  # same names, another seed: not the same races


def test_baseline_from_an_earlier_screen_pairs_the_same_races(tmp_path, capsys):
    b = _bench()
    args = ["--policy", "racer_bold", "--tracks", "oval", "--episodes", "1", "--laps", "1", "--opponents", "1"]
    assert b.main([*args, "--out", str(tmp_path)]) == 0
    csv_path = tmp_path / "racer_bold" / "race_episodes.csv"
    assert len(b.read_races(csv_path)) == 1
    capsys.readouterr()
    assert b.main([*args, "--baseline", str(csv_path)]) == 0  # the same driver raced again, paired with its CSV
    out = capsys.readouterr().out.split("paired with")[1]
    cells = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| racer")}
    assert cells["racer_bold"].count("+0.000 [+0.000, +0.000]") == 3  # the same driver on the same races: seeded, equal
    first = json.loads((tmp_path / "screen.json").read_text())  # the first screen's summary (no baseline)
    (pol,) = first["policies"]
    assert pol["policy"] == "racer_bold" and pol["races"] == 1 and "paired" not in pol and first["protocol"]["laps"] == 1
    assert pol["eligible"] == b.eligible(pol, 0.75, 0.5, 1.0)
    with pytest.raises(SystemExit) as err:
        b.main([*args, "--baseline", "reference_racer"])
    assert "neither one of --policy" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(SystemExit) as err:
        b.main([*args, "--baseline", str(tmp_path / "nope.csv")])
    assert "is not a race_episodes.csv" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(SystemExit) as err:  # another seed: the same (track, surface, episode), another race
        b.main([*args, "--seed", "1", "--baseline", str(csv_path)])
    assert "other races" in str(err.value)
