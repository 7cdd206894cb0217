"""The fused one-env path of the rangefinder degradations (NumPy on one scan) gives exactly the torch path's
numbers, step after step, and a one-env stack equals row i of a batched stack given per-row seeds."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torcsrl.transforms import degradation_names, make_degradation, seed_degradation_rows, seed_degradations
from torcsrl.transforms.rangefinder import BeamDegradation


def _scans(T: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(T, 19, generator=g) * 220.0 - 10.0  # some beams beyond 200 m, a few off-track scans below
    x = x.clamp(0.0, 200.0)
    x[::17] = -1.0  # off the track: every beam at -1
    return x


def _run(t, xs: torch.Tensor) -> torch.Tensor:
    """Drive transform ``t`` over the scans ``xs [T, *B, 19]`` as an env would (reset, then steps)."""
    B = xs.shape[1:-1]
    out = [t._reset(TensorDict({}, B), TensorDict({"rangefinder": xs[0].clone()}, B)).get("rangefinder")]
    for x in xs[1:]:
        out.append(t._call(TensorDict({"rangefinder": x.clone()}, B)).get("rangefinder"))
    return torch.stack(out)


@pytest.mark.parametrize("name", degradation_names("rangefinder"))
@pytest.mark.parametrize("severity", [1, 3, 5])
def test_fused_equals_torch_path(name, severity):
    xs = _scans(120, seed=severity)
    fused = make_degradation(name, severity, seed=7)
    plain = make_degradation(name, severity, seed=7)
    if isinstance(plain, BeamDegradation):
        plain._fused = False  # the torch path at one env
    a, b = _run(fused, xs), _run(plain, xs)
    assert torch.equal(a, b)
    if name.endswith(("noise", "dropout", "fog", "rain", "snow")):
        assert not torch.equal(a, xs)  # it did degrade


@pytest.mark.parametrize("name", ["rangefinder.noise", "rangefinder.fog", "rangefinder.rain", "rangefinder.snow",
                                  "rangefinder.outliers", "rangefinder.quantize", "rangefinder.dropout", "rangefinder.stuck",
                                  "rangefinder.latency", "state.noise", "state.latency"])
def test_one_env_equals_its_row_of_a_batch(name):
    """What the batched evaluation relies on: row i of a batch with per-row seeds = a one-env copy with seed i."""
    key = "state" if name.startswith("state") else "rangefinder"
    T, n = 60, 4
    xs = _scans(T * n).reshape(T, n, 19)
    if key == "state":
        xs = xs[..., :11]
    seeds = [11, 12, 13, 14]
    batch = make_degradation(name, 4)
    seed_degradation_rows(batch, seeds)

    def run(t, xs):
        B = xs.shape[1:-1]
        out = [t._reset(TensorDict({}, B), TensorDict({key: xs[0].clone()}, B)).get(key)]
        for x in xs[1:]:
            out.append(t._call(TensorDict({key: x.clone()}, B)).get(key))
        return torch.stack(out)

    rows = run(batch, xs)
    for i, s in enumerate(seeds):
        one = make_degradation(name, 4)
        seed_degradations(one, s)
        assert torch.equal(run(one, xs[:, i]), rows[:, i]), i
