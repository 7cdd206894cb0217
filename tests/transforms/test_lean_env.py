"""LeanTransformedEnv: TorchRL's TransformedEnv without the per-step input copy, same results."""

import pytest
import torch
from torchrl.envs import Compose, ObservationNorm, RewardSum, TransformedEnv

from torcsrl.transforms import KeepClean, LeanTransformedEnv, make_degradation
from torcsrl.transforms._base import _input_untouched

from _toy_sensor_env import ToySensorEnv


def _stack(extra=()):
    return Compose(KeepClean(["rangefinder"]), make_degradation("rangefinder.noise", 3, seed=1),
                   make_degradation("state.latency", 2, seed=2), make_degradation("rangefinder.dead_beams", 4, seed=3),
                   ObservationNorm(loc=torch.zeros(()), scale=torch.tensor(0.01), in_keys=["rangefinder"]), *extra)


def _race():
    from torcsrl.envs import make_env

    return make_env(track="oval", sensors=("rangefinder", "state"), max_steps=40, seed=0)


@pytest.mark.parametrize("make_base", [lambda: ToySensorEnv(batch_size=(3,), max_steps=17), _race], ids=["toy_batch3", "race"])
def test_lean_env_steps_exactly_as_transformed_env(make_base):
    """Same rollouts (episodes end and reset inside), the caller's input left as it was."""
    ref_env, lean_env = TransformedEnv(make_base(), _stack()), LeanTransformedEnv(make_base(), _stack())
    assert _input_untouched(lean_env.transform)
    torch.manual_seed(0)
    ref = ref_env.rollout(100, break_when_any_done=False)
    torch.manual_seed(0)
    lean = lean_env.rollout(100, break_when_any_done=False)
    assert bool(ref["next", "done"].any())  # resets happened inside the rollout
    assert set(ref.keys(True, True)) == set(lean.keys(True, True))
    for k in ref.keys(True, True):
        torch.testing.assert_close(lean[k], ref[k], rtol=0, atol=0, msg=str(k))
    td = lean_env.reset()
    td.set("action", lean_env.action_spec.rand())
    before = {k: v.clone() for k, v in td.items(True, True)}
    lean_env.step(td.clone(False))
    lean_env.step(td)
    assert set(td.exclude("next").keys(True, True)) == set(before)
    for k, v in before.items():
        torch.testing.assert_close(td[k], v, rtol=0, atol=0)


def test_lean_env_defers_to_transformed_env_for_transforms_that_read_the_step_input():
    stack = _stack([RewardSum()])
    assert not _input_untouched(stack)
    ref_env, lean_env = TransformedEnv(ToySensorEnv(max_steps=9), _stack([RewardSum()])), LeanTransformedEnv(ToySensorEnv(max_steps=9), stack)
    torch.manual_seed(0)
    ref = ref_env.rollout(30, break_when_any_done=False)
    torch.manual_seed(0)
    lean = lean_env.rollout(30, break_when_any_done=False)
    torch.testing.assert_close(lean["next", "episode_reward"], ref["next", "episode_reward"], rtol=0, atol=0)
    torch.testing.assert_close(lean["next", "rangefinder"], ref["next", "rangefinder"], rtol=0, atol=0)
