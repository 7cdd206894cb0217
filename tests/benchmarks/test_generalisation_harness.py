"""benchmarks/generalisation.py: its summary arithmetic, and one real (tiny) trial end to end."""

from __future__ import annotations

import math

from _bench import load_benchmark


def _bench():
    return load_benchmark("generalisation")


def test_summary_counts_bundled_and_generated_apart_and_ratios_only_completed():
    b = _bench()
    rows = [
        {"policy": "p", "track": "kidney", "surface": "asphalt", "success": True, "fastest_lap": 60.0, "flips_per_km": 4.0},
        {"policy": "p", "track": "alpine", "surface": "asphalt", "success": False, "fastest_lap": math.nan, "flips_per_km": 30.0},
        {"policy": "p", "track": "gen-0", "surface": "asphalt", "success": True, "fastest_lap": 110.0, "flips_per_km": 8.0},
    ]
    expert = {("kidney", "asphalt"): 50.0, ("alpine", "asphalt"): 70.0, ("gen-0", "asphalt"): 100.0}
    (s,) = b.summarise(rows, expert, {"gen-0"})
    assert (s["heldout_completed"], s["heldout_total"], s["generated_completed"], s["generated_total"]) == (1, 2, 1, 1)
    assert math.isclose(s["median_lap_vs_expert"], (1.2 + 1.1) / 2)
    assert s["median_flips_per_km"] == 8.0
    assert "| p | asphalt | 1/2 | 1/1 (100 %) | 1.150 | 8.0 |" in b.table([s])


def test_one_real_trial_of_the_heuristic():
    b = _bench()
    (row,) = b.run_grid(["heuristic"], ["oval"], ["asphalt"], 1, 1, {"heuristic": 10.0})
    assert row["track"] == "oval" and row["success"] and row["fastest_lap"] > 30


def test_no_bundled_without_generated_tracks_fails_in_one_line(capsys):
    import pytest

    b = _bench()
    with pytest.raises(SystemExit):
        b.main(["--policy", "heuristic", "--no-bundled", "--generated", "0"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "no tracks to drive" in err and "--generated" in err
    with pytest.raises(SystemExit):
        b.main(["--policy", "heuristic", "--screen", "--generated", "-2"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--generated -2: expected a whole number >= 0" in err


def test_several_starts_are_the_grid_then_seeded_random_points(capsys):
    """--starts 3: one trial from the grid (the same as --starts 1) and two from seeded points of the lap, the same
    for every call; 0 starts fails in one line."""
    import pytest

    b = _bench()
    one = b.run_grid(["heuristic"], ["oval"], ["asphalt"], 1, 1, {"heuristic": 10.0})
    three = b.run_grid(["heuristic"], ["oval"], ["asphalt"], 1, 1, {"heuristic": 10.0}, starts=3)
    assert [r["start"] for r in three] == [0, 1, 2]
    assert three[0] == one[0]  # start 0 is the grid start every earlier screen drove
    assert len({r["mean_speed_kmh"] for r in three}) == 3  # three different trials
    assert b.run_grid(["heuristic"], ["oval"], ["asphalt"], 1, 1, {"heuristic": 10.0}, starts=3)[1:] == three[1:]  # seeded
    (s,) = b.summarise(three, {("oval", "asphalt"): 40.0}, set())
    assert s["heldout_total"] == 3  # counted per trial
    with pytest.raises(SystemExit):
        b.main(["--policy", "heuristic", "--starts", "0"])
    assert "--starts 0: expected a whole number >= 1" in capsys.readouterr().err


def test_the_screen_drives_training_tracks_and_training_range_seeds_only():
    """--screen: set:train and seeds 10001.. (8 by default, --generated N more, proc circuits with --generator proc);
    without it the held-out set and held-out seeds. No screen track is a held-out one."""
    from torcsrl.envs import tracks
    from torcsrl.envs.tracks.procedural import HELDOUT_SEEDS

    b = _bench()
    bundled, gen = b.track_lists(True)
    assert bundled == tracks.resolve("set:train") and gen == [f"gen-{s}" for s in range(10001, 10009)]
    _, proc = b.track_lists(True, "proc", 16)
    assert proc[0] == "proc-10001" and proc[-1] == "proc-10016" and len(proc) == 16
    assert not set(tracks.resolve("set:heldout")) & set(bundled)
    assert all(int(t.split("-")[1]) >= HELDOUT_SEEDS[1] for t in gen + proc)
    _, both = b.track_lists(True, "both")
    assert both == gen + [f"proc-{s}" for s in range(10001, 10009)]
    _, hboth = b.track_lists(False, "both", 3)
    assert hboth == ["gen-0", "gen-1", "gen-2", "proc-0", "proc-1", "proc-2"]
    held, hgen = b.track_lists(False, "gen", 3)
    assert held == tracks.resolve("set:heldout") and len(hgen) == 3 and all(int(t.split("-")[1]) < HELDOUT_SEEDS[1] for t in hgen)
