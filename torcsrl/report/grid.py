"""The grid of a robustness report: its config, its cells, and running them (batched as cars, cached)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import hashlib
import json
import math
import multiprocessing as mp
import os
import socket
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torcsrl import metrics
from torcsrl.evaluate import (PROTOCOL_VERSION, Degradation, EvalError, check_policy_env, parse_degradation, run_cell, validate_grid,
                              write_json)
from torcsrl.evaluate.app import worker_policy
from torcsrl.policies import BUILTIN_POLICIES, REFERENCE_POLICY, Policy, load_policy
from torcsrl.utils.faults import OutputError, ignore_signals_in_worker, stop_pool, writable_folder
from torcsrl.utils.ray_session import RayError, check_address, ray_session

__all__ = [  # this module's own names (the package re-exports them with results' and app's)
    "DEFAULT_DEGRADATIONS",
    "DEFAULT_TRACKS",
    "DEFAULT_SEVERITIES",
    "EFFECT_FAMILIES",
    "Cell",
    "ReportConfig",
    "prepare",
    "run_report",
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
    make_env keywords; ``workers``: processes (None: min(4, CPUs), or on a Ray cluster its CPUs);
    ``n_boot``: bootstrap resamples; ``batch_cars``: up to
    this many episodes of the cells that share a policy and a track drive as cars of one env
    (:func:`torcsrl.evaluate.batched.run_batch`, the same episodes as one car at a time; 1 = one car
    at a time; policies that cannot drive a batch always drive one car at a time); ``ray``: None (cells
    run in this process or in ``workers`` processes), or the Ray address the cells run on as Ray tasks
    (``local``: a Ray instance of ``workers`` CPUs started here; ``auto``; ``host:port``; ``ray://host:port``:
    :mod:`torcsrl.utils.ray_session`) — the same cells, cache and report either way."""

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
    workers: int | None = 1
    n_boot: int = 1000
    batch_cars: int = 128
    ray: str | None = None

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
    tracks), ``torcsrl/transforms`` (degradations) and ``torcsrl/evaluate/`` (the episode protocol); read
    once per process."""
    root = Path(__file__).resolve().parents[1]
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


def _worker_init() -> None:
    import torch

    torch.set_num_threads(1)
    ignore_signals_in_worker()


def _cell_degradation(cell: Cell) -> Degradation | None:
    return Degradation(cell.corruption, cell.severity, cell.params) if cell.corruption != metrics.CLEAN else None


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _run_group_task(cells: Sequence[Cell], policy: Any, cfg: dict[str, Any], config_hash: str,
                    paths: Sequence[str | None], max_cars: int | None = None) -> list[dict[str, Any]]:
    """Run cells that share a policy, a track and a surface as cars of one env (in a worker), write each
    cell's JSON atomically (the same record as :func:`_run_cell_task` would write; not where its path is
    None); returns the records."""
    from torcsrl.evaluate.batched import run_batch

    t0 = time.perf_counter()
    pol = worker_policy(policy)
    pol.name = cells[0].policy
    c0 = cells[0]
    out = run_batch(pol, c0.track, None if c0.own_surface else c0.surface, [_cell_degradation(c) for c in cells],
                    episodes=cfg["episodes"], laps=cfg["laps"], seed=cfg["seed"], max_steps=cfg["max_steps"],
                    env_kwargs=cfg["env_kwargs"], max_cars=max_cars)
    wall = time.perf_counter() - t0
    records = []
    for cell, rows, path in zip(cells, out, paths):
        record = {"key": cell.key(config_hash), "config_hash": config_hash, "cell": asdict(cell), "config": cfg,
                  "rows": rows, "wall_s": wall / len(cells), "batch_cells": len(cells), "worker": _worker_name(),
                  "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
        if path is not None:
            write_json(record, path)
        records.append(record)
    return records


def _run_cell_task(cell: Cell, policy: Any, cfg: dict[str, Any], config_hash: str, path: str | None) -> dict[str, Any]:
    """Run one cell (in a worker) and write its JSON atomically (not where ``path`` is None); returns the record."""
    t0 = time.perf_counter()
    pol = worker_policy(policy)
    pol.name = cell.policy
    deg = _cell_degradation(cell)
    max_steps = cfg["random_max_steps"] if cell.policy == RANDOM else cfg["max_steps"]
    rows, _ = run_cell(pol, cell.track, None if cell.own_surface else cell.surface, deg, episodes=cfg["episodes"], laps=cfg["laps"], seed=cfg["seed"],
                       max_steps=max_steps, env_kwargs=cfg["env_kwargs"])
    record = {"key": cell.key(config_hash), "config_hash": config_hash, "cell": asdict(cell), "config": cfg,
              "rows": rows, "wall_s": time.perf_counter() - t0, "worker": _worker_name(),
              "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    if path is not None:
        write_json(record, path)
    return record


def _run_task(task: tuple) -> list[tuple[Cell, dict[str, Any]]]:
    """One task of :func:`plan_tasks`: [(cell, record)]."""
    cells, pspec, ccfg, config_hash, paths, max_cars = task
    if len(cells) == 1:
        return [(cells[0], _run_cell_task(cells[0], pspec, ccfg, config_hash, paths[0]))]
    return list(zip(cells, _run_group_task(cells, pspec, ccfg, config_hash, paths, max_cars)))


def _ray_task(policy: Any, task: tuple) -> list[tuple[Cell, dict[str, Any]]]:
    """One task of :func:`plan_tasks` as a Ray task (``policy`` apart: Ray resolves only top-level object
    refs): one torch thread, as :func:`_worker_init` gives a pool worker; the worker's episode code must be
    the driver's (a cluster node with other torcsrl sources would fill the cache with other episodes). It
    writes no file: the driver writes the cache (the worker may be another machine)."""
    import torch

    torch.set_num_threads(1)
    cells, _, ccfg, config_hash, paths, max_cars = task
    if ccfg["code"] != code_hash():
        raise EvalError(f"the Ray worker {_worker_name()} runs other torcsrl episode code (code hash {code_hash()}, this "
                        f"machine's {ccfg['code']}); allowed: the same torcsrl version installed on every node")
    return _run_task((cells, policy, ccfg, config_hash, paths, max_cars))


def _run_on_ray(ray: Any, tasks: Sequence[tuple[list[Cell], Any, list[str]]], ccfg: dict[str, Any], config_hash: str,
                batch_cars: int, done: Any) -> None:
    """Run ``tasks`` as Ray tasks (one CPU each), hand each finished cell to ``done`` after writing its cache
    file here, in the order they finish; on any exception (Ctrl-C, SIGTERM, a failed cell) cancel what is still
    running or queued (finished cells are in the cache already) and re-raise — a failed cell's own exception,
    not Ray's wrapper, so its one line reads as on the local path."""
    remote = ray.remote(_ray_task).options(num_cpus=1)
    shipped: dict[Any, Any] = {}

    def ship(pspec: Any) -> Any:  # a built-in name loads anywhere; a checkpoint travels as the loaded policy
        if isinstance(pspec, str) and pspec in BUILTIN_POLICIES:
            return pspec
        key = pspec if isinstance(pspec, str) else id(pspec)
        if key not in shipped:
            shipped[key] = ray.put(worker_policy(pspec))
        return shipped[key]

    pending: dict[Any, tuple[list[Cell], list[str]]] = {}
    try:
        for cells, pspec, paths in tasks:
            ref = remote.remote(ship(pspec), (cells, None, ccfg, config_hash, [None] * len(cells), batch_cars))
            pending[ref] = (cells, paths)
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)  # a timeout: signal handlers run meanwhile
            for ref in ready:
                cells, paths = pending.pop(ref)
                try:
                    out = ray.get(ref)
                except ray.exceptions.RayTaskError as err:
                    cause = getattr(err, "cause", None)
                    if isinstance(cause, Exception):
                        raise cause from None
                    raise EvalError(f"the Ray task of {cells[0].label()} failed: {_first_line(err)}") from None
                except ray.exceptions.RayError as err:  # a worker or node died (after Ray's retries)
                    raise EvalError(f"the Ray task of {cells[0].label()} failed: {_first_line(err)}") from None
                for (cell, rec), path in zip(out, paths):
                    write_json(rec, path)
                    done(cell, rec)
    except BaseException:
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001 - finished meanwhile, or the cluster is gone: nothing left to stop
                pass
        raise


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0] if text else ''}"


