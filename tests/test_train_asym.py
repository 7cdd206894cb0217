"""Asymmetric actor-critic (``critic_obs_keys``), ``init.actor`` and ``learner.critic_warmup_updates``: a smoke run of
experiment=camera_asym on the race env, what is stored and checkpointed, starting an actor from a checkpoint, and the
one-line errors for critic keys and checkpoints that do not fit."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from torcsrl import agents
from torcsrl.config import ConfigError, validate
from torcsrl.training import train
from torcsrl.policies import CheckpointPolicy, export_policy
from torcsrl.pipeline import critic_obs_keys, make_eval_envs, make_train_env, stored_keys
from torcsrl.training.common import make_networks
from torcsrl.training.offpolicy import make_buffer
from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint
from torcsrl.utils.logging import read_csv_metric
from _compose import compose_config

ROOT = Path(__file__).resolve().parents[1]
#: camera_asym shrunk: 32x32 frames (debug=smoke) need a two-layer CNN; one named track, validated on it
SMALL = ["experiment=camera_asym", "debug=smoke", "env.track=oval", "env.procedural=null", "eval.env={}", "eval.per_track=false",
         "collector.init_random_frames=100", "learner.warmup_frames=100", "buffer.size=10000", "algo.encoder.cnn_channels=[8,8]",
         "algo.encoder.cnn_kernels=[8,4]", "algo.encoder.cnn_strides=[4,2]", "algo.encoder.feature_dim=16", "checkpoint.buffer=false",
         "env.max_steps=100", "eval.every_episodes=1"]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def compose_cfg(*overrides: str):
    return compose_config(*overrides)


def test_camera_asym_composes_to_a_camera_actor_and_a_privileged_critic():
    cfg = compose_cfg("experiment=camera_asym")
    validate(cfg)
    assert cfg.algo.name == "td3" and list(cfg.env.sensors) == ["pixels", "telemetry"]
    assert critic_obs_keys(cfg) == ["rangefinder", "state"] and cfg.algo.encoder.augment_shift > 0
    assert stored_keys(cfg) == ["pixels", "telemetry", "rangefinder", "state"]
    assert critic_obs_keys(compose_cfg()) is None  # the default: the critic sees what the actor sees
    assert critic_obs_keys(compose_cfg("critic_obs_keys=[rangefinder,state]")) is None  # the actor's own keys: symmetric


def test_smoke_asymmetric_td3_on_the_race_env(tmp_path):
    r = train(compose_cfg(*SMALL, f"run_dir={tmp_path}", "total_frames=300", "learner.critic_warmup_updates=20",
                          "algo.policy_delay=1"))  # an actor step before every log
    assert r["frames"] >= 300 and r["updates"] > 20 and math.isfinite(r["loss/qvalue"]) and math.isfinite(r["eval/reward"])
    # a row: the actor's uint8 frame + telemetry (9), the critic's rangefinder (19) + state (11), action, reward, flags, pointer
    assert r["bytes_per_transition"] == 3 * 32 * 32 + 4 * (9 + 19 + 11) + 4 * 2 + 4 + 3 + 4
    actor_losses = read_csv_metric(tmp_path, "loss/actor")
    assert actor_losses and all(math.isfinite(v) for _, v in actor_losses)
    ck = load_checkpoint(r["checkpoint"])
    # the checkpoint describes the actor's observations; the critic's layout is recorded for resuming only
    assert ck["meta"]["obs_layout"] == "pixels:3x32x32,telemetry:9" and ck["meta"]["pipeline"]["scales"].keys() == {"telemetry"}
    assert ck["meta"]["critic_obs_layout"] == "rangefinder:19,state:11"
    assert ck["loss"]["qvalue_network_params.layers.0.weight"].shape[1] == 19 + 11 + 2  # critic input: its vectors + action
    # the exported actor drives an env WITHOUT the rangefinder
    pol = CheckpointPolicy(r["checkpoint"])
    assert pol.obs_keys == ("pixels", "telemetry") and pol.env_overrides["sensors"] == ("pixels", "telemetry")
    from torcsrl.envs import make_env

    env = make_env(sensors=("pixels", "telemetry"), camera={"height": 32, "width": 32}, track="oval", seed=0)
    try:
        assert "rangefinder" not in env.observation_spec.keys()
        pol.check_env(env)
        td = pol(env.reset())
        assert td["action"].shape[-1] == 2 and torch.isfinite(td["action"]).all()
    finally:
        env.close()


def test_training_env_has_both_sets_validation_env_the_actors_only():
    cfg = compose_cfg(*SMALL)
    env, evals = make_train_env(cfg), make_eval_envs(cfg)
    try:
        assert {"pixels", "telemetry", "rangefinder", "state"} <= set(env.observation_spec.keys())
        ev = evals[""]
        assert {"pixels", "telemetry"} <= set(ev.observation_spec.keys())
        assert not {"rangefinder", "state"} & set(ev.observation_spec.keys())
        # the collector's policy reads only the actor's keys
        actor, critic, loss = make_networks(cfg, agents.get("td3"), env, ["pixels", "telemetry"], torch.device("cpu"))
        policy = agents.get("td3").make_exploration(cfg.algo, actor, env, ["pixels", "telemetry"])
        assert set(policy.in_keys) == {"pixels", "telemetry"}
        assert critic.encoder.keys == ["rangefinder", "state"] and actor.encoder.keys == ["pixels", "telemetry"]
        assert set(loss.in_keys) >= {"pixels", "telemetry", "rangefinder", "state", ("next", "state"), ("next", "pixels")}
        # the buffer stores both sets; the sampled batch feeds both networks
        buf = make_buffer(cfg, Path("/nonexistent"))
        td = env.reset()
        for _ in range(4):
            td = policy(td)
            out, td = env.step_and_maybe_reset(td)
            buf.extend(out)
        batch = buf.sample(3)
        assert batch["pixels"].dtype == torch.uint8 and batch["next", "rangefinder"].shape == (3, 19)
        lq, _ = loss.value_loss(batch)
        la, _ = loss.actor_loss(batch)
        assert torch.isfinite(lq) and torch.isfinite(la)
    finally:
        env.close()
        evals[""].close()


def test_init_actor_loads_a_checkpoint_and_a_policy_file(tmp_path):
    src = train(compose_cfg(*SMALL, f"run_dir={tmp_path / 'src'}", "total_frames=200"))
    trained = CheckpointPolicy(src["checkpoint"]).actor.state_dict()
    export_policy(src["checkpoint"], tmp_path / "actor.pt")
    for spec in (tmp_path / "src", tmp_path / "actor.pt"):  # a run folder (its newest checkpoint), a policy file
        cfg = compose_cfg(*SMALL, f"init.actor={spec}", "seed=7")
        env = make_train_env(cfg)
        try:
            actor, _, loss = make_networks(cfg, agents.get("td3"), env, ["pixels", "telemetry"], torch.device("cpu"))
        finally:
            env.close()
        for k, v in trained.items():
            assert torch.equal(actor.state_dict()[k], v), k
            assert torch.equal(loss.state_dict()[f"target_actor_network_params.{k}"], v), k  # the target starts as it too
    fresh_env = make_train_env(compose_cfg(*SMALL, "seed=7"))
    try:
        fresh, _, _ = make_networks(compose_cfg(*SMALL, "seed=7"), agents.get("td3"), fresh_env, ["pixels", "telemetry"], torch.device("cpu"))
    finally:
        fresh_env.close()
    assert not torch.equal(fresh.net[0].weight, trained["net.0.weight"])  # without init.actor: a fresh actor


def _one_line(err) -> str:
    msg = str(err.value)
    assert "\n" not in msg, msg
    return msg


def test_init_actor_refuses_what_does_not_fit(tmp_path):
    env = make_train_env(compose_cfg(*SMALL))
    try:
        def build(*ov):
            cfg = compose_cfg(*SMALL, *ov)
            return make_networks(cfg, agents.get("td3"), env, list(cfg.env.sensors), torch.device("cpu"))

        rangefinder_driver = ROOT / "torcsrl" / "assets" / "reference_dagger.pt"
        with pytest.raises(ValueError) as e:
            build(f"init.actor={rangefinder_driver}")
        assert "sees 'rangefinder:19,state:11'" in _one_line(e) and "this run's actor sees 'pixels:3x32x32,telemetry:9'" in str(e.value)
        with pytest.raises(ValueError) as e:
            build(f"init.actor={tmp_path / 'nothing'}")
        assert "no such file or folder" in _one_line(e)
        (tmp_path / "empty").mkdir()
        with pytest.raises(ValueError) as e:
            build(f"init.actor={tmp_path / 'empty'}")
        assert "holds no checkpoint" in _one_line(e)
        from torcsrl.policies import export_ensemble

        ens = export_ensemble([rangefinder_driver, rangefinder_driver], tmp_path / "ens.pt")
        with pytest.raises(ValueError) as e:  # an ensemble file is several actors
            build(f"init.actor={ens}")
        assert "an ensemble of 2 students, not one actor" in _one_line(e) and "torcsrl.policies member" in str(e.value)
        src = train(compose_cfg(*SMALL, f"run_dir={tmp_path / 'src'}", "total_frames=150"))
        with pytest.raises(ValueError) as e:  # same observations, another network shape
            build(f"init.actor={src['checkpoint']}", "algo.actor_hidden=[16,16]")
        assert "actor network differs" in _one_line(e) and "algo.actor_hidden" in str(e.value)
    finally:
        env.close()


def test_asymmetric_td3_learns_from_demonstrations_that_keep_the_critics_keys(tmp_path):
    """TD3+BC / RLPD on the asymmetric actor-critic: the demonstrations keep the critic's rangefinder and state beside
    the actor's pixels and telemetry; a folder written for the actor alone (camera_distill's) is refused in one line."""
    import json

    from torcsrl.training.demos import DemoError, write_demos

    demo = ["demos.teacher=sensor_sight", "demos.episode_steps=100", "demos.bc_weight=0.4", "demos.pretrain_steps=5"]
    r = train(compose_cfg(*SMALL, *demo, f"run_dir={tmp_path / 'run'}", "total_frames=300", "demos.frames=150"))
    kept = json.loads((tmp_path / "run" / "demos" / "meta.json").read_text())["obs_keys"]
    assert kept == ["pixels", "telemetry", "rangefinder", "state"]
    assert r["frames"] >= 300 and math.isfinite(r["loss/qvalue"])
    actor_losses = read_csv_metric(tmp_path / "run", "loss/actor")
    assert actor_losses and all(math.isfinite(v) for _, v in actor_losses)
    actor_only = write_demos(compose_cfg(*SMALL, *demo, "critic_obs_keys=null"), tmp_path / "actor_only", frames=120, seed=3)
    assert json.loads((actor_only / "meta.json").read_text())["obs_keys"] == ["pixels", "telemetry"]
    with pytest.raises(DemoError) as e:
        train(compose_cfg(*SMALL, *demo, f"run_dir={tmp_path / 'run2'}", "total_frames=300", f"demos.path={actor_only}"))
    assert "this run also needs ['rangefinder', 'state']" in _one_line(e)


@pytest.mark.parametrize(
    "overrides,words",
    [
        (["critic_obs_keys=[lidar]"], "critic_obs_keys: unknown sensor(s) ['lidar']; allowed: rangefinder, state, telemetry"),
        (["critic_obs_keys=[]"], "critic_obs_keys: expected a non-empty list of sensors or null"),
        (["algo=dagger", "critic_obs_keys=[rangefinder]"], "critic_obs_keys: algo=dagger has no critic"),
    ],
)
def test_bad_critic_keys_are_one_line_before_any_work(tmp_path, overrides, words):
    with pytest.raises(ConfigError) as e:
        train(compose_cfg("env=toy", "debug=smoke", "env.sensors=[pixels]", f"run_dir={tmp_path / 'run'}", *overrides))
    assert words in _one_line(e) and not (tmp_path / "run").exists()


def test_resuming_with_other_critic_keys_is_refused(tmp_path):
    base = ["env=toy", "debug=smoke", "env.sensors=[pixels]", "algo.encoder.cnn_channels=[8,8]", f"run_dir={tmp_path}",
            "total_frames=150", "checkpoint.buffer=false"]
    train(compose_cfg(*base))
    with pytest.raises(CheckpointError) as e:
        train(compose_cfg(*base, "critic_obs_keys=[rangefinder,state]", "checkpoint.resume=latest", "total_frames=300"))
    assert "critic_obs_layout=None; this run expects critic_obs_layout='rangefinder:19,state:6'" in _one_line(e)
