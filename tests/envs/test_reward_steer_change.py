"""The steer_change reward term: |steering command - the previous step's|, 0 after a reset, off in every preset."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import torcsrl  # noqa: F401
from torcsrl.envs.rewards import PRESETS, REWARD_TERMS, Reward


def test_no_preset_weighs_steer_change_and_a_mapping_turns_it_on():
    assert all(w.get("steer_change", 0.0) == 0.0 for w in PRESETS.values())
    r = Reward({"preset": "progress", "steer_change": -0.5}, scale=2.0)
    terms = np.zeros((len(REWARD_TERMS), 2))
    terms[REWARD_TERMS.index("progress")] = [1.0, 1.0]
    terms[REWARD_TERMS.index("steer_change")] = [0.0, 2.0]
    assert r(terms).tolist() == [2.0, 2.0 * (1.0 - 1.0)]
    with pytest.raises(ValueError, match="unknown reward terms"):
        Reward({"preset": "progress", "steer_rate": -1.0})


def test_the_term_measures_the_command_change_and_restarts_at_zero():
    env = gym.make("torcsrl/Race-v0", reward={"preset": "progress", "steer_change": -1.0}, disable_env_checker=True)
    env.reset(seed=0)
    changes, rewards = [], []
    for a in ([0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5], [2.0, 0.5]):  # the last is clipped to 1
        _, r, _, _, info = env.step(np.array(a, np.float32))
        changes.append(float(info["reward_steer_change"]))
        rewards.append((r, float(info["reward_progress"])))
    assert changes == pytest.approx([0.5, 1.0, 0.0, 1.5])
    for (r, prog), ch in zip(rewards, changes):
        assert r == pytest.approx(prog - ch)
    env.reset()
    _, _, _, _, info = env.step(np.array([0.25, 0.5], np.float32))
    assert float(info["reward_steer_change"]) == pytest.approx(0.25)


def test_a_preset_reward_is_the_same_with_the_term_weighed_zero():
    def drive(reward):
        env = gym.make("torcsrl/Race-v0", reward=reward, disable_env_checker=True)
        env.reset(seed=1)
        rng = np.random.default_rng(0)
        return [env.step(rng.uniform(-1, 1, 2).astype(np.float32))[1] for _ in range(40)]

    assert drive("summers_final") == drive({"preset": "summers_final", "steer_change": 0.0})
