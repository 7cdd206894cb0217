"""TD3 (Fujimoto et al. 2018) and DDPG (Lillicrap et al. 2015) losses with a fused critic ensemble.

Shaped like TorchRL's ``TD3Loss`` (``_AcceptedKeys``, ``actor_loss``/``value_loss``, targets as
``target_*_params`` so TorchRL's ``SoftUpdate`` drives them), but built for speed on CPU:

* the twin critics are ONE :class:`~torcsrl.agents.networks.Critic` with stacked weights
  (one batched matmul per layer) instead of ``vmap`` over two parameter sets;
* the actor loss evaluates only Q1 with detached critic weights (TorchRL's TD3Loss runs every
  critic there and discards all but the first);
* the target networks are module copies bound to the target parameter tensors
  (:func:`~torcsrl.objectives.common.bind_target`), not parameters swapped in on every call;
* the networks are called on plain tensors, so no TensorDict is built per forward.

Measured on the project's 2-core CPU (``benchmarks/train_throughput.py``). DDPG is this loss
with one critic and no target policy smoothing (:class:`DDPGLoss`); its values equal TorchRL's
``DDPGLoss`` on the same batch and weights (tested).

Targets: ``y = r + gamma^n (1 - terminated) min_i Q'_i(s', clip(mu'(s') + clip(eps, -c, c)))``,
``eps ~ N(0, policy_noise^2)``. Truncation (time limit) bootstraps; termination does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives.common import LossModule

from torcsrl.agents.networks import Critic, DeterministicActor
from torcsrl.objectives.common import ObsUnpacker, bind_target, discount

_LOSSES = {
    "l2": lambda x, y: (x - y).pow(2),
    "smooth_l1": lambda x, y: nn.functional.smooth_l1_loss(x, y, reduction="none"),
    "l1": lambda x, y: (x - y).abs(),
}


class TD3Loss(LossModule):
    """Twin-delayed DDPG loss with a fused critic ensemble.

    Args:
        actor_network: the deterministic actor (``forward(*obs) -> action``).
        qvalue_network: the critic ensemble (``forward(*obs, action) -> [E, B, 1]``).

    Keyword Args:
        obs_keys: observation keys, in the order the networks take them.
        image_keys: the subset of ``obs_keys`` that are images (DrQ-augmented when ``augment_shift > 0``).
        action_low, action_high: action bounds (target actions are clipped into them).
        gamma: discount per env step [-].
        policy_noise: std of the target policy smoothing noise (sigma~), in action units.
        noise_clip: clip c of that noise.
        loss_function: ``"l2"`` | ``"smooth_l1"`` | ``"l1"``.
        augment_shift: DrQ random-shift pad [pixels] applied to image observations (0 = off).
        critic_obs_keys, critic_image_keys: what the critics see when it differs from the actor's input (asymmetric
            actor-critic, Pinto et al. 2017: privileged state for the critics, the camera for the actor); ``None`` =
            ``obs_keys`` (one unpacking per batch, shared).
        use_prioritized_weights: weight the critic loss by ``priority_weight`` when present ("auto").
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (``set_keys``).

        Attributes:
            action: the action taken.  reward / done / terminated: read under ``"next"``.
            priority: where the per-sample TD error is written for prioritized replay.
            priority_weight: importance-sampling weights from a prioritized buffer.
            gamma: per-sample discount ``gamma**n`` written by TorchRL's ``MultiStepTransform``.
        """

        action: NestedKey = "action"
        state_action_value: NestedKey = "state_action_value"
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        priority_weight: NestedKey = "priority_weight"
        steps_to_next_obs: NestedKey = "steps_to_next_obs"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_actor", "loss_qvalue", "pred_value", "next_state_value", "target_value"]

    actor_network: nn.Module
    qvalue_network: nn.Module
    actor_network_params: TensorDictParams
    qvalue_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: DeterministicActor,
        qvalue_network: Critic,
        *,
        obs_keys: list[str],
        image_keys: list[str] = (),
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        gamma: float = 0.99,
        policy_noise: float = 0.2,
        noise_clip: float = 0.5,
        loss_function: str = "l2",
        augment_shift: int = 0,
        critic_obs_keys: list[str] | None = None,
        critic_image_keys: list[str] = (),
        use_prioritized_weights: str | bool = "auto",
    ) -> None:
        super().__init__()
        if loss_function not in _LOSSES:
            raise ValueError(f"unknown loss_function {loss_function!r}; known: {', '.join(_LOSSES)}")
        self.use_prioritized_weights = use_prioritized_weights
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        self.convert_to_functional(qvalue_network, "qvalue_network", create_target_params=True)
        self.__dict__["target_actor"] = bind_target(actor_network, self._modules["target_actor_network_params"])
        self.__dict__["target_qvalue"] = bind_target(qvalue_network, self._modules["target_qvalue_network_params"])
        self.num_qvalue_nets = qvalue_network.num_nets
        self.gamma, self.policy_noise, self.noise_clip = float(gamma), float(policy_noise), float(noise_clip)
        self.loss_function = loss_function
        self._dist = _LOSSES[loss_function]
        self.register_buffer("min_action", torch.as_tensor(action_low, dtype=torch.float32).clone())
        self.register_buffer("max_action", torch.as_tensor(action_high, dtype=torch.float32).clone())
        self.obs = ObsUnpacker(obs_keys, list(image_keys), augment_shift)
        self.critic_obs = None if critic_obs_keys is None else ObsUnpacker(critic_obs_keys, list(critic_image_keys), augment_shift)
        self._in_keys = None

    # TorchRL bookkeeping -------------------------------------------------------------
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._in_keys = None

    @property
    def in_keys(self):
        keys = [
            self.tensor_keys.action,
            ("next", self.tensor_keys.reward),
            ("next", self.tensor_keys.done),
            ("next", self.tensor_keys.terminated),
            *self.obs.keys,
            *[("next", k) for k in self.obs.keys],
        ]
        if self.critic_obs is not None:
            keys += [*self.critic_obs.keys, *[("next", k) for k in self.critic_obs.keys]]
        return keys

    def _weights(self, td: TensorDictBase) -> torch.Tensor | None:
        w = self._maybe_get_priority_weight(td)
        return None if w is None else w.reshape(-1)

    @staticmethod
    def _reduce(x: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
        return x.mean() if w is None else (x * w).mean()

    # the two losses -------------------------------------------------------------------
    # ``actor_loss``/``value_loss`` are wrapped by TorchRL's LossModule metaclass (exploration and
    # recurrent-mode contexts, ~20 us a call); the training step calls the ``_``-prefixed bodies.
    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-Q1(s, mu(s))`` with the critic's weights detached: gradients reach the actor only."""
        loss, meta = self._actor_loss(tensordict)
        meta.pop("_action"), meta.pop("_q")
        return loss, meta

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """Sum over critics of the mean regression loss to the clipped double-Q target (and the per-sample TD error)."""
        return self._value_loss(tensordict, td_error=True)

    def _actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        obs = self.obs(tensordict)
        action = self.actor_network(*obs)
        cobs = obs if self.critic_obs is None else self.critic_obs(tensordict)
        q = self.qvalue_network.member(*cobs, action, index=0).squeeze(-1)
        loss = self._reduce(-q, self._weights(tensordict))
        # "_action", "_q": for the actor regularisers of torcsrl.agents._build.update (popped there, not logged)
        return loss, {"state_action_value_actor": q.detach().mean(), "_action": action, "_q": q.detach()}

    def _target(self, tensordict: TensorDictBase, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        nxt = tensordict.get("next")
        with torch.no_grad():
            next_obs = self.obs(tensordict, nxt=True)
            next_action = self.target_actor(*next_obs)
            if self.policy_noise > 0:
                noise = torch.randn_like(next_action).mul_(self.policy_noise).clamp_(-self.noise_clip, self.noise_clip)
                next_action = torch.clamp(next_action.add_(noise), self.min_action, self.max_action)
            if self.critic_obs is not None:
                next_obs = self.critic_obs(tensordict, nxt=True)
            next_q = self.target_qvalue(*next_obs, next_action).squeeze(-1)  # [E, B]
            next_q = torch.amin(next_q, 0) if next_q.shape[0] > 1 else next_q[0]
            reward = nxt.get(self.tensor_keys.reward).reshape(-1)
            term = nxt.get(self.tensor_keys.terminated).reshape(-1)
            g = discount(tensordict, self.gamma, self.tensor_keys.steps_to_next_obs)
            if torch.is_tensor(g):
                g = g.reshape(-1)
            target = torch.where(term, reward, reward + g * next_q)
        return target, next_q

    def _value_loss(self, tensordict: TensorDictBase, td_error: bool) -> tuple[torch.Tensor, dict]:
        """``td_error``: also return the per-sample TD error (the priority of prioritized replay)."""
        action = tensordict.get(self.tensor_keys.action)
        target, next_q = self._target(tensordict, action)
        q = self.qvalue_network(*(self.obs if self.critic_obs is None else self.critic_obs)(tensordict), action).squeeze(-1)  # [E, B]
        w = self._weights(tensordict)
        if w is None and self.loss_function == "l2":  # one fused kernel: sum_e mean_b (q - y)^2
            loss = nn.functional.mse_loss(q, target.expand_as(q)) * q.shape[0]
        else:
            loss = self._reduce(self._dist(q, target.expand_as(q)).sum(0), w)
        meta = {"pred_value": q.detach().mean(), "next_state_value": next_q.mean(), "target_value": target.mean()}
        if td_error:
            with torch.no_grad():
                meta["td_error"] = torch.amax((q - target).abs_(), 0)
        return loss, meta

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        loss_qvalue, meta_v = self.value_loss(tensordict)
        loss_actor, meta_a = self.actor_loss(tensordict)
        tensordict.set(self.tensor_keys.priority, meta_v.pop("td_error").unsqueeze(-1))
        return TensorDict(loss_actor=loss_actor, loss_qvalue=loss_qvalue, **meta_a, **meta_v)


class DDPGLoss(TD3Loss):
    """DDPG: one critic, no target policy smoothing (equal to TorchRL's ``DDPGLoss`` with an l2 loss)."""

    def __init__(self, actor_network: DeterministicActor, qvalue_network: Critic, **kwargs) -> None:
        if qvalue_network.num_nets != 1:
            raise ValueError(f"DDPG has one critic; got an ensemble of {qvalue_network.num_nets}")
        kwargs.setdefault("policy_noise", 0.0)
        super().__init__(actor_network, qvalue_network, **kwargs)
