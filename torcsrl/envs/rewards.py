"""Named reward terms and the presets of the studies.

The scalar reward is ``scale · Σ weight[term] · term``; every term is reported in ``info``
(gymnasium) or under ``("info", "reward_<term>")`` (TorchRL) so it can be logged. Speeds are in
m/s, angles in radians, distances in metres.

=============  ==========================================  =====================
term           value per control step                       unit
=============  ==========================================  =====================
speed_cos      v_x · cos θ                                  m/s
speed_sin      −v_x · |sin θ|                               m/s
track_pos      −v_x · |trackPos|                            m/s
progress       Δs along the centreline this step            m
termination    1 on the step that terminates, else 0        –
collision      contact impulse with other cars this step    kN s
positions      race positions gained this step (− lost)     –
gap            safe-distance shortfall to the car ahead:    –
               max(0, 1 − gap / max(10 m, 1 s · v_x))
blocking       lateral move towards the line of a car       m
               within 20 m behind (|d − d_f| shrinking)
steer_change   |steering command − the previous step's|     action units
               (0 on an episode's first step)
=============  ==========================================  =====================

``steer_change`` is a smoothness term (a weight of −w makes a full left-to-right flip, 2 units, cost 2w per step
before the scale); no preset weighs it, so ``reward={preset: progress, steer_change: -1}`` turns it on.
The four before it are race terms (:mod:`torcsrl.envs.traffic`; 0 without traffic). Their weights carry the sign:
``race`` = ``summers_final`` + collision −1 per kN s, positions +1, gap −0.5 (Summers 2022's safe distance),
blocking −0.5 per m.

θ is the angle between the car and the track axis; v_x the car's forward speed.

Presets (weights):
- ``summers_initial`` (Summers 2022, first reward): v_x cos θ;
- ``summers_final`` (Summers 2022, final): v_x (cos θ − |sin θ|), termination −1;
- ``lau`` (Lau 2016 / Andersson et al.): v_x (cos θ − |sin θ| − |trackPos|), termination −500;
- ``progress``: Δs per step, termination −1;
- ``race``: ``summers_final`` plus the race terms (above).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

REWARD_TERMS: tuple[str, ...] = ("speed_cos", "speed_sin", "track_pos", "progress", "termination",
                                  "collision", "positions", "gap", "blocking", "steer_change")
#: The race terms (computed by :class:`torcsrl.envs.traffic.Traffic`), in REWARD_TERMS order.
RACE_TERMS: tuple[str, ...] = REWARD_TERMS[5:9]
#: Terms every preset leaves at weight 0 (summed apart, so that the presets' rewards stay the same to the bit).
EXTRA_TERMS: tuple[str, ...] = REWARD_TERMS[9:]

PRESETS: dict[str, dict[str, float]] = {
    "summers_initial": {"speed_cos": 1.0},
    "summers_final": {"speed_cos": 1.0, "speed_sin": 1.0, "termination": -1.0},
    "lau": {"speed_cos": 1.0, "speed_sin": 1.0, "track_pos": 1.0, "termination": -500.0},
    "progress": {"progress": 1.0, "termination": -1.0},
    "race": {"speed_cos": 1.0, "speed_sin": 1.0, "termination": -1.0, "collision": -1.0, "positions": 1.0, "gap": -0.5,
             "blocking": -0.5},
}


class Reward:
    """Weighted sum of named terms.

    Args:
        weights: a preset name, or a mapping ``{term: weight}`` (missing terms weigh 0), or a
            mapping with ``preset`` plus overrides, e.g. ``{"preset": "lau", "termination": -1}``.
        scale: factor on the summed reward (e.g. 0.01 to keep returns near 1–100).
    """

    def __init__(self, weights: str | Mapping[str, float] = "summers_final", scale: float = 1.0) -> None:
        if isinstance(weights, str):
            if weights not in PRESETS:
                raise ValueError(f"unknown reward preset {weights!r}; presets: {', '.join(PRESETS)}")
            w = dict(PRESETS[weights])
        elif isinstance(weights, Mapping):
            weights = dict(weights)
            preset = weights.pop("preset", None)
            if preset is not None and preset not in PRESETS:
                raise ValueError(f"unknown reward preset {preset!r}; presets: {', '.join(PRESETS)}")
            w = dict(PRESETS[preset]) if preset else {}
            unknown = [k for k in weights if k not in REWARD_TERMS]
            if unknown:
                raise ValueError(f"unknown reward terms {unknown}; terms: {', '.join(REWARD_TERMS)}")
            w.update({k: float(v) for k, v in weights.items()})
        else:
            raise ValueError(f"reward must be a preset name or a mapping of term weights, got {weights!r}")
        self.weights = {k: float(w.get(k, 0.0)) for k in REWARD_TERMS}
        bad = {k: v for k, v in self.weights.items() if not math.isfinite(v)}
        if bad:
            raise ValueError(f"reward weights must be finite numbers, got {bad}; allowed: any finite weight per term of {', '.join(REWARD_TERMS)}")
        self._w = np.array([self.weights[k] for k in REWARD_TERMS])
        n_core = len(REWARD_TERMS) - len(EXTRA_TERMS)
        self.core_weights = self._w[:n_core]
        #: (row, weight) of each extra term with a non-zero weight
        self.extra = [(n_core + j, self.weights[k]) for j, k in enumerate(EXTRA_TERMS) if self.weights[k] != 0.0]
        try:
            self.scale = float(scale)
        except (TypeError, ValueError):
            self.scale = math.nan
        if not math.isfinite(self.scale):
            raise ValueError(f"reward_scale must be a finite number, got {scale!r}; allowed: any finite factor (e.g. 0.05)")

    @staticmethod
    def terms(vx, angle, track_pos, progress, terminated, race: np.ndarray | None = None,
              steer_change: np.ndarray | None = None) -> np.ndarray:
        """All terms ``[T, N]`` in :data:`REWARD_TERMS` order, from arrays ``[N]`` (``race [4, N]``: the race
        terms, zeros when None; ``steer_change [N]``: zeros when None)."""
        vx = np.asarray(vx, dtype=np.float64)
        n = vx.shape[0]
        return np.concatenate([np.stack([
            vx * np.cos(angle),
            -vx * np.abs(np.sin(angle)),
            -vx * np.abs(track_pos),
            np.asarray(progress, dtype=np.float64),
            np.asarray(terminated, dtype=np.float64),
        ]), np.zeros((len(RACE_TERMS), n)) if race is None else race,
            (np.zeros(n) if steer_change is None else np.asarray(steer_change, dtype=np.float64))[None]])

    def __call__(self, terms: np.ndarray) -> np.ndarray:
        """Scalar rewards ``[N]`` from terms ``[T, N]``."""
        total = self.core_weights @ terms[:len(self.core_weights)]
        for row, w in self.extra:
            total = total + w * terms[row]
        return self.scale * total
