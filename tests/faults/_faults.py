"""Shared helpers of the fault-injection suite: composed configs, CLI runs, process checks.

Every test here injects one fault a careful user or an operator meets (a signal, a corrupt file, a
nonsense value, a folder that cannot be written) and checks the framework's answer: one line saying
what is wrong and what is allowed, no orphaned process, nothing corrupted silently.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from _compose import compose_config

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}


def cfg_for(*overrides: str, toy: bool = True):
    """A composed training config, shrunk by ``debug=smoke`` (on the toy env unless ``toy=False``)."""
    return compose_config(*(["env=toy"] if toy else []), "debug=smoke", *overrides)


def run_cli(module: str, *args: str, timeout: float = 300, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``python -m <module> <args>``; stdout and stderr captured as text."""
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd or ROOT, env=ENV, capture_output=True, text=True,
                          timeout=timeout)


def one_line_error(proc: subprocess.CompletedProcess, prog: str) -> str:
    """The error line of a CLI that failed as it should: exit status 2, no traceback, one ``<prog>: error:`` line."""
    err = proc.stderr
    assert "Traceback" not in err, err[-3000:]
    assert proc.returncode == 2, (proc.returncode, err[-3000:])
    lines = [ln for ln in err.splitlines() if f"{prog}: error:" in ln]
    assert len(lines) == 1, err[-3000:]
    return lines[0]


def run_main(main, argv: list[str], capsys) -> tuple[int, str]:
    """An entry point's ``main(argv)`` in this process (no interpreter start-up): (exit status, stderr)."""
    capsys.readouterr()
    rc = main(argv)
    return rc, capsys.readouterr().err


def one_line(rc: int, err: str, prog: str) -> str:
    """:func:`one_line_error` for an in-process :func:`run_main`."""
    assert "Traceback" not in err, err[-3000:]
    assert rc == 2, (rc, err[-3000:])
    lines = [ln for ln in err.splitlines() if f"{prog}: error:" in ln]
    assert len(lines) == 1, err[-3000:]
    return lines[0]


def descendants(pid: int) -> list[int]:
    """Every live process whose ancestry includes ``pid`` (read from /proc)."""
    parents: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            parents[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    out, frontier = [], [pid]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parents.items() if pp == p]
        out += kids
        frontier += kids
    return out


def alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"
