"""Fault soak: kill training and report runs at random points, resume them, and check they end where the
uninterrupted runs end; count leftover processes and record memory.

    python benchmarks/fault_soak.py [--train-kills 12] [--report-kills 8] [--seed 0]

Training (toy env, in-process collector, 1500 frames, checkpoints every 200, disk replay buffer): one uninterrupted
reference run, then per trial a fresh run killed with SIGKILL or SIGTERM (alternating) after a random delay
(uniform from half the reference's start-up time to 85 % of its wall time), then ``checkpoint.resume=latest`` to the end (or a fresh
``overwrite=true`` run when the kill came before the first checkpoint). The final checkpoint's networks,
optimisers and counters, and the CSV logs (but the wall-clock ones), must equal the reference's bit for bit.

Report (heuristic driver on the oval, 2 degradations x severities 0 1 3, ``--workers 2``): one uninterrupted
reference, then per trial a fresh report killed at a random point (before 85 % of the reference's wall time) and re-run into the same ``--out`` (finished
cells come from the cache); the episode rows and the summary must equal the reference's.

After every kill it waits up to 20 s and counts the killed run's processes (workers, resource tracker) still
alive: they are leftovers. A SIGTERM that lands during interpreter start-up, before the entry point installs its
handler, ends the process with the default action (exit code -15; nothing was started yet). It prints the peak RSS of each run's process tree [MiB] and the figures.
Run it from the repository root (the subprocesses run ``python -m torcsrl...`` there, so they import this checkout).
"""

from __future__ import annotations

import argparse
import csv
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore", "PYTHONPATH": str(ROOT)}
TRAIN = ["env=toy", "debug=smoke", "total_frames=1500", "checkpoint.every_frames=200", "buffer.storage=disk", "progress=false"]
REPORT = ["--policy", "heuristic", "--tracks", "oval", "--degradations", "rangefinder.noise", "state.noise",
          "--severities", "0", "1", "3", "--workers", "2", "--max-steps", "300", "--n-boot", "200"]


# ------------------------------------------------------------------------------------------ processes
def _tree(pid: int) -> list[int]:
    parents = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parents[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError):
                pass
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parents.items() if pp == p]
        out += kids
        todo += kids
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _rss_mib(pids: list[int]) -> float:
    total = 0
    for p in pids:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            pass
    return total / 1024.0


