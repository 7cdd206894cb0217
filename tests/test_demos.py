"""Demonstrations (torcsrl/demos.py), their use in training (RLPD, TD3+BC, CAPS, pre-training) and BC / DAgger."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from torcsrl.training.demos import DemoError, load_demos, write_demos
from _compose import compose_config

ROOT = Path(__file__).resolve().parents[1]
RACE = ["debug=smoke", "env.track=oval", "env.max_steps=200", "eval.max_steps=30", "threads=1"]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def cfg_for(*overrides: str):
    return compose_config(*RACE, *overrides)


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demos") / "d"
    write_demos(cfg_for("demos.sigma_max=0.3", "demos.episode_steps=150"), out, frames=240, seed=5)
    return out


@pytest.fixture(scope="module")
def other_shard(tmp_path_factory):
    """A second, smaller shard (another seed): demos.path=[demo_dir, other_shard] is a pool."""
    out = tmp_path_factory.mktemp("demos") / "other"
    write_demos(cfg_for("demos.sigma_max=0.3", "demos.episode_steps=150"), out, frames=80, seed=9)
    return out


def test_demos_store_the_executed_action_and_the_experts_label(demo_dir):
    meta = json.loads((demo_dir / "demos.json").read_text())
    assert meta["frames"] == 240 and meta["record"]["obs_layout"] == "rangefinder:19,state:11"
    assert meta["stats"]["episodes"] >= 1  # 150-step episodes: at least one ended and restarted
    cfg = cfg_for()
    from torcsrl.training.demos import make_demo_env
    from torcsrl.pipeline import pipeline_record

    env = make_demo_env(cfg, 0)
    try:
        buf = load_demos(demo_dir, pipeline_record(cfg, env), 32)
    finally:
        env.close()
    rows = buf[:]
    assert len(buf) == 240
    diff = (rows["action"] - rows["expert_action"]).abs()
    assert diff.max() > 0.01  # DART noise was executed ...
    assert rows["expert_action"].abs().max() <= 1.0 and rows["action"].abs().max() <= 1.0
    assert rows["state"].abs().max() < 5  # ... and the observations are the policy's (scaled), not raw km/h
    # the expert accelerates from the grid (a traction-limited launch: ~0.46 of the pedal at 10 Hz)
    assert (rows["expert_action"][:, 1] > 0.3).float().mean() > 0.3


def test_noise_free_expert_stays_on_the_road(tmp_path):
    out = write_demos(cfg_for("demos.sigma_max=0.0", "env.start=grid", "demos.episode_steps=400"), tmp_path / "clean", frames=300, seed=1)
    stats = json.loads((out / "demos.json").read_text())["stats"]
    assert stats["terminated"] == 0


def test_demos_of_another_pipeline_are_refused_in_one_line(demo_dir):
    cfg = cfg_for("env.normalize=false")
    from torcsrl.training.demos import make_demo_env
    from torcsrl.pipeline import pipeline_record

    env = make_demo_env(cfg, 0)
    try:
        with pytest.raises(DemoError, match="normalize=True; this run has normalize=False") as err:
            load_demos(demo_dir, pipeline_record(cfg, env), 32)
    finally:
        env.close()
    assert "\n" not in str(err.value)
    with pytest.raises(DemoError, match="not a demonstration folder"):
        load_demos(demo_dir.parent, {}, 32)


def test_training_with_demos_bc_and_smoothness_runs_and_resumes(tmp_path, demo_dir):
    from torcsrl.training import train

    over = [f"demos.path={demo_dir}", "demos.bc_weight=0.4", "demos.pretrain_steps=30", "demos.critic_pretrain_steps=10",
            "algo.smooth.temporal=0.2", "algo.smooth.spatial=0.2", "collector.frames_per_batch=1", "total_frames=300",
            "checkpoint.every_frames=150", f"run_dir={tmp_path / 'run'}"]
    res = train(cfg_for(*over))
    assert res["frames"] == 300 and res["updates"] > 0
    ck = torch.load(Path(res["checkpoint"]), weights_only=False)
    assert ck["counters"]["pretrained"] is True
    from torcsrl.utils.logging import read_csv_metric

    bc = read_csv_metric(tmp_path / "run", "loss/bc")
    assert bc and all(v >= 0 for _, v in bc)


def test_actor_regularisers_pull_towards_labels_and_smooth():
    from types import SimpleNamespace

    from torcsrl.agents import _build, td3
    from torcsrl.envs.toy import make_toy_env

    env = make_toy_env(seed=0)
    cfg = cfg_for("env=toy").algo
    keys = list(env.observation_spec.keys())
    actor = td3.make_actor(cfg, env, keys)
    loss = td3.make_loss(cfg, actor, td3.make_critic(cfg, env, keys), env, keys)
    batch = env.rollout(64, break_when_any_done=False)
    label = torch.full_like(batch["action"], 0.7)
    batch.set("expert_action", label)
    reg = SimpleNamespace(bc_weight=1.0, n_demo=64, smooth=SimpleNamespace(temporal=0.5, spatial=0.5, spatial_sigma=0.05))
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    first = last = None
    for _ in range(60):
        la, q_meta = loss.actor_loss(batch)
        la, m = _build.actor_regularisers(loss, batch, q_meta["_action"], q_meta["_q"], la, reg)
        opt.zero_grad()
        la.backward()
        opt.step()
        first = first or {k: float(v) for k, v in m.items()}
        last = {k: float(v) for k, v in m.items()}
    assert set(last) == {"loss/bc", "loss/smooth_temporal", "loss/smooth_spatial"}
    assert last["loss/bc"] < 0.5 * first["loss/bc"]


@pytest.mark.parametrize("algo", ["bc", "dagger"])
def test_imitation_baselines_train_and_evaluate_like_rl_drivers(tmp_path, demo_dir, other_shard, algo):
    """BC (on a pool of two shards) and DAgger (with the cosine schedule: it decays each fit to 0 and restarts every
    round) train, and their checkpoints drive like RL drivers'."""
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import load_policy
    from torcsrl.training import train
    from torcsrl.utils.logging import read_csv_metric

    demos = f"demos.path=[{demo_dir},{other_shard}]" if algo == "bc" else f"demos.path={demo_dir}"
    res = train(cfg_for(f"algo={algo}", demos, "algo.bc_steps=40", "demos.dagger_rounds=1", "demos.dagger_frames=60",
                        "algo.bc_lr_schedule=cosine", "logger.every_frames=10", f"run_dir={tmp_path / algo}"))
    assert res["updates"] == 40 * (2 if algo == "dagger" else 1)
    assert res["frames"] == (60 if algo == "dagger" else 0)
    lr = dict(read_csv_metric(tmp_path / algo, "train/actor_lr"))
    assert 0 < lr[30] < lr[20] < lr[10] < 1e-3 and lr[40] == pytest.approx(0.0, abs=1e-12)  # fit 1 decays from actor_lr to 0
    if algo == "dagger":
        assert lr[50] == pytest.approx(lr[10]) and lr[80] == pytest.approx(0.0, abs=1e-12)  # fit 2 restarts from actor_lr
    pol = load_policy(str(tmp_path / algo))
    rows, _ = run_cell(pol, "oval", laps=1, max_steps=20, env_kwargs={"control_hz": 10, "substeps": 20})
    assert rows[0]["steps"] >= 1


