"""Thread policy: how many intra-op threads torch gets, from the cores and the env workers.

Small networks (256x256, batch 256) gain little past a few threads, and on a small box the
learner's threads compete with env worker processes and with anything else running: measured on
the project's 2-core machine, 2 learner threads ran 1.8x faster than 1 when idle but collapsed
below 1 thread's speed as soon as another process was busy (the whole TD3 loop on Pendulum,
``benchmarks/train_throughput.py``: 1.4-1.5x with the second core free, 8-100 steps/s instead of
~80 with other jobs running). The policy:

* ``threads: <int>`` is taken as given;
* ``threads: auto`` -> ``cores - env_workers - 1`` (one core left for the collector/OS),
  clamped to [1, 8]; on machines with 2 cores or fewer it is 1.

The count is fixed for a run (and stored in its checkpoints): float reductions depend on it,
so an exact resume needs the same count.
"""

from __future__ import annotations

import os

import torch

MAX_AUTO_THREADS = 8


def available_cores() -> int:
    """Cores this process may run on (affinity mask aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def resolve_threads(threads: int | str, env_workers: int = 0, cores: int | None = None) -> int:
    """The thread count the policy gives (see the module docstring); bad values raise one clear line."""
    if isinstance(threads, str):
        if threads != "auto":
            raise ValueError(f"threads must be an integer >= 1 or 'auto', got {threads!r}")
        cores = available_cores() if cores is None else cores
        if cores <= 2:
            return 1
        return max(1, min(MAX_AUTO_THREADS, cores - int(env_workers) - 1))
    if int(threads) < 1:
        raise ValueError(f"threads must be an integer >= 1 or 'auto', got {threads!r}")
    return int(threads)


def configure_threads(threads: int | str, env_workers: int = 0) -> int:
    """Apply the policy to torch (intra-op threads; inter-op stays at 1 where still settable). Returns the count."""
    n = resolve_threads(threads, env_workers)
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set once in this process
        pass
    return n


def process_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) that process ``pid`` has used so far, from ``/proc/<pid>/stat``; 0.0 where that cannot
    be read (not Linux, the process has ended). For the CPU time of worker processes, which ``time.process_time`` of
    their parent does not include (nor ``RUSAGE_CHILDREN`` while they run)."""
    try:
        with open(f"/proc/{int(pid)}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15 of stat)
    except (OSError, ValueError, IndexError):
        return 0.0
