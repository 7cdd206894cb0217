"""The race simulation core and its gymnasium face.

:class:`RaceCore` is the one simulation every face shares: N cars in one pybullet client (cars
never collide; each has its own track, progress and episode), TORCS-style sensors, named reward
terms, lap bookkeeping and the episode rules. :class:`RaceEnv` is its gymnasium face (one car);
:class:`torcsrl.envs.batched.TorchRaceEnv` its TorchRL face (one car or a batch).

One control step (the template method, :meth:`RaceCore.step`):
act (sanitise) → physics substeps → locate (Frenet projection, surfaces under the wheels) →
bookkeeping (progress, laps) → observe (sensors) → reward terms → terminated → truncated → info.

Modules: :mod:`~torcsrl.envs.race.rules` (the episode's modes, info keys, termination reasons and setting
checks), :mod:`~torcsrl.envs.race.core` (:class:`RaceCore`), :mod:`~torcsrl.envs.race.locate` (where each car is
on its track), :mod:`~torcsrl.envs.race.views` (the track slots, the learners as the camera sees them),
:mod:`~torcsrl.envs.race.gym_env` (:class:`RaceEnv`, its top-down frame).
"""

from __future__ import annotations

from torcsrl.envs.race.core import RaceCore
from torcsrl.envs.race.gym_env import RaceEnv, render_top_down
from torcsrl.envs.race.locate import PYTHON_WALK_MAX_CARS, SCALAR_LOCATE_MAX_CARS
from torcsrl.envs.race.rules import (ACTION_MODES, INFO_KEYS, START_MODES, TERMINATION_REASONS,
                                     episode_setting_problems, wrap_deltas)

__all__ = [
    "RaceCore",
    "RaceEnv",
    "ACTION_MODES",
    "START_MODES",
    "INFO_KEYS",
    "TERMINATION_REASONS",
    "SCALAR_LOCATE_MAX_CARS",
    "PYTHON_WALK_MAX_CARS",
    "wrap_deltas",
    "episode_setting_problems",
    "render_top_down",
]
