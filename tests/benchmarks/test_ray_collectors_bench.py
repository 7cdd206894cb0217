"""benchmarks/ray_collectors.py: a worker count that cannot share the cars is refused in one line before anything
starts; one tiny real measurement of each contender (local processes, Ray actors) gives the table's row."""

from __future__ import annotations

import pytest
from _bench import load_benchmark


def test_a_worker_count_that_does_not_divide_the_cars_is_one_line(capsys):
    pytest.importorskip("ray")
    b = load_benchmark("ray_collectors")
    assert b.main(["--workers", "3", "--cars", "8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["--workers 3: the 8 cars are split evenly over the workers; allowed: divisors of 8"]


def test_both_contenders_measure_frames(capsys):
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        ray.shutdown()
    b = load_benchmark("ray_collectors")
    for kind in ("local", "ray"):
        r = b.measure(kind, 1, 2, 8, 1)
        assert r["kind"] == kind and r["fps"] > 0 and r["start_s"] > 0
    assert not ray.is_initialized()  # the Ray instance the benchmark started is shut down after it
