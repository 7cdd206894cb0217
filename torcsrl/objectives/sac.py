"""SAC (Haarnoja et al. 2018, the version with automatic entropy tuning and no value network) on the actor-critic base.

What SAC changes in the base (:class:`~torcsrl.objectives.base.ActorCriticLoss`), as TorchRL's ``SACLoss`` (v2)
computes it:

* the actor is the tanh-Gaussian :class:`~torcsrl.nets.TanhGaussianActor`, without a target copy;
* the target acts with the ONLINE policy and adds the entropy bonus:
  ``y = r + gamma^n (1 - terminated) (min_i Q'_i(s', a') - alpha log pi(a'|s'))``, ``a' ~ pi(.|s')``;
* the actor loss is ``alpha log pi(a|s) - min_i Q_i(s, a)``, ``a ~ pi(.|s)`` reparameterised, the critics' weights
  detached and alpha a constant there;
* the temperature loss ``-log alpha (log pi(a|s) + H_target)`` tunes alpha so the policy's entropy tracks
  ``target_entropy`` (``"auto"``: minus the action size, as TorchRL and SB3 use).

The critic regression is the base's (TD3's), on the fused twin critics. ``actor_loss`` returns the policy's mean
action as ``"_action"`` (the demonstrations' BC term and the CAPS smoothness terms act on what evaluation drives)
and the sample's log-density as ``"_log_prob"`` (for :meth:`SACLoss.alpha_loss`).
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torch import nn

from torcsrl.nets import Critic, TanhGaussianActor
from torcsrl.objectives.base import ActorCriticLoss


class SACLoss(ActorCriticLoss):
    """Soft actor-critic loss with twin fused critics and a learnt temperature.

    Keyword Args:
        target_entropy: ``"auto"`` (minus the action size) or the entropy the temperature aims at [nats].
        alpha_init: the temperature alpha at the start [-].
        **kwargs: the base's (``obs_keys``, ``action_low``, ``action_high``, ``gamma``, ``loss_function``, ...).
    """

    out_keys = ["loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy", "pred_value", "next_state_value", "target_value"]
    delay_actor = False

    def __init__(self, actor_network: TanhGaussianActor, qvalue_network: Critic, *, target_entropy: str | float = "auto",
                 alpha_init: float = 1.0, **kwargs) -> None:
        if not hasattr(actor_network, "sample"):
            raise ValueError(f"SAC needs a stochastic actor (TanhGaussianActor); got {type(actor_network).__name__}")
        super().__init__(actor_network, qvalue_network, **kwargs)
        n = int(self.min_action.numel())
        self.target_entropy = -float(n) if target_entropy == "auto" else float(target_entropy)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(float(alpha_init))))

    @property
    def alpha(self) -> torch.Tensor:
        """The temperature ``exp(log alpha)``, detached."""
        return self.log_alpha.detach().exp()

    @torch.no_grad()
    def target(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Soft clipped double-Q target with the online policy's next action (see module docstring)."""
        next_action, next_logp, _ = self.actor_network.sample(*self.obs(td, nxt=True))
        next_q = self.critic_value(self.target_qvalue(*self.critic_inputs(td, nxt=True), next_action))  # [E, B]
        next_v = torch.amin(next_q, 0) - self.alpha * next_logp
        return self.bootstrap(td, next_v), next_v

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``alpha log pi(a|s) - min_i Q_i(s, a)`` with the critics' weights detached: gradients reach the actor only."""
        obs = self.obs(tensordict)
        action, logp, mean_action = self.actor_network.sample(*obs)
        q = torch.amin(self.critic_value(self.qvalue_network.detached(*self.critic_inputs(tensordict, obs), action)), 0)
        alpha = self.alpha
        loss = self._reduce(alpha * logp - q, self._weights(tensordict))
        return loss, {"state_action_value_actor": q.detach().mean(), "entropy": -logp.detach().mean(), "alpha": alpha,
                      "_action": mean_action, "_q": q.detach(), "_log_prob": logp.detach()}

    def alpha_loss(self, log_prob: torch.Tensor) -> torch.Tensor:
        """``-mean(log alpha (log pi + H_target))``: gradients reach ``log_alpha`` only."""
        return -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()

    def _more_losses(self, meta_actor: dict) -> dict[str, torch.Tensor]:
        return {"loss_alpha": self.alpha_loss(meta_actor["_log_prob"])}
