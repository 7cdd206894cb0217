"""Checks a composed training config before anything is built, and records what a run was made from.

:func:`validate` runs at the start of ``python -m torcsrl.train`` (and in the tests on every config the tree can
compose), so a misspelt key, a wrong type, an unknown name or an out-of-range value stops the run in its first
second with one message per problem, naming the key and what is allowed -- never after an hour of training.
Hydra itself already refuses ``key=value`` overrides of keys that do not exist; this catches the rest
(``+key=...``, keys added by experiment files, values of the wrong type, names the registries do not know).

Nothing is listed twice: the allowed keys and their types come from the config files that document them
(``conf/train.yaml``, ``conf/algo/base.yaml``, ``conf/logger/csv.yaml``) and from the signatures of the code
that consumes them (``make_env`` / ``RaceCore``, ``make_toy_env``, ``CarCameras``, ``VehicleParams``); the names
come from the registries (:func:`torcsrl.envs.tracks.resolve`, ``surfaces.ROAD_SURFACES``, ``check_sensors``,
``rewards.Reward``, ``torcsrl.agents.ALGOS``, :func:`torcsrl.transforms.make_stack`).

Run records (:func:`save_run_info`, :func:`write_metrics`): ``config.yaml`` (the resolved config),
``git_rev.txt`` (commit, ``-dirty`` when the tree differs from it; ``git_diff.patch`` then holds the difference of
the tracked files) and ``metrics.json`` (what ``train(cfg)`` returned; non-finite numbers as null).
"""

from __future__ import annotations

import difflib
import inspect
import json
import math
import subprocess
from collections.abc import Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

__all__ = ["CONF_DIR", "ConfigError", "validate", "problems", "save_run_info", "write_metrics", "objective", "git_revision"]

#: The Hydra config tree: ``conf/`` at the top of the repository, reached through the package's
#: ``torcsrl/conf`` link (a wheel holds a copy there), so ``python -m torcsrl.train`` finds it in a
#: checkout, an editable install and a plain ``pip install`` alike.
CONF_DIR = Path(__file__).resolve().parent / "conf"
#: Top-level keys beyond conf/train.yaml's own and its groups' (set by presets).
EXTRA_TOP_KEYS = {"optimized_metric": (str, type(None))}
#: Config sections filled by groups (checked on their own below).
GROUP_SECTIONS = ("algo", "env", "logger", "degradation", "curriculum")
#: env keys that train() sets itself (seed + 1000 (worker + 1), cpu).
ENV_KEYS_SET_BY_TRAIN = ("seed", "device")
#: (low, high, what) bounds of numbers; None = unbounded; "open" excludes the low end, "both-open" both ends.
RANGES: dict[str, tuple[float | None, float | None, str]] = {
    "total_frames": (1, None, "closed"),
    "seed": (0, None, "closed"),
    "algo.gamma": (0.0, 1.0, "closed"),
    "algo.tau": (0.0, 1.0, "open"),
    "algo.actor_lr": (0.0, None, "open"),
    "algo.critic_lr": (0.0, None, "open"),
    "algo.batch_size": (1, None, "closed"),
    "algo.policy_delay": (1, None, "closed"),
    "algo.n_steps": (1, None, "closed"),
    "algo.num_atoms": (2, None, "closed"),
    "learner.utd_ratio": (0.0, None, "open"),
    "learner.critic_warmup_updates": (0, None, "closed"),
    "buffer.size": (1, None, "closed"),
    "collector.frames_per_batch": (1, None, "closed"),
    "collector.num_workers": (0, None, "closed"),
    "eval.episodes": (1, None, "closed"),
    "eval.every_episodes": (1, None, "closed"),
    "eval.max_steps": (1, None, "closed"),
    "logger.every_frames": (1, None, "closed"),
    "checkpoint.every_frames": (0, None, "closed"),
    "checkpoint.keep": (1, None, "closed"),
    "max_minutes": (0.0, None, "open"),
    "demos.frames": (0, None, "closed"),
    "demos.sigma_max": (0.0, None, "closed"),
    "demos.episode_steps": (1, None, "closed"),
    "demos.ratio": (0.0, 1.0, "closed"),
    "demos.bc_weight": (0.0, None, "closed"),
    "demos.pretrain_steps": (0, None, "closed"),
    "demos.critic_pretrain_steps": (0, None, "closed"),
    "demos.dagger_rounds": (0, None, "closed"),
    "demos.dagger_frames": (1, None, "closed"),
    "demos.dagger_beta": (0.0, 1.0, "closed"),
    "algo.bc_steps": (1, None, "closed"),
    "algo.aux_privileged": (0.0, None, "closed"),
    "algo.bc_pedal_expectile": (0.0, 1.0, "both-open"),
    "algo.grip_estimate": (0.0, None, "closed"),
    "algo.bc_near_car_weight": (0.0, None, "open"),
    "algo.bc_near_car_m": (0.0, 200.0, "open"),
    "algo.bc_slow_weight": (0.0, None, "open"),
    "algo.bc_slow_kmh": (0.0, 300.0, "open"),
    "algo.smooth.temporal": (0.0, None, "closed"),
    "algo.smooth.spatial": (0.0, None, "closed"),
    "algo.smooth.spatial_sigma": (0.0, None, "closed"),
}
SEVERITIES = (1, 5)


class ConfigError(ValueError):
    """A config that cannot run; the message has one line per problem (``key: what is wrong; allowed: ...``)."""


# ---------------------------------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------------------------------
def validate(cfg: DictConfig | Mapping) -> None:
    """Raise :class:`ConfigError` listing every problem of the training config ``cfg``; return None if it is sound."""
    found = problems(cfg)
    if found:
        head = "invalid config" + (f" ({len(found)} problems)" if len(found) > 1 else "")
        raise ConfigError(head + ":\n  " + "\n  ".join(found) if len(found) > 1 else f"{head}: {found[0]}")


