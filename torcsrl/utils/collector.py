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

Multi-process collection stays with TorchRL's ``MultiSyncCollector`` / ``MultiAsyncCollector``; their workers run
:class:`LeanCollector` (``collector_class=LeanCollector``): TorchRL's ``Collector`` (its construction, weight sync,
shared output buffer and worker protocol) with this module's step loop in ``rollout``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
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


class LeanCollector(Collector):
    """TorchRL's ``Collector`` for the workers of ``MultiSyncCollector`` / ``MultiAsyncCollector``
    (``collector_class=LeanCollector``), its per-step loop replaced by :class:`StepCollector`'s.

    Everything around the loop is TorchRL's: the policy built in the worker and its weight sync, the output
    buffer in shared memory, random frames, trajectory ids, truncation of the last step, the worker protocol.
    The loop keeps what a batch of rollouts needs — policy (``ExplorationType`` of the collector),
    ``env.step_and_maybe_reset``, the carrier, new trajectory ids where an episode ended — and gives the same
    batches as ``Collector`` (tested key by key). Where it would need more (device casts between policy and env,
    a replay buffer written by the worker, resets at every batch, a compiled or interruptible policy, hooks,
    compacted observations) ``Collector.rollout`` runs instead. Measured in ``benchmarks/ppo_paths.py``.
    """

    def rollout(self) -> TensorDictBase:
        if (self._cast_to_policy_device or self._cast_to_env_device or self.replay_buffer is not None or self.reset_at_each_iter
                or self.compiled_policy or self.cudagraphed_policy or self.interruptor is not None or self.pre_collect_hook is not None
                or self._compact_next_keys):
            return super().rollout()
        env, policy, keys = self.env, self._wrapped_policy, self._policy_output_keys
        track = self.track_traj_ids
        ids = self._carrier.get(("collector", "traj_ids")) if track else None
        if track and self._use_buffers:
            self._final_rollout.fill_(("collector", "traj_ids"), -1)
        steps = []
        with set_exploration_type(self.exploration_type):
            for _ in range(self.frames_per_batch):
                td = self._carrier
                if self._should_use_random_frames():
                    env.rand_action(td)
                else:
                    out = policy(td)
                    if out is not td:
                        td.update(out, keys_to_update=keys)
                step, carrier = env.step_and_maybe_reset(td)
                if self._carrier_has_no_device:
                    carrier.clear_device_()
                if track:  # a car whose episode ended drives a new trajectory from the next step (Collector._update_traj_ids)
                    done = step.get(("next", "done")).reshape(ids.shape)
                    if done.any():
                        ids = ids.masked_scatter(done, self._traj_pool.get_traj_and_increment(done.sum(), device=done.device))
                    carrier.set(("collector", "traj_ids"), ids)
                self._carrier = carrier
                steps.append(step)
        if self._use_buffers:
            result = torch.stack(steps, self._final_rollout.ndim - 1, out=self._final_rollout)
        else:
            result = TensorDict.maybe_dense_stack(steps, dim=-1)
            result.refine_names(..., "time")
        return self._maybe_set_truncated(result)


#: ``collector.worker_loop`` -> the collector class of the worker processes.
WORKER_LOOPS = {"lean": LeanCollector, "torchrl": Collector}


def worker_collector_class(cfg) -> type:
    """The worker processes' collector class named by ``cfg.collector.worker_loop`` (default ``lean``)."""
    name = cfg.collector.get("worker_loop", "lean")
    if name not in WORKER_LOOPS:
        raise ValueError(f"collector.worker_loop={name!r}: unknown worker collector; allowed: {', '.join(WORKER_LOOPS)}")
    return WORKER_LOOPS[name]
