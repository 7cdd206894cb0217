"""SAC (Haarnoja et al. 2018): tanh-Gaussian actor, twin critics, automatic entropy tuning.

The factories every agent has (``make_actor`` ... ``update``); SAC writes only where it differs from its siblings:
a stochastic actor (and its own exploration: it acts by sampling itself, so ``algo.exploration`` must be ``none``;
evaluation drives its mean action), the entropy-regularised loss (``torcsrl.objectives.sac``) over two fused critics,
and a third optimiser for the temperature. Targets, demonstrations, the CAPS smoothness terms and the update's
schedule are the siblings'. Defaults: ``conf/algo/sac.yaml``.
"""

from __future__ import annotations

from typing import Any

import torch
from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.agents._build import make_target_updater  # noqa: F401
from torcsrl.agents.exploration import BehaviourPolicy, PolicySample, StochasticBrake
from torcsrl.nets import TanhGaussianActor
from torcsrl.objectives.sac import SACLoss

NAME = "sac"


def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """pi(a|s): tanh-Gaussian in the env's bounds, state-dependent std; ``actor(*obs)`` is its mean action."""
    low, high = _build.action_bounds(env)
    return TanhGaussianActor(_build.encoder(cfg, env, obs_keys), low, high, tuple(cfg.actor_hidden), state_dependent_std=True)


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """Q1, Q2 (s, a): twin critics as one fused ensemble (``obs_keys``: what the critics see, ``critic_obs_keys``)."""
    return _build.critic(cfg, env, obs_keys, num_nets=2, out_dim=1)


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """y = r + gamma (1 - terminated) (min_i Q'_i(s', a') - alpha log pi(a'|s')), a' ~ pi(.|s'); alpha tuned to
    ``target_entropy``."""
    return SACLoss(actor, critic, loss_function=cfg.loss_function, target_entropy=cfg.target_entropy, alpha_init=float(cfg.alpha_init),
                   **_build.loss_kwargs(cfg, env, obs_keys, critic_obs_keys))


def make_exploration(cfg: Any, actor, env: EnvBase, obs_keys: list[str]):
    """Draws from the policy (its mean under DETERMINISTIC exploration) -> stochastic brake."""
    mods = [PolicySample(actor, obs_keys)]  # observations go to the actor's device, actions come back to the CPU
    b = cfg.stochastic_brake
    if b.enabled:
        mods.append(StochasticBrake(prob=float(b.prob), mu=float(b.mu), sigma=float(b.sigma)))
    return BehaviourPolicy(*mods)


def make_optimizers(cfg: Any, loss):
    """One Adam per network, and one for the temperature log alpha (``alpha_lr``)."""
    adam = _build.FusedAdam if cfg.fused_adam else torch.optim.Adam
    return {**_build.optimizers(cfg, loss), "alpha": adam([loss.log_alpha], lr=float(cfg.alpha_lr))}


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """Critic every step; actor, temperature and targets every ``policy_delay`` steps."""
    return _build.update(loss, optim, updater, batch, n_update, policy_delay=int(cfg.policy_delay), grad_clip=cfg.grad_clip,
                         precision=cfg.precision, reg=cfg, actor=actor)
