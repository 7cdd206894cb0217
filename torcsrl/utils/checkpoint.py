"""Atomic, self-describing checkpoints.

A checkpoint is one ``torch.save`` file of plain containers and tensors (loadable with
``torch.load(weights_only=True)``) whose ``"meta"`` entry says what it holds: the format tag, the
algorithm, the observation layout and the action size. :func:`load_checkpoint` checks these
against what the current run expects and raises :class:`CheckpointError` with ONE line saying
what was expected, for a file from another algorithm or observation layout, or a file that is
corrupt or truncated. Files are written to ``<name>.tmp``, fsynced, then renamed over the final
name, so a crash leaves either the old file or the new one, never half of one.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path
from typing import Any

import torch

FORMAT = "torcsrl-checkpoint"
VERSION = 1
_CKPT_RE = re.compile(r"^ckpt_(\d+)\.pt$")


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used by this run (one-line message)."""


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (which must hold a ``"meta"`` dict) atomically to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(payload.get("meta", {}))
    meta.update(format=FORMAT, version=VERSION)
    payload = {**payload, "meta": meta}
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
    except (OSError, RuntimeError) as err:  # a full disk: torch's writer raises RuntimeError, plain writes OSError
        tmp.unlink(missing_ok=True)
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err).splitlines()[0][:200]
        raise CheckpointError(f"cannot write checkpoint {path} ({reason}); the older checkpoints are intact; allowed: a folder "
                              "this user can write, on a disk with free space") from None
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return path


def load_checkpoint(path: str | Path, expect: dict[str, Any] | None = None) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` and check its ``meta`` against ``expect``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means the same thing here
        raise CheckpointError(
            f"checkpoint {path} is corrupt or truncated ({type(err).__name__}); expected a {FORMAT} v{VERSION} file written by torcsrl.train"
        ) from None
    meta = payload.get("meta") if isinstance(payload, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path} is not a {FORMAT} file (no torcsrl meta header); expected one written by torcsrl.train")
    if meta.get("version") != VERSION:
        raise CheckpointError(f"checkpoint {path} is {FORMAT} v{meta.get('version')}; this torcsrl reads v{VERSION}")
    for key, want in (expect or {}).items():
        got = meta.get(key)
        if got != want:
            raise CheckpointError(f"checkpoint {path} was written for {key}={got!r}; this run expects {key}={want!r}")
    return payload


def checkpoint_path(ckpt_dir: str | Path, frames: int) -> Path:
    return Path(ckpt_dir) / f"ckpt_{frames:012d}.pt"


def list_checkpoints(ckpt_dir: str | Path) -> list[Path]:
    """Complete checkpoints in ``ckpt_dir``, oldest first (``.tmp`` leftovers are ignored)."""
    d = Path(ckpt_dir)
    if not d.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in d.iterdir() if (m := _CKPT_RE.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(ckpt_dir: str | Path) -> Path | None:
    cks = list_checkpoints(ckpt_dir)
    return cks[-1] if cks else None


def save_dir_atomically(final: Path, write) -> Path:
    """Call ``write(tmp_dir)`` then rename ``tmp_dir`` to ``final`` (replacing an older ``final``)."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(final.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        write(tmp)
    except (OSError, RuntimeError) as err:  # a full disk (memmap and torch writers raise RuntimeError too)
        shutil.rmtree(tmp, ignore_errors=True)
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err).splitlines()[0][:200]
        raise CheckpointError(f"cannot write {final} ({reason}); the older copies are intact; allowed: a folder this user "
                              "can write, on a disk with free space") from None
    _fsync_dir(tmp)
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    _fsync_dir(final.parent)
    return final


def prune(ckpt_dir: str | Path, keep: int) -> None:
    """Delete all but the newest ``keep`` checkpoints (and their buffer folders)."""
    cks = list_checkpoints(ckpt_dir)
    for p in cks[: max(0, len(cks) - keep)]:
        buf = p.with_name(p.stem + "_buffer")
        p.unlink(missing_ok=True)
        if buf.exists():
            shutil.rmtree(buf, ignore_errors=True)
