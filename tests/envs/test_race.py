"""RaceEnv contract: gymnasium and TorchRL faces, sensors, rewards, episodes, bad input."""

from __future__ import annotations

import functools
import math
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch

import torcsrl.envs  # noqa: F401  (registers torcsrl/Race-v0)
from torcsrl.envs import make_env
from torcsrl.envs.race import RaceCore, RaceEnv
from torcsrl.envs.rewards import PRESETS, REWARD_TERMS, Reward
from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG, STATE_SLOTS

torch.set_num_threads(1)


def _rollout_gym(env, seed, steps=60):
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = [np.concatenate([obs["rangefinder"], obs["state"]])]
    for _ in range(steps):
        a = np.array([rng.uniform(-0.3, 0.3), rng.uniform(0.2, 1.0)], np.float32)
        obs, r, term, trunc, info = env.step(a)
        out.append(np.concatenate([obs["rangefinder"], obs["state"], [r]]))
        if term or trunc:
            break
    return out


# ---------------------------------------------------------------- gymnasium face
def test_gymnasium_check_env_passes_without_warnings():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("torcsrl/Race-v0", track="oval").unwrapped
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=False)
    allow = ("pybullet",)  # nothing else may warn
    bad = [str(w.message) for w in caught if not any(a in str(w.message) for a in allow)]
    assert bad == []
    env.close()


def test_same_seed_same_rollout_and_different_seed_differs():
    env = gym.make("torcsrl/Race-v0", track=["oval", "hairpins"], start="random", spawn_jitter=(1.0, 0.05))
    a = _rollout_gym(env, 3)
    b = _rollout_gym(env, 3)
    c = _rollout_gym(env, 4)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], c[0])
    env.close()


def test_gym_env_pickles_and_behaves_the_same():
    env = gym.make("torcsrl/Race-v0", track="hairpins").unwrapped
    clone = pickle.loads(pickle.dumps(env))
    assert all(np.array_equal(x, y) for x, y in zip(_rollout_gym(env, 1, 30), _rollout_gym(clone, 1, 30)))
    env.close()
    clone.close()


def test_observation_slots_and_rangefinder_geometry():
    env = RaceEnv(track="oval")  # 14 m wide, 500 m straight from the start line
    obs, info = env.reset(seed=0)
    rf, st = obs["rangefinder"], obs["state"]
    assert rf.shape == (len(RANGEFINDER_ANGLES_DEG),) and st.shape == (len(STATE_SLOTS),)
    assert env.observation_space.contains(obs)
    left, right = rf[RANGEFINDER_ANGLES_DEG.index(90)], rf[RANGEFINDER_ANGLES_DEG.index(-90)]
    # beams at ±90° measure the half-widths (the car sits on the centreline), beam 0 sees down the straight
    assert abs(left - 7.0) < 0.05 and abs(right - 7.0) < 0.05
    assert rf[RANGEFINDER_ANGLES_DEG.index(0)] == pytest.approx(200.0)
    # beam at 30°: hits the left edge 7 m away laterally -> 14 m along the beam
    assert rf[RANGEFINDER_ANGLES_DEG.index(30)] == pytest.approx(14.0, abs=0.1)  # yaw on the grid is within 0.002 rad
    assert abs(st[STATE_SLOTS.index("trackPos")]) < 0.01 and abs(st[STATE_SLOTS.index("angle_rad")]) < 0.01
    assert info["lap"] == 0 and info["distRaced"] == 0.0
    for _ in range(250):
        obs, *_ = env.step(np.array([0.0, 0.6], np.float32))
    st = obs["state"]
    assert st[STATE_SLOTS.index("speedX_kmh")] > 50.0 and st[STATE_SLOTS.index("gear")] >= 1
    assert st[STATE_SLOTS.index("rpm")] > 1000.0
    # wheels spin at about v / r (r ~ 0.3 m): the front (undriven) ones roll freely
    v = st[STATE_SLOTS.index("speedX_kmh")] / 3.6
    assert 2.5 * v < st[STATE_SLOTS.index("wheelSpinVel_fl")] < 4.0 * v
    env.close()


