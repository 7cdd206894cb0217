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

On the actor-critic base (:class:`~torcsrl.objectives.base.ActorCriticLoss`, whose deterministic actor loss it
keeps), D4PG overrides the value of a critic output (the expectation over the atoms), the target (a distribution)
and the value loss (cross-entropy).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torcsrl.nets import Critic, DeterministicActor
from torcsrl.objectives.base import ActorCriticLoss


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


class D4PGLoss(ActorCriticLoss):
    """Distributional deterministic-policy-gradient loss with a categorical critic.

    Args:
        actor_network: the deterministic actor.
        qvalue_network: a one-member :class:`~torcsrl.nets.Critic` with ``out_dim = num_atoms``.

    Keyword Args:
        v_min, v_max: support of the return distribution [return units].
        **kwargs: the base's (``obs_keys``, ``action_low``, ``action_high``, ``gamma``, ...).
    """

    def __init__(self, actor_network: DeterministicActor, qvalue_network: Critic, *, v_min: float, v_max: float, **kwargs) -> None:
        if qvalue_network.num_nets != 1 or qvalue_network.out_dim < 2:
            raise ValueError(f"D4PG needs one critic with >= 2 atoms; got {qvalue_network.num_nets} critics, {qvalue_network.out_dim} outputs")
        if not v_min < v_max:
            raise ValueError(f"v_min must be < v_max, got {v_min}, {v_max}")
        super().__init__(actor_network, qvalue_network, **kwargs)
        self.register_buffer("support", torch.linspace(float(v_min), float(v_max), qvalue_network.out_dim))
        self._bounds = (float(v_min), float(v_max))

    def critic_value(self, out: torch.Tensor) -> torch.Tensor:
        """``sum_j p_j z_j``: the expected return of the logits ``out``."""
        return (torch.softmax(out, -1) * self.support).sum(-1)

    @torch.no_grad()
    def target(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """(the C51-projected target distribution ``[B, K]``, its next-state probabilities ``[B, K]``)."""
        next_action = self.target_actor(*self.obs(td, nxt=True))
        next_probs = torch.softmax(self.target_qvalue(*self.critic_inputs(td, nxt=True), next_action)[0], -1)
        reward, term, g = self.reward_discount(td)
        g = (g if torch.is_tensor(g) else torch.full_like(reward, g)) * (~term)
        return categorical_projection(next_probs, reward, g, self.support, self._bounds), next_probs

    def value_loss(self, tensordict: TensorDictBase, td_error: bool = False) -> tuple[torch.Tensor, dict]:
        """Cross-entropy between the projected target distribution and the predicted one; ``td_error``: also the
        per-sample cross-entropy (the priority of prioritized replay)."""
        target, _ = self.target(tensordict)
        logits = self.qvalue_network(*self.critic_inputs(tensordict), tensordict.get(self.tensor_keys.action))[0]
        logp = torch.log_softmax(logits, -1)
        ce = -(target * logp).sum(-1)
        loss = self._reduce(ce, self._weights(tensordict))
        with torch.no_grad():
            pred = (logp.exp() * self.support).sum(-1)
            tv = (target * self.support).sum(-1)
        meta = {"pred_value": pred.mean(), "target_value": tv.mean()}
        if td_error:
            meta["td_error"] = ce.detach()
        return loss, meta
