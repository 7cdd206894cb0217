"""train(cfg) on the toy env: smoke runs, exact resume after SIGKILL, checkpoint errors, configs, buffers."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torcsrl.train import build_base_env, make_buffer, train, transition_bytes
from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint
from torcsrl.utils.logging import read_csv_metric

ROOT = Path(__file__).resolve().parents[1]
CONF = str(ROOT / "conf")


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def cfg_for(*overrides: str):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("train", overrides=["env=toy", "debug=smoke", *overrides])


@pytest.mark.parametrize("algo,logger", [("ddpg", "csv"), ("td3", "csv"), ("d4pg", "csv"), ("td3", "tensorboard"), ("td3", "wandb")])
def test_every_config_composes(algo, logger):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("train", overrides=[f"algo={algo}", f"logger={logger}"], return_hydra_config=True)
    assert cfg.env.name == "race" and cfg.hydra.job.chdir is False
    assert cfg.hydra.run.dir.startswith("outputs/")
    assert cfg.algo.name == algo and logger in cfg.logger.backends


def test_default_command_is_td3_on_the_race_env_with_rangefinder_and_state():
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("train")
    assert cfg.algo.name == "td3" and cfg.env.name == "race"
    assert list(cfg.env.sensors) == ["rangefinder", "state"]
    assert cfg.total_frames >= 100_000


@pytest.mark.parametrize(
    "algo,extra",
    [
        ("ddpg", []),
        ("td3", ["algo.stochastic_brake.enabled=true"]),
        ("d4pg", ["buffer.prioritized=true", "buffer.storage=disk", "env.num_cars=2"]),
    ],
)
def test_smoke_vector_observations(tmp_path, algo, extra):
    r = train(cfg_for(f"algo={algo}", f"run_dir={tmp_path}", "total_frames=400", *extra))
    assert r["frames"] >= 400 and r["updates"] > 0 and r["episodes"] > 0
    assert math.isfinite(r["loss/qvalue"]) and math.isfinite(r["eval/reward"])
    # d4pg adds MultiStepTransform keys: steps_to_next_obs (8), gamma (4), nonterminal (1), original_reward (4), our nstep flag (1)
    assert r["bytes_per_transition"] == (215 if algo != "d4pg" else 215 + 8 + 4 + 1 + 4 + 1)
    rows = read_csv_metric(tmp_path, "loss/qvalue")
    assert rows and all(math.isfinite(v) for _, v in rows)
    assert read_csv_metric(tmp_path, "time/steps_per_s")
    assert read_csv_metric(tmp_path, "eval/laps")
    assert Path(r["checkpoint"]).is_file()


def test_smoke_pixels_with_drq_shift(tmp_path):
    r = train(cfg_for("algo=td3", f"run_dir={tmp_path}", "total_frames=200", "env.sensors=[rangefinder,state,pixels]",
                      "algo.encoder.augment_shift=2", "checkpoint.buffer=false"))
    assert r["updates"] > 0 and math.isfinite(r["loss/qvalue"])
    # uint8 frames, stored twice (obs and next obs): 2 * 3*32*32 + the vector transition
    assert r["bytes_per_transition"] == 2 * 3 * 32 * 32 + 215


def test_multisync_collector_two_workers_on_their_own_tracks(tmp_path):
    r = train(cfg_for("algo=td3", f"run_dir={tmp_path}", "total_frames=200", "collector.num_workers=2",
                      "collector.worker_tracks=[stadium,oval]", "checkpoint.buffer=false"))
    assert r["frames"] >= 200 and r["updates"] > 0 and math.isfinite(r["loss/qvalue"])


def test_exact_resume_after_sigkill(tmp_path):
    """A run killed with SIGKILL and resumed from its last checkpoint logs exactly what the uninterrupted run logs."""
    ov = ["algo=d4pg", "buffer.prioritized=true", "algo.exploration.kind=ou", "algo.exploration.theta=[0.6,1.0]",
          "algo.exploration.mu=[0.0,0.5]", "algo.exploration.sigma=[0.3,0.3]", "total_frames=600", "checkpoint.every_frames=200"]
    ref = train(cfg_for(*ov, f"run_dir={tmp_path / 'ref'}"))

    killed = tmp_path / "killed"
    cmd = [sys.executable, "-m", "torcsrl.train", "env=toy", "debug=smoke", *ov, f"run_dir={killed}", f"hydra.run.dir={tmp_path / 'hydra'}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckdir = killed / "checkpoints"
    deadline = time.monotonic() + 120
    while not (ckdir.is_dir() and any(p.suffix == ".pt" for p in ckdir.iterdir())):
        assert proc.poll() is None, "the run ended before its first checkpoint"
        assert time.monotonic() < deadline
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    first = sorted(p for p in ckdir.iterdir() if p.suffix == ".pt")[-1]
    assert int(first.stem.split("_")[1]) < 600  # killed mid-run

    res = train(cfg_for(*ov, f"run_dir={killed}", "checkpoint.resume=latest"))
    for k in ("frames", "updates", "episodes", "loss/qvalue", "loss/actor", "eval/reward", "eval/laps"):
        assert res[k] == ref[k], k
    for m in ("loss/qvalue", "loss/actor", "eval/reward", "train/episode_reward", "train/buffer_size"):
        assert read_csv_metric(killed, m) == read_csv_metric(tmp_path / "ref", m), m


def test_bad_checkpoints_give_one_clear_line(tmp_path):
    r = train(cfg_for("algo=td3", f"run_dir={tmp_path / 'a'}", "total_frames=200", "checkpoint.buffer=false"))
    good = Path(r["checkpoint"])

    def one_line(exc_info, *words):
        msg = str(exc_info.value)
        assert "\n" not in msg
        for w in words:
            assert w in msg, msg

    with pytest.raises(CheckpointError) as e:  # another algorithm
        train(cfg_for("algo=ddpg", f"run_dir={tmp_path / 'b'}", f"checkpoint.resume={good}"))
    one_line(e, "algo='td3'", "expects algo='ddpg'")
    with pytest.raises(CheckpointError) as e:  # another observation layout
        train(cfg_for("algo=td3", f"run_dir={tmp_path / 'c'}", f"checkpoint.resume={good}", "env.sensors=[rangefinder]"))
    one_line(e, "obs_layout", "rangefinder:19")
    truncated = tmp_path / "trunc.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(truncated)
    one_line(e, "corrupt or truncated")
    junk = tmp_path / "junk.pt"
    torch.save({"weights": torch.zeros(3)}, junk)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(junk)
    one_line(e, "not a torcsrl-checkpoint")
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(tmp_path / "missing.pt")
    one_line(e, "does not exist")


def test_buffer_save_load_shares_between_experiments(tmp_path):
    cfg = cfg_for("algo=td3", f"run_dir={tmp_path}")
    env = build_base_env("toy", {"seed": 0})
    ro = env.rollout(50, break_when_any_done=False)
    td = ro.select("rangefinder", "state", "action", ("next", "rangefinder"), ("next", "state"), ("next", "reward"), ("next", "done"),
                   ("next", "terminated"), ("next", "truncated"))
    rb = make_buffer(cfg, tmp_path)
    rb.extend(td)
    assert transition_bytes(td) == 215
    rb.dumps(str(tmp_path / "shared"))
    rb2 = make_buffer(cfg, tmp_path)
    rb2.loads(str(tmp_path / "shared"))
    assert len(rb2) == 50
    torch.testing.assert_close(rb2[:]["next", "reward"], td["next", "reward"])


def test_unknown_env_name_is_one_clear_line():
    with pytest.raises(ValueError, match="unknown env.name 'carla'; known: race, toy, gym"):
        build_base_env("carla", {})