def test_shards_written_apart_sample_as_one_pool(tmp_path, demo_dir, other_shard):
    """demos.path=[A, B]: shards (e.g. written on two cores with different seeds) are sampled as one pool, every
    batch in proportion to the shards' rows; an empty list or a wrong folder fails in one line."""
    from torcsrl.config import validate
    from torcsrl.training.demos import DemoPool, make_demo_env
    from torcsrl.training.demos import make_demos
    from torcsrl.pipeline import pipeline_record

    cfg = cfg_for(f"demos.path=[{demo_dir},{other_shard}]")
    env = make_demo_env(cfg, 0)
    try:
        pool = make_demos(cfg, env, tmp_path)
        assert isinstance(pool, DemoPool) and len(pool) == 240 + 80 and "expert_action" in pool.extra_keys
        batch = pool.sample(64)
        assert batch.shape == (64,)
        # 240:80 rows -> 48:16 of a batch of 64; the two shards' rows are told apart by their observations
        a, b = (load_demos(p, pipeline_record(cfg, env), 8)[:]["state"] for p in (demo_dir, other_shard))
        in_a = (batch["state"][:, None] == a[None]).all(-1).any(-1)
        in_b = (batch["state"][:, None] == b[None]).all(-1).any(-1)
        assert int(in_a.sum()) == 48 and int(in_b.sum()) == 16
        with pytest.raises(DemoError, match="empty list"):
            make_demos(cfg_for("demos.path=[]", "demos.frames=1"), env, tmp_path)
        with pytest.raises(DemoError, match="not a demonstration folder"):
            make_demos(cfg_for(f"demos.path=[{demo_dir},{tmp_path / 'nowhere'}]"), env, tmp_path)
    finally:
        env.close()
    with pytest.raises(ValueError, match="algo.bc_lr_schedule: unknown schedule 'linear'; allowed: constant, cosine"):
        validate(cfg_for("algo=bc", "algo.bc_lr_schedule=linear"))