class Run:
    """A ``python -m <module>`` subprocess whose process tree is watched (peak RSS, members seen)."""

    def __init__(self, module: str, args: list[str], log: Path) -> None:
        self.log = open(log, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", module, *args], cwd=ROOT, env=ENV, stdout=self.log, stderr=self.log)
        self.seen: set[int] = set()
        self.peak_mib = 0.0
        self.t0 = time.monotonic()
        self.log_path = log
        self.t_marker: float | None = None  # seconds until the log first held the marker (see wait)

    def watch(self) -> None:
        kids = _tree(self.proc.pid)
        self.seen.update(kids)
        self.peak_mib = max(self.peak_mib, _rss_mib([self.proc.pid, *kids]))

    def wait(self, timeout_s: float = 900.0, marker: str | None = None) -> int:
        deadline = time.monotonic() + timeout_s
        while self.proc.poll() is None:
            self.watch()
            if marker and self.t_marker is None and marker in self.log_path.read_text(errors="replace"):
                self.t_marker = time.monotonic() - self.t0
            if time.monotonic() > deadline:
                self.proc.kill()
                raise RuntimeError(f"{self.proc.args} did not finish within {timeout_s} s")
            time.sleep(0.1)
        self.log.close()
        return self.proc.returncode

    def run_for(self, seconds: float) -> bool:
        """Watch for ``seconds``; False when the run ended on its own first."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                return False
            self.watch()
            time.sleep(0.05)
        return True

    def kill(self, sig: int) -> tuple[int, int]:
        """Send ``sig``; (return code, leftover processes 20 s later); leftovers are then SIGKILLed."""
        self.watch()
        self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self.log.close()
        deadline = time.monotonic() + 20
        while any(_alive(p) for p in self.seen) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = [p for p in self.seen if _alive(p)]
        for p in left:
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass
        return rc, len(left)


# ------------------------------------------------------------------------------------------ comparisons
def _csv_rows(run_dir: Path) -> dict[str, list]:
    """Every CSV log but the wall-clock ones (scalars/time/: steps/s, elapsed and CPU seconds)."""
    logs = run_dir / "logs"
    return {str(f.relative_to(logs)): f.read_text().splitlines() for f in sorted(logs.rglob("*.csv"))
            if "time" not in f.relative_to(logs).parts}


def _final_state(run_dir: Path):
    import torch

    from torcsrl.utils.checkpoint import latest_checkpoint, load_checkpoint

    ck = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    return {k: ck[k] for k in ("loss", "optim", "counters", "policy")}


def _equal(a, b) -> bool:
    import torch

    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b


def _report_rows(out: Path) -> tuple[list, list]:
    def rows(f: Path) -> list:
        with open(f) as fh:
            return sorted(tuple(r) for r in csv.reader(fh))
    return rows(out / "robustness.csv"), rows(out / "robustness_summary.csv")


# ------------------------------------------------------------------------------------------ trials
def train_trials(n: int, work: Path, rng: random.Random, figures: dict) -> None:
    ref = Run("torcsrl.train", [*TRAIN, f"run_dir={work / 'train_ref'}", f"hydra.run.dir={work / 'hydra'}"], work / "train_ref.log")
    assert ref.wait(marker="[torcsrl] training") == 0, (work / "train_ref.log").read_text()[-2000:]
    wall = time.monotonic() - ref.t0
    start = ref.t_marker or 0.0  # interpreter start-up and building: the kill points are drawn mostly after it
    figures["train_ref_wall_s"] = wall
    figures["peak_rss_mib"].append(ref.peak_mib)
    ref_state, ref_csv = _final_state(work / "train_ref"), _csv_rows(work / "train_ref")
    for i in range(n):
        sig = (signal.SIGKILL, signal.SIGTERM)[i % 2]
        d = work / f"train_{i}"
        delay = rng.uniform(0.5 * start, 0.85 * wall)
        for _ in range(3):  # a run that ends before its kill point is started again, killed earlier
            shutil.rmtree(d, ignore_errors=True)
            run = Run("torcsrl.train", [*TRAIN, f"run_dir={d}", f"hydra.run.dir={work / 'hydra'}"], work / f"train_{i}.log")
            if run.run_for(delay):
                rc, left = run.kill(sig)
                figures["kills"][signal.Signals(sig).name] += 1
                figures["leftover_processes"] += left
                figures["train_rc"].setdefault(signal.Signals(sig).name, set()).add(rc)
                figures["peak_rss_mib"].append(run.peak_mib)
                break
            run.wait()
            figures["train_ended_before_kill"] += 1
            delay *= 0.6
        has_ckpt = any((d / "checkpoints").glob("ckpt_*.pt")) if (d / "checkpoints").is_dir() else False
        resume = ["checkpoint.resume=latest"] if has_ckpt else ["overwrite=true"]
        again = Run("torcsrl.train", [*TRAIN, f"run_dir={d}", f"hydra.run.dir={work / 'hydra'}", *resume], work / f"train_{i}_resume.log")
        rc = again.wait()
        figures["peak_rss_mib"].append(again.peak_mib)
        same = rc == 0 and _equal(_final_state(d), ref_state) and _csv_rows(d) == ref_csv
        figures["train_equal"] += int(same)
        figures["train_trials"] += 1
        print(f"  train trial {i}: {signal.Signals(sig).name} after {delay:.1f} s, resumed {'from a checkpoint' if has_ckpt else 'afresh'}: "
              f"{'equal' if same else 'DIFFERENT (rc %d)' % rc}", flush=True)
        if same:
            shutil.rmtree(d, ignore_errors=True)


def report_trials(n: int, work: Path, rng: random.Random, figures: dict) -> None:
    ref = Run("torcsrl.report", [*REPORT, "--out", str(work / "report_ref")], work / "report_ref.log")
    assert ref.wait() == 0, (work / "report_ref.log").read_text()[-2000:]
    wall = time.monotonic() - ref.t0
    figures["report_ref_wall_s"] = wall
    figures["peak_rss_mib"].append(ref.peak_mib)
    want = _report_rows(work / "report_ref")
    for i in range(n):
        sig = (signal.SIGTERM, signal.SIGKILL)[i % 2]
        out = work / f"report_{i}"
        delay = rng.uniform(0.3, 0.85 * wall)
        for _ in range(3):  # a run that ends before its kill point is started again, killed earlier
            shutil.rmtree(out, ignore_errors=True)
            run = Run("torcsrl.report", [*REPORT, "--out", str(out)], work / f"report_{i}.log")
            if run.run_for(delay):
                rc, left = run.kill(sig)
                figures["kills"][signal.Signals(sig).name] += 1
                figures["leftover_processes"] += left
                figures["report_rc"].setdefault(signal.Signals(sig).name, set()).add(rc)
                figures["peak_rss_mib"].append(run.peak_mib)
                break
            run.wait()
            figures["report_ended_before_kill"] += 1
            delay *= 0.6
        cached = len(list((out / "cells").glob("*.json"))) if (out / "cells").is_dir() else 0
        again = Run("torcsrl.report", [*REPORT, "--out", str(out)], work / f"report_{i}_rerun.log")
        rc = again.wait()
        figures["peak_rss_mib"].append(again.peak_mib)
        same = rc == 0 and _report_rows(out) == want
        figures["report_equal"] += int(same)
        figures["report_trials"] += 1
        print(f"  report trial {i}: {signal.Signals(sig).name} after {delay:.1f} s ({cached} cells kept), re-run: "
              f"{'equal' if same else 'DIFFERENT (rc %d)' % rc}", flush=True)
        if same:
            shutil.rmtree(out, ignore_errors=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train-kills", type=int, default=12)
    ap.add_argument("--report-kills", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one, removed at the end)")
    a = ap.parse_args(argv)
    rng = random.Random(a.seed)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="fault_soak_"))
    work.mkdir(parents=True, exist_ok=True)
    figures = {"kills": {"SIGKILL": 0, "SIGTERM": 0}, "leftover_processes": 0, "peak_rss_mib": [], "train_trials": 0, "train_equal": 0,
               "report_trials": 0, "report_equal": 0, "train_ended_before_kill": 0, "report_ended_before_kill": 0,
               "train_rc": {}, "report_rc": {}}
    t0 = time.monotonic()
    print(f"fault soak: {a.train_kills} training trials, {a.report_kills} report trials, seed {a.seed}, scratch {work}", flush=True)
    train_trials(a.train_kills, work, rng, figures)
    report_trials(a.report_kills, work, rng, figures)
    f = figures
    kills = f["kills"]["SIGKILL"] + f["kills"]["SIGTERM"]
    print(f"kills: {kills} ({f['kills']['SIGKILL']} SIGKILL, {f['kills']['SIGTERM']} SIGTERM; "
          f"{f['train_ended_before_kill'] + f['report_ended_before_kill']} runs ended before their kill point and were run again)")
    print(f"exit codes: train {dict((k, sorted(v)) for k, v in f['train_rc'].items())}, "
          f"report {dict((k, sorted(v)) for k, v in f['report_rc'].items())}")
    print(f"training: {f['train_equal']}/{f['train_trials']} resumed runs equal the uninterrupted one "
          f"(networks, optimisers, counters, CSV logs; reference {f['train_ref_wall_s']:.1f} s)")
    print(f"report: {f['report_equal']}/{f['report_trials']} re-runs equal the uninterrupted one "
          f"(episode rows and summary; reference {f['report_ref_wall_s']:.1f} s)")
    print(f"leftover processes after kills: {f['leftover_processes']}")
    rss = f["peak_rss_mib"]
    print(f"peak RSS of a run's process tree: median {sorted(rss)[len(rss) // 2]:.0f} MiB, max {max(rss):.0f} MiB over {len(rss)} runs")
    print(f"wall {time.monotonic() - t0:.0f} s")
    ok = f["train_equal"] == f["train_trials"] and f["report_equal"] == f["report_trials"] and f["leftover_processes"] == 0
    if not a.work and ok:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
