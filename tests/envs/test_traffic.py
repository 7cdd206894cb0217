"""Cars that share a track (torcsrl.envs.traffic): contacts, the opponents sensor, determinism, bad input."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torcsrl.envs import make_env
from torcsrl.envs.race import RaceCore
from torcsrl.envs.traffic import TrafficError, TrafficSpec, load_opponent_policy, opponent_sectors, sector_directions

FAST = dict(control_hz=10, substeps=20)


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _place(core: RaceCore, car: int, s: float, d: float = 0.0, speed: float = 0.0) -> None:
    """Put ``car`` at (s, d) of its track copy, heading along the track."""
    t = core.car_tracks[car]
    xy = np.asarray(t.to_world(s, d)) + core.car_origins()[car]
    core.fleet.reset([car], xy[None], [float(t.heading(s))], speed)


def test_opponent_sectors_hand_placed():
    # car 0 at the origin heading +x; others ahead, left, behind-right, out of range, and one of another race
    xy = np.array([[0.0, 0.0], [20.0, 0.5], [0.5, 30.0], [-50.0, -1.0], [0.0, -250.0], [5.0, 0.0]])
    groups = np.array([0, 0, 0, 0, 0, 1])
    out = opponent_sectors(xy, np.zeros(6), groups)
    r = out[0]
    assert r.shape == (36,) and r.dtype == np.float32
    assert r[17] == pytest.approx(math.hypot(20.0, 0.5))  # ahead, slightly left: SCR's sector 17 ([-10, 0) clockwise)
    assert r[9] == pytest.approx(math.hypot(0.5, 30.0))   # to the left (90 deg anticlockwise = -90 clockwise): sector 9
    assert r[35] == pytest.approx(math.hypot(50.0, 1.0))  # behind, slightly right: the last sector
    assert np.count_nonzero(r < 200.0) == 3 and (r[r >= 200.0] == 200.0).all()  # free sectors read 200 m
    # the nearest car of a sector wins; heading turns the sectors (car 0 facing +y: car 1 now on its right)
    out = opponent_sectors(np.array([[0.0, 0.0], [20.0, 0.0], [10.0, 0.0]]), np.array([math.pi / 2, 0.0, 0.0]), np.zeros(3, int))
    assert out[0][27] == pytest.approx(10.0) and np.count_nonzero(out[0] < 200) == 1


def test_opponents_key_and_rangefinder_ignores_cars():
    env = make_env(track="oval", num_cars=1, seed=0, sensors=("rangefinder", "state", "opponents"),
                   traffic={"opponents": 1, "driver": {"kind": "parked"}}, **FAST)
    try:
        env.reset()
        c = env.core
        _place(c, 1, 400.0)  # far away: nothing in range
        _place(c, 0, 10.0)
        c._locate()
        c._observe()
        far_rf = c.obs["rangefinder"].copy()
        assert (c.obs["opponents"] == 200.0).all()
        _place(c, 1, 22.0)  # 12 m straight ahead, on the centre line
        c._locate()
        c._observe()
        opp = c.obs["opponents"][0]
        assert opp.argmin() in (17, 18) and opp.min() == pytest.approx(12.0, abs=0.05)
        np.testing.assert_array_equal(c.obs["rangefinder"], far_rf)  # beams see the track edges only, never a car
    finally:
        env.close()


def test_contact_between_two_cars_is_detected_and_reported():
    env = make_env(track="oval", num_cars=1, seed=0, sensors=("state",), traffic={"opponents": 1, "driver": {"kind": "parked"}},
                   **FAST)
    try:
        env.reset()
        c = env.core
        _place(c, 1, 30.0)  # a parked car 20 m ahead on the learner's line
        _place(c, 0, 10.0, speed=15.0)
        c._locate()
        hit = None
        for t in range(30):
            td = env.step(TensorDict({"action": torch.tensor([0.0, 1.0])}, []))
            info = td["next", "info"]
            if int(info["collisions"]) > 0:
                hit = t
                break
        assert hit is not None, "the learner never touched the parked car"
        assert c.fleet.contact_impulse[0, 1] > 0 and c.fleet.contact_impulse[0, 1] == c.fleet.contact_impulse[1, 0]
        assert float(info["impulse"]) > 0 and float(info["damage"]) >= float(info["impulse"]) - 1e-6
        assert c.traffic.collisions[1] == 1  # the other car of the contact is booked too
        # where the other car was: the learner ran into the car ahead, the parked car was hit from behind
        assert c.traffic.contact_sides.tolist() == [[1, 0, 0], [0, 0, 1]] and c.traffic.CONTACT_SIDES == ("ahead", "alongside", "behind")
        assert float(info["reward_collision"]) == pytest.approx(float(info["impulse"]), rel=1e-5)
    finally:
        env.close()


def test_a_contact_side_by_side_is_booked_alongside_for_both_cars():
    env = make_env(track="oval", num_cars=1, seed=0, sensors=("state",), traffic={"opponents": 1, "driver": {"kind": "parked"}},
                   **FAST)
    try:
        env.reset()
        c = env.core
        _place(c, 1, 30.0, d=-2.2)  # parked 2.2 m right of the axis; the learner 2 m behind it, easing right into its flank
        _place(c, 0, 28.0, d=0.0, speed=4.0)
        c._locate()
        for _ in range(20):
            env.step(TensorDict({"action": torch.tensor([-0.3, 0.2])}, []))
            if c.traffic.collisions[0]:
                break
        assert c.traffic.collisions.tolist() == [1, 1]
        assert c.traffic.contact_sides.tolist() == [[0, 1, 0], [0, 1, 0]]  # alongside, for each of the two
    finally:
        env.close()


def _rollout(seed: int, steps: int = 25):
    env = make_env(track="oval", num_cars=2, seed=seed, sensors=("state", "opponents"), start="random",
                   traffic={"opponents": 2, "driver": {"kind": "expert", "pace": [0.7, 0.9]}}, **FAST)
    try:
        torch.manual_seed(0)
        acts = torch.rand(steps, 2, 2) * 2 - 1
        td = env.reset()
        out = [td["opponents"].clone()]
        for a in acts:
            td = env.step(td.set("action", a))
            out.append(torch.cat([td["next", "opponents"], td["next", "info", "racePos"].float(), td["next", "state"]], -1))
            td = td["next"]
        return torch.stack(out[1:]), out[0], env.core.traffic.pace.copy()
    finally:
        env.close()


def test_scripted_opponents_give_room_to_a_car_alongside():
    """TORCS bt's side-collision filter: an expert opponent with a car overlapping it along the track and closer than
    side_gap_m across keeps side_gap_m between centres on its own side (never turning in across it); with no car
    alongside, or side_gap_m 0, it tracks its racing line."""
    def core_with(**tr):
        env = make_env(track="oval", num_cars=1, seed=0, sensors=("state",),
                       traffic={"opponents": 1, "driver": {"kind": "expert"}, **tr}, **FAST)
        env.reset()
        return env

    env, off = core_with(), core_with(side_gap_m=0)
    try:
        for e in (env, off):
            _place(e.core, 1, 100.0, d=0.0, speed=20.0)  # the opponent on the centre line
        c = env.core
        wl, wr = (float(np.asarray(w).reshape(-1)[0]) for w in c.car_tracks[1].width(100.0))
        _place(c, 0, 102.0, d=2.0, speed=20.0)  # alongside on its left, 2 m across
        c._locate()
        lo, hi = c.traffic._side_room(c, 1)
        assert hi == pytest.approx(float(c.d[0]) - 3.2) and lo == pytest.approx(-wr + 1.2)
        _place(c, 0, 99.0, d=-2.5, speed=20.0)  # on its right: it stays left of it
        c._locate()
        lo, hi = c.traffic._side_room(c, 1)
        assert lo == pytest.approx(float(c.d[0]) + 3.2) and hi == pytest.approx(wl - 1.2)
        for s, d in ((115.0, 0.0), (100.0, 3.5), (90.0, 1.0), (96.0, 0.3)):  # well ahead, wide apart, well behind, straight behind
            _place(c, 0, s, d=d, speed=20.0)
            c._locate()
            assert c.traffic._side_room(c, 1) is None, (s, d)
        _place(off.core, 0, 102.0, d=2.0, speed=20.0)
        off.core._locate()
        assert off.core.traffic._side_room(off.core, 1) is None  # side_gap_m 0: the old, blind opponents
        # and it steers that way: the oval's line runs along the right edge here (d -4.8 m); with a car on its right
        # it steers left of what its line asks
        for e in (env, off):
            _place(e.core, 0, 102.0, d=-1.5, speed=20.0)
            e.core._locate()
        view = c.traffic.actions(c, (np.zeros(1), np.zeros(1), np.zeros(1)))
        line = off.core.traffic.actions(off.core, (np.zeros(1), np.zeros(1), np.zeros(1)))
        assert view[0][1] > line[0][1] + 0.05, (view[0][1], line[0][1])  # steer > 0: left
    finally:
        env.close()
        off.close()
    with pytest.raises(TrafficError, match="side_gap_m must be a number"):
        TrafficSpec.from_config({"side_gap_m": -1})


def test_same_seed_same_race():
    a, a0, pa = _rollout(3)
    b, b0, pb = _rollout(3)
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(a0, b0, rtol=0, atol=0)
    np.testing.assert_array_equal(pa, pb)
    _, c0, pc = _rollout(4)
    assert not np.array_equal(pa, pc)  # another seed: other paces (and grid order)


def test_exact_resume_with_opponents():
    kw = dict(track="oval", num_cars=1, seed=5, sensors=("state", "opponents"),
              traffic={"opponents": 2, "driver": {"kind": "expert", "pace": 0.8}}, **FAST)
    env, twin = make_env(**kw), make_env(**kw)
    try:
        td = env.reset()
        twin.reset()
        act = td.set("action", torch.tensor([0.0, 0.6]))
        for _ in range(8):
            env.step(act)
        twin.set_sim_state(env.get_sim_state())
        for _ in range(8):
            x = env.step(act)["next"]
            y = twin.step(act)["next"]
            torch.testing.assert_close(x["opponents"], y["opponents"], rtol=0, atol=0)
            torch.testing.assert_close(x["state"], y["state"], rtol=0, atol=0)
    finally:
        env.close()
        twin.close()


def test_bad_traffic_fails_in_one_line():
    with pytest.raises(TrafficError, match="do not fit the grid of 12 slots; allowed: opponents <= 11") as e:
        TrafficSpec.from_config({"opponents": 12})
    assert "\n" not in str(e.value)
    with pytest.raises(TrafficError, match="allowed: expert, policy, slow, parked"):
        TrafficSpec.from_config({"driver": {"kind": "bus"}})
    from torcsrl.policies import load_policy

    with pytest.raises(TrafficError, match="cannot give an opponent; allowed: a policy on rangefinder, state, telemetry, opponents"):
        load_opponent_policy("reference_camera", load_policy)
    with pytest.raises(ValueError, match="traffic: unknown keys"):
        RaceCore(track="oval", traffic={"opponent": 3})


def test_policy_opponents_forget_their_readings_when_their_race_restarts(tmp_path):
    """Opponents of kind policy: a frozen checkpoint with a state history (state_history=3) acts for both opponent cars
    as one batch; when the race restarts its stacks restart too (K copies of the new first reading), not the last
    race's readings."""
    from _compose import compose_config

    from torcsrl.policies import load_policy
    from torcsrl.training import train
    from torcsrl.utils.checkpoint import latest_checkpoint

    train(compose_config("debug=smoke", "env.track=oval", "eval.max_steps=20", "threads=1", "algo=dagger", "state_history=3",
                         "demos.frames=80", "algo.bc_steps=5", "demos.dagger_rounds=0", f"run_dir={tmp_path / 'r'}"))
    ck = str(latest_checkpoint(tmp_path / "r" / "checkpoints"))
    env = make_env(track="oval", num_cars=1, seed=3, sensors=("rangefinder", "state", "opponents"), max_steps=4,
                   traffic={"opponents": 2, "driver": {"kind": "policy", "policy": ck}}, policy_loader=load_policy, **FAST)
    try:
        pol = env.core.traffic._policies[ck]
        td = env.reset()
        for _ in range(4):
            td = env.step(td.set("action", torch.tensor([0.0, 0.8])))["next"]
        hist = pol._history["state"]
        assert hist.shape == (2, 33) and not torch.equal(hist[:, :11], hist[:, -11:])  # 2 cars, 3 different readings
        env.reset()
        env.step(td.set("action", torch.tensor([0.0, 0.8])))
        new = pol._history["state"]
        assert torch.equal(new[:, :11], new[:, 11:22])  # the restart's first reading, repeated (then the newest)
    finally:
        env.close()


