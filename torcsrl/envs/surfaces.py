"""Road surfaces as data: friction coefficient, rolling resistance and display colour.

The table lives in ``surfaces.yaml`` beside this module. A surface's *id* is its index in
:data:`SURFACE_NAMES`; arrays of surface ids are what the track model and the vehicle exchange.
``grass`` is what lies off the track.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np
import yaml


@dataclass(frozen=True)
class Surface:
    """One road surface.

    Attributes:
        name: surface name (``asphalt``, ``wet``, ``dirt``, ``gravel``, ``ice``, ``grass``).
        mu: peak tyre-road friction coefficient [-].
        rolling_resistance: rolling-resistance coefficient [-] (force = crr · normal load).
        color: RGB in [0, 1].
    """

    name: str
    mu: float
    rolling_resistance: float
    color: tuple[float, float, float]


def _load() -> dict[str, Surface]:
    text = resources.files("torcsrl.envs").joinpath("surfaces.yaml").read_text()
    raw = yaml.safe_load(text)
    out = {}
    for name, spec in raw.items():
        out[name] = Surface(name, float(spec["mu"]), float(spec["rolling_resistance"]), tuple(spec["color"]))
    return out


SURFACES: dict[str, Surface] = _load()
SURFACE_NAMES: tuple[str, ...] = tuple(SURFACES)
#: Surfaces a track stretch may have (everything but grass, which is off the track).
ROAD_SURFACES: tuple[str, ...] = tuple(n for n in SURFACE_NAMES if n != "grass")
GRASS_ID: int = SURFACE_NAMES.index("grass")
#: mu and rolling resistance indexed by surface id.
MU: np.ndarray = np.array([SURFACES[n].mu for n in SURFACE_NAMES])
ROLLING_RESISTANCE: np.ndarray = np.array([SURFACES[n].rolling_resistance for n in SURFACE_NAMES])
COLORS: np.ndarray = np.array([SURFACES[n].color for n in SURFACE_NAMES])


def surface_id(name: str) -> int:
    """The id of a surface name; an unknown name raises ``ValueError`` listing the known ones."""
    try:
        return SURFACE_NAMES.index(name)
    except ValueError:
        raise ValueError(f"unknown surface {name!r}; known surfaces: {', '.join(SURFACE_NAMES)}") from None


def get(name: str) -> Surface:
    """The :class:`Surface` called ``name`` (``ValueError`` listing the known names otherwise)."""
    return SURFACES[SURFACE_NAMES[surface_id(name)]]
