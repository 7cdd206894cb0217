"""A pure-torch proportional prioritized sampler for TorchRL replay buffers.

TorchRL's ``PrioritizedSampler`` needs its C++ segment trees, and the ``torchrl`` 0.14.1 wheel's
extension does not load against torch 2.13 (undefined symbol), so prioritized replay would be
unavailable. :class:`TorchPrioritizedSampler` implements the same sampler contract with torch
ops: P(i) = p_i^alpha / sum_j p_j^alpha (Schaul et al. 2016), importance weights
``(N P(i))^-beta`` normalised by their maximum over the buffer, new transitions at the largest
priority seen. Sampling is O(N) per batch (``torch.multinomial``): fine for the buffer sizes
used here, slower than a sum tree past a few million transitions.
"""

from __future__ import annotations

import torch
from torchrl.data.replay_buffers.samplers import Sampler


class TorchPrioritizedSampler(Sampler):
    """Proportional prioritized sampling.

    Args:
        max_capacity: the storage size.
        alpha: priority exponent [-] (0 = uniform).
        beta: importance-sampling exponent [-].
        eps: added to every priority so none is zero.
    """

    def __init__(self, max_capacity: int, alpha: float = 0.6, beta: float = 0.4, eps: float = 1e-6):
        super().__init__()
        self.alpha, self.beta, self.eps = float(alpha), float(beta), float(eps)
        self._prio = torch.zeros(int(max_capacity), dtype=torch.float64)
        self._max = 1.0

    def sample(self, storage, batch_size: int):
        n = len(storage)
        if n == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        p = self._prio[:n].pow(self.alpha)
        probs = p / p.sum()
        index = torch.multinomial(probs, batch_size, replacement=True)
        w = (n * probs[index]).pow(-self.beta)
        w_max = (n * probs.min()).pow(-self.beta)
        return index, {"priority_weight": (w / w_max).to(torch.float32)}

    def extend(self, index: torch.Tensor) -> None:
        self._prio[torch.as_tensor(index).reshape(-1)] = self._max

    def add(self, index: int) -> None:
        self._prio[index] = self._max

    def update_priority(self, index, priority, *, storage=None) -> None:
        index = torch.as_tensor(index).reshape(-1)
        pr = torch.as_tensor(priority, dtype=torch.float64).reshape(-1).abs() + self.eps
        self._prio[index] = pr
        self._max = max(self._max, float(pr.max()))

    def _empty(self) -> None:
        self._prio.zero_()
        self._max = 1.0

    def state_dict(self) -> dict:
        return {"prio": self._prio.clone(), "max": self._max}

    def load_state_dict(self, state_dict: dict) -> None:
        self._prio.copy_(state_dict["prio"])
        self._max = float(state_dict["max"])

    def dumps(self, path) -> None:
        from pathlib import Path

        Path(path).mkdir(parents=True, exist_ok=True)
        torch.save(self.state_dict(), Path(path) / "priorities.pt")

    def loads(self, path) -> None:
        from pathlib import Path

        self.load_state_dict(torch.load(Path(path) / "priorities.pt", weights_only=True))

    def _sampleable_count(self, storage) -> int:  # noqa: D401 - TorchRL hook
        return len(storage)