def test_all_beams_read_minus_one_off_track_and_episode_terminates():
    env = RaceEnv(track="oval", offtrack_grace_s=10.0)
    env.reset(seed=0)
    term = False
    for _ in range(400):
        obs, r, term, trunc, info = env.step(np.array([1.0, 0.6], np.float32))
        if obs["state"][STATE_SLOTS.index("trackPos")] > 1.05:
            break
    assert (obs["rangefinder"] == -1.0).all()
    assert not term  # the grace period holds it
    env.close()
    env = RaceEnv(track="oval")  # no grace
    env.reset(seed=0)
    for i in range(400):
        obs, r, term, trunc, info = env.step(np.array([1.0, 0.6], np.float32))
        if term or trunc:
            break
    assert term and not trunc and info["termination"] == "off_track"
    assert abs(obs["state"][STATE_SLOTS.index("trackPos")]) > 1.0
    assert info["reward_termination"] == 1.0
    env.close()


def test_truncation_at_the_step_limit_is_not_termination():
    env = RaceEnv(track="oval", max_steps=25)
    env.reset(seed=0)
    for i in range(25):
        _, _, term, trunc, _ = env.step(np.array([0.0, 0.4], np.float32))
        assert not term
        assert trunc == (i == 24)
    env.close()


def test_no_progress_terminates():
    env = RaceEnv(track="oval", no_progress_s=2.0)
    env.reset(seed=0)
    for i in range(200):
        _, _, term, trunc, info = env.step(np.array([0.0, 0.0], np.float32))
        if term or trunc:
            break
    assert term and info["termination"] == "no_progress"
    assert i == pytest.approx(100, abs=2)  # 2 s at 50 Hz
    env.close()


def test_driving_backwards_terminates():
    core = RaceCore(track="oval", backwards_m=10.0)
    core.reset()
    t = core.car_tracks[0]
    xy = t.to_world(100.0, 0.0)
    core.fleet.reset([0], xy[None], [float(t.heading(100.0)) + math.pi], [15.0])
    core.s[:] = 100.0
    core.chord[:] = int(t._locate(100.0)[0])
    for i in range(100):
        core.step(np.array([[0.0, 0.2]]))
        if core.terminated[0]:
            break
    assert core.terminated[0] and core.reason[0] == 2
    assert core.dist_raced[0] < -10.0
    core.close()


# ---------------------------------------------------------------- rewards
@pytest.mark.parametrize("preset", list(PRESETS))
def test_reward_presets_match_their_formulas(preset):
    vx, th, tp, ds = 30.0, 0.3, -0.4, 0.61
    r = Reward(preset)
    terms = Reward.terms(np.array([vx]), np.array([th]), np.array([tp]), np.array([ds]), np.array([False]))
    value = float(r(terms)[0])
    expected = {
        "summers_initial": vx * math.cos(th),
        "summers_final": vx * (math.cos(th) - abs(math.sin(th))),
        "lau": vx * (math.cos(th) - abs(math.sin(th)) - abs(tp)),
        "progress": ds,
        "race": vx * (math.cos(th) - abs(math.sin(th))),  # the race terms are 0 without traffic
    }[preset]
    assert value == pytest.approx(expected)
    done = Reward.terms(np.array([vx]), np.array([th]), np.array([tp]), np.array([ds]), np.array([True]))
    assert float(r(done)[0]) - value == pytest.approx(PRESETS[preset].get("termination", 0.0))


def test_termination_penalty_and_scale_are_configurable():
    r = Reward({"preset": "lau", "termination": -1.0}, scale=0.01)
    t = Reward.terms(np.array([10.0]), np.array([0.0]), np.array([0.0]), np.array([0.2]), np.array([True]))
    assert float(r(t)[0]) == pytest.approx(0.01 * (10.0 - 1.0))
    assert Reward("lau").weights["termination"] == -500.0


def test_env_reward_is_the_weighted_sum_of_the_logged_terms():
    env = RaceEnv(track="oval", reward="lau", reward_scale=0.5)
    env.reset(seed=0)
    w = env.core.reward.weights
    for _ in range(30):
        _, r, *_, info = env.step(np.array([0.05, 0.8], np.float32))
        assert r == pytest.approx(0.5 * sum(w[k] * info[f"reward_{k}"] for k in REWARD_TERMS))
    assert info["reward_speed_cos"] > 0 and info["reward_progress"] > 0
    env.close()


# ---------------------------------------------------------------- track sets and starts
def test_track_set_sampled_per_episode_from_the_seed():
    env = RaceEnv(track="set:train")
    seen = []
    env.reset(seed=5)
    for _ in range(12):
        _, info = env.reset()
        seen.append(info["track"])
    env.reset(seed=5)
    again = [env.reset()[1]["track"] for _ in range(12)]
    assert seen == again and len(set(seen)) >= 3
    env.close()


