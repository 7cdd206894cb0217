"""SAC and PPO through train(cfg): smoke runs (vectors and pixels), exact resume, demonstrations and smoothness (SAC),
evaluation like the other drivers, and one-line refusals of the options that do not apply to them."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torcsrl.config import ConfigError, validate
from torcsrl.training import train
from torcsrl.utils.logging import read_csv_metric

ROOT = Path(__file__).resolve().parents[1]
CONF = str(ROOT / "conf")
PIXELS = ["env.sensors=[rangefinder,state,pixels]", "algo.encoder.augment_shift=2", "checkpoint.buffer=false"]
PPO = ["algo.rollout_steps=50", "algo.epochs=2", "algo.batch_size=32"]  # rollouts of 50 steps a car, 2 epochs of minibatches of 32


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def cfg_for(*overrides: str, env: str = "toy"):
    extra = ["env=toy"] if env == "toy" else ["env.track=oval", "env.max_steps=200", "eval.max_steps=30"]
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("train", overrides=[*extra, "debug=smoke", *overrides])


@pytest.mark.parametrize("algo,extra", [("sac", PIXELS), ("ppo", [*PPO, PIXELS[0]])], ids=["sac-pixels", "ppo-pixels"])
def test_smoke(tmp_path, algo, extra):
    r = train(cfg_for(f"algo={algo}", f"run_dir={tmp_path}", "total_frames=150", "logger.every_frames=50", *extra))
    assert r["frames"] >= 150 and r["updates"] > 0
    key = "loss/qvalue" if algo == "sac" else "loss/critic"
    rows = read_csv_metric(tmp_path, key)
    assert len(rows) >= 2 and all(math.isfinite(v) for _, v in rows) and len({v for _, v in rows}) > 1  # the losses move
    if algo == "sac":
        alpha = [v for _, v in read_csv_metric(tmp_path, "loss/alpha")]
        assert alpha and alpha[-1] != 1.0  # the temperature is tuned
    else:
        assert read_csv_metric(tmp_path, "loss/objective") and read_csv_metric(tmp_path, "loss/entropy")
    assert Path(r["checkpoint"]).is_file()


@pytest.mark.parametrize("algo,extra", [("sac", []), ("ppo", [*PPO, "env.num_cars=2"])], ids=["sac-vector", "ppo-vector-2cars"])
def test_exact_resume(tmp_path, algo, extra):
    """Vector observations (PPO: two cars in one env): the losses move, and a run stopped at a checkpoint and resumed
    logs exactly what the uninterrupted run logs."""
    ov = [f"algo={algo}", *extra, "checkpoint.every_frames=200", "logger.every_frames=50", "eval.every_episodes=1"]
    ref = train(cfg_for(*ov, "total_frames=400", f"run_dir={tmp_path / 'ref'}"))
    train(cfg_for(*ov, "total_frames=200", f"run_dir={tmp_path / 'cut'}"))
    res = train(cfg_for(*ov, "total_frames=400", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    keys = ["frames", "updates", "episodes"] + (["loss/qvalue", "loss/actor", "loss/alpha"] if algo == "sac" else
                                                ["loss/objective", "loss/critic"])
    for k in keys:
        assert res[k] == ref[k], k
    for m in ("loss/qvalue" if algo == "sac" else "loss/critic", "eval/reward", "train/episode_reward"):
        assert read_csv_metric(tmp_path / "cut", m) == read_csv_metric(tmp_path / "ref", m), m
    rows = read_csv_metric(tmp_path / "ref", "loss/qvalue" if algo == "sac" else "loss/critic")
    assert len(rows) >= 2 and all(math.isfinite(v) for _, v in rows) and len({v for _, v in rows}) > 1  # the losses move
    if algo == "sac":
        assert read_csv_metric(tmp_path / "ref", "loss/alpha")[-1][1] != 1.0  # the temperature is tuned


def test_race_env_sac_with_demonstrations_and_smoothness_and_ppo_evaluate_like_the_others(tmp_path):
    """SAC learns beside demonstrations (RLPD rows, the TD3+BC term, BC pre-training) with the CAPS terms; SAC's and
    PPO's checkpoints drive as CheckpointPolicy (the mean action; PPO's observation statistics come with it)."""
    from torcsrl.training.demos import write_demos
    from torcsrl.policies import CheckpointPolicy

    demos = write_demos(cfg_for("demos.sigma_max=0.3", "demos.episode_steps=100", env="race"), tmp_path / "demos", frames=120, seed=5)
    sac = train(cfg_for("algo=sac", f"demos.path={demos}", "demos.bc_weight=0.4", "demos.pretrain_steps=10", "demos.critic_pretrain_steps=5",
                        "algo.smooth.temporal=0.2", "algo.smooth.spatial=0.2", "total_frames=150", f"run_dir={tmp_path / 'sac'}", env="race"))
    assert sac["updates"] > 0 and math.isfinite(sac["loss/bc"]) and math.isfinite(sac["loss/smooth_temporal"])
    ppo = train(cfg_for("algo=ppo", *PPO, "env.num_cars=2", "total_frames=200", f"run_dir={tmp_path / 'ppo'}", env="race"))
    for r, algo in ((sac, "sac"), (ppo, "ppo")):
        pol = CheckpointPolicy(r["checkpoint"])
        assert pol.algo == algo
        obs = {k: torch.rand(*shape) for k, shape in pol.obs_shapes.items()}
        a = pol._act(*obs.values())
        torch.testing.assert_close(a, pol._act(*obs.values()))  # deterministic
        assert a.shape == (2,) and a.abs().max() <= 1
    ck = torch.load(ppo["checkpoint"], weights_only=False)
    assert float(ck["actor"]["encoder.norm.count"]) > 0  # the statistics the policy was trained with


@pytest.mark.parametrize("overrides,line", [
    (["algo=sac", "algo.exploration.kind=ou"], "algo.exploration.kind=ou: algo=sac explores by sampling its own policy"),
    (["algo=sac", "algo.exploration.sigma=0.3"], "algo.exploration.sigma=0.3: noise settings do not apply to algo=sac"),
    (["algo=sac", "algo.policy_noise=0.2"], "algo.policy_noise=0.2: TD3's target policy smoothing does not apply to algo=sac"),
    (["algo=ppo", "demos.frames=100"], "demos: algo=ppo learns on-policy from its own rollouts and does not support demonstrations"),
    (["algo=ppo", "buffer.prioritized=true"], "buffer.prioritized=true: algo=ppo has no replay buffer and does not support prioritised"),
    (["algo=ppo", "algo.encoder.augment_shift=4"], "algo.encoder.augment_shift=4: algo=ppo does not augment its images"),
    (["algo=ppo", "algo.lr_schedule=cosine"], "algo.lr_schedule: unknown schedule 'cosine'; allowed: constant, linear"),
    (["algo=ppo", "algo.target_kl=0"], "algo.target_kl=0: the approximate KL at which a rollout's epochs stop; allowed: a number > 0"),
    (["algo=td3", "algo.lr_schedule=linear"], "algo.lr_schedule=linear: the learning-rate schedule applies to algo=ppo only"),
    (["algo=sac", "algo.target_kl=0.02"], "algo.target_kl=0.02: the KL early stop of a rollout's epochs applies to algo=ppo only"),
    (["algo=td3", "algo.log_std_end=-1"], "algo.log_std_end=-1: the policy-std schedule applies to algo=ppo only; allowed: null"),
    (["algo=ppo", "algo.log_std_end=-9"], "algo.log_std_end=-9: the policy's log std at total_frames; allowed: a number in [-5, 2]"),
])

def test_options_that_do_not_apply_are_refused_in_one_line(overrides, line):
    with pytest.raises(ConfigError) as err:
        validate(cfg_for(*overrides))
    assert str(err.value).count("\n") == 0 and line in str(err.value)


def test_a_log_std_list_of_the_wrong_length_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match=r"^algo.log_std_init=\[0.0, 0.0, 0.0\]: one number, or one per action dimension \(2\)$"):
        train(cfg_for("algo=ppo", *PPO, "algo.log_std_init=[0,0,0]", f"run_dir={tmp_path}", "total_frames=100"))


def test_ppo_linear_learning_rate_kl_early_stop_and_smoothness(tmp_path):
    """``algo.lr_schedule=linear`` takes the rates from actor_lr/critic_lr towards 0 over the run, set before each
    rollout's update; ``algo.target_kl`` stops a rollout's epochs early (logged as train/epochs, fewer than asked); the
    CAPS terms (``algo.smooth``) act on PPO's mean action and are logged; a run stopped at a checkpoint and resumed
    follows the same schedule exactly."""
    ov = ["algo=ppo", *PPO, "env.num_cars=2", "algo.epochs=8", "algo.lr_schedule=linear", "algo.target_kl=0.0005",
          "algo.smooth.temporal=1.0", "algo.smooth.spatial=0.5",
          "checkpoint.every_frames=200", "logger.every_frames=100", "eval.every_episodes=1000"]
    ref = train(cfg_for(*ov, "total_frames=400", f"run_dir={tmp_path / 'ref'}"))
    epochs = [v for _, v in read_csv_metric(tmp_path / "ref", "train/epochs")]
    assert epochs and min(epochs) < 8  # a tiny target KL stops the epochs early
    for term in ("loss/smooth_temporal", "loss/smooth_spatial"):
        rows = read_csv_metric(tmp_path / "ref", term)
        assert rows and all(math.isfinite(v) and v >= 0 for _, v in rows), term
    ck = torch.load(ref["checkpoint"], weights_only=False)
    lrs = [g["lr"] for g in ck["optim"]["actor"]["param_groups"]]
    assert lrs == [pytest.approx(3e-4 * (1 - 300 / 400))]  # the last rollout (frames 300..400) ran at 1/4 of the rate
    # the schedule runs over total_frames, so the exact-resume check holds it constant (a run cut by a smaller
    # total_frames would anneal over that one)
    ov = [*ov, "algo.lr_schedule=constant"]
    ref = train(cfg_for(*ov, "total_frames=400", f"run_dir={tmp_path / 'ref2'}"))
    train(cfg_for(*ov, "total_frames=200", f"run_dir={tmp_path / 'cut'}"))
    res = train(cfg_for(*ov, "total_frames=400", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    for k in ("frames", "updates", "loss/objective", "loss/critic", "loss/smooth_temporal", "loss/smooth_spatial"):
        assert res[k] == ref[k], k


def test_ppo_log_std_schedule_sets_the_std_each_rollout_explores_with(tmp_path):
    """``algo.log_std_end``: the actor's log std goes linearly from log_std_init to log_std_end over total_frames, set
    before each rollout and not moved by the updates (learnt, it would drift from the schedule's value)."""
    ov = ["algo=ppo", *PPO, "env.num_cars=2", "algo.log_std_init=0.0", "algo.log_std_end=-1.0", "algo.actor_lr=0.05",
          "checkpoint.every_frames=100", "checkpoint.keep=10", "logger.every_frames=100", "eval.every_episodes=1000",
          "total_frames=400"]
    out = train(cfg_for(*ov, f"run_dir={tmp_path / 'sched'}"))
    ckpts = sorted((tmp_path / "sched" / "checkpoints").glob("ckpt_*.pt"))
    assert len(ckpts) >= 3 and out["frames"] == 400
    for path in ckpts:
        ck = torch.load(path, weights_only=False)
        frames = int(ck["counters"]["frames"])
        torch.testing.assert_close(ck["actor"]["log_std"], torch.full((2,), -frames / 400))  # the next rollout's std
    learnt = train(cfg_for(*ov[:-1], "algo.log_std_end=null", "total_frames=400", f"run_dir={tmp_path / 'learnt'}"))
    ck = torch.load(learnt["checkpoint"], weights_only=False)
    assert not torch.allclose(ck["actor"]["log_std"], torch.zeros(2))  # without the schedule the updates move it


def test_set_learning_rates_schedules():
    from torcsrl.training.onpolicy import set_learning_rates

    opt = {"actor": torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=1.0)}
    set_learning_rates(opt, {"actor": 2e-4}, "constant", 50, 100)
    assert opt["actor"].param_groups[0]["lr"] == 1.0  # constant: the optimiser keeps its rate
    set_learning_rates(opt, {"actor": 2e-4}, "linear", 50, 100)
    assert opt["actor"].param_groups[0]["lr"] == pytest.approx(1e-4)
    set_learning_rates(opt, {"actor": 2e-4}, "linear", 150, 100)
    assert opt["actor"].param_groups[0]["lr"] == 0.0  # past the budget (a resumed run with more frames): never negative
    with pytest.raises(ValueError, match="allowed: constant, linear"):
        set_learning_rates(opt, {"actor": 2e-4}, "cosine", 0, 100)


