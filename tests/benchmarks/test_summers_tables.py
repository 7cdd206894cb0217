"""benchmarks/summers_tables.py: the grid, its bad input, a resumed run of another config refused, and one tiny real
train-then-table pass end to end."""

from __future__ import annotations

import math

import pytest
from _bench import load_benchmark


def _bench():
    return load_benchmark("summers_tables")


def test_default_grid_is_td3_three_seeds_and_ddpg_d4pg_once_on_both_presets():
    b = _bench()
    cells = b.grid(list(b.PRESETS), None, None)
    assert len(cells) == 10
    assert sorted(s for p, a, s in cells if a == "td3" and p == "summers_dirt") == [0, 1, 2]
    assert {(a, s) for p, a, s in cells if a != "td3"} == {("ddpg", 0), ("d4pg", 0)}
    assert cells[:6] == [(p, a, 0) for a in ("td3", "ddpg", "d4pg") for p in b.PRESETS]  # every algorithm before more seeds


def test_bad_preset_algorithm_and_arguments_fail_in_one_line(capsys):
    b = _bench()
    for argv, want in ((["--presets", "summers_ice"], "preset 'summers_ice' is not a table preset; allowed: summers_road"),
                       (["--algos", "ppo"], "algorithm 'ppo' is not in the tables; allowed: ddpg, td3, d4pg"),
                       (["--runs", "/nonexistent"], "not a training run folder"),
                       (["--runs", "/tmp", "--tracks", "oval"], "not a training run folder")):
        assert b.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and want in err[0], err
    with pytest.raises(SystemExit):
        b.main(["--frames", "0"])
    assert "--frames 0: expected a whole number >= 1" in capsys.readouterr().err


def test_train_then_tables_end_to_end_and_a_resume_of_another_config_is_refused(tmp_path, capsys):
    """A 300-frame TD3 agent on the road preset, tabulated on one held-out track; then the same folder asked for with
    another algorithm's settings is refused before anything trains; asked for again as it was, it is left as is."""
    b = _bench()
    out = tmp_path / "tables"
    argv = ["--train", "--presets", "summers_road", "--algos", "td3", "--seeds", "0", "--frames", "300", "--jobs", "1",
            "--laps", "1", "--surfaces", "asphalt", "--tracks", "kidney", "--workers", "1", "--out", str(out),
            "--set", "learner.warmup_frames=100", "collector.init_random_frames=100"]
    assert b.main(argv) == 0
    text = (out / "summers_tables.md").read_text()
    assert "| TD3 | fast_straights (asphalt) | 0 | 300 |" in text
    assert "| kidney | asphalt |" in text and "training budget 300 frames per agent (Summers: 1,000,000)" in text
    rd = out / "runs" / "summers_road_td3_s0"
    assert b.newest_checkpoint(rd).name == "ckpt_000000000300.pt"
    # the same folder, recorded under another batch size: refused in one line naming the key
    (rd / "config.yaml").write_text((rd / "config.yaml").read_text().replace("batch_size: 256", "batch_size: 100", 1))
    capsys.readouterr()
    assert b.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a run of another config: algo.batch_size=100 in the run, 256 asked" in err[0], err
    (rd / "config.yaml").write_text((rd / "config.yaml").read_text().replace("batch_size: 100", "batch_size: 256", 1))
    jobs = b.plan([("summers_road", "td3", 0)], 600, out, ("learner.warmup_frames=100", "collector.init_random_frames=100"))
    assert jobs[0][1][-1] == "checkpoint.resume=latest"  # a larger budget resumes the run


def test_summary_counts_and_ratios_of_completed_trials_only():
    b = _bench()
    agent = {"checkpoint": "c", "algo": "td3", "track": "fast_straights", "surface": "asphalt", "seed": 0, "frames": 10}
    rows = [{"policy": "c", "track": "kidney", "surface": "asphalt", "success": True, "laps": 10, "fastest_lap": 66.0, "flips_per_km": 3.0},
            {"policy": "c", "track": "alpine", "surface": "asphalt", "success": False, "laps": 2, "fastest_lap": 90.0, "flips_per_km": 9.0}]
    expert = {("kidney", "asphalt"): 60.0, ("alpine", "asphalt"): 70.0}
    (s,) = b.summary_rows([agent], rows, expert)
    assert (s["asphalt_completed"], s["asphalt_total"]) == (1, 2) and math.isclose(s["asphalt_lap_vs_expert"], 1.1)
    assert "| TD3 | fast_straights (asphalt) | 0 | 10 | 1/2 | 1.100 | 6.0 |" in b.summary_table([s], ["asphalt"])
    assert "| TD3 | fast_straights (asphalt) | 1 | 1/2 | 1.100 |" in b.pooled_table([s], ["asphalt"])
