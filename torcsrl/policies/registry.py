"""Policy specs: :func:`load_policy` turns a *spec* (a string) into a :class:`~torcsrl.policies.base.Policy`.

============================  =================================================================
spec                          policy
============================  =================================================================
``path/to/ckpt.pt``           the deterministic actor of a torcsrl checkpoint: a training
                              checkpoint (``torcsrl.train``) or a policy file written by
                              :func:`export_policy` (actor weights + config only)
``reference``                 the shipped reference driver, :data:`REFERENCE_POLICY`
``reference-td3``             the shipped RL (TD3) driver, :data:`REFERENCE_RL_POLICY`
``reference_racer``           the shipped racing driver (rangefinder + state + opponents, asphalt and
                              dirt; a medoid ensemble of four students behind a side guard),
                              :data:`REFERENCE_RACER_POLICY`
``reference_camera``          the shipped camera-only driver (hood camera + telemetry),
                              :data:`REFERENCE_CAMERA_POLICY` (also ``reference-camera``)
``expert``                    the scripted expert (:mod:`torcsrl.envs.expert`: pure pursuit on
                              a racing line + speed profile) driven from the ``state``
                              observation and ``info/distFromStart`` (an observation adapter:
                              degrading ``state`` degrades it; the rangefinder it ignores)
``expert_centre``             the same expert on the track's centre line (its speed profile too)
``sensor_fast``               :class:`SensorDriver` with ``SensorDriver.FAST`` (grip-aware, ~1.08x the
                              expert's lap on training tracks)
``sensor_fast_sight[:<m>]``   the fast camera teacher: ``SensorDriver.CAMERA_FAST`` planning on at most
                              80 m (or ``<m>``) of free road (~1.19x the expert on training tracks)
``racer``                     :class:`SensorRacer`: ``sensor_fast`` that passes (or lifts for) the
                              cars its ``opponents`` sensor shows: the race student's teacher
``racer_bold``                the same with ``SensorRacer.BOLD`` (passes more, collides more)
``racer_safe[:<gamma>[:<d>[:<f>[:<m>]]]]`` ``racer_bold`` braking at ``9 mu^gamma`` m/s^2 (gamma 2): as
                              bold on asphalt, a margin on low grip; ``<d>`` in place of 9: a margin on asphalt
                              too; ``<f>``: the rate while a car is within 60 m (or ``<m>``): pushes in a fight
``racer_clean[:<gamma>...]``  ``racer_safe`` with a 1.5-lane following corridor near bends (fewer contacts)
``racer_keep[:<gamma>...]``   ``racer_safe`` that finishes a pass on the side it is on (holds its lane when
                              that side is taken, never crosses the passed car's path)
``racer_yield[:<gamma>...]``  ``racer_safe`` that completes a pass before the braking zone of the bend
                              ahead or gives it up (holds its lane, brakes to drop behind)
``heuristic``                 a sensor-only driver in the style of the TORCS SCR sample robot:
                              steers from ``angle`` / ``trackPos`` and the longest rangefinder
                              beam, picks its speed from the free distance ahead
``sensor``                    :class:`SensorDriver`: a stateless rangefinder + state driver (target
                              speed from the free distance ahead, traction control) whose choices the
                              observation explains: the imitation teacher of ``demos.teacher=sensor``
``sensor_grip``               the same driver told the friction under the car (``info/surfaceMu``):
                              the privileged teacher of the camera driver (``demos.teacher=sensor_grip``)
``random``                    uniform random actions in [-1, 1], seeded per episode (R_random)
``a.pt+b.pt[+...][@reduce]``  :class:`EnsemblePolicy`: the checkpoints drive as one, their actions
                              combined by ``mean`` (default), ``median``, ``cautious`` (mean
                              steering, the most cautious pedal), ``medoid`` (per row one
                              member's whole action, nearest the median) or ``guarded[:<m>]``
                              (the medoid, with the most cautious pedal while a car is within
                              m metres ahead); an ensemble file written by
                              :func:`export_ensemble` loads the same way
``side_guard[:<c>[:<g>[:<e>]]]:<spec>``  :class:`SideGuard`: a racer (any spec that reads opponents
                              and state) whose steering keeps ``c`` m (2.6) of lateral room from a
                              car beside it: steering toward it halved, ``g`` (0.04) per metre short
                              steered away, never beyond trackPos ``e`` (0.75); nothing else changed
============================  =================================================================

**Named values.** The parametrised drivers also take their values by name, ``name(key=value,...)``, in any order and
any subset (the rest default): ``racer_safe(gamma=1.27,decel=8,fight_decel=9)`` is ``racer_safe:1.27:8:9``,
``racer_yield(gamma=1.27,decel=8,fight_decel=9,abandon_m=20)`` is ``racer_yield:1.27:8:9:60:0:20``,
``sensor_fast_sight(sight_m=70)`` is ``sensor_fast_sight:70``, ``side_guard(clear_m=3,gain_per_m=0.05):racer_safe``
is ``side_guard:3:0.05:racer_safe``. ``racer(...)`` and ``racer_bold(...)`` take the racer keys on their own gains
(:data:`NAMED_VALUES` lists each name's keys). An unknown key or a bad value fails in one line
(:class:`~torcsrl.policies.base.PolicyError`) naming the key and listing the allowed ones; the colon forms load as
they always have (checkpoints and result files record them).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from torcsrl.policies.base import Policy, PolicyError
from torcsrl.policies.files import ensemble_of_files, load_policy_file
from torcsrl.policies.guard import SideGuard
from torcsrl.policies.scripted import ExpertPolicy, HeuristicPolicy, RandomPolicy
from torcsrl.policies.teachers import SensorDriver, SensorRacer

__all__ = ["BUILTIN_POLICIES", "REFERENCE_POLICY", "REFERENCE_RL_POLICY", "REFERENCE_CAMERA_POLICY", "REFERENCE_RACER_POLICY",
           "REFERENCE_PPO_POLICY", "RACER_VALUES_FORM", "RACER_SPECS", "RACER_VALUES", "GUARD_VALUES", "SIGHT_VALUES", "NAMED_VALUES", "load_policy",
           "is_ensemble_spec", "racer_gains", "sight_teacher", "split_named_spec"]

_ASSETS = Path(__file__).resolve().parent.parent / "assets"
#: Where the shipped reference driver lives (a policy file written by :func:`export_policy`): the best driver made by
#: the generalisation recipe (``reference_dagger.md`` beside it: command, selection on training tracks, figures).
REFERENCE_POLICY = _ASSETS / "reference_dagger.pt"
#: The shipped RL (TD3) driver, ``reference-td3`` (``reference_td3.md``).
REFERENCE_RL_POLICY = _ASSETS / "reference_td3.pt"
#: The shipped PPO driver, ``reference_rl`` (``reference_rl.md``): PPO past a grip-estimating DAgger student, one network
#: on rangefinder + a 3 s state history.
REFERENCE_PPO_POLICY = _ASSETS / "reference_rl.pt"
#: The shipped camera-only driver, ``reference_camera`` (``reference_camera.md``: command, selection, figures).
REFERENCE_CAMERA_POLICY = _ASSETS / "reference_camera.pt"
#: The shipped racing driver, ``reference_racer`` (``reference_racer.md``: command, selection, figures).
REFERENCE_RACER_POLICY = _ASSETS / "reference_racer.pt"
#: The values a parametrised racer teacher takes (:data:`RACER_VALUES`, all optional, in order).
RACER_VALUES_FORM = "[:<gamma>[:<decel>[:<fight decel>[:<fight m>[:<clear m>[:<abandon m>]]]]]]"
#: The parametrised racer teachers (:func:`racer_gains`) as listed in :data:`BUILTIN_POLICIES` and ``demos.TEACHERS``.
RACER_SPECS = tuple(f"{base}{RACER_VALUES_FORM}" for base in ("racer_safe", "racer_clean", "racer_keep", "racer_yield"))
#: Names of the built-in policies (anything else is a checkpoint path).
BUILTIN_POLICIES = ("expert", "expert_centre", "heuristic", "sensor", "sensor_grip", "sensor_fast", "sensor_sight[:<metres>]",
                    "sensor_fast_sight[:<metres>]", "racer", "racer_bold", *RACER_SPECS, "random", "reference", "reference-td3", "reference_rl",
                    "reference_camera", "reference_racer", "side_guard[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy>")


#: The values of ``racer_safe:<gamma>:<decel>:<fight decel>:<fight m>:<clear m>:<abandon m>``, in order, each as
#: ``key: (SensorRacer keyword, what it is, the test it must pass, the allowed range as the error says it)``; ``key``
#: is its name in ``racer_safe(key=value,...)``.
RACER_VALUES: dict[str, tuple[str, str, Callable[[float], bool], str]] = {
    "gamma": ("grip_exponent", "the grip exponent", lambda v: v >= 1.0, ">= 1 (1: braking in proportion to the grip)"),
    "decel": ("decel_per_mu", "the braking rate", lambda v: 0.0 < v <= 12.0, "in (0, 12] m/s^2 at mu 1 (the default: 9)"),
    "fight_decel": ("fight_decel_per_mu", "the braking rate in a fight", lambda v: 0.0 < v <= 12.0, "in (0, 12] m/s^2 at mu 1"),
    "fight_m": ("fight_m", "the fight distance", lambda v: 0.0 < v <= 200.0, "in (0, 200] m (the opponents sensor's range)"),
    "clear_m": ("clear_m", "the room kept past a car passed", lambda v: 0.0 <= v <= 30.0, "in [0, 30] m (the default: 0)"),
    "abandon_m": ("abandon_m", "the distance before the braking point with no pass left unfinished", lambda v: 0.0 <= v <= 200.0,
                  "in [0, 200] m (racer_yield's default: 30; none for the others)"),
}
#: The value of ``sensor_sight[:<m>]`` / ``sensor_fast_sight[:<m>]`` by name (``sensor_sight(sight_m=...)``).
SIGHT_VALUES: dict[str, tuple[str, str, Callable[[float], bool], str]] = {
    "sight_m": ("sight_m", "the sight distance", lambda v: v > 8.0, "> 8 m (the driver's d0; the default: 80)"),
}
#: The :class:`SideGuard` settings by name (``side_guard(clear_m=...,...):<policy spec>``; all of
#: :attr:`SideGuard.DEFAULTS`, where the colon form takes the first, second and last).
GUARD_VALUES: dict[str, tuple[str, str, Callable[[float], bool], str]] = {
    "clear_m": ("clear_m", "the lateral room kept", lambda v: v >= 0.0, ">= 0 m (the default: 2.6)"),
    "gain_per_m": ("gain_per_m", "the steering per metre short of it", lambda v: v >= 0.0, ">= 0 per m (the default: 0.04)"),
    "reach_m": ("reach_m", "how far ahead or behind a car counts as beside", lambda v: v >= 0.0, ">= 0 m (the default: 5.5)"),
    "toward": ("toward", "the factor on steering toward it", lambda v: 0.0 <= v <= 1.0, "in [0, 1] (the default: 0.5)"),
    "edge_tp": ("edge_tp", "the trackPos beyond which it does not push further out", lambda v: 0.0 <= v <= 1.0,
                "in [0, 1] (the default: 0.75)"),
}
#: The racer teachers by spec name: their gains (``SensorRacer`` keywords) and whether they plan with the safe grip
#: exponent unless given one (:attr:`SensorRacer.SAFE_GRIP_EXPONENT`). The colon values are taken by the last four.
_RACERS: dict[str, tuple[dict[str, Any], bool]] = {
    "racer": ({}, False), "racer_bold": (SensorRacer.BOLD, False), "racer_safe": (SensorRacer.BOLD, True),
    "racer_clean": (SensorRacer.CLEAN, True), "racer_keep": (SensorRacer.KEEP, True), "racer_yield": (SensorRacer.YIELD, True),
}
_COLON_RACERS = ("racer_safe", "racer_clean", "racer_keep", "racer_yield")
#: The camera teachers by spec name: their gains (``SensorDriver`` keywords).
_SIGHT_TEACHERS: dict[str, dict[str, Any]] = {"sensor_sight": {"decel_per_mu": SensorDriver.GRIP_DECEL_PER_MU},
                                              "sensor_fast_sight": SensorDriver.CAMERA_FAST}
#: The names that take values by name (``name(key=value,...)``) and their keys.
NAMED_VALUES: dict[str, tuple[str, ...]] = {**{n: tuple(RACER_VALUES) for n in _RACERS}, **{n: tuple(SIGHT_VALUES) for n in _SIGHT_TEACHERS},
                                            SideGuard.PREFIX: tuple(GUARD_VALUES)}

_NAMED = re.compile(r"(?P<name>[A-Za-z_][A-Za-z0-9_-]*)\((?P<args>[^()]*)\)")



def spec_number(text: str, ok, not_a_number: str, out_of_range) -> float:
    """``text`` as a finite float that ``ok`` accepts; else one :class:`PolicyError` line (``not_a_number``, or
    ``out_of_range(value)``). The named and the colon spellings of a driver's values read numbers through it."""
    try:
        v = float(text)
    except ValueError:
        raise PolicyError(not_a_number) from None
    if not math.isfinite(v) or not ok(v):
        raise PolicyError(out_of_range(v))
    return v

