"""The bundled track library, track sets and procedural tracks.

Public API::

    from torcsrl.envs import tracks
    tracks.names()                       # bundled track names
    t = tracks.load("oval")              # a validated Track
    t = tracks.load("oval", surface="ice")
    t = tracks.generate(7, length_m=2500, corners=9)
    t = tracks.generate_circuit(7, difficulty=0.8)   # hairpins, chicanes, long straights, ...
    tracks.track_sets()                  # {"train": [...], "heldout": [...], ...}
    tracks.resolve("set:train")          # names in a set (or [name] for a track name)

Tracks are data files in ``torcsrl/envs/tracks/data`` (segment lists, or sidecars naming a
centreline point file); sets are in ``data/sets.yaml``. ``gen-<seed>`` names a procedural track
with the generator's default knobs and ``proc-<seed>`` a procedural circuit
(:func:`generate_circuit`, difficulty drawn from the seed; ``proc-<seed>@<difficulty>`` with that
difficulty in [0, 1]), so config can mix bundled and generated tracks.
"""

from __future__ import annotations

import copy
from functools import lru_cache
from importlib import resources
from pathlib import Path

import yaml

from torcsrl.envs.track import Track, TrackError
from torcsrl.envs.tracks.generator import generate, generate_circuit
from torcsrl.envs.tracks.sources import load_file

__all__ = ["Track", "TrackError", "names", "load", "load_file", "generate", "generate_circuit", "track_sets", "resolve",
           "data_dir", "cache_info", "clear_cache"]


def data_dir() -> Path:
    """Folder holding the bundled track files."""
    return Path(str(resources.files("torcsrl.envs.tracks").joinpath("data")))


def names() -> list[str]:
    """Names of the bundled tracks, sorted."""
    return sorted(p.stem for p in data_dir().glob("*.yaml") if p.stem != "sets")


def _generated(name: str) -> bool:
    """``gen-<seed>``, ``proc-<seed>`` or ``proc-<seed>@<difficulty>``: a procedural track named by its seed."""
    if name.startswith("gen-") and name[4:].isdigit():
        return True
    return _proc_name(name) is not None


def _proc_name(name: str) -> tuple[int, float | None] | None:
    """(seed, difficulty) of ``proc-<seed>`` (difficulty None: drawn from the seed) or ``proc-<seed>@<difficulty>``
    (a number in [0, 1]); None for any other name."""
    if not name.startswith("proc-"):
        return None
    seed, _, diff = name[5:].partition("@")
    if not seed.isdigit():
        return None
    if not _:
        return int(seed), None
    try:
        d = float(diff)
    except ValueError:
        return None
    return (int(seed), d) if 0.0 <= d <= 1.0 else None


#: Tracks kept parsed / generated [-]: a procedural pool (100) and the named tracks fit; bounded, because every env
#: seed draws its own pool, so a long run (a DAgger env per round) would otherwise keep every track it ever drew
#: (~4 MB each once driven: its projection caches).
TRACK_CACHE_SIZE = 160


@lru_cache(maxsize=TRACK_CACHE_SIZE)
def _load_cached(name: str) -> Track:
    if name.startswith("gen-"):
        return generate(int(name[4:]))
    proc = _proc_name(name)
    if proc is not None:
        seed, difficulty = proc
        return generate_circuit(seed, difficulty, name=name)
    return load_file(data_dir() / f"{name}.yaml")


def cache_info():
    """Hits, misses, size and bound (TRACK_CACHE_SIZE) of the parsed-track cache (``functools`` cache info)."""
    return _load_cached.cache_info()


def clear_cache() -> None:
    """Forget every parsed track (the next :func:`load` of each parses or generates it again)."""
    _load_cached.cache_clear()


def load(name: str, surface: str | None = None) -> Track:
    """A bundled (or ``gen-<seed>`` / ``proc-<seed>``) track by name, optionally on another road surface.

    Raises:
        ValueError: unknown name (the message lists the available ones) or unknown surface.
    """
    if not isinstance(name, str):
        raise ValueError(f"a track name must be a string, got {name!r}")
    if _generated(name) or name in names():
        track = copy.copy(_load_cached(name))
    else:
        raise ValueError(f"unknown track {name!r}; available: {', '.join(names())} (or gen-<seed> / proc-<seed> / "
                         f"proc-<seed>@<difficulty 0..1> for a generated one)")
    return track.with_surface(surface) if surface else track


@lru_cache(maxsize=1)
def _sets() -> dict[str, list[str]]:
    raw = yaml.safe_load((data_dir() / "sets.yaml").read_text())
    known = set(names())
    for set_name, members in raw.items():
        missing = [m for m in members if m not in known and not _generated(m)]
        if missing:
            raise TrackError(f"{data_dir() / 'sets.yaml'}: set {set_name!r} names unknown tracks {missing}")
    return {k: list(v) for k, v in raw.items()}


def track_sets() -> dict[str, list[str]]:
    """Named track sets, e.g. ``train`` and ``heldout`` (copies: safe to modify)."""
    return {k: list(v) for k, v in _sets().items()}


def resolve(spec: str | list[str] | tuple[str, ...]) -> list[str]:
    """Track names from a name, a ``set:<name>`` reference, or a list mixing both."""
    if isinstance(spec, (list, tuple)):
        out: list[str] = []
        for item in spec:
            out.extend(resolve(item))
        if not out:
            raise ValueError("an empty list of tracks; give at least one track name or set:<name>")
        return out
    if not isinstance(spec, str):
        raise ValueError(f"tracks are given by name, set:<name> or a list of those, got {spec!r}")
    if spec.startswith("set:"):
        sets = _sets()
        key = spec[4:]
        if key not in sets:
            raise ValueError(f"unknown track set {key!r}; available sets: {', '.join(sorted(sets))}")
        return list(sets[key])
    load(spec)  # validates the name
    return [spec]
