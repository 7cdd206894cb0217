"""D4PG-style agent (Barth-Maron et al. 2018): categorical critic, N-step returns, many actors.

The factories every agent has (``make_actor`` ... ``update``); D4PG writes only where it differs from its siblings:
one critic with ``num_atoms`` logits on ``[v_min, v_max]`` and the distributional loss (``torcsrl.objectives.d4pg``).
N-step returns (``n_steps``), prioritized replay and many actors (``collector.num_workers``) are set up by the
training loop from the config. Defaults: ``conf/algo/d4pg.yaml``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.agents._build import make_actor, make_exploration, make_optimizers, make_target_updater  # noqa: F401
from torcsrl.objectives.d4pg import D4PGLoss

NAME = "d4pg"


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """Z(s, a): logits over ``num_atoms`` returns (``obs_keys``: what it sees, ``critic_obs_keys``)."""
    return _build.critic(cfg, env, obs_keys, num_nets=1, out_dim=int(cfg.num_atoms))


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """Cross-entropy to the C51-projected target distribution; actor ascends the expected return."""
    v_min, v_max = _build.value_support(cfg)
    return D4PGLoss(actor, critic, v_min=v_min, v_max=v_max, **_build.loss_kwargs(cfg, env, obs_keys, critic_obs_keys))


def update(cfg: Any, loss, optim, updater, batch, n_update: int, actor: bool = True) -> dict:
    """Critic, actor and targets every step."""
    return _build.update(loss, optim, updater, batch, n_update, policy_delay=1, grad_clip=cfg.grad_clip,
                         precision=cfg.precision, reg=cfg, actor=actor)
