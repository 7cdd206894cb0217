"""Raycast car physics in pybullet (:mod:`torcsrl.envs.vehicle.fleet`)."""

from __future__ import annotations

from torcsrl.envs.vehicle.fleet import *  # noqa: F401,F403
from torcsrl.envs.vehicle.fleet import BACKENDS, PYTHON_BACKEND_MAX_CARS, __all__  # noqa: F401
