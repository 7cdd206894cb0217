"""Behaviour cloning and DAgger (``algo=bc`` / ``algo=dagger``): pure imitation of the scripted expert.

The imitation baselines beside the RL agents: the same deterministic actor (so evaluation, the
report and export treat a BC driver exactly like a TD3 one), fitted by regression
``|mu(s) - a*|^2`` to the expert's labels ``a*`` of the demonstrations (:mod:`torcsrl.demos`).
DAgger (Ross et al. 2011) adds rounds in which the learner drives, the expert labels the states it
reaches, and the actor is refitted on everything. The loop is :func:`torcsrl.imitation.train`.
Defaults: ``conf/algo/bc.yaml``, ``conf/algo/dagger.yaml``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from torcsrl.agents import _build
from torcsrl.agents._build import PRECISIONS, bc_step  # noqa: F401 -- public: imitation, TD3+BC pre-training, config check

NAME = "bc"


def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """mu(s) -> action in the env's bounds (the RL agents' actor)."""
    return _build.actor(cfg, env, obs_keys)


def make_optimizers(cfg: Any, actor) -> dict:
    """One Adam for the actor."""
    return {"actor": (_build.FusedAdam if cfg.fused_adam else __import__("torch").optim.Adam)(
        list(actor.parameters()), lr=float(cfg.actor_lr), weight_decay=float(cfg.weight_decay))}
