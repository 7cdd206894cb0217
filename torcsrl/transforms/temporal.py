"""Faults in time, for any sensor key: latency (a delayed reading) and holds (a dropped
scan / frame repeats the previous one).

One transform may hold several keys (``in_keys=["pixels", "depth"]``); they then share the
draws (the same delay, the same dropped frames), so the camera's colour and depth stay in step.
"""

from __future__ import annotations

import torch

from ._base import Degradation

__all__ = ["Latency", "Hold", "ScanDrop", "FrameDrop"]

_ALL_SENSOR_KEYS = ("rangefinder", "state", "telemetry", "pixels", "depth")


class Latency(Degradation):
    """Whole-reading delay: the env at step t sees the reading of step t - k.

    ``steps`` k per severity 1, 2, 3, 5, 8 (episode); from s3 a per-step jitter of ±``jitter``
    steps (the delay then wanders between k - 1 and k + 1). Right after a reset there is no past,
    so the reset reading is repeated until k readings have arrived.

    ``Latency(steps=2)`` with no ``in_keys`` delays every sensor key the env has
    ("rangefinder", "state", "pixels", "depth"): a late control loop. Registry names
    ``rangefinder.latency``, ``state.latency``, ``camera.latency`` restrict it to one sensor.
    """

    name = "latency"
    sensor = "any"
    auto_keys = _ALL_SENSOR_KEYS
    ladder = {"steps": (1, 2, 3, 5, 8), "jitter": (0, 0, 1, 1, 1)}
    kinds = {"steps": "int", "jitter": "int"}
    temporal = True
    episodic = True

    def __init__(self, severity=3, **kwargs):
        if "steps" in kwargs and "jitter" not in kwargs:
            kwargs["jitter"] = 0  # an explicit delay means exactly that delay
        super().__init__(severity, **kwargs)
        self.max_delay = int((self._ladder["steps"] + self._ladder["jitter"]).max().item())
        self.buffer_len = self.max_delay + 1
        lo, hi = self.severity_range
        self._jitter = bool(self._ladder["jitter"][lo - 1 : hi].max() > 0)

    def _begin_step(self, st, reset):
        if self._jitter:
            j = st["jitter"]
            u = self.rand(st["_B"], st["_dev"]) * (2 * j + 1)
            st["delay"] = (st["steps"] + (u.floor() - j)).clamp(0, self.max_delay).long()
        elif "delay" not in st or reset is not None:
            st["delay"] = st["steps"].long()

    def _degrade(self, x, key, st, reset):
        L = self.buffer_len
        B = st["_B"]
        nb = len(B)
        kst = st["_keys"].get(key)
        if kst is None or kst["hist"].shape[1:] != x.shape:
            kst = st["_keys"][key] = {
                "hist": x.unsqueeze(0).expand((L,) + x.shape).clone(),
                "ptr": 0,
            }
        hist = kst["hist"]
        if reset is not None:
            m = self.bview(reset, x, nb).unsqueeze(0)
            hist.copy_(torch.where(m, x.unsqueeze(0), hist))
        else:
            kst["ptr"] = (kst["ptr"] + 1) % L
            hist[kst["ptr"]].copy_(x)
        idx = (kst["ptr"] - st["delay"]) % L
        N = idx.numel()
        flat = hist.reshape(L, N, -1)
        out = flat[idx.reshape(N), torch.arange(N, device=x.device)]
        return out.reshape(x.shape)


class Hold(Degradation):
    """With probability p per step (per env), the reading is not refreshed: the previous one
    is repeated (a dropped scan or frame). Consecutive drops keep holding the same reading."""

    name = "hold"
    sensor = "any"
    auto_keys = _ALL_SENSOR_KEYS
    ladder = {"p": (0.01, 0.02, 0.05, 0.10, 0.20)}
    kinds = {"p": "prob"}
    temporal = True

    def _begin_step(self, st, reset):
        drop = self.rand(st["_B"], st["_dev"]) < st["p"]
        st["drop"] = drop

    def _degrade(self, x, key, st, reset):
        nb = len(st["_B"])
        kst = st["_keys"].get(key)
        if kst is None or kst["last"].shape != x.shape:
            kst = st["_keys"][key] = {"last": x.clone()}
        last = kst["last"]
        if reset is not None:
            out = torch.where(self.bview(reset, x, nb), x, last)
        else:
            out = torch.where(self.bview(st["drop"], x, nb), last, x)
        kst["last"] = out
        return out


class ScanDrop(Hold):
    """``rangefinder.scan_drop``: hold the previous scan with probability p (1%..20%)."""

    name = "rangefinder.scan_drop"
    sensor = "rangefinder"
    default_in_keys = ("rangefinder",)


class FrameDrop(Hold):
    """``camera.frame_drop``: hold the previous camera frame with probability p (1%..20%).
    With no ``in_keys`` it holds "pixels" and "depth" together (whichever the env has)."""

    name = "camera.frame_drop"
    sensor = "camera"
    auto_keys = ("pixels", "depth")
