"""Reliability helpers shared by the entry points: one-line answers to faults.

- :func:`writable_folder` / :class:`OutputError`: a folder that cannot be created or written (a path
  through a file, no permission, a full disk) fails before any work, in one line naming it.
- :func:`os_error_line`: an ``OSError`` met while writing (a disk that fills up mid-run) as one line;
  :func:`cli_error`: what an entry point prints and returns for an error it expects, an ``OSError`` or a stop.
- :func:`graceful_termination`: SIGTERM (what ``kill``, ``timeout`` and job schedulers send) ends a run
  like Ctrl-C does, so its ``finally`` blocks stop the worker processes; the entry points then print one
  line and exit with 128 + the signal number.
  :func:`stop_pool` terminates a process pool's workers; :func:`ignore_signals_in_worker` (pool initialisers)
  leaves Ctrl-C to the parent and ends a worker when its parent dies, SIGKILL included (Linux).
- :func:`claim_run_dir`: one run per run folder (a lock), and no fresh run into a folder holding another run
  unless it resumes it or ``overwrite`` is asked for.
- :func:`file_digest`: SHA-256 of a file, for replay-buffer checksums.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import shutil
import signal
import sys
import uuid
from pathlib import Path


class OutputError(ValueError):
    """An output that cannot be written (one-line message naming the path)."""


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT or SIGTERM); ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def os_error_line(err: OSError, doing: str = "cannot write") -> str:
    """``"cannot write <path>: <reason>; allowed: ..."`` for an ``OSError`` met while writing outputs."""
    where = err.filename if err.filename is not None else "the output"
    reason = err.strerror or str(err)
    return f"{doing} {where}: {reason}; allowed: a folder this user can write, on a disk with free space"


def writable_folder(path: str | Path, what: str) -> Path:
    """Create ``path`` (and parents) and write a probe file in it; :class:`OutputError` naming ``what``
    (e.g. ``"run_dir"``) and the path when that fails."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".torcsrl-write-probe-{uuid.uuid4().hex[:8]}"
        with open(probe, "wb") as f:
            f.write(b"ok")
        probe.unlink()
    except OSError as err:
        raise OutputError(f"{what}: " + os_error_line(err)) from None
    return path


def _raise_interrupted(signum, frame):  # noqa: ARG001 - signal handler signature
    raise Interrupted(signum)


@contextlib.contextmanager
def graceful_termination(signals=(signal.SIGTERM, signal.SIGINT)):
    """Within the block, SIGTERM and SIGINT raise :class:`Interrupted` (a KeyboardInterrupt) in the main
    thread, so ``try/finally`` blocks shut process pools and collectors down; the previous handlers are
    restored after. Outside the main thread it does nothing."""
    old = {}
    try:
        for s in signals:
            old[s] = signal.signal(s, _raise_interrupted)
    except ValueError:  # not the main thread
        for s, h in old.items():
            signal.signal(s, h)
        yield
        return
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def cli_error(prog: str, err: BaseException, stopped: str = "") -> int:
    """Print ``err`` on stderr as the one line ``<prog>: error: ...`` and return the process exit code: a stop
    (Ctrl-C, or SIGTERM under :func:`graceful_termination`) as ``stopped by <signal>; <stopped>`` with 128 + the
    signal number, an ``OSError`` through :func:`os_error_line`, anything else (the entry point's own one-line
    errors) as its message, with 2."""
    if isinstance(err, KeyboardInterrupt):
        line = f"stopped by {getattr(err, 'name', 'SIGINT')}" + (f"; {stopped}" if stopped else "")
    elif isinstance(err, OSError):
        line = os_error_line(err)
    else:
        line = str(err)
    print(f"{prog}: error: {line}", file=sys.stderr)
    return exit_code(err)


def exit_code(err: BaseException) -> int:
    """128 + the signal number for :class:`Interrupted` (130 for Ctrl-C, 143 for SIGTERM), else 2."""
    return 128 + err.signum if isinstance(err, Interrupted) else (130 if isinstance(err, KeyboardInterrupt) else 2)


def file_digest(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of the file at ``path``."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def ignore_signals_in_worker() -> None:
    """For pool initialisers: a worker ignores SIGINT (Ctrl-C reaches the whole process group; the
    parent decides and shuts the pool down) and dies with its parent on Linux."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent()


def die_with_parent() -> None:
    """Linux: SIGTERM this process when its parent dies (``PR_SET_PDEATHSIG``), so that a SIGKILLed run
    leaves no orphaned worker behind. Elsewhere: nothing."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        if os.getppid() == 1:  # the parent is already gone
            os.kill(os.getpid(), signal.SIGTERM)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def stop_pool(ex, timeout_s: float = 10.0) -> None:
    """Stop a ``concurrent.futures.ProcessPoolExecutor`` now: cancel what has not started, terminate the
    worker processes (a running task is abandoned; finished results were already handed back) and
    reap them, so no worker outlives the run."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout_s)
        if p.is_alive():
            p.kill()
            p.join(timeout_s)
    # the pool's manager thread notices its workers gone and closes its wake-up pipe; wait for it, or the interpreter's
    # exit hook (concurrent.futures.process._python_exit) can write to that pipe as it closes (EBADF, a traceback)
    manager = getattr(ex, "_executor_manager_thread", None)
    if manager is not None and manager.is_alive():
        manager.join(timeout_s)


# ---------------------------------------------------------------------------------------------
# run folders: one run at a time, and no silent mixing with an older run
# ---------------------------------------------------------------------------------------------
LOCK_NAME = ".torcsrl.lock"
#: What a run folder may hold before a new run starts in it: Hydra's own records of this very run.
_FRESH_OK = {LOCK_NAME, ".hydra", "train.log"}
_HELD: dict[str, list] = {}  # resolved run_dir -> [fd, depth]: the locks this process holds


class RunDirError(ValueError):
    """A run folder that is in use by another run, or holds an older run (one-line message)."""


@contextlib.contextmanager
def claim_run_dir(run_dir: str | Path, *, resume: bool = False, overwrite: bool = False):
    """Hold ``run_dir`` for one run: an exclusive ``flock`` on ``<run_dir>/.torcsrl.lock`` (released by the
    kernel when the process ends, SIGKILL included), and a refusal to start a fresh run in a folder that holds
    another run's files unless ``resume`` (continue it) or ``overwrite`` (delete them first). Re-entrant within
    one process (``python -m torcsrl.train`` claims the folder before writing config.yaml, then ``train`` again)."""
    import fcntl  # deferred: POSIX only (the module imports on any platform)

    run_dir = writable_folder(run_dir, "run_dir")
    key = str(run_dir.resolve())
    if key in _HELD:
        _HELD[key][1] += 1
        try:
            yield run_dir
        finally:
            _HELD[key][1] -= 1
        return
    fd = os.open(run_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise RunDirError(f"run_dir {run_dir} is in use by another run (pid {holder}); allowed: another run_dir, or wait "
                          "until that run ends") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        old = sorted(p.name for p in run_dir.iterdir() if p.name not in _FRESH_OK)
        if old and overwrite:
            for name in old:
                p = run_dir / name
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        elif old and not resume:
            shown = ", ".join(old[:5]) + (", ..." if len(old) > 5 else "")
            raise RunDirError(f"run_dir {run_dir} already holds a run ({shown}); allowed: checkpoint.resume=latest to continue "
                              "it, overwrite=true to replace it, or an empty or new run_dir")
        _HELD[key] = [fd, 1]
    except BaseException:
        os.close(fd)
        raise
    try:
        yield run_dir
    finally:
        _HELD.pop(key, None)
        os.close(fd)  # releases the flock
