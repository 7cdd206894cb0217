"""Curricula: ordered training stages, each a set of config overrides, promoted by validation results.

A curriculum (``conf/curriculum/*.yaml``, ``cfg.curriculum.stages``) is an ordered mapping of named stages::

    curriculum:
      stages:
        solo:                                   # a name (an override can retune or drop a stage by it)
          overrides:                            # dotted config keys -> values
            env.procedural.difficulty: [0.0, 0.3]
          promote: {metric: clean, at_least: 0.8, over: 3}      # mean of the last 3 validations >= 0.8
        race:
          overrides: {env.traffic: {opponents: 3, driver: {kind: expert, pace: 0.85}}}
          promote: null                         # the final stage may have none (a final one is never used)

**Stages are cumulative**: stage k trains on the base config with the overrides of stages 0 .. k applied in order, so
a stage states only what changes. An override may set

* ``env.<key>`` and ``eval.env.<key>`` for any ``make_env`` keyword except those that fix what the networks see, the
  number of streams or the control problem (:data:`FIXED_ENV_KEYS`: sensors, camera, num_cars, normalize,
  action_mode, control rate, car, beams); a deeper key (``env.traffic.driver.pace``) changes one value inside;
* ``degradation.severity`` and ``degradation.stack[.<entry>[.<field>]]``.

Each stage's config is checked like the base config (:func:`check`, gathered by :func:`torcsrl.training.problems`) before
training starts.

**Promotion** (``promote``): after every validation the stage's criterion reads one number from the validation's
metrics (:data:`METRICS`), keeps it for the stage, and promotes when ``over`` (k) of them are in and

* ``rule: mean`` (default): their mean over the last k is ``>= at_least`` (or ``<= at_most``);
* ``rule: every``: each of the last k is (k validations in a row);

and the stage has trained ``min_frames`` frames at least. Validations of an earlier stage never count for a later one.

**Rehearsal** (``rehearse: {stage: <name>, frames: N[, overrides: {...}]}``, ``algo=dagger`` only): once training has
left the named stage, every DAgger round also drives N frames in that stage's env (its config, :meth:`Curriculum.config`
at that stage, then the rehearsal's own ``overrides``, the keys a stage may set: :meth:`Curriculum.rehearsal_config`),
labelled by the teacher like the round's own — so a student that moves on to traffic keeps being corrected where it
drives alone (rehearsal against forgetting an earlier task; the round's own frames are unchanged), and with overrides
where it drives alone on roads the stage's env did not hold (``env.procedural.generator: proc``: circuits with
hairpins).

**The loop's interface** (:mod:`torcsrl.training.offpolicy`, :mod:`torcsrl.training.imitation`): ``Curriculum.from_config(cfg)``; ``config(cfg)`` the stage's config
(with no stages: ``cfg`` itself); ``observe(eval_metrics, frames, episodes)`` after each validation, returning the
promotion event (or None) after which the loop rebuilds the training env, its collector and the validation envs;
``state_dict()`` / ``load_state_dict()`` in the checkpoint (stage, its validations, the promotion history), so an
exact resume resumes the stage.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from torcsrl.agents import IMITATION, ON_POLICY
from torcsrl.pipeline import env_signature

__all__ = ["Curriculum", "CurriculumError", "Criterion", "Stage", "Rehearsal", "METRICS", "RULES", "FIXED_ENV_KEYS", "check",
           "stageable_env_keys"]

#: What a criterion may read from a validation (``torcsrl.training.common.validate_all``):
METRICS = {
    "clean": "the share of the validation's tracks (eval.per_track; else its one env: 0 or 1) driven clean: laps >= "
             "eval.lap_limit (1 if null) and no collision with another car. Over k validations with rule mean: the clean-lap rate",
    "eval/laps": "laps completed per validation episode (mean over the tracks with eval.per_track)",
    "eval/laps_min": "laps of the worst validation track (eval.per_track; else eval/laps)",
    "eval/reward": "return of a validation episode",
    "eval/lap_time": "fastest validation lap [s] (NaN, never met, without a timed lap); use at_most",
    "eval/lap_time_mean": "mean validation lap time [s]; use at_most",
    "eval/collisions": "contacts with other cars per validation episode (0 without traffic); use at_most",
}
RULES = ("mean", "every")
#: env keys a stage may not change: what the networks see and how many streams the buffer holds (sensors, camera,
#: num_cars, normalize), the action and the control problem the checkpoint's policy is rebuilt with
#: (torcsrl.policies.DYNAMICS_KEYS), and what train sets itself.
FIXED_ENV_KEYS = ("name", "sensors", "camera", "num_cars", "normalize", "action_mode", "control_hz", "substeps", "vehicle",
                  "vehicle_overrides", "rangefinder_angles_deg", "rangefinder_range_m", "seed", "device")
_CRITERION_KEYS = ("metric", "at_least", "at_most", "over", "rule", "min_frames")
_STAGE_KEYS = ("overrides", "promote")
_CURRICULUM_KEYS = ("stages", "rehearse")
_REHEARSE_KEYS = ("stage", "frames", "overrides")


class CurriculumError(ValueError):
    """A curriculum that cannot run, or a checkpoint written under another one (one line, naming what is allowed)."""


@dataclass(frozen=True)
class Criterion:
    """When a stage is done: ``rule`` over the last ``over`` validations' ``metric`` against ``at_least`` / ``at_most``."""

    metric: str
    at_least: float | None = None
    at_most: float | None = None
    over: int = 1
    rule: str = "mean"
    min_frames: int = 0

    @classmethod
    def parse(cls, d: Any, where: str) -> Criterion:
        if not isinstance(d, Mapping):
            raise CurriculumError(f"{where}: expected a mapping {{metric, at_least | at_most, over, rule, min_frames}} or null, got {d!r}")
        unknown = [k for k in d if k not in _CRITERION_KEYS]
        if unknown:
            raise CurriculumError(f"{where}: unknown key {unknown[0]!r}; allowed: {', '.join(_CRITERION_KEYS)}")
        metric = d.get("metric")
        if metric not in METRICS:
            raise CurriculumError(f"{where}.metric: unknown metric {metric!r}; allowed: {', '.join(METRICS)}")
        lo, hi = d.get("at_least"), d.get("at_most")
        if (lo is None) == (hi is None):
            raise CurriculumError(f"{where}: give exactly one threshold, at_least or at_most (a number)")
        for k, v in (("at_least", lo), ("at_most", hi)):
            if v is not None and not _is_num(v):
                raise CurriculumError(f"{where}.{k}: expected a number, got {v!r}")
        over, min_frames = d.get("over", 1), d.get("min_frames", 0)
        if not (isinstance(over, int) and not isinstance(over, bool) and over >= 1):
            raise CurriculumError(f"{where}.over: expected a positive integer (validations), got {over!r}")
        if not (isinstance(min_frames, int) and not isinstance(min_frames, bool) and min_frames >= 0):
            raise CurriculumError(f"{where}.min_frames: expected an integer >= 0 (frames), got {min_frames!r}")
        rule = d.get("rule", "mean")
        if rule not in RULES:
            raise CurriculumError(f"{where}.rule: unknown rule {rule!r}; allowed: {', '.join(RULES)}")
        return cls(str(metric), None if lo is None else float(lo), None if hi is None else float(hi), int(over), str(rule),
                   int(min_frames))

    def value(self, metrics: Mapping[str, float], lap_target: int) -> float:
        """This criterion's number from one validation's metrics."""
        laps = metrics.get("eval/laps_min", metrics.get("eval/laps", math.nan))
        if self.metric == "clean":
            tracks = [k[5:-5] for k in metrics if k.startswith("eval/") and k.endswith("/laps") and k.count("/") == 2]
            if not tracks:  # one validation env: eval/laps (the mean over eval.episodes) reaches the target only if all did
                tracks = [""]
            pre = [f"eval/{t}/" if t else "eval/" for t in tracks]
            return sum(metrics[p + "laps"] >= lap_target and metrics.get(p + "collisions", 0.0) == 0 for p in pre) / len(pre)
        if self.metric == "eval/laps_min":
            return float(laps)
        if self.metric == "eval/collisions":
            return float(metrics.get("eval/collisions", 0.0))
        return float(metrics.get(self.metric, math.nan))

    def _ok(self, x: float) -> bool:
        return x >= self.at_least if self.at_least is not None else x <= self.at_most  # NaN: False

    def met(self, values: list[float], frames_in_stage: int) -> tuple[bool, float]:
        """(promote?, the number compared: the mean, or the worst, of the last ``over`` values)."""
        if len(values) < self.over or frames_in_stage < self.min_frames:
            return False, math.nan
        last = values[-self.over:]
        if self.rule == "mean":
            agg = sum(last) / len(last)
            return self._ok(agg), agg
        worst = min(last) if self.at_least is not None else max(last)
        return all(self._ok(x) for x in last), worst

    def describe(self) -> str:
        op, x = (">=", self.at_least) if self.at_least is not None else ("<=", self.at_most)
        what = f"mean of the last {self.over}" if self.rule == "mean" and self.over > 1 else (
            f"{self.over} validations in a row" if self.over > 1 else "one validation")
        return f"{self.metric} {op} {x:g} ({what}{f', after {self.min_frames} frames' if self.min_frames else ''})"


