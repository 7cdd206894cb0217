"""torcsrl/RaceFlat-v0: the race's vector keys as one Box, for single-file RL code (CleanRL's layout)."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

import torcsrl.envs  # noqa: F401  (registers torcsrl/Race-v0 and torcsrl/RaceFlat-v0)
from torcsrl.envs.flat import FlatObservation
from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG, STATE_SLOTS, TELEMETRY_SLOTS


def test_check_env_passes_on_the_flat_face():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("torcsrl/RaceFlat-v0", track="oval")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)  # the wrapped env: the flat face is the wrapper
    allow = ("pybullet", "different from the unwrapped version")  # check_env notes that it checks a wrapper
    bad = [str(w.message) for w in caught if not any(a in str(w.message) for a in allow)]
    assert bad == []
    assert env.observation_space.shape == (len(RANGEFINDER_ANGLES_DEG) + len(STATE_SLOTS),)
    env.close()


def test_slot_order_is_rangefinder_then_state_and_the_spec_rebuilds_it():
    env = gym.make("torcsrl/RaceFlat-v0", track="oval")
    assert env.keys == ("rangefinder", "state")
    assert env.slot_names == [f"rangefinder.{i}" for i in range(19)] + [f"state.{s}" for s in STATE_SLOTS]
    assert env.slices == {"rangefinder": slice(0, 19), "state": slice(19, 30)}
    low, high = env.observation_space.low, env.observation_space.high
    assert low[0] == -1.0 and high[0] == 200.0 and low[19] == pytest.approx(-np.pi) and high[28] == 2e4  # rpm
    again = gym.make(env.spec)  # the spec records the wrapper once: rebuilding does not flatten twice
    assert again.observation_space == env.observation_space
    env.close()
    again.close()


def test_flat_vector_is_the_dict_concatenated_for_the_same_seed_and_actions():
    kw = dict(track=["oval", "hairpins"], sensors=("state", "telemetry", "rangefinder"), start="random", max_steps=40)
    flat, nested = gym.make("torcsrl/RaceFlat-v0", **kw), gym.make("torcsrl/Race-v0", **kw)
    assert flat.keys == ("rangefinder", "state", "telemetry")  # sensor order, not the order asked for
    assert flat.slot_names[30:] == [f"telemetry.{s}" for s in TELEMETRY_SLOTS]
    actions = np.random.default_rng(0).uniform(-1, 1, (60, 2)).astype(np.float32)
    f, _ = flat.reset(seed=3)
    d, _ = nested.reset(seed=3)
    steps = 0
    for a in actions:
        assert f.dtype == np.float32 and f.shape == flat.observation_space.shape
        assert np.array_equal(f, np.concatenate([d["rangefinder"], d["state"], d["telemetry"]]))
        f, rf, tf, uf, _ = flat.step(a)
        d, rd, td, ud, _ = nested.step(a)
        assert (rf, tf, uf) == (rd, td, ud)
        steps += 1
        if tf or uf:
            break
    assert steps > 1
    flat.close()
    nested.close()


class _ImageEnv(gym.Env):
    """A Dict env with an image key (no physics needed to test the refusal)."""

    observation_space = spaces.Dict({"rangefinder": spaces.Box(-1, 200, (19,), np.float32),
                                     "pixels": spaces.Box(0, 255, (3, 8, 8), np.uint8),
                                     "depth": spaces.Box(0, np.inf, (1, 8, 8), np.float32)})
    action_space = spaces.Box(-1, 1, (2,), np.float32)


def test_image_keys_are_refused_in_one_line_naming_them():
    with pytest.raises(ValueError, match=r"vector keys only; this env also observes pixels, depth") as err:
        FlatObservation(_ImageEnv())
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="flattens a Dict"):
        FlatObservation(gym.make("Pendulum-v1"))


# ---------------------------------------------------------------- a CleanRL-shaped TD3 on the flat face
@pytest.fixture
def one_thread():
    """One intra-op thread: tiny networks run fastest so, and the machine is shared."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_cleanrl_shaped_td3_runs_with_finite_losses(one_thread):
    """td3_continuous_action.py's shape, shrunk: networks sized from the single spaces, SyncVectorEnv of
    RecordEpisodeStatistics envs, episode returns read the gymnasium 1.x way (``infos["episode"]`` + ``"_episode"``)."""
    torch.manual_seed(0)
    total_timesteps, learning_starts, batch_size, gamma, tau, policy_frequency = 300, 100, 32, 0.99, 0.005, 2

    def make_env():
        env = gym.make("torcsrl/RaceFlat-v0", track="oval", max_steps=60)
        return gym.wrappers.RecordEpisodeStatistics(env)

    envs = gym.vector.SyncVectorEnv([make_env])
    assert isinstance(envs.single_action_space, spaces.Box)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))

    def mlp(n_in, n_out):
        return torch.nn.Sequential(torch.nn.Linear(n_in, 32), torch.nn.ReLU(), torch.nn.Linear(32, n_out))

    actor, actor_target = mlp(obs_dim, act_dim), mlp(obs_dim, act_dim)
    qf1, qf2, qf1_target, qf2_target = (mlp(obs_dim + act_dim, 1) for _ in range(4))
    actor_target.load_state_dict(actor.state_dict())
    qf1_target.load_state_dict(qf1.state_dict())
    qf2_target.load_state_dict(qf2.state_dict())
    q_optimizer = torch.optim.Adam(list(qf1.parameters()) + list(qf2.parameters()), lr=1e-3)
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=1e-3)
    scale = torch.as_tensor(envs.single_observation_space.high, dtype=torch.float32).abs().clamp(1.0, 1e3)

    def pi(net, x):
        return torch.tanh(net(x / scale))

    buf = {k: [] for k in ("obs", "next_obs", "actions", "rewards", "dones")}
    obs, _ = envs.reset(seed=0)
    autoreset = np.zeros(envs.num_envs, dtype=bool)  # gymnasium 1.x: the step after an episode's end resets
    returns, losses = [], []
    for global_step in range(total_timesteps):
        if global_step < learning_starts:
            actions = np.array([envs.single_action_space.sample() for _ in range(envs.num_envs)])
        else:
            with torch.no_grad():
                actions = pi(actor, torch.as_tensor(obs)).numpy()
                actions = np.clip(actions + np.random.normal(0, 0.1, actions.shape), -1, 1).astype(np.float32)
        next_obs, rewards, terminations, truncations, infos = envs.step(actions)
        if "episode" in infos:
            returns += list(infos["episode"]["r"][infos["_episode"]])
        for i in np.flatnonzero(~autoreset):  # skip the reset transitions (next-step autoreset)
            for k, v in zip(buf, (obs[i], next_obs[i], actions[i], rewards[i], terminations[i])):
                buf[k].append(v)
        autoreset = np.logical_or(terminations, truncations)
        obs = next_obs

        if global_step > learning_starts:
            idx = np.random.randint(0, len(buf["obs"]), batch_size)
            b_obs, b_next, b_act, b_rew, b_done = (torch.as_tensor(np.asarray(buf[k])[idx], dtype=torch.float32)
                                                   for k in buf)
            with torch.no_grad():
                clipped_noise = (torch.randn_like(b_act) * 0.2).clamp(-0.5, 0.5)
                next_actions = (pi(actor_target, b_next) + clipped_noise).clamp(-1, 1)
                x_next = torch.cat([b_next / scale, next_actions], 1)
                min_q = torch.min(qf1_target(x_next), qf2_target(x_next)).view(-1)
                target = b_rew + (1 - b_done) * gamma * min_q
            x = torch.cat([b_obs / scale, b_act], 1)
            qf_loss = torch.nn.functional.mse_loss(qf1(x).view(-1), target) + \
                torch.nn.functional.mse_loss(qf2(x).view(-1), target)
            q_optimizer.zero_grad()
            qf_loss.backward()
            q_optimizer.step()
            losses.append(qf_loss.item())
            if global_step % policy_frequency == 0:
                actor_loss = -qf1(torch.cat([b_obs / scale, pi(actor, b_obs)], 1)).mean()
                actor_optimizer.zero_grad()
                actor_loss.backward()
                actor_optimizer.step()
                losses.append(actor_loss.item())
                for net, tgt in ((actor, actor_target), (qf1, qf1_target), (qf2, qf2_target)):
                    for p, tp in zip(net.parameters(), tgt.parameters()):
                        tp.data.copy_(tau * p.data + (1 - tau) * tp.data)
    envs.close()
    assert len(losses) > 200 and np.isfinite(losses).all()
    assert returns and np.isfinite(returns).all()  # at least one episode ended and was recorded