def test_imitation_without_demonstrations_says_so(tmp_path):
    from torcsrl.training import train

    with pytest.raises(ValueError, match="set demos.frames > 0"):
        train(cfg_for("algo=bc", f"run_dir={tmp_path}"))


def test_sensor_teacher_labels_are_a_function_of_the_stored_observation(tmp_path):
    """demos.teacher=sensor: the label of every stored row is the SensorDriver applied to that row's own
    observation (unscaled): nothing the network cannot see went into it."""
    from torcsrl.transforms import obs_scale
    from torcsrl.policies import SensorDriver

    out = write_demos(cfg_for("demos.teacher=sensor", "demos.sigma_max=0.2", "demos.episode_steps=150"), tmp_path / "s", frames=200, seed=2)
    cfg = cfg_for()
    from torcsrl.training.demos import make_demo_env
    from torcsrl.pipeline import pipeline_record

    env = make_demo_env(cfg, 0)
    try:
        rows = load_demos(out, pipeline_record(cfg, env), 16)[:]
    finally:
        env.close()
    drv = SensorDriver()
    r = rows["rangefinder"] * torch.as_tensor(obs_scale("rangefinder"))
    st = rows["state"] * torch.as_tensor(obs_scale("state"))
    again = torch.tensor([drv.act(r[i].numpy(), st[i].numpy()) for i in range(len(rows))])
    torch.testing.assert_close(again, rows["expert_action"], atol=2e-3, rtol=0)  # float32 scaling round trip


@pytest.mark.parametrize("surface", ["asphalt", "dirt"])
def test_sensor_driver_laps_the_oval_at_the_training_rate(surface):
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import load_policy

    rows, _ = run_cell(load_policy("sensor"), "oval", surface, laps=1, env_kwargs={"control_hz": 10, "substeps": 20})
    assert rows[0]["success"] and rows[0]["off_track_events"] == 0


@pytest.mark.parametrize("surface", ["asphalt", "dirt"])
def test_sensor_teacher_steers_smoothly_through_esses_at_10_hz(surface):
    """The speed-scaled gains keep the 10 Hz steering loop from ringing: the first teacher's gains
    (``SensorDriver.V1``) flip the steering 50+ times per km here, the scripted expert a handful."""
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import SensorDriver

    kw = {"control_hz": 10, "substeps": 20}
    new, _ = run_cell(SensorDriver(), "esses", surface, laps=1, env_kwargs=kw)
    old, _ = run_cell(SensorDriver(**SensorDriver.V1), "esses", surface, laps=1, env_kwargs=kw)
    assert new[0]["success"] and old[0]["success"]
    assert new[0]["steer_flips_per_km"] <= 30.0 < old[0]["steer_flips_per_km"], (new[0]["steer_flips_per_km"], old[0]["steer_flips_per_km"])
    assert new[0]["fastest_lap"] < old[0]["fastest_lap"]


