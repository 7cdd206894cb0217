"""Training: :func:`train` checks a composed training config, holds its run folder and runs the loop of its algorithm.

Loops (each reads in the order its algorithm runs: ``make_*`` calls, then collect -> extend -> update -> log ->
validate -> checkpoint): :mod:`~torcsrl.training.offpolicy` (DDPG, TD3, D4PG, SAC), :mod:`~torcsrl.training.onpolicy`
(PPO), :mod:`~torcsrl.training.imitation` (BC, DAgger); what they share is :mod:`~torcsrl.training.common`'s;
demonstrations and curricula are :mod:`~torcsrl.training.demos` and :mod:`~torcsrl.training.curriculum`.

:func:`problems` / :func:`validate` are the whole config check, gathered from the subsystems that own each part:
:func:`torcsrl.training.checks.check` (the config's own sections), :func:`torcsrl.pipeline.check` (env, degradations,
histories, critic keys), :func:`torcsrl.training.demos.check` and :func:`torcsrl.training.curriculum.check` (which
checks every stage's config with :func:`problems` again); :mod:`torcsrl.config` gives them to the entry points.

``python -m torcsrl.train`` is the Hydra entry (:mod:`torcsrl.train`); tests call :func:`train` on a config composed
with Hydra's ``compose`` API.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, open_dict

from torcsrl import agents, pipeline
from torcsrl.training import checks, curriculum, demos, imitation, offpolicy, onpolicy
from torcsrl.training.checks import ConfigError
from torcsrl.training.common import resolve_run_dir
from torcsrl.utils.faults import claim_run_dir

__all__ = ["ConfigError", "problems", "validate", "train"]


def problems(cfg: DictConfig | Mapping) -> list[str]:
    """Every problem of the training config ``cfg`` as ``"<key>: <message>"`` lines (empty when it is sound)."""
    c, out = checks.resolve(cfg)
    if c is None:
        return out
    out = checks.check(c) + pipeline.check(c) + demos.check(c)
    if c.get("curriculum") is not None:  # its stages, and every stage's config checked like this one
        out += curriculum.check(cfg, list(out), problems)
    return out


def validate(cfg: DictConfig | Mapping) -> None:
    """Raise :class:`ConfigError` listing every problem of ``cfg`` (:func:`problems`); None if it is sound."""
    checks.raise_problems(problems(cfg))


def train(cfg: DictConfig) -> dict[str, Any]:
    """Train ``cfg.algo`` on ``cfg.env``; returns the final metrics (and where things were written).

    The config is checked first (:func:`validate`: unknown keys, wrong types, unknown names, severities): a
    ``ConfigError`` naming every problem, before anything is built. The run folder is then held for this run alone
    (:func:`torcsrl.utils.faults.claim_run_dir`: a lock, and a folder holding another run is refused unless
    ``checkpoint.resume`` or ``overwrite=true``), and the algorithm's loop runs in it: BC / DAgger
    (:mod:`~torcsrl.training.imitation`: no critic, no collector), PPO (:mod:`~torcsrl.training.onpolicy`: rollouts,
    then epochs of minibatches), the others :mod:`~torcsrl.training.offpolicy`."""
    validate(cfg)
    run_dir = resolve_run_dir(cfg)
    if not cfg.run_dir:  # pin the folder (a time stamp outside Hydra) for everything that asks for it below
        cfg = cfg.copy()
        with open_dict(cfg):
            cfg.run_dir = str(run_dir)
    with claim_run_dir(run_dir, resume=bool(cfg.checkpoint.resume), overwrite=bool(cfg.get("overwrite", False))):
        if cfg.algo.name in agents.IMITATION:
            return imitation.train(cfg)
        if cfg.algo.name in agents.ON_POLICY:
            return onpolicy.train(cfg, Path(run_dir))
        return offpolicy.train(cfg, Path(run_dir))