def split_named_spec(spec: str) -> tuple[str, dict[str, str], str] | None:
    """``name(key=value,...)[:<rest>]`` -> ``(name, {key: value text}, rest)`` (``rest`` empty when there is none);
    None for a spec of another form (a colon spec, a file). :class:`PolicyError` (one line) for a malformed list of
    values or a name that takes none."""
    m = _NAMED.match(spec)
    if m is None:
        return None
    name, rest = m["name"], spec[m.end():]
    if rest and not rest.startswith(":"):
        return None
    allowed = NAMED_VALUES.get(name)
    if allowed is None:
        raise PolicyError(f"policy {spec!r}: {name} takes no named values; named values are taken by {', '.join(NAMED_VALUES)}")
    values: dict[str, str] = {}
    for item in filter(None, (x.strip() for x in m["args"].split(","))):
        key, sep, text = (x.strip() for x in item.partition("="))
        if not sep or not key or not text:
            raise PolicyError(f"policy {spec!r}: {item!r} is not key=value; allowed keys: {', '.join(allowed)}")
        if key in values:
            raise PolicyError(f"policy {spec!r}: {key} is given twice; allowed keys: {', '.join(allowed)}")
        values[key] = text
    return name, values, rest[1:]


def _named_values(spec: str, values: Mapping[str, str], table: Mapping[str, tuple[str, str, Callable[[float], bool], str]]) -> dict[str, float]:
    """``{keyword: value}`` from named value texts, each checked by ``table``; :class:`PolicyError` (one line) naming
    the key and listing the allowed keys for an unknown key or a bad value."""
    keys = ", ".join(table)
    out: dict[str, float] = {}
    for key, text in values.items():
        if key not in table:
            raise PolicyError(f"policy {spec!r}: unknown key {key!r}; allowed keys: {keys}")
        kw, what, ok, allowed = table[key]
        out[kw] = spec_number(text, ok, f"policy {spec!r}: {key} ({what}) must be a number {allowed}, got {text!r}; allowed keys: {keys}",
                              lambda v: f"policy {spec!r}: {key} ({what}) must be {allowed}, got {v:g}; allowed keys: {keys}")
    return out