def test_random_start_and_surface_override():
    env = RaceEnv(track="rallycross", surface=["ice", "wet"], start="random")
    env.reset(seed=0)
    starts, surfs = set(), set()
    for _ in range(8):
        _, info = env.reset()
        starts.add(round(info["distFromStart"], 1))
        surfs.add(info["surface"])
        assert set(np.unique(env.core.fleet.wheel_surfaces)) <= {1, 4}  # wet or ice, never the track's dirt
    assert len(starts) == 8 and surfs == {"ice", "wet"}
    env.close()


# ---------------------------------------------------------------- TorchRL face
def test_torchrl_env_specs_single_and_batched():
    from torchrl.envs.utils import check_env_specs

    env = make_env(track="oval", seed=0)
    assert env.batch_size == torch.Size([])
    check_env_specs(env)
    env.close()
    benv = make_env(track=["oval", "hairpins"], num_cars=4, seed=0)
    assert benv.batch_size == torch.Size([4])
    check_env_specs(benv)
    benv.close()


def test_torchrl_same_seed_same_rollout():
    def roll(seed):
        env = make_env(track="hairpins", start="random", seed=seed)
        torch.manual_seed(0)
        td = env.rollout(40, break_when_any_done=False)
        env.close()
        return td

    a, b, c = roll(1), roll(1), roll(2)
    assert torch.equal(a["next", "state"], b["next", "state"]) and torch.equal(a["action"], b["action"])
    assert not torch.equal(a["state"][0], c["state"][0])


def test_batched_partial_reset_keeps_the_other_cars():
    env = make_env(track="oval", num_cars=3, seed=0)
    td = env.reset()
    act = torch.tensor([[0.0, 0.8]] * 3)
    for _ in range(100):
        td = env.step(td.set("action", act))["next"]
    raced = td["info", "distRaced"].clone()
    assert (raced > 5.0).all()
    reset = torch.tensor([[False], [True], [False]])
    td = env.reset(td.set("_reset", reset))
    after = td["info", "distRaced"]
    assert after[1] == 0.0 and torch.equal(after[0], raced[0]) and torch.equal(after[2], raced[2])
    env.close()


def test_batched_cars_do_not_collide_and_progress_independently():
    throttle = torch.tensor([[0.0, 0.15], [0.0, 0.3], [0.0, 0.45], [0.0, 0.6]])
    env = make_env(track="oval", num_cars=4, seed=0)  # all four start on the same grid spot
    td = env.reset()
    for _ in range(100):
        td = env.step(td.set("action", throttle))["next"]
    raced = td["info", "distRaced"].ravel()
    assert (torch.diff(raced) > 0).all() and td["done"].sum() == 0
    env.close()
    # each car drives exactly as it would alone: nothing pushed it
    solo = make_env(track="oval", seed=0)
    td = solo.reset()
    for _ in range(100):
        td = solo.step(td.set("action", throttle[2]))["next"]
    assert float(td["info", "distRaced"]) == pytest.approx(float(raced[2]), abs=1e-3)
    solo.close()


def test_parallel_env_and_collector():
    from torchrl.collectors import Collector
    from torchrl.envs import ParallelEnv

    penv = ParallelEnv(2, functools.partial(make_env, track="oval", max_steps=30), mp_start_method="fork")
    penv.set_seed(0)
    td = penv.rollout(10)
    assert td.batch_size == torch.Size([2, 10])
    coll = Collector(penv, policy=None, frames_per_batch=40, total_frames=40)
    for batch in coll:
        assert batch.numel() == 40 and (batch["next", "info", "distRaced"] >= 0).any()
    coll.shutdown()
    if not penv.is_closed:
        penv.close()


def test_torchrl_env_pickles():
    env = make_env(track="oval", seed=3)
    clone = pickle.loads(pickle.dumps(env))
    assert torch.equal(env.reset()["rangefinder"], clone.reset()["rangefinder"])
    env.close()
    clone.close()


