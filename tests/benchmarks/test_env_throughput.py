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


def test_the_raw_racecar_stays_on_the_plane(monkeypatch):
    """The reference car is carried back before it drives off pybullet_data's plane: one falling through empty space
    has no contacts and steps ~2.5x faster, which halved the env/raw ratio of long runs."""
    import pybullet as p

    bench = load_benchmark("physics_throughput")
    monkeypatch.setattr(bench, "PLANE_KEEP_M", 3.0)
    step, close = bench.make_racecar(rays=19)
    try:
        for _ in range(1500):  # ~12 m at the random actions' pace
            step()
        (x, y, z), _ = p.getBasePositionAndOrientation(step.car, physicsClientId=step.client)
    finally:
        close()
    assert abs(x) <= 3.5 and abs(y) <= 3.5 and z > -0.5


def test_env_profile_times_the_parts_of_a_step(capsys):
    """benchmarks/env_profile.py: every part is timed inside the step it belongs to, and the table prints."""
    from torcsrl.envs.race.core import RaceCore

    bench = load_benchmark("env_profile")
    step = RaceCore.__dict__["step"]
    r = bench.profile(steps=80)
    assert RaceCore.__dict__["step"] is step  # the timers are taken off again
    assert r["env.step"] > r["RaceCore.step"] > r["car physics (CarFleet.step)"] > r["reading the bodies' frames"] > 0
    assert r["observation"] > r["rangefinder rays"] > 0 and r["gym info dict"] > 0
    assert bench.main(["--steps", "40"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"car physics \(CarFleet.step\) +\d+\.\d +\d+\.\d%", out) and "reset (RaceCore.reset)" in out
