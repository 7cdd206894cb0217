"""Frame stacking: the actor sees the last K frames of each image key, stacked along channels.

``frame_stack: K`` (top level of the training config) puts :class:`FrameStack` at the END of the
observation pipeline (:func:`torcsrl.train.observation_transforms`: after every degradation and the
scaling), so each frame in a stack is the frame the car saw at that step, weather and all. A
``pixels`` observation ``[3, H, W]`` becomes ``[3K, H, W]`` (uint8), oldest frame first, newest in
the last three channels. At a reset the stack holds K copies of the first frame (TorchRL's
``CatFrames``, ``padding="same"``); partial resets of a batched env reset their rows only.

It is not a degradation: nothing is lost or corrupted, and it carries no random state. What it
does carry (the last K - 1 frames of every row) is part of an exact resume (:meth:`get_sim_state`).

The replay ring stores every frame ONCE (:class:`torcsrl.utils.replay.ReplayBuffer`, ``history=``):
a row keeps the newest frame of its stack, and a sampled transition gathers the K - 1 frames before
it from the same stream's earlier rows, cut at the episode's start (padded with its first frame: the
same stack this transform gave the policy). So a demonstration folder written at K = 1 trains a
student of any K, and K does not multiply the bytes per transition.

:class:`torcsrl.policies.CheckpointPolicy` keeps the same history itself (reset per episode), so a
stacked checkpoint drives the plain one-frame envs of ``evaluate``, ``report`` and the benchmarks.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
from torch.nn.parameter import UninitializedBuffer
from torchrl.envs import CatFrames

__all__ = ["IMAGE_KEYS", "FrameStack", "stack_frames"]

#: Observation keys that are images ``[C, H, W]`` (stackable).
IMAGE_KEYS = ("pixels", "depth")


class FrameStack(CatFrames):
    """TorchRL's ``CatFrames`` along the channel dim (``dim=-3``) of ``keys``, K frames, first frame repeated at a reset.

    Args:
        frames: K, frames per stack (>= 2; one frame needs no transform).
        keys: image observation keys ``[C, H, W]`` to stack.
    """

    def __init__(self, frames: int, keys: Sequence[str]):
        if int(frames) < 2:
            raise ValueError(f"FrameStack: frames={frames}; allowed: an integer >= 2 (one frame needs no stack)")
        super().__init__(N=int(frames), dim=-3, in_keys=list(keys), padding="same")
        self.frames = int(frames)

    # exact resume (torcsrl.train._stateful_transforms): the frames held for the next stack
    def get_sim_state(self) -> dict[str, Any]:
        """The frames held per key (None before the first reset: CatFrames' buffers are uninitialised until then)."""
        return {name: None if isinstance(buf, UninitializedBuffer) else buf.clone()
                for name, buf in self.named_buffers() if name.startswith("_cat_buffers_")}

    def set_sim_state(self, state: dict[str, Any]) -> None:
        for name, value in state.items():
            if value is None:
                self.register_buffer(name, UninitializedBuffer(device=torch.device("cpu"), dtype=torch.get_default_dtype()))
            else:
                self.register_buffer(name, value.clone())


def stack_frames(history: torch.Tensor | None, frame: torch.Tensor, frames: int) -> torch.Tensor:
    """The next stack ``[..., K*C, H, W]`` of a policy that keeps its own history: ``frame`` ``[..., C, H, W]``
    appended to ``history`` (the previous stack, or None at an episode's start: K copies of ``frame``)."""
    c = frame.shape[-3]
    if history is None or history.shape[:-3] != frame.shape[:-3]:
        return torch.cat([frame] * int(frames), -3)
    return torch.cat([history[..., c:, :, :], frame], -3)
