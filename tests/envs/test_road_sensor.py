"""The privileged ``road`` sensor (an asymmetric critic's): the grip under the wheels and the mean curvature of the
centreline over five stretches ahead, from the track map."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.envs.sensors import ROAD_AHEAD_M, ROAD_SLOTS, road_readings
from torcsrl.envs.track import Track


def _circle(radius: float, n: int = 720) -> Track:
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return Track("circle", np.stack([radius * np.cos(a), radius * np.sin(a)], 1), 6.0, 6.0, 0)


@pytest.mark.parametrize("radius", [30.0, 120.0])
def test_a_circle_reads_one_over_its_radius_on_every_stretch(radius):
    circle, other = _circle(radius), _circle(2 * radius)  # cars on two tracks in one call: each read on its own
    got = road_readings([circle, other, circle], np.array([17.0, 5.0, 300.0]), np.array([0.6, 0.5, 1.0]))
    assert got.shape == (3, len(ROAD_SLOTS)) == (3, 1 + len(ROAD_AHEAD_M)) and got[:, 0].tolist() == pytest.approx([0.6, 0.5, 1.0])
    n = len(ROAD_AHEAD_M)  # counter-clockwise: bends left, > 0
    assert got[:, 1:].ravel().tolist() == pytest.approx([1 / radius] * n + [0.5 / radius] * n + [1 / radius] * n, rel=0.01)


def test_the_race_env_reads_the_bends_ahead_and_the_surface_under_the_wheels():
    """On hairpins from the grid (a straight, then a hairpin 150-200 m on): the near stretch reads straight while a far one reads the
    bend; mu is the info's surfaceMu (asphalt 1.0, dirt lower); the key is in the TorchRL spec and the gymnasium space."""
    from gymnasium.utils.env_checker import check_env

    from torcsrl.envs.race.gym_env import RaceEnv

    env = make_env(track="hairpins", surface="dirt", sensors=("rangefinder", "state", "road"), seed=0)
    try:
        assert env.observation_spec["road"].shape == (6,)
        td = env.reset()
        road = td["road"]
        assert abs(float(road[1])) < 1e-3 and float(road[1:].abs().max()) > 5e-3  # straight under the car, a bend ahead
        td["action"] = torch.tensor([0.0, 0.5])
        nxt = env.step(td)["next"]
        assert float(nxt["road"][0]) == pytest.approx(float(nxt["info", "surfaceMu"]), abs=1e-6) and float(nxt["road"][0]) < 0.9
    finally:
        env.close()
    gym = RaceEnv(track="oval", sensors=("rangefinder", "state", "road"))
    try:
        check_env(gym, skip_render_check=True)
    finally:
        gym.close()


def test_an_unknown_sensor_names_road_among_the_allowed():
    with pytest.raises(ValueError, match=r"allowed: .*road"):
        make_env(track="oval", sensors=("rangefinder", "roads"))