@dataclass(frozen=True)
class Stage:
    """One stage: its name, its overrides (dotted key -> plain value) and its promotion criterion (None: final)."""

    name: str
    overrides: dict[str, Any] = field(default_factory=dict)
    promote: Criterion | None = None


@dataclass(frozen=True)
class Rehearsal:
    """``curriculum.rehearse``: after leaving stage ``stage`` (its index), every DAgger round also drives ``frames``
    frames [env steps] in that stage's env, with ``overrides`` (dotted key -> plain value, the keys a stage may set)
    applied on top of it."""

    stage: int
    name: str
    frames: int
    overrides: dict[str, Any] = field(default_factory=dict)


class Curriculum:
    """The stages of ``cfg.curriculum`` and where training stands in them (see the module docstring)."""

    def __init__(self, stages: list[Stage], lap_target: int = 1, rehearse: Rehearsal | None = None):
        self.stages = list(stages)
        self.lap_target = int(lap_target)
        self.rehearse = rehearse
        self.stage = 0
        self.values: list[float] = []  # the criterion's numbers of this stage's validations
        self.entered_frames = 0  # frames collected when this stage began
        self.history: list[dict[str, Any]] = []  # promotion events

    # ---- building ---------------------------------------------------------------------------------------------
    @classmethod
    def from_config(cls, cfg: DictConfig | Mapping) -> Curriculum:
        """The curriculum of a training config (``curriculum.stages``; none or empty: no stages). :class:`CurriculumError`
        (one line) for a malformed stage, an unknown criterion metric, a non-final stage without a criterion, or an
        override of a key a stage may not change."""
        cur = cfg.get("curriculum") if cfg is not None else None
        raw = OmegaConf.to_container(cur, resolve=False) if isinstance(cur, DictConfig) else (dict(cur) if cur else {})
        unknown = [k for k in raw if k not in _CURRICULUM_KEYS]
        if unknown:
            raise CurriculumError(f"curriculum.{unknown[0]}: unknown key; allowed: {', '.join(_CURRICULUM_KEYS)} (conf/curriculum/none.yaml)")
        stages_raw = raw.get("stages") or {}
        if not isinstance(stages_raw, Mapping):
            raise CurriculumError(f"curriculum.stages: expected a mapping of named stages {{<name>: {{overrides, promote}}}}, got {stages_raw!r}")
        items = [(str(k), v) for k, v in stages_raw.items() if v is not None]  # a stage dropped by an override: name=null
        env = cfg.get("env") if cfg is not None else None
        env_name = env.get("name", "race") if env is not None else "race"
        stages = []
        for i, (name, s) in enumerate(items):
            where = f"curriculum.stages.{name}"
            if not isinstance(s, Mapping):
                raise CurriculumError(f"{where}: expected a mapping {{overrides, promote}}, got {s!r}")
            bad = [k for k in s if k not in _STAGE_KEYS]
            if bad:
                raise CurriculumError(f"{where}.{bad[0]}: unknown key; allowed: {', '.join(_STAGE_KEYS)}")
            ov = s.get("overrides") or {}
            if not isinstance(ov, Mapping):
                raise CurriculumError(f"{where}.overrides: expected a mapping {{<dotted key>: value}}, got {ov!r}")
            for key in ov:
                _check_key(str(key), f"{where}.overrides", env_name)
            final = i == len(items) - 1
            promote = s.get("promote")
            if promote is None and not final:
                raise CurriculumError(f"{where}: a stage before the last needs a promotion criterion, promote: {{metric, at_least | "
                                      f"at_most, over, rule}} (metrics: {', '.join(METRICS)}); only the final stage "
                                      f"({items[-1][0]}) may have promote: null")
            crit = Criterion.parse(promote, f"{where}.promote") if promote is not None else None
            stages.append(Stage(name, {str(k): _plain(v) for k, v in ov.items()}, crit))
        ev = cfg.get("eval") if cfg is not None else None
        lap_limit = ev.get("lap_limit") if ev is not None else None
        return cls(stages, int(lap_limit or 1), _rehearsal(raw.get("rehearse"), [s.name for s in stages], env_name))

    # ---- the stage's config ----------------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        return bool(self.stages)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.stages]

    @property
    def name(self) -> str:
        return self.stages[self.stage].name if self.stages else ""

    def config(self, cfg: DictConfig, stage: int | None = None) -> DictConfig:
        """``cfg`` with the overrides of stages 0 .. ``stage`` (default: the current one) applied in order; ``cfg``
        itself when there are no stages. ``ValueError`` when a deeper key's parent is not a mapping at that stage."""
        if not self.stages:
            return cfg
        k = self.stage if stage is None else int(stage)
        out = copy.deepcopy(cfg)
        with open_dict(out):
            for s in self.stages[:k + 1]:
                _apply(out, s.overrides, f"curriculum.stages.{s.name}.overrides")
        return out

    def rehearsal_config(self, cfg: DictConfig) -> DictConfig:
        """The config a rehearsal drives: the rehearsed stage's (:meth:`config`) with ``rehearse.overrides`` on top."""
        r = self.rehearse
        if r is None:
            raise CurriculumError("curriculum.rehearse is null: no rehearsal config; allowed: {stage: <name>, frames: N}")
        out = self.config(cfg, stage=r.stage)
        with open_dict(out):
            _apply(out, r.overrides, "curriculum.rehearse.overrides")
        return out

    def rehearsal(self) -> Rehearsal | None:
        """The rehearsal a DAgger round of the current stage drives (None: none configured, or not past its stage yet)."""
        r = self.rehearse
        return r if r is not None and self.stage > r.stage else None

    # ---- promotion -------------------------------------------------------------------------------------------
    def observe(self, metrics: Mapping[str, float], frames: int, episodes: int = 0) -> dict[str, Any] | None:
        """Book one validation of the current stage; promote when its criterion is met. Returns the promotion event
        (``{"stage", "from", "to", "frames", "episodes", "validations", "criterion", "value"}``) or None."""
        crit = self.stages[self.stage].promote if self.stages else None
        if crit is None or self.stage == len(self.stages) - 1:
            return None
        self.values.append(crit.value(metrics, self.lap_target))
        ok, agg = crit.met(self.values, int(frames) - self.entered_frames)
        if not ok:
            return None
        event = {"stage": self.stage + 1, "from": self.name, "to": self.stages[self.stage + 1].name, "frames": int(frames),
                 "episodes": int(episodes), "validations": len(self.values), "criterion": crit.describe(), "value": agg}
        self.history.append(event)
        self.stage += 1
        self.values = []
        self.entered_frames = int(frames)
        return event

    # ---- checkpoint ------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"names": self.names, "stage": self.stage, "values": list(self.values), "entered_frames": self.entered_frames,
                "history": copy.deepcopy(self.history)}

    def load_state_dict(self, state: Mapping[str, Any] | None, where: str = "the checkpoint") -> None:
        """Resume the stage of ``state`` (None: a checkpoint of a run without a curriculum). :class:`CurriculumError`
        unless the checkpoint's stages are this curriculum's (the same names, in order)."""
        names = list(state["names"]) if state else []
        if names != self.names:
            theirs = ", ".join(names) if names else "none"
            raise CurriculumError(f"{where} was written with curriculum stages [{theirs}], this config has "
                                  f"[{', '.join(self.names) or 'none'}]; allowed: the checkpoint's curriculum, or a fresh run_dir")
        if not state:
            return
        self.stage = int(state["stage"])
        self.values = [float(v) for v in state["values"]]
        self.entered_frames = int(state["entered_frames"])
        self.history = copy.deepcopy(list(state["history"]))

    def summary(self) -> dict[str, Any]:
        """What ``<run_dir>/curriculum.json`` holds: the stages, the current one and the promotions."""
        return {"stages": [{"name": s.name, "overrides": s.overrides, "promote": asdict(s.promote) if s.promote else None}
                           for s in self.stages],
                "rehearse": asdict(self.rehearse) if self.rehearse else None,
                "stage": self.stage, "name": self.name, "promotions": copy.deepcopy(self.history)}


