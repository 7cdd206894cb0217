"""Frame stacking: the actor sees the last K frames of each image key, stacked along channels — and, with
``state_history: K``, the last K readings of its on-board state (``state`` / ``telemetry``), concatenated.

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

**State history** (``state_history: K``, :data:`HISTORY_KEYS`): the same transform along the last dim
(``dim=-1``): ``state`` ``[11]`` becomes ``[11K]``, oldest reading first, after the scaling. One reading
says little about the road's grip; about a second of them (wheel spin against speed under throttle and
braking) says it well — the adaptation-module idea of RMA (Kumar et al. 2021), here as a plain input. The
replay stores such a row whole (a vector is cheap), so demonstrations must be written at the same K.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
from torch.nn.parameter import UninitializedBuffer
from torchrl.envs import CatFrames

__all__ = ["HISTORY_KEYS", "IMAGE_KEYS", "FrameStack", "stack_frames"]

#: Observation keys that are images ``[C, H, W]`` (stackable).
IMAGE_KEYS = ("pixels", "depth")
#: Vector keys ``[D]`` whose last K readings ``state_history: K`` gives the actor (on-board state).
HISTORY_KEYS = ("state", "telemetry")


class FrameStack(CatFrames):
    """TorchRL's ``CatFrames`` along the channel dim (``dim=-3``) of ``keys``, K frames, first frame repeated at a reset.

    Args:
        frames: K, frames per stack (>= 2; one frame needs no transform).
        keys: observation keys to stack: images ``[C, H, W]`` (``dim=-3``) or vectors ``[D]`` (``dim=-1``).
        dim: the dim the frames are concatenated along: -3 (image channels) or -1 (a vector's readings).
    """

    def __init__(self, frames: int, keys: Sequence[str], dim: int = -3):
        if int(frames) < 2:
            raise ValueError(f"FrameStack: frames={frames}; allowed: an integer >= 2 (one frame needs no stack)")
        if dim not in (-3, -1):
            raise ValueError(f"FrameStack: dim={dim}; allowed: -3 (images [C, H, W]) or -1 (vectors [D])")
        super().__init__(N=int(frames), dim=int(dim), in_keys=list(keys), padding="same")
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


def stack_frames(history: torch.Tensor | None, frame: torch.Tensor, frames: int, dim: int = -3,
                 restart: Sequence[int] | None = None) -> torch.Tensor:
    """The next stack ``[..., K*C, H, W]`` of a policy that keeps its own history: ``frame`` ``[..., C, H, W]``
    appended to ``history`` (the previous stack, or None at an episode's start: K copies of ``frame``).
    ``dim=-1``: the same for vectors, ``[..., D]`` -> ``[..., K*D]``. ``restart``: rows of a batch (the first dim)
    that start a new episode: their stacks are K copies of their ``frame``, as ``CatFrames`` does on a partial reset."""
    c = frame.shape[dim]
    if history is None or history.shape[:dim] != frame.shape[:dim]:
        return torch.cat([frame] * int(frames), dim)
    stack = torch.cat([history.narrow(dim, c, history.shape[dim] - c), frame], dim)
    if restart:
        rows = list(restart)
        stack[rows] = torch.cat([frame[rows]] * int(frames), dim)
    return stack
