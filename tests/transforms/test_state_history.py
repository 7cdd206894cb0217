"""``state_history: K``: the actor sees the last K readings of its on-board state (torcsrl.transforms.FrameStack, dim=-1),
in training, in demonstrations and in a checkpoint driving the plain one-reading envs of evaluate / report."""

from __future__ import annotations

import pytest
import torch

from _compose import compose_config
from _history import assert_policy_history_matches_training_env
from torcsrl.transforms import FrameStack, stack_frames

RACE = ["debug=smoke", "env.track=oval", "env.max_steps=200", "eval.max_steps=30", "threads=1"]


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def test_stack_frames_along_the_last_dim_keeps_the_newest_reading_last():
    a, b, c = (torch.full((2, 3), float(v)) for v in (1, 2, 3))
    h = stack_frames(None, a, 3, dim=-1)
    assert h.shape == (2, 9) and torch.equal(h, torch.ones(2, 9))  # an episode's start: K copies of the first reading
    h = stack_frames(h, b, 3, dim=-1)
    h = stack_frames(h, c, 3, dim=-1)
    assert h[0].tolist() == [1, 1, 1, 2, 2, 2, 3, 3, 3]
    assert torch.equal(stack_frames(h, a, 3, dim=-1)[:, :6], h[:, 3:])  # the oldest reading leaves
    r = stack_frames(h, torch.tensor([[7.0] * 3, [8.0] * 3]), 3, dim=-1, restart=[1])  # row 1 starts a new episode
    assert r[0].tolist() == [2, 2, 2, 3, 3, 3, 7, 7, 7] and r[1].tolist() == [8.0] * 9
    with pytest.raises(ValueError, match="dim=-2"):
        FrameStack(3, ["state"], dim=-2)


def test_the_training_env_and_the_checkpoints_own_history_agree_across_a_reset(tmp_path):
    """A DAgger student with state_history=4 (demonstrations written at K=4, one relabelling round): its checkpoint reads
    the one-reading env (obs_shapes: state [11]) and, keeping the history itself (scaled, then stacked), feeds its actor
    exactly what the training env fed it, across an episode's end."""
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.training import train
    from torcsrl.utils.checkpoint import latest_checkpoint

    cfg = compose_config(*RACE, "algo=dagger", "state_history=4", "demos.frames=120", "algo.bc_steps=10",
                         "demos.dagger_rounds=1", "demos.dagger_frames=40", f"run_dir={tmp_path / 'run'}")
    res = train(cfg)
    assert res["updates"] == 20 and res["frames"] == 40  # round 1 drove 40 frames
    pol = CheckpointPolicy(latest_checkpoint(tmp_path / "run" / "checkpoints"))
    assert pol.state_history == 4 and pol.obs_shapes["state"] == (11,) and pol.obs_shapes["rangefinder"] == (19,)
    assert pol.meta["obs_layout"] == "rangefinder:19,state:44" and pol.meta["pipeline"]["state_history"] == 4
    from torcsrl.evaluate.batched import supports_batch

    assert supports_batch(pol)  # the report's RowActor keeps each car's readings (tests/test_batched_eval.py)
    last = assert_policy_history_matches_training_env(pol, cfg, 9, action=lambda t: (0.1 * (t % 3 - 1), 0.8))
    assert not torch.equal(last["state"][:11], last["state"][-11:])  # the history holds different readings


def test_demonstrations_of_another_history_are_refused_in_one_line(tmp_path):
    from torcsrl.training.demos import DemoError, load_demos, make_demo_env, write_demos
    from torcsrl.pipeline import pipeline_record

    write_demos(compose_config(*RACE, "state_history=3"), tmp_path / "d", frames=30, seed=1)
    cfg = compose_config(*RACE)
    env = make_demo_env(cfg, 0)
    try:
        with pytest.raises(DemoError, match=r"written with state_history=3; this run has state_history=1") as err:
            load_demos(tmp_path / "d", pipeline_record(cfg, env), 8)
        assert "\n" not in str(err.value)
    finally:
        env.close()


@pytest.mark.parametrize("over, msg", [
    (["state_history=0"], "state_history: expected an integer from 1 to 100"),
    (["state_history=4", "env.sensors=[rangefinder]"], r"state_history=4 stacks the on-board state \(state, telemetry\)"),
    (["state_history=4", "algo=ppo", "algo.grip_estimate=1.0"], r"algo.grip_estimate=1.0: algo=ppo keeps the grip head of the student"),
    (["frame_stack=4", "algo=ppo", "env.sensors=[camera]"], "frame_stack=4: algo=ppo is not built for frame stacks yet"),
])
def test_a_history_the_actor_cannot_have_is_one_line(over, msg):
    import re

    from torcsrl.config import problems

    found = problems(compose_config(*RACE, *over))
    assert any(re.search(msg, line) for line in found), found


def test_ppo_trains_on_a_state_history_from_a_grip_student(tmp_path):
    """PPO with ``state_history=4`` started from a DAgger grip student (``init.actor``; the head reads the history, the
    MLP the newest 2 readings): before any update its deterministic action is the student's; PPO's updates move the
    policy but not the grip head (its estimate enters the MLP detached); its checkpoint keeps its own history and
    drives the plain one-reading env as the training env fed it."""
    from torcsrl import agents
    from torcsrl.pipeline import actor_obs_keys, make_train_env
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.training import train
    from torcsrl.training.common import make_networks
    from torcsrl.utils.checkpoint import latest_checkpoint, load_checkpoint

    grip = ["state_history=4", "algo.grip_estimate=1.0", "algo.grip_inputs=history", "algo.actor_readings=2", "algo.actor_hidden=[32,32]"]
    train(compose_config(*RACE, "algo=dagger", *grip, "demos.frames=120", "algo.bc_steps=10", "demos.dagger_rounds=0",
                         f"run_dir={tmp_path / 'student'}"))
    student_ck = latest_checkpoint(tmp_path / "student" / "checkpoints")
    student = CheckpointPolicy(student_ck)
    ppo = [*RACE, "algo=ppo", *grip, f"init.actor={student_ck}", "algo.obs_norm=false", "algo.log_std_init=-1.6", "env.num_cars=2",
           "algo.rollout_steps=20", "algo.batch_size=20", "algo.epochs=2"]
    cfg = compose_config(*ppo, "total_frames=80", f"run_dir={tmp_path / 'ppo'}")
    env = make_train_env(cfg)
    try:
        actor, _, _ = make_networks(cfg, agents.get("ppo"), env, actor_obs_keys(cfg), torch.device("cpu"))
        obs = env.reset()
        x = [obs.get(k) for k in actor_obs_keys(cfg)]
        with torch.no_grad():
            torch.testing.assert_close(actor(*x), student.actor(*x))
    finally:
        env.close()
    res = train(cfg)
    assert res["updates"] > 0
    ck = load_checkpoint(res["checkpoint"])
    sd = ck["actor"]
    for k, v in student.actor.state_dict().items():
        if k.startswith("grip_head."):
            assert torch.equal(sd[k], v), k  # the head as loaded
    assert any(not torch.equal(sd[k], v) for k, v in student.actor.state_dict().items() if k.startswith("net."))  # the policy moved
    pol = CheckpointPolicy(res["checkpoint"])
    assert pol.state_history == 4 and pol.actor.grip_head is not None
    one_car = compose_config(*ppo, "env.num_cars=1", f"run_dir={tmp_path / 'ppo'}")
    assert_policy_history_matches_training_env(pol, one_car, 9, action=lambda t: (0.1 * (t % 3 - 1), 0.8))
