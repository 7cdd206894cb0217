"""Multiruns with Hydra's launchers (basic, joblib; ray and optuna when installed) and the sweep summary."""

from __future__ import annotations

import importlib.util
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from torcsrl import sweep

ROOT = Path(__file__).resolve().parents[1]
#: a tiny job: the toy env, the smoke settings, a validation after every episode (so eval/* metrics exist)
TINY = ["env=toy", "debug=smoke", "total_frames=200", "eval.every_episodes=1", "checkpoint.buffer=false", "threads=1"]


def multirun(out: Path, *overrides: str, python: str = sys.executable, timeout: int = 400) -> subprocess.CompletedProcess:
    cmd = [python, "-m", "torcsrl.train", "-m", *TINY, *overrides, f"hydra.sweep.dir={out}"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def job_dirs(out: Path) -> list[Path]:
    return sorted((p for p in out.iterdir() if (p / ".hydra").is_dir()), key=lambda p: int(p.name.split("_")[0]))


@pytest.fixture(scope="module")
def grid(tmp_path_factory) -> Path:
    """python -m torcsrl.train -m algo=ddpg,td3 seed=0,1 (basic launcher: jobs one after another)."""
    out = tmp_path_factory.mktemp("grid")
    multirun(out, "algo=ddpg,td3", "seed=0,1")
    return out


def test_basic_grid_one_folder_per_job_named_by_its_overrides(grid):
    dirs = job_dirs(grid)
    assert [d.name.split(",")[0] for d in dirs] == ["0_algo=ddpg", "1_algo=ddpg", "2_algo=td3", "3_algo=td3"]
    assert all(re.search(r"seed=[01]", d.name) and "env=toy" in d.name for d in dirs)
    for d in dirs:
        metrics = json.loads((d / "metrics.json").read_text())
        assert metrics["frames"] >= 200 and math.isfinite(metrics["eval/reward"])
        cfg = yaml.safe_load((d / "config.yaml").read_text())  # the resolved config
        assert "${" not in (d / "config.yaml").read_text() and cfg["env"]["name"] == "toy"
        assert cfg["logger"]["exp_name"] == cfg["algo"]["name"]
        assert re.fullmatch(r"([0-9a-f]{40}(-dirty)?|unknown)\n", (d / "git_rev.txt").read_text())
        assert (d / ".hydra" / "overrides.yaml").is_file() and (d / "checkpoints").is_dir()


def test_sweep_summary_of_a_real_sweep(grid, capsys):
    assert sweep.main([str(grid)]) == 0
    md = capsys.readouterr().out
    assert "| algo | n | eval/laps | eval/reward | wall_s |" in md.replace("eval/lap_time | eval/lap_time_mean | ", "")
    assert "`env=toy`" in md and "±" in md
    rows = (grid / "summary.csv").read_text().splitlines()
    head = rows[0].split(",")
    assert head[:4] == ["algo", "jobs", "missing", "seeds"] and "eval/reward_mean" in head and "eval/reward_ci95" in head
    assert len(rows) == 3  # ddpg, td3: the seeds are the samples
    jobs = sweep.load_jobs(grid)
    td3 = [j.metrics["eval/reward"] for j in jobs if j.overrides["algo"] == "td3"]
    mean, ci, n = sweep.mean_ci(td3)
    line = next(r.split(",") for r in rows[1:] if r.startswith("td3"))
    assert n == 2 and float(line[head.index("eval/reward_mean")]) == pytest.approx(mean, rel=1e-5)
    assert float(line[head.index("eval/reward_ci95")]) == pytest.approx(ci, rel=1e-5)
    assert (grid / "summary.md").read_text().startswith("### Sweep")


def test_joblib_launcher_runs_jobs_in_parallel_with_the_same_results(grid, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="hydra-joblib-launcher is not installed (the [dev] extra)")
    proc = multirun(tmp_path, "hydra/launcher=parallel", "algo=td3", "seed=0,1")
    assert "Joblib.Parallel(n_jobs=2" in proc.stderr + proc.stdout
    dirs = job_dirs(tmp_path)
    assert [d.name.split(",")[0] for d in dirs] == ["0_algo=td3", "1_algo=td3"]
    basic = {j.overrides["seed"]: j.metrics for j in sweep.load_jobs(grid) if j.overrides["algo"] == "td3"}
    for j in sweep.load_jobs(tmp_path):  # same config and seed, another launcher: the same numbers (CPU)
        for k in ("frames", "updates", "episodes", "loss/qvalue", "eval/reward"):
            assert j.metrics[k] == basic[j.overrides["seed"]][k], k


def _has(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


@pytest.mark.skipif(not (_has("hydra_plugins.hydra_ray_launcher") and _has("ray")),
                    reason="hydra-ray-launcher / ray are not installed (the [distributed] extra)")
def test_ray_launcher(tmp_path):
    multirun(tmp_path, "hydra/launcher=ray_local", "hydra.launcher.ray.init.num_cpus=2", "algo=ddpg,td3", "seed=0", timeout=600)
    dirs = job_dirs(tmp_path)
    assert len(dirs) == 2 and all((d / "metrics.json").is_file() for d in dirs)


@pytest.mark.skipif(not _has("hydra_plugins.hydra_optuna_sweeper"),
                    reason="hydra-optuna-sweeper is not installed (pip install 'torcsrl[sweeps]')")
def test_optuna_sweeper(tmp_path):
    multirun(tmp_path, "hparams_search=td3_optuna", "hydra.sweeper.n_trials=2", "hydra.sweeper.sampler.n_startup_trials=1")
    res = yaml.safe_load((tmp_path / "optimization_results.yaml").read_text())
    assert math.isfinite(res["best_value"]) and set(res["best_params"]) >= {"algo.actor_lr", "algo.batch_size"}
    assert [d.name for d in job_dirs(tmp_path)] == ["0", "1"]


# --------------------------------------------------------------------------------------- summary units
def fake_job(root: Path, name: str, overrides: list[str], metrics: dict | None) -> None:
    d = root / name
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    if metrics is not None:
        (d / "metrics.json").write_text(json.dumps(metrics))


def test_mean_ci_is_the_student_t_interval():
    m, ci, n = sweep.mean_ci([1.0, 2.0, 3.0])
    assert (m, n) == (2.0, 3) and ci == pytest.approx(4.302653 / math.sqrt(3), rel=1e-6)
    m, ci, n = sweep.mean_ci([5.0])
    assert m == 5.0 and math.isnan(ci) and n == 1
    assert math.isnan(sweep.mean_ci([])[0])


def test_summary_groups_by_overrides_minus_seed_and_counts_missing(tmp_path, capsys):
    fake_job(tmp_path, "0_a", ["algo=ddpg", "surface=ice", "seed=0"], {"eval/reward": 1.0, "wall_s": 2.0, "run_dir": "x"})
    fake_job(tmp_path, "1_a", ["algo=ddpg", "surface=ice", "seed=1"], {"eval/reward": 3.0, "wall_s": 2.0, "run_dir": "y"})
    fake_job(tmp_path, "2_a", ["algo=ddpg", "surface=ice", "seed=2"], None)  # failed job
    fake_job(tmp_path, "3_a", ["algo=td3", "surface=ice", "seed=0", "run_dir=/tmp/z"], {"eval/reward": None, "wall_s": 1.0})
    fake_job(tmp_path, "10_a", ["algo=td3", "surface=ice", "seed=1"], {"eval/reward": 4.0, "wall_s": 1.0})
    rows, varying, shared = sweep.summarise(sweep.load_jobs(tmp_path))
    assert varying == ["algo"] and shared == {"surface": "ice"}
    assert [(r.config["algo"], len(r.jobs), r.missing) for r in rows] == [("ddpg", 3, 1), ("td3", 2, 0)]
    assert rows[1].values("eval/reward") == [4.0]  # null (NaN when written) is left out
    assert sweep.main([str(tmp_path), "--metrics", "eval/reward", "--out", str(tmp_path / "s")]) == 0
    md = capsys.readouterr().out
    assert "| ddpg | 2 (1 missing) | 2 ± 12.7 |" in md and "| td3 | 2 | 4 |" in md
    assert sweep.main([str(tmp_path), "--metrics", "eval/rewrd"]) == 2
    assert "eval/reward" in capsys.readouterr().err
    assert sweep.main([str(tmp_path / "s")]) == 2  # no jobs there
