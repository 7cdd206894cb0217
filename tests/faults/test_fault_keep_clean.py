"""Defect 9: a weather preset built in code with ``keep_clean=True`` acts on the sensors the env has
(the default rangefinder + state race env has no pixels or depth)."""

from __future__ import annotations

import pytest
from torchrl.envs.utils import check_env_specs

from torcsrl.transforms import DegradedEnv, make_preset


@pytest.mark.parametrize("preset", ["rain", "fog", "dust"])
def test_keep_clean_preset_on_the_default_race_env(preset):
    from torcsrl.envs import make_env

    env = DegradedEnv(make_env(track="oval", max_steps=50), make_preset(preset, 4, keep_clean=True))  # the README's example
    try:
        env.set_seed(0)
        td = env.rollout(3)
        keys = set(td.keys())
        assert {"rangefinder_clean", "state_clean"} <= keys
        assert not {"pixels_clean", "depth_clean"} & keys
        check_env_specs(env)
    finally:
        env.close()


def test_keep_clean_preset_keeps_pixels_where_the_env_has_them():
    from torcsrl.envs.toy import make_toy_env

    env = DegradedEnv(make_toy_env(sensors=("rangefinder", "state", "pixels"), camera={"height": 16, "width": 16}),
                      make_preset("rain", 3, keep_clean=True))
    try:
        env.set_seed(0)
        td = env.rollout(2)
        assert {"rangefinder_clean", "state_clean", "pixels_clean"} <= set(td.keys())
    finally:
        env.close()
