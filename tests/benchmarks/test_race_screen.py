"""benchmarks/race_screen.py: the racer selection screen refuses held-out tracks in one line, and a real (tiny) screen
prints its table with the eligibility computed from the races."""

from __future__ import annotations

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
    assert cells[5] == "2" and cells[6] == "yes"  # paces drawn per race: 2 races, 2 scenarios; thresholds at 0
    rows = b.screen(["racer_bold"], ["oval"], episodes=2, laps=1, opponents=1)
    assert not b.eligible(rows[0], 0.0, 0.0, -1.0)  # no driver has fewer than 0 collisions a race
    assert b.eligible(rows[0], 0.0, 0.0, 99.0)


@pytest.mark.parametrize("argv,match", [(["--tracks", "oval", "--surfaces", "grass"], "unknown surface 'grass'"),
                                        (["--tracks", "no_such_track"], "no_such_track")])
def test_an_off_road_surface_or_an_unknown_track_is_refused_in_one_line(argv, match):
    with pytest.raises(SystemExit) as err:
        _bench().main(["--policy", "racer_bold", *argv])
    assert match in str(err.value) and str(err.value).startswith("race_screen: ") and "\n" not in str(err.value)


def test_surfaces_race_every_track_on_each_and_an_unknown_surface_is_refused_in_one_line(capsys):
    b = _bench()
    assert b.main(["--policy", "racer_bold", "--tracks", "oval", "--surfaces", "asphalt", "dirt", "--episodes", "1",
                   "--laps", "1", "--opponents", "1"]) == 0
    out = capsys.readouterr().out
    assert "oval on asphalt dirt" in out
    row = next(line for line in out.splitlines() if line.startswith("| racer_bold |"))
    assert [c.strip() for c in row.strip("|").split("|")][1] == "2"  # one race a track and surface
    per = [[c.strip() for c in line.strip("|").split("|")] for line in out.split("per surface:")[1].splitlines()
           if line.startswith("| racer_bold |")]
    assert [p[1] for p in per] == ["asphalt", "dirt"] and all(p[2] == "1" for p in per)  # one race on each
    total = [c.strip() for c in row.strip("|").split("|")]
    assert sum(int(p[3]) for p in per) == int(total[2]) and sum(int(p[4]) for p in per) == int(total[3])  # finished, wins
    with pytest.raises(SystemExit) as err:
        b.main(["--policy", "racer_bold", "--tracks", "oval", "--surfaces", "lava"])
    assert "unknown surface 'lava'" in str(err.value) and "asphalt" in str(err.value) and "\n" not in str(err.value)