# ---------------------------------------------------------------------------------------------------------------
# checks
# ---------------------------------------------------------------------------------------------------------------
def stageable_env_keys(env_name: str) -> list[str]:
    """The env keys a stage may override (``make_env``'s keywords less :data:`FIXED_ENV_KEYS`)."""
    return sorted(set(env_signature(env_name)) - set(FIXED_ENV_KEYS))


def _check_key(key: str, where: str, env_name: str) -> None:
    parts = key.split(".")
    env_keys = stageable_env_keys(env_name if env_name in ("race", "toy") else "race")
    allowed = (f"env.<{' | '.join(env_keys)}>[.<sub key>], eval.env.<the same>, degradation.severity, "
               "degradation.stack[.<entry>[.<field>]]")
    if parts[:1] == ["env"] and len(parts) >= 2:
        k = parts[1]
    elif parts[:2] == ["eval", "env"] and len(parts) >= 3:
        k = parts[2]
    elif parts[:1] == ["degradation"] and (parts[1:] == ["severity"] or parts[1:2] == ["stack"]):
        return
    else:
        raise CurriculumError(f"{where}: unknown key {key!r}; allowed: {allowed}")
    if k in FIXED_ENV_KEYS:
        raise CurriculumError(f"{where}: {key} cannot change between stages (it fixes what the networks see, the replay "
                              f"buffer's streams or the policy's control problem); allowed: {allowed}")
    if k not in env_keys:
        raise CurriculumError(f"{where}: unknown key {key!r} (env={env_name} has no {k!r}); allowed: {allowed}")


