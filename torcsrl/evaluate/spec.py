"""What an evaluation runs, checked before it runs: the grid of tracks and surfaces, the degradation, the seeds
and the step cap of an episode (the inputs of the episode protocol, :mod:`torcsrl.evaluate.protocol`).

Light on purpose: the apps check their arguments with it before torch, TorchRL or pybullet load.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from torcsrl import metrics
from torcsrl.envs import surfaces as _surf
from torcsrl.envs import tracks as _tracks

__all__ = ["PROTOCOL_VERSION", "EvalError", "seed_for", "Degradation", "parse_degradation", "default_max_steps",
           "validate_grid"]

#: Version of the episode protocol (part of every cache key: bump it when a metric's meaning changes).
PROTOCOL_VERSION = 1


class EvalError(ValueError):
    """Bad evaluation input (unknown track, surface or degradation, empty grid): one line."""


def seed_for(seed: int, *parts: Any) -> int:
    """A 63-bit seed derived from ``seed`` and ``parts`` (stable across runs and processes)."""
    h = hashlib.sha256(repr((int(seed),) + tuple(str(p) for p in parts)).encode()).digest()
    return int.from_bytes(h[:8], "little") & ((1 << 63) - 1)


@dataclass(frozen=True)
class Degradation:
    """A degradation by registry name at a severity (0 = clean) with optional parameter overrides."""

    name: str = metrics.CLEAN
    severity: int = 0
    params: tuple[tuple[str, Any], ...] = ()

    @property
    def clean(self) -> bool:
        return self.name == metrics.CLEAN or self.severity == 0

    def label(self) -> str:
        return "clean" if self.clean else f"{self.name}@{self.severity}"

    def keys(self) -> tuple[str, ...]:
        """Observation keys the degradation can touch."""
        if self.clean:
            return ()
        from torcsrl.transforms import registry  # deferred: torchrl; a clean run and the argument checks need none

        if self.name.startswith("weather."):
            comps = registry.PRESETS[self.name.split(".", 1)[1]]
            return tuple(sorted({k for q, _, _ in comps for k in registry.applies_to(q)}))
        return tuple(registry.applies_to(self.name))

    def build(self):
        """The TorchRL transform (keys the env lacks are skipped)."""
        from torcsrl.transforms import make_degradation  # deferred: torchrl, only when the env is built

        if self.name.startswith("weather."):
            return make_degradation(self.name, severity=self.severity)
        return make_degradation(self.name, severity=self.severity, optional=True, **dict(self.params))


def _severity(v: Any, spec: Any) -> int:
    """An integer severity from ``v`` (of the degradation ``spec``), or EvalError."""
    try:
        if isinstance(v, bool) or (isinstance(v, float) and not v.is_integer()):
            raise ValueError
        return int(v)
    except (TypeError, ValueError):
        raise EvalError(f"degradation {spec!r}: severity {v!r} is not an integer; allowed: name or name@severity with "
                        "severity in 0..5 (0 = clean)") from None


def parse_degradation(d: Any, severity: int | None = None) -> Degradation:
    """A :class:`Degradation` from None, ``"name"``, ``"name@s"``, ``(name, s)``, a mapping
    ``{name, severity, **params}`` or a Degradation; checks the name and severity (EvalError)."""
    if d is None:
        return Degradation()
    if isinstance(d, Degradation):
        deg = d
    elif isinstance(d, str):
        name, _, s = d.partition("@")
        deg = Degradation(name, _severity(s if s else (severity if severity is not None else 3), d))
    elif isinstance(d, Mapping):
        m = dict(d)
        if "name" not in m:
            raise EvalError(f"a degradation mapping needs a name, got {d!r}; allowed: {{name, severity, **params}}")
        name = m.pop("name")
        s = _severity(m.pop("severity", severity if severity is not None else 3), d)
        deg = Degradation(name, s, tuple(sorted(m.items())))
    elif isinstance(d, (tuple, list)) and len(d) == 2:
        deg = Degradation(str(d[0]), _severity(d[1], d))
    else:
        raise EvalError(f"cannot read a degradation from {d!r}; use 'name', 'name@severity' or {{name, severity}}")
    if deg.name in (metrics.CLEAN, "clean"):
        return Degradation()
    if not 0 <= deg.severity <= 5:
        raise EvalError(f"severity must be in 0..5 (0 = clean), got {deg.severity} for {deg.name}")
    if deg.severity == 0:
        return Degradation()
    try:
        from torcsrl.transforms import registry  # deferred: torchrl, only for a named degradation
    except ImportError as err:
        raise EvalError(f"degradations need torcsrl.transforms, which cannot be imported ({err})") from None
    if deg.name.startswith("weather."):
        if deg.name.split(".", 1)[1] not in registry.PRESETS:
            raise EvalError(f"unknown weather preset {deg.name!r}; known: {', '.join('weather.' + p for p in registry.PRESETS)}")
    else:
        try:
            registry.degradation_class(deg.name)
        except ValueError as err:
            raise EvalError(str(err)) from None
    return deg


def default_max_steps(track_length_m: float, laps: int, dt: float = 0.02, min_speed_ms: float = 10.0,
                      min_lap_s: float = 60.0) -> int:
    """Step cap of an episode: ``laps`` laps at ``min_speed_ms`` (at least ``min_lap_s`` each)."""
    return int(math.ceil(laps * max(min_lap_s, track_length_m / min_speed_ms) / dt))


def validate_grid(tracks: Sequence[str] | str, surfaces: Sequence[str | None] | str | None) -> tuple[list[str], list[str | None]]:
    """Resolve track names and sets (``set:heldout``) and check surfaces; EvalError (one line)."""
    if isinstance(tracks, str):
        tracks = [tracks]
    if not tracks:
        raise EvalError("no track given (empty grid); name a track or a set such as set:heldout")
    try:
        names = _tracks.resolve(list(tracks))
        for n in names:
            _tracks.load(n)
    except ValueError as err:
        raise EvalError(str(err)) from None
    if not names:
        raise EvalError(f"the tracks {list(tracks)} resolve to no track (empty grid)")
    seen: list[str] = []
    for n in names:
        if n not in seen:
            seen.append(n)
    if surfaces is None or isinstance(surfaces, str):
        surfaces = [surfaces]
    surfaces = list(surfaces) or [None]
    for s in surfaces:
        if s is not None and s not in _surf.ROAD_SURFACES:
            raise EvalError(f"unknown surface {s!r}; road surfaces: {', '.join(_surf.ROAD_SURFACES)}")
    return seen, surfaces
