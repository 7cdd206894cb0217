"""The report app: ``python -m torcsrl.report``.

The app checks its arguments (:func:`check_config`) before it loads the episode machinery (torch, TorchRL and pybullet,
through :mod:`~torcsrl.report.runner`) or matplotlib (:mod:`~torcsrl.report.results`): ``--help`` and a bad argument
answer at once.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torcsrl.evaluate.app import one_torch_thread, policy_errors
from torcsrl.evaluate.spec import EvalError
from torcsrl.report.grid import DEFAULT_DEGRADATIONS, ReportConfig, check_counts, expand_degradations
from torcsrl.utils.faults import cli_error, graceful_termination
from torcsrl.utils.hydra_app import AppError, check_keys, compose, flags_to_overrides, is_multirun
from torcsrl.utils.seq import as_list

__all__ = ["FLAGS", "TYPES", "check_config", "run_config", "run_checked", "main"]

#: The flags of earlier versions, aliases of the config's keys (conf/report.yaml).
FLAGS = {"--policy": ("policies", "many"), "--policies": ("policies", "many"), "--reference": ("reference", "one"),
         "--tracks": ("tracks", "many"), "--track": ("tracks", "many"), "--surfaces": ("surfaces", "many"),
         "--surface": ("surfaces", "many"), "--degradations": ("degradations", "many"), "--degradation": ("degradations", "many"),
         "--severities": ("severities", "many"), "--episodes": ("episodes", "one"), "--laps": ("laps", "one"),
         "--seed": ("seed", "one"), "--max-steps": ("max_steps", "one"), "--random-max-steps": ("random_max_steps", "one"),
         "--workers": ("workers", "one"), "--n-boot": ("n_boot", "one"), "--batch-cars": ("batch_cars", "one"),
         "--out": ("out", "one"), "--cache": ("cache", "one"), "--from-dir": ("from_dir", "one"), "--ray": ("ray", "one")}
_OPT_INT = (int, type(None))
TYPES = {"policies": (list, str, type(None)), "reference": (str, type(None)), "tracks": (list, str), "surfaces": (list, str, type(None)),
         "degradations": (list, str), "severities": (list, int), "episodes": (int,), "laps": (int,), "seed": (int,),
         "max_steps": _OPT_INT, "random_max_steps": (int,), "env_kwargs": (dict,), "workers": _OPT_INT, "n_boot": (int,),
         "batch_cars": (int,), "ray": (str, type(None)), "out": (str, type(None)), "cache": (str, type(None)),
         "from_dir": (str, type(None))}


def check_config(cfg: Any) -> dict[str, Any]:
    """The settings of a composed ``conf/report.yaml``, checked before anything runs: unknown keys, types, the
    severities and every count; EvalError (one line) otherwise."""
    try:
        c = check_keys(cfg, "report", TYPES)
    except AppError as err:
        raise EvalError(str(err)) from None
    sev = as_list(c["severities"], keep_none=True)
    bad = [s for s in sev if isinstance(s, bool) or not isinstance(s, int)]
    if bad:
        raise EvalError(f"severities must be integers in 0..5, got {bad}")
    check_counts(n_boot=c["n_boot"], episodes=c["episodes"], laps=c["laps"], workers=c["workers"], max_steps=c["max_steps"],
                 random_max_steps=c["random_max_steps"], batch_cars=c["batch_cars"])
    return c


def run_config(cfg: Any, verbose: bool = True) -> tuple[dict[str, Any], Path]:
    """The report of a composed ``conf/report.yaml`` (checked first: :func:`check_config`); returns (result, output
    folder)."""
    return run_checked(check_config(cfg), verbose)


def run_checked(c: dict[str, Any], verbose: bool = True) -> tuple[dict[str, Any], Path]:
    """:func:`run_config` from settings :func:`check_config` has passed."""
    # deferred: the report's files (matplotlib) and the episode machinery (torch, TorchRL, pybullet) load once the
    # arguments are checked
    from torcsrl.report.results import build_report, read_rows
    from torcsrl.report.runner import default_policies, run_report

    sev = as_list(c["severities"], keep_none=True)
    out = Path(c["out"]) if c["out"] else Path("outputs") / "report" / time.strftime("%Y-%m-%d_%H-%M-%S")
    degradations = as_list(c["degradations"], keep_none=True)
    policies = as_list(c["policies"], keep_none=True)
    if c["from_dir"]:
        rows = read_rows(c["from_dir"])
        cors = None if degradations == list(DEFAULT_DEGRADATIONS) else expand_degradations(degradations)
        return build_report(rows, out, policies=policies, reference=c["reference"], corruptions=cors,
                            n_boot=c["n_boot"], seed=c["seed"], meta={"source": str(c["from_dir"])}, verbose=verbose), out
    if policies is None:
        policies, note = default_policies()
        if note and verbose:
            print(f"[torcsrl.report] {note}", file=sys.stderr)
    rcfg = ReportConfig(policies=policies, reference=c["reference"], tracks=as_list(c["tracks"], keep_none=True),
                        surfaces=as_list(c["surfaces"], keep_none=True) or [None], degradations=expand_degradations(degradations),
                        severities=sev, episodes=c["episodes"], laps=c["laps"], seed=c["seed"], max_steps=c["max_steps"],
                        random_max_steps=c["random_max_steps"], env_kwargs=dict(c["env_kwargs"]), workers=c["workers"],
                        n_boot=c["n_boot"], batch_cars=c["batch_cars"], ray=c["ray"])
    cache = c["cache"] or (None if c["out"] else Path("outputs") / "report" / "cells")
    return run_report(rcfg, out, cache, verbose=verbose), out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torcsrl.report [key=value ...] [--flag value ...]`` (see conf/report.yaml)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print("Degradation robustness reports.\n\nusage: python -m torcsrl.report [key=value ...]; keys and defaults: "
              "conf/report.yaml; flags: " + " ".join(FLAGS))
        return 0
    try:
        overrides = flags_to_overrides(argv, FLAGS)
        if is_multirun(overrides):
            raise AppError("a report is one run (its cells run batched and in worker processes); sweep torcsrl.evaluate "
                           "with -m and build the report with from_dir=<sweep folder>")
        c = check_config(compose("report", overrides))
        one_torch_thread()
        with graceful_termination():
            res, out = run_checked(c)
    except (EvalError, *policy_errors(), AppError, OSError, KeyboardInterrupt) as err:
        return cli_error("torcsrl.report", err, stopped="worker processes (or Ray tasks) stopped; finished cells are kept in the "
                         "cache and a re-run skips them")
    print(res["summary_line"])
    print(f"report: {out / 'REPORT.md'}  ({out / 'report.html'})")
    return 0
