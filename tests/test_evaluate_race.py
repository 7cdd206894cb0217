"""The evaluate command's race mode: N laps against K opponents, the race table and its files."""

from __future__ import annotations

import pytest
import torch

from torcsrl.evaluate import EvalError
from torcsrl.evaluate.race import RACE_COLUMNS, evaluate_race, race_summary, race_table


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def test_race_table_from_a_short_race(tmp_path):
    tr = {"opponents": 2, "driver": {"kind": "expert", "pace": 0.6}, "order": "fixed", "learner_slot": "first"}
    res = evaluate_race("expert", "oval", laps=1, out_dir=tmp_path, traffic=tr, env_kwargs={"control_hz": 10, "substeps": 20},
                        verbose=False)
    row = res["episodes"][0]
    assert row["success"] and row["position"] == 1 and row["win"]  # from pole at full pace against 60 % pace
    assert row["collisions"] == 0 and row["damage"] == 0.0 and row["lead_m"] > 0 and row["opponents"] == 2
    assert (row["contacts_ahead"], row["contacts_alongside"], row["contacts_behind"]) == (0, 0, 0)
    assert row["start_position"] == 1 and row["opponent_paces"] == [0.6, 0.6]  # learner_slot first
    s = res["summary"][0]
    assert (s["races"], s["finished"], s["wins"], s["mean_position"]) == (1, 1, 1, 1.0)
    md = (tmp_path / "race.md").read_text()
    assert "| " + " | ".join(RACE_COLUMNS) + " |" in md and "| oval | asphalt | 1 | 1/1 | 1/1 | 1.00 | 0.00 |" in md
    assert "give 3.2 m of room to a car alongside" in md  # which opponents the table was raced against
    assert md.split("| oval | asphalt | 1 | 1/1 | 1/1 |")[1].split("\n")[0].rstrip().endswith("| 1 |")  # 1 scenario raced
    assert (tmp_path / "race_oval_asphalt.png").stat().st_size > 0 and (tmp_path / "race_episodes.csv").exists()


def test_the_race_trace_marks_each_contact_by_where_the_other_car_was(tmp_path):
    """A full-pace expert from the back of the grid runs into two 50 % experts (it does not see them): the trace's
    contacts carry their sides, the learner's add up to its row's ``contacts_*`` and the race plot draws them."""
    from torcsrl.envs import tracks
    from torcsrl.envs.traffic import Traffic
    from torcsrl.evaluate.plots import plot_race
    from torcsrl.evaluate.race import run_race_cell
    from torcsrl.policies import load_policy

    tr = {"opponents": 2, "driver": {"kind": "expert", "pace": 0.5}, "order": "fixed", "learner_slot": "last"}
    rows, traces = run_race_cell(load_policy("expert"), "oval", None, tr, laps=1, env_kwargs={"control_hz": 10, "substeps": 20},
                                 trace=True)
    row, hits = rows[0], traces[0]["hits"]
    assert row["collisions"] >= 1 and all(side in Traffic.CONTACT_SIDES for _, _, side in hits)
    own = [side for _, car, side in hits if car == 0]
    assert len(own) == row["collisions"]
    assert [own.count(k) for k in Traffic.CONTACT_SIDES] == [row[f"contacts_{k}"] for k in Traffic.CONTACT_SIDES]
    assert row["contacts_ahead"] >= 1 and any(car != 0 and side == "behind" for _, car, side in hits)  # it ran into them
    assert plot_race(tracks.load("oval"), traces[0], tmp_path / "race.png").stat().st_size > 0
    old = {**traces[0], "hits": [(t, c) for t, c, _ in hits]}  # a trace without sides (crosses) still plots
    assert plot_race(tracks.load("oval"), old, tmp_path / "old.png").stat().st_size > 0


def test_race_summary_counts_dnf_and_table_rows():
    rows = [{"track": "t", "surface": "asphalt", "opponents": 3, "position": 2, "win": False, "collisions": 1, "overtakes": 1,
             "damage": 0.5, "gap_ahead_m": 4.0, "lead_m": -4.0, "contacts_ahead": 1, "contacts_alongside": 0, "contacts_behind": 0},
            {"track": "t", "surface": "asphalt", "opponents": 3, "position": None, "win": False, "collisions": 3, "overtakes": 0,
             "damage": 2.5, "gap_ahead_m": 9.0, "lead_m": -30.0, "contacts_ahead": 0, "contacts_alongside": 1, "contacts_behind": 2}]
    s = race_summary(rows)
    assert (s["finished"], s["wins"], s["mean_position"], s["collisions_per_race"]) == (1, 0, 2.0, 2.0)
    assert (s["contact_free"], s["most_collisions"]) == (0, 3)
    header, body = race_table([s])
    assert header == list(RACE_COLUMNS) and body[0][3:9] == ["1/2", "0/2", "2.00", "2.00", "0/2", "3"]
    assert header[9] == "coll. ahead·alongside·behind" and body[0][9] == "1·1·2"  # where the other car was, summed


