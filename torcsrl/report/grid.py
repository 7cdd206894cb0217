"""The grid of a robustness report: its config, its cells and their names, the checks of its counts.

Light on purpose (no torch, no pybullet): the app checks a report's arguments with it before anything heavy loads;
running the grid is :mod:`torcsrl.report.runner`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torcsrl import metrics
from torcsrl.evaluate.spec import PROTOCOL_VERSION, EvalError

__all__ = [  # this module's own names (the package re-exports them with the runner's, results' and app's)
    "DEFAULT_DEGRADATIONS",
    "DEFAULT_TRACKS",
    "DEFAULT_SEVERITIES",
    "EFFECT_FAMILIES",
    "RANDOM",
    "Cell",
    "ReportConfig",
    "check_counts",
    "code_hash",
    "default_workers",
    "expand_degradations",
    "sensor_and_family",
    "stable_hash",
]

#: The no-argument report: two held-out tracks (asphalt and dirt), four degradations over two
#: sensors, severities 0, 1, 3, 5, one episode of one lap per cell.
DEFAULT_TRACKS = ("kidney", "rallycross")
DEFAULT_DEGRADATIONS = ("rangefinder.noise", "rangefinder.dropout", "state.noise", "state.latency")
DEFAULT_SEVERITIES = (0, 1, 3, 5)
#: Effect families used to group the per-degradation tables (by the part after the sensor).
EFFECT_FAMILIES: dict[str, tuple[str, ...]] = {
    "noise & bias": ("noise", "quantize", "outliers", "bias_scale", "bias"),
    "missing data": ("dropout", "dead_beams", "fov_loss", "stuck", "scan_drop", "frame_drop", "occlusion", "mud"),
    "timing": ("latency",),
    "weather & light": ("fog", "rain", "snow", "spray", "droplets", "glare", "darkness", "motion_blur"),
}
RANDOM = "random"


def sensor_and_family(name: str) -> tuple[str, str]:
    """("rangefinder", "noise & bias") for "rangefinder.noise"; weather presets → ("all sensors", "weather preset")."""
    if name.startswith("weather."):
        return "all sensors", "weather preset"
    sensor, _, effect = name.partition(".")
    for fam, effects in EFFECT_FAMILIES.items():
        if effect in effects:
            return sensor, fam
    return sensor, "other"


@dataclass
class ReportConfig:
    """What a report runs. ``policies``: specs (:func:`torcsrl.policies.load_policy`);
    ``reference``: the CE denominator (default: the first policy); ``tracks``: names or sets;
    ``surfaces``: road surfaces (None: each track's own); ``degradations``: registry names or
    ``weather.<preset>``; ``severities``: subset of 0..5 (0 is always run); ``episodes`` per
    cell; ``laps`` per episode; ``max_steps``: step cap (default: laps at 10 m/s);
    ``random_max_steps``: cap for the random baseline's episodes; ``env_kwargs``: more
    make_env keywords; ``workers``: processes (None: min(4, CPUs), or on a Ray cluster its CPUs);
    ``n_boot``: bootstrap resamples; ``batch_cars``: up to
    this many episodes of the cells that share a policy and a track drive as cars of one env
    (:func:`torcsrl.evaluate.batched.run_batch`, the same episodes as one car at a time; 1 = one car
    at a time; policies that cannot drive a batch always drive one car at a time); ``ray``: None (cells
    run in this process or in ``workers`` processes), or the Ray address the cells run on as Ray tasks
    (``local``: a Ray instance of ``workers`` CPUs started here; ``auto``; ``host:port``; ``ray://host:port``:
    :mod:`torcsrl.utils.ray_session`) — the same cells, cache and report either way."""

    policies: list[str] = field(default_factory=lambda: ["reference"])
    reference: str | None = None
    tracks: list[str] = field(default_factory=lambda: list(DEFAULT_TRACKS))
    surfaces: list[str | None] = field(default_factory=lambda: [None])
    degradations: list[str] = field(default_factory=lambda: list(DEFAULT_DEGRADATIONS))
    severities: list[int] = field(default_factory=lambda: list(DEFAULT_SEVERITIES))
    episodes: int = 1
    laps: int = 1
    seed: int = 0
    max_steps: int | None = None
    random_max_steps: int = 1500
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    workers: int | None = 1
    n_boot: int = 1000
    batch_cars: int = 128
    ray: str | None = None

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> "ReportConfig":
        """From a plain mapping (e.g. ``OmegaConf.to_container(cfg.report)``); unknown keys: EvalError."""
        known = set(cls.__dataclass_fields__)
        bad = sorted(set(d) - known)
        if bad:
            raise EvalError(f"unknown report setting(s) {bad}; known: {', '.join(sorted(known))}")
        return cls(**{k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in d.items()})

    def cell_config(self) -> dict[str, Any]:
        """The part of the config every cell depends on (its hash is the config hash): the episode
        protocol and the code that produces an episode (env, degradations, evaluation loop)."""
        return {"protocol": PROTOCOL_VERSION, "episodes": int(self.episodes), "laps": int(self.laps), "seed": int(self.seed),
                "max_steps": self.max_steps, "random_max_steps": int(self.random_max_steps),
                "env_kwargs": {k: self.env_kwargs[k] for k in sorted(self.env_kwargs)}, "code": code_hash()}


@functools.lru_cache(maxsize=1)
def code_hash() -> str:
    """Hash of the sources that decide an episode's outcome: ``torcsrl/envs`` (physics, sensors,
    tracks), ``torcsrl/transforms`` (degradations) and ``torcsrl/evaluate/`` (the episode protocol); read
    once per process."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    files = sorted([*(root / "envs").rglob("*.py"), *(root / "envs").rglob("*.yaml"), *(root / "transforms").rglob("*.py"),
                    *(root / "evaluate").glob("*.py")])
    for f in files:
        if "__pycache__" in f.parts:
            continue
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def stable_hash(obj: Any) -> str:
    """SHA-256 hex digest of ``obj`` as sorted-key JSON (the same for equal configs in any process)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


# --------------------------------------------------------------------------------------------
# Cells
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Cell:
    policy: str  # unique name in this report
    spec: str
    fingerprint: str
    track: str
    surface: str
    corruption: str
    severity: int
    params: tuple = ()
    own_surface: bool = True  # the track's own surfaces (``surface`` is then only its label)

    def key(self, config_hash: str) -> str:
        return stable_hash([config_hash, self.fingerprint, self.track, self.surface, self.own_surface, self.corruption,
                      self.severity, list(self.params)])[:32]

    def label(self) -> str:
        c = "clean" if self.corruption == metrics.CLEAN else f"{self.corruption}@{self.severity}"
        return f"{self.policy} {self.track}/{self.surface} {c}"


def default_workers() -> int:
    """Worker processes when ``workers`` is None: min(4, this machine's CPUs)."""
    return max(1, min(4, os.cpu_count() or 1))


def check_counts(**counts: Any) -> None:
    """EvalError (one line) for a count below 1: ``n_boot`` (bootstrap resamples), ``episodes``, ``laps``, ``workers``,
    ``max_steps`` (None: the default), ``random_max_steps``."""
    for name, v in counts.items():
        if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 1):
            flag = "--" + name.replace("_", "-")
            raise EvalError(f"{flag} (report {name}) must be an integer >= 1, got {v!r}; allowed: 1, 2, ... "
                            + ("(1000 is the default)" if name == "n_boot" else ""))


def expand_degradations(names: Sequence[str]) -> list[str]:
    """Names, with the groups ``all-rangefinder``, ``all-state``, ``all-camera``, ``heldout`` expanded."""
    out: list[str] = []
    for n in names:
        if n.startswith("all-") or n == "heldout":
            try:
                from torcsrl.transforms import registry  # deferred: torchrl, only for a group of degradations
            except ImportError as err:
                raise EvalError(f"degradation groups need torcsrl.transforms ({err})") from None
            out += registry.degradation_names(heldout=True) if n == "heldout" else registry.degradation_names(n[4:])
        else:
            out.append(n)
    return list(dict.fromkeys(out))