def plan_tasks(todo: Sequence[tuple[Cell, Any, Path]], batchable: set[str], episodes: int, batch_cars: int,
               workers: int = 1) -> list[tuple[list[Cell], Any, list[str]]]:
    """Group the cells to run into tasks: the cells of a batchable policy that share a track and a
    surface become one task (one env of at most ``batch_cars`` cars, refilled cell after cell: see
    :func:`torcsrl.evaluate.batched.run_batch`), split further while there are fewer tasks than
    ``workers``; every other cell (every cell when ``batch_cars`` is 1 or below ``episodes``) is a task of its own."""
    groups: dict[tuple, list[tuple[Cell, Any, Path]]] = {}
    tasks: list[list[tuple[Cell, Any, Path]]] = []
    per = 1 << 30 if int(batch_cars) >= int(episodes) and int(batch_cars) > 1 else 1
    for item in todo:
        cell = item[0]
        if cell.policy in batchable and per > 1 and cell.policy != RANDOM:
            groups.setdefault((cell.policy, cell.track, cell.surface, cell.own_surface), []).append(item)
        else:
            tasks.append([item])
    for items in groups.values():
        tasks += [items[i:i + per] for i in range(0, len(items), per)]
    while len(tasks) < workers:
        big = max(range(len(tasks)), key=lambda i: len(tasks[i]), default=None)
        if big is None or len(tasks[big]) < 2:
            break
        t = tasks.pop(big)
        tasks += [t[:len(t) // 2], t[len(t) // 2:]]
    tasks.sort(key=len, reverse=True)  # the big batches first: they finish last
    return [([c for c, _, _ in t], t[0][1], [str(p) for _, _, p in t]) for t in tasks]


def _eta(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


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
    from torcsrl.evaluate.batched import supports_batch

    return {"cells": cells, "reused": reused, "batchable": {p.name for p in pols if supports_batch(p)}, "policies": [p.name for p in pols], "policy_info": {p.name: p.describe() for p in pols},
            "reference": ref_name, "tracks": tracks, "surfaces": surfaces, "degradations": [d.name for d in degs], "severities": sev}


def default_workers() -> int:
    """Worker processes when ``workers`` is None: min(4, this machine's CPUs)."""
    return max(1, min(4, os.cpu_count() or 1))


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
                 random_max_steps=cfg.random_max_steps, batch_cars=cfg.batch_cars)
    try:
        address = check_address(cfg.ray)
    except RayError as err:
        raise EvalError(str(err)) from None
    plan = prepare(cfg)
    out = Path(out_dir)
    cache = Path(cache_dir) if cache_dir is not None else out / "cells"
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
    done = 0
    ep_total = len(todo) * int(cfg.episodes)

    def _done(cell: Cell, rec: dict[str, Any]) -> None:
        nonlocal done
        done += 1
        rows = rec["rows"]
        lcr = metrics.lap_completion_rate(r["success"] for r in rows)
        el = time.perf_counter() - t_run
        rate = done * int(cfg.episodes) / el if el > 0 else math.inf
        eta = (ep_total - done * int(cfg.episodes)) / rate if rate > 0 else math.inf
        log(f"[{done}/{len(todo)} cells, {rate:.2f} episodes/s, ETA {_eta(eta)}] {cell.label()}: LCR {lcr:.2f}, "
            f"return {np.mean([r['return'] for r in rows]):.0f}")
        records[cell] = rec

    with contextlib.ExitStack() as stack:
        ray = info = None
        if address is not None and todo:  # connect first: an unreachable cluster fails before any folder or episode
            try:
                ray, info = stack.enter_context(ray_session(address, num_cpus=cfg.workers or default_workers()))
            except RayError as err:
                raise EvalError(str(err)) from None
        try:
            writable_folder(out, "--out")
            writable_folder(cache, "--cache")
        except OutputError as err:
            raise EvalError(str(err)) from None
        slots = int(cfg.workers) if cfg.workers is not None else (info.cpus if info is not None else default_workers())
        workers = max(1, min(slots, len(todo) or 1))
        tasks = plan_tasks(todo, plan["batchable"], int(cfg.episodes), int(cfg.batch_cars), workers)
        workers = max(1, min(workers, len(tasks)))
        n_batched = sum(len(c) for c, _, _ in tasks if len(c) > 1)
        where = f"on Ray ({info.describe()})" if info is not None else f"on {workers} worker(s)"
        log(f"{len(plan['cells'])} cells ({n_cached} cached, {len(todo)} to run, {len(plan['reused'])} reuse a clean run) "
            f"in {len(tasks)} task(s) ({n_batched} cells batched as cars) {where}; report -> {out}; cache {cache}")
        t_run = time.perf_counter()
        if ray is not None:
            _run_on_ray(ray, tasks, ccfg, config_hash, int(cfg.batch_cars), _done)
        elif workers == 1:
            for cells, pspec, paths in tasks:
                for cell, rec in _run_task((cells, pspec, ccfg, config_hash, paths, int(cfg.batch_cars))):
                    _done(cell, rec)
        elif tasks:
            ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_worker_init)
            try:
                futs = [ex.submit(_run_task, (cells, pspec, ccfg, config_hash, paths, int(cfg.batch_cars)))
                        for cells, pspec, paths in tasks]
                for fut in cf.as_completed(futs):
                    for cell, rec in fut.result():
                        _done(cell, rec)
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
    from torcsrl.report.results import build_report

    res = build_report(rows, out, policies=plan["policies"], reference=plan["reference"], corruptions=plan["degradations"],
                       severities=plan["severities"], n_boot=cfg.n_boot, seed=cfg.seed, meta=meta, cells=cells_out,
                       verbose=verbose)
    res.update(computed=len(todo), cached=n_cached, reused=len(plan["reused"]), wall_s=time.perf_counter() - t0)
    el = time.perf_counter() - t_run
    log(f"done in {res['wall_s']:.0f} s: {len(todo)} cells run ({ep_total} episodes, "
        f"{ep_total / el if el > 0 and ep_total else 0:.2f} episodes/s), {n_cached} from the cache; report in {out}")
    return res



def default_policies() -> tuple[list[str], str | None]:
    """(policy specs, note): the shipped reference driver, or the expert until it ships."""
    if REFERENCE_POLICY.is_file():
        return ["reference"], None
    return ["expert"], (f"note: the shipped reference driver {REFERENCE_POLICY} does not exist yet; reporting on the scripted "
                        "expert instead (it reads only 'state' + its map, so rangefinder degradations cannot affect it)")



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


