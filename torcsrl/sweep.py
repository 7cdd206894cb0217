"""Summarise a Hydra multirun: one row per configuration, mean ± 95 % CI across seeds.

``python -m torcsrl.sweep outputs/multirun/train/<time> [--metrics eval/reward eval/laps] [--ignore seed]``

Every job folder under the sweep (any folder holding ``.hydra/overrides.yaml``) contributes its
``metrics.json`` (what ``train(cfg)`` returned, written by ``python -m torcsrl.train``). Jobs are grouped by
their command-line overrides minus the ignored keys (``seed`` by default: the rows are configurations, the
seeds their samples); for every numeric metric a row gets the mean over the jobs that report a finite value,
the half-width of its two-sided Student-t confidence interval (``t_{0.975, n-1} · sd / sqrt(n)``; none for one
job) and n. Jobs without ``metrics.json`` (failed, or still running) are counted per row as ``missing``.

Writes ``summary.csv`` (every numeric metric: ``<metric>_mean``, ``<metric>_ci95``, ``<metric>_n``) and
``summary.md`` (the selected metrics as ``mean ± ci``) into the sweep folder (or ``--out``) and prints the
Markdown table. The override keys that vary between rows are the table's first columns; those shared by every
job are listed above it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

__all__ = ["Job", "Row", "load_jobs", "summarise", "mean_ci", "write_csv", "markdown", "main"]

#: Override keys that never define a configuration (where a run writes, how it resumes).
ALWAYS_IGNORED = ("run_dir", "checkpoint.resume", "buffer.load", "buffer.path")
#: Metrics of the Markdown table when none are named: validation results and wall-clock time.
DEFAULT_PREFIXES = ("eval/",)
DEFAULT_EXTRA = ("wall_s",)


@dataclass
class Job:
    """One job folder of a sweep."""

    path: Path
    overrides: dict[str, str]  # key -> value as typed on the command line (leading +/++/~ dropped)
    metrics: dict[str, Any] | None  # None: no metrics.json (failed or still running)


@dataclass
class Row:
    """One configuration: the jobs sharing its overrides (up to the ignored keys)."""

    config: dict[str, str]
    jobs: list[Job] = field(default_factory=list)

    @property
    def missing(self) -> int:
        return sum(j.metrics is None for j in self.jobs)

    def values(self, metric: str) -> list[float]:
        out = []
        for j in self.jobs:
            v = (j.metrics or {}).get(metric)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                out.append(float(v))
        return out


def _split(override: str) -> tuple[str, str]:
    key, _, value = override.partition("=")
    return key.lstrip("+~"), value


def _job_order(p: Path) -> tuple:
    head = p.name.split("_", 1)[0]
    return (int(head), str(p)) if head.isdigit() else (math.inf, str(p))


def load_jobs(root: str | Path) -> list[Job]:
    """Every job folder under ``root`` (in job-number order), with its overrides and metrics."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder (give the multirun folder, e.g. outputs/multirun/train/<time>)")
    jobs = []
    for ov in root.rglob(".hydra/overrides.yaml"):
        d = ov.parent.parent
        overrides = dict(_split(str(o)) for o in (yaml.safe_load(ov.read_text()) or []))
        mfile = d / "metrics.json"
        metrics = json.loads(mfile.read_text()) if mfile.is_file() else None
        jobs.append(Job(d, overrides, metrics))
    return sorted(jobs, key=lambda j: _job_order(j.path))


def summarise(jobs: Sequence[Job], ignore: Sequence[str] = ("seed",)) -> tuple[list[Row], list[str], dict[str, str]]:
    """(rows, the override keys that vary between rows, the overrides shared by every job)."""
    skip = set(ignore) | set(ALWAYS_IGNORED)

    def keep(k: str) -> bool:
        return k not in skip and not k.startswith("hydra.")

    rows: dict[tuple, Row] = {}
    for j in jobs:
        config = {k: v for k, v in j.overrides.items() if keep(k)}
        rows.setdefault(tuple(sorted(config.items())), Row(config)).jobs.append(j)
    keys: list[str] = []
    for r in rows.values():
        keys += [k for k in r.config if k not in keys]
    varying = [k for k in keys if len({r.config.get(k) for r in rows.values()}) > 1]
    shared = {k: next(iter(rows.values())).config[k] for k in keys if k not in varying and rows}
    shared = {k: v for k, v in shared.items() if all(r.config.get(k) == v for r in rows.values())}
    return list(rows.values()), varying, shared


def mean_ci(values: Sequence[float], confidence: float = 0.95) -> tuple[float, float, int]:
    """(mean, half-width of the Student-t confidence interval, n); the half-width is NaN below 2 values."""
    n = len(values)
    if n == 0:
        return math.nan, math.nan, 0
    m = sum(values) / n
    if n == 1:
        return m, math.nan, 1
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (n - 1))
    from scipy.stats import t  # deferred: scipy.stats (~0.5 s), only for a confidence interval

    return m, float(t.ppf(0.5 + confidence / 2, n - 1)) * sd / math.sqrt(n), n


