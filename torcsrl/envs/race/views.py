"""What a :class:`~torcsrl.envs.race.core.RaceCore` is built from and shows: its track slots, loaded on first use
(:class:`TrackSlots`), and the learners of a race as the camera sees them (:class:`LearnerView`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from torcsrl.envs import tracks as _tracks
from torcsrl.envs.world import TRACK_SPACING_M

__all__ = ["TrackSlots", "LearnerView"]


class LearnerView:
    """The learners of a race core as the camera sees them (:class:`torcsrl.envs.camera.CarCameras` reads ``fleet``,
    ``slot``, ``car_tracks``, ``_geometry``, ``steps``, ``sensors``, ``track_origins``): frames are rendered for the
    learners only, and race group g's copy of a track is a visual world of its own (virtual slot
    ``slot + n_slots x g``, at the group's origin), so each learner sees its own opponents."""

    def __init__(self, core) -> None:
        self._core = core
        self.sensors = core.sensors
        self.fleet = _LearnerFleet(core)
        self._geometry = _Cycle(core._geometry)

    @property
    def slot(self) -> np.ndarray:
        c = self._core
        nl = c.n_learners
        return c.slot[:nl] + len(c._geometry) * np.arange(nl)

    @property
    def car_tracks(self) -> list:
        return self._core.car_tracks[: self._core.n_learners]

    @property
    def steps(self) -> np.ndarray:
        return self._core.steps[: self._core.n_learners]

    @property
    def track_origins(self) -> np.ndarray:
        c = self._core
        k = len(c._geometry)
        g = np.arange(k * c.n_learners) // k
        return c.track_origins[np.arange(k * c.n_learners) % k] + np.stack([np.zeros(len(g)), g * TRACK_SPACING_M], 1)


class TrackSlots(Sequence):
    """The base :class:`~torcsrl.envs.track.Track` of each slot, by name, loaded on first access: the first ``loaded``
    at once, the rest (a procedural pool of ~100 generated tracks, ~10 ms each) when a car first draws them. A
    generated track is a function of its name, so the order of loading changes nothing."""

    def __init__(self, names: Sequence[str], loaded: int = 0) -> None:
        self._names = list(names)
        self._tracks: list[Any] = [None] * len(self._names)
        for i in range(min(int(loaded), len(self._names))):
            self[i]

    def __len__(self) -> int:
        return len(self._names)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        t = self._tracks[i]
        if t is None:
            t = self._tracks[i] = _tracks.load(self._names[i])
        return t


class _Cycle:
    def __init__(self, items: list) -> None:
        self._items = items

    def __getitem__(self, i: int):
        return self._items[int(i) % len(self._items)]


class _LearnerFleet:
    def __init__(self, core) -> None:
        self._core = core
        self.params = core.fleet.params

    @property
    def pos(self) -> np.ndarray:
        return self._core.fleet.pos[: self._core.n_learners]

    @property
    def rotation(self) -> np.ndarray:
        return self._core.fleet.rotation[: self._core.n_learners]
