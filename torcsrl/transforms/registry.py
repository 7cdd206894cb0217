"""Names for every degradation and weather preset, as config and reports refer to them.

Degradation names are ``<sensor>.<effect>``: ``rangefinder.fog``, ``state.noise``,
``camera.fog``. :func:`make_degradation` also accepts the bare effect ("fog") together with the
observation keys, and picks the sensor from the keys.

Weather presets (``weather.<name>``: rain, fog, snow, night, dust) degrade several sensors
together at one severity; see :data:`PRESETS`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from torchrl.envs import Compose, Transform

from . import camera, rangefinder, state, temporal
from ._base import Degradation, KeepClean, SENSOR_KEYS, derive_seed

__all__ = [
    "HELDOUT",
    "PRESETS",
    "applies_to",
    "degradation_names",
    "degradation_class",
    "make_degradation",
    "make_preset",
    "make_stack",
    "preset_names",
    "sensor_of_key",
]


@dataclass(frozen=True)
class _Entry:
    cls: type[Degradation]
    in_keys: tuple[str, ...]  # default keys for this name
    keys: tuple[str, ...]  # every observation key it can degrade


def _cam(cls, depth: bool | None = None) -> _Entry:
    depth = cls.supports_depth if depth is None else depth
    return _Entry(cls, ("pixels",), ("pixels", "depth") if depth else ("pixels",))


_R = ("rangefinder",)
_S = ("state",)
_O = ("opponents",)

_REGISTRY: dict[str, _Entry] = {
    # rangefinder
    "rangefinder.noise": _Entry(rangefinder.BeamNoise, _R, _R),
    "rangefinder.quantize": _Entry(rangefinder.BeamQuantize, _R, _R),
    "rangefinder.dropout": _Entry(rangefinder.BeamDropout, _R, _R),
    "rangefinder.dead_beams": _Entry(rangefinder.DeadBeams, _R, _R),
    "rangefinder.fov_loss": _Entry(rangefinder.FovLoss, _R, _R),
    "rangefinder.bias_scale": _Entry(rangefinder.BeamBiasScale, _R, _R),
    "rangefinder.stuck": _Entry(rangefinder.StuckBeams, _R, _R),
    "rangefinder.outliers": _Entry(rangefinder.BeamOutliers, _R, _R),
    "rangefinder.latency": _Entry(temporal.Latency, _R, _R),
    "rangefinder.scan_drop": _Entry(temporal.ScanDrop, _R, _R),
    "rangefinder.fog": _Entry(rangefinder.BeamFog, _R, _R),
    "rangefinder.rain": _Entry(rangefinder.BeamRain, _R, _R),
    "rangefinder.snow": _Entry(rangefinder.BeamSnow, _R, _R),
    "rangefinder.spray": _Entry(rangefinder.BeamSpray, _R, _R),
    # state
    "state.noise": _Entry(state.StateNoise, _S, _S),
    "state.bias": _Entry(state.StateBias, _S, _S),
    "state.dropout": _Entry(state.StateDropout, _S, _S),
    "state.latency": _Entry(temporal.Latency, _S, _S),
    # camera
    "camera.fog": _cam(camera.Fog),
    "camera.rain": _cam(camera.Rain),
    "camera.snow": _cam(camera.Snow),
    "camera.droplets": _cam(camera.Droplets),
    "camera.mud": _cam(camera.Mud),
    "camera.glare": _cam(camera.Glare),
    "camera.darkness": _cam(camera.Darkness),
    "camera.motion_blur": _cam(camera.MotionBlur),
    "camera.noise": _cam(camera.ImageNoise),
    "camera.occlusion": _cam(camera.Occlusion),
    "camera.frame_drop": _Entry(temporal.FrameDrop, ("pixels",), ("pixels", "depth")),
    "camera.latency": _Entry(temporal.Latency, ("pixels",), ("pixels", "depth")),
    # opponents (TORCS SCR's 36-sector sensor; the rangefinder's transforms on the sectors that see a car)
    "opponents.noise": _Entry(rangefinder.OpponentNoise, _O, _O),
    "opponents.dropout": _Entry(rangefinder.OpponentDropout, _O, _O),
    "opponents.latency": _Entry(temporal.Latency, _O, _O),
}

#: Kept out of training-time randomisation (as ImageNet-C holds out 4 corruptions): one
#: unseen effect per family: camera light (glare), camera lens (droplets), rangefinder
#: weather (snow), rangefinder fault (stuck beams).
HELDOUT: tuple[str, ...] = (
    "camera.glare",
    "camera.droplets",
    "rangefinder.snow",
    "rangefinder.stuck",
)


def sensor_of_key(key: str) -> str:
    """"rangefinder" | "state" | "camera" for a known observation key."""
    for sensor, keys in SENSOR_KEYS.items():
        if key in keys:
            return sensor
    raise ValueError(
        f"cannot tell which sensor the key {key!r} belongs to (known keys: "
        f"{[k for ks in SENSOR_KEYS.values() for k in ks]}); use a qualified name such as "
        "'camera.fog' with keys=[...]"
    )


def _known() -> str:
    names = sorted(_REGISTRY)
    return ", ".join(names) + "; presets: " + ", ".join(f"weather.{p}" for p in PRESETS)


def degradation_names(sensor: str | None = None, heldout: bool | None = None) -> list[str]:
    """Registered names, optionally only those for ``sensor`` ("rangefinder", "state",
    "camera", or an observation key "pixels" / "depth"), and only held-out ones
    (``heldout=True``) or only training ones (``heldout=False``)."""
    all_keys = [k for ks in SENSOR_KEYS.values() for k in ks]
    if sensor is not None and sensor not in SENSOR_KEYS and sensor not in all_keys:
        raise ValueError(
            f"unknown sensor {sensor!r}; use one of {list(SENSOR_KEYS)} or an observation key {all_keys}"
        )
    out = []
    for n, e in _REGISTRY.items():
        if sensor in SENSOR_KEYS and not n.startswith(sensor + "."):
            continue
        if sensor in all_keys and sensor not in e.keys:
            continue
        if heldout is True and n not in HELDOUT:
            continue
        if heldout is False and n in HELDOUT:
            continue
        out.append(n)
    return out


def applies_to(name: str) -> tuple[str, ...]:
    """Observation keys the degradation ``name`` can degrade, e.g. camera.fog → (pixels, depth)."""
    return _entry(name).keys


def degradation_class(name: str) -> type[Degradation]:
    return _entry(name).cls


def _entry(name: str) -> _Entry:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown degradation {name!r}; known: {_known()}") from None


def _resolve(name: str, keys: Sequence[str] | None) -> list[tuple[str, list[str] | None]]:
    """(qualified name, keys) pairs for a possibly bare ``name``."""
    if name in _REGISTRY:
        return [(name, None if keys is None else list(keys))]
    if "." in name:
        raise ValueError(f"unknown degradation {name!r}; known: {_known()}")
    candidates = [n for n in _REGISTRY if n.split(".", 1)[1] == name]
    if not candidates:
        raise ValueError(f"unknown degradation {name!r}; known: {_known()}")
    if keys is None:
        if len(candidates) == 1:
            return [(candidates[0], None)]
        raise ValueError(
            f"{name!r} exists for several sensors ({', '.join(candidates)}): pass keys=[...] "
            "or a qualified name"
        )
    by_sensor: dict[str, list[str]] = {}
    for k in keys:
        by_sensor.setdefault(sensor_of_key(k), []).append(k)
    out = []
    for sensor, ks in by_sensor.items():
        q = f"{sensor}.{name}"
        if q not in _REGISTRY:
            raise ValueError(
                f"{name!r} does not apply to {ks} ({sensor}); it exists as {', '.join(candidates)}"
            )
        bad = [k for k in ks if k not in _REGISTRY[q].keys]
        if bad:
            raise ValueError(f"{q} cannot degrade {bad}; it applies to {list(_REGISTRY[q].keys)}")
        out.append((q, ks))
    return out


def make_degradation(
    name: str,
    severity: int | tuple[int, int] = 3,
    keys: Sequence[str] | None = None,
    *,
    out_keys: Sequence[str] | None = None,
    seed: int | None = None,
    optional: bool = False,
    **params: Any,
) -> Transform:
    """The transform registered as ``name`` at ``severity``.

    ``name`` is qualified ("camera.fog"), bare with ``keys`` ("fog", keys=["rangefinder"]:
    several sensors give a Compose, one per sensor), or a preset ("weather.rain").
    ``params`` override ladder parameters or options by name.

    >>> make_degradation("fog", severity=3, keys=["rangefinder"])
    BeamFog(severity=3, keys=['rangefinder'])
    """
    if name.startswith("weather."):
        if params or out_keys is not None:
            raise ValueError("weather presets take no parameter overrides or out_keys")
        return make_preset(name.split(".", 1)[1], severity, seed=seed)
    parts = _resolve(name, keys)
    ts = []
    for i, (q, ks) in enumerate(parts):
        e = _REGISTRY[q]
        in_keys = list(e.in_keys) if ks is None else ks
        s = None if seed is None else (seed if len(parts) == 1 else derive_seed(seed, i))
        t = e.cls(
            severity,
            in_keys=in_keys,
            out_keys=out_keys if len(parts) == 1 else None,
            seed=s,
            optional=optional,
            **params,
        )
        t.label = q
        ts.append(t)
    return ts[0] if len(ts) == 1 else Compose(*ts)


# ------------------------------------------------------------------------ presets
#: weather presets: name → list of (degradation, severity offset, extra kwargs). A component
#: at offset -k runs at s - k and is left out below 1 (rain s2 has no darkness). Components
#: for sensors the env lacks are skipped.
PRESETS: dict[str, list[tuple[str, int, dict]]] = {
    # "rain s4" = camera rain s4 + darkness s2 + rangefinder rain s4
    "rain": [
        ("camera.rain", 0, {}),
        ("camera.darkness", -2, {}),
        ("rangefinder.rain", 0, {}),
    ],
    "fog": [
        ("camera.fog", 0, {"in_keys": ["pixels", "depth"]}),
        ("rangefinder.fog", 0, {}),
    ],
    "snow": [
        ("camera.snow", 0, {}),
        ("camera.fog", -2, {"in_keys": ["pixels", "depth"], "airlight": 0.85}),
        ("rangefinder.snow", 0, {}),
    ],
    "night": [
        ("camera.darkness", 0, {}),
        ("camera.motion_blur", -2, {"direction": 0.0}),  # longer exposure, yaw smear
    ],
    "dust": [
        ("camera.fog", 0, {"in_keys": ["pixels", "depth"], "airlight": (0.72, 0.62, 0.48)}),
        ("camera.mud", -1, {}),
        ("rangefinder.spray", 0, {}),
        ("rangefinder.outliers", 0, {}),
    ],
}


def preset_names(heldout: bool | None = None) -> list[str]:
    """Preset names; a preset is held out when one of its components is."""
    out = []
    for p, comps in PRESETS.items():
        h = any(c in HELDOUT for c, _, _ in comps)
        if heldout is None or heldout == h:
            out.append(p)
    return out


def make_preset(
    name: str,
    severity: int = 3,
    *,
    seed: int | None = None,
    keep_clean: bool = False,
) -> Compose:
    """The weather preset ``name`` ("rain", "fog", "snow", "night", "dust", or "weather.rain")
    at ``severity`` 1..5: a Compose of degradations, each skipping sensors the env lacks.
    ``keep_clean`` first copies every sensor key to ``<key>_clean``."""
    if name.startswith("weather."):
        name = name.split(".", 1)[1]
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
    if isinstance(severity, bool) or not isinstance(severity, int) or not 1 <= severity <= 5:
        raise ValueError(f"preset severity must be an int in 1..5, got {severity!r}")
    ts: list[Transform] = []
    if keep_clean:
        ts.append(KeepClean([k for ks in SENSOR_KEYS.values() for k in ks], optional=True))
    for i, (q, off, kw) in enumerate(PRESETS[name]):
        if severity + off < 1:
            continue
        kw = dict(kw)
        e = _REGISTRY[q]
        in_keys = kw.pop("in_keys", list(e.in_keys))
        s = None if seed is None else derive_seed(seed, name, i)
        t = e.cls(severity + off, in_keys=in_keys, seed=s, optional=True, **kw)
        t.label = q
        ts.append(t)
    return Compose(*ts)


# ------------------------------------------------------------------------ stacks
def make_stack(
    spec: Mapping[str, Any] | Sequence[Any],
    *,
    seed: int | None = None,
    keep_clean: Sequence[str] = (),
) -> Compose:
    """A Compose from config.

    ``spec`` is a mapping of named entries (Hydra-friendly: an override can add or drop one by
    name; an entry set to null is dropped) or a list. Each entry is a name string or a dict
    ``{name: ..., severity: ..., keys: [...], <param>: ...}`` (``name`` defaults to the entry's
    key in a mapping). ``keep_clean`` keys are copied to ``<key>_clean`` first.

    >>> make_stack({"fog": {"name": "camera.fog", "severity": 3}, "drop": "rangefinder.dropout"})
    """
    if isinstance(spec, Mapping):
        items = [(k, v) for k, v in spec.items() if v is not None]
    else:
        items = [(None, v) for v in spec]
    ts: list[Transform] = []
    if keep_clean:
        ts.append(KeepClean(list(keep_clean)))
    for i, (label, v) in enumerate(items):
        if isinstance(v, str):
            v = {"name": v}
        v = dict(v)
        if v.pop("enabled", True) is False:
            continue
        name = v.pop("name", label)
        if name is None:
            raise ValueError(f"stack entry {i} has no name: {v}")
        sev = v.pop("severity", 3)
        if isinstance(sev, list):
            sev = tuple(sev)
        keys = v.pop("keys", None)
        s = None if seed is None else derive_seed(seed, "stack", i)
        ts.append(make_degradation(name, sev, keys, seed=s, **v))
    return Compose(*ts)
