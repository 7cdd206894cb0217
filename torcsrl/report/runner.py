"""Running a report's grid: every cell's episodes (batched as cars of one env per policy and track, in worker
processes or as Ray tasks), each cell cached as one JSON file, then the report (:mod:`torcsrl.report.results`)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import math
import multiprocessing as mp
import os
import socket
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torcsrl import metrics
from torcsrl.envs import tracks as _tracks
from torcsrl.evaluate.batched import run_batch, supports_batch
from torcsrl.evaluate.protocol import check_policy_env, run_cell
from torcsrl.evaluate.results import write_json
from torcsrl.evaluate.spec import Degradation, EvalError, parse_degradation, validate_grid
from torcsrl.evaluate.workers import worker_init, worker_policy
from torcsrl.policies import BUILTIN_POLICIES, REFERENCE_POLICY, Policy, load_policy
from torcsrl.report.grid import RANDOM, Cell, ReportConfig, check_counts, code_hash, default_workers, stable_hash
from torcsrl.report.results import build_report
from torcsrl.utils.faults import OutputError, stop_pool, writable_folder
from torcsrl.utils.ray_session import RayError, check_address, ray_session

__all__ = ["default_policies", "plan_tasks", "prepare", "run_report"]


def _cell_degradation(cell: Cell) -> Degradation | None:
    return Degradation(cell.corruption, cell.severity, cell.params) if cell.corruption != metrics.CLEAN else None


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _run_group_task(cells: Sequence[Cell], policy: Any, cfg: dict[str, Any], config_hash: str,
                    paths: Sequence[str | None], max_cars: int | None = None) -> list[dict[str, Any]]:
    """Run cells that share a policy, a track and a surface as cars of one env (in a worker), write each
    cell's JSON atomically (the same record as :func:`_run_cell_task` would write; not where its path is
    None); returns the records."""
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
    refs): one torch thread, as :func:`~torcsrl.evaluate.workers.worker_init` gives a pool worker; the worker's episode code must be
    the driver's (a cluster node with other torcsrl sources would fill the cache with other episodes). It
    writes no file: the driver writes the cache (the worker may be another machine)."""
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
    return {"cells": cells, "reused": reused, "batchable": {p.name for p in pols if supports_batch(p)}, "policies": [p.name for p in pols], "policy_info": {p.name: p.describe() for p in pols},
            "reference": ref_name, "tracks": tracks, "surfaces": surfaces, "degradations": [d.name for d in degs], "severities": sev}


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
    config_hash = stable_hash(ccfg)[:16]
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
            ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=worker_init)
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
