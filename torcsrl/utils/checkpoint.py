"""Atomic, self-describing checkpoints.

A checkpoint is one ``torch.save`` file of plain containers and tensors (loadable with
``torch.load(weights_only=True)``) whose ``"meta"`` entry says what it holds: the format tag, the
algorithm, the observation layout and the action size. :func:`load_checkpoint` checks these
against what the current run expects and raises :class:`CheckpointError` with ONE line saying
what was expected, for a file from another algorithm or observation layout, or a file that is
corrupt or truncated. Files are written to ``<name>.tmp``, fsynced, then renamed over the final
name, so a crash leaves either the old file or the new one, never half of one.

Checksums: ``meta["sha256"]`` is a SHA-256 over every value of the payload (tensor bytes, dtypes, shapes,
and every other leaf), so bytes overwritten inside an otherwise loadable file are caught on load with one
line naming the file (files written before checksums existed, like older shipped drivers, load unchecked).
"""

from __future__ import annotations

import hashlib
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


def payload_digest(payload: Any) -> str:
    """SHA-256 over ``payload`` (nested dicts / lists / tuples of tensors and plain values), in order; the
    checkpoint's own ``meta["sha256"]`` is left out."""
    h = hashlib.sha256()

    def walk(x: Any) -> None:
        if isinstance(x, torch.Tensor):
            t = x.detach().cpu().contiguous()
            h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
            if t.numel():
                h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.dtype != torch.bool
                         else t.numpy().tobytes())
        elif isinstance(x, dict):
            items = [(k, v) for k, v in x.items() if not (k == "sha256" and isinstance(v, str) and len(v) == 64)]
            h.update(f"D{len(items)}".encode())
            for k, v in items:
                h.update(repr(k).encode())
                walk(v)
        elif isinstance(x, (list, tuple)):
            h.update(f"{'L' if isinstance(x, list) else 'U'}{len(x)}".encode())
            for v in x:
                walk(v)
        else:
            h.update(repr(x).encode())

    walk(payload)
    return h.hexdigest()


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (which must hold a ``"meta"`` dict) atomically to ``path``, with its checksum."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(payload.get("meta", {}))
    meta.pop("sha256", None)
    meta.update(format=FORMAT, version=VERSION)
    payload = {**payload, "meta": meta}
    meta["sha256"] = payload_digest(payload)
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
    if "sha256" in meta and payload_digest(payload) != meta["sha256"]:
        raise CheckpointError(f"checkpoint {path} is corrupt: its contents do not match their SHA-256 checksum (bytes changed "
                              "after it was written); allowed: an intact checkpoint (an older one, or a fresh copy)")
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


def previous_good(ckpt_dir: str | Path, before: Path, check=None) -> Path | None:
    """The newest checkpoint older than ``before`` that loads and passes its checksums (and ``check(path)``,
    e.g. its replay buffer's), or None."""
    for p in reversed(list_checkpoints(ckpt_dir)):
        if p == Path(before) or _frames(p) >= _frames(Path(before)):
            continue
        try:
            load_checkpoint(p)
            if check is not None:
                check(p)
        except (CheckpointError, ValueError):
            continue
        return p
    return None


def _frames(p: Path) -> int:
    m = _CKPT_RE.match(p.name)
    return int(m.group(1)) if m else -1


def resume_from(resume: str | Path, ckpt_dir: str | Path, expect: dict[str, Any] | None = None,
                check=None) -> tuple[Path, dict[str, Any]]:
    """The checkpoint a run resumes from (``checkpoint.resume``: ``"latest"`` under ``ckpt_dir``, or a path) and its
    payload, checked against ``expect`` and by ``check(path)`` (ValueError: what else it needs is damaged, e.g. its
    replay buffer dump). CheckpointError (one line) when there is none, or when it is corrupt or ``check`` fails
    (with ``"latest"``: naming the previous good one to resume from)."""
    latest = str(resume) == "latest"
    path = latest_checkpoint(ckpt_dir) if latest else Path(resume)
    if path is None:
        raise CheckpointError(f"checkpoint.resume=latest but {ckpt_dir} holds no checkpoint")
    try:
        ck = load_checkpoint(path, expect=expect)
        if check is not None:
            try:
                check(path)
            except ValueError as err:
                raise CheckpointError(f"checkpoint {path}: its replay buffer cannot be restored ({err})") from None
        return path, ck
    except CheckpointError as err:
        if not latest or "corrupt" not in str(err) and "cannot be restored" not in str(err):
            raise
        good = previous_good(ckpt_dir, path, check=check)
        hint = (f"; the previous good one is {good}: resume with checkpoint.resume={good}" if good
                else "; no older intact checkpoint is left in " + str(ckpt_dir))
        raise CheckpointError(f"{err}{hint}") from None


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
