"""Agents: DDPG, TD3 and D4PG with identical factories (``make_actor``, ``make_critic``, ``make_loss``,
``make_target_updater``, ``make_exploration``, ``make_optimizers``, ``update``) over shared networks."""

from __future__ import annotations

import importlib
from types import ModuleType

ALGOS = ("ddpg", "td3", "d4pg", "bc", "dagger")
#: Imitation baselines (no critic; trained by torcsrl.imitation.train from expert demonstrations).
IMITATION = ("bc", "dagger")
#: Actor-critic RL agents (identical factories: make_actor ... update).
RL_ALGOS = tuple(a for a in ALGOS if a not in IMITATION)


def get(name: str) -> ModuleType:
    """The agent module called ``name`` (``ValueError`` listing the known ones otherwise)."""
    if name not in ALGOS:
        raise ValueError(f"unknown algorithm {name!r}; known: {', '.join(ALGOS)}")
    return importlib.import_module(f"torcsrl.agents.{name}")
