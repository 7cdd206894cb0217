"""The report app: ``python -m torcsrl.report``."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torcsrl.evaluate import EvalError
from torcsrl.policies import PolicyError
from torcsrl.report.grid import DEFAULT_DEGRADATIONS, ReportConfig, check_counts, default_policies, expand_degradations, run_report
from torcsrl.report.results import build_report, read_rows
from torcsrl.utils.faults import cli_error, graceful_termination

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


def _as_list(v: Any) -> list | None:
    return None if v is None else list(v) if isinstance(v, (list, tuple)) else [v]


def run_config(cfg: Any, verbose: bool = True) -> tuple[dict[str, Any], Path]:
    """The report of a composed ``conf/report.yaml`` (checked first); returns (result, output folder)."""
    from torcsrl.utils.hydra_app import AppError, check_keys

    try:
        c = check_keys(cfg, "report", TYPES)
    except AppError as err:
        raise EvalError(str(err)) from None
    sev = _as_list(c["severities"])
    bad = [s for s in sev if isinstance(s, bool) or not isinstance(s, int)]
    if bad:
        raise EvalError(f"severities must be integers in 0..5, got {bad}")
    check_counts(n_boot=c["n_boot"], episodes=c["episodes"], laps=c["laps"], workers=c["workers"], max_steps=c["max_steps"],
                 random_max_steps=c["random_max_steps"], batch_cars=c["batch_cars"])
    out = Path(c["out"]) if c["out"] else Path("outputs") / "report" / time.strftime("%Y-%m-%d_%H-%M-%S")
    degradations = _as_list(c["degradations"])
    if c["from_dir"]:
        rows = read_rows(c["from_dir"])
        cors = None if degradations == list(DEFAULT_DEGRADATIONS) else expand_degradations(degradations)
        return build_report(rows, out, policies=_as_list(c["policies"]), reference=c["reference"], corruptions=cors,
                            n_boot=c["n_boot"], seed=c["seed"], meta={"source": str(c["from_dir"])}, verbose=verbose), out
    policies = _as_list(c["policies"])
    if policies is None:
        policies, note = default_policies()
        if note and verbose:
            print(f"[torcsrl.report] {note}", file=sys.stderr)
    rcfg = ReportConfig(policies=policies, reference=c["reference"], tracks=_as_list(c["tracks"]),
                        surfaces=_as_list(c["surfaces"]) or [None], degradations=expand_degradations(degradations),
                        severities=sev, episodes=c["episodes"], laps=c["laps"], seed=c["seed"], max_steps=c["max_steps"],
                        random_max_steps=c["random_max_steps"], env_kwargs=dict(c["env_kwargs"]), workers=c["workers"],
                        n_boot=c["n_boot"], batch_cars=c["batch_cars"], ray=c["ray"])
    cache = c["cache"] or (None if c["out"] else Path("outputs") / "report" / "cells")
    return run_report(rcfg, out, cache, verbose=verbose), out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torcsrl.report [key=value ...] [--flag value ...]`` (see conf/report.yaml)."""
    from torcsrl.utils.hydra_app import AppError, compose, flags_to_overrides, is_multirun

    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print("Degradation robustness reports.\n\nusage: python -m torcsrl.report [key=value ...]; keys and defaults: "
              "conf/report.yaml; flags: " + " ".join(FLAGS))
        return 0
    import torch

    torch.set_num_threads(1)
    try:
        overrides = flags_to_overrides(argv, FLAGS)
        if is_multirun(overrides):
            raise AppError("a report is one run (its cells run batched and in worker processes); sweep torcsrl.evaluate "
                           "with -m and build the report with from_dir=<sweep folder>")
        cfg = compose("report", overrides)
        with graceful_termination():
            res, out = run_config(cfg)
    except (EvalError, PolicyError, AppError, OSError, KeyboardInterrupt) as err:
        return cli_error("torcsrl.report", err, stopped="worker processes (or Ray tasks) stopped; finished cells are kept in the "
                         "cache and a re-run skips them")
    print(res["summary_line"])
    print(f"report: {out / 'REPORT.md'}  ({out / 'report.html'})")
    return 0
