"""Degradation robustness reports: policies × tracks × degradations × severities 0..5.

``python -m torcsrl.report`` (no arguments) drives the shipped reference driver
(:data:`torcsrl.policies.REFERENCE_POLICY`; the scripted expert until it ships) on 2 held-out
tracks × 4 degradations × severities 0, 1, 3, 5 × 1 episode of 1 lap: a few minutes on a laptop.

``python -m torcsrl.report --policy A.pt B.pt --reference A.pt --tracks set:heldout
--degradations rangefinder.fog state.latency --severities 0 1 2 3 4 5 --episodes 5 --workers 8``

Every cell (policy, track, surface, degradation, severity) runs ``episodes`` episodes of ``laps``
laps with :func:`torcsrl.evaluate.run_cell`: episode ``e`` starts from the env seed
``seed_for(seed, "env", track, surface, e)`` and its degradation draws come from
``seed_for(seed, "degradation", name, severity, e)`` — the same for every policy (common random
numbers), so differences between policies are not weather luck. Severity 0 (the clean run) is
one cell per (policy, track, surface), shared by every degradation. The uniform random policy's
clean cells give R_random for the normalised return. A degradation that touches none of a
policy's observation keys cannot change its driving: that policy's clean episodes stand in for
those cells (flagged ``reused_clean``).

Cells run in parallel processes (``--workers``) and each is cached as one JSON file in
``<out>/cells/`` (or ``--cache``), named by a hash of the policy's bytes, the cell and the
config: an interrupted report re-run with the same folder skips the cells already done, and a
changed policy file or config (laps, episodes, seed, step cap, env settings) recomputes them.

Outputs (``--out``): ``robustness.json`` (config, config hash, every cell with its seeds, the
metrics), ``robustness.csv`` (one row per episode), ``robustness_summary.csv`` (per policy ×
degradation × severity), ``REPORT.md`` and a self-contained ``report.html`` (a summary line,
a leaderboard, per-degradation tables grouped by sensor and effect, the plots inline),
``nr_heatmap.png`` (NR over degradation × severity, one panel per policy) and
``severity_curves.png`` (NR against severity per degradation, one line per policy, 95 % bands).
Metric definitions: :mod:`torcsrl.metrics`.

``--from-dir DIR`` builds the report from results already on disk instead: every
``evaluation.json`` under DIR (e.g. the jobs of a Hydra multirun of ``torcsrl.evaluate``, one
per track/degradation/severity) and every cached cell JSON.
"""

from __future__ import annotations

import argparse
import base64
import concurrent.futures as cf
import functools
import hashlib
import html
import json
import math
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torcsrl import metrics
from torcsrl.evaluate import (PROTOCOL_VERSION, Degradation, EvalError, _f, check_policy_env, markdown_table,
                              parse_degradation, read_evaluations, run_cell, validate_grid, write_csv, write_json)
from torcsrl.policies import BUILTIN_POLICIES, REFERENCE_POLICY, Policy, PolicyError, load_policy
from torcsrl.utils.faults import (OutputError, exit_code, graceful_termination, ignore_signals_in_worker, os_error_line, stop_pool,
                                  writable_folder)

__all__ = [
    "DEFAULT_DEGRADATIONS",
    "DEFAULT_TRACKS",
    "DEFAULT_SEVERITIES",
    "EFFECT_FAMILIES",
    "ReportConfig",
    "run_report",
    "build_report",
    "read_rows",
    "main",
]

#: The no-argument report: two held-out tracks (asphalt and dirt), four degradations over two
#: sensors, severities 0, 1, 3, 5, one episode of one lap per cell.
DEFAULT_TRACKS = ("kidney", "rallycross")
DEFAULT_DEGRADATIONS = ("rangefinder.noise", "rangefinder.dropout", "state.noise", "state.latency")
DEFAULT_SEVERITIES = (0, 1, 3, 5)
#: Effect families used to group the per-degradation tables (by the part after the sensor).
EFFECT_FAMILIES: dict[str, tuple[str, ...]] = {
    "noise & bias": ("noise", "quantize", "outliers", "bias_scale", "bias"),
    "missing data": ("dropout", "dead_beams", "fov_loss", "stuck", "scan_drop", "frame_drop", "occlusion", "mud"),
    "timing": ("latency",),
    "weather & light": ("fog", "rain", "snow", "spray", "droplets", "glare", "darkness", "motion_blur"),
}
RANDOM = "random"


def sensor_and_family(name: str) -> tuple[str, str]:
    """("rangefinder", "noise & bias") for "rangefinder.noise"; weather presets → ("all sensors", "weather preset")."""
    if name.startswith("weather."):
        return "all sensors", "weather preset"
    sensor, _, effect = name.partition(".")
    for fam, effects in EFFECT_FAMILIES.items():
        if effect in effects:
            return sensor, fam
    return sensor, "other"