def racer_gains(name: str) -> dict[str, Any] | None:
    """The :class:`SensorRacer` gains of ``racer_safe`` + :data:`RACER_VALUES_FORM` (and ``racer_clean[...]``,
    ``racer_keep[...]``, ``racer_yield[...]``): ``SensorRacer.BOLD`` / ``CLEAN`` / ``KEEP`` / ``YIELD`` with
    ``grip_exponent`` gamma (default 2), where given ``decel_per_mu`` [m/s^2 at mu 1; the default is
    ``SensorDriver.FAST``'s 9], ``fight_decel_per_mu`` (the rate while a car is within ``fight_m``) and ``fight_m``
    [m, default 60] (:data:`RACER_VALUES`); the same by name, ``racer_safe(gamma=1.27,decel=8)``, and for ``racer(...)``
    / ``racer_bold(...)`` on their own gains. None for other names (``racer`` and ``racer_bold`` bare too);
    :class:`PolicyError` (one line) for a bad value."""
    named = split_named_spec(name)
    if named is not None:
        base, values, rest = named
        if base not in _RACERS or rest:
            return None
        gains, safe = _RACERS[base]
        out = {**gains, "grip_exponent": SensorRacer.SAFE_GRIP_EXPONENT} if safe else dict(gains)
        return {**out, **_named_values(name, values, RACER_VALUES)}
    for base in _COLON_RACERS:
        if name == base or name.startswith(base + ":"):
            form = f"{base}{RACER_VALUES_FORM}, e.g. {base}:2 or {base}:1.27:8:9"
            parts = name.split(":")[1:]
            if len(parts) > len(RACER_VALUES):
                raise PolicyError(f"{name!r}: at most six values after '{base}': {form}")
            out = {**_RACERS[base][0], "grip_exponent": SensorRacer.SAFE_GRIP_EXPONENT}
            for text, (key, what, ok, allowed) in zip(parts, RACER_VALUES.values()):
                out[key] = spec_number(text, ok, f"{name!r}: {what} must be a number {allowed}, got {text!r}: {form}",
                                       lambda v: f"{name!r}: {what} must be {allowed}, got {v:g}")
            return out
    return None