def test_ppo_caps_temporal_term_pulls_consecutive_mean_actions_together():
    """A few steps of the temporal CAPS term alone bring mu(s) and mu(s') closer (the gradient reaches the actor)."""
    from torcsrl.nets import TanhGaussianActor
    from torcsrl import agents
    from torcsrl.objectives.ppo import PPOBatch
    from torcsrl.pipeline import actor_obs_keys, make_train_env

    torch.manual_seed(0)
    cfg = cfg_for("algo=ppo", *PPO)
    env = make_train_env(cfg)
    keys = actor_obs_keys(cfg)
    agent = agents.get("ppo")
    actor, critic = agent.make_actor(cfg.algo, env, keys), agent.make_critic(cfg.algo, env, keys)
    loss = agent.make_loss(cfg.algo, actor, critic, env, keys)
    assert isinstance(actor, TanhGaussianActor)
    obs = [torch.randn(64, *env.observation_spec[k].shape) for k in keys]
    nxt = [torch.randn(64, *env.observation_spec[k].shape) for k in keys]
    z = torch.zeros(64)
    batch = PPOBatch(actor.encoder.prepare(*obs), critic.encoder.prepare(*obs), torch.zeros(64, 2), z, z, z[:, None], z[:, None],
                     actor.encoder.prepare(*nxt))
    opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
    first = None
    for _ in range(50):
        total, out = loss.smoothness(batch, temporal=1.0)
        first = float(out["loss/smooth_temporal"]) if first is None else first
        opt.zero_grad()
        total.backward()
        opt.step()
    assert float(out["loss/smooth_temporal"]) < 0.5 * first
    env.close()


