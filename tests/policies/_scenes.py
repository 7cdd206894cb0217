"""Shared scenes of the policy tests: observations of a hand-built road and hand-placed cars."""

from __future__ import annotations

import math

import numpy as np
import torch

from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG, STATE_SLOTS
from torcsrl.policies import REFERENCE_POLICY, REFERENCE_RL_POLICY

#: The shipped rangefinder drivers (the DAgger reference and the TD3 reference read the same observations).
A, B = str(REFERENCE_POLICY), str(REFERENCE_RL_POLICY)


def act(pol, td):
    """The action ``pol`` writes on a copy of ``td``."""
    return pol(td.clone())["action"]


def straight_road(half_width_m: float = 6.0, speed_kmh: float = 72.0):
    """Beams [m] and a raw state of a car on the axis of a straight road, heading along it."""
    r = np.array([min(200.0, half_width_m / max(abs(math.sin(math.radians(a))), 1e-9)) for a in RANGEFINDER_ANGLES_DEG])
    st = np.zeros(len(STATE_SLOTS))
    st[STATE_SLOTS.index("speedX_kmh")] = speed_kmh
    return r, st


def sectors(**cars):
    """36 free sectors (200 m) with a car at ``s<k>=distance``."""
    opp = np.full(36, 200.0)
    for k, dist in cars.items():
        opp[int(k[1:])] = dist
    return opp


def guard_scene(steer, tp=0.0, **cars):
    """One row: an action (steer, pedal 0.5), the opponents sectors (``s<k>=distance``, the rest free) and trackPos."""
    opp = torch.full((1, 36), 200.0)
    for k, d in cars.items():
        opp[0, int(k[1:])] = d
    return torch.tensor([[steer, 0.5]]), opp, torch.tensor([tp])
