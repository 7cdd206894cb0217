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