@pytest.mark.parametrize("preset", ["generalise_rl", "generalise_rl_stable", "generalise_rl_student"])
def test_generalise_rl_preset_trains_on_the_race_env(tmp_path, preset):
    """``experiment=generalise_rl`` (and its stable variant) with a tiny budget: its levers (linear rates, KL stop, CAPS)
    run together on the procedural pool with surfaces drawn per episode, validation per training track, and a
    checkpoint is written."""
    if preset == "generalise_rl_stable":  # the variant changes only the update's size (its minibatch is shrunk below)
        c = cfg_for(f"experiment={preset}")
        assert (c.algo.epochs, c.algo.actor_lr, c.algo.clip_epsilon) == (4, 1e-4, 0.1)  # (minibatch and budget: smoke-sized here)
    if preset == "generalise_rl_student":  # the shipped student as the start: its network's size, not the smoke one
        assert cfg_for(f"experiment={preset}").init.actor.endswith("reference_dagger.pt")
    student = ["algo.actor_hidden=[256,256]"] if preset == "generalise_rl_student" else []
    cfg = cfg_for(f"experiment={preset}", *student, f"run_dir={tmp_path}", "total_frames=200", "env.num_cars=2", "algo.rollout_steps=50",
                  "algo.batch_size=32", "env.procedural.pool=2", "env.max_steps=40", "eval.env.track=oval", "eval.every_episodes=1", "eval.max_steps=30",
                  "logger.every_frames=100", "checkpoint.every_frames=100", env="race")
    assert cfg.algo.lr_schedule == "linear" and cfg.algo.target_kl == 0.02 and cfg.algo.smooth.temporal == 0.5
    r = train(cfg)
    assert r["frames"] >= 200 and r["updates"] > 0 and Path(r["checkpoint"]).is_file()
    assert read_csv_metric(tmp_path, "loss/smooth_temporal") and read_csv_metric(tmp_path, "eval/oval/laps")


