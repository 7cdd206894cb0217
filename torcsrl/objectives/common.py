"""Pieces shared by our actor-critic losses: target-network binding and batch unpacking."""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase, TensorDictParams
from torch import nn

from torcsrl.nets import random_shift, shift_pad


def bind_target(module: nn.Module, target_params: TensorDictParams) -> nn.Module:
    """A copy of ``module`` whose parameters ARE the tensors of ``target_params``.

    TorchRL's ``SoftUpdate``/``HardUpdate`` and ``load_state_dict`` update ``target_params`` in
    place, so the copy always computes with the current target weights, without the cost of
    swapping parameters in and out of the module on every call (~100 us each on CPU).
    """
    target = copy.deepcopy(module)
    for key, val in target_params.items(True, True):
        key = key if isinstance(key, tuple) else (key,)
        sub = target
        for k in key[:-1]:
            sub = getattr(sub, k)
        name = key[-1]
        sub._parameters.pop(name, None)
        sub._buffers.pop(name, None)
        sub.register_buffer(name, val, persistent=False)
    return target


class ObsUnpacker:
    """Reads the observation tensors of a batch (root or ``"next"``) in network order, with optional DrQ shifts.

    Args:
        keys: observation keys in the order the networks take them.
        image_keys: the subset of ``keys`` that are images (augmented when ``shift > 0``).
        shift: DrQ random-shift padding in pixels (0 = no augmentation), or ``(rows, cols)`` (:func:`shift_pad`).
    """

    def __init__(self, keys: list[str], image_keys: list[str], shift: int | tuple[int, int] = 0):
        self.keys, self.image_keys, self.shift = list(keys), set(image_keys), shift_pad(shift)

    def __call__(self, td: TensorDictBase, nxt: bool = False) -> list[torch.Tensor]:
        src = td.get("next") if nxt else td
        out = []
        for k in self.keys:
            x = src.get(k)
            if any(self.shift) and k in self.image_keys:
                x = random_shift(x, self.shift)
            out.append(x)
        return out


def discount(td: TensorDictBase, gamma: float, key: str) -> torch.Tensor | float:
    """gamma ** n for n-step batches (``key``: n, written by TorchRL's MultiStepTransform), else gamma."""
    n = td.get(key, None)
    if n is None:
        return gamma
    return gamma ** n.to(torch.float32)