def test_pedal_expectile_leans_the_fit_towards_braking():
    """algo.bc_pedal_expectile=tau: where one observation carries both labels (brake -1 and throttle +1, half each),
    squared error fits the pedal to their mean 0 and the expectile fit to 2 tau - 1 (the tau-expectile of +-1);
    steering stays the squared-error fit. Out-of-range tau, tau with an RL algo or with separate pedals fails in one line."""
    from types import SimpleNamespace

    from tensordict import TensorDict

    from torcsrl.agents._build import bc_step
    from torcsrl.config import validate

    class Const(torch.nn.Module):  # the smallest actor: one free action
        def __init__(self):
            super().__init__()
            self.a = torch.nn.Parameter(torch.zeros(2))

        def forward(self, x):
            return self.a.expand(x.shape[0], 2)

    labels = torch.tensor([[0.3, -1.0], [0.3, 1.0]]).repeat(32, 1)
    batch = TensorDict({"state": torch.zeros(64, 1), "expert_action": labels}, [64])
    fits = {}
    for tau in (0.5, 0.2):
        actor = _ConstActor()
        net = SimpleNamespace(actor_network=actor, obs=lambda b: (b["state"],))
        optim = {"actor": torch.optim.SGD(actor.parameters(), lr=0.2)}
        for _ in range(300):
            bc_step(net, optim, batch, "float32", SimpleNamespace(bc_pedal_expectile=tau))
        fits[tau] = actor.a.detach()
    assert fits[0.5][1] == pytest.approx(0.0, abs=1e-4) and fits[0.2][1] == pytest.approx(2 * 0.2 - 1, abs=1e-3)
    assert fits[0.2][0] == pytest.approx(0.3, abs=1e-4) and fits[0.5][0] == pytest.approx(0.3, abs=1e-4)
    with pytest.raises(ValueError, match=r"algo.bc_pedal_expectile: 1.0 is out of range; allowed: \(0, 1\)"):
        validate(cfg_for("algo=bc", "algo.bc_pedal_expectile=1.0"))
    with pytest.raises(ValueError, match="algo.bc_pedal_expectile=0.2: the pedal expectile shapes the imitation fit of algo=bc / dagger only"):
        validate(cfg_for("algo=td3", "algo.bc_pedal_expectile=0.2"))
    with pytest.raises(ValueError, match="weighs action 1 as a pedal .*allowed: 0.5, or env.action_mode=combined"):
        validate(cfg_for("algo=bc", "algo.bc_pedal_expectile=0.2", "+env.action_mode=separate"))
    validate(cfg_for("algo=dagger", "algo.bc_pedal_expectile=0.2"))


