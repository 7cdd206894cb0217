"""The race's observation as one flat vector: :class:`FlatObservation`, the wrapper of ``torcsrl/RaceFlat-v0``.

``gymnasium.make("torcsrl/Race-v0")`` observes a ``Dict`` (one entry per sensor). Single-file RL code (CleanRL's
``td3_continuous_action.py`` and the like) sizes its networks from ``single_observation_space.shape``, which a
``Dict`` does not have. ``gymnasium.make("torcsrl/RaceFlat-v0", **same kwargs as Race-v0)`` is the same env under
:class:`FlatObservation`: the vector keys concatenated into one ``Box`` float32, in a fixed slot order.

Slot order: the vector keys in sensor order (:data:`torcsrl.envs.sensors.SENSOR_NAMES`), then any other vector key
in the ``Dict``'s order; within a key, its own order:

- ``rangefinder`` (19 with the default beams): ``rangefinder.0`` … ``rangefinder.18`` [m], beam ``i`` at
  :data:`~torcsrl.envs.sensors.RANGEFINDER_ANGLES_DEG` ``[i]`` (−90° … 90°, positive = left); all −1 off the track;
- ``state`` (11): ``state.<slot>`` for each of :data:`~torcsrl.envs.sensors.STATE_SLOTS` (angle_rad [rad],
  trackPos [-], speedX/Y/Z_kmh [km/h], wheelSpinVel_fl/fr/rl/rr [rad/s], rpm [1/min], gear [-]);
- ``telemetry`` (9): ``telemetry.<slot>`` for each of :data:`~torcsrl.envs.sensors.TELEMETRY_SLOTS`;
- ``opponents`` (36): ``opponents.0`` … ``opponents.35`` [m], one per 10° sector.

So the default sensors (``rangefinder``, ``state``) give 30 slots: 19 beams, then the 11 state slots.
:attr:`FlatObservation.slot_names` lists every slot, :attr:`FlatObservation.slices` each key's slice. Image keys
(``pixels``, ``depth``) cannot be flattened: an env that observes them is refused in one line naming them.
The values are the env's own, in its units (no scaling).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from torcsrl.envs.sensors import SENSOR_NAMES, STATE_SLOTS, TELEMETRY_SLOTS

__all__ = ["FlatObservation", "flat_slot_names"]

#: Named slots of the keys whose slots have names (the others are numbered).
_NAMED_SLOTS: dict[str, tuple[str, ...]] = {"state": STATE_SLOTS, "telemetry": TELEMETRY_SLOTS}


def flat_slot_names(key: str, size: int) -> list[str]:
    """``<key>.<slot>`` for the ``size`` slots of ``key``: the named slots of ``state`` / ``telemetry``, else
    ``<key>.0`` … ``<key>.<size-1>``."""
    names = _NAMED_SLOTS.get(key)
    if names is not None and len(names) == size:
        return [f"{key}.{n}" for n in names]
    return [f"{key}.{i}" for i in range(size)]


class FlatObservation(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """The vector keys of a ``Dict`` observation concatenated into one ``Box`` float32, in a fixed slot order.

    The order is the vector keys in sensor order (rangefinder, state, telemetry, opponents), then any other
    one-dimensional key in the ``Dict``'s order (see the module docstring for every slot and its unit).

    Attributes:
        keys: the flattened keys, in slot order.
        slot_names: one name per slot, ``<key>.<slot>`` (``rangefinder.0``, ``state.angle_rad``, …).
        slices: ``{key: slice}``, where each key's slots sit in the flat vector.

    Raises:
        ValueError: the observation space is not a ``Dict`` of ``Box`` es, or it holds keys that are not vectors
            (``pixels``, ``depth``); the message names them.
    """

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.ObservationWrapper.__init__(self, env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict):
            raise ValueError(f"FlatObservation flattens a Dict observation; this env observes {type(space).__name__}")
        ordered = [k for k in SENSOR_NAMES if k in space.spaces] + [k for k in space.spaces if k not in SENSOR_NAMES]
        not_vectors = [k for k in ordered if not (isinstance(space[k], spaces.Box) and len(space[k].shape) == 1)]
        if not_vectors:
            raise ValueError(f"FlatObservation flattens vector keys only; this env also observes {', '.join(not_vectors)} "
                             "(images): leave them out of sensors=, or use torcsrl/Race-v0's Dict observation")
        self.keys: tuple[str, ...] = tuple(ordered)
        self.slices: dict[str, slice] = {}
        self.slot_names: list[str] = []
        lows, highs, start = [], [], 0
        for k in self.keys:
            box = space.spaces[k]
            n = int(box.shape[0])
            self.slices[k] = slice(start, start + n)
            self.slot_names += flat_slot_names(k, n)
            lows.append(np.asarray(box.low, dtype=np.float32))
            highs.append(np.asarray(box.high, dtype=np.float32))
            start += n
        self.observation_space = spaces.Box(np.concatenate(lows), np.concatenate(highs), dtype=np.float32)

    def observation(self, observation: dict[str, Any]) -> np.ndarray:
        """The flat vector ``[len(slot_names)]`` float32 of one ``Dict`` observation."""
        return np.concatenate([np.asarray(observation[k], dtype=np.float32) for k in self.keys])
