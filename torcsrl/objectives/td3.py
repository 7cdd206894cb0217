"""TD3 (Fujimoto et al. 2018) and DDPG (Lillicrap et al. 2015): what they add to the actor-critic base is the target.

TD3: ``y = r + gamma^n (1 - terminated) min_i Q'_i(s', clip(mu'(s') + clip(eps, -c, c), low, high))``,
``eps ~ N(0, policy_noise^2)`` (twin critics, target policy smoothing; the delayed actor update is the update's
``policy_delay``). DDPG: the same with one critic and no smoothing; its values equal TorchRL's ``DDPGLoss`` on the
same batch and weights (tested). Truncation (time limit) bootstraps; termination does not.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torcsrl.nets import Critic, DeterministicActor
from torcsrl.objectives.base import ActorCriticLoss


class TD3Loss(ActorCriticLoss):
    """Twin-delayed DDPG loss with a fused critic ensemble (:class:`~torcsrl.objectives.base.ActorCriticLoss`).

    Keyword Args:
        policy_noise: std of the target policy smoothing noise (sigma~), in action units.
        noise_clip: clip c of that noise.
        **kwargs: the base's (``obs_keys``, ``action_low``, ``action_high``, ``gamma``, ``loss_function``, ...).
    """

    out_keys = ["loss_actor", "loss_qvalue", "pred_value", "next_state_value", "target_value"]

    def __init__(self, actor_network: DeterministicActor, qvalue_network: Critic, *, policy_noise: float = 0.2,
                 noise_clip: float = 0.5, **kwargs) -> None:
        super().__init__(actor_network, qvalue_network, **kwargs)
        self.policy_noise, self.noise_clip = float(policy_noise), float(noise_clip)

    @torch.no_grad()
    def target(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Clipped double-Q target with target policy smoothing (see module docstring)."""
        next_action = self.target_actor(*self.obs(td, nxt=True))
        if self.policy_noise > 0:
            noise = torch.randn_like(next_action).mul_(self.policy_noise).clamp_(-self.noise_clip, self.noise_clip)
            next_action = torch.clamp(next_action.add_(noise), self.min_action, self.max_action)
        next_q = self.critic_value(self.target_qvalue(*self.critic_inputs(td, nxt=True), next_action))  # [E, B]
        next_q = torch.amin(next_q, 0) if next_q.shape[0] > 1 else next_q[0]
        return self.bootstrap(td, next_q), next_q


class DDPGLoss(TD3Loss):
    """DDPG: one critic, no target policy smoothing (equal to TorchRL's ``DDPGLoss`` with an l2 loss)."""

    def __init__(self, actor_network: DeterministicActor, qvalue_network: Critic, **kwargs) -> None:
        if qvalue_network.num_nets != 1:
            raise ValueError(f"DDPG has one critic; got an ensemble of {qvalue_network.num_nets}")
        kwargs.setdefault("policy_noise", 0.0)
        super().__init__(actor_network, qvalue_network, **kwargs)
