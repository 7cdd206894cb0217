"""train(cfg) on the toy env: smoke runs, exact resume after SIGKILL, checkpoint errors, configs, buffers."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torcsrl.pipeline import build_base_env
from torcsrl.training import train
from torcsrl.training.offpolicy import make_buffer
from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint
from torcsrl.utils.logging import read_csv_metric
from _compose import compose_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def cfg_for(*overrides: str):
    return compose_config("env=toy", "debug=smoke", *overrides)


@pytest.mark.parametrize("algo,logger", [("ddpg", "csv"), ("td3", "csv"), ("d4pg", "csv"), ("td3", "tensorboard"), ("td3", "wandb")])
def test_every_config_composes(algo, logger):
    cfg = compose_config(f"algo={algo}", f"logger={logger}", hydra=True)
    assert cfg.env.name == "race" and cfg.hydra.job.chdir is False
    assert cfg.hydra.run.dir.startswith("outputs/")
    assert cfg.algo.name == algo and logger in cfg.logger.backends


def test_default_command_is_td3_on_the_race_env_with_rangefinder_and_state():
    cfg = compose_config()
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
    # one row: rangefinder 19 + state 6 floats, action 2 floats, reward, 3 flags, the int32 finals pointer (n-step returns
    # are formed when sampling, so d4pg stores the same rows); the next observation is the following row's
    assert r["bytes_per_transition"] == 4 * (19 + 6) + 4 * 2 + 4 + 3 + 4 == 119
    assert r["bytes_per_final"] == 4 * (19 + 6)  # one per finished episode
    rows = read_csv_metric(tmp_path, "loss/qvalue")
    assert rows and all(math.isfinite(v) for _, v in rows)
    assert read_csv_metric(tmp_path, "time/steps_per_s")
    assert read_csv_metric(tmp_path, "eval/laps")
    assert Path(r["checkpoint"]).is_file()


def test_the_actor_loss_is_logged_under_a_policy_delay(tmp_path):
    """TD3 updates its actor every policy_delay-th step; a log line shows the latest value of every loss key, so the
    actor loss is there even when the update just before the line was critic-only (2 updates a batch of 10 frames,
    20 between lines of 100 frames: the last one before each line is always the odd, critic-only one)."""
    train(cfg_for("algo=td3", "algo.policy_delay=2", "learner.utd_ratio=0.2", f"run_dir={tmp_path}", "total_frames=400"))
    q, actor = read_csv_metric(tmp_path, "loss/qvalue"), read_csv_metric(tmp_path, "loss/actor")
    assert len(q) >= 3 and [f for f, _ in actor] == [f for f, _ in q] and all(math.isfinite(v) for _, v in actor)


def test_smoke_pixels_with_drq_shift(tmp_path):
    r = train(cfg_for("algo=td3", f"run_dir={tmp_path}", "total_frames=200", "env.sensors=[rangefinder,state,pixels]",
                      "algo.encoder.augment_shift=2", "checkpoint.buffer=false"))
    assert r["updates"] > 0 and math.isfinite(r["loss/qvalue"])
    # uint8 frames stored ONCE (the next frame is the following row's, or the finals table's at an episode end)
    assert r["bytes_per_transition"] == 3 * 32 * 32 + 119


@pytest.mark.parametrize("algo", ["td3", "d4pg"])
def test_smoke_bfloat16_updates_with_pixels(tmp_path, algo):
    """algo.precision=bfloat16 through the whole loop (CNN encoder + vectors): finite losses, float32 checkpoint."""
    r = train(cfg_for(f"algo={algo}", f"run_dir={tmp_path}", "total_frames=200", "env.sensors=[rangefinder,state,pixels]",
                      "algo.encoder.augment_shift=2", "checkpoint.buffer=false", "algo.precision=bfloat16",
                      "algo.policy_delay=1"))  # an actor step before every log
    assert r["updates"] > 0 and math.isfinite(r["loss/qvalue"])
    actor = read_csv_metric(tmp_path, "loss/actor")
    assert actor and all(math.isfinite(v) for _, v in actor)
    ck = load_checkpoint(r["checkpoint"])
    assert all(v.dtype == torch.float32 for k, v in ck["loss"].items() if torch.is_floating_point(v))


def test_multisync_collector_two_workers_on_their_own_tracks(tmp_path):
    r = train(cfg_for("algo=td3", f"run_dir={tmp_path}", "total_frames=200", "collector.num_workers=2",
                      "collector.worker_tracks=[stadium,oval]", "checkpoint.buffer=false"))
    assert r["frames"] >= 200 and r["updates"] > 0 and math.isfinite(r["loss/qvalue"])


def test_worker_collector_leaves_the_learner_its_threads(tmp_path):
    """TorchRL's MultiSyncCollector sets the learner to max(1, threads - workers) unless told: make_collector tells it."""
    from torchrl.envs.utils import RandomPolicy

    from torcsrl.pipeline import make_train_env
    from torcsrl.training.offpolicy import make_collector

    cfg = cfg_for("algo=td3", "collector.num_workers=2", "threads=2")
    torch.set_num_threads(2)
    env = make_train_env(cfg)
    try:
        col = make_collector(cfg, env, RandomPolicy(env.action_spec))
        try:
            assert col.num_threads == 2 and torch.get_num_threads() == 2
        finally:
            col.shutdown()
    finally:
        env.close()


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


