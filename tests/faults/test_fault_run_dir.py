"""Defect 3: a run folder holds one run. A second run into a folder in use is refused (a lock); a fresh run into a
folder holding an older run is refused unless it resumes it or asks to overwrite it; overwriting leaves no old rows."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from _faults import ENV, ROOT, cfg_for, one_line_error, run_cli

from torcsrl.training import train
from torcsrl.utils.checkpoint import CheckpointError
from torcsrl.utils.faults import RunDirError
from torcsrl.utils.logging import read_csv_metric


def test_second_run_into_a_finished_folder_is_refused_then_overwritten(tmp_path):
    run = tmp_path / "run"
    train(cfg_for(f"run_dir={run}", "total_frames=200"))
    steps = [s for s, _ in read_csv_metric(run, "train/frames")]
    with pytest.raises(RunDirError, match=r"already holds a run \(checkpoints, logs.*allowed: checkpoint.resume=latest.*overwrite=true") as e:
        train(cfg_for(f"run_dir={run}", "total_frames=200"))
    assert "\n" not in str(e.value)
    assert [s for s, _ in read_csv_metric(run, "train/frames")] == steps  # nothing appended
    train(cfg_for(f"run_dir={run}", "total_frames=200", "overwrite=true"))
    assert [s for s, _ in read_csv_metric(run, "train/frames")] == steps  # the new run's rows only, not appended


def test_second_command_into_a_finished_folder_is_one_line(tmp_path):
    run = tmp_path / "run"
    train(cfg_for(f"run_dir={run}", "total_frames=200"))
    before = (run / "config.yaml").exists()
    proc = run_cli("torcsrl.train", "env=toy", "debug=smoke", "total_frames=200", f"run_dir={run}", f"hydra.run.dir={tmp_path / 'h'}")
    line = one_line_error(proc, "torcsrl.train")
    assert "already holds a run" in line and "overwrite=true" in line
    assert (run / "config.yaml").exists() == before  # the refused run wrote nothing


def test_two_runs_into_one_folder_at_once(tmp_path):
    run = tmp_path / "run"
    first = subprocess.Popen([sys.executable, "-m", "torcsrl.train", "env=toy", "debug=smoke", "total_frames=1000000",
                              f"run_dir={run}", f"hydra.run.dir={tmp_path / 'h1'}"], cwd=ROOT, env=ENV,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (run / "logs").exists():
            assert first.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        for extra in ("overwrite=true", "checkpoint.resume=latest"):
            with pytest.raises(RunDirError, match=f"run_dir {run} is in use by another run \\(pid {first.pid}\\); allowed") as e:
                train(cfg_for(f"run_dir={run}", extra))
            assert "\n" not in str(e.value)
        assert first.poll() is None  # the first run goes on
    finally:
        first.kill()
        first.wait()
    # the kernel released the lock of the killed run: resuming is allowed now
    try:
        train(cfg_for(f"run_dir={run}", "checkpoint.resume=latest"))
    except CheckpointError as err:  # killed before its first checkpoint
        assert "holds no checkpoint" in str(err)
