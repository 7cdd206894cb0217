"""PPO (Schulman et al. 2017): TorchRL's ``ClipPPOLoss`` with GAE, a tanh-Gaussian policy and observation normalisation.

The factories every agent has (``make_actor`` ... ``update``), for an on-policy learner: the actor is the
tanh-Gaussian :class:`~torcsrl.nets.TanhGaussianActor` with one learnt std per action dimension (SB3's and TorchRL's
PPO), behind TorchRL's ``ProbabilisticActor`` and ``TanhNormal``; the critic is a state-value network
:class:`~torcsrl.nets.ValueNet`; both standardise their vector observations by running statistics (``obs_norm``,
:class:`~torcsrl.nets.RunningNorm`, saved with the networks so evaluation feeds the policy what it learnt on). There
are no target networks (``make_target_updater`` returns None) and no exploration noise (the policy samples itself).
``update`` is one minibatch step of the clipped surrogate + value + entropy losses; the loop that collects rollouts
of the batched env and runs epochs of minibatches is :func:`torcsrl.onpolicy.train`. Defaults: ``conf/algo/ppo.yaml``.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from torcsrl.agents import _build
from torcsrl.nets import TanhGaussianActor, ValueNet

NAME = "ppo"


class _DistParams(nn.Module):
    """The actor's (loc, std) of the pre-tanh Gaussian, for TorchRL's ``TanhNormal``."""

    def __init__(self, actor: TanhGaussianActor):
        super().__init__()
        self.actor = actor

    def forward(self, *obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.actor.dist(*obs)


def _policy(actor: TanhGaussianActor, env: EnvBase, obs_keys: list[str]) -> ProbabilisticActor:
    """``actor`` as TorchRL's ``ProbabilisticActor``: samples (with its log-probability) while exploring, its mean
    action ``tanh(loc)`` under DETERMINISTIC exploration."""
    low, high = _build.action_bounds(env)
    low, high = low.to(actor.a_mid.device), high.to(actor.a_mid.device)
    params = TensorDictModule(_DistParams(actor), in_keys=list(obs_keys), out_keys=["loc", "scale"])
    return ProbabilisticActor(params, in_keys=["loc", "scale"], distribution_class=TanhNormal,
                              distribution_kwargs={"low": low, "high": high}, return_log_prob=True)


def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """pi(a|s): tanh-Gaussian in the env's bounds, one learnt std per action dimension; ``actor(*obs)`` is its mean action."""
    low, high = _build.action_bounds(env)
    return TanhGaussianActor(_build.encoder(cfg, env, obs_keys, obs_norm=bool(cfg.obs_norm)), low, high, tuple(cfg.actor_hidden),
                             state_dependent_std=False, log_std_init=float(cfg.log_std_init))


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """V(s): the state value (its own encoder and observation statistics)."""
    return ValueNet(_build.encoder(cfg, env, obs_keys, obs_norm=bool(cfg.obs_norm)), tuple(cfg.critic_hidden))


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """TorchRL's ``ClipPPOLoss`` (clipped surrogate, l2 value loss, entropy bonus, advantages normalised per minibatch)
    with TorchRL's ``GAE(gamma, gae_lambda)`` as its value estimator."""
    if critic_obs_keys is not None:
        raise ValueError("algo=ppo: the value network sees the actor's observations; allowed: critic_obs_keys=null")
    value = ValueOperator(critic, in_keys=list(obs_keys))
    loss = ClipPPOLoss(_policy(actor, env, obs_keys), value, clip_epsilon=float(cfg.clip_epsilon), entropy_coeff=float(cfg.entropy_coef),
                       critic_coeff=float(cfg.value_coef), loss_critic_type="l2", normalize_advantage=True)
    loss.make_value_estimator(ValueEstimators.GAE, gamma=float(cfg.gamma), lmbda=float(cfg.gae_lambda))
    return loss


def make_target_updater(cfg: Any, loss):
    """None: PPO has no target networks."""
    return None


def make_exploration(cfg: Any, actor, env: EnvBase, obs_keys: list[str]):
    """The policy itself: a sample and its log-probability while exploring (``algo.exploration`` must be ``none``)."""
    return _policy(actor, env, obs_keys)


def make_optimizers(cfg: Any, loss):
    """One Adam for the actor (``actor_lr``), one for the value network (``critic_lr``)."""
    adam = _build.FusedAdam if cfg.fused_adam else torch.optim.Adam
    kw = dict(weight_decay=float(cfg.weight_decay))
    return {"actor": adam(list(loss.actor_network.parameters()), lr=float(cfg.actor_lr), **kw),
            "critic": adam(list(loss.critic_network.parameters()), lr=float(cfg.critic_lr), **kw)}


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """One minibatch step on ``batch`` (advantages and value targets already there: :func:`torcsrl.onpolicy.train`):
    clipped surrogate + ``value_coef`` x value loss + ``entropy_coef`` x entropy bonus, gradients clipped to
    ``grad_clip``; ``actor=False``: the value network only."""
    with _build.precision_context(cfg.precision, batch.device or "cpu"):
        td = loss(batch)
    total = td["loss_critic"] + (td["loss_objective"] + td["loss_entropy"] if actor else 0.0)
    opts = [optim["actor"], optim["critic"]] if actor else [optim["critic"]]
    for o in opts:
        o.zero_grad(set_to_none=True)
    total.backward()
    if cfg.grad_clip:  # one norm over everything stepped (SB3's max_grad_norm)
        torch.nn.utils.clip_grad_norm_([p for o in opts for p in o.param_groups[0]["params"]], cfg.grad_clip)
    for o in opts:
        _build._step(o)
    return {"loss/objective": td["loss_objective"].detach(), "loss/critic": td["loss_critic"].detach(),
            "loss/entropy": td["entropy"].detach(), "loss/kl_approx": td["kl_approx"].detach(),
            "loss/clip_fraction": td["clip_fraction"].detach()}
