"""TD3 (Fujimoto et al. 2018): twin critics, delayed actor/target updates, target policy smoothing.

The factories every agent has (``make_actor`` ... ``update``); TD3 writes only where it differs from its siblings:
two critics fused into one ensemble network, target policy smoothing (``policy_noise`` sigma~, ``noise_clip`` c),
actor and targets updated every ``policy_delay`` critic steps. Defaults: ``conf/algo/td3.yaml``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.agents._build import make_actor, make_exploration, make_optimizers, make_target_updater  # noqa: F401
from torcsrl.objectives.td3 import TD3Loss

NAME = "td3"


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """Q1, Q2 (s, a): twin critics as one fused ensemble (``obs_keys``: what the critics see, ``critic_obs_keys``)."""
    return _build.critic(cfg, env, obs_keys, num_nets=2, out_dim=1)


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """y = r + gamma (1 - terminated) min_i Q'_i(s', clip(mu'(s') + clip(eps, -c, c)))."""
    return TD3Loss(actor, critic, loss_function=cfg.loss_function, policy_noise=float(cfg.policy_noise),
                   noise_clip=float(cfg.noise_clip), **_build.loss_kwargs(cfg, env, obs_keys, critic_obs_keys))


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """Critic every step; actor and targets every ``policy_delay`` steps."""
    return _build.update(loss, optim, updater, batch, n_update, policy_delay=int(cfg.policy_delay), grad_clip=cfg.grad_clip,
                         precision=cfg.precision, reg=cfg, actor=actor)