def test_race_env_resumes_exactly(tmp_path):
    """The pybullet race env saves its whole simulation in the checkpoint (RaceCore.get_state):
    a run stopped at a checkpoint and resumed logs exactly what the uninterrupted run logs."""
    def race(*ov):
        return compose_config("env=race", "debug=smoke", "env.track=[hairpins,oval]", "env.num_cars=2", "env.max_steps=60",
                              "eval.max_steps=30", "checkpoint.every_frames=200", "collector.frames_per_batch=20", *ov)

    ref = train(race("total_frames=400", f"run_dir={tmp_path / 'ref'}"))
    train(race("total_frames=200", f"run_dir={tmp_path / 'cut'}"))
    res = train(race("total_frames=400", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    assert ref["episodes"] > 4  # episodes ended and restarted inside the run
    for k in ("frames", "updates", "episodes", "loss/qvalue", "eval/reward"):
        assert res[k] == ref[k], k
    for m in ("loss/qvalue", "train/episode_reward", "train/buffer_size"):
        assert read_csv_metric(tmp_path / "cut", m) == read_csv_metric(tmp_path / "ref", m), m
    saved = sorted(int(p.stem.split("_")[1]) for p in (tmp_path / "cut" / "checkpoints").glob("ckpt_*.pt"))
    assert saved == [200, 400], saved  # the resumed run saved on schedule, not again right after resuming


def test_per_track_validation_logs_every_track_and_resumes_exactly(tmp_path):
    """eval.per_track: one validation env per track of the list, each logged under eval/<track>/, the
    means and the worst track over them; their states are in the checkpoint (exact resume)."""
    def race(*ov):
        return compose_config("env=race", "debug=smoke", "env.track=[hairpins,oval]", "eval.per_track=true", "env.max_steps=60",
                              "eval.max_steps=40", "eval.every_episodes=2", "checkpoint.every_frames=200",
                              "collector.frames_per_batch=20", *ov)

    ref = train(race("total_frames=400", f"run_dir={tmp_path / 'ref'}"))
    metric = lambda run, m: read_csv_metric(tmp_path / run, m)  # noqa: E731
    steps = [s for s, _ in metric("ref", "eval/laps")]
    assert len(steps) >= 2
    for track in ("hairpins", "oval"):
        assert [s for s, _ in metric("ref", f"eval/{track}/reward")] == steps
    for (_, mean), (_, a), (_, b) in zip(metric("ref", "eval/reward"), metric("ref", "eval/hairpins/reward"),
                                         metric("ref", "eval/oval/reward")):
        assert mean == pytest.approx((a + b) / 2)
    laps = {t: dict(metric("ref", f"eval/{t}/laps")) for t in ("hairpins", "oval")}
    for s, worst in metric("ref", "eval/laps_min"):
        assert worst == min(laps["hairpins"][s], laps["oval"][s])
    assert metric("ref", "eval/hairpins/reward") != metric("ref", "eval/oval/reward")  # two tracks, two drives

    train(race("total_frames=200", f"run_dir={tmp_path / 'cut'}"))
    res = train(race("total_frames=400", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    for k in ("frames", "updates", "episodes", "eval/reward"):
        assert res[k] == ref[k], k
    for m in ("eval/hairpins/reward", "eval/oval/reward", "loss/qvalue"):
        assert metric("cut", m) == metric("ref", m), m
    with pytest.raises(CheckpointError, match=r"validated on \[.hairpins., .oval.\], this config on one env") as e:
        train(race("total_frames=600", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest", "eval.per_track=false"))
    assert "\n" not in str(e.value)


def test_per_track_validation_needs_tracks(tmp_path):
    with pytest.raises(ValueError, match="eval.per_track=true validates on each track of env.track; env.name='toy' has no tracks"):
        train(cfg_for(f"run_dir={tmp_path}", "total_frames=200", "eval.per_track=true"))


def test_resume_is_exact_with_stateful_degradations(tmp_path):
    """Degradations with per-episode draws and temporal buffers (stuck beams, latency, noise) save
    their generators and running state in the checkpoint: the resumed run logs what the
    uninterrupted run logs."""
    ov = ["degradation=[rangefinder.stuck,state.latency,rangefinder.noise]", "checkpoint.every_frames=300"]
    ref = train(cfg_for(*ov, "total_frames=600", f"run_dir={tmp_path / 'ref'}"))
    train(cfg_for(*ov, "total_frames=300", f"run_dir={tmp_path / 'cut'}"))
    res = train(cfg_for(*ov, "total_frames=600", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    for k in ("frames", "updates", "episodes", "loss/qvalue", "eval/reward"):
        assert res[k] == ref[k], k
    for m in ("loss/qvalue", "train/episode_reward"):
        assert read_csv_metric(tmp_path / "cut", m) == read_csv_metric(tmp_path / "ref", m), m


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


def _toy_rollout(steps: int, cars: int = 3, max_steps: int = 7):
    """[cars, steps] transitions of the toy env with truncations (max_steps) and crashes (random starts)."""
    torch.manual_seed(0)
    env = build_base_env("toy", {"seed": 0, "num_cars": cars, "max_steps": max_steps, "start": "random", "dt": 0.5})
    base = torch.tensor([[0.0, -0.2], [0.9, 1.0], [-0.9, 1.0]])[torch.arange(cars) % 3]  # car 0 cruises, the others crash

    def policy(td):
        return td.set("action", (base + 0.1 * torch.randn(cars, 2)).clamp(-1, 1))

    ro = env.rollout(steps, policy, break_when_any_done=False)
    assert ro["next", "truncated"].any() and ro["next", "terminated"].any()
    return ro


KEYS = ["rangefinder", "state"]


def _flat(ro):
    """Time-major flat transitions (the buffer's order)."""
    return ro.transpose(0, 1).reshape(-1)


def _same(got, want, keys=(*KEYS, "action", ("next", "rangefinder"), ("next", "state"), ("next", "reward"), ("next", "done"),
                            ("next", "terminated"), ("next", "truncated"))):
    for k in keys:
        torch.testing.assert_close(got[k], want[k], msg=str(k))


def test_replay_stores_each_observation_once_and_rebuilds_next_observations():
    from torcsrl.utils.replay import ReplayBuffer

    ro = _toy_rollout(20)
    rb = ReplayBuffer(1000, 8, KEYS, streams=3)
    rb.extend(ro[:, :5])  # a batch of 5 steps, then one step at a time
    for t in range(5, 20):
        rb.extend(ro[:, t : t + 1])
        _same(rb[:], _flat(ro[:, : t + 1]))  # the newest transitions are sampleable at once
    assert len(rb) == 60 and "next" not in rb._rows.keys()
    small = ReplayBuffer(12, 8, KEYS, streams=3)  # wraps around: keeps the newest 4 steps
    small.extend(ro)
    _same(small[:], _flat(ro[:, -4:]))
    batch = small.sample()
    _same(batch, small.transitions(batch["index"]))
    assert batch.shape == (8,) and set(batch["index"].tolist()) <= set(((torch.arange(12) + small.written - 12) % small.rows).tolist())


def test_replay_pixels_are_stored_once():
    from torcsrl.utils.replay import ReplayBuffer

    torch.manual_seed(0)
    env = build_base_env("toy", {"seed": 0, "num_cars": 2, "max_steps": 5, "sensors": ("state", "pixels"), "camera": {"height": 8, "width": 8}})
    ro = env.rollout(12, break_when_any_done=False)
    rb = ReplayBuffer(100, 4, ["state", "pixels"], streams=2)
    rb.extend(ro)
    _same(rb[:], _flat(ro), keys=("state", "pixels", ("next", "state"), ("next", "pixels"), ("next", "truncated")))
    assert rb.bytes_per_transition == 3 * 8 * 8 + 4 * 6 + 4 * 2 + 4 + 3 + 4  # one frame per row
    assert rb.finals_written == 4  # one final frame per finished episode (2 cars x 2 truncations)


def test_replay_n_step_returns_equal_torchrl_multistep():
    from torchrl.envs import MultiStepTransform

    from torcsrl.utils.replay import ReplayBuffer

    n, gamma = 3, 0.9
    ro = _toy_rollout(20)
    ref_in = ro.clone()
    ref_in["next", "end_terminated"] = ref_in["next", "terminated"].clone()  # gathered from the window's end
    ref = MultiStepTransform(n, gamma).inv(ref_in)  # transitions t < 20 - n
    rb = ReplayBuffer(1000, 8, KEYS, streams=3, n_steps=n, gamma=gamma)
    for t in range(20):
        rb.extend(ro[:, t])
    got = rb[:]
    assert len(rb) == 3 * (20 - n + 1)  # sampleable once the window is complete
    want = _flat(ref)
    m = want.numel()
    _same(got[:m], want, keys=(*KEYS, "action", ("next", "rangefinder"), ("next", "state")))
    torch.testing.assert_close(got[:m]["steps_to_next_obs"].reshape(-1), want["steps_to_next_obs"].reshape(-1))
    torch.testing.assert_close(got[:m]["next", "reward"], want["next", "reward"])
    torch.testing.assert_close(got[:m]["next", "terminated"], want["next", "end_terminated"])


def test_buffer_save_load_shares_between_experiments(tmp_path):
    ro = _toy_rollout(20)
    cfg = cfg_for("algo=td3", f"run_dir={tmp_path}", "env.num_cars=3", "buffer.prioritized=true")
    rb = make_buffer(cfg, tmp_path)
    rb.extend(ro)
    rb.dumps(str(tmp_path / "shared"))
    rb2 = make_buffer(cfg, tmp_path)  # the same layout: row for row (the exact-resume path)
    rb2.loads(str(tmp_path / "shared"))
    assert (rb2.written, rb2.finals_written, len(rb2)) == (rb.written, rb.finals_written, 60)
    _same(rb2[:], _flat(ro))
    torch.testing.assert_close(rb2.priorities.prio, rb.priorities.prio)
    small = make_buffer(cfg_for("algo=td3", "env.num_cars=3", "buffer.size=30"), tmp_path)  # another capacity: the newest rows
    small.loads(str(tmp_path / "shared"))
    _same(small[:], _flat(ro[:, -10:]))
    d4pg = make_buffer(cfg_for("algo=d4pg", "env.num_cars=3"), tmp_path)  # another algorithm: n-step returns from the same rows
    d4pg.loads(str(tmp_path / "shared"))
    direct = make_buffer(cfg_for("algo=d4pg", "env.num_cars=3"), tmp_path)
    direct.extend(ro)
    _same(d4pg[:], direct[:], keys=(*KEYS, ("next", "state"), ("next", "reward"), "steps_to_next_obs"))
    with pytest.raises(ValueError, match="has 3 streams"):
        make_buffer(cfg_for("algo=td3"), tmp_path).loads(str(tmp_path / "shared"))
    disk = make_buffer(cfg_for("algo=td3", "env.num_cars=3", "buffer.storage=disk", f"buffer.path={tmp_path / 'mm'}"), tmp_path)
    disk.extend(ro)
    assert any((tmp_path / "mm").rglob("*.memmap"))
    _same(disk[:], _flat(ro))


def test_unknown_env_name_is_one_clear_line():
    with pytest.raises(ValueError, match="unknown env.name 'carla'; known: race, toy, gym"):
        build_base_env("carla", {})


@pytest.mark.parametrize("exp,algo", [("summers_dirt", "d4pg"), ("summers2022", "ddpg")])
def test_summers_presets_train_on_the_race_env_with_a_tiny_budget(tmp_path, exp, algo):
    """The seeds' presets on their own tracks and surfaces (hairpins on dirt; fast_straights/hairpins on asphalt or
    dirt), shrunk: random frames first, then updates, validation on the training track, a checkpoint."""
    cfg = compose_config(f"experiment={exp}", f"algo={algo}", "debug=smoke", f"run_dir={tmp_path}", "total_frames=300",
                         "collector.init_random_frames=100", "learner.warmup_frames=100", "eval.every_episodes=1",
                         "eval.max_steps=30", "env.max_steps=100", "checkpoint.every_frames=300")
    assert cfg.env.name == "race" and cfg.env.reward == "summers_final"
    r = train(cfg)
    assert r["frames"] >= 300 and r["updates"] > 0 and Path(r["checkpoint"]).is_file()
    assert math.isfinite(r["loss/qvalue"]) and read_csv_metric(tmp_path, "eval/reward")
