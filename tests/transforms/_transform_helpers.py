"""Shared helpers for the transform tests."""

from __future__ import annotations

import torch

from torcsrl.transforms import applies_to, degradation_class, degradation_names, make_degradation

NAMES = degradation_names()

#: knobs that make slow faults show within a short test episode
TEST_PARAMS = {"rangefinder.stuck": {"onset_max": 5}}


def keys_for(name: str) -> list[str]:
    return list(applies_to(name))


def make(name: str, severity=3, seed: int | None = 0, **kw):
    params = {**TEST_PARAMS.get(name, {}), **kw}
    return make_degradation(name, severity, keys_for(name), seed=seed, **params)


def cls(name: str):
    return degradation_class(name)


def is_temporal(name: str) -> bool:
    return cls(name).temporal


def is_stochastic(name: str) -> bool:
    return cls(name).stochastic


def deviation(a: torch.Tensor, b: torch.Tensor) -> float:
    """Mean |a - b| as float, ignoring off-track scans (-1)."""
    a = a.float()
    b = b.float()
    return float((a - b).abs().mean())
