import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    """STYLE: algorithm tests run on one intra-op thread (the box is shared)."""
    torch.set_num_threads(1)
