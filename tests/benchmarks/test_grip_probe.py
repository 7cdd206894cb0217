"""benchmarks/grip_probe.py: how well a history of the on-board state tells the road's friction (training tracks only)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from _bench import load_benchmark


def _bench():
    return load_benchmark("grip_probe")


def test_history_rows_hold_the_last_readings_oldest_first():
    x = np.arange(8, dtype=np.float32).reshape(4, 2)
    h = _bench().history(x, 3)
    assert h.shape == (4, 6)
    assert h[0].tolist() == [0, 1, 0, 1, 0, 1]  # the first reading repeated before the start
    assert h[3].tolist() == [2, 3, 4, 5, 6, 7]


def test_a_short_probe_prints_its_table_on_every_surface(capsys):
    b = _bench()
    assert b.main(["--steps", "25", "--history", "1", "3", "--fit-steps", "30"]) == 0
    out = capsys.readouterr().out
    assert "52 (track, surface) pairs" in out and "tested on gen-10005..8" in out
    rows = re.findall(r"^\| (\d+) \| ([0-9.]+) \|", out, flags=re.M)
    assert [r[0] for r in rows] == ["1", "3"] and all(0.0 < float(r[1]) < 1.0 for r in rows)
    for bad in (["--history", "0"], ["--policy", "nope"]):
        with pytest.raises(SystemExit):
            b.main(bad)
    assert "--policy: policy 'nope' is neither a checkpoint file" in capsys.readouterr().err
