"""Start-up time of the command lines: ``--help`` and a bad argument must answer at once, before any heavy import.

    python benchmarks/startup.py [--ref 622f515] [--runs 3]

Each command runs as a fresh subprocess, ``--runs`` times after one untimed warm-up run (which writes the ``.pyc``
files of a fresh tree); the table holds the median wall time [s]. With ``--ref <git-rev>`` the same commands also run in a ``git worktree`` of that
revision (imported from there through ``PYTHONPATH``), interleaved with this tree's runs so a load on the machine
weighs on both alike, and the ratio ref / this tree is printed. ``rc`` is this tree's exit status (a bad argument: 2,
or 1 where Hydra itself refuses an override); ``banner`` says whether the output held pybullet's build banner.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: (label, arguments after ``python``) of every command timed.
COMMANDS: list[tuple[str, list[str]]] = [
    ("import torcsrl", ["-c", "import torcsrl"]),
    ("evaluate --help", ["-m", "torcsrl.evaluate", "--help"]),
    ("report --help", ["-m", "torcsrl.report", "--help"]),
    ("train --help", ["-m", "torcsrl.train", "--help"]),
    ("evaluate --laps many", ["-m", "torcsrl.evaluate", "--laps", "many"]),
    ("report --episodes 0", ["-m", "torcsrl.report", "--episodes", "0"]),
    ("train algo=nope", ["-m", "torcsrl.train", "algo=nope"]),
]
BANNER = "pybullet build time"


def run_once(args: list[str], tree: Path, timeout_s: float) -> tuple[float, int, bool]:
    """(wall time [s], exit status, banner seen) of ``python <args>`` run in ``tree`` with ``tree`` first on the path."""
    env = dict(os.environ, PYTHONPATH=str(tree) + os.pathsep + os.environ.get("PYTHONPATH", ""), HYDRA_FULL_ERROR="0")
    t0 = time.perf_counter()
    try:
        out = subprocess.run([sys.executable, *args], cwd=tree, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return float("inf"), -1, False
    wall = time.perf_counter() - t0
    return wall, out.returncode, BANNER in out.stdout or BANNER in out.stderr


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", help="a git revision to time side by side (e.g. 622f515)")
    ap.add_argument("--runs", type=int, default=3, help="timed runs per command and tree (the median is shown)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds before a run counts as hung")
    a = ap.parse_args(argv)

    trees: dict[str, Path] = {"this tree": ROOT}
    tmp = None
    if a.ref:
        tmp = tempfile.mkdtemp(prefix="torcsrl-startup-")
        ref_dir = Path(tmp) / "ref"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(ref_dir), a.ref], check=True)
        trees = {f"ref {a.ref}": ref_dir, "this tree": ROOT}
    try:
        times: dict[tuple[str, str], list[float]] = {}
        last: dict[tuple[str, str], tuple[int, bool]] = {}
        for label, args in COMMANDS:  # warm-up: .pyc files, Hydra's and numba's caches
            for name, tree in trees.items():
                run_once(args, tree, a.timeout)
        for _ in range(a.runs):
            for label, args in COMMANDS:
                for name, tree in trees.items():
                    wall, rc, banner = run_once(args, tree, a.timeout)
                    times.setdefault((label, name), []).append(wall)
                    last[(label, name)] = (rc, banner)
    finally:
        if tmp is not None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(Path(tmp) / "ref")], check=False)

    names = list(trees)
    head = f"{'command':<24}" + "".join(f"{n + ' [s]':>18}" for n in names) + (f"{'ratio':>8}" if a.ref else "")
    head += f"{'rc':>5}{'banner':>8}"
    print(f"median of {a.runs} runs, python {sys.version.split()[0]}, {os.cpu_count()} CPUs")
    print(head)
    print("-" * len(head))
    for label, _ in COMMANDS:
        med = [statistics.median(times[(label, n)]) for n in names]
        row = f"{label:<24}" + "".join(f"{m:>18.2f}" for m in med)
        if a.ref:
            row += f"{med[0] / med[1]:>7.1f}x"
        rc, banner = last[(label, "this tree")]
        print(row + f"{rc:>5}{'yes' if banner else 'no':>8}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