def numeric_metrics(jobs: Sequence[Job]) -> list[str]:
    """Every metric some job reports as a number, in first-seen order."""
    out: list[str] = []
    for j in jobs:
        for k, v in (j.metrics or {}).items():
            if (isinstance(v, (int, float)) and not isinstance(v, bool) or v is None) and k not in out:
                out.append(k)
    return [k for k in out if any(isinstance((j.metrics or {}).get(k), (int, float)) for j in jobs)]


def default_table_metrics(metrics: Sequence[str]) -> list[str]:
    chosen = [m for m in metrics if m.startswith(DEFAULT_PREFIXES)] + [m for m in DEFAULT_EXTRA if m in metrics]
    return chosen or list(metrics)


def _seeds(r: Row) -> str:
    return " ".join(j.overrides.get("seed", "?") for j in r.jobs if j.metrics is not None)


def write_csv(path: Path, rows: Sequence[Row], varying: Sequence[str], metrics: Sequence[str], confidence: float = 0.95) -> Path:
    """One line per configuration: the varying overrides, jobs, missing, seeds, then mean / ci / n per metric."""
    tag = f"ci{round(confidence * 100)}"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([*varying, "jobs", "missing", "seeds", *[f"{m}_{s}" for m in metrics for s in ("mean", tag, "n")]])
        for r in rows:
            cells: list[Any] = [r.config.get(k, "") for k in varying] + [len(r.jobs), r.missing, _seeds(r)]
            for m in metrics:
                mean, ci, n = mean_ci(r.values(m), confidence)
                cells += ["" if math.isnan(mean) else f"{mean:.6g}", "" if math.isnan(ci) else f"{ci:.6g}", n]
            w.writerow(cells)
    return path


def _fmt(x: float) -> str:
    if math.isnan(x):
        return "–"
    return f"{x:.0f}" if abs(x) >= 1000 else f"{x:.3g}"


def markdown(rows: Sequence[Row], varying: Sequence[str], shared: dict[str, str], metrics: Sequence[str],
             confidence: float = 0.95, title: str | None = None) -> str:
    """The table: varying overrides, n (jobs with metrics), then ``mean ± ci`` per metric."""
    lines = []
    if title:
        lines += [f"### {title}", ""]
    if shared:
        lines += ["Common overrides: " + ", ".join(f"`{k}={v}`" for k, v in shared.items()), ""]
    lines += [f"Mean ± {round(confidence * 100)} % CI (Student t) across seeds; n = jobs with metrics.", ""]
    head = [*(varying or ["config"]), "n", *metrics]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "|".join("---" if i < len(varying or [0]) else "---:" for i in range(len(head))) + "|")
    for r in rows:
        cells = [r.config.get(k, "") for k in varying] if varying else ["(all)"]
        n_ok = len(r.jobs) - r.missing
        cells.append(f"{n_ok}" + (f" ({r.missing} missing)" if r.missing else ""))
        for m in metrics:
            mean, ci, _ = mean_ci(r.values(m), confidence)
            cells.append(_fmt(mean) + ("" if math.isnan(ci) else f" ± {_fmt(ci)}"))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torcsrl.sweep", description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep_dir", help="a multirun folder, e.g. outputs/multirun/train/<time>")
    parser.add_argument("--metrics", nargs="+", default=None,
                        help="metrics of the Markdown table (default: eval/* and wall_s); the CSV has every numeric metric")
    parser.add_argument("--ignore", nargs="*", default=["seed"], help="override keys that do not define a configuration (default: seed)")
    parser.add_argument("--confidence", type=float, default=0.95)
    parser.add_argument("--out", default=None, help="folder for summary.csv and summary.md (default: the sweep folder)")
    args = parser.parse_args(argv)
    try:
        jobs = load_jobs(args.sweep_dir)
    except FileNotFoundError as err:
        print(f"torcsrl.sweep: error: {err}", file=sys.stderr)
        return 2
    if not jobs:
        print(f"torcsrl.sweep: error: no job folders (with .hydra/overrides.yaml) under {args.sweep_dir}", file=sys.stderr)
        return 2
    if not 0 < args.confidence < 1:
        print(f"torcsrl.sweep: error: --confidence must lie in (0, 1), got {args.confidence}", file=sys.stderr)
        return 2
    rows, varying, shared = summarise(jobs, args.ignore)
    all_metrics = numeric_metrics(jobs)
    table = args.metrics or default_table_metrics(all_metrics)
    unknown = [m for m in table if m not in all_metrics]
    if unknown:
        print(f"torcsrl.sweep: error: no job reports {unknown}; metrics: {', '.join(all_metrics) or '(none: no metrics.json yet)'}",
              file=sys.stderr)
        return 2
    out = Path(args.out or args.sweep_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "summary.csv", rows, varying, all_metrics, args.confidence)
    md = markdown(rows, varying, shared, table, args.confidence, title=f"Sweep {Path(args.sweep_dir).name}: {len(jobs)} jobs")
    (out / "summary.md").write_text(md)
    print(md)
    print(f"[torcsrl.sweep] {len(jobs)} jobs in {len(rows)} configurations -> {out / 'summary.csv'}, {out / 'summary.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
