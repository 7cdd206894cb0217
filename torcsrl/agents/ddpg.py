"""DDPG (Lillicrap et al. 2015): one critic, OU exploration (Andersson et al.'s TORCS setting), 400/300 nets.

The factories every agent has (``make_actor`` ... ``update``); DDPG writes only where it differs from its siblings:
one critic, no target policy smoothing, actor and targets updated every step. Defaults: ``conf/algo/ddpg.yaml``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.agents._build import make_actor, make_exploration, make_optimizers, make_target_updater  # noqa: F401
from torcsrl.objectives.td3 import DDPGLoss

NAME = "ddpg"


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """Q(s, a): one critic (``obs_keys``: what it sees, ``critic_obs_keys``)."""
    return _build.critic(cfg, env, obs_keys, num_nets=1, out_dim=1)


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """y = r + gamma (1 - terminated) Q'(s', mu'(s'))."""
    return DDPGLoss(actor, critic, loss_function=cfg.loss_function, **_build.loss_kwargs(cfg, env, obs_keys, critic_obs_keys))


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """Critic, actor and targets every step."""
    return _build.update(loss, optim, updater, batch, n_update, policy_delay=1, grad_clip=cfg.grad_clip,
                         precision=cfg.precision, reg=cfg, actor=actor)
