"""Procedural training distributions: pools of generated tracks drawn from a seed range.

A race env built with ``procedural={"seeds": [lo, hi], "pool": N, "share": p}`` adds ``N`` generated
tracks to its track list (names ``proc-<seed>``, :func:`torcsrl.envs.tracks.generate_circuit`; or
``gen-<seed>`` with ``generator: gen``; ``generator: [gen, proc]`` mixes them, the pool's k-th track from the
k-th generator in turn — half blobs, half circuits). With ``difficulty: [lo, hi]`` (``proc`` only) each pool
circuit's difficulty is ``lo + (hi - lo) u`` (to 3 decimals), ``u`` the difficulty its seed would draw,
so a curriculum that raises ``hi`` makes the same seeds' circuits tighter; the tracks are then named
``proc-<seed>@<difficulty>``. Their seeds are drawn without replacement from
``[lo, hi)`` by a stream seeded with the env's own seed, so every env (worker, validation env) of a
run gets its own tracks and the same config and seed always get the same ones. Each episode then
drives a pool track with probability ``share`` and one of the named tracks otherwise.

Seed ranges are data, and held out means held out:

* :data:`TRAIN_SEEDS` ``[10_000, 1_000_000)`` — the default training range;
* :data:`HELDOUT_SEEDS` ``[0, 1_000)`` — evaluation only (``benchmarks/generalisation.py`` drives
  ``proc-0 … proc-<n-1>``); a training range that overlaps it is refused before anything is built.

Why a pool and not a fresh track every episode: a new track costs ~60 ms to generate and wall in
(generator + rangefinder mesh), and pybullet keeps the vertex lists of every collision mesh built in
a client, so rebuilding walls each episode grows memory without bound. A pool of a few hundred tracks
built once (a few seconds) gives the same coverage for training runs of this size; the pool size is a
knob (``pool``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from torcsrl.envs.tracks.generator import seed_difficulty

__all__ = ["TRAIN_SEEDS", "HELDOUT_SEEDS", "GENERATORS", "ProceduralSpec", "heldout_names"]

#: Default training seed range [lo, hi) of procedural tracks.
TRAIN_SEEDS: tuple[int, int] = (10_000, 1_000_000)
#: Seed range [lo, hi) reserved for evaluation: never trained, selected or tuned on.
HELDOUT_SEEDS: tuple[int, int] = (0, 1_000)
#: Track-name prefix of each generator: ``proc`` (circuits with hairpins, chicanes, straights; difficulty
#: drawn from the seed) or ``gen`` (the older blob-around-a-circle generator with default knobs).
GENERATORS = {"proc": "proc-", "gen": "gen-"}


def heldout_names(n: int, generator: str = "proc", start: int = HELDOUT_SEEDS[0]) -> list[str]:
    """Names of ``n`` held-out procedural tracks: ``proc-<start> … proc-<start + n - 1>``."""
    lo, hi = HELDOUT_SEEDS
    if not (lo <= start and start + n <= hi):
        raise ValueError(f"held-out procedural seeds are [{lo}, {hi}); {n} tracks from {start} leave it")
    return [f"{GENERATORS[generator]}{s}" for s in range(start, start + n)]


@dataclass(frozen=True)
class ProceduralSpec:
    """A pool of generated training tracks (see the module docstring).

    Attributes:
        seeds: ``(lo, hi)`` range the pool's seeds are drawn from [-].
        pool: tracks in the pool [-].
        share: probability that an episode drives a pool track rather than a named one [-].
        generator: ``proc`` or ``gen`` (:data:`GENERATORS`), or a tuple of them: the pool's k-th track comes from
            ``generator[k % len(generator)]`` (a mixed pool; the same seeds as one generator would draw).
        difficulty: ``(lo, hi)`` within [0, 1] that the pool circuits' difficulties are scaled into
            (0: wide, gentle, few features ... 1: tight hairpins, narrow; ``generate_circuit``); None:
            each seed's own draw.
    """

    seeds: tuple[int, int] = TRAIN_SEEDS
    pool: int = 200
    share: float = 0.8
    generator: str | tuple[str, ...] = "proc"
    difficulty: tuple[float, float] | None = None

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> ProceduralSpec | None:
        """The spec of a ``procedural`` mapping (None or empty: no pool); ``ValueError`` (one line) when a
        value is out of range, the seed range is empty, smaller than the pool or overlaps the held-out range."""
        if cfg is None:
            return None
        d = dict(cfg)
        if not d:
            return None
        unknown = sorted(set(d) - {"seeds", "pool", "share", "generator", "difficulty"})
        if unknown:
            raise ValueError(f"procedural: unknown keys {unknown}; allowed: seeds, pool, share, generator, difficulty")
        seeds = d.get("seeds", TRAIN_SEEDS)
        try:
            lo, hi = (int(v) for v in seeds)
        except (TypeError, ValueError):
            raise ValueError(f"procedural.seeds must be [lo, hi) (two integers), got {seeds!r}") from None
        if lo < 0 or hi <= lo:
            raise ValueError(f"procedural.seeds=[{lo}, {hi}) is empty or negative; give 0 <= lo < hi")
        hlo, hhi = HELDOUT_SEEDS
        if lo < hhi and hlo < hi:
            raise ValueError(f"procedural.seeds=[{lo}, {hi}) overlaps the held-out seed range [{hlo}, {hhi}); "
                             f"training seeds must lie outside it (default {list(TRAIN_SEEDS)})")
        pool = d.get("pool", cls.pool)
        if isinstance(pool, bool) or int(pool) != pool or pool < 1:
            raise ValueError(f"procedural.pool must be a positive integer, got {pool!r}")
        if int(pool) > hi - lo:
            raise ValueError(f"procedural.pool={pool} exceeds the {hi - lo} seeds of procedural.seeds=[{lo}, {hi})")
        share = float(d.get("share", cls.share))
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"procedural.share={share} is outside [0, 1]")
        gen = _generator(d.get("generator", cls.generator))
        return cls((lo, hi), int(pool), share, gen, _difficulty(d.get("difficulty"), gen))

    def track_seeds(self, env_seed: int | None) -> list[int]:
        """The pool's track seeds for an env seeded with ``env_seed`` (distinct, deterministic)."""
        lo, hi = self.seeds
        rng = np.random.default_rng([0x70726F63, lo, hi, 0 if env_seed is None else int(env_seed) & ((1 << 63) - 1)])
        out: list[int] = []
        seen: set[int] = set()
        while len(out) < self.pool:
            for s in rng.integers(lo, hi, size=self.pool - len(out)).tolist():
                if s not in seen:
                    seen.add(s)
                    out.append(int(s))
        return out

    def names(self, env_seed: int | None) -> list[str]:
        """Track names of the pool for an env seeded with ``env_seed`` (``proc-<seed>@<difficulty>`` with a difficulty range)."""
        if self.difficulty is None:
            gens = (self.generator,) if isinstance(self.generator, str) else self.generator
            return [f"{GENERATORS[gens[k % len(gens)]]}{s}" for k, s in enumerate(self.track_seeds(env_seed))]
        lo, hi = self.difficulty
        return [f"proc-{s}@{lo + (hi - lo) * seed_difficulty(s):.3f}" for s in self.track_seeds(env_seed)]