def _sight(name: str) -> float:
    """The sight distance [m] of ``sensor_sight`` / ``sensor_fast_sight`` (:data:`SensorDriver.CAMERA_SIGHT_M`) or
    ``<name>:<metres>``."""
    if ":" not in name:
        return SensorDriver.CAMERA_SIGHT_M
    base, tail = name.split(":", 1)
    try:
        return float(tail)
    except ValueError:
        raise PolicyError(f"{name!r}: the sight distance after '{base}:' must be a number of metres, e.g. {base}:70") from None


def sight_teacher(name: str, **keys: str) -> SensorDriver | None:
    """The camera teachers: ``sensor_sight[:<m>]`` (grip-aware, ``GRIP_DECEL_PER_MU``) and ``sensor_fast_sight[:<m>]``
    (``SensorDriver.CAMERA_FAST``), each planning on at most ``<m>`` (80) metres of free road, or by name
    (``sensor_sight(sight_m=<m>)``); ``keys``: where it reads its observations (``SensorDriver``'s
    ``rangefinder_key`` / ``state_key``). None for other names."""
    named = split_named_spec(name)
    if named is not None:
        base, values, rest = named
        if base not in _SIGHT_TEACHERS or rest:
            return None
        sight = _named_values(name, values, SIGHT_VALUES).get("sight_m", SensorDriver.CAMERA_SIGHT_M)
    else:
        base = next((b for b in _SIGHT_TEACHERS if name == b or name.startswith(b + ":")), None)
        if base is None:
            return None
        sight = _sight(name)
    drv = SensorDriver(**_SIGHT_TEACHERS[base], sight_m=sight, **keys)
    if base == "sensor_fast_sight":
        drv.spec = drv.name = name
    return drv