def check(cfg: DictConfig | Mapping, base_problems: list[str], config_problems: Callable[[DictConfig], list[str]]) -> list[str]:
    """The curriculum's problems as config-check lines: its structure (:meth:`Curriculum.from_config`), then every
    stage's config checked like the base config by ``config_problems`` (the whole check, :func:`torcsrl.training.problems`;
    only what the stage adds to ``base_problems``), prefixed with the stage's name. Refused with algorithms whose loop
    does not follow a curriculum (bc, on-policy); DAgger's rounds follow the stages (:mod:`torcsrl.training.imitation`)."""
    try:
        cur = Curriculum.from_config(cfg)
    except CurriculumError as err:
        return [str(err)]
    if not cur.active:
        return []
    algo = (cfg.get("algo") or {}).get("name")
    if cur.rehearse is not None and algo != "dagger":
        return [f"curriculum.rehearse: algo={algo} cannot rehearse an earlier stage (its collector drives one env); allowed: "
                "algo=dagger (its rounds drive the rehearsed stage's env beside their own), or curriculum.rehearse=null"]
    if algo in (*IMITATION, *ON_POLICY) and algo != "dagger":
        return [f"curriculum: algo={algo} does not follow a curriculum (its loop has no stages); allowed: curriculum=none, an "
                "off-policy algo (ddpg, td3, d4pg, sac), or algo=dagger (its rounds follow the stages)"]
    if base_problems:
        return []  # the stages are checked once the base config is sound
    if not isinstance(cfg, DictConfig):  # a plain mapping (config.problems of a dict): the stages merge into a DictConfig
        cfg = OmegaConf.create(dict(cfg))

    out: list[str] = []
    deg = cfg.get("degradation")
    for k, stage in enumerate(cur.stages):
        if any(key.startswith("degradation.severity") for key in stage.overrides) and not (deg and deg.get("stack")):
            out.append(f"curriculum.stages.{stage.name}: overrides degradation.severity but degradation.stack is empty (no "
                       "degradation to grade); allowed: a degradation group with entries (e.g. degradation=randomised), or no "
                       "severity override")
            continue
        try:
            staged = cur.config(cfg, k)
        except CurriculumError as err:
            out.append(str(err))
            continue
        with open_dict(staged):
            staged.curriculum = {"stages": {}}
        out += [f"curriculum.stages.{stage.name}: {line}" for line in config_problems(staged) if line not in base_problems]
    if cur.rehearse is not None and cur.rehearse.overrides and not out:  # the rehearsal's env, checked like a stage's
        try:
            staged = cur.rehearsal_config(cfg)
        except CurriculumError as err:
            return [str(err)]
        with open_dict(staged):
            staged.curriculum = {"stages": {}}
        out += [f"curriculum.rehearse: {line}" for line in config_problems(staged) if line not in base_problems]
    return out


