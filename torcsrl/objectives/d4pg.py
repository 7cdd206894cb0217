"""D4PG-style distributional critic loss (Barth-Maron et al. 2018; TorchRL has none).

The critic outputs logits over ``num_atoms`` fixed returns ``z_j`` evenly spaced on
``[v_min, v_max]`` (C51, Bellemare et al. 2017). Target distribution: the target critic's
distribution at ``(s', mu'(s'))`` shifted by ``Tz = r + gamma^n (1 - terminated) z``, clamped to
``[v_min, v_max]`` and projected back onto the atoms (:func:`categorical_projection`). Critic
loss: cross-entropy between that projection and the predicted distribution. Actor loss:
``-E_z[Q(s, mu(s))]`` under the predicted distribution, critic weights detached.

N-step returns arrive in the batch as ``("next", "reward")`` summed over the window and
``steps_to_next_obs`` (the keys TorchRL's ``MultiStepTransform`` writes; the training loop's
:mod:`torcsrl.utils.replay` forms them at sampling, tested equal to that transform); the
per-sample cross-entropy is written as the priority for prioritized replay.

Shaped like TorchRL's ``TD3Loss``: ``_AcceptedKeys``, ``actor_loss``/``value_loss``, targets
in ``target_*_params`` driven by TorchRL's ``SoftUpdate``.
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


def categorical_projection(next_probs: torch.Tensor, reward: torch.Tensor, gamma: torch.Tensor | float, support: torch.Tensor,
                           bounds: tuple[float, float] | None = None) -> torch.Tensor:
    """C51 projection of the distribution ``next_probs`` on ``support``, shifted by ``r + gamma * z``.

    Args:
        next_probs: ``[B, K]`` probabilities of the returns ``support`` (rows sum to 1).
        reward: ``[B]`` rewards (n-step sums).
        gamma: ``[B]`` or scalar effective discount, already zero where the episode terminated.
        support: ``[K]`` atoms ``z_j``, evenly spaced, increasing.
        bounds: ``(z_0, z_{K-1})`` as Python floats, when the caller has them (no device sync).

    Returns:
        ``[B, K]`` probabilities: mass of ``Tz_j = clamp(r + gamma z_j, v_min, v_max)`` split between the
        two neighbouring atoms in proportion to closeness (all of it on one atom when ``Tz_j`` lands on it).
    """
    k = support.numel()
    v_min, v_max = bounds if bounds is not None else (float(support[0]), float(support[-1]))
    dz = (v_max - v_min) / (k - 1)
    g = gamma if torch.is_tensor(gamma) else torch.tensor(gamma, dtype=support.dtype)
    tz = torch.addcmul(reward.reshape(-1, 1), g.reshape(-1, 1), support.reshape(1, -1)).clamp_(v_min, v_max)
    b = tz.sub_(v_min).div_(dz).clamp_(0, k - 1)
    lo = b.floor()
    hi = b.ceil()
    w_hi = b.sub_(lo)  # 0 when b is integral: all mass goes to lo (== hi)
    p_hi = next_probs * w_hi
    out = torch.zeros_like(next_probs)
    out.scatter_add_(1, lo.long(), next_probs - p_hi)
    out.scatter_add_(1, hi.long(), p_hi)
    return out


class D4PGLoss(LossModule):
    """Distributional deterministic-policy-gradient loss with a categorical critic.

    Args:
        actor_network: the deterministic actor.
        qvalue_network: a one-member :class:`~torcsrl.agents.networks.Critic` with ``out_dim = num_atoms``.

    Keyword Args:
        obs_keys, image_keys, action_low, action_high, gamma, augment_shift, critic_obs_keys, critic_image_keys,
        use_prioritized_weights:
            as in :class:`~torcsrl.objectives.td3.TD3Loss`.
        v_min, v_max: support of the return distribution [return units].
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (see :class:`~torcsrl.objectives.td3.TD3Loss`)."""

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
    out_keys = ["loss_actor", "loss_qvalue", "pred_value", "target_value"]

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
        v_min: float,
        v_max: float,
        gamma: float = 0.99,
        augment_shift: int = 0,
        critic_obs_keys: list[str] | None = None,
        critic_image_keys: list[str] = (),
        use_prioritized_weights: str | bool = "auto",
    ) -> None:
        super().__init__()
        if qvalue_network.num_nets != 1 or qvalue_network.out_dim < 2:
            raise ValueError(f"D4PG needs one critic with >= 2 atoms; got {qvalue_network.num_nets} critics, {qvalue_network.out_dim} outputs")
        if not v_min < v_max:
            raise ValueError(f"v_min must be < v_max, got {v_min}, {v_max}")
        self.use_prioritized_weights = use_prioritized_weights
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        self.convert_to_functional(qvalue_network, "qvalue_network", create_target_params=True)
        self.__dict__["target_actor"] = bind_target(actor_network, self._modules["target_actor_network_params"])
        self.__dict__["target_qvalue"] = bind_target(qvalue_network, self._modules["target_qvalue_network_params"])
        self.gamma = float(gamma)
        self.register_buffer("support", torch.linspace(float(v_min), float(v_max), qvalue_network.out_dim))
        self._bounds = (float(v_min), float(v_max))
        self.register_buffer("min_action", torch.as_tensor(action_low, dtype=torch.float32).clone())
        self.register_buffer("max_action", torch.as_tensor(action_high, dtype=torch.float32).clone())
        self.obs = ObsUnpacker(obs_keys, list(image_keys), augment_shift)
        self.critic_obs = None if critic_obs_keys is None else ObsUnpacker(critic_obs_keys, list(critic_image_keys), augment_shift)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

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

    # ``actor_loss``/``value_loss`` are wrapped by TorchRL's LossModule metaclass (exploration and
    # recurrent-mode contexts, ~20 us a call); the training step calls the ``_``-prefixed bodies.
    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-sum_j p_j(s, mu(s)) z_j`` with the critic's weights detached."""
        loss, meta = self._actor_loss(tensordict)
        meta.pop("_action"), meta.pop("_q")
        return loss, meta

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """Cross-entropy between the projected target distribution and the predicted one."""
        return self._value_loss(tensordict, td_error=True)

    def _actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        obs = self.obs(tensordict)
        action = self.actor_network(*obs)
        cobs = obs if self.critic_obs is None else self.critic_obs(tensordict)
        logits = self.qvalue_network.member(*cobs, action, index=0)
        q = (torch.softmax(logits, -1) * self.support).sum(-1)
        w = self._weights(tensordict)
        loss = -q.mean() if w is None else -(q * w).mean()
        return loss, {"state_action_value_actor": q.detach().mean(), "_action": action, "_q": q.detach()}

    def _value_loss(self, tensordict: TensorDictBase, td_error: bool) -> tuple[torch.Tensor, dict]:
        """``td_error``: also return the per-sample cross-entropy (the priority of prioritized replay)."""
        nxt = tensordict.get("next")
        with torch.no_grad():
            next_obs = self.obs(tensordict, nxt=True)
            next_action = self.target_actor(*next_obs)
            if self.critic_obs is not None:
                next_obs = self.critic_obs(tensordict, nxt=True)
            next_probs = torch.softmax(self.target_qvalue(*next_obs, next_action)[0], -1)
            reward = nxt.get(self.tensor_keys.reward).reshape(-1)
            term = nxt.get(self.tensor_keys.terminated).reshape(-1)
            g = discount(tensordict, self.gamma, self.tensor_keys.steps_to_next_obs)
            g = (g.reshape(-1) if torch.is_tensor(g) else torch.full_like(reward, g)) * (~term)
            target = categorical_projection(next_probs, reward, g, self.support, self._bounds)
        cobs = (self.obs if self.critic_obs is None else self.critic_obs)(tensordict)
        logits = self.qvalue_network(*cobs, tensordict.get(self.tensor_keys.action))[0]
        logp = torch.log_softmax(logits, -1)
        ce = -(target * logp).sum(-1)
        w = self._weights(tensordict)
        loss = ce.mean() if w is None else (ce * w).mean()
        with torch.no_grad():
            pred = (logp.exp() * self.support).sum(-1)
            tv = (target * self.support).sum(-1)
        meta = {"pred_value": pred.mean(), "target_value": tv.mean()}
        if td_error:
            meta["td_error"] = ce.detach()
        return loss, meta

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        loss_qvalue, meta_v = self.value_loss(tensordict)
        loss_actor, meta_a = self.actor_loss(tensordict)
        tensordict.set(self.tensor_keys.priority, meta_v.pop("td_error").unsqueeze(-1))
        return TensorDict(loss_actor=loss_actor, loss_qvalue=loss_qvalue, **meta_a, **meta_v)
