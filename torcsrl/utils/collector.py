"""In-process data collection: TorchRL's ``Collector`` semantics without its per-step machinery.

With one env step per gradient step, TorchRL's ``Collector`` spends ~1-2 ms per step on
bookkeeping around ``env.step_and_maybe_reset`` (carrier updates, device casts, stacking into
its output buffer) — as much as a quarter of a TD3 step on the project's CPU.
:class:`StepCollector` keeps what the training loop relies on and nothing else:

* a batch is ``frames_per_batch`` frames (``frames_per_batch / batch numel`` env steps), time
  on the last dim (``[T]`` for a single env, ``[N, T]`` for N cars), like ``Collector`` — except
  that a batch of ONE step keeps the env's batch shape (``[]`` or ``[N]``: no copy to add a
  time dim);
* before ``init_random_frames`` frames have been collected (checked at the start of a batch)
  actions are drawn uniformly from the action spec (``env.rand_action``), afterwards from the
  policy, under ``ExplorationType.RANDOM`` and ``torch.no_grad``;
* ``env.step_and_maybe_reset`` steps and resets finished cars (partial resets);
* the entries of TorchRL's ``InitTracker`` and ``RewardSum`` transforms (``"is_init"``: the
  observation comes from a reset, read by the OU noise; ``("next", "episode_reward")``: the
  return so far) are kept here, where the env lacks them, for ~0.3 ms per step less than the
  transforms cost;
* the policy's lean per-step path (``policy.act``, :class:`~torcsrl.agents.exploration.BehaviourPolicy`)
  is used when it has one;
* its state (frames and the in-flight tensordict: exploration-noise state and the running
  return included) is checkpointable for an exact resume.

Multi-process collection stays with TorchRL's ``MultiSyncCollector``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type


class StepCollector:
    """Iterates over batches of ``frames_per_batch`` frames of ``env`` driven by ``policy``.

    Args:
        env: the training env (batch ``[]`` or ``[N]``).
        policy: TensorDict module writing ``"action"``.
        frames_per_batch: frames per batch (a multiple of the env's batch numel).
        init_random_frames: frames of uniform random actions at the start.
    """

    def __init__(self, env: EnvBase, policy, frames_per_batch: int, init_random_frames: int = 0):
        n = max(1, env.batch_size.numel())
        if frames_per_batch < 1 or frames_per_batch % n:
            raise ValueError(f"collector.frames_per_batch={frames_per_batch} must be a positive multiple of the env's {n} cars")
        self.env, self.policy = env, policy
        self.steps_per_batch = frames_per_batch // n
        self.init_random_frames = int(init_random_frames)
        self.frames = 0
        self._act = getattr(policy, "act", policy)
        self._carrier = env.reset()
        keys = self._carrier.keys()
        self._track_init, self._track_return = "is_init" not in keys, "episode_reward" not in keys
        shape = (*env.batch_size, 1)
        if self._track_init:
            self._carrier.set("is_init", torch.ones(shape, dtype=torch.bool))
        if self._track_return:
            self._carrier.set("episode_reward", torch.zeros(shape))

    def __iter__(self):
        return self

    @torch.no_grad()
    def __next__(self) -> TensorDictBase:
        random = self.frames < self.init_random_frames
        out = []
        with set_exploration_type(ExplorationType.RANDOM):
            for _ in range(self.steps_per_batch):
                td = self._carrier
                if random:
                    self.env.rand_action(td)
                else:
                    self._act(td)
                step, carrier = self.env.step_and_maybe_reset(td)
                if self._track_init or self._track_return:
                    nxt = step.get("next")
                    done = nxt.get("done")
                    if self._track_init:
                        carrier.set("is_init", done.clone())
                    if self._track_return:
                        ret = td.get("episode_reward") + nxt.get("reward")
                        nxt.set("episode_reward", ret)
                        carrier.set("episode_reward", torch.where(done, 0.0, ret))
                self._carrier = carrier
                out.append(step)
        data = out[0] if len(out) == 1 else torch.stack(out, -1)
        self.frames += data.numel()
        return data

    def update_policy_weights_(self) -> None:
        """Nothing to do: the policy runs in this process."""

    def shutdown(self) -> None:
        """Nothing to do: the training loop closes the env."""

    def state_dict(self) -> dict:
        return {"frames": self.frames, "carrier": self._carrier.to_dict()}

    def load_state_dict(self, state: dict, carrier: bool = True) -> None:
        """Restore the frame count and (``carrier``) the in-flight tensordict — only meaningful together
        with the env's own simulation state."""
        self.frames = int(state["frames"])
        if carrier:
            self._carrier.update(TensorDict.from_dict(state["carrier"], batch_size=self.env.batch_size))