# ---------------------------------------------------------------- bad input
def test_bad_input_messages():
    with pytest.raises(ValueError, match=r"unknown sensors \['lidar'\]; allowed: rangefinder, state, telemetry, pixels, depth"):
        RaceEnv(sensors=("lidar",))
    with pytest.raises(ValueError, match=r"unknown reward terms \['sped'\]; terms: speed_cos"):
        RaceEnv(reward={"sped": 1.0})
    with pytest.raises(ValueError, match="unknown reward preset 'summers'; presets: summers_initial"):
        RaceEnv(reward="summers")
    with pytest.raises(ValueError, match="unknown track 'monza'; available: "):
        RaceEnv(track="monza")
    with pytest.raises(ValueError, match="unknown surface 'lava'"):
        RaceEnv(surface="lava")
    with pytest.raises(ValueError, match="unknown vehicle_backend 'cuda'; allowed: auto, numpy, numba, python"):
        RaceEnv(vehicle_backend="cuda")
    env = RaceEnv(track="oval")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action has shape \(3,\); expected \(2,\)"):
        env.step(np.zeros(3, np.float32))
    before = env.core.fleet.pos.copy()
    with pytest.raises(ValueError, match="action contains NaN or inf"):
        env.step(np.array([np.nan, 0.5], np.float32))
    assert np.array_equal(before, env.core.fleet.pos)  # physics untouched
    obs, *_ = env.step(np.array([5.0, -7.0], np.float32))  # clipped, not rejected
    assert np.isfinite(obs["state"]).all()
    env.close()


# ---------------------------------------------------------------- outside clients and rendering
def test_plain_gymnasium_vector_loop_works_unchanged():
    from gymnasium.wrappers import FlattenObservation

    envs = gym.vector.SyncVectorEnv([lambda: FlattenObservation(gym.make("torcsrl/Race-v0", track="oval", max_steps=50))] * 2)
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (2, 30)
    total = np.zeros(2)
    for _ in range(60):  # crosses an autoreset
        obs, r, term, trunc, _ = envs.step(np.tile([0.0, 0.7], (2, 1)).astype(np.float32))
        total += r
    assert (total > 0).all()
    envs.close()