def test_near_car_weight_leans_the_fit_to_the_rows_in_traffic():
    """algo.bc_near_car_weight=w: rows whose opponents sensor reads a car nearer than bc_near_car_m count w times.
    Half the rows have a car 5 m away (label pedal -1, lift), half a free sensor (label +1): the plain fit is 0, with
    w = 3 the weighted mean (3 (-1) + 1) / 4 = -0.5. The reach in metres becomes the stored (normalised) units; a weight
    without the opponents sensor, with an RL algo or out of range fails in one line."""
    from types import SimpleNamespace

    from tensordict import TensorDict

    from torcsrl.agents._build import bc_step, near_car_weights
    from torcsrl.config import validate
    from torcsrl.training.imitation import near_car_setting

    opp = torch.ones(64, 36)
    opp[:32, 7] = 5.0 / 200.0  # one car 5 m away, sector 7; the rest free (200 m = 1.0 normalised)
    labels = torch.tensor([[0.0, -1.0]]).repeat(64, 1)
    labels[32:, 1] = 1.0
    batch = TensorDict({"state": torch.zeros(64, 1), "opponents": opp, "expert_action": labels}, [64])
    assert near_car_weights(opp, 3.0, 15.0 / 200.0).tolist() == [3.0] * 32 + [1.0] * 32
    fits = {}
    for near in (None, (3.0, 15.0 / 200.0), (3.0, 4.0 / 200.0)):
        actor = _ConstActor()
        net = SimpleNamespace(actor_network=actor, obs=lambda b: (b["state"],))
        optim = {"actor": torch.optim.SGD(actor.parameters(), lr=0.2)}
        for _ in range(300):
            _, extra = bc_step(net, optim, batch, "float32", None, None, near)
        fits[near] = (float(actor.a.detach()[1]), float(extra.get("loss/near_car_rows", -1)))
    assert fits[None][0] == pytest.approx(0.0, abs=1e-4)
    assert fits[(3.0, 15.0 / 200.0)] == pytest.approx((-0.5, 0.5), abs=1e-4)
    assert fits[(3.0, 4.0 / 200.0)] == pytest.approx((0.0, 0.0), abs=1e-4)  # the car at 5 m is beyond a 4 m reach
    cfg = cfg_for("algo=dagger", "env.sensors=[rangefinder,state,opponents]", "algo.bc_near_car_weight=3", "algo.bc_near_car_m=20")
    validate(cfg)
    assert near_car_setting(cfg, ["rangefinder", "state", "opponents"]) == pytest.approx((3.0, 0.1))
    assert near_car_setting(cfg_for("algo=dagger"), ["rangefinder", "state"]) is None
    with pytest.raises(ValueError, match=r"algo.bc_near_car_weight=3 weighs the rows by the opponents sensor, which the actor "
                                         r"does not read .*allowed: 1.0, or env.sensors with opponents"):
        validate(cfg_for("algo=dagger", "algo.bc_near_car_weight=3"))
    with pytest.raises(ValueError, match=r"algo.bc_near_car_weight=3.0 weighs the rows by the opponents sensor"):
        near_car_setting(cfg_for("algo=dagger", "algo.bc_near_car_weight=3"), ["rangefinder", "state"])
    with pytest.raises(ValueError, match="algo.bc_near_car_weight=3: the near-car weight shapes the imitation fit of algo=bc / dagger only"):
        validate(cfg_for("algo=td3", "env.sensors=[rangefinder,state,opponents]", "algo.bc_near_car_weight=3"))
    with pytest.raises(ValueError, match=r"algo.bc_near_car_m: 0.0 is out of range; allowed: \(0, 200\]"):
        validate(cfg_for("algo=dagger", "env.sensors=[rangefinder,state,opponents]", "algo.bc_near_car_weight=3", "algo.bc_near_car_m=0.0"))