def test_the_race_summary_tells_a_pile_up_from_contacts_spread_over_the_races():
    """25 contacts in 24 races: 12 in one and 13 over the rest, or about one a race — the same mean, told apart by the
    contact-free races and the most in one race."""
    row = {"track": "t", "surface": "asphalt", "opponents": 3, "position": 1, "win": True, "overtakes": 0, "damage": 0.0,
           "gap_ahead_m": 0.0, "lead_m": 5.0}
    pile_up = [{**row, "collisions": c} for c in [12] + [1] * 13 + [0] * 10]
    spread = [{**row, "collisions": c} for c in [2] + [1] * 23]
    a, b = race_summary(pile_up), race_summary(spread)
    assert a["collisions_per_race"] == b["collisions_per_race"] == 25 / 24
    assert (a["contact_free"], a["most_collisions"]) == (10, 12) and (b["contact_free"], b["most_collisions"]) == (0, 2)


def test_races_from_the_same_start_are_the_same_race_and_the_table_counts_scenarios():
    """Deterministic physics: against identical opponents at one pace the race seed only moves the learner's start
    position, and two races from the same start end the same; `scenarios` counts the distinct starts (and paces)."""
    tr = {"opponents": 1, "driver": {"kind": "expert", "pace": 0.6}, "order": "random"}
    kw = {"laps": 1, "traffic": tr, "env_kwargs": {"control_hz": 10, "substeps": 20}, "plots": False, "verbose": False}
    rows = evaluate_race("expert", "oval", episodes=4, **kw)["episodes"]
    starts = [r["start_position"] for r in rows]
    assert set(starts) <= {1, 2} and len(set(r["env_seed"] for r in rows)) == 4
    by_start = {}
    for r in rows:
        by_start.setdefault(r["start_position"], set()).add((r["steps"], r["fastest_lap"], r["position"]))
    assert all(len(v) == 1 for v in by_start.values()), by_start  # one race per start, whatever the seed
    assert race_summary(rows)["scenarios"] == len(set(starts))
    drawn = evaluate_race("expert", "oval", episodes=4, **{**kw, "traffic": {**tr, "driver": {"kind": "expert", "pace": [0.55, 0.65]}}})
    assert drawn["summary"][0]["scenarios"] == 4  # a pace drawn per race: every race its own
    assert len({r["opponent_paces"][0] for r in drawn["episodes"]}) == 4
    rolling = evaluate_race("expert", "oval", episodes=3, **{**kw, "env_kwargs": {**kw["env_kwargs"], "start": "random"}})  # evaluate start=random: the grid at a random point of the lap
    assert rolling["summary"][0]["scenarios"] == 3 and len({tuple(r["start_xy_m"]) for r in rolling["episodes"]}) == 3


def test_race_mode_bad_input_one_line():
    with pytest.raises(EvalError, match="do not fit the grid"):
        evaluate_race("expert", "oval", opponents=20, verbose=False)


def test_race_workers_give_the_same_races(tmp_path):
    """workers=2 spreads the tracks' races over processes: the same rows as in one process (seeded per track and race)."""
    tr = {"opponents": 1, "driver": {"kind": "expert", "pace": 0.6}, "order": "random"}
    kw = {"laps": 1, "traffic": tr, "env_kwargs": {"control_hz": 10, "substeps": 20}, "plots": False, "verbose": False}
    one = evaluate_race("expert", ["oval", "hairpins"], workers=1, **kw)
    two = evaluate_race("expert", ["oval", "hairpins"], workers=2, **kw)
    keys = ("track", "position", "collisions", "steps", "fastest_lap", "env_seed")
    assert [tuple(r[k] for k in keys) for r in one["episodes"]] == [tuple(r[k] for k in keys) for r in two["episodes"]]
    assert [r["track"] for r in two["episodes"]] == ["oval", "hairpins"]


def test_race_opponents_side_gap_reaches_the_traffic_and_is_checked():
    """side_gap_m (evaluate's key, --side-gap) sets how much room the scripted opponents give a car alongside; 0 gives
    the blind opponents of before; a bad value fails in one line before anything drives."""
    from torcsrl.envs.traffic import TrafficSpec
    from torcsrl.evaluate.race import race_traffic

    assert TrafficSpec.from_config(race_traffic(3, 0.85)).side_gap_m == 3.2
    assert TrafficSpec.from_config(race_traffic(3, 0.85, side_gap_m=0)).side_gap_m == 0.0
    with pytest.raises(EvalError, match="side_gap_m must be a number") as e:
        evaluate_race("expert", "oval", laps=1, side_gap_m=-2, plots=False, verbose=False)
    assert "\n" not in str(e.value)