def _side_guard(spec: str) -> SideGuard:
    """``side_guard[:<c>[:<g>[:<e>]]]:<policy spec>`` or ``side_guard(key=value,...):<policy spec>``."""
    named = split_named_spec(spec)
    if named is None:
        settings, inner = SideGuard.split_spec(spec)
    else:
        settings, inner = _named_values(spec, named[1], GUARD_VALUES), named[2]
        if not inner:
            raise PolicyError(f"side guard spec {spec!r} names no policy; allowed: {SideGuard.PREFIX}(key=value,...):<policy spec>, "
                              f"keys: {', '.join(GUARD_VALUES)}, e.g. {SideGuard.PREFIX}(clear_m=3):racer_safe:1.27:8:9")
    return SideGuard.from_settings(load_policy(inner), settings, spec=spec)


def is_ensemble_spec(spec: str | Path) -> bool:
    """Whether ``spec`` names an ensemble of checkpoints (``a.pt+b.pt[+...][@reduce]``; a file whose name has a ``+``
    is still a file)."""
    return "+" in str(spec) and not Path(str(spec)).exists()


def _policy_file(s: str | Path, name: str | None = None) -> Policy:
    """:func:`load_policy_file`, a path that does not exist named as a spec that is neither a file nor a built-in."""
    if not Path(s).exists():
        raise PolicyError(f"policy {str(s)!r} is neither a checkpoint file that exists nor one of {', '.join(BUILTIN_POLICIES)}")
    return load_policy_file(s, name=name)


