"""The training config's check, as the entry points use it, and the records of what a run was made from.

:func:`validate` / :func:`problems` check a composed training config before anything is built: each subsystem checks
its own part beside the code it checks (:func:`torcsrl.training.checks.check`: the config's own sections;
:func:`torcsrl.pipeline.check`: env, degradations, histories; :func:`torcsrl.training.demos.check`;
:func:`torcsrl.training.curriculum.check`: every stage's config again), gathered by :func:`torcsrl.training.problems`,
which :func:`torcsrl.training.train` runs too. ``python -m torcsrl.train`` runs it first, and the tests on every config
the tree can compose.

Run records (:func:`save_run_info`, :func:`write_metrics`): ``config.yaml`` (the resolved config),
``git_rev.txt`` (commit, ``-dirty`` when the tree differs from it; ``git_diff.patch`` then holds the difference of
the tracked files) and ``metrics.json`` (what ``train(cfg)`` returned; non-finite numbers as null).
"""

from __future__ import annotations

import json
import math
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from torcsrl.training import ConfigError, problems, validate
from torcsrl.training.checks import section
from torcsrl.utils.hydra_app import CONF_DIR

__all__ = ["ConfigError", "validate", "problems", "save_run_info", "write_metrics", "objective", "git_revision"]


def save_run_info(cfg: DictConfig, run_dir: str | Path) -> None:
    """Write ``config.yaml`` (resolved) and ``git_rev.txt`` (+ ``git_diff.patch`` when dirty) into ``run_dir``."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    body = {k: section(cfg, k) for k in cfg.keys() if k != "hydra"}
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(body)))
    rev, diff = git_revision()
    (run_dir / "git_rev.txt").write_text(rev + "\n")
    if diff:
        (run_dir / "git_diff.patch").write_text(diff)


def write_metrics(run_dir: str | Path, metrics: Mapping[str, Any]) -> Path:
    """``metrics.json`` in ``run_dir``: the final metrics, numbers as numbers, NaN/inf as null (strict JSON)."""

    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, (str, int, float, bool)) or v is None:
            return v
        if hasattr(v, "item"):
            return clean(v.item())
        return str(v)

    path = Path(run_dir) / "metrics.json"
    path.write_text(json.dumps({k: clean(v) for k, v in metrics.items()}, indent=2, sort_keys=True) + "\n")
    return path


def objective(metrics: Mapping[str, Any], name: str | None) -> float | None:
    """The value a sweeper optimises: ``metrics[name]`` as a float (None without a name).

    A missing or non-numeric value (e.g. ``eval/reward`` of a run too short to validate) raises RuntimeError, which
    ``torcsrl.train``'s main lets through to Hydra: the Optuna sweeper records a failed trial (the sweep goes on
    while the failures stay within ``hydra.sweeper.max_failure_rate``) instead of choking on a NaN.
    """
    if not name:
        return None
    v = metrics.get(name)
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise RuntimeError(f"optimized_metric {name!r} is not a finite number in this run's metrics ({v!r}); "
                           f"metrics: {', '.join(sorted(metrics))}")
    return float(v)


def git_revision(root: str | Path | None = None) -> tuple[str, str]:
    """(``<commit>`` or ``<commit>-dirty`` or ``unknown``, the diff of tracked files against it when dirty)."""
    root = Path(root) if root else CONF_DIR.parent

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30, check=True).stdout

    try:
        rev = git("rev-parse", "HEAD").strip()
        diff = git("diff", "HEAD")
    except (OSError, subprocess.SubprocessError):
        return "unknown", ""
    return (rev + "-dirty" if diff else rev), diff
