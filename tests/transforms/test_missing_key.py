"""A degradation of a key the env does not produce fails when it is attached, in one line naming the key and the env's
keys (TorchRL computes specs lazily: without the check it would fail at the first reset, in a traceback)."""

from __future__ import annotations

import pytest
from torchrl.envs import Compose, TransformedEnv

from torcsrl.envs.toy import make_toy_env
from torcsrl.transforms import BeamNoise, DegradedEnv, KeepClean, LeanTransformedEnv, make_degradation, make_preset, make_stack
from torcsrl.transforms._base import MissingKeyError
from torcsrl.utils.faults import cli_error


def _rangefinder_env():
    return make_toy_env(sensors=("rangefinder", "state"), seed=0)


def _camera_env():
    return make_toy_env(sensors=("pixels",), camera={"width": 16, "height": 16}, seed=0)


@pytest.mark.parametrize("wrap", [TransformedEnv, LeanTransformedEnv, DegradedEnv])
def test_camera_fog_on_a_rangefinder_env_fails_at_construction(wrap):
    with pytest.raises(MissingKeyError) as err:
        wrap(_rangefinder_env(), make_degradation("camera.fog", 3))
    line = str(err.value)
    assert line.startswith("camera.fog reads 'pixels', which this env does not produce; its keys: rangefinder, state")
    assert "\n" not in line
    assert isinstance(err.value, KeyError) and isinstance(err.value, ValueError)


def test_rangefinder_fog_on_a_camera_env_fails_at_construction():
    with pytest.raises(MissingKeyError, match=r"^rangefinder\.fog reads 'rangefinder', which this env does not produce; "
                                              r"its keys: pixels"):
        TransformedEnv(_camera_env(), make_degradation("rangefinder.fog", 3))


def test_a_stack_names_the_entry_that_does_not_fit():
    stack = make_stack({"noise": "rangefinder.noise", "rain": "camera.rain"}, seed=0)  # no env yet: nothing to check
    with pytest.raises(MissingKeyError, match=r"^camera\.rain reads 'pixels'"):
        LeanTransformedEnv(_rangefinder_env(), stack)


def test_append_transform_and_a_compose_joining_later_are_checked_too():
    env = TransformedEnv(_rangefinder_env(), make_degradation("rangefinder.noise", 2))
    with pytest.raises(MissingKeyError, match="reads 'pixels'"):
        env.append_transform(make_degradation("camera.noise", 2))
    with pytest.raises(MissingKeyError, match=r"BeamNoise reads 'lidar'|rangefinder\.noise reads 'lidar'"):
        TransformedEnv(_camera_env(), Compose(KeepClean(["pixels"]), BeamNoise(3, in_keys=["lidar"])))


def test_fitting_stacks_still_build_and_run():
    env = LeanTransformedEnv(_rangefinder_env(), make_stack({"noise": "rangefinder.noise", "bias": "state.bias"}, seed=0))
    env.rollout(3)
    # a key an earlier transform writes is a key of the stack
    env = TransformedEnv(_rangefinder_env(), Compose(KeepClean(["rangefinder"]),
                                                     BeamNoise(3, in_keys=["rangefinder_clean"], seed=0)))
    assert "rangefinder_clean" in env.rollout(2).keys()
    # optional components (weather presets, evaluation's robustness cells) skip what the env lacks
    TransformedEnv(_rangefinder_env(), make_preset("fog", 3, seed=0)).rollout(2)
    TransformedEnv(_rangefinder_env(), make_degradation("camera.fog", 3, optional=True)).rollout(2)
    TransformedEnv(_camera_env(), make_degradation("camera.fog", 3, seed=0)).rollout(2)


def test_the_entry_points_print_it_as_one_line(capsys):
    try:
        TransformedEnv(_rangefinder_env(), make_degradation("camera.fog", 3))
    except MissingKeyError as err:
        assert cli_error("train", err) == 2
    out = capsys.readouterr().err
    assert out.count("\n") == 1 and out.startswith("train: error: camera.fog reads 'pixels', which this env does not "
                                                   "produce; its keys: rangefinder, state")