@dataclass
class ReportConfig:
    """What a report runs. ``policies``: specs (:func:`torcsrl.policies.load_policy`);
    ``reference``: the CE denominator (default: the first policy); ``tracks``: names or sets;
    ``surfaces``: road surfaces (None: each track's own); ``degradations``: registry names or
    ``weather.<preset>``; ``severities``: subset of 0..5 (0 is always run); ``episodes`` per
    cell; ``laps`` per episode; ``max_steps``: step cap (default: laps at 10 m/s);
    ``random_max_steps``: cap for the random baseline's episodes; ``env_kwargs``: more
    make_env keywords; ``workers``: processes; ``n_boot``: bootstrap resamples."""

    policies: list[str] = field(default_factory=lambda: ["reference"])
    reference: str | None = None
    tracks: list[str] = field(default_factory=lambda: list(DEFAULT_TRACKS))
    surfaces: list[str | None] = field(default_factory=lambda: [None])
    degradations: list[str] = field(default_factory=lambda: list(DEFAULT_DEGRADATIONS))
    severities: list[int] = field(default_factory=lambda: list(DEFAULT_SEVERITIES))
    episodes: int = 1
    laps: int = 1
    seed: int = 0
    max_steps: int | None = None
    random_max_steps: int = 1500
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    workers: int = 1
    n_boot: int = 1000

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> "ReportConfig":
        """From a plain mapping (e.g. ``OmegaConf.to_container(cfg.report)``); unknown keys: EvalError."""
        known = set(cls.__dataclass_fields__)
        bad = sorted(set(d) - known)
        if bad:
            raise EvalError(f"unknown report setting(s) {bad}; known: {', '.join(sorted(known))}")
        return cls(**{k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in d.items()})

    def cell_config(self) -> dict[str, Any]:
        """The part of the config every cell depends on (its hash is the config hash): the episode
        protocol and the code that produces an episode (env, degradations, evaluation loop)."""
        return {"protocol": PROTOCOL_VERSION, "episodes": int(self.episodes), "laps": int(self.laps), "seed": int(self.seed),
                "max_steps": self.max_steps, "random_max_steps": int(self.random_max_steps),
                "env_kwargs": {k: self.env_kwargs[k] for k in sorted(self.env_kwargs)}, "code": code_hash()}