def problems(cfg: DictConfig | Mapping) -> list[str]:
    """Every problem of ``cfg`` as ``"<key>: <message>"`` lines (empty when the config is sound)."""
    out: list[str] = []
    if isinstance(cfg, DictConfig):
        for top in cfg.keys():
            node = cfg._get_node(top)
            if top == "hydra":
                continue
            if OmegaConf.is_missing(cfg, top):
                out.append(f"{top}: must be given (it is ??? in the config); e.g. {top}=<value>")
            elif OmegaConf.is_config(node):
                try:
                    missing = OmegaConf.missing_keys(node)
                except Exception:  # noqa: BLE001 -- an interpolation of a missing value: reported where it is missing
                    missing = set()
                for key in sorted(missing):  # OmegaConf names them from the top already ("algo.name")
                    full = key if str(key).startswith(f"{top}.") else f"{top}.{key}"
                    out.append(f"{full}: must be given (it is ??? in the config); e.g. {full}=<value>")
        if out:
            return out  # values that interpolate them cannot be resolved yet
        try:
            c = {k: _container(cfg, k) for k in cfg.keys() if k != "hydra"}
        except Exception as err:  # an interpolation that does not resolve
            return out + [f"cannot resolve the config: {type(err).__name__}: {err}"]
    else:
        c = {k: v for k, v in dict(cfg).items() if k != "hydra"}
    ref = _train_reference()
    # top level and the sections conf/train.yaml defines
    allowed_top = set(ref) | set(GROUP_SECTIONS) | set(EXTRA_TOP_KEYS)
    for k in c:
        if k not in allowed_top:
            out.append(_unknown(k, k, allowed_top, "conf/train.yaml"))
    for k, v in c.items():
        if k in ref:
            _against(ref[k], v, k, out, skip=("eval.env", "collector.worker_tracks"), source="conf/train.yaml")
        elif k in EXTRA_TOP_KEYS and not isinstance(v, EXTRA_TOP_KEYS[k]):
            out.append(f"{k}: expected a string, got {v!r}")
    if "algo" in c:
        _check_algo(c["algo"], out)
    _check_budget(c, out)
    if "device" in c:
        _check_device(c["device"], out)
        workers = (c.get("collector") or {}).get("num_workers") if isinstance(c.get("collector"), Mapping) else 0
        if str(c["device"]) != "cpu" and _is_num(workers) and workers > 0:
            out.append(f"device: {c['device']!r} with collector.num_workers={workers}: the env processes act on the CPU copy of the "
                       "actor only in-process; allowed: collector.num_workers=0 with a GPU device, or device=cpu")
    _check_critic_obs_keys(c, out)
    _check_frame_stack(c, out)
    _check_state_history(c, out)
    _check_algo_fit(c, out)
    demos = c.get("demos")
    if isinstance(demos, Mapping) and "teacher" in demos:
        from torcsrl.demos import TEACHERS, known_teacher

        if not known_teacher(str(demos["teacher"])):
            out.append(f"demos.teacher: unknown teacher {demos['teacher']!r}; allowed: {', '.join(TEACHERS)}")
    if "logger" in c:
        _against(_load_ref("logger/csv.yaml"), c["logger"], "logger", out, source="conf/logger/csv.yaml")
        known = sorted(p.stem for p in (CONF_DIR / "logger").glob("*.yaml"))
        for b in c["logger"].get("backends") or []:
            if b not in known:
                out.append(f"logger.backends: unknown backend {b!r}; allowed: {', '.join(known)}")
    env = c.get("env")
    if isinstance(env, Mapping):
        _check_env(env, "env", out)
        ev = (c.get("eval") or {}).get("env") or {}
        if not isinstance(ev, Mapping):
            out.append(f"eval.env: expected a mapping of env settings, got {ev!r}")
        elif ev:
            _check_env({**env, **ev}, "eval.env", out, only=set(ev))
        wt = (c.get("collector") or {}).get("worker_tracks")
        if wt is not None:
            if not isinstance(wt, list) or not wt:
                out.append(f"collector.worker_tracks: expected a non-empty list of tracks or null, got {wt!r}")
            else:
                for i, t in enumerate(wt):
                    _check_env({**env, "track": t}, f"collector.worker_tracks[{i}]", out, only={"track"}, bare=True)
    elif env is not None:
        out.append(f"env: expected a mapping, got {env!r}")
    if "degradation" in c:
        sensors = (env or {}).get("sensors") if isinstance(env, Mapping) else None
        _check_degradation(c["degradation"], sensors, out)
    if "threads" in c:
        from torcsrl.utils.threads import resolve_threads

        try:
            resolve_threads(c["threads"], 0, cores=4)
        except (ValueError, TypeError) as err:
            out.append(f"threads: {err}")
    if c.get("curriculum") is not None:  # its stages, and every stage's config checked like this one (torcsrl/curriculum.py)
        from torcsrl.curriculum import problems as curriculum_problems

        out += curriculum_problems(cfg, list(out))
    return out


