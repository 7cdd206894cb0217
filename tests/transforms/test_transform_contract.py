"""The contract every degradation keeps, checked for every registered name.

no env (plain TensorDict) · out_keys keep the clean value · Compose + TransformedEnv rollout +
check_env_specs (batch [] and [3]) · spec unchanged · reset observation degraded · same seed →
same output, other seed → other output · envs in a batch get independent draws · replay buffer
· severity is monotone. (ParallelEnv: test_transform_parallel.py, on a representative stack.)
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, check_env_specs

from _toy_sensor_env import ToySensorEnv
from _transform_helpers import NAMES, deviation, is_stochastic, is_temporal, keys_for, make
from torcsrl.transforms import DegradedEnv, KeepClean


@pytest.fixture(scope="module")
def clean_rollout() -> TensorDict:
    """Clean data [8 envs, 24 steps] with random phases (time dim named "time")."""
    env = ToySensorEnv([8], seed=3)
    with torch.no_grad():
        return env.rollout(24, break_when_any_done=False)


@pytest.fixture(scope="module")
def same_rollout() -> TensorDict:
    """Clean data [8, 16] where every env reads the same (isolates the transforms' draws)."""
    env = ToySensorEnv([8], fixed_phase=True, offtrack=False, seed=3)
    return env.rollout(16, break_when_any_done=False)


def _obs(td: TensorDict, keys) -> TensorDict:
    out = td.select(*keys).clone()
    if td.names and "time" in td.names:
        out.refine_names(*td.names)
    return out


@pytest.mark.parametrize("name", NAMES)
def test_plain_tensordict(name, clean_rollout):
    keys = keys_for(name)
    td = _obs(clean_rollout[:, 3], keys)  # env 0 is off the track at step 3
    out = make(name, 5)(td.clone())
    for k in keys:
        assert out[k].dtype == td[k].dtype and out[k].shape == td[k].shape
    if k == "rangefinder":
        assert (td[k][0] == -1).all() and (out[k][0] == -1).all(), "off-track scan must pass through"
    if not is_temporal(name):
        assert any((out[k] != td[k]).any() for k in keys)
    else:  # a snapshot has no past: temporal faults are the identity
        assert all(torch.equal(out[k], td[k]) for k in keys)


@pytest.mark.parametrize("name", NAMES)
def test_out_keys_keep_clean(name, clean_rollout):
    keys = keys_for(name)
    td = _obs(clean_rollout[:, 5], keys)
    t = make(name, 5, out_keys=[k + "_deg" for k in keys])
    out = t(td.clone())
    for k in keys:
        assert torch.equal(out[k], td[k])
        assert out[k + "_deg"].dtype == td[k].dtype and out[k + "_deg"].shape == td[k].shape


@pytest.mark.parametrize("name", NAMES)
def test_env_specs_rollout(name):
    keys = keys_for(name)
    base = ToySensorEnv([3])
    spec = base.observation_spec.clone()
    env = DegradedEnv(base, Compose(KeepClean(keys), make(name)))
    check_env_specs(env)
    for k in keys:
        assert env.observation_spec[k] == spec[k], "spec must be unchanged"
        assert env.observation_spec[k + "_clean"] == spec[k]
    td = env.rollout(6)
    assert td.batch_size == (3, 6)
    env1 = DegradedEnv(ToySensorEnv([]), make(name))
    check_env_specs(env1)


@pytest.mark.parametrize("name", [n for n in NAMES if not is_temporal(n)])
def test_reset_observation_degraded(name):
    keys = keys_for(name)
    env = DegradedEnv(ToySensorEnv([16]), Compose(KeepClean(keys), make(name, 5)))
    td = env.reset()
    assert any((td[k] != td[k + "_clean"]).any() for k in keys)


@pytest.mark.parametrize("name", NAMES)
def test_seed_reproducible(name):
    keys = keys_for(name)

    def run(seed):
        env = DegradedEnv(ToySensorEnv([8]), make(name, 5, seed=None))
        env.set_seed(seed)
        return env.rollout(12, break_when_any_done=False).select(*keys, ("next", keys[0]))

    a, b, c = run(7), run(7), run(8)
    assert (a == b).all()
    if is_stochastic(name):
        assert not (a == c).all()


@pytest.mark.parametrize("name", NAMES)
def test_envs_in_batch_differ(name, same_rollout):
    keys = keys_for(name)
    td = _obs(same_rollout, keys)
    sev = 5 if is_stochastic(name) else (1, 5)  # deterministic ones differ by a per-env severity
    out = make(name, sev, seed=1)(td.clone())
    k = keys[0]
    assert torch.equal(td[k][0], td[k][1])
    assert any(not torch.equal(out[k][0], out[k][j]) for j in range(1, 8))


@pytest.mark.parametrize("name", NAMES)
def test_replay_buffer(name, clean_rollout):
    keys = keys_for(name)
    data = _obs(clean_rollout, keys).reshape(-1)
    data.names = [None]
    rb = ReplayBuffer(storage=LazyTensorStorage(256), transform=make(name, 5), batch_size=32)
    rb.extend(data)
    sample, info = rb.sample(return_info=True)
    idx = info["index"]
    for k in keys:
        assert sample[k].dtype == data[k].dtype and sample[k].shape == (32,) + data[k].shape[1:]
    stored = data[idx]
    if not is_temporal(name):
        assert any((sample[k] != stored[k]).any() for k in keys)
    assert all(torch.equal(rb.storage[idx][k], stored[k]) for k in keys), "storage stays clean"


@pytest.mark.parametrize("name", NAMES)
def test_severity_monotone(name, clean_rollout):
    keys = keys_for(name)
    k = keys[0]
    td = _obs(clean_rollout, keys)
    devs = []
    for s in range(1, 6):
        out = make(name, s, seed=11)(td.clone())
        devs.append(deviation(out[k], td[k]))
    assert devs[4] > devs[0], devs
    for a, b in zip(devs, devs[1:]):
        assert b >= 0.75 * a - 1e-6, f"not monotone: {devs}"


@pytest.mark.parametrize("name", ["rangefinder.noise", "rangefinder.dead_beams", "state.noise", "state.latency"])
def test_p_switches_the_effect_on_for_a_share_of_episodes(name):
    """``p``: each env's effect is on for an episode with probability p (drawn at each reset), off envs read clean;
    ``p=1`` draws nothing more, so it is the effect without ``p`` to the bit; p outside (0, 1] is refused."""
    keys = keys_for(name)

    def rollout(**kw):
        torch.manual_seed(0)  # the random actions
        env = DegradedEnv(ToySensorEnv([64], offtrack=False, seed=3), Compose(KeepClean(keys), make(name, 5, seed=1, **kw)))
        return env.rollout(8, break_when_any_done=False)

    def clean_rows(td):  # envs whose observation equals the clean one at every step
        k = keys[0]
        return (td[k] == td[k + "_clean"]).reshape(64, 8, -1).all(-1).all(-1)

    base, same, half = rollout(), rollout(p=1.0), rollout(p=0.5)
    assert (base == same).all()
    assert not clean_rows(base).any()
    off = clean_rows(half)
    assert 16 <= int(off.sum()) <= 48  # about half of 64 envs read clean the whole episode
    on = ~off
    k = keys[0]
    assert not torch.equal(half[k][on], half[k + "_clean"][on])
    with pytest.raises(ValueError, match="allowed: 0 < p <= 1"):
        make(name, 5, p=0.0)
