"""benchmarks/teacher_gap.py: a student and its teacher on one track, the student or the teacher driving."""

from __future__ import annotations

import re
from pathlib import Path

from _bench import load_benchmark

ROOT = Path(__file__).resolve().parents[2]
STUDENT = ROOT / "torcsrl" / "assets" / "reference_dagger.pt"  # the sensor driver's rangefinder student


def _bench():
    return load_benchmark("teacher_gap")


def test_the_student_scored_on_its_teachers_own_states_and_on_its_own(capsys):
    b = _bench()
    assert b.main([str(STUDENT), "--track", "oval", "--teacher", "sensor", "--steps", "80", "--driver", "teacher"]) == 0
    out = capsys.readouterr().out
    assert "sensor, teacher driving: step cap" in out and "where the teacher brakes harder than -0.3" in out
    steer_gap = float(re.search(r"mean \|steer gap\| ([0-9.]+)", out).group(1))
    assert steer_gap < 0.1  # a student of this teacher, on the teacher's own line
    assert b.main([str(STUDENT), "--track", "oval", "--teacher", "sensor", "--steps", "40"]) == 0
    out = capsys.readouterr().out
    assert "student driving" in out and "| dist m | speedX km/h |" in out


RACER = ROOT / "torcsrl" / "assets" / "reference_racer.pt"  # reads the opponents sensor


def test_a_racer_and_its_teacher_in_a_race_split_near_a_car_and_clear(capsys):
    b = _bench()
    assert b.main([str(RACER), "--track", "oval", "--teacher", "racer_safe:1.5", "--opponents", "3", "--steps", "200"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"race against 3 experts at pace 0.85: position ([1-4]) of 4 at the end, (\d+) contact", out)
    assert m, out
    near = re.search(r"near a car \(< 15 m\): (\d+) steps", out)
    clear = re.search(r"clear of cars: (\d+) steps", out)
    assert near and clear and int(near.group(1)) + int(clear.group(1)) == 200  # every step in one group
    assert int(near.group(1)) > 0  # from a grid start, cars are within 15 m
    last = [ln for ln in out.splitlines() if ln.startswith("| ") and not ln.startswith("| dist")][-1]
    assert 0.0 < float(last.split("|")[-2]) <= 200.0  # the nearest car's distance column [m]


def test_a_race_needs_a_student_that_reads_opponents_and_a_pace_in_range(capsys):
    b = _bench()
    for argv, words in (([str(STUDENT), "--opponents", "3"], "needs a student that reads the opponents sensor"),
                        ([str(RACER), "--opponents", "3", "--pace", "2"], "pace must be a number in [0.05, 1.5]"),
                        ([str(RACER), "--opponents", "30"], "do not fit the grid of 12 slots"),
                        ([str(RACER), "--opponents", "-1"], "--opponents must be >= 0")):
        try:
            b.main(argv)
        except SystemExit as e:
            assert e.code == 2
        else:
            raise AssertionError(f"{argv} was accepted")
        assert words in capsys.readouterr().err


def test_an_ensemble_file_is_scored_as_it_drives(tmp_path, capsys):
    from torcsrl.policies import export_ensemble, export_member

    b = _bench()
    args = ["--track", "oval", "--teacher", "racer_safe:1.5", "--steps", "60"]
    member = export_member(RACER, 0, tmp_path / "one.pt")  # the shipped racer is an ensemble: one of its students
    assert b.main([str(member), *args]) == 0
    one = capsys.readouterr().out
    ens = export_ensemble([member, member], tmp_path / "two.pt", reduce="medoid")  # two copies: the student's own actions
    assert b.main([str(ens), *args]) == 0
    two = capsys.readouterr().out
    gaps = [re.search(r"mean \|steer gap\| ([0-9.]+), mean \|pedal gap\| ([0-9.]+)", o).groups() for o in (one, two)]
    assert gaps[0] == gaps[1] and "grip estimate: mean" in two
    try:
        b.main(["racer_safe:1.5", *args])
    except SystemExit as e:
        assert e.code == 2 and "is a built-in driver" in capsys.readouterr().err
    else:
        raise AssertionError("a built-in driver was scored")


def test_a_guarded_file_is_scored_with_its_guard_and_alone_as_its_students(tmp_path, capsys):
    """A side guard (the shipped racer's) corrects only beside a car: alone on the oval a guarded ensemble scores as the
    same ensemble unguarded, to the digit; in a race it reads the opponents in metres (its students' scaling undone)."""
    from torcsrl.policies import export_ensemble, export_member

    b = _bench()
    member = export_member(RACER, 0, tmp_path / "one.pt")
    outs = []
    for name, guard in (("bare", None), ("guarded", {"clear_m": 2.6})):
        ens = export_ensemble([member, member], tmp_path / f"{name}.pt", reduce="medoid", guard=guard)
        assert b.main([str(ens), "--track", "oval", "--teacher", "racer_safe:1.5", "--steps", "60"]) == 0
        outs.append(capsys.readouterr().out)
    gaps = [re.search(r"mean \|steer gap\| ([0-9.]+), mean \|pedal gap\| ([0-9.]+)", o).groups() for o in outs]
    assert gaps[0] == gaps[1]
    assert b.main([str(tmp_path / "guarded.pt"), "--track", "oval", "--teacher", "racer_safe:1.5", "--opponents", "3", "--steps", "80"]) == 0
    assert re.search(r"race against 3 experts at pace 0.85: position [1-4] of 4", capsys.readouterr().out)
