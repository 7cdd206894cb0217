"""torcsrl/utils/collector.py: the worker collector (LeanCollector) gives TorchRL's Collector's batches."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType

from torcsrl.envs.batched import TorchRaceEnv
from torcsrl.utils.collector import LeanCollector


class _Steer(torch.nn.Module):
    """A deterministic policy of the observation (so two collectors on equally seeded envs must agree)."""

    def forward(self, rf):
        a = torch.stack([rf[..., 11] - rf[..., 7], torch.full_like(rf[..., 0], 0.4)], -1)
        return a.clamp(-1, 1)


def _collector(cls, init_random_frames=0):
    env = TorchRaceEnv(num_cars=3, track="oval", control_hz=10, substeps=20, max_steps=25, seed=7)
    policy = TensorDictModule(_Steer(), in_keys=["rangefinder"], out_keys=["action"])
    return cls(env, policy, frames_per_batch=3 * 20, total_frames=-1, exploration_type=ExplorationType.RANDOM,
               init_random_frames=init_random_frames,
               auto_register_policy_transforms=False)


@pytest.mark.parametrize("random_frames", [0, 60])
def test_lean_collector_batches_equal_torchrl_collectors(random_frames):
    """Two batches (one episode ends and resets inside them) of LeanCollector and of TorchRL's Collector, with the same
    env seed and policy, are equal in every key (trajectory ids included), shape [cars, T], time named; random frames
    draw the same actions."""
    batches = []
    for cls in (LeanCollector, Collector):
        col = _collector(cls, random_frames)
        try:
            torch.manual_seed(3)  # the random frames' actions: the same draws for both
            it = iter(col)
            batches.append([next(it).clone() for _ in range(2)])
        finally:
            col.shutdown()
    for a, b in zip(*batches):
        assert a.batch_size == b.batch_size == torch.Size([3, 20]) and a.names[-1] == "time"
        assert set(a.keys(True, True)) == set(b.keys(True, True))
        for k in a.keys(True, True):
            assert torch.equal(a[k], b[k]), k
    assert batches[0][1]["next", "done"].any()  # the episodes of 25 steps ended inside the 40 steps
    ids = batches[0][1]["collector", "traj_ids"]
    assert (ids[:, -1] > ids[:, 0]).all()  # and new trajectories began