def test_a_killed_dagger_run_resumes_exactly_after_its_last_round(tmp_path, demo_dir):
    """A DAgger run stopped after round 1 and resumed (``checkpoint.resume=latest``) ends with the same actor, to the
    bit, as the run that was never stopped (CPU): the optimiser, the generators and round 1's relabelled rows
    (``<run_dir>/dagger/round_001``) come back. A missing rows folder, an empty run_dir and a checkpoint written before
    imitation runs could resume each fail in one line."""
    import shutil

    from torcsrl.training import train
    from torcsrl.utils.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint, save_checkpoint
    from torcsrl.utils.logging import read_csv_metric

    def run(d, rounds, *extra):
        return train(cfg_for("algo=dagger", f"demos.path={demo_dir}", "algo.bc_steps=20", f"demos.dagger_rounds={rounds}",
                             "demos.dagger_frames=60", "algo.bc_lr_schedule=cosine", "logger.every_frames=10", f"run_dir={d}", *extra))

    full = run(tmp_path / "full", 2)
    run(tmp_path / "cut", 1)
    assert (tmp_path / "cut" / "dagger" / "round_001" / "meta.json").is_file()
    shutil.copytree(tmp_path / "cut", tmp_path / "norows")
    shutil.copytree(tmp_path / "cut", tmp_path / "old")
    resumed = run(tmp_path / "cut", 2, "checkpoint.resume=latest")
    assert resumed["updates"] == full["updates"] == 60 and resumed["frames"] == full["frames"] == 120
    a, b = load_checkpoint(full["checkpoint"])["actor"], load_checkpoint(resumed["checkpoint"])["actor"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert read_csv_metric(tmp_path / "cut", "loss/bc") == read_csv_metric(tmp_path / "full", "loss/bc")

    with pytest.raises(CheckpointError, match=r"env.track"):  # the resume command without one of the run's env overrides
        run(tmp_path / "norows", 2, "checkpoint.resume=latest", "env.track=esses")
    with pytest.raises(CheckpointError, match=r"relabelled by demos.teacher=.*allowed: the checkpoint's teacher"):
        run(tmp_path / "norows", 2, "checkpoint.resume=latest", "demos.teacher=sensor_sight")
    shutil.rmtree(tmp_path / "norows" / "dagger" / "round_001")
    with pytest.raises(CheckpointError, match=r"round_001 \(round 1's relabelled rows\) is missing; allowed: .*checkpoint.buffer=true"):
        run(tmp_path / "norows", 3, "checkpoint.resume=latest")
    with pytest.raises(CheckpointError, match="holds no checkpoint"):
        run(tmp_path / "empty", 2, "checkpoint.resume=latest")
    last = latest_checkpoint(tmp_path / "old" / "checkpoints")
    ck = load_checkpoint(last)
    del ck["rng"], ck["optim"]
    save_checkpoint(last, ck)
    with pytest.raises(CheckpointError, match=r"holds no optim, rng \(an imitation checkpoint written before .*allowed: "):
        run(tmp_path / "old", 2, "checkpoint.resume=latest")


def test_dagger_fits_on_the_same_batches_without_the_next_observations(tmp_path, demo_dir, monkeypatch):
    """Imitation samples its batches without ``next`` (only CAPS's temporal term reads it): the same rows, so the
    actor is the one a fit on full transitions gives, to the bit; with ``algo.smooth.temporal`` > 0 it samples them whole."""
    import torcsrl.training.imitation as imitation_mod
    from torcsrl.training import train
    from torcsrl.utils.checkpoint import load_checkpoint
    from torcsrl.utils.logging import read_csv_metric

    real, asked = imitation_mod.mixed_sample, []

    def run(d, whole=False, *extra):
        def spy(buffers, batch_size, successor=True):
            asked.append(successor)
            return real(buffers, batch_size, True if whole else successor)

        monkeypatch.setattr(imitation_mod, "mixed_sample", spy)
        asked.clear()
        res = train(cfg_for("algo=dagger", f"demos.path={demo_dir}", "algo.bc_steps=20", "demos.dagger_rounds=1",
                            "demos.dagger_frames=60", "logger.every_frames=10", f"run_dir={d}", *extra))
        return load_checkpoint(res["checkpoint"])["actor"], set(asked)

    lean, flags = run(tmp_path / "lean")
    whole, _ = run(tmp_path / "whole", True)
    assert flags == {False} and lean.keys() == whole.keys() and all(torch.equal(lean[k], whole[k]) for k in lean)
    _, flags = run(tmp_path / "caps", False, "algo.smooth.temporal=0.2")
    assert flags == {True} and read_csv_metric(tmp_path / "caps", "loss/smooth_temporal")


def test_slow_rows_weigh_more_in_the_imitation_fit():
    """``algo.bc_slow_weight``: a row whose newest state reading drives slower than ``bc_slow_kmh`` counts w times.
    Half the rows crawl at 2 km/h (label pedal +1, creep off), half drive at 100 km/h (label -1): the plain fit is 0,
    with w = 3 the weighted mean (3 - 1) / 4 = +0.5. The speed is the newest reading's (a state history's last slots),
    not an older one's; with the near-car weight a row weighs the product. The km/h become the stored units; a weight
    without the race env's state, with an RL algo or out of range fails in one line."""
    from types import SimpleNamespace

    from tensordict import TensorDict

    from torcsrl.agents._build import bc_step, slow_weights
    from torcsrl.config import validate
    from torcsrl.envs.sensors import STATE_SLOTS
    from torcsrl.training.imitation import slow_setting

    n, v = len(STATE_SLOTS), STATE_SLOTS.index("speedX_kmh")
    state = torch.zeros(64, 2 * n)  # two readings, newest last
    state[:32, n + v] = 2.0 / 300.0  # crawling now
    state[32:, n + v] = 100.0 / 300.0  # driving now ...
    state[32:, v] = 1.0 / 300.0  # ... after a standstill one reading before (not counted)
    labels = torch.tensor([[0.0, 1.0]]).repeat(64, 1)
    labels[32:, 1] = -1.0
    opp = torch.ones(64, 36)
    opp[::2, 3] = 5.0 / 200.0  # every other row has a car 5 m away
    batch = TensorDict({"state": state, "opponents": opp, "expert_action": labels}, [64])
    slow = (3.0, 5.0 / 300.0, v, n)
    assert slow_weights(state, *slow).tolist() == [3.0] * 32 + [1.0] * 32
    fits = {}
    for key, near, sl in (("plain", None, None), ("slow", None, slow), ("both", (2.0, 15.0 / 200.0), slow)):
        actor = _ConstActor()
        net = SimpleNamespace(actor_network=actor, obs=lambda b: (b["state"],))
        optim = {"actor": torch.optim.SGD(actor.parameters(), lr=0.2)}
        for _ in range(300):
            _, extra = bc_step(net, optim, batch, "float32", None, None, near, sl)
        fits[key] = (float(actor.a.detach()[1]), float(extra.get("loss/slow_rows", -1)))
    assert fits["plain"] == pytest.approx((0.0, -1.0), abs=1e-4)
    assert fits["slow"] == pytest.approx((0.5, 0.5), abs=1e-4)
    assert fits["both"] == pytest.approx((0.5, 0.5), abs=1e-4)  # near-car rows double in both halves: (16 (6 + 3) - 16 (2 + 1)) / 192
    cfg = cfg_for("algo=dagger", "algo.bc_slow_weight=4", "algo.bc_slow_kmh=6")
    validate(cfg)
    assert slow_setting(cfg, ["rangefinder", "state"]) == pytest.approx((4.0, 0.02, v, n))
    assert slow_setting(cfg_for("algo=dagger"), ["rangefinder", "state"]) is None
    with pytest.raises(ValueError, match=r"algo.bc_slow_weight=4.0 weighs the rows by the state's speedX_kmh, which the actor does not read"):
        slow_setting(cfg, ["rangefinder"])
    with pytest.raises(ValueError, match=r"algo.bc_slow_weight=4 weighs the rows by the race env's state .*allowed: 1.0, or env=race with state"):
        validate(cfg_for("algo=dagger", "env.sensors=[rangefinder]", "algo.bc_slow_weight=4"))
    with pytest.raises(ValueError, match="algo.bc_slow_weight=4: the slow-row weight shapes the imitation fit of algo=bc / dagger only"):
        validate(cfg_for("algo=td3", "algo.bc_slow_weight=4"))
    with pytest.raises(ValueError, match=r"algo.bc_slow_kmh: 0.0 is out of range; allowed: \(0, 300\]"):
        validate(cfg_for("algo=dagger", "algo.bc_slow_weight=4", "algo.bc_slow_kmh=0.0"))


class _ConstActor(torch.nn.Module):
    """An actor that writes one learnt action for every row: its fit is the (weighted) mean label."""

    def __init__(self):
        super().__init__()
        self.a = torch.nn.Parameter(torch.zeros(2))

    def forward(self, x):
        return self.a.expand(x.shape[0], 2)
