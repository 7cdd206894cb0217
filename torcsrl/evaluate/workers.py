"""Worker processes of evaluate and report: a pool of spawned processes (one torch thread each), and the policy a task
names, loaded once per process."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from torcsrl.policies import BUILTIN_POLICIES, Policy, load_policy
from torcsrl.utils.faults import ignore_signals_in_worker, stop_pool

__all__ = ["map_tasks", "worker_init", "worker_policy", "worker_spec"]

_POLICIES: dict[str, Policy] = {}


def worker_policy(policy: str | Policy) -> Policy:
    """The policy a task names: loaded once per process from its spec (see :func:`worker_spec`), or the object."""
    if isinstance(policy, str):
        if policy not in _POLICIES:
            _POLICIES[policy] = load_policy(policy)
        return _POLICIES[policy]
    return policy


def worker_spec(pol: Policy) -> str | Policy:
    """What a worker process gets for ``pol``: its spec where the spec loads it again (a built-in name or a file),
    else the policy object itself."""
    return pol.spec if pol.spec in BUILTIN_POLICIES or Path(pol.spec).is_file() else pol


def worker_init() -> None:
    """A pool worker's start: one torch thread; Ctrl-C is the parent's to handle."""
    torch.set_num_threads(1)
    ignore_signals_in_worker()


def map_tasks(fn: Callable[..., Any], tasks: Sequence[tuple], workers: int = 1):
    """``fn(*task)`` for every task, in order: in this process (workers <= 1) or in a pool of
    ``workers`` spawned processes (one torch thread each)."""
    workers = max(1, min(int(workers), len(tasks)))
    if workers == 1:
        for t in tasks:
            yield fn(*t)
        return
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=worker_init) as ex:
        futs = [ex.submit(fn, *t) for t in tasks]
        try:
            for f in futs:
                yield f.result()
        except BaseException:  # a signal (Interrupted), a failed task, or the consumer stopped early (GeneratorExit)
            stop_pool(ex)
            raise