def test_opponent_policies_are_handed_in_by_the_layer_above():
    """The env loads no policies: an opponent of kind policy is loaded by the ``policy_loader`` make_env is given (the
    layer above hands in ``torcsrl.policies.load_policy``); without one, or when the loader fails, the env fails in one
    line. Scripted opponents need none, through gymnasium too."""
    import gymnasium as gym

    from torcsrl.envs import ENV_ID

    tr = {"opponents": 1, "driver": {"kind": "policy", "policy": "some_driver"}}
    with pytest.raises(TrafficError, match="needs a policy loader, which this env was not given") as e:
        RaceCore(track="oval", traffic=tr)
    assert "\n" not in str(e.value)
    asked = []

    def loader(spec):
        asked.append(spec)
        if spec != "some_driver":
            raise ValueError(f"no driver {spec!r}")
        return SimpleNamespace(obs_keys=("pixels",))

    with pytest.raises(TrafficError, match="reads \\['pixels'\\], which the env cannot give an opponent"):
        load_opponent_policy("some_driver", loader)
    with pytest.raises(TrafficError, match="traffic opponent policy 'other': no driver 'other'"):
        load_opponent_policy("other", loader)
    with pytest.raises(TrafficError, match="needs a policy loader"):
        make_env(track="oval", traffic=tr, **FAST)
    with pytest.raises(TrafficError, match="reads \\['pixels'\\]"):
        make_env(track="oval", traffic=tr, policy_loader=loader, **FAST)
    assert asked == ["some_driver", "other", "some_driver"]
    with pytest.raises(TrafficError, match="traffic: unknown keys \\['policy_loader'\\]"):
        TrafficSpec.from_config({"opponents": 1, "policy_loader": loader})
    with pytest.raises(TrafficError, match="policy_loader must be a callable"):
        TrafficSpec.from_config({"opponents": 1}).with_policy_loader("torcsrl.policies.load_policy")
    env = gym.make(ENV_ID, track="oval", traffic={"opponents": 2, "driver": {"kind": "expert", "pace": 0.6}}, **FAST)
    try:
        obs, _ = env.reset(seed=0)
        obs, *_ = env.step(np.array([0.0, 0.5], dtype=np.float32))
        assert env.unwrapped.core.traffic.K == 2
    finally:
        env.close()


def test_sector_directions_are_the_sectors_opponent_sectors_fills():
    """A car placed along sector k's centre direction (``sector_directions``) is seen in sector k."""
    cos, sin = sector_directions()
    for k in (0, 9, 17, 18, 26, 35):
        xy = np.array([[0.0, 0.0], [20.0 * cos[k], 20.0 * sin[k]]])
        opp = opponent_sectors(xy, np.zeros(2), np.zeros(2, dtype=np.int64))
        assert opp[0, k] == pytest.approx(20.0, abs=1e-4) and (np.delete(opp[0], k) == 200.0).all(), k