def test_render_rgb_array_top_down():
    env = gym.make("torcsrl/Race-v0", track="hairpins", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (400, 400, 3) and frame.dtype == np.uint8
    assert (np.abs(frame.astype(int) - [230, 20, 20]).sum(-1) < 10).sum() > 20  # the car is drawn
    env.close()


def test_scalar_and_vectorised_locate_agree():
    core = RaceCore(track="hairpins", start="random", spawn_jitter=(4.0, 0.3))
    core.reset()
    rng = np.random.default_rng(0)
    for _ in range(120):
        core.step(np.array([[rng.uniform(-0.5, 0.5), 0.7]]))
        if core.terminated[0] or core.truncated[0]:
            core.reset()
        s, d, ids = core.s.copy(), core.d.copy(), core.fleet.wheel_surfaces.copy()
        t = core.car_tracks[0]
        pts = np.concatenate([core.fleet.pos[:, None, :2], core.fleet.wheel_xy], axis=1)
        s2, d2 = t.project(pts)
        assert abs(t.wrap_delta(s2[0, 0], s[0])) < 1e-6 and abs(d2[0, 0] - d[0]) < 1e-6
        assert np.array_equal(t.surface_at(pts[0, 1:]), ids[0])
    core.close()


@pytest.mark.parametrize("track", ["kidney", ["hairpins", "oval", "rallycross"]])
def test_vectorised_locate_equals_the_plain_python_one(track):
    """RaceCore._locate_walk (the chord walk vectorised over the cars) writes the bits _locate_scalar writes, wheel
    surfaces included, and when a car's walk fails it returns None having written what the scalar loop wrote
    (the cars before the first failing one, and that car's own point if it settled)."""
    core = RaceCore(track=track, num_cars=24, seed=1)
    core.reset()
    rng = np.random.default_rng(2)
    n, fails = core.n, 0
    for rep in range(40):
        tr = core.car_tracks
        s = np.array([rng.uniform(0.0, t.length) for t in tr])
        s[:2] = [0.0, tr[1].length - 1e-9]  # on the start line
        d = rng.uniform(-1.0, 1.0, n) * [0.0, 3.0, 10.0, 40.0][rep % 4]
        xy = np.stack([t.to_world(s[i], d[i]) for i, t in enumerate(tr)])
        wheels = xy[:, None, :] + rng.normal(0.0, 1.5, (n, 4, 2))
        yaw = rng.uniform(-math.pi, math.pi, n)
        chord = np.array([(int(t._locate(s[i])[0]) + int(rng.integers(-5, 6))) % len(t) for i, t in enumerate(tr)])
        if rep % 5 == 0:
            chord[rng.integers(0, n, 3)] = 7  # far chords: some walks fail
        out = []
        for f in (core._locate_scalar, core._locate_walk):
            core.chord[:] = chord
            for a in (core.s, core.d, core.track_pos, core.angle):
                a[:] = -9.0
            ids = f(xy, wheels, yaw)
            out.append([ids] + [a.copy() for a in (core.s, core.d, core.chord, core.track_pos, core.angle)])
        (ia, *a), (ib, *b) = out
        assert (ia is None) == (ib is None), rep
        fails += ia is None
        if ia is not None:
            assert np.array_equal(ia, ib)
        for u, v in zip(a, b):
            assert u.tobytes() == v.tobytes(), rep
    assert 0 < fails < 40
    core.close()


def test_wrap_deltas_is_each_tracks_wrap_delta_bit_for_bit():
    from torcsrl.envs import tracks
    from torcsrl.envs.race import wrap_deltas

    ts = [tracks.load(name) for name in ("kidney", "oval", "hairpins")]
    rng = np.random.default_rng(0)
    for _ in range(50):
        tr = [ts[i] for i in rng.integers(0, 3, 64)]
        lengths = np.array([t.length for t in tr])
        s_old = rng.uniform(0.0, 1.0, 64) * lengths
        s = np.mod(s_old + rng.normal(0.0, 5.0, 64) + rng.choice([0.0, 1e-12, 0.5], 64) * lengths, lengths)
        s[:3] = [0.0, lengths[1] - 1e-9, s_old[2]]
        want = np.array([t.wrap_delta(s[i], s_old[i]) for i, t in enumerate(tr)])
        assert wrap_deltas(s, s_old, lengths).tobytes() == want.tobytes()


def test_cars_per_world_drive_as_in_one_world_and_resume_exactly():
    """cars_per_world deals the cars over several pybullet worlds: the same episodes, bit for bit, as one world;
    get_state / set_state carry every world."""
    kw = dict(track="kidney", num_cars=5, start="random", spawn_jitter=(2.0, 0.2), seed=3)
    one, split = RaceCore(**kw), RaceCore(**kw, cars_per_world=2)
    assert len(split.fleet.clients) == 3 and len(one.fleet.clients) == 1
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, (40, 5, 2))
    actions[:, :, 1] = np.abs(actions[:, :, 1])
    saved = None
    for core in (one, split):
        core.reset()
    for k, a in enumerate(actions):
        for core in (one, split):
            core.step(a)
        assert one.fleet._raw.tobytes() == split.fleet._raw.tobytes(), k
        assert one.s.tobytes() == split.s.tobytes() and one.obs["rangefinder"].tobytes() == split.obs["rangefinder"].tobytes()
        if k == 19:
            saved = split.get_state()
            assert len(saved["more_worlds"]) == 2
    twin = RaceCore(**kw, cars_per_world=2)
    twin.reset()
    twin.set_state(saved)
    for a in actions[20:]:
        twin.step(a)
    assert twin.fleet._raw.tobytes() == split.fleet._raw.tobytes() and twin.rewards.tobytes() == split.rewards.tobytes()
    with pytest.raises(ValueError, match="pybullet worlds"):
        one.set_state(saved)
    for core in (one, split, twin):
        core.close()
    with pytest.raises(ValueError, match="one world"):
        RaceCore(track="oval", num_cars=2, cars_per_world=1, sensors=("state", "pixels"))
    with pytest.raises(ValueError, match="cars_per_world"):
        RaceCore(track="oval", num_cars=2, cars_per_world=0)


def test_parked_cars_leave_the_others_alone_and_restart_as_if_never_parked():
    """RaceCore.park: the other cars' episodes are bit for bit what they would have been, a parked car's
    rangefinder reads off-track, and its next reset starts it as if it had never been parked."""
    kw = dict(track="kidney", num_cars=6, start="random", seed=5)
    a, b = RaceCore(**kw), RaceCore(**kw)
    rng = np.random.default_rng(1)
    acts = rng.uniform(-1.0, 1.0, (30, 6, 2))
    acts[:, :, 1] = np.abs(acts[:, :, 1])
    for core in (a, b):
        core.reset()
    for k, act in enumerate(acts):
        if k == 4:
            b.park([1, 4])
            assert b.parked.tolist() == [False, True, False, False, True, False]
        if k == 15:
            for core in (a, b):
                core.reset(np.array([1]))
            assert b.parked.tolist() == [False, False, False, False, True, False]
        for core in (a, b):
            core.step(act)
        keep = [0, 2, 3, 5] + ([1] if k >= 15 else [])
        assert a.fleet._raw[keep].tobytes() == b.fleet._raw[keep].tobytes(), k
        assert a.obs["rangefinder"][keep].tobytes() == b.obs["rangefinder"][keep].tobytes(), k
        assert a.rewards[keep].tobytes() == b.rewards[keep].tobytes(), k
        if 4 <= k:
            assert (b.obs["rangefinder"][4] == -1.0).all()
    for core in (a, b):
        core.close()


