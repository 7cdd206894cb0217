"""The training config's own checks: its keys and types against the files that document them, the algorithm
section, the budget, the device, what fits the algorithm, the logger, the threads, the traffic opponents' policies.

Every check names the key, what is wrong and what is allowed, one line per problem (:class:`ConfigError`), so a
misspelt key, a wrong type, an unknown name or an out-of-range value stops a run in its first second -- never after
an hour of training. Hydra itself already refuses ``key=value`` overrides of keys that do not exist; this catches the
rest (``+key=...``, keys added by experiment files, values of the wrong type, names the registries do not know).

Nothing is listed twice: the allowed keys and their types come from the config files that document them
(``conf/train.yaml``, ``conf/algo/base.yaml``, ``conf/logger/csv.yaml``); the names from the registries
(``torcsrl.agents.ALGOS``, the logger backends in ``conf/logger/``). The other subsystems check their own parts
(:func:`torcsrl.pipeline.check`, :func:`torcsrl.training.demos.check`, :func:`torcsrl.training.curriculum.check`);
:func:`torcsrl.training.problems` gathers them all.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import lru_cache
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from torcsrl.agents import ALGOS, IMITATION, ON_POLICY
from torcsrl.agents.bc import PRECISIONS
from torcsrl.nets import shift_pad
from torcsrl.pipeline import is_number, unknown_key
from torcsrl.policies import load_policy
from torcsrl.utils.hydra_app import CONF_DIR
from torcsrl.utils.ray_session import RayError, check_address
from torcsrl.utils.threads import resolve_threads

__all__ = ["ConfigError", "resolve", "check", "section", "raise_problems"]

#: Top-level keys beyond conf/train.yaml's own and its groups' (set by presets).
EXTRA_TOP_KEYS = {"optimized_metric": (str, type(None))}
#: Config sections filled by groups (checked on their own below).
GROUP_SECTIONS = ("algo", "env", "logger", "degradation", "curriculum")
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


class ConfigError(ValueError):
    """A config that cannot run; the message has one line per problem (``key: what is wrong; allowed: ...``)."""


def raise_problems(found: list[str]) -> None:
    """Raise :class:`ConfigError` with one line per problem in ``found`` (nothing when it is empty)."""
    if found:
        head = "invalid config" + (f" ({len(found)} problems)" if len(found) > 1 else "")
        raise ConfigError(head + ":\n  " + "\n  ".join(found) if len(found) > 1 else f"{head}: {found[0]}")


def resolve(cfg: DictConfig | Mapping) -> tuple[dict | None, list[str]]:
    """``(the config as plain values, [])``, or ``(None, problems)`` when values are missing (``???``) or an
    interpolation does not resolve: the checks of the values wait until they can be read."""
    out: list[str] = []
    if not isinstance(cfg, DictConfig):
        return {k: v for k, v in dict(cfg).items() if k != "hydra"}, out
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
        return None, out  # values that interpolate them cannot be resolved yet
    try:
        return {k: section(cfg, k) for k in cfg.keys() if k != "hydra"}, out
    except Exception as err:  # an interpolation that does not resolve
        return None, [f"cannot resolve the config: {type(err).__name__}: {err}"]


def check(c: Mapping) -> list[str]:
    """The problems of the plain training config ``c`` (:func:`resolve`) in its own sections, as ``"<key>: <message>"``
    lines."""
    out: list[str] = []
    ref = _train_reference()
    # top level and the sections conf/train.yaml defines
    allowed_top = set(ref) | set(GROUP_SECTIONS) | set(EXTRA_TOP_KEYS)
    for k in c:
        if k not in allowed_top:
            out.append(unknown_key(k, k, allowed_top, "conf/train.yaml"))
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
        if str(c["device"]) != "cpu" and is_number(workers) and workers > 0:
            out.append(f"device: {c['device']!r} with collector.num_workers={workers}: the env processes act on the CPU copy of the "
                       "actor only in-process; allowed: collector.num_workers=0 with a GPU device, or device=cpu")
    _check_algo_fit(c, out)
    if "logger" in c:
        _against(_load_ref("logger/csv.yaml"), c["logger"], "logger", out, source="conf/logger/csv.yaml")
        known = sorted(p.stem for p in (CONF_DIR / "logger").glob("*.yaml"))
        for b in c["logger"].get("backends") or []:
            if b not in known:
                out.append(f"logger.backends: unknown backend {b!r}; allowed: {', '.join(known)}")
    _check_opponent_policies(c, out)
    if "threads" in c:
        try:
            resolve_threads(c["threads"], 0, cores=4)
        except (ValueError, TypeError) as err:
            out.append(f"threads: {err}")
    return out


# ---------------------------------------------------------------------------------------------------------------
# references: what the documenting files and signatures allow
# ---------------------------------------------------------------------------------------------------------------
def section(cfg: DictConfig, key: str) -> Any:
    """The top-level entry ``key`` of ``cfg`` as plain values (interpolations resolved; ``???`` where missing)."""
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
                out.append(unknown_key(sub, k, ref, source))
            else:
                _against(ref[k], v, sub, out, skip, source, per_dim)
        return
    if val is None or ref is None or ref == "???" or val == "???":
        return  # null = "none / derived"; ??? is reported by the missing-keys check
    ok = True
    if isinstance(ref, bool):
        ok = isinstance(val, bool)
    elif is_number(ref):
        nums = [val] if not isinstance(val, list) or path not in per_dim else val
        want_int = isinstance(ref, int)
        ok = bool(nums) and all(is_number(x) and (not want_int or isinstance(x, int) or float(x).is_integer()) for x in nums)
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
        ok = isinstance(val, str) or is_number(val)
    elif isinstance(ref, list):
        ok = isinstance(val, list)
    if not ok:
        want = _type_name(ref) + (" (or one per action dimension)" if path in per_dim else "")
        out.append(f"{path}: expected {want} like {ref!r}, got {val!r}")


# ---------------------------------------------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------------------------------------------
#: Learning-rate schedules of one imitation fit (algo.bc_lr_schedule; torcsrl/training/imitation.py).
BC_LR_SCHEDULES = ("constant", "cosine")
LR_SCHEDULES = ("constant", "linear")  # algo.lr_schedule (PPO)


def _shift_pads(algo: Any) -> tuple[int, int]:
    """``algo.encoder.augment_shift`` as (rows, cols) pads (:func:`torcsrl.nets.shift_pad`; ValueError when it is none)."""
    enc = algo.get("encoder") if isinstance(algo, Mapping) and isinstance(algo.get("encoder"), Mapping) else {}
    return shift_pad(enc.get("augment_shift", 0))


def _check_algo(algo: Any, out: list[str]) -> None:
    ref = _load_ref("algo/base.yaml")
    per_dim = (*(f"algo.exploration.{k}" for k in ("sigma", "theta", "mu")), "algo.log_std_init")
    _against(ref, algo, "algo", out, source="conf/algo/base.yaml", per_dim=per_dim, skip=("algo.encoder.augment_shift",))
    try:
        _shift_pads(algo)
    except ValueError as err:
        out.append(f"algo.{err}")
    if isinstance(algo, Mapping) and algo.get("name") not in (*ALGOS, "???"):
        out.append(f"algo.name: unknown algorithm {algo.get('name')!r}; allowed: {', '.join(ALGOS)}")
    if isinstance(algo, Mapping) and "precision" in algo and algo["precision"] not in PRECISIONS:
        out.append(f"algo.precision: unknown precision {algo['precision']!r}; allowed: {', '.join(PRECISIONS)}")
    if isinstance(algo, Mapping) and algo.get("bc_lr_schedule", "constant") not in BC_LR_SCHEDULES:
        out.append(f"algo.bc_lr_schedule: unknown schedule {algo['bc_lr_schedule']!r}; allowed: {', '.join(BC_LR_SCHEDULES)}")
    if isinstance(algo, Mapping) and algo.get("lr_schedule", "constant") not in LR_SCHEDULES:
        out.append(f"algo.lr_schedule: unknown schedule {algo['lr_schedule']!r}; allowed: {', '.join(LR_SCHEDULES)}")
    end = algo.get("log_std_end") if isinstance(algo, Mapping) else None
    if end is not None and not (is_number(end) and -5.0 <= float(end) <= 2.0):
        out.append(f"algo.log_std_end={end!r}: the policy's log std at total_frames; allowed: a number in [-5, 2] (the actor's "
                   "log std bounds), or null (learnt)")
    kl = algo.get("target_kl") if isinstance(algo, Mapping) else None
    if kl is not None and (isinstance(kl, bool) or not is_number(kl) or kl <= 0):
        out.append(f"algo.target_kl={kl!r}: the approximate KL at which a rollout's epochs stop; allowed: a number > 0 [nats], or null")


def _check_device(device: Any, out: list[str]) -> None:
    """``device`` must name a torch device this machine has, where the networks, losses and sampled batches go: ``cpu``,
    or ``cuda`` / ``cuda:<i>`` where ``torch.cuda.is_available()`` (envs, collector and replay buffer stay on the CPU)."""
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
    elif lag == 1 and not (is_number(col.get("num_workers")) and col["num_workers"] >= 1):
        out.append(f"collector.policy_lag=1 needs worker processes to collect while this one updates; allowed: collector.num_workers>=1 "
                   f"(got {col.get('num_workers')}), or policy_lag=0")
    address = col.get("ray")
    if address is not None:
        try:
            check_address(address)
        except RayError as err:
            out.append(f"collector.{err}")
        else:
            if not (is_number(col.get("num_workers")) and col["num_workers"] >= 1):
                out.append(f"collector.ray={address}: the Ray actors are the env workers; allowed: collector.num_workers>=1 "
                           f"(got {col.get('num_workers')}), or collector.ray=null")
            if name in ("bc", "dagger"):
                out.append(f"collector.ray={address}: algo={name} collects its demonstrations and DAgger rounds in this process; "
                           "allowed: collector.ray=null")
    tau = algo.get("bc_pedal_expectile", 0.5)
    if is_number(tau) and tau != 0.5:
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
        if not (is_number(w) and w != 1.0):
            continue
        if name not in ("bc", "dagger"):
            out.append(f"algo.{key}={w}: {what} shapes the imitation fit of algo=bc / dagger only (algo={name}); allowed: 1.0, "
                       "or algo=bc / dagger")
        elif not ok:
            out.append(f"algo.{key}={w} weighs the rows by {by}, which the actor does not read (env={env_name}, its keys {keys}); "
                       f"allowed: 1.0, or {allowed}")
    grip = algo.get("grip_estimate", 0.0)
    init_actor = (c.get("init") or {}).get("actor") if isinstance(c.get("init"), Mapping) else None
    if is_number(grip) and grip > 0 and name == "ppo" and not init_actor:
        out.append(f"algo.grip_estimate={grip}: algo=ppo keeps the grip head of the student it starts from (the head learns from "
                   "demonstrations' privileged mu, which PPO has none of); allowed: 0, or init.actor=<a grip student's checkpoint>")
    elif is_number(grip) and grip > 0 and name not in ("bc", "dagger", "ppo"):
        out.append(f"algo.grip_estimate={grip}: the grip head learns from the demonstrations' privileged mu, which only algo=bc / "
                   f"dagger fit (algo={name}); allowed: 0, algo=bc / dagger, or algo=ppo started from a grip student (init.actor)")
    gin, readings, k = algo.get("grip_inputs", "all"), algo.get("actor_readings"), c.get("state_history", 1)
    if gin not in ("all", "history"):
        out.append(f"algo.grip_inputs={gin!r}; allowed: all (every feature), history (the state history only)")
    if readings is not None and (isinstance(readings, bool) or not is_number(readings) or not float(readings).is_integer() or readings < 1):
        out.append(f"algo.actor_readings={readings!r}; allowed: null (the whole state history) or a number of readings >= 1")
    elif readings is not None and is_number(k) and readings > k:
        out.append(f"algo.actor_readings={readings}: the actor's MLP would read more readings than state_history={k} holds; allowed: "
                   f"1..{k}, or null")
    if (gin == "history" or readings is not None) and not (is_number(grip) and grip > 0):
        out.append(f"algo.grip_inputs={gin} / actor_readings={readings} shape a grip head, which algo.grip_estimate={grip} does not "
                   "build; allowed: grip_estimate > 0, or grip_inputs=all and actor_readings=null")
    hid = algo.get("grip_hidden", [64])
    if not (isinstance(hid, Sequence) and not isinstance(hid, str) and all(is_number(h) and float(h).is_integer() and h >= 1 for h in hid)):
        out.append(f"algo.grip_hidden={hid!r}: expected a list of hidden layer sizes >= 1, e.g. [64] (or [] for a linear head)")
    if name != "ppo" and name in ALGOS:
        if algo.get("lr_schedule", "constant") != "constant":
            out.append(f"algo.lr_schedule={algo['lr_schedule']}: the learning-rate schedule applies to algo=ppo only (algo={name}: "
                       "bc_lr_schedule for bc/dagger); allowed: constant")
        if algo.get("target_kl") is not None:
            out.append(f"algo.target_kl={algo['target_kl']}: the KL early stop of a rollout's epochs applies to algo=ppo only; allowed: null")
        if algo.get("log_std_end") is not None:
            out.append(f"algo.log_std_end={algo['log_std_end']}: the policy-std schedule applies to algo=ppo only; allowed: null")
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
    if name == "sac" and is_number(algo.get("policy_noise")) and algo["policy_noise"] != 0:
        out.append(f"algo.policy_noise={algo['policy_noise']}: TD3's target policy smoothing does not apply to algo=sac (its target "
                   "samples the policy); allowed: 0")
    if name != "ppo":
        return
    other = "or an off-policy algo: ddpg, td3, d4pg, sac"
    demos = c.get("demos") if isinstance(c.get("demos"), Mapping) else {}
    if demos.get("path") or (is_number(demos.get("frames")) and demos.get("frames") > 0):
        out.append(f"demos: algo=ppo learns on-policy from its own rollouts and does not support demonstrations (replay data); allowed: "
                   f"demos.frames=0 and demos.path=null, {other}")
    buf = c.get("buffer") if isinstance(c.get("buffer"), Mapping) else {}
    if buf.get("prioritized"):
        out.append(f"buffer.prioritized=true: algo=ppo has no replay buffer and does not support prioritised replay; allowed: false, {other}")
    if buf.get("load"):
        out.append(f"buffer.load={buf['load']}: algo=ppo has no replay buffer to load; allowed: null, {other}")
    if is_number(algo.get("n_steps")) and algo["n_steps"] != 1:
        out.append(f"algo.n_steps={algo['n_steps']}: algo=ppo's returns are GAE (algo.gae_lambda), not n-step; allowed: 1")
    col = c.get("collector") if isinstance(c.get("collector"), Mapping) else {}
    env = c.get("env") if isinstance(c.get("env"), Mapping) else {}
    cars = env.get("num_cars") if env.get("num_cars") is not None else 1
    if is_number(col.get("num_workers")) and col["num_workers"] > 0 and is_number(cars) and cars >= 1 and cars % col["num_workers"]:
        divisors = ", ".join(str(d) for d in range(1, int(cars) + 1) if cars % d == 0)
        out.append(f"collector.num_workers={col['num_workers']}: algo=ppo splits env.num_cars={cars} cars evenly over the worker "
                   f"processes; allowed: a divisor of {cars} ({divisors}), or 0")
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
    algo = c.get("algo") if isinstance(c.get("algo"), Mapping) else {}
    warmup = (c.get("learner") or {}).get("warmup_frames") if isinstance(c.get("learner"), Mapping) else None
    total = c.get("total_frames")
    if algo.get("name") in (*IMITATION, *ON_POLICY) or not (is_number(warmup) and is_number(total)):
        return
    if warmup >= total:
        out.append(f"learner.warmup_frames: {warmup} >= total_frames {total}: the run would make no gradient step; "
                   f"allowed: warmup_frames < total_frames (e.g. learner.warmup_frames={max(0, int(total) // 10)})")


def _check_opponent_policies(c: Mapping, out: list[str]) -> None:
    """Each policy a traffic opponent drives with (``env.traffic``, ``eval.env.traffic``) loads
    (:func:`torcsrl.policies.load_policy`) and reads only what the env gives an opponent
    (:func:`torcsrl.envs.traffic.load_opponent_policy`). Traffic settings that do not parse are the pipeline's to report
    (:func:`torcsrl.pipeline.check`)."""
    env = c.get("env") if isinstance(c.get("env"), Mapping) else {}
    if env.get("name") != "race":
        return
    ev = (c.get("eval") or {}).get("env") if isinstance(c.get("eval"), Mapping) else None
    for path, traffic in (("env.traffic", env.get("traffic")), ("eval.env.traffic", ev.get("traffic") if isinstance(ev, Mapping) else None)):
        if traffic is None:
            continue
        # the race env's traffic module (pybullet) only when a config has traffic
        from torcsrl.envs.traffic import TrafficError, TrafficSpec, load_opponent_policy

        try:
            spec = TrafficSpec.from_config(traffic)
        except TrafficError:
            continue
        try:
            for name in (spec.policy_specs() if spec is not None else []):
                load_opponent_policy(name, load_policy)
        except TrafficError as err:
            out.append(f"{path}: {err}")
