"""Agents: DDPG, TD3, D4PG, SAC and PPO with identical factories (``make_actor``, ``make_critic``, ``make_loss``,
``make_target_updater``, ``make_exploration``, ``make_optimizers``, ``update``) over the networks of
:mod:`torcsrl.nets`, and the imitation baselines BC and DAgger."""

from __future__ import annotations

import importlib
from types import ModuleType

ALGOS = ("ddpg", "td3", "d4pg", "sac", "ppo", "bc", "dagger")
#: Imitation baselines (no critic; trained by torcsrl.imitation.train from expert demonstrations).
IMITATION = ("bc", "dagger")
#: Actor-critic RL agents (identical factories: make_actor ... update).
RL_ALGOS = tuple(a for a in ALGOS if a not in IMITATION)
#: On-policy agents (no replay buffer; trained by torcsrl.onpolicy.train).
ON_POLICY = ("ppo",)
#: Off-policy agents (replay buffer, demonstrations; trained by torcsrl.train's loop).
OFF_POLICY = tuple(a for a in RL_ALGOS if a not in ON_POLICY)


def get(name: str) -> ModuleType:
    """The agent module called ``name`` (``ValueError`` listing the known ones otherwise)."""
    if name not in ALGOS:
        raise ValueError(f"unknown algorithm {name!r}; known: {', '.join(ALGOS)}")
    return importlib.import_module(f"torcsrl.agents.{name}")
