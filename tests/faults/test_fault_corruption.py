"""Defect 4: corruption is caught, never accepted silently. Checkpoints and replay-buffer dumps carry SHA-256
checksums; a mismatch fails with one line naming the file; ``checkpoint.resume=latest`` with a corrupt newest
checkpoint says so and names the previous good one; a truncated memmap is neither zero-filled nor extended."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest
from _faults import cfg_for

from torcsrl.training import train
from torcsrl.utils.checkpoint import CheckpointError, list_checkpoints, load_checkpoint


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished toy run with checkpoints at 300 and 600 frames, each with its replay buffer."""
    import torch

    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("corrupt") / "run"
    train(cfg_for(f"run_dir={d}", "total_frames=600", "checkpoint.every_frames=300"))
    return d


def _copy(run: Path, tmp_path: Path) -> Path:
    import shutil

    dst = tmp_path / "run"
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns(".torcsrl.lock"))
    return dst


def _overwrite_tensor_bytes(ckpt: Path) -> None:
    """Overwrite 16 bytes in the middle of the largest tensor record of a torch zip file (the zip stays readable)."""
    with zipfile.ZipFile(ckpt) as z:
        info = max((i for i in z.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    with open(ckpt, "r+b") as f:
        f.seek(info.header_offset + 26)
        n, m = int.from_bytes(f.read(2), "little"), int.from_bytes(f.read(2), "little")
        f.seek(info.header_offset + 30 + n + m + info.file_size // 2)
        f.write(b"\x7f" * 16)


def test_overwritten_tensor_bytes_fail_in_one_line(run, tmp_path):
    d = _copy(run, tmp_path)
    ck = list_checkpoints(d / "checkpoints")[-1]
    _overwrite_tensor_bytes(ck)
    with pytest.raises(CheckpointError, match="corrupt.*SHA-256") as e:
        load_checkpoint(ck)
    assert str(ck) in str(e.value) and "\n" not in str(e.value)
    from torcsrl.policies import PolicyError, load_policy

    with pytest.raises(PolicyError) as e:  # evaluate / report refuse to drive it
        load_policy(str(ck))
    assert str(ck) in str(e.value) and "\n" not in str(e.value)


def test_resume_latest_with_a_corrupt_newest_names_the_previous_good_one(run, tmp_path):
    d = _copy(run, tmp_path)
    older, newest = list_checkpoints(d / "checkpoints")[-2:]
    _overwrite_tensor_bytes(newest)
    with pytest.raises(CheckpointError) as e:
        train(cfg_for(f"run_dir={d}", "total_frames=900", "checkpoint.every_frames=300", "checkpoint.resume=latest"))
    msg = str(e.value)
    assert "\n" not in msg and str(newest) in msg and "corrupt" in msg
    assert f"the previous good one is {older}" in msg and f"checkpoint.resume={older}" in msg


def test_truncated_replay_memmap_fails_and_is_left_as_it_was(run, tmp_path):
    d = _copy(run, tmp_path)
    older, newest = list_checkpoints(d / "checkpoints")[-2:]
    mm = sorted((newest.with_name(newest.stem + "_buffer") / "rows").glob("*.memmap"), key=lambda p: p.stat().st_size)[-1]
    size = mm.stat().st_size
    with open(mm, "r+b") as f:
        f.truncate(size // 2)
    with pytest.raises(CheckpointError) as e:
        train(cfg_for(f"run_dir={d}", "total_frames=900", "checkpoint.every_frames=300", "checkpoint.resume=latest"))
    msg = str(e.value)
    assert "\n" not in msg and str(mm) in msg and "truncated" in msg and f"the previous good one is {older}" in msg
    assert mm.stat().st_size == size // 2  # not extended


def test_flipped_bytes_in_a_buffer_dump(run, tmp_path):
    from torcsrl.training.offpolicy import make_buffer

    d = _copy(run, tmp_path)
    newest = list_checkpoints(d / "checkpoints")[-1]
    mm = sorted((newest.with_name(newest.stem + "_buffer") / "rows").glob("*.memmap"))[0]
    with open(mm, "r+b") as f:
        f.seek(8)
        b = f.read(1)
        f.seek(8)
        f.write(bytes([b[0] ^ 0xFF]))
    buf = make_buffer(cfg_for(), tmp_path / "other")
    with pytest.raises(ValueError, match="does not match its SHA-256 checksum") as e:
        buf.loads(str(mm.parents[1]))
    assert str(mm) in str(e.value) and "\n" not in str(e.value)


def test_intact_checkpoint_and_resume_still_work(run, tmp_path):
    d = _copy(run, tmp_path)
    r = train(cfg_for(f"run_dir={d}", "total_frames=900", "checkpoint.every_frames=300", "checkpoint.resume=latest"))
    assert r["frames"] >= 900
