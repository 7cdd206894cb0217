import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    """The fault suite runs on one intra-op thread (the box is shared)."""
    torch.set_num_threads(1)