def test_ppo_starts_from_a_deterministic_imitation_student():
    """``init.actor`` of a deterministic student (the shipped DAgger driver) into PPO's tanh-Gaussian actor: the student's
    network becomes the mean, so PPO's deterministic action is the student's action; the std starts at log_std_init."""
    from torcsrl import agents
    from torcsrl.pipeline import actor_obs_keys, make_train_env
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.training.common import make_networks

    asset = ROOT / "torcsrl" / "assets" / "reference_dagger.pt"
    cfg = cfg_for("experiment=generalise_rl_stable", "algo.obs_norm=false", f"init.actor={asset}", "algo.log_std_init=-1.5",
                  "algo.actor_hidden=[256,256]",
                  "env.num_cars=2", env="race")
    env = make_train_env(cfg)
    try:
        keys = actor_obs_keys(cfg)
        actor, _, _ = make_networks(cfg, agents.get("ppo"), env, keys, torch.device("cpu"))
    finally:
        env.close()
    student = CheckpointPolicy(asset).actor
    torch.manual_seed(0)
    obs = [torch.rand(16, 19) * 100, torch.randn(16, 11)]
    with torch.no_grad():
        torch.testing.assert_close(actor(*obs), student(*obs))
    torch.testing.assert_close(actor.log_std.data, torch.full((2,), -1.5))