def test_laps_count_full_laps_driven_and_times_run_line_to_line():
    """After a random start, crossing the line is not a lap: ``lap`` counts full lengths driven;
    lap times run from one line crossing to the next (the partial first lap is untimed)."""
    core = RaceCore(track="oval", start="random")
    core.reset()
    L = core.car_tracks[0].length
    core.s0[:] = L - 50.0  # 50 m before the line
    for dist, t, lap, last in ((49.0, 2.0, 0, 0.0), (51.0, 2.5, 0, 0.0), (L + 10.0, 40.0, 1, 0.0),
                               (L + 51.0, 42.0, 1, 39.5), (2 * L + 1.0, 60.0, 2, 39.5)):
        core.dist_raced[:] = dist
        core.time[:] = t
        core._laps()
        assert int(core.lap[0]) == lap, (dist, core.lap)
        assert float(core.last_lap_time[0]) == pytest.approx(last), (dist, core.last_lap_time)
    core.close()


def test_one_car_float_bookkeeping_matches_the_vectorised_rules():
    """RaceCore keeps one car's books in floats (_book_one); the same drive in a 2-car core (the
    array rules) books the same rewards, terms, terminations and laps, step for step."""
    one = RaceCore(track="hairpins", num_cars=1, reward="lau", reward_scale=0.05, max_steps=150, no_progress_s=2.0)
    two = RaceCore(track="hairpins", num_cars=2, reward="lau", reward_scale=0.05, max_steps=150, no_progress_s=2.0)
    one.reset()
    two.reset()
    rng = np.random.default_rng(3)
    reasons = set()
    base = np.array([0.9, 1.0])  # per episode: a steady steer and throttle, plus noise
    for _ in range(600):
        a = np.clip(base + rng.normal(0.0, 0.1, 2), -1.0, 1.0)
        one.step(a[None])
        two.step(np.stack([a, a]))
        assert np.allclose(one.terms[:, 0], two.terms[:, 0], atol=1e-9)
        assert abs(one.rewards[0] - two.rewards[0]) < 1e-9
        for k in ("terminated", "truncated", "finished", "reason", "lap", "steps"):
            assert getattr(one, k)[0] == getattr(two, k)[0], k
        for k in ("time", "dist_raced", "best_dist", "best_dist_time", "offtrack_time"):
            assert abs(getattr(one, k)[0] - getattr(two, k)[0]) < 1e-9, k
        if one.terminated[0] or one.truncated[0]:
            reasons.add(int(one.reason[0]) if one.terminated[0] else -1)
            base = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-0.5, 1.0)])
            one.reset()
            two.reset()
    assert len(reasons) >= 2, reasons  # more than one way to end an episode was exercised
    one.close()
    two.close()


def test_stable_baselines3_trains_on_the_gymnasium_face_unchanged():
    """An outside client: SB3's TD3 with its dict-observation policy learns for a few hundred steps
    (needs ``pip install -e ".[bench]"``; skipped otherwise, and CI does not install it)."""
    sb3 = pytest.importorskip("stable_baselines3")
    import torch

    torch.set_num_threads(1)
    env = gym.make("torcsrl/Race-v0", track="oval", control_hz=10, substeps=20)
    model = sb3.TD3("MultiInputPolicy", env, learning_starts=100, seed=0, verbose=0,
                    policy_kwargs={"net_arch": [32, 32]})
    model.learn(300)
    obs, _ = env.reset(seed=0)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(action.astype(np.float32))
    env.close()


