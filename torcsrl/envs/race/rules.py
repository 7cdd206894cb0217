"""The episode's vocabulary and rules, shared by the core, its faces and the config checks: the action and start
modes, the ``info`` keys, the termination reasons, the checks of the episode settings, and the progress of cars on
tracks of their own (:func:`wrap_deltas`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["ACTION_MODES", "START_MODES", "INFO_KEYS", "TERMINATION_REASONS", "wrap_deltas", "episode_setting_problems"]

ACTION_MODES = ("combined", "separate")
START_MODES = ("grid", "random")
#: Keys of the per-car bookkeeping reported in ``info`` (TORCS names; SI units).
#: ``surfaceMu`` [-] is the mean friction coefficient under the car's four wheels (surface x tyre): privileged
#: knowledge for teachers (a camera sees the surface, no TORCS sensor does); no observation carries it.
INFO_KEYS: tuple[str, ...] = ("distFromStart", "distRaced", "lap", "curLapTime", "lastLapTime", "bestLapTime", "surfaceMu")
TERMINATION_REASONS: tuple[str, ...] = ("", "off_track", "backwards", "no_progress", "flipped")


def wrap_deltas(s_new: np.ndarray, s_old: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """:meth:`Track.wrap_delta` of each car on its own track (lap lengths ``lengths``), vectorised: the same
    operations elementwise, so each entry has the bits ``car_tracks[i].wrap_delta(s_new[i], s_old[i])`` has."""
    half = 0.5 * lengths
    return np.mod(s_new - s_old + half, lengths) - half


def episode_setting_problems(**settings: Any) -> list[tuple[str, str]]:
    """``(key, message)`` for each of ``spawn_jitter``, ``offtrack_grace_s``, ``no_progress_s``,
    ``backwards_m`` given in ``settings`` that :class:`~torcsrl.envs.race.core.RaceCore` cannot use (also run by torcsrl.config)."""
    out: list[tuple[str, str]] = []

    def number(v: Any) -> float | None:
        try:
            x = float(v)
        except (TypeError, ValueError):
            return None
        return x if math.isfinite(x) else None

    if "spawn_jitter" in settings and settings["spawn_jitter"] is not None:
        sj = settings["spawn_jitter"]
        vals = [number(v) for v in sj] if isinstance(sj, (list, tuple)) else []
        if len(vals) != 2 or any(v is None or v < 0 for v in vals):
            out.append(("spawn_jitter", f"must be two finite half-ranges [d_m, yaw_rad] >= 0, got {sj!r}; allowed: e.g. [1.0, 0.1]"))
    for key, none_ok in (("offtrack_grace_s", False), ("no_progress_s", True), ("backwards_m", False)):
        if key not in settings or (settings[key] is None and none_ok):
            continue
        v = number(settings[key])
        if v is None or v < 0:
            out.append((key, f"must be a finite number >= 0, got {settings[key]!r}; allowed: [0, inf)"
                             + (" or None (never)" if none_ok else "")))
    return out