def save_run_info(cfg: DictConfig, run_dir: str | Path) -> None:
    """Write ``config.yaml`` (resolved) and ``git_rev.txt`` (+ ``git_diff.patch`` when dirty) into ``run_dir``."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    body = {k: _container(cfg, k) for k in cfg.keys() if k != "hydra"}
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(body)))
    rev, diff = git_revision()
    (run_dir / "git_rev.txt").write_text(rev + "\n")
    if diff:
        (run_dir / "git_diff.patch").write_text(diff)


def write_metrics(run_dir: str | Path, metrics: Mapping[str, Any]) -> Path:
    """``metrics.json`` in ``run_dir``: the final metrics, numbers as numbers, NaN/inf as null (strict JSON)."""

    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, (str, int, float, bool)) or v is None:
            return v
        if hasattr(v, "item"):
            return clean(v.item())
        return str(v)

    path = Path(run_dir) / "metrics.json"
    path.write_text(json.dumps({k: clean(v) for k, v in metrics.items()}, indent=2, sort_keys=True) + "\n")
    return path


def objective(metrics: Mapping[str, Any], name: str | None) -> float | None:
    """The value a sweeper optimises: ``metrics[name]`` as a float (None without a name).

    A missing or non-numeric value (e.g. ``eval/reward`` of a run too short to validate) raises RuntimeError, which
    ``torcsrl.train``'s main lets through to Hydra: the Optuna sweeper records a failed trial (the sweep goes on
    while the failures stay within ``hydra.sweeper.max_failure_rate``) instead of choking on a NaN.
    """
    if not name:
        return None
    v = metrics.get(name)
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise RuntimeError(f"optimized_metric {name!r} is not a finite number in this run's metrics ({v!r}); "
                           f"metrics: {', '.join(sorted(metrics))}")
    return float(v)


def git_revision(root: str | Path | None = None) -> tuple[str, str]:
    """(``<commit>`` or ``<commit>-dirty`` or ``unknown``, the diff of tracked files against it when dirty)."""
    root = Path(root) if root else CONF_DIR.parent

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30, check=True).stdout

    try:
        rev = git("rev-parse", "HEAD").strip()
        diff = git("diff", "HEAD")
    except (OSError, subprocess.SubprocessError):
        return "unknown", ""
    return (rev + "-dirty" if diff else rev), diff


# ---------------------------------------------------------------------------------------------------------------
# references: what the documenting files and signatures allow
# ---------------------------------------------------------------------------------------------------------------
def _container(cfg: DictConfig, key: str) -> Any:
    node = cfg._get_node(key)
    if OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True, throw_on_missing=False)
    return cfg[key] if not OmegaConf.is_missing(cfg, key) else "???"


@lru_cache(maxsize=None)
def _load_ref(rel: str) -> dict:
    raw = OmegaConf.to_container(OmegaConf.load(CONF_DIR / rel), resolve=False)
    raw.pop("defaults", None)
    raw.pop("hydra", None)
    return raw


def _train_reference() -> dict:
    return _load_ref("train.yaml")


@lru_cache(maxsize=None)
def _env_signature(name: str) -> dict[str, inspect.Parameter]:
    """Keyword arguments an env accepts: make_env + RaceCore (race) or make_toy_env (toy)."""
    if name == "race":
        from torcsrl.envs import make_env
        from torcsrl.envs.race import RaceCore

        params = dict(inspect.signature(RaceCore.__init__).parameters)
        params.update(inspect.signature(make_env).parameters)
    else:
        from torcsrl.envs.toy import make_toy_env

        params = dict(inspect.signature(make_toy_env).parameters)
    return {k: p for k, p in params.items() if k != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)}


def _unknown(path: str, key: str, allowed, source: str) -> str:
    allowed = sorted(str(a) for a in allowed)
    close = difflib.get_close_matches(str(key), allowed, n=1)
    hint = f" (did you mean {path.rsplit('.', 1)[0] + '.' if '.' in path else ''}{close[0]}?)" if close else ""
    return f"{path}: unknown key{hint}; allowed: {', '.join(allowed)} ({source})"


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _type_name(v: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "a list", dict: "a mapping"}[type(v)]


def _against(ref: Any, val: Any, path: str, out: list[str], skip: Sequence[str] = (), source: str = "",
             per_dim: Sequence[str] = ()) -> None:
    """Check ``val`` against the documented reference value ``ref``: known keys, types, ranges."""
    if path in skip:
        return
    if isinstance(ref, dict):
        if val is None and not ref:
            return
        if not isinstance(val, Mapping):
            out.append(f"{path}: expected a mapping with keys {', '.join(sorted(ref))}, got {val!r}")
            return
        for k, v in val.items():
            sub = f"{path}.{k}"
            if k not in ref:
                out.append(_unknown(sub, k, ref, source))
            else:
                _against(ref[k], v, sub, out, skip, source, per_dim)
        return
    if val is None or ref is None or ref == "???" or val == "???":
        return  # null = "none / derived"; ??? is reported by the missing-keys check
    ok = True
    if isinstance(ref, bool):
        ok = isinstance(val, bool)
    elif _is_num(ref):
        nums = [val] if not isinstance(val, list) or path not in per_dim else val
        want_int = isinstance(ref, int)
        ok = bool(nums) and all(_is_num(x) and (not want_int or isinstance(x, int) or float(x).is_integer()) for x in nums)
        if ok and path in RANGES:
            lo, hi, kind = RANGES[path]
            for x in nums:
                if (lo is not None and (x < lo or (kind in ("open", "both-open") and x == lo))) or \
                        (hi is not None and (x > hi or (kind == "both-open" and x == hi))):
                    lo_s = "-inf" if lo is None else f"{lo:g}"
                    hi_s = "inf" if hi is None else f"{hi:g}"
                    left = "(" if kind in ("open", "both-open") else "["
                    right = ")" if kind == "both-open" else "]"
                    out.append(f"{path}: {x!r} is out of range; allowed: {left}{lo_s}, {hi_s}{right}")
                    return
    elif isinstance(ref, str):
        ok = isinstance(val, str) or _is_num(val)
    elif isinstance(ref, list):
        ok = isinstance(val, list)
    if not ok:
        want = _type_name(ref) + (" (or one per action dimension)" if path in per_dim else "")
        out.append(f"{path}: expected {want} like {ref!r}, got {val!r}")


# ---------------------------------------------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------------------------------------------
#: Learning-rate schedules of one imitation fit (algo.bc_lr_schedule; torcsrl/imitation.py).
BC_LR_SCHEDULES = ("constant", "cosine")


def _shift_pads(algo: Any) -> tuple[int, int]:
    """``algo.encoder.augment_shift`` as (rows, cols) pads (:func:`torcsrl.nets.shift_pad`; ValueError when it is none)."""
    from torcsrl.nets import shift_pad

    enc = algo.get("encoder") if isinstance(algo, Mapping) and isinstance(algo.get("encoder"), Mapping) else {}
    return shift_pad(enc.get("augment_shift", 0))


def _check_algo(algo: Any, out: list[str]) -> None:
    from torcsrl.agents import ALGOS

    ref = _load_ref("algo/base.yaml")
    per_dim = tuple(f"algo.exploration.{k}" for k in ("sigma", "theta", "mu"))
    _against(ref, algo, "algo", out, source="conf/algo/base.yaml", per_dim=per_dim, skip=("algo.encoder.augment_shift",))
    try:
        _shift_pads(algo)
    except ValueError as err:
        out.append(f"algo.{err}")
    if isinstance(algo, Mapping) and algo.get("name") not in (*ALGOS, "???"):
        out.append(f"algo.name: unknown algorithm {algo.get('name')!r}; allowed: {', '.join(ALGOS)}")
    from torcsrl.agents._build import PRECISIONS

    if isinstance(algo, Mapping) and "precision" in algo and algo["precision"] not in PRECISIONS:
        out.append(f"algo.precision: unknown precision {algo['precision']!r}; allowed: {', '.join(PRECISIONS)}")
    if isinstance(algo, Mapping) and algo.get("bc_lr_schedule", "constant") not in BC_LR_SCHEDULES:
        out.append(f"algo.bc_lr_schedule: unknown schedule {algo['bc_lr_schedule']!r}; allowed: {', '.join(BC_LR_SCHEDULES)}")


def _check_device(device: Any, out: list[str]) -> None:
    """``device`` must name a torch device this machine has, where the networks, losses and sampled batches go: ``cpu``,
    or ``cuda`` / ``cuda:<i>`` where ``torch.cuda.is_available()`` (envs, collector and replay buffer stay on the CPU)."""
    import torch

    allowed = "cpu, cuda, cuda:<i>" if torch.cuda.is_available() else "cpu (cuda where torch.cuda.is_available())"
    try:
        dev = torch.device(str(device))
    except (RuntimeError, ValueError):
        out.append(f"device: {device!r} is not a torch device; allowed: {allowed}")
        return
    if dev.type == "cpu":
        return
    if dev.type != "cuda":
        out.append(f"device: {str(device)!r}: the training loop places its networks on cpu or cuda only; allowed: {allowed}")
        return
    if not torch.cuda.is_available():
        out.append(f"device: {str(device)!r} is not available on this machine (torch {torch.__version__}: "
                   f"torch.cuda.is_available() is False); allowed: {allowed}")
    elif dev.index is not None and dev.index >= torch.cuda.device_count():
        out.append(f"device: {str(device)!r}: this machine has {torch.cuda.device_count()} CUDA device(s); allowed: {allowed}")


def _check_critic_obs_keys(c: Mapping, out: list[str]) -> None:
    """``critic_obs_keys`` (asymmetric actor-critic): null, or sensor names, for the actor-critic algorithms (demonstrations
    then keep the critic's keys too: :func:`torcsrl.demos.write_demos`; folders without them are refused when loaded)."""
    keys = c.get("critic_obs_keys")
    if keys is None:
        return
    from torcsrl.agents import IMITATION
    from torcsrl.envs.sensors import SENSOR_NAMES

    if not isinstance(keys, list) or not keys or not all(isinstance(k, str) for k in keys):
        out.append(f"critic_obs_keys: expected a non-empty list of sensors or null, got {keys!r}; allowed sensors: {', '.join(SENSOR_NAMES)}")
        return
    bad = [k for k in keys if k not in SENSOR_NAMES]
    if bad:
        out.append(f"critic_obs_keys: unknown sensor(s) {bad}; allowed: {', '.join(SENSOR_NAMES)}")
    algo = (c.get("algo") or {}).get("name") if isinstance(c.get("algo"), Mapping) else None
    if algo in IMITATION:
        out.append(f"critic_obs_keys: algo={algo} has no critic; allowed: null, or an actor-critic algo (ddpg, td3, d4pg, sac)")


def _check_frame_stack(c: Mapping, out: list[str]) -> None:
    """``frame_stack``: an integer 1..16; above 1 the actor must see an image (pixels or depth), and PPO's value network is
    not stacked (one frame)."""
    from torcsrl.transforms import IMAGE_KEYS

    _check_stack(c, out, "frame_stack", 16, "frames per stack", IMAGE_KEYS, "image observations",
                 "sensors with pixels (sensors=camera | pixels | both)", "frame stacks")


def _check_state_history(c: Mapping, out: list[str]) -> None:
    """``state_history``: an integer 1..100; above 1 the actor must see ``state`` or ``telemetry`` (what is stacked), and
    not with PPO (its value network sees one reading)."""
    from torcsrl.transforms import HISTORY_KEYS

    _check_stack(c, out, "state_history", 100, "readings of the on-board state", HISTORY_KEYS, "the on-board state",
                 "sensors with state or telemetry", "histories")


def _check_stack(c: Mapping, out: list[str], name: str, most: int, unit: str, stackable: tuple[str, ...], what: str,
                 sensors_hint: str, plural: str) -> None:
    """A stack setting ``name`` (``frame_stack``, ``state_history``): an integer 1..``most``; above 1 the actor must see
    one of ``stackable`` and the algo must not be PPO."""
    k = c.get(name, 1)
    if k is None or isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= most:
        out.append(f"{name}: expected an integer from 1 to {most} ({unit}), got {k!r}")
        return
    if k == 1:
        return
    env = c.get("env") if isinstance(c.get("env"), Mapping) else {}
    keys = list(c.get("obs_keys") or env.get("sensors") or [])
    if not any(x in stackable for x in keys):
        out.append(f"{name}={k} stacks {what} ({', '.join(stackable)}); the actor sees {keys}: allowed: {name}=1, or {sensors_hint}")
    algo = (c.get("algo") or {}).get("name") if isinstance(c.get("algo"), Mapping) else None
    if algo == "ppo":
        out.append(f"{name}={k}: algo=ppo is not built for {plural} yet; allowed: {name}=1 with algo=ppo, or an "
                   "off-policy or imitation algo (ddpg, td3, d4pg, sac, bc, dagger)")


def _check_algo_fit(c: Mapping, out: list[str]) -> None:
    """Settings that do not apply to the chosen algorithm. SAC and PPO explore by sampling their own policy: no action
    or parameter noise (``algo.exploration`` stays at ``kind: none`` and the base's values), and SAC has no TD3 target
    smoothing. PPO learns on-policy from the batched env's rollouts: no replay (demonstrations, prioritised replay, a
    loaded buffer, n-step returns), worker processes only as many as divide ``env.num_cars`` (the cars are split
    evenly), no asymmetric critic, no stochastic brake (its update needs the log-probability of the action taken), the
    CPU only."""
    algo = c.get("algo") if isinstance(c.get("algo"), Mapping) else {}
    name = algo.get("name")
    col = c.get("collector") if isinstance(c.get("collector"), Mapping) else {}
    lag = col.get("policy_lag", 0)
    if lag not in (0, 1, None) or isinstance(lag, bool):
        out.append(f"collector.policy_lag={lag!r}: rollouts of policy lag while the learner updates; allowed: 0 (collect, then update) or 1")
    elif lag == 1 and name != "ppo":
        out.append(f"collector.policy_lag=1: the workers collect the next rollout during the update only for algo=ppo (algo={name} "
                   "collects a step between updates); allowed: 0, or algo=ppo")
    elif lag == 1 and not (_is_num(col.get("num_workers")) and col["num_workers"] >= 1):
        out.append(f"collector.policy_lag=1 needs worker processes to collect while this one updates; allowed: collector.num_workers>=1 "
                   f"(got {col.get('num_workers')}), or policy_lag=0")
    tau = algo.get("bc_pedal_expectile", 0.5)
    if _is_num(tau) and tau != 0.5:
        env = c.get("env") if isinstance(c.get("env"), Mapping) else {}
        if name not in ("bc", "dagger"):
            out.append(f"algo.bc_pedal_expectile={tau}: the pedal expectile shapes the imitation fit of algo=bc / dagger only "
                       f"(algo={name}); allowed: 0.5, or algo=bc / dagger")
        elif env.get("action_mode") not in (None, "combined"):
            out.append(f"algo.bc_pedal_expectile={tau} weighs action 1 as a pedal (< 0 = brake), which env.action_mode="
                       f"{env.get('action_mode')} does not have; allowed: 0.5, or env.action_mode=combined")
    env = c.get("env") if isinstance(c.get("env"), Mapping) else {}
    keys = c.get("obs_keys") or env.get("sensors") or []
    keys = [keys] if isinstance(keys, str) else list(keys)
    env_name = env.get("name", "race")
    row_weights = (  # (key, what, the rows are weighed by, can the actor's rows give it, allowed)
        ("bc_near_car_weight", "the near-car weight", "the opponents sensor", "opponents" in keys, "env.sensors with opponents"),
        ("bc_slow_weight", "the slow-row weight", "the race env's state (speedX_kmh)", env_name == "race" and "state" in keys,
         "env=race with state in env.sensors"))
    for key, what, by, ok, allowed in row_weights:
        w = algo.get(key, 1.0)
        if not (_is_num(w) and w != 1.0):
            continue
        if name not in ("bc", "dagger"):
            out.append(f"algo.{key}={w}: {what} shapes the imitation fit of algo=bc / dagger only (algo={name}); allowed: 1.0, "
                       "or algo=bc / dagger")
        elif not ok:
            out.append(f"algo.{key}={w} weighs the rows by {by}, which the actor does not read (env={env_name}, its keys {keys}); "
                       f"allowed: 1.0, or {allowed}")
    grip = algo.get("grip_estimate", 0.0)
    if _is_num(grip) and grip > 0 and name not in ("bc", "dagger"):
        out.append(f"algo.grip_estimate={grip}: the grip head learns from the demonstrations' privileged mu, which only algo=bc / "
                   f"dagger fit (algo={name}); allowed: 0, or algo=bc / dagger")
    gin, readings, k = algo.get("grip_inputs", "all"), algo.get("actor_readings"), c.get("state_history", 1)
    if gin not in ("all", "history"):
        out.append(f"algo.grip_inputs={gin!r}; allowed: all (every feature), history (the state history only)")
    if readings is not None and (isinstance(readings, bool) or not _is_num(readings) or not float(readings).is_integer() or readings < 1):
        out.append(f"algo.actor_readings={readings!r}; allowed: null (the whole state history) or a number of readings >= 1")
    elif readings is not None and _is_num(k) and readings > k:
        out.append(f"algo.actor_readings={readings}: the actor's MLP would read more readings than state_history={k} holds; allowed: "
                   f"1..{k}, or null")
    if (gin == "history" or readings is not None) and not (_is_num(grip) and grip > 0):
        out.append(f"algo.grip_inputs={gin} / actor_readings={readings} shape a grip head, which algo.grip_estimate={grip} does not "
                   "build; allowed: grip_estimate > 0, or grip_inputs=all and actor_readings=null")
    hid = algo.get("grip_hidden", [64])
    if not (isinstance(hid, Sequence) and not isinstance(hid, str) and all(_is_num(h) and float(h).is_integer() and h >= 1 for h in hid)):
        out.append(f"algo.grip_hidden={hid!r}: expected a list of hidden layer sizes >= 1, e.g. [64] (or [] for a linear head)")
    if name not in ("sac", "ppo"):
        return
    why = f"algo={name} explores by sampling its own policy"
    expl = algo.get("exploration") if isinstance(algo.get("exploration"), Mapping) else {}
    base = _load_ref("algo/base.yaml")["exploration"]
    if expl.get("kind", "none") != "none":
        out.append(f"algo.exploration.kind={expl.get('kind')}: {why} (no action or parameter noise); allowed: algo.exploration.kind=none")
    else:
        for k, v in expl.items():
            if k != "kind" and k in base and v != base[k]:
                out.append(f"algo.exploration.{k}={v}: noise settings do not apply to algo={name} ({why}); allowed: the default "
                           f"{base[k]!r} (leave it unset)")
    if name == "sac" and _is_num(algo.get("policy_noise")) and algo["policy_noise"] != 0:
        out.append(f"algo.policy_noise={algo['policy_noise']}: TD3's target policy smoothing does not apply to algo=sac (its target "
                   "samples the policy); allowed: 0")
    if name != "ppo":
        return
    other = "or an off-policy algo: ddpg, td3, d4pg, sac"
    demos = c.get("demos") if isinstance(c.get("demos"), Mapping) else {}
    if demos.get("path") or (_is_num(demos.get("frames")) and demos.get("frames") > 0):
        out.append(f"demos: algo=ppo learns on-policy from its own rollouts and does not support demonstrations (replay data); allowed: "
                   f"demos.frames=0 and demos.path=null, {other}")
    buf = c.get("buffer") if isinstance(c.get("buffer"), Mapping) else {}
    if buf.get("prioritized"):
        out.append(f"buffer.prioritized=true: algo=ppo has no replay buffer and does not support prioritised replay; allowed: false, {other}")
    if buf.get("load"):
        out.append(f"buffer.load={buf['load']}: algo=ppo has no replay buffer to load; allowed: null, {other}")
    if _is_num(algo.get("n_steps")) and algo["n_steps"] != 1:
        out.append(f"algo.n_steps={algo['n_steps']}: algo=ppo's returns are GAE (algo.gae_lambda), not n-step; allowed: 1")
    col = c.get("collector") if isinstance(c.get("collector"), Mapping) else {}
    env = c.get("env") if isinstance(c.get("env"), Mapping) else {}
    cars = env.get("num_cars") if env.get("num_cars") is not None else 1
    if _is_num(col.get("num_workers")) and col["num_workers"] > 0 and _is_num(cars) and cars >= 1 and cars % col["num_workers"]:
        divisors = ", ".join(str(d) for d in range(1, int(cars) + 1) if cars % d == 0)
        out.append(f"collector.num_workers={col['num_workers']}: algo=ppo splits env.num_cars={cars} cars evenly over the worker "
                   f"processes; allowed: a divisor of {cars} ({divisors}), or 0")
    if c.get("critic_obs_keys"):
        out.append("critic_obs_keys: algo=ppo's value network sees the actor's observations; allowed: null")
    try:
        shifted = any(_shift_pads(algo))
    except ValueError:
        shifted = False  # reported by _check_algo
    if shifted:
        out.append(f"algo.encoder.augment_shift={algo['encoder']['augment_shift']}: algo=ppo does not augment its images (no DrQ/DrAC in its "
                   f"update: the ratio is that of the frame it acted on); allowed: 0, {other}")
    brake = algo.get("stochastic_brake") if isinstance(algo.get("stochastic_brake"), Mapping) else {}
    if brake.get("enabled"):
        out.append("algo.stochastic_brake.enabled=true: algo=ppo's update needs the log-probability of the action taken, which the "
                   "brake would replace; allowed: false")


def _check_budget(c: Mapping, out: list[str]) -> None:
    """A run whose warm-up covers its whole budget makes no gradient step: refuse it (RL algorithms only)."""
    from torcsrl.agents import IMITATION, ON_POLICY

    algo = c.get("algo") if isinstance(c.get("algo"), Mapping) else {}
    warmup = (c.get("learner") or {}).get("warmup_frames") if isinstance(c.get("learner"), Mapping) else None
    total = c.get("total_frames")
    if algo.get("name") in (*IMITATION, *ON_POLICY) or not (_is_num(warmup) and _is_num(total)):
        return
    if warmup >= total:
        out.append(f"learner.warmup_frames: {warmup} >= total_frames {total}: the run would make no gradient step; "
                   f"allowed: warmup_frames < total_frames (e.g. learner.warmup_frames={max(0, int(total) // 10)})")


def _check_env(env: Mapping, path: str, out: list[str], only: set | None = None, bare: bool = False) -> None:
    """``env`` (make_env keyword arguments + name, normalize); ``only``: report only these keys (eval.env)."""
    name = env.get("name")
    if name == "gym":  # benchmarks: any Gymnasium id, nothing of ours to check
        return
    if name not in ("race", "toy"):
        out.append(f"{path}.name: unknown env {name!r}; allowed: race, toy")
        return

    def key(k: str) -> str:
        return path if bare else f"{path}.{k}"

    def mine(k: str) -> bool:
        return only is None or k in only

    sig = _env_signature(name)
    race_sig = _env_signature("race")
    allowed = (set(sig) | {"name", "normalize"}) - set(ENV_KEYS_SET_BY_TRAIN)
    for k, v in env.items():
        if not mine(k) or k in allowed:
            continue
        if k in ENV_KEYS_SET_BY_TRAIN:
            out.append(f"{key(k)}: set by train itself (env seed = seed + 1000 (worker + 1), device cpu); use seed=... / device=...")
        elif name == "toy" and k in race_sig and v is None:
            continue  # race-only knobs left at null (vehicle, reward_scale, ...) do not reach the toy env
        elif name == "toy" and k in race_sig:
            out.append(f"{key(k)}: the toy env has no {k!r} (race env only); allowed for env=toy: {', '.join(sorted(allowed))}")
        else:
            out.append(_unknown(key(k), k, allowed, f"torcsrl.envs.{'make_env / RaceCore' if name == 'race' else 'toy.make_toy_env'}"))
    # numbers and flags: typed by the signature's defaults
    for k, v in env.items():
        if not mine(k) or k not in sig or v is None:
            continue
        d = sig[k].default
        if isinstance(d, bool) and not isinstance(v, bool):
            out.append(f"{key(k)}: expected a boolean, got {v!r}")
        elif _is_num(d) and not _is_num(v):
            out.append(f"{key(k)}: expected {'an integer' if isinstance(d, int) else 'a number'}, got {v!r}")
    if "normalize" in env and mine("normalize") and not isinstance(env["normalize"], bool):
        out.append(f"{key('normalize')}: expected a boolean, got {env['normalize']!r}")
    for k in ("num_cars", "max_steps", "substeps"):
        v = env.get(k)
        if mine(k) and v is not None and _is_num(v) and (int(v) != v or v < 1):
            out.append(f"{key(k)}: must be a positive integer, got {v!r}")
    v = env.get("lap_limit")
    if mine("lap_limit") and v is not None and (not _is_num(v) or int(v) != v or v < 1):
        out.append(f"{key('lap_limit')}: must be a positive integer or null, got {v!r}")
    if name == "race":
        _check_race_env(env, key, mine, out)
    else:
        _check_toy_env(env, path, key, mine, out)


def _check_race_env(env: Mapping, key, mine, out: list[str]) -> None:
    from torcsrl.envs import surfaces, tracks
    from torcsrl.envs.race import ACTION_MODES, START_MODES
    from torcsrl.envs.rewards import Reward
    from torcsrl.envs.sensors import check_sensors

    if mine("track") and env.get("track") is not None:
        try:
            tracks.resolve(list(env["track"]) if isinstance(env["track"], list) else env["track"])
        except (ValueError, tracks.TrackError) as err:
            sets = ", ".join(f"set:{s}" for s in sorted(tracks.track_sets()))
            out.append(f"{key('track')}: {err}; sets: {sets}; or a list of those")
    if mine("procedural") and env.get("procedural") is not None:
        from torcsrl.envs.tracks.procedural import ProceduralSpec

        try:
            ProceduralSpec.from_config(env["procedural"])
        except (ValueError, TypeError) as err:
            out.append(f"{key('procedural')}: {err}")
    if mine("surface"):
        for s in _as_list(env.get("surface")):
            if s is not None and s not in surfaces.ROAD_SURFACES:
                out.append(f"{key('surface')}: unknown surface {s!r}; allowed: {', '.join(surfaces.ROAD_SURFACES)} "
                           "(a list: one drawn per episode; null: each track's own)")
    if mine("sensors") and env.get("sensors") is not None:
        try:
            check_sensors(env["sensors"])
        except ValueError as err:
            out.append(f"{key('sensors')}: {err}")
    if mine("reward") and env.get("reward") is not None:
        try:
            Reward(env["reward"], 1.0)
        except (ValueError, TypeError) as err:
            out.append(f"{key('reward')}: {err}")
    if mine("reward_scale") and env.get("reward_scale") is not None:
        try:
            Reward("summers_final", env["reward_scale"])
        except (ValueError, TypeError) as err:
            out.append(f"{key('reward_scale')}: {err}")
    from torcsrl.envs.race import episode_setting_problems

    given = {k: env[k] for k in ("spawn_jitter", "offtrack_grace_s", "no_progress_s", "backwards_m") if k in env and mine(k)}
    for k, msg in episode_setting_problems(**given):
        out.append(f"{key(k)}: {msg}")
    if mine("start") and env.get("start") is not None and env["start"] not in START_MODES:
        out.append(f"{key('start')}: unknown start {env['start']!r}; allowed: {', '.join(START_MODES)}")
    if mine("action_mode") and env.get("action_mode") is not None and env["action_mode"] not in ACTION_MODES:
        out.append(f"{key('action_mode')}: unknown action_mode {env['action_mode']!r}; allowed: {', '.join(ACTION_MODES)}")
    if mine("vehicle") and env.get("vehicle") is not None:
        from torcsrl.envs.vehicle import available_vehicles

        if env["vehicle"] not in available_vehicles():
            out.append(f"{key('vehicle')}: unknown vehicle {env['vehicle']!r}; allowed: {', '.join(available_vehicles())}")
    if mine("vehicle_overrides") and env.get("vehicle_overrides"):
        import dataclasses

        from torcsrl.envs.vehicle import VehicleParams

        fields = {f.name for f in dataclasses.fields(VehicleParams)} - {"name"}
        vo = env["vehicle_overrides"]
        if not isinstance(vo, Mapping):
            out.append(f"{key('vehicle_overrides')}: expected a mapping {{parameter: value}}, got {vo!r}")
        else:
            for k in vo:
                if k not in fields:
                    out.append(_unknown(f"{key('vehicle_overrides')}.{k}", k, fields, "torcsrl.envs.vehicle.VehicleParams"))
    if mine("camera"):
        _check_camera(env.get("camera"), key("camera"), out)
    if mine("traffic") and env.get("traffic") is not None:
        from torcsrl.envs.traffic import TrafficError, TrafficSpec, _load_opponent_policy

        try:
            spec = TrafficSpec.from_config(env["traffic"])
            for pol in spec.policy_specs():
                _load_opponent_policy(pol)
        except TrafficError as err:
            out.append(f"{key('traffic')}: {err}")


def _check_camera(cam: Any, path: str, out: list[str]) -> None:
    if cam is None:
        return
    if not isinstance(cam, Mapping):
        out.append(f"{path}: expected a mapping of camera settings or null, got {cam!r}")
        return
    from torcsrl.envs.camera import MOUNTS, RENDERERS, CarCameras

    params = {k: p for k, p in inspect.signature(CarCameras.__init__).parameters.items() if k not in ("self", "client_id", "sim")}
    for k, v in cam.items():
        if k not in params:
            out.append(_unknown(f"{path}.{k}", k, params, "torcsrl.envs.camera.CarCameras"))
        elif k in ("height", "width", "every") and not (_is_num(v) and int(v) == v and v >= 1):
            out.append(f"{path}.{k}: must be a positive integer, got {v!r}")
        elif k == "mount" and isinstance(v, str) and v not in MOUNTS:
            out.append(f"{path}.mount: unknown mount {v!r}; allowed: {', '.join(MOUNTS)}")
        elif k == "renderer" and isinstance(v, str) and v not in RENDERERS:
            out.append(f"{path}.renderer: unknown renderer {v!r}; allowed: {', '.join(RENDERERS)}")


def _check_toy_env(env: Mapping, path: str, key, mine, out: list[str]) -> None:
    """The toy env checks its own arguments and is cheap to build: build it (no pybullet)."""
    from torcsrl.envs import surfaces
    from torcsrl.envs.toy import TRACKS, make_toy_env

    sig = _env_signature("toy")
    if mine("track") and env.get("track") is not None and (not isinstance(env["track"], str) or env["track"] not in TRACKS):
        out.append(f"{key('track')}: unknown toy track {env['track']!r}; allowed for env=toy: {', '.join(TRACKS)} "
                   "(the race env's tracks, sets and lists need env=race)")
        return
    s = env.get("surface")
    if mine("surface") and s is not None and (not isinstance(s, str) or s not in surfaces.ROAD_SURFACES):
        out.append(f"{key('surface')}: the toy env takes one surface of {', '.join(surfaces.ROAD_SURFACES)} or null, got {s!r} "
                   "(lists drawn per episode need env=race)")
        return
    if mine("camera") and isinstance(env.get("camera"), Mapping):
        _check_camera(env["camera"], key("camera"), out)
    kw = {k: v for k, v in env.items() if k in sig and v is not None and k not in ENV_KEYS_SET_BY_TRAIN}
    if "sensors" in kw:
        kw["sensors"] = tuple(kw["sensors"]) if isinstance(kw["sensors"], list) else kw["sensors"]
    built_from = {"sensors", "reward", "start", "num_cars", "max_steps", "lap_limit", "dt", "camera"}
    if not any(mine(k) for k in built_from):
        return
    try:
        make_toy_env(**kw).close()
    except (ValueError, TypeError) as err:
        what = next((k for k, word in (("sensors", "sensor"), ("reward", "reward"), ("start", "start"), ("track", "track"))
                     if word in str(err)), None)
        out.append(f"{key(what) if what else path}: {err}")


def _check_degradation(deg: Any, sensors: Any, out: list[str]) -> None:
    from torcsrl.transforms import make_stack
    from torcsrl.transforms.registry import PRESETS, applies_to

    if deg is None:
        return
    if not isinstance(deg, Mapping):
        out.append(f"degradation: expected a mapping {{severity, stack}}, got {deg!r}")
        return
    for k in deg:
        if k not in ("severity", "stack"):
            out.append(_unknown(f"degradation.{k}", k, ("severity", "stack"), "conf/degradation/none.yaml"))
    _check_severity(deg.get("severity"), "degradation.severity", out)
    stack = deg.get("stack") or {}
    if not isinstance(stack, Mapping):
        out.append(f"degradation.stack: expected a mapping of named entries (name: {{name, severity, ...}}), got {stack!r}")
        return
    sensors = set(sensors or ())
    for label, entry in stack.items():
        path = f"degradation.stack.{label}"
        if entry is None:
            continue  # dropped by an override
        e = {"name": entry} if isinstance(entry, str) else entry
        if not isinstance(e, Mapping):
            out.append(f"{path}: expected a degradation name or a mapping {{name, severity, ...}}, got {entry!r}")
            continue
        if "severity" in e and not _check_severity(e["severity"], f"{path}.severity", out):
            continue
        try:
            make_stack({label: dict(e)}, seed=0)
        except (ValueError, TypeError) as err:
            out.append(f"{path}: {err}")
            continue
        name = e.get("name", label)
        if e.get("optional") or not sensors or e.get("enabled", True) is False:
            continue
        if isinstance(name, str) and name.startswith("weather."):
            keys = {k for c, _, kw in PRESETS[name.split(".", 1)[1]] for k in kw.get("in_keys", applies_to(c)[:1])}
        elif e.get("keys"):
            keys = set(e["keys"])
        else:
            try:
                keys = set(applies_to(name))
            except ValueError:  # a bare effect name: make_stack resolved it with keys
                continue
        if not keys & sensors:
            out.append(f"{path}: {name} degrades {', '.join(sorted(keys))}, which env.sensors ({', '.join(sorted(sensors))}) "
                       "does not include; choose sensors=pixels or both, another degradation, or optional: true")


def _check_severity(sev: Any, path: str, out: list[str]) -> bool:
    """A severity is an integer in 1..5 or a range [lo, hi] within it (drawn per episode); None = the default."""
    lo, hi = SEVERITIES

    def one(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi

    if sev is None or one(sev) or (isinstance(sev, list) and len(sev) == 2 and all(map(one, sev)) and sev[0] <= sev[1]):
        return True
    out.append(f"{path}: severity must be an integer in {lo}..{hi} or a range [lo, hi] within it, got {sev!r}")
    return False


def _as_list(x: Any) -> list:
    return list(x) if isinstance(x, (list, tuple)) else [x]