def load_policy(spec: str | Path | Policy) -> Policy:
    """The :class:`~torcsrl.policies.base.Policy` for ``spec`` (see the module docstring);
    :class:`~torcsrl.policies.base.PolicyError` (one line) for a missing, corrupt or unusable checkpoint or a bad value."""
    if isinstance(spec, Policy):
        return spec
    s = str(spec)
    if (s.startswith(SideGuard.PREFIX + ":") or s.startswith(SideGuard.PREFIX + "(")) and not Path(s).exists():
        return _side_guard(s)
    if s == "expert":
        return ExpertPolicy()
    if s == "expert_centre":
        return ExpertPolicy(line="centre")
    if s == "racer":
        return SensorRacer()
    if s == "racer_bold":
        drv = SensorRacer(**SensorRacer.BOLD)
        drv.spec = drv.name = "racer_bold"
        return drv
    named = split_named_spec(s) if not Path(s).exists() else None
    kw = racer_gains(s)
    if kw is not None:
        drv = SensorRacer(**kw)
        drv.spec = drv.name = s
        return drv
    if s == "heuristic":
        return HeuristicPolicy()
    if s == "sensor":
        return SensorDriver()
    if s == "sensor_grip":
        return SensorDriver(decel_per_mu=SensorDriver.GRIP_DECEL_PER_MU)
    sight = sight_teacher(s)
    if sight is not None:
        return sight
    if named is not None:  # a name that takes values, with a rest it does not take
        raise PolicyError(f"policy {s!r}: only side_guard(...) is followed by ':<policy spec>'; {named[0]}(...) ends the spec")
    if s == "sensor_fast":
        drv = SensorDriver(**SensorDriver.FAST)
        drv.spec = drv.name = "sensor_fast"
        return drv
    if s == "random":
        return RandomPolicy()
    if s == "reference":
        if not REFERENCE_POLICY.is_file():
            raise PolicyError(f"the reference driver {REFERENCE_POLICY} is not shipped yet; pass a checkpoint path, 'expert' or 'heuristic'")
        return _policy_file(REFERENCE_POLICY, name="reference")
    if s == "reference-td3":
        return _policy_file(REFERENCE_RL_POLICY, name="reference-td3")
    if s in ("reference_rl", "reference-rl"):
        return _policy_file(REFERENCE_PPO_POLICY, name="reference_rl")
    if s in ("reference_racer", "reference-racer"):
        if not REFERENCE_RACER_POLICY.is_file():
            raise PolicyError(f"the racing driver {REFERENCE_RACER_POLICY} is not shipped yet; pass a checkpoint path")
        return _policy_file(REFERENCE_RACER_POLICY, name="reference_racer")
    if s in ("reference_camera", "reference-camera"):
        if not REFERENCE_CAMERA_POLICY.is_file():
            raise PolicyError(f"the camera driver {REFERENCE_CAMERA_POLICY} is not shipped yet; pass a checkpoint path")
        return _policy_file(REFERENCE_CAMERA_POLICY, name="reference_camera")
    if is_ensemble_spec(s):
        files, _, reduce = s.partition("@")
        for f in files.split("+"):
            if not Path(f).exists():
                _policy_file(f)  # raises: neither a file nor a built-in
        return ensemble_of_files(files.split("+"), reduce or "mean")
    return _policy_file(s)
