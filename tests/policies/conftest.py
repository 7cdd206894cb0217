"""Fixtures of the policy tests."""

from __future__ import annotations

import pytest
import torch

from torcsrl.envs import make_env
from torcsrl.policies import load_policy

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def states():
    """Observations of a car driven by the reference driver on the oval (the members disagree on some of them)."""
    pol = load_policy("reference")
    env = make_env(track="oval", sensors=pol.env_overrides["sensors"], control_hz=10, substeps=20)
    try:
        td = env.reset()
        out = []
        for _ in range(60):
            out.append(td.select(*pol.obs_keys).clone())
            td = env.step(pol(td))["next"]
        return torch.stack(out)
    finally:
        env.close()
