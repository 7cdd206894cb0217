"""Fixtures for the transform contract tests (pybullet-free: a toy env with the four keys)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))  # _toy_sensor_env, also for ParallelEnv workers


@pytest.fixture(autouse=True)
def _one_thread():
    """One intra-op thread, as the benchmarks measure and a shared 2-core machine prefers;
    restored afterwards so other test folders keep their own setting."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
