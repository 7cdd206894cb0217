"""Defect 1: SIGTERM (what ``kill``, ``timeout`` and job schedulers send), SIGINT and SIGKILL to a run with worker
processes -- ``report --workers``, ``evaluate --workers`` and training with ``collector.num_workers >= 1`` -- leave no
worker or resource tracker behind; on SIGTERM / SIGINT the run exits with one line (no KeyboardInterrupt traceback),
and its finished cells and checkpoints stay intact."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _faults import ENV, ROOT, alive, descendants

from torcsrl.utils.checkpoint import latest_checkpoint, load_checkpoint


def _start(module: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", module, *args], cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(proc: subprocess.Popen, ready, timeout_s: float = 180.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        if proc.poll() is not None:
            pytest.fail(f"the run ended before the fault could be injected: {proc.stderr.read()[-2000:]}")
        assert time.monotonic() < deadline, "timed out waiting for the run to reach the point of the fault"
        time.sleep(0.05)


def _signal_and_check(proc: subprocess.Popen, sig: int, min_children: int) -> str:
    """Send ``sig`` once ``min_children`` descendants exist; return stderr. Every descendant seen must be gone."""
    kids = descendants(proc.pid)
    assert len(kids) >= min_children, kids
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"the run did not stop within 60 s of {signal.Signals(sig).name}: {err[-2000:]}")
    deadline = time.monotonic() + 20
    while any(alive(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [k for k in kids if alive(k)]
    for k in left:  # do not leave them to the rest of the suite
        try:
            os.kill(k, signal.SIGKILL)
        except OSError:
            pass
    assert not left, f"{len(left)} orphaned process(es) after {signal.Signals(sig).name}: {left}"
    if sig != signal.SIGKILL:
        assert "Traceback" not in err, err[-3000:]
        assert proc.returncode == 128 + sig, (proc.returncode, err[-2000:])
        lines = [ln for ln in err.splitlines() if ": error: stopped by" in ln]
        assert len(lines) == 1 and signal.Signals(sig).name in lines[0], err[-2000:]
    return err


def _cells(cache: Path) -> list[Path]:
    return sorted(cache.glob("*.json")) if cache.is_dir() else []


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_report_workers_stop_with_the_run(tmp_path, sig):
    out = tmp_path / "r"
    proc = _start("torcsrl.report", "--policy", "heuristic", "--tracks", "oval", "--degradations", "rangefinder.noise",
                  "state.noise", "--severities", "0", "1", "3", "5", "--workers", "2", "--max-steps", "400", "--out", str(out))
    _wait_for(proc, lambda: len(descendants(proc.pid)) >= 3)
    time.sleep(4.0)  # the workers are driving cells
    _signal_and_check(proc, sig, min_children=3)  # two workers and the resource tracker
    for p in _cells(out / "cells"):  # finished cells intact
        assert json.loads(p.read_text())["rows"]


def test_evaluate_workers_stop_on_sigint(tmp_path):
    proc = _start("torcsrl.evaluate", "--policy", "heuristic", "--track", "oval", "esses", "kidney", "--laps", "1",
                  "--expert-laps", "0", "--no-plots", "--workers", "2", "--max-steps", "20000", "--out", str(tmp_path / "e"))
    _wait_for(proc, lambda: len(descendants(proc.pid)) >= 3)
    time.sleep(3.0)  # the workers are driving
    _signal_and_check(proc, signal.SIGINT, min_children=3)


@pytest.mark.parametrize("sig", [signal.SIGTERM])  # SIGKILL: benchmarks/fault_soak.py (TorchRL's workers exit with their parent)
def test_training_with_collector_workers_stops_with_the_run(tmp_path, sig):
    run = tmp_path / "run"
    proc = _start("torcsrl.train", "env=toy", "debug=smoke", "collector.num_workers=2", "checkpoint.every_frames=200",
                  "total_frames=100000", f"run_dir={run}", f"hydra.run.dir={tmp_path / 'hydra'}")
    _wait_for(proc, lambda: latest_checkpoint(run / "checkpoints") is not None)
    err = _signal_and_check(proc, sig, min_children=2)
    last = latest_checkpoint(run / "checkpoints")
    if sig == signal.SIGTERM:
        assert str(last) in err and "checkpoint.resume=latest" in err
        # the resume hint repeats the run's own overrides (a bare run_dir= resume would build another config), not
        # run_dir / hydra.* twice
        cmd = shlex.split(err.split("resume: ", 1)[1].splitlines()[0])
        assert cmd == ["python", "-m", "torcsrl.train", "env=toy", "debug=smoke", "collector.num_workers=2",
                       "checkpoint.every_frames=200", "total_frames=100000", f"run_dir={run}", "checkpoint.resume=latest"], cmd
    assert load_checkpoint(last)["counters"]["frames"] >= 200


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_generalisation_benchmark_workers_stop_with_it(tmp_path, sig):
    """``benchmarks/generalisation.py --workers 2`` stopped midway: its trial workers go with it (SIGTERM: one line,
    exit 143; SIGKILL: they die with their parent)."""
    proc = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "generalisation.py"), "--screen", "--policy", "heuristic",
                             "--laps", "10", "--generated", "2", "--surfaces", "asphalt", "--workers", "2", "--out", str(tmp_path / "g")],
                            cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for(proc, lambda: len(descendants(proc.pid)) >= 2)
    time.sleep(3.0)  # the workers are driving
    err = _signal_and_check(proc, sig, min_children=2)
    if sig == signal.SIGTERM:
        assert "generalisation: error: stopped by SIGTERM; no table written" in err
    assert not (tmp_path / "g" / "generalisation.json").exists()
