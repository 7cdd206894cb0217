"""Defect 6: resuming compares the env (and degradation) settings with the checkpoint's and names the difference,
instead of restoring one track's state into another track's env, or failing with a traceback for another num_cars."""

from __future__ import annotations

import pytest
from _faults import cfg_for

from torcsrl.training import train
from torcsrl.utils.checkpoint import CheckpointError


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    import torch

    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("resume_env") / "run"
    train(cfg_for(f"run_dir={d}", "total_frames=300", "checkpoint.every_frames=300"))
    return d


@pytest.mark.parametrize("override,named", [
    ("env.track=oval", "env.track='stadium' in the checkpoint, 'oval' here"),
    ("env.num_cars=2", "env.num_cars=1 in the checkpoint, 2 here"),
    ("degradation=rangefinder.noise", "degradation.stack.rangefinder_noise"),
])
def test_resume_with_another_env_names_the_difference(run, override, named):
    with pytest.raises(CheckpointError, match="was written for another env") as e:
        train(cfg_for(f"run_dir={run}", "total_frames=600", "checkpoint.resume=latest", override))
    assert named in str(e.value) and "\n" not in str(e.value)
