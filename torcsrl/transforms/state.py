"""Degradations of the "state" vector (angle, trackPos, speeds, wheel spin, rpm, gear, ...).

The slots have different units and scales, so the transforms treat the vector generically:

* ``slots``: indices of the slots to degrade (default: all);
* ``scale``: the size of one "unit" of each slot, a number or a [S] list (default 1.0). Absolute
  terms (noise a, bias B) are multiplied by it; relative terms (noise b, scale error ε) are not.

State latency is :class:`~torcsrl.transforms.temporal.Latency` on "state"
(registry name ``state.latency``).
"""

from __future__ import annotations

import torch

from ._base import Degradation

__all__ = ["StateDegradation", "StateNoise", "StateBias", "StateDropout"]


class StateDegradation(Degradation):
    sensor = "state"
    default_in_keys = ("state",)
    options = {"slots": None, "scale": 1.0}

    def _check_spec(self, key, spec):
        if not spec.dtype.is_floating_point or len(spec.shape) < 1:
            raise TypeError(f"{type(self).__name__}: {key!r} must be a float vector [..., S]")
        S = spec.shape[-1]
        slots = self.opts["slots"]
        if slots is not None and (max(slots) >= S or min(slots) < -S):
            raise ValueError(f"{type(self).__name__}: slots {slots} out of range for S={S}")
        sc = self.opts["scale"]
        if not isinstance(sc, (int, float)) and len(sc) != S:
            raise ValueError(f"{type(self).__name__}: scale has {len(sc)} entries for S={S}")

    def _check_options(self):
        sc = self.opts["scale"]
        sc = [sc] if isinstance(sc, (int, float)) else list(sc)
        if any(float(v) < 0 for v in sc):
            raise ValueError(f"{type(self).__name__}: scale must be >= 0")

    def _scale(self, x):
        sc = self.opts["scale"]
        if isinstance(sc, (int, float)):
            return float(sc)
        return torch.as_tensor(sc, dtype=x.dtype, device=x.device)

    def _degrade(self, x, key, st, reset):
        y = self._vec(x, key, st, reset, len(st["_B"]))
        slots = self.opts["slots"]
        if slots is None:
            return y
        sel = torch.zeros(x.shape[-1], dtype=torch.bool, device=x.device)
        sel[list(slots)] = True
        return torch.where(sel, y, x)

    def _vec(self, x, key, st, reset, nb):
        raise NotImplementedError


class StateNoise(StateDegradation):
    """``state.noise``: x + N(0, a·scale + b·|x|) every step."""

    name = "state.noise"
    ladder = {"a": (0.005, 0.01, 0.02, 0.04, 0.08), "b": (0.005, 0.01, 0.02, 0.03, 0.05)}

    def _vec(self, x, key, st, reset, nb):
        sigma = self.bview(st["a"], x, nb) * self._scale(x) + self.bview(st["b"], x, nb) * x.abs()
        return torch.addcmul(x, self.randn(x.shape, x.device), sigma)


class StateBias(StateDegradation):
    """``state.bias``: miscalibrated sensors, (1 + ε_i)·x + b_i per slot with ε_i ~ U(±E),
    b_i ~ U(±bias·scale), drawn at each reset. bias = .01, .025, .05, .1, .2; eps = .5..5 %."""

    name = "state.bias"
    ladder = {"bias": (0.01, 0.025, 0.05, 0.1, 0.2), "eps": (0.005, 0.01, 0.02, 0.03, 0.05)}
    episodic = True

    def _vec(self, x, key, st, reset, nb):
        kst = st["_keys"].get(key)
        if kst is None or kst["u"].shape != x.shape + (2,):
            kst = st["_keys"][key] = {"u": self.rand(x.shape + (2,), x.device) * 2 - 1}
        elif reset is not None:
            new = self.rand(x.shape + (2,), x.device) * 2 - 1
            kst["u"] = torch.where(self.bview(reset, new, nb), new, kst["u"])
        u = kst["u"]
        bias = u[..., 0] * self.bview(st["bias"], x, nb) * self._scale(x)
        scale = 1.0 + u[..., 1] * self.bview(st["eps"], x, nb)
        return torch.addcmul(bias, scale, x)


class StateDropout(StateDegradation):
    """``state.dropout``: each slot, each step, reads ``fill`` (default 0: a sensor that
    returned nothing) with probability p = 2, 5, 10, 20, 35 %."""

    name = "state.dropout"
    ladder = {"p": (0.02, 0.05, 0.10, 0.20, 0.35)}
    kinds = {"p": "prob"}
    options = {"slots": None, "scale": 1.0, "fill": 0.0}

    def _vec(self, x, key, st, reset, nb):
        drop = self.rand(x.shape, x.device) < self.bview(st["p"], x, nb)
        return x.masked_fill(drop, float(self.opts["fill"]))
