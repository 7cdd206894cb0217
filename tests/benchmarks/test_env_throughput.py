"""benchmarks/env_throughput.py's table of the env against raw pybullet runs and prints both ratios."""

from __future__ import annotations

import re

from _bench import load_benchmark


def test_the_env_vs_raw_table_prints_both_ratios(capsys):
    bench = load_benchmark("env_throughput")
    r = bench.vs_raw(steps=60, rounds=1)
    assert r["raw"] > 0 and r["env_step"] >= r["env_all"] > 0
    bench.print_vs_raw(r, 60, 1)
    out = capsys.readouterr().out
    assert re.search(r"ratio env / raw, step only: +\d+\.\d\dx", out)
    assert re.search(r"ratio env / raw, resets included: +\d+\.\d\dx", out)
