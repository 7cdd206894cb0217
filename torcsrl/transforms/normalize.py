"""Observation scaling: the race env's sensor readings (SI / TORCS units) divided into about [-1, 1].

:func:`obs_scale` gives the divisors of one observation key, from the sensors' own constants
(:data:`torcsrl.envs.sensors.RANGE_M`, :data:`~torcsrl.envs.sensors.STATE_SCALE`): rangefinder / 200 m (so [0, 1],
-1/200 off track), angle / pi, trackPos as is, speeds / 300 km/h, wheel spin / 150 rad/s, rpm / 10,000, gear / 6,
opponents' sectors / 200 m, the privileged road's curvatures x 20 m -- which maps a lap at racing speed into about
[-1, 1], as the studies fed their networks.
:func:`normalize_transform` is the TorchRL transform that applies them; the observation pipeline
(:func:`torcsrl.pipeline.observation_transforms`) puts it after every degradation when ``env.normalize``.
"""

from __future__ import annotations

import numpy as np
import torch
from torchrl.envs.transforms import Compose, ObservationNorm

from torcsrl.envs.sensors import RANGE_M, RANGEFINDER_ANGLES_DEG, ROAD_SCALE, STATE_SCALE, STATE_SLOTS, TELEMETRY_SLOTS

__all__ = ["NORMALIZED_KEYS", "normalize_transform", "obs_scale"]

#: The observation keys that have a scale (images are left as they are).
NORMALIZED_KEYS = ("rangefinder", "state", "telemetry", "opponents", "road")


def obs_scale(key: str, n_beams: int = len(RANGEFINDER_ANGLES_DEG)) -> np.ndarray:
    """Divisors that normalise observation ``key`` (rangefinder, state, telemetry, opponents or road)."""
    if key == "rangefinder":
        return np.full(n_beams, RANGE_M, dtype=np.float32)
    if key == "opponents":
        return np.full(36, 200.0, dtype=np.float32)
    if key == "road":
        return np.array(ROAD_SCALE, dtype=np.float32)
    if key in ("state", "telemetry"):
        return np.array([STATE_SCALE[s] for s in (STATE_SLOTS if key == "state" else TELEMETRY_SLOTS)], dtype=np.float32)
    raise ValueError(f"no scale for {key!r}; scales exist for rangefinder, state, telemetry, opponents and road")


def normalize_transform(keys=("rangefinder", "state"), n_beams: int = len(RANGEFINDER_ANGLES_DEG)) -> Compose:
    """A TorchRL ``Compose`` of ``ObservationNorm`` dividing each key by :func:`obs_scale`."""
    ts = []
    for k in keys:
        scale = torch.as_tensor(1.0 / obs_scale(k, n_beams))
        ts.append(ObservationNorm(loc=torch.zeros_like(scale), scale=scale, in_keys=[k], standard_normal=False))
    return Compose(*ts)