def test_ppo_with_a_privileged_critic_reads_the_road_in_its_value_network_only(tmp_path):
    """``critic_obs_keys=[rangefinder,state,road]`` with algo=ppo: the training env adds the privileged ``road`` sensor,
    the value network reads it (and its running statistics cover it), the actor and the exported driver do not: the
    checkpoint drives an env without it."""
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.utils.checkpoint import load_checkpoint

    cfg = cfg_for("algo=ppo", *PPO, "env.num_cars=2", "total_frames=200", "critic_obs_keys=[rangefinder,state,road]",
                  f"run_dir={tmp_path}", env="race")
    r = train(cfg)
    assert r["updates"] > 0 and math.isfinite(r["loss/critic"])
    ck = load_checkpoint(r["checkpoint"])
    first = {k: v for k, v in ck["critic"].items() if k.endswith("net.0.weight")}
    actor_first = {k: v for k, v in ck["actor"].items() if k.endswith("net.0.weight") and not k.startswith("grip")}
    assert next(iter(first.values())).shape[1] == next(iter(actor_first.values())).shape[1] + 6  # the road's 6 slots
    pol = CheckpointPolicy(r["checkpoint"])
    assert list(pol.obs_keys) == ["rangefinder", "state"]
    from torcsrl.envs import make_env

    env = make_env(track="oval", sensors=("rangefinder", "state"), seed=0)
    try:
        pol.check_env(env)
        td = env.reset()
        assert pol(td)["action"].shape == (2,)
    finally:
        env.close()


def test_generalise_grip_presets_train_the_student_then_ppo_past_it(tmp_path):
    """``experiment=generalise_grip`` (DAgger of the fast grip-aware teacher into a grip student) and
    ``experiment=generalise_rl_grip`` (PPO from that student's checkpoint) with tiny budgets: the student has a grip head
    on a 30-reading state history; PPO starts from it, keeps the head, and writes a checkpoint that still has it."""
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.utils.checkpoint import latest_checkpoint

    small = ["env.procedural.pool=2", "env.max_steps=40", "eval.env.track=oval", "eval.max_steps=30"]
    student = cfg_for("experiment=generalise_grip", *small, "demos.frames=120", "demos.episode_steps=60", "algo.bc_steps=10",
                      "demos.dagger_rounds=1", "demos.dagger_frames=40", f"run_dir={tmp_path / 'grip'}", env="race")
    assert student.demos.teacher == "racer_safe:1.27:8:9" and student.state_history == 30
    train(student)
    ck = latest_checkpoint(tmp_path / "grip" / "checkpoints")
    assert CheckpointPolicy(ck).actor.grip_head is not None
    cfg = cfg_for("experiment=generalise_rl_grip", *small, f"init.actor={ck}", f"run_dir={tmp_path / 'ppo'}", "total_frames=200",
                  "env.num_cars=2", "algo.rollout_steps=50", "algo.batch_size=32", "eval.every_episodes=1", "checkpoint.every_frames=100",
                  env="race")
    r = train(cfg)
    assert r["updates"] > 0
    pol = CheckpointPolicy(r["checkpoint"])
    assert pol.state_history == 30 and pol.actor.grip_head is not None and hasattr(pol.actor, "log_std")