@functools.lru_cache(maxsize=1)
def code_hash() -> str:
    """Hash of the sources that decide an episode's outcome: ``torcsrl/envs`` (physics, sensors,
    tracks), ``torcsrl/transforms`` (degradations) and ``torcsrl/evaluate.py`` (the loop); read
    once per process."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    files = sorted([*(root / "envs").rglob("*.py"), *(root / "envs").rglob("*.yaml"), *(root / "transforms").rglob("*.py"),
                    *(root / "evaluate").glob("*.py")])
    for f in files:
        if "__pycache__" in f.parts:
            continue
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


# --------------------------------------------------------------------------------------------
# Cells
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Cell:
    policy: str  # unique name in this report
    spec: str
    fingerprint: str
    track: str
    surface: str
    corruption: str
    severity: int
    params: tuple = ()
    own_surface: bool = True  # the track's own surfaces (``surface`` is then only its label)

    def key(self, config_hash: str) -> str:
        return _hash([config_hash, self.fingerprint, self.track, self.surface, self.own_surface, self.corruption,
                      self.severity, list(self.params)])[:32]

    def label(self) -> str:
        c = "clean" if self.corruption == metrics.CLEAN else f"{self.corruption}@{self.severity}"
        return f"{self.policy} {self.track}/{self.surface} {c}"


_POLICY_CACHE: dict[str, Policy] = {}


def _worker_init() -> None:
    import torch

    torch.set_num_threads(1)
    ignore_signals_in_worker()


def _run_cell_task(cell: Cell, policy: Any, cfg: dict[str, Any], config_hash: str, path: str) -> dict[str, Any]:
    """Run one cell (in a worker) and write its JSON atomically; returns the record."""
    t0 = time.perf_counter()
    if isinstance(policy, str):
        if policy not in _POLICY_CACHE:
            _POLICY_CACHE[policy] = load_policy(policy)
        pol = _POLICY_CACHE[policy]
    else:
        pol = policy
    pol.name = cell.policy
    deg = Degradation(cell.corruption, cell.severity, cell.params) if cell.corruption != metrics.CLEAN else None
    max_steps = cfg["random_max_steps"] if cell.policy == RANDOM else cfg["max_steps"]
    rows, _ = run_cell(pol, cell.track, None if cell.own_surface else cell.surface, deg, episodes=cfg["episodes"], laps=cfg["laps"], seed=cfg["seed"],
                       max_steps=max_steps, env_kwargs=cfg["env_kwargs"])
    record = {"key": cell.key(config_hash), "config_hash": config_hash, "cell": asdict(cell), "config": cfg,
              "rows": rows, "wall_s": time.perf_counter() - t0, "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    write_json(record, path)
    return record


def _load_cached(path: Path, key: str) -> dict[str, Any] | None:
    try:
        rec = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return rec if rec.get("key") == key else None


# --------------------------------------------------------------------------------------------
# Running a grid
# --------------------------------------------------------------------------------------------
def _unique_names(policies: Sequence[Policy]) -> list[str]:
    names, seen = [], {}
    for p in policies:
        n = p.name
        if n in seen:
            seen[n] += 1
            n = f"{n}_{seen[n]}"
        else:
            seen[n] = 0
        names.append(n)
    return names


def prepare(cfg: ReportConfig) -> dict[str, Any]:
    """Check every input and build the cell list — all before any episode runs.

    Raises EvalError / PolicyError with one line for a missing or mismatched checkpoint, an
    unknown track, surface or degradation, a severity outside 0..5, or an empty grid.
    """
    if not cfg.policies:
        raise EvalError("no policy given (empty grid)")
    if int(cfg.episodes) < 1 or int(cfg.laps) < 1:
        raise EvalError(f"episodes and laps must be >= 1, got episodes={cfg.episodes}, laps={cfg.laps}")
    sev = sorted({int(s) for s in cfg.severities})
    bad = [s for s in sev if not 0 <= s <= 5]
    if bad:
        raise EvalError(f"severities must be in 0..5 (0 = clean), got {bad}")
    degs = [parse_degradation(d, 1) for d in dict.fromkeys(cfg.degradations)]
    degs = [d for d in degs if not d.clean]
    if not degs:
        raise EvalError("no degradation given (empty grid); e.g. --degradations rangefinder.noise state.latency")
    if not [s for s in sev if s >= 1]:
        raise EvalError(f"no severity >= 1 in {cfg.severities} (empty grid); e.g. --severities 0 1 3 5")
    tracks, surfaces = validate_grid(cfg.tracks, cfg.surfaces)
    specs = list(dict.fromkeys(str(p) for p in cfg.policies))
    ref_spec = str(cfg.reference) if cfg.reference is not None else specs[0]
    if ref_spec not in specs:
        specs.append(ref_spec)
    pols = [load_policy(s) for s in specs]
    for s, p in zip(specs, pols):
        if p.name == RANDOM:
            raise EvalError("the random policy is the NR baseline and always runs; do not list it as a policy")
        check_policy_env(p, tracks[0], cfg.env_kwargs)
    names = _unique_names(pols)
    for p, n in zip(pols, names):
        p.name = n
    ref_name = names[specs.index(ref_spec)]
    random = load_policy(RANDOM)
    from torcsrl.envs import tracks as _tracks

    surface_names = {(t, s): (s or _tracks.load(t).default_surface) for t in tracks for s in surfaces}
    cells: list[tuple[Cell, Any]] = []
    reused: list[tuple[Cell, Cell]] = []  # (cell, clean cell standing in for it)
    for spec, p in zip(specs, pols):
        pspec = spec if (spec in BUILTIN_POLICIES or Path(spec).exists()) else p
        for t in tracks:
            for s in surfaces:
                su = surface_names[(t, s)]
                clean = Cell(p.name, str(spec), p.fingerprint, t, su, metrics.CLEAN, 0, (), s is None)
                cells.append((clean, pspec))
                for d in degs:
                    touches = set(d.keys()) & set(p.obs_keys)
                    for v in sev:
                        if v == 0:
                            continue
                        c = Cell(p.name, str(spec), p.fingerprint, t, su, d.name, v, d.params, s is None)
                        if touches:
                            cells.append((c, pspec))
                        else:
                            reused.append((c, clean))
    for t in tracks:
        for s in surfaces:
            cells.append((Cell(RANDOM, RANDOM, random.fingerprint, t, surface_names[(t, s)], metrics.CLEAN, 0, (), s is None),
                          RANDOM))
    return {"cells": cells, "reused": reused, "policies": [p.name for p in pols], "policy_info": {p.name: p.describe() for p in pols},
            "reference": ref_name, "tracks": tracks, "surfaces": surfaces, "degradations": [d.name for d in degs], "severities": sev}


def check_counts(**counts: Any) -> None:
    """EvalError (one line) for a count below 1: ``n_boot`` (bootstrap resamples), ``episodes``, ``laps``, ``workers``,
    ``max_steps`` (None: the default), ``random_max_steps``."""
    for name, v in counts.items():
        if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 1):
            flag = "--" + name.replace("_", "-")
            raise EvalError(f"{flag} (report {name}) must be an integer >= 1, got {v!r}; allowed: 1, 2, ... "
                            + ("(1000 is the default)" if name == "n_boot" else ""))


def run_report(cfg: ReportConfig, out_dir: str | Path, cache_dir: str | Path | None = None, verbose: bool = True) -> dict[str, Any]:
    """Run (or resume) the grid of ``cfg`` and write the report to ``out_dir``; returns
    ``{"summary", "files", "computed", "cached", "cells", ...}``."""
    t0 = time.perf_counter()
    check_counts(n_boot=cfg.n_boot, episodes=cfg.episodes, laps=cfg.laps, workers=cfg.workers, max_steps=cfg.max_steps,
                 random_max_steps=cfg.random_max_steps)
    plan = prepare(cfg)
    out = Path(out_dir)
    cache = Path(cache_dir) if cache_dir is not None else out / "cells"
    try:
        writable_folder(out, "--out")
        writable_folder(cache, "--cache")
    except OutputError as err:
        raise EvalError(str(err)) from None
    ccfg = cfg.cell_config()
    config_hash = _hash(ccfg)[:16]
    records: dict[Cell, dict[str, Any]] = {}
    todo: list[tuple[Cell, Any, Path]] = []
    for cell, pspec in plan["cells"]:
        key = cell.key(config_hash)
        path = cache / f"{key}.json"
        rec = _load_cached(path, key)
        if rec is not None:
            for r in rec["rows"]:  # the same bytes may be listed under another name this time
                r["policy"] = cell.policy
            records[cell] = rec
        else:
            todo.append((cell, pspec, path))
    n_cached = len(records)
    log = (lambda msg: print(f"[torcsrl.report] {msg}", file=sys.stderr, flush=True)) if verbose else (lambda msg: None)
    log(f"{len(plan['cells'])} cells ({n_cached} cached, {len(todo)} to run, {len(plan['reused'])} reuse a clean run) "
        f"on {max(1, min(int(cfg.workers), len(todo) or 1))} worker(s); cache {cache}")
    done = 0

    def _done(cell: Cell, rec: dict[str, Any]) -> None:
        nonlocal done
        done += 1
        rows = rec["rows"]
        lcr = metrics.lap_completion_rate(r["success"] for r in rows)
        log(f"[{done}/{len(todo)}] {cell.label()}: LCR {lcr:.2f}, return {np.mean([r['return'] for r in rows]):.0f}, "
            f"{rec['wall_s']:.1f} s")
        records[cell] = rec

    workers = max(1, min(int(cfg.workers), len(todo)))
    if workers == 1:
        for cell, pspec, path in todo:
            _done(cell, _run_cell_task(cell, pspec, ccfg, config_hash, str(path)))
    elif todo:
        ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_worker_init)
        try:
            futs = {ex.submit(_run_cell_task, cell, pspec, ccfg, config_hash, str(path)): cell for cell, pspec, path in todo}
            for fut in cf.as_completed(futs):
                _done(futs[fut], fut.result())
        except BaseException:  # a signal (Interrupted) or a failed cell: finished cells are in the cache already
            stop_pool(ex)
            raise
        ex.shutdown()
    # clean runs standing in for degradations a policy does not observe
    for cell, clean in plan["reused"]:
        rows = [dict(r, corruption=cell.corruption, severity=cell.severity, reused_clean=True) for r in records[clean]["rows"]]
        records[cell] = {"key": None, "config_hash": config_hash, "cell": asdict(cell), "rows": rows, "reused_clean": True}
    rows = [r for rec in records.values() for r in rec["rows"]]
    ran = {c for c, _, _ in todo}
    cells_out = [dict(rec, computed=cell in ran) for cell, rec in records.items()]
    meta = {"config": {**asdict(cfg), "cell_config": ccfg}, "config_hash": config_hash, "policy_info": plan["policy_info"],
            "cache_dir": str(cache)}
    res = build_report(rows, out, policies=plan["policies"], reference=plan["reference"], corruptions=plan["degradations"],
                       severities=plan["severities"], n_boot=cfg.n_boot, seed=cfg.seed, meta=meta, cells=cells_out,
                       verbose=verbose)
    res.update(computed=len(todo), cached=n_cached, reused=len(plan["reused"]), wall_s=time.perf_counter() - t0)
    log(f"done in {res['wall_s']:.0f} s: {len(todo)} cells run, {n_cached} from the cache; report in {out}")
    return res


# --------------------------------------------------------------------------------------------
# Reading results from disk
# --------------------------------------------------------------------------------------------
def read_rows(root: str | Path) -> list[dict[str, Any]]:
    """Episode rows from every ``evaluation.json`` (torcsrl.evaluate outputs, e.g. a Hydra
    multirun's jobs) and every cached cell JSON under ``root``. Duplicate episodes (same policy,
    fingerprint, track, surface, degradation, severity, episode, seeds) are kept once."""
    root = Path(root)
    if not root.exists():
        raise EvalError(f"{root} does not exist")
    rows: list[dict[str, Any]] = []
    for d in read_evaluations(root):
        rows += d.get("episodes", [])
    for p in sorted(root.rglob("*.json")):
        if p.name in ("evaluation.json", "robustness.json"):
            continue
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(d, dict) and isinstance(d.get("rows"), list) and "cell" in d:
            rows += d["rows"]
    seen, out = set(), []
    for r in rows:
        k = (r.get("policy"), r.get("policy_fingerprint"), r.get("track"), r.get("surface"), r.get("corruption"),
             int(r.get("severity", 0)), int(r.get("episode", 0)), r.get("env_seed"), r.get("degradation_seed"))
        if k not in seen:
            seen.add(k)
            out.append(r)
    if not out:
        raise EvalError(f"no evaluation results (evaluation.json or cell JSON files) under {root}")
    return out


# --------------------------------------------------------------------------------------------
# The report: JSON, CSV, Markdown, HTML, plots
# --------------------------------------------------------------------------------------------
class _Doc:
    """Blocks rendered both to Markdown and to self-contained HTML."""

    def __init__(self) -> None:
        self.blocks: list[tuple[str, Any]] = []

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", (level, text)))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def table(self, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        self.blocks.append(("table", (list(header), [list(r) for r in rows])))

    def img(self, path: Path, alt: str) -> None:
        self.blocks.append(("img", (Path(path), alt)))

    def markdown(self) -> str:
        out = []
        for kind, b in self.blocks:
            if kind == "h":
                out.append("#" * b[0] + " " + b[1])
            elif kind == "p":
                out.append(b)
            elif kind == "table":
                out.append(markdown_table(*b))
            elif kind == "img":
                out.append(f"![{b[1]}]({b[0].name})")
            out.append("")
        return "\n".join(out)

    def html(self, title: str) -> str:
        import re

        def inline(t: str) -> str:
            t = html.escape(t)
            return re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", t)

        parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>"
                 "body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}"
                 "table{border-collapse:collapse;margin:.5em 0 1.5em;font-size:13px}"
                 "th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f0f0f0}"
                 "td:first-child,th:first-child{text-align:left}img{max-width:100%}code{background:#f4f4f4}"
                 "</style></head><body>"]
        for kind, b in self.blocks:
            if kind == "h":
                parts.append(f"<h{b[0]}>{inline(b[1])}</h{b[0]}>")
            elif kind == "p":
                if b.startswith("- "):
                    items = "".join(f"<li>{inline(x[2:])}</li>" for x in b.split("\n") if x.startswith("- "))
                    parts.append(f"<ul>{items}</ul>")
                else:
                    parts.append(f"<p>{inline(b)}</p>")
            elif kind == "table":
                head = "".join(f"<th>{inline(c)}</th>" for c in b[0])
                body = "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in b[1])
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            elif kind == "img":
                data = base64.b64encode(b[0].read_bytes()).decode()
                parts.append(f"<p><img alt='{html.escape(b[1])}' src='data:image/png;base64,{data}'></p>")
        parts.append("</body></html>")
        return "\n".join(parts)


def _ci(v, ci, fmt="{:.2f}") -> str:
    s = _f(v, fmt)
    if ci and ci[0] is not None and ci[1] is not None and v is not None and not (ci[0] == ci[1] == v):
        s += f" ({_f(ci[0], fmt)}–{_f(ci[1], fmt)})"
    return s


def _pct(v) -> str:
    return _f(None if v is None else 100.0 * v, "{:.0f}%")


def plot_heatmap(summary: Mapping[str, Any], path: Path, reused: set[tuple[str, str]] = frozenset()) -> Path:
    """NR over degradation × severity, one panel per policy (RdYlGn, 0..1; NaN grey); a † marks
    the (policy, degradation) pairs in ``reused`` (the degradation misses the policy's inputs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pols = list(summary["policies"])
    cors = summary["corruptions"]
    sev = summary["severities"]
    n = len(pols)
    fig, axes = plt.subplots(1, n, figsize=(2.2 + 0.8 * len(sev) * n + 1.2, 1.3 + 0.42 * len(cors)), squeeze=False,
                             layout="constrained")
    cmap = plt.get_cmap("RdYlGn").with_extremes(bad="0.85")
    im = None
    for ax, p in zip(axes[0], pols):
        m = np.full((len(cors), len(sev)), np.nan)
        for i, c in enumerate(cors):
            for j, s in enumerate(sev):
                v = summary["policies"][p]["corruptions"][c]["severities"][str(s)]["nr"]
                m[i, j] = np.nan if v is None else v
        im = ax.imshow(np.ma.masked_invalid(m), cmap=cmap, vmin=0.0, vmax=1.0, aspect="auto")
        for i in range(len(cors)):
            for j in range(len(sev)):
                txt = "n/a" if np.isnan(m[i, j]) else f"{m[i, j]:.2f}" + ("†" if (p, cors[i]) in reused and sev[j] else "")
                ax.text(j, i, txt, ha="center", va="center", fontsize=8,
                        color="k" if np.isnan(m[i, j]) or 0.25 < m[i, j] < 0.85 else "w")
        ax.set_xticks(range(len(sev)), [str(s) for s in sev])
        ax.set_yticks(range(len(cors)), cors if ax is axes[0][0] else [""] * len(cors))
        ax.set_xlabel("severity")
        ax.set_title(p, fontsize=10)
    fig.colorbar(im, ax=axes[0].tolist(), label="normalised return NR", shrink=0.9)
    title = "Normalised return NR by degradation and severity (1 = clean, 0 = random driving)"
    if reused:
        title += "\n† not observed by the policy: its clean run stands in"
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_severity_curves(summary: Mapping[str, Any], path: Path, reused: set[tuple[str, str]] = frozenset()) -> Path:
    """NR against severity, one panel per degradation, one line per policy with its 95 % band
    (dotted, hollow markers: a policy that does not observe what the degradation corrupts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pols = list(summary["policies"])
    cors = summary["corruptions"]
    sev = summary["severities"]
    ncol = min(4, len(cors))
    nrow = int(math.ceil(len(cors) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.3 * ncol, 2.7 * nrow + 0.6), squeeze=False, sharey=True)
    colors = plt.get_cmap("tab10")
    for k, c in enumerate(cors):
        ax = axes[k // ncol][k % ncol]
        for i, p in enumerate(pols):
            cs = summary["policies"][p]["corruptions"][c]["severities"]
            y = np.array([np.nan if cs[str(s)]["nr"] is None else cs[str(s)]["nr"] for s in sev], dtype=float)
            lo = np.array([np.nan if cs[str(s)]["nr_ci"][0] is None else cs[str(s)]["nr_ci"][0] for s in sev], dtype=float)
            hi = np.array([np.nan if cs[str(s)]["nr_ci"][1] is None else cs[str(s)]["nr_ci"][1] for s in sev], dtype=float)
            if (p, c) in reused:
                ax.plot(sev, y, "o:", color=colors(i % 10), lw=1.2, ms=4, mfc="none")
            else:
                ax.plot(sev, y, "o-", color=colors(i % 10), label=p, lw=1.6, ms=4)
            ax.fill_between(sev, lo, hi, color=colors(i % 10), alpha=0.18, lw=0)
        ax.axhline(1.0, color="0.6", lw=0.8, ls="--")
        ax.axhline(0.0, color="0.6", lw=0.8, ls=":")
        ax.set_title(c, fontsize=9)
        ax.set_xticks(sev)
        ax.set_xlabel("severity (0 = clean)")
        if k % ncol == 0:
            ax.set_ylabel("NR")
        ax.grid(alpha=0.3)
    for k in range(len(cors), nrow * ncol):
        axes[k // ncol][k % ncol].set_visible(False)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=colors(i % 10), marker="o", lw=1.6, ms=4) for i in range(len(pols))]
    labels = list(pols)
    if reused:
        handles.append(Line2D([], [], color="0.4", marker="o", ls=":", mfc="none", ms=4))
        labels.append("not observed (clean run)")
    fig.legend(handles, labels, loc="upper center", ncol=min(len(handles), 5), fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fails_clean(first_break: Mapping[str, Any] | None) -> bool:
    """A policy whose "first break" is severity 0 never completed laps clean: no degradation broke it."""
    return bool(first_break) and first_break["severity"] == 0


def build_report(rows: Sequence[Mapping[str, Any]], out_dir: str | Path, *, policies: Sequence[str] | None = None,
                 reference: str | None = None, corruptions: Sequence[str] | None = None, severities: Sequence[int] | None = None,
                 n_boot: int = 1000, seed: int = 0, meta: Mapping[str, Any] | None = None,
                 cells: Sequence[Mapping[str, Any]] | None = None, verbose: bool = True) -> dict[str, Any]:
    """Metrics from episode ``rows`` and every output file in ``out_dir``; returns
    ``{"summary", "files", "summary_line"}``."""
    check_counts(n_boot=n_boot)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [dict(r) for r in rows]
    summary = metrics.robustness_summary(rows, policies=policies, reference=reference, random_policy=RANDOM,
                                         corruptions=corruptions, severities=severities, n_boot=n_boot, seed=seed)
    meta = dict(meta or {})
    pols = list(summary["policies"])
    ref = summary["reference"]
    sev = summary["severities"]
    cors = summary["corruptions"]

    # files: JSON, CSVs
    config_hash = meta.get("config_hash") or _hash(sorted({str(r.get("policy_fingerprint")) for r in rows}))[:16]
    if cells is None:
        groups: dict[tuple, list] = {}
        for r in rows:
            groups.setdefault((r["policy"], r["track"], r["surface"], r["corruption"], int(r["severity"])), []).append(r)
        cells = [{"cell": dict(zip(("policy", "track", "surface", "corruption", "severity"), k)), "rows": v} for k, v in groups.items()]
    write_json({**meta, "config_hash": config_hash, "summary": summary, "cells": list(cells)}, out / "robustness.json")
    ep_cols = ["policy", "track", "surface", "corruption", "severity", "episode", "env_seed", "degradation_seed", "return",
               "success", "laps", "laps_target", "terminated", "termination", "steps", "distance_m", "fastest_lap", "mean_lap",
               "mean_speed_kmh", "off_track_events", "steer_abs_delta", "steer_flips_per_km", "reused_clean",
               "policy_fingerprint"]
    write_csv([dict(r, config_hash=config_hash) for r in rows], out / "robustness.csv", ep_cols + ["config_hash"])
    srows = []
    for p in pols:
        for c in cors:
            pc = summary["policies"][p]["corruptions"][c]
            for s in sev:
                d = pc["severities"][str(s)]
                srows.append({"policy": p, "corruption": c, "sensor": sensor_and_family(c)[0], "effect": sensor_and_family(c)[1],
                              "severity": s, "nr": d["nr"], "nr_lo": d["nr_ci"][0], "nr_hi": d["nr_ci"][1], "lcr": d["lcr"],
                              "lcr_lo": d["lcr_ci"][0], "lcr_hi": d["lcr_ci"][1], "return": d["return"], "episodes": d["n"],
                              "ce": pc["ce"], "relative_ce": pc["relative_ce"], "ausc": pc["ausc"],
                              "breaking_severity": pc["breaking_severity"]})
    write_csv(srows, out / "robustness_summary.csv")

    # plots
    reused = {(r["policy"], r["corruption"]) for r in rows if r.get("reused_clean")}
    heat = plot_heatmap(summary, out / "nr_heatmap.png", reused)
    curves = plot_severity_curves(summary, out / "severity_curves.png", reused)

    # the document
    def rank_key(p):
        v = summary["policies"][p]["mrr"]
        return -(v if v is not None else -1e9)

    board = sorted(pols, key=rank_key)
    best = board[0]
    bp = summary["policies"][best]
    wc = bp["worst_case"]
    fb = bp["first_break"]
    n_p = f"{len(pols)} polic{'y' if len(pols) == 1 else 'ies'}"
    lead = f"**{best}** has the highest mRR of {n_p}:" if len(pols) > 1 else f"**{best}**: mRR"
    line = (f"{lead} {_ci(bp['mrr'], bp['mrr_ci'])}, mCE {_pct(bp['mce'])} of {ref}'s; "
            f"clean LCR {_pct(bp['clean']['lcr'])}; worst degradation {wc['corruption']} (mean NR {_f(wc['nr'])}); "
            + ("already fails clean (LCR < 50% at severity 0): read normalised return, not breaking severity."
               if _fails_clean(fb) else
               f"first breaks (LCR < 50%) under {fb['corruption']} at severity {fb['severity']}." if fb
               else "never breaks (LCR >= 50% everywhere)."))
    finite = [p for p in pols if summary["policies"][p]["mce"] is not None]
    if len(pols) > 1 and finite:
        low = min(finite, key=lambda p: summary["policies"][p]["mce"])
        if low != best:
            line += f" Lowest mCE: **{low}** ({_pct(summary['policies'][low]['mce'])})."
    doc = _Doc()
    doc.h(1, "Degradation robustness report")
    doc.p(line)
    tracks = sorted({f"{r['track']}/{r['surface']}" for r in rows if r["policy"] != RANDOM})
    n_ep = sorted({int(r.get("laps_target", 1)) for r in rows})
    doc.p(f"{len(pols)} polic{'y' if len(pols) == 1 else 'ies'} × {len(tracks)} track(s) ({', '.join(tracks)}) × {len(cors)} "
          f"degradation(s) × severities {', '.join(map(str, sev))}; {summary['units']} episode unit(s) (tracks × episodes) per cell, "
          f"{'/'.join(map(str, n_ep))} lap(s) each. Reference policy for CE: **{ref}**. Config hash `{config_hash}`. "
          f"Intervals: 95% percentile bootstrap over episode units ({n_boot} resamples, seed {seed}).")
    doc.h(2, "Leaderboard")
    header = ["Rank", "Policy", "Clean LCR", "Clean return", "mRR (95% CI)", "mCE (95% CI)", "Relative mCE", "Mean AUSC",
              "Worst case (mean NR)", "First break"]
    body = []
    for i, p in enumerate(board, 1):
        d = summary["policies"][p]
        w = d["worst_case"]
        b = d["first_break"]
        body.append([str(i), p + (" (ref)" if p == ref else ""), _pct(d["clean"]["lcr"]), _f(d["clean"]["return"], "{:.0f}"),
                     _ci(d["mrr"], d["mrr_ci"]), _ci(None if d["mce"] is None else 100 * d["mce"],
                                                     [None if v is None else 100 * v for v in d["mce_ci"]], "{:.0f}%"),
                     _pct(d["relative_mce"]), _f(d["mean_ausc"]), f"{w['corruption']} ({_f(w['nr'])})" if w["corruption"] else "–",
                     "fails clean" if _fails_clean(b) else f"{b['corruption']} @ {b['severity']}" if b else "none"])
    doc.table(header, body)
    doc.h(2, "Plots")
    doc.img(heat, "NR heatmap")
    doc.img(curves, "severity curves")
    doc.h(2, "Per degradation")
    doc.p("NR per severity (95% CI), lap completion rate (LCR) per severity, AUSC (area under NR(s), 1 = no loss), the "
          "breaking severity (first s with LCR < 50%), and CE / relative CE against the reference (100% = as robust as the "
          "reference; ∞: the reference never failed there but this policy did).")
    s_hi = [s for s in sev if s >= 1]
    for p in board:
        doc.h(3, f"{p}" + (" (reference)" if p == ref else ""))
        by_sensor: dict[str, list[str]] = {}
        for c in cors:
            by_sensor.setdefault(sensor_and_family(c)[0], []).append(c)
        for sensor, cs in by_sensor.items():
            cs = sorted(cs, key=lambda c: (list(EFFECT_FAMILIES).index(sensor_and_family(c)[1]) if sensor_and_family(c)[1] in EFFECT_FAMILIES else 99, c))
            header = ["Effect", "Degradation", *[f"NR s{s}" for s in s_hi], *[f"LCR s{s}" for s in s_hi], "AUSC", "Breaks at",
                      "CE", "Rel. CE"]
            body = []
            for c in cs:
                d = summary["policies"][p]["corruptions"][c]
                body.append([sensor_and_family(c)[1], c + (" †" if (p, c) in reused else ""),
                             *[_ci(d["severities"][str(s)]["nr"], d["severities"][str(s)]["nr_ci"]) for s in s_hi],
                             *[_pct(d["severities"][str(s)]["lcr"]) for s in s_hi], _f(d["ausc"]),
                             "–" if d["breaking_severity"] is None else str(d["breaking_severity"]),
                             _pct(d["ce"]), _pct(d["relative_ce"])])
            doc.p(f"**{sensor}**")
            doc.table(header, body)
    if reused:
        doc.p("† the degradation touches none of the policy's observation keys, so its clean episodes stand in.")
    doc.h(2, "Definitions")
    doc.p("- NR = (R − R_random) / (R_clean − R_random) per (track, episode), R_random from uniform random actions on the clean track; "
          "mRR = mean NR over degradations and severities ≥ 1.\n"
          "- LCR = share of episodes that drove all their laps without leaving the track, driving backwards, stalling or flipping; "
          "DE = 1 − LCR; CE_c = Σ_s DE / Σ_s DE_ref over s ≥ 1; mCE = mean CE_c; relative CE subtracts each policy's clean DE first.\n"
          "- AUSC = trapezoid area under NR(s) (NR clipped to [0, 1]) over the tested severities, divided by their span.\n"
          "- Common random numbers: every policy saw the same starts and the same degradation draws (seeded per "
          "(seed, degradation, severity, episode)).")
    notes = list(summary["notes"]) + list(meta.get("notes", []))
    if notes:
        doc.h(2, "Notes")
        doc.p("\n".join(f"- {n}" for n in notes))
    (out / "REPORT.md").write_text(doc.markdown())
    (out / "report.html").write_text(doc.html("torcsrl robustness report"))
    files = [str(out / f) for f in ("robustness.json", "robustness.csv", "robustness_summary.csv", "REPORT.md", "report.html",
                                    "nr_heatmap.png", "severity_curves.png")]
    return {"summary": summary, "files": files, "summary_line": line.replace("**", "")}


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------
def default_policies() -> tuple[list[str], str | None]:
    """(policy specs, note): the shipped reference driver, or the expert until it ships."""
    if REFERENCE_POLICY.is_file():
        return ["reference"], None
    return ["expert"], (f"note: the shipped reference driver {REFERENCE_POLICY} does not exist yet; reporting on the scripted "
                        "expert instead (it reads only 'state' + its map, so rangefinder degradations cannot affect it)")


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
                 random_max_steps=args.random_max_steps)
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
                       random_max_steps=args.random_max_steps, workers=args.workers, n_boot=args.n_boot)
    cache = args.cache or (None if args.out else Path("outputs") / "report" / "cells")
    return run_report(cfg, out, cache)


def expand_degradations(names: Sequence[str]) -> list[str]:
    """Names, with the groups ``all-rangefinder``, ``all-state``, ``all-camera``, ``heldout`` expanded."""
    out: list[str] = []
    for n in names:
        if n.startswith("all-") or n == "heldout":
            try:
                from torcsrl.transforms import registry
            except ImportError as err:
                raise EvalError(f"degradation groups need torcsrl.transforms ({err})") from None
            out += registry.degradation_names(heldout=True) if n == "heldout" else registry.degradation_names(n[4:])
        else:
            out.append(n)
    return list(dict.fromkeys(out))


if __name__ == "__main__":
    sys.exit(main())