def test_memory_stays_flat_over_resets_and_steps():
    import importlib.util
    import pathlib

    spec = importlib.util.spec_from_file_location("soak", pathlib.Path(__file__).parents[2] / "benchmarks" / "soak.py")
    soak = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(soak)
    r = soak.soak(resets=1000, steps=5000)
    assert r["growth_mib"] < 5.0, r
    assert r["reset_us"] < 5 * r["step_us"], r  # a reset costs about a step: the world is never reloaded


def test_lap_limited_episode_with_the_expert_and_lap_bookkeeping():
    from torcsrl.envs.expert import ExpertDriver

    env = RaceEnv(track="oval", lap_limit=2, action_mode="separate", max_steps=20_000)
    env.reset(seed=0)
    core = env.core
    expert = ExpertDriver(core.car_tracks[0], core.fleet.params)
    expert.reset(0.0)
    laps_seen, steps = [], 0
    while True:
        steer, throttle, brake = expert.act(core.fleet, 0)
        obs, r, term, trunc, info = env.step(np.array([steer, 2 * throttle - 1, 2 * brake - 1], np.float32))
        steps += 1
        if info["lap"] > len(laps_seen):
            laps_seen.append(info["lastLapTime"])
        if term or trunc:
            break
    assert trunc and not term and info["finished"] and info["lap"] == 2
    first, second = laps_seen
    assert first > second > 0.0  # standing start vs flying lap
    assert info["bestLapTime"] == pytest.approx(second)
    assert info["distRaced"] == pytest.approx(2 * core.car_tracks[0].length, abs=3.0)
    assert steps * core.dt == pytest.approx(first + second, abs=0.05)
    env.close()


def test_sim_state_restores_the_cameras_held_frames():
    """With camera every > 1 the frame a car sees between renders is held: the saved state carries it,
    so a restored env shows exactly the frames the saved one would have shown."""
    from torcsrl.envs import make_env

    def make():
        return make_env(track="oval", sensors=("state", "pixels"), camera={"height": 24, "width": 32, "every": 3}, seed=4)

    env = make()
    td = env.reset()
    act = env.action_spec.zero()
    act[..., -1] = 0.5
    for _ in range(4):  # mid-way between two renders
        td = env.step(td.set("action", act))["next"]
    saved = env.get_sim_state()
    ref = []
    for _ in range(5):
        td = env.step(td.set("action", act))["next"]
        ref.append(td["pixels"].clone())
    assert any(not torch.equal(a, b) for a, b in zip(ref, ref[1:]))  # the view changes: the check can fail
    other = make()
    other.reset()
    other.set_sim_state(saved)
    x = td.clone()  # the step reads only the action
    for i in range(5):
        x = other.step(x.set("action", act))["next"]
        torch.testing.assert_close(x["pixels"], ref[i], rtol=0, atol=0, msg=f"step {i}")
    env.close()
    other.close()


def test_vehicle_backends_drive_the_same_race():
    """env vehicle_backend: the same episode with every backend of the car model, to rounding."""
    pos = {}
    for backend in ("numba", "numpy", "python"):
        env = make_env(track="oval", num_cars=2, seed=1, vehicle_backend=backend, control_hz=10, substeps=20)
        assert env.core.fleet.backend == backend
        td = env.reset()
        start = env.core.fleet.pos.copy()
        for _ in range(40):
            td = env.step(td.set("action", torch.tensor([[0.2, 0.8], [-0.1, 1.0]])))["next"]
        pos[backend] = env.core.fleet.pos.copy()
        env.close()
    assert np.abs(pos["numba"] - pos["numpy"]).max() < 1e-6 and np.abs(pos["python"] - pos["numpy"]).max() < 1e-6
    assert (np.linalg.norm(pos["numba"][:, :2] - start[:, :2], axis=1) > 10.0).all()  # the cars did drive


def test_gym_info_reads_the_cores_info_for_the_one_car():
    """RaceEnv's info for one car (read as floats, without RaceCore.info()'s [N] copies) is the core's info()."""
    env = gym.make("torcsrl/Race-v0", track="hairpins")
    env.reset(seed=4)
    core = env.unwrapped.core
    rng = np.random.default_rng(4)
    laps = 0
    for _ in range(600):
        _, _, te, tr, info = env.step(np.array([rng.uniform(-0.2, 0.2), 1.0], dtype=np.float32))
        general = {k: (int(v[0]) if k == "lap" else float(v[0])) for k, v in core.info().items()}
        assert {k: info[k] for k in general} == general
        laps = max(laps, info["lap"])
        if te or tr:
            env.reset()
    env.close()
