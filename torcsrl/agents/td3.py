"""TD3 (Fujimoto et al. 2018): twin critics, delayed actor/target updates, target policy smoothing.

Same factories, in the same order, as ``ddpg.py`` and ``d4pg.py``; the differences are the
algorithm's: two critics fused into one ensemble network (``num_nets=2``), target policy
smoothing (``policy_noise`` sigma~, ``noise_clip`` c), actor and targets updated every
``policy_delay`` critic steps. Defaults: ``conf/algo/td3.yaml``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.objectives.td3 import TD3Loss

NAME = "td3"


def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """mu(s) -> action in the env's bounds."""
    return _build.actor(cfg, env, obs_keys)


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """Q1, Q2 (s, a): twin critics as one fused ensemble (``obs_keys``: what the critics see, ``critic_obs_keys``)."""
    return _build.critic(cfg, env, obs_keys, num_nets=2, out_dim=1)


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """TD3 loss: y = r + gamma (1 - terminated) min_i Q'_i(s', clip(mu'(s') + clip(eps, -c, c)))."""
    return TD3Loss(actor, critic, loss_function=cfg.loss_function, policy_noise=float(cfg.policy_noise),
                   noise_clip=float(cfg.noise_clip), **_build.loss_kwargs(cfg, env, obs_keys, critic_obs_keys))


def make_target_updater(cfg: Any, loss):
    return _build.target_updater(cfg, loss)


def make_exploration(cfg: Any, actor, env: EnvBase, obs_keys: list[str]):
    return _build.exploration(cfg, actor, env, obs_keys)


def make_optimizers(cfg: Any, loss):
    return _build.optimizers(cfg, loss)


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """Critic every step; actor and targets every ``policy_delay`` steps."""
    return _build.update(loss, optim, updater, batch, n_update, policy_delay=int(cfg.policy_delay), grad_clip=cfg.grad_clip,
                         precision=cfg.precision, reg=cfg, actor=actor)
