"""One observation pipeline: what a checkpoint's policy is fed equals what its actor saw in training."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from _compose import compose_config



@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from torcsrl.training import train

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("pipe") / "run"
    cfg = compose_config("debug=smoke", "env.track=oval", "env.max_steps=100", "eval.max_steps=20", "total_frames=150",
                         "checkpoint.every_frames=150", f"run_dir={out}")
    res = train(cfg)
    return cfg, Path(res["checkpoint"])


def test_policy_sees_exactly_the_training_observations(run):
    from torcsrl.envs import make_env
    from torcsrl.policies import CheckpointPolicy
    from torcsrl.pipeline import env_kwargs, make_train_env

    cfg, ck = run
    pol = CheckpointPolicy(ck)
    assert pol.pipeline["scales"]["rangefinder"][0] == 200.0 and pol.pipeline["control_hz"] == 10
    train_env = make_train_env(cfg)  # what the actor was trained on (degradations + scaling)
    raw = make_env(**env_kwargs(cfg.env, seed=int(cfg.seed) + 1000 * 0, device="cpu"))  # what evaluation drives: raw SI units
    try:
        a, b = train_env.reset(), raw.reset()
        for _ in range(5):
            act = torch.tensor([0.1, 0.5])
            a = train_env.step(a.set("action", act))["next"]
            b = raw.step(b.set("action", act))["next"]
        with torch.no_grad():
            from_train = pol.actor(*(a.get(k) for k in pol.obs_keys))
            from_raw = pol._act(*(b.get(k) for k in pol.obs_keys))
        assert not torch.equal(a.get("state"), b.get("state"))  # the scaling did something ...
        torch.testing.assert_close(from_raw, from_train)  # ... and the policy redoes exactly it
    finally:
        train_env.close()
        raw.close()


def test_a_checkpoint_whose_record_disagrees_is_refused(run, tmp_path):
    from torcsrl.policies import CheckpointPolicy, PolicyError

    _, ck = run
    data = torch.load(ck, weights_only=False)
    data["meta"]["pipeline"]["scales"]["rangefinder"] = [100.0] * 19
    bad = tmp_path / "bad.pt"
    from torcsrl.utils.checkpoint import save_checkpoint

    save_checkpoint(bad, data)  # written WITH this record (a plain torch.save of edited bytes fails its checksum first)
    with pytest.raises(PolicyError, match="observation scaling") as err:
        CheckpointPolicy(bad)
    assert "\n" not in str(err.value)
