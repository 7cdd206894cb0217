"""The report app: ``python -m torcsrl.report``."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any


from torcsrl.evaluate import EvalError
from torcsrl.policies import PolicyError
from torcsrl.report.grid import (DEFAULT_DEGRADATIONS, DEFAULT_SEVERITIES, DEFAULT_TRACKS, ReportConfig, check_counts,
                                 default_policies, expand_degradations, run_report)
from torcsrl.report.results import build_report, read_rows
from torcsrl.utils.faults import exit_code, graceful_termination, os_error_line

def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torcsrl.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", "--policies", dest="policy", nargs="+", default=None,
                        help="policy specs: checkpoint paths, 'reference', 'expert', 'heuristic' (default: the shipped reference driver)")
    parser.add_argument("--reference", default=None, help="reference policy for CE / mCE (default: the first policy)")
    parser.add_argument("--tracks", "--track", dest="tracks", nargs="+", default=list(DEFAULT_TRACKS),
                        help=f"track names and/or sets such as set:heldout (default: {' '.join(DEFAULT_TRACKS)})")
    parser.add_argument("--surfaces", "--surface", dest="surfaces", nargs="+", default=None,
                        help="road surfaces (default: each track's own)")
    parser.add_argument("--degradations", "--degradation", dest="degradations", nargs="+", default=list(DEFAULT_DEGRADATIONS),
                        help="degradation names (rangefinder.fog, state.latency, weather.rain, ...); 'all-rangefinder', "
                             f"'all-state', 'heldout' expand to groups (default: {' '.join(DEFAULT_DEGRADATIONS)})")
    parser.add_argument("--severities", nargs="+", type=int, default=list(DEFAULT_SEVERITIES),
                        help=f"severities in 0..5, 0 = clean (default: {' '.join(map(str, DEFAULT_SEVERITIES))})")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per cell")
    parser.add_argument("--laps", type=int, default=1, help="laps per episode")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default: the laps at 10 m/s)")
    parser.add_argument("--random-max-steps", type=int, default=1500, help="step cap of the random baseline's episodes")
    parser.add_argument("--workers", type=int, default=max(1, min(4, os.cpu_count() or 1)),
                        help="processes running cells in parallel (default: min(4, CPUs))")
    parser.add_argument("--n-boot", type=int, default=1000, help="bootstrap resamples")
    parser.add_argument("--batch-cars", type=int, default=512,
                        help="episodes of one policy and track driven as cars of one env (1: one car at a time)")
    parser.add_argument("--out", default=None, help="output folder (default outputs/report/<time>)")
    parser.add_argument("--cache", default=None, help="cell cache folder (default <out>/cells, or outputs/report/cells without --out)")
    parser.add_argument("--from-dir", default=None, help="build the report from evaluation/cell JSON files under this folder")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    out = Path(args.out) if args.out else Path("outputs") / "report" / time.strftime("%Y-%m-%d_%H-%M-%S")
    try:
        with graceful_termination():
            res = _run_main(args, out)
    except (EvalError, PolicyError) as err:
        print(f"torcsrl.report: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"torcsrl.report: error: {os_error_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        print(f"torcsrl.report: error: stopped by {getattr(err, 'name', 'SIGINT')}; worker processes stopped; finished cells "
              "are kept in the cache and a re-run skips them", file=sys.stderr)
        return exit_code(err)
    print(res["summary_line"])
    print(f"report: {out / 'REPORT.md'}  ({out / 'report.html'})")
    return 0


def _run_main(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """The work of :func:`main` once the flags are parsed."""
    check_counts(n_boot=args.n_boot, episodes=args.episodes, laps=args.laps, workers=args.workers, max_steps=args.max_steps,
                 random_max_steps=args.random_max_steps, batch_cars=args.batch_cars)
    if args.from_dir:
        rows = read_rows(args.from_dir)
        cors = None if args.degradations == list(DEFAULT_DEGRADATIONS) else args.degradations
        return build_report(rows, out, policies=args.policy, reference=args.reference, corruptions=cors,
                            n_boot=args.n_boot, seed=args.seed, meta={"source": str(args.from_dir)})
    policies = args.policy
    if policies is None:
        policies, note = default_policies()
        if note:
            print(f"[torcsrl.report] {note}", file=sys.stderr)
    degs = expand_degradations(args.degradations)
    cfg = ReportConfig(policies=list(policies), reference=args.reference, tracks=args.tracks,
                       surfaces=args.surfaces or [None], degradations=degs, severities=args.severities,
                       episodes=args.episodes, laps=args.laps, seed=args.seed, max_steps=args.max_steps,
                       random_max_steps=args.random_max_steps, workers=args.workers, n_boot=args.n_boot,
                       batch_cars=args.batch_cars)
    cache = args.cache or (None if args.out else Path("outputs") / "report" / "cells")
    return run_report(cfg, out, cache)


