"""Defect 5: ``device`` is checked before any work: a name torch does not know, a device this machine lacks,
or one the training loop does not place networks on, fails with one line naming what is allowed.
(Where the networks go when it is accepted: tests/test_train_device.py.)"""

from __future__ import annotations

import pytest
import torch
from _faults import cfg_for

from torcsrl.config import ConfigError, validate


def test_unknown_device_is_refused():
    with pytest.raises(ConfigError, match=r"device: 'banana' is not a torch device.*allowed: cpu") as e:
        validate(cfg_for("device=banana"))
    assert "\n" not in str(e.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_on_a_cpu_only_torch_is_refused_before_training(tmp_path):
    from torcsrl.training import train

    with pytest.raises(ConfigError, match=r"device: 'cuda' is not available on this machine.*allowed: cpu") as e:
        train(cfg_for("device=cuda", f"run_dir={tmp_path / 'run'}"))
    assert "\n" not in str(e.value) and not (tmp_path / "run").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA here")
def test_cuda_where_it_exists_is_accepted():
    validate(cfg_for("device=cuda"))


def test_devices_the_loop_does_not_place_on_are_refused():
    with pytest.raises(ConfigError, match=r"device: 'meta': the training loop places its networks on cpu or cuda only; allowed: cpu") as e:
        validate(cfg_for("device=meta"))
    assert "\n" not in str(e.value)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA here")
def test_gpu_with_worker_processes_is_refused():
    with pytest.raises(ConfigError, match=r"collector.num_workers=2.*allowed: collector.num_workers=0 with a GPU device"):
        validate(cfg_for("device=cuda", "collector.num_workers=2"))


def test_cpu_is_accepted():
    validate(cfg_for("device=cpu"))