def _apply(out: DictConfig, overrides: Mapping[str, Any], where: str) -> None:
    """Set the dotted ``overrides`` in ``out`` (opened for new keys). :class:`CurriculumError` (one line) when a deeper
    key's parent is not a mapping there."""
    for key, value in overrides.items():
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(out, parent, default=None)
        if not isinstance(node, DictConfig):
            raise CurriculumError(f"{where}: {key} sets {leaf!r} inside {parent}, which is "
                                  f"{'null' if node is None else repr(node)} at this stage; allowed: the whole "
                                  f"mapping ({parent}: {{...}}) in this or an earlier stage")
        OmegaConf.update(out, key, copy.deepcopy(value), merge=False, force_add=True)


def _rehearsal(value: Any, names: list[str], env_name: str = "race") -> Rehearsal | None:
    """``curriculum.rehearse``: null, or {stage: <a stage before the last>, frames: <integer >= 1>, overrides: {<dotted
    key>: value} (optional; the keys a stage may set)}."""
    if value is None:
        return None
    where = "curriculum.rehearse"
    if not isinstance(value, Mapping):
        raise CurriculumError(f"{where}: expected null or a mapping {{stage: <name>, frames: <frames per DAgger round>}}, got {value!r}")
    bad = [k for k in value if k not in _REHEARSE_KEYS]
    if bad:
        raise CurriculumError(f"{where}.{bad[0]}: unknown key; allowed: {', '.join(_REHEARSE_KEYS)}")
    stage, frames = value.get("stage"), value.get("frames")
    earlier = names[:-1]
    if stage not in earlier:
        raise CurriculumError(f"{where}.stage: {stage!r} is not a stage before the last; allowed: {', '.join(earlier) or 'none (one stage)'}")
    if not (isinstance(frames, int) and not isinstance(frames, bool) and frames >= 1):
        raise CurriculumError(f"{where}.frames: expected a positive integer (env steps per DAgger round), got {frames!r}")
    ov = value.get("overrides") or {}
    if not isinstance(ov, Mapping):
        raise CurriculumError(f"{where}.overrides: expected a mapping {{<dotted key>: value}}, got {ov!r}")
    for key in ov:
        _check_key(str(key), f"{where}.overrides", env_name)
    return Rehearsal(names.index(stage), str(stage), int(frames), {str(k): _plain(v) for k, v in ov.items()})


def _plain(v: Any) -> Any:
    return OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
