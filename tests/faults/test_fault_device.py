"""Defect 5: ``device`` is checked before any work: a name torch does not know, a device this machine lacks,
or one the training loop does not run on, fails with one line naming what is allowed."""

from __future__ import annotations

import pytest
import torch
from _faults import cfg_for, one_line_error, run_cli

from torcsrl.config import ConfigError, validate


def test_unknown_device_is_refused():
    with pytest.raises(ConfigError, match=r"device: 'banana' is not a torch device.*allowed: cpu") as e:
        validate(cfg_for("device=banana"))
    assert "\n" not in str(e.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_on_a_cpu_only_torch_is_refused_on_the_command_line(tmp_path):
    proc = run_cli("torcsrl.train", "device=cuda", "env=toy", "debug=smoke", f"run_dir={tmp_path / 'run'}")
    line = one_line_error(proc, "torcsrl.train")
    assert "device: 'cuda'" in line and "not available" in line and "allowed: cpu" in line
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_cpu_is_accepted():
    validate(cfg_for("device=cpu"))