def _generator(value) -> str | tuple[str, ...]:
    """``procedural.generator``: one of :data:`GENERATORS`, or a list of distinct ones (a mixed pool)."""
    many = not isinstance(value, str) and hasattr(value, "__iter__")
    names = [str(v) for v in value] if many else [str(value)]
    bad = [n for n in names if n not in GENERATORS]
    if bad or not names or len(set(names)) != len(names):
        why = f"{bad[0]!r} is not known" if bad else "needs at least one generator" if not names else "repeats a generator"
        raise ValueError(f"procedural.generator={list(names) if many else names[0]!r}: {why}; allowed: "
                         f"{', '.join(GENERATORS)} or a list of them (a mixed pool)")
    return names[0] if len(names) == 1 else tuple(names)


def _difficulty(value, generator: str | tuple[str, ...]) -> tuple[float, float] | None:
    """``procedural.difficulty``: null, a number or [lo, hi] within [0, 1] (generator proc only)."""
    if value is None:
        return None
    nums = list(value) if isinstance(value, (list, tuple)) else [value, value]
    ok = len(nums) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in nums)
    if not ok or not 0.0 <= nums[0] <= nums[1] <= 1.0:
        raise ValueError(f"procedural.difficulty must be a number or [lo, hi] with 0 <= lo <= hi <= 1, got {value!r}")
    if generator != "proc":
        raise ValueError(f"procedural.difficulty scales generate_circuit's difficulty: it needs generator: proc, not {generator!r}")
    return float(nums[0]), float(nums[1])
