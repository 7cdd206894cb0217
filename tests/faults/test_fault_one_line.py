"""Defect 7: inputs that used to end in a traceback now get one line saying what is wrong and what is allowed."""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import pytest
from _faults import ENV, ROOT, cfg_for, one_line, one_line_error, run_cli, run_main

from torcsrl.envs import tracks
from torcsrl.training.offpolicy import make_buffer


# ---------------------------------------------------------------- evaluate's flags
@pytest.mark.parametrize("args,words", [
    (["--degradation", "rangefinder.noise@abc"], ["rangefinder.noise@abc", "allowed"]),
    (["--max-steps", "-5"], ["--max-steps", ">= 1"]),
])
def test_evaluate_bad_flags(tmp_path, args, words, capsys):
    from torcsrl.evaluate import main

    line = one_line(*run_main(main, ["--policy", "heuristic", "--track", "oval", "--laps", "1", "--expert-laps", "0",
                                     "--no-plots", "--out", str(tmp_path / "e"), *args], capsys), "torcsrl.evaluate")
    assert all(w in line for w in words), line


# ---------------------------------------------------------------- output folders that cannot be written
def test_evaluate_out_that_cannot_be_written(tmp_path, capsys):
    from torcsrl.evaluate import main

    (tmp_path / "file").write_text("not a folder")
    line = one_line(*run_main(main, ["--policy", "heuristic", "--track", "oval", "--laps", "1", "--expert-laps", "0",
                                     "--no-plots", "--out", str(tmp_path / "file" / "out")], capsys), "torcsrl.evaluate")
    assert str(tmp_path / "file") in line and "cannot write" in line


def test_report_out_that_cannot_be_written(tmp_path, capsys):
    from torcsrl.report import main

    (tmp_path / "file").write_text("not a folder")
    line = one_line(*run_main(main, ["--policy", "heuristic", "--tracks", "oval", "--degradations", "rangefinder.noise",
                                     "--severities", "0", "1", "--workers", "1", "--out", str(tmp_path / "file" / "out")], capsys),
                    "torcsrl.report")
    assert str(tmp_path / "file") in line and "cannot write" in line


def test_train_run_dir_that_cannot_be_written(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    proc = run_cli("torcsrl.train", "env=toy", "debug=smoke", f"hydra.run.dir={tmp_path / 'hydra'}",
                   f"run_dir={tmp_path / 'file' / 'sub'}", timeout=120)
    line = one_line_error(proc, "torcsrl.train")
    assert str(tmp_path / "file") in line and "cannot write" in line


def test_train_buffer_path_that_cannot_be_written(tmp_path):
    from torcsrl.training import train
    from torcsrl.utils.faults import OutputError

    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(OutputError, match=r"buffer.path: cannot write") as e:
        train(cfg_for(f"run_dir={tmp_path / 'run'}", "buffer.storage=disk", f"buffer.path={tmp_path / 'file' / 'sub'}"))
    assert str(tmp_path / "file") in str(e.value) and "\n" not in str(e.value)


def _small_disk():
    """Files larger than 256 KiB cannot be written (RLIMIT_FSIZE: EFBIG, as a full disk gives ENOSPC)."""
    resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))


def test_train_on_a_full_disk_is_one_line(tmp_path):
    run = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "torcsrl.train", "env=toy", "debug=smoke", f"run_dir={run}",
                           f"hydra.run.dir={tmp_path / 'hydra'}", "buffer.storage=disk"],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120, preexec_fn=_small_disk)
    line = one_line_error(proc, "torcsrl.train")
    assert "cannot write" in line, line


def test_evaluate_on_a_full_disk_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "torcsrl.evaluate", "--policy", "heuristic", "--track", "oval", "--laps", "1",
                           "--expert-laps", "0", "--max-steps", "300", "--out", str(tmp_path / "e")],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048)))
    line = one_line_error(proc, "torcsrl.evaluate")
    assert "cannot write" in line, line


# ---------------------------------------------------------------- a buffer folder with rows/ missing
def test_buffer_folder_without_rows(tmp_path):
    from torcsrl.training import train

    cfg = cfg_for("algo=td3")
    r = train(cfg_for("algo=td3", f"run_dir={tmp_path / 'run'}", "total_frames=200", "buffer.save_at_end=true"))
    dump = Path(r["run_dir"]) / "buffer_final"
    import shutil

    shutil.rmtree(dump / "rows")
    buf = make_buffer(cfg, tmp_path / "other")
    with pytest.raises(ValueError, match=r"rows") as e:
        buf.loads(str(dump))
    assert "\n" not in str(e.value) and str(dump) in str(e.value)


# ---------------------------------------------------------------- track files
def _segments(length, radius=50.0):
    return ("name: t\nwidth: 10\nsegments:\n"
            f"  - {{type: straight, length: {length}}}\n  - {{type: arc, radius: {radius}, angle: 180, turn: left}}\n"
            f"  - {{type: straight, length: {length}}}\n  - {{type: arc, radius: {radius}, angle: 180, turn: left}}\n")


@pytest.mark.parametrize("name,body", [
    ("binary", bytes(range(256)) * 8),
    ("nan", _segments(".nan").encode()),
    ("inf", _segments(".inf").encode()),
    ("nan_radius", _segments(100, ".nan").encode()),
    ("absurd", _segments("1.0e12").encode()),
    ("absurd_width", _segments(100).replace("width: 10", "width: 1.0e9").encode()),
])
def test_track_files_fail_in_one_line_naming_the_file(tmp_path, name, body):
    import tracemalloc

    path = tmp_path / f"{name}.yaml"
    path.write_bytes(body)
    tracemalloc.start()
    try:
        with pytest.raises(tracks.TrackError) as e:
            tracks.load_file(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert "\n" not in str(e.value) and str(path) in str(e.value)
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MiB allocated before failing"


def test_point_files_with_nan_and_binary(tmp_path):
    (tmp_path / "c.yaml").write_text("name: c\npoints: c.csv\n")
    (tmp_path / "c.csv").write_bytes(b"\x00\xff\xfe" * 100)
    with pytest.raises(tracks.TrackError, match="not a text file"):
        tracks.load_file(tmp_path / "c.yaml")


# ---------------------------------------------------------------- env arguments and steps
def test_spawn_jitter_of_one_number():
    from torcsrl.envs import make_env

    with pytest.raises(ValueError, match=r"spawn_jitter must be two finite half-ranges") as e:
        make_env(track="oval", spawn_jitter=(1,))
    assert "\n" not in str(e.value)
    from torcsrl.config import problems

    assert any(p.startswith("env.spawn_jitter:") for p in problems(cfg_for("env.spawn_jitter=[1]", toy=False)))


def test_torchrl_step_without_action():
    from torcsrl.envs import make_env

    env = make_env(track="oval")
    try:
        td = env.reset()
        with pytest.raises(KeyError, match="no 'action' entry") as e:
            env.step(td)
        assert "\n" not in str(e.value)
    finally:
        env.close()
