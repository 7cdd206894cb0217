"""Metric logging through TorchRL's loggers, and a console progress line.

Metric names are namespaced (glossary):

* ``train/episode_reward`` sum of rewards of the training episodes that ended in the last batch;
  ``train/episodes`` training episodes finished so far; ``train/laps`` laps of those episodes;
  ``train/buffer_size`` transitions in the replay buffer; ``train/frames`` env steps so far.
* ``eval/reward``, ``eval/laps``, ``eval/lap_time`` [s] (best completed lap, NaN if none),
  ``eval/steps`` — deterministic validation episodes (no noise, no buffer, no updates).
* ``loss/qvalue``, ``loss/actor``, ``loss/pred_value``, ``loss/target_value``, ... — last update.
* ``time/steps_per_s`` env steps per wall-clock second over the last logging window (collection
  and updates together); ``time/updates_per_s``; ``time/elapsed_s`` wall-clock seconds since the
  run (or resume) started; ``time/cpu_s`` CPU seconds this process used in that time (all its
  threads: on a shared box, steps per CPU-second compare implementations better than steps/s);
  ``time/worker_cpu_s`` CPU seconds the collector's worker processes used since they started (PPO with
  ``collector.num_workers`` >= 1; ``time/cpu_s`` leaves them out).

Backends (``logger.backends``): ``csv`` (TorchRL's CSVLogger; one file per metric under
``<run_dir>/logs/<exp>/scalars/``), ``tensorboard`` (only when installed; otherwise a one-line
notice) and ``wandb`` (offline by default; only when installed).
"""

from __future__ import annotations

import importlib.util
import math
import sys
import time
from pathlib import Path
from typing import Any, Iterable

from torchrl.record.loggers import CSVLogger, Logger


def make_loggers(backends: Iterable[str], run_dir: Path, exp_name: str, wandb_project: str = "torcsrl", wandb_mode: str = "offline") -> list[Logger]:
    """TorchRL loggers for ``backends``; unknown names raise, uninstalled optional ones are skipped with a notice."""
    out: list[Logger] = []
    log_dir = str(Path(run_dir) / "logs")
    for name in backends:
        if name == "csv":
            out.append(CSVLogger(exp_name=exp_name, log_dir=log_dir))
        elif name == "tensorboard":
            if importlib.util.find_spec("tensorboard") is None:
                print("torcsrl: tensorboard is not installed; logging to the other backends only", file=sys.stderr)
                continue
            from torchrl.record.loggers.tensorboard import TensorboardLogger  # deferred: optional (tensorboard)

            out.append(TensorboardLogger(exp_name=exp_name, log_dir=log_dir))
        elif name == "wandb":
            if importlib.util.find_spec("wandb") is None:
                print("torcsrl: wandb is not installed; logging to the other backends only", file=sys.stderr)
                continue
            from torchrl.record.loggers.wandb import WandbLogger  # deferred: optional (wandb)

            out.append(WandbLogger(exp_name=exp_name, save_dir=log_dir, project=wandb_project, offline=wandb_mode == "offline"))
        else:
            raise ValueError(f"unknown logger backend {name!r}; known: csv, tensorboard, wandb")
    return out


def log_metrics(loggers: list[Logger], metrics: dict[str, Any], step: int) -> None:
    for k, v in metrics.items():
        v = float(v)
        for lg in loggers:
            lg.log_scalar(k, v, step=step)


def truncate_csv_after(run_dir: Path, step: int) -> None:
    """Drop CSV rows logged after ``step`` (a resumed run logs them again)."""
    root = Path(run_dir) / "logs"
    if not root.is_dir():
        return
    for f in root.rglob("*.csv"):
        rows = f.read_text().splitlines()
        keep = [r for r in rows if r and int(float(r.split(",")[0])) <= step]
        if len(keep) != len(rows):
            f.write_text("".join(r + "\n" for r in keep))


def read_csv_metric(run_dir: Path, name: str) -> list[tuple[int, float]]:
    """(step, value) rows of one metric written by the csv backend (any experiment folder)."""
    rows = []
    for f in sorted((Path(run_dir) / "logs").glob(f"*/scalars/{name}.csv")):
        for line in f.read_text().splitlines():
            if line:
                s, v = line.split(",")
                rows.append((int(float(s)), float(v)))
    return rows


class Progress:
    """One console line: frames, steps/s, ETA and the latest validation (tqdm-free, stderr, rate-limited)."""

    def __init__(self, total: int, enabled: bool = True, every_s: float = 1.0, stream=sys.stderr):
        self.total, self.enabled, self.every_s, self.stream = int(total), enabled, every_s, stream
        self._last = 0.0
        self.eval_text = "-"

    def update(self, frames: int, steps_per_s: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < self.every_s:
            return
        self._last = now
        eta = (self.total - frames) / steps_per_s if steps_per_s > 0 and math.isfinite(steps_per_s) else float("nan")
        eta_s = "?" if not math.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(max(0.0, eta)))
        pct = 100.0 * frames / max(1, self.total)
        line = f"\r[torcsrl] {frames}/{self.total} steps ({pct:5.1f}%) | {steps_per_s:7.1f} steps/s | ETA {eta_s} | eval {self.eval_text}"
        self.stream.write(line)
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()
