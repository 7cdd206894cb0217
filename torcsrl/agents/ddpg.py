"""DDPG (Lillicrap et al. 2015): one critic, OU exploration (Andersson et al.'s TORCS setting), 400/300 nets.

Same factories, in the same order, as ``td3.py`` and ``d4pg.py``; the differences are the
algorithm's: one critic (``num_nets=1``), no target policy smoothing, actor and targets
updated every step. Defaults: ``conf/algo/ddpg.yaml``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.objectives.td3 import DDPGLoss

NAME = "ddpg"


def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """mu(s) -> action in the env's bounds."""
    return _build.actor(cfg, env, obs_keys)


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """Q(s, a): one critic (``obs_keys``: what it sees, ``critic_obs_keys``)."""
    return _build.critic(cfg, env, obs_keys, num_nets=1, out_dim=1)


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """DDPG loss: y = r + gamma (1 - terminated) Q'(s', mu'(s'))."""
    return DDPGLoss(actor, critic, loss_function=cfg.loss_function, **_build.loss_kwargs(cfg, env, obs_keys, critic_obs_keys))


def make_target_updater(cfg: Any, loss):
    return _build.target_updater(cfg, loss)


def make_exploration(cfg: Any, actor, env: EnvBase, obs_keys: list[str]):
    return _build.exploration(cfg, actor, env, obs_keys)


def make_optimizers(cfg: Any, loss):
    return _build.optimizers(cfg, loss)


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """Critic, actor and targets every step."""
    return _build.update(loss, optim, updater, batch, n_update, policy_delay=1, grad_clip=cfg.grad_clip,
                         precision=cfg.precision, reg=cfg, actor=actor)
