"""The env and its observation pipeline, from config: built by one factory, recorded in every checkpoint.

``cfg.env`` holds exactly the keyword arguments of ``torcsrl.envs.make_env`` plus ``name`` (``race``, ``toy`` or
``gym``) and ``normalize``; null values are left to make_env's defaults, and ``seed``/``device`` are set here
(training worker ``i`` gets ``seed + 1000 (i + 1)`` and, with ``collector.worker_tracks``, its own track).

What the policy sees (:func:`observation_transforms`): the clean sensors, then the degradation stack
(``cfg.degradation.stack``, in sensor units, seeded from the env's seed), then the scaling
(:func:`torcsrl.transforms.normalize_transform`, ``env.normalize``), then the frame and state histories
(``frame_stack``, ``state_history``). Training (:func:`make_train_env`), validation (:func:`make_eval_envs`), the
demonstration writer and the imitation loop build their envs here; :func:`pipeline_record` writes down what an
observation of the config means (layout, scales, degradations, control rate, car, action mode, histories), and every
checkpoint and demonstration folder carries it, so a policy is never fed differently scaled observations.

:func:`check` is the pipeline's part of the config check (:func:`torcsrl.config.problems`): the env settings
(``env``, ``eval.env``, ``collector.worker_tracks``), the degradation stack, the histories and the critic's keys.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
from collections.abc import Callable, Mapping
from functools import lru_cache
from typing import Any

from omegaconf import DictConfig, OmegaConf
from torchrl.envs import Compose, EnvBase, InitTracker, RewardSum

from torcsrl.agents import IMITATION
from torcsrl.transforms import (
    HISTORY_KEYS,
    IMAGE_KEYS,
    NORMALIZED_KEYS,
    PRESETS,
    FrameStack,
    LeanTransformedEnv,
    applies_to,
    check_severity,
    derive_seed,
    make_stack,
    normalize_transform,
    obs_scale,
)
from torcsrl.utils.seq import as_list

__all__ = ["env_kwargs", "build_base_env", "transformed", "observation_transforms", "make_train_env", "make_eval_envs",
           "actor_obs_keys", "critic_obs_keys", "stored_keys", "state_history", "frame_history", "frame_layout", "obs_layout",
           "expected_meta", "pipeline_record", "env_seed", "env_signature", "check", "ENV_KEYS_SET_BY_TRAIN"]

#: env keys that the factories set themselves (seed + 1000 (worker + 1), cpu).
ENV_KEYS_SET_BY_TRAIN = ("seed", "device")


# ---------------------------------------------------------------------------------------
# which keys
# ---------------------------------------------------------------------------------------
def actor_obs_keys(cfg: DictConfig) -> list[str]:
    """The observation keys the actor reads: ``obs_keys``, else ``env.sensors``."""
    return list(cfg.obs_keys or cfg.env.sensors)


def critic_obs_keys(cfg: DictConfig) -> list[str] | None:
    """What the critic sees when it is not what the actor sees (``critic_obs_keys``: asymmetric actor-critic), else None."""
    keys = cfg.get("critic_obs_keys")
    if not keys:
        return None
    keys = list(keys)
    return None if keys == actor_obs_keys(cfg) else keys


def stored_keys(cfg: DictConfig) -> list[str]:
    """The observation keys a transition keeps: the actor's, then the critic's own (asymmetric actor-critic)."""
    keys = actor_obs_keys(cfg)
    return keys + [k for k in (critic_obs_keys(cfg) or []) if k not in keys]


def state_history(cfg: DictConfig) -> dict[str, int]:
    """``{vector key: K}`` of the keys the actor sees as their last K readings (``state_history`` > 1), else ``{}``."""
    k = int(cfg.get("state_history", 1) or 1)
    if k <= 1:
        return {}
    return {key: k for key in actor_obs_keys(cfg) if key in HISTORY_KEYS}


def frame_history(cfg: DictConfig) -> dict[str, int]:
    """``{image key: K}`` of the stored keys the actor sees stacked (``frame_stack`` > 1), else ``{}``."""
    k = int(cfg.get("frame_stack", 1) or 1)
    if k <= 1:
        return {}
    return {key: k for key in stored_keys(cfg) if key in IMAGE_KEYS}


def frame_layout(layout: str | None, frames: int) -> str | None:
    """An ``obs_layout`` (``key:CxHxW,...``) with the image keys' channels of ONE frame (``frames`` = K of a stack)."""
    if layout is None or int(frames) <= 1:
        return layout
    parts = []
    for part in str(layout).split(","):
        k, _, shp = part.partition(":")
        dims = shp.split("x")
        if k in IMAGE_KEYS and dims and dims[0].isdigit():
            dims[0] = str(int(dims[0]) // int(frames))
        parts.append(f"{k}:{'x'.join(dims)}")
    return ",".join(parts)


# ---------------------------------------------------------------------------------------
# envs
# ---------------------------------------------------------------------------------------
def env_kwargs(env_cfg: Any, **override: Any) -> dict:
    """make_env keyword arguments from ``cfg.env``: everything but ``name``; nulls left to make_env."""
    d = OmegaConf.to_container(env_cfg, resolve=True) if isinstance(env_cfg, DictConfig) else dict(env_cfg)
    d.update(override)
    d.pop("name", None)
    d.pop("normalize", None)  # consumed by observation_transforms
    if d.get("sensors") is not None:
        d["sensors"] = tuple(d["sensors"])
    return {k: v for k, v in d.items() if v is not None}


def build_base_env(name: str, kwargs: dict, policy_loader: Callable[[str], Any] | None = None) -> EnvBase:
    """``torcsrl.envs.make_env(**kwargs)`` for ``race``, ``make_toy_env(**kwargs)`` for ``toy``, TorchRL's ``GymEnv`` for
    ``gym`` (benchmarks; observation key ``observation``). ``policy_loader`` (a policy spec -> a policy:
    ``torcsrl.policies.load_policy``, handed in by the layer above) loads the race's traffic opponents of kind ``policy``."""
    # each env module is imported when asked for: the toy env runs without pybullet, gym without the race env
    if name == "toy":
        # deferred: the toy env, only for env=toy
        from torcsrl.envs.toy import make_toy_env

        return make_toy_env(**kwargs)
    if name == "gym":
        # deferred: torchrl's gym wrapper, only for env=toy
        from torchrl.envs import GymEnv

        env = GymEnv(kwargs["id"], device=kwargs.get("device", "cpu"))
        if kwargs.get("seed") is not None:
            env.set_seed(int(kwargs["seed"]))
        return env
    if name == "race":
        try:
            # deferred: pybullet loads with the race env only (the toy env needs none)
            from torcsrl.envs import make_env
        except ImportError as err:
            raise RuntimeError(f"env.name=race needs torcsrl.envs.make_env, which cannot be imported ({err}); use env=toy meanwhile") from None
        if policy_loader is not None and kwargs.get("traffic") is not None:
            kwargs = {**kwargs, "policy_loader": policy_loader}
        return make_env(**kwargs)
    raise ValueError(f"unknown env.name {name!r}; known: race, toy, gym")


def transformed(base: EnvBase, transforms: list) -> EnvBase:
    """``base`` under ``transforms`` (:class:`~torcsrl.transforms.LeanTransformedEnv`: no per-step input
    copy for observation-only stacks), or ``base`` itself when there are none (an empty ``TransformedEnv``
    still clones every step's input: ~0.1 ms)."""
    if not transforms:
        return base
    return LeanTransformedEnv(base, Compose(*transforms))


def env_seed(base: EnvBase, default: int) -> int:
    """The seed ``base`` was built with: the race env keeps its kwargs, the toy env its numpy SeedSequence."""
    seed = getattr(base, "_kwargs", {}).get("seed") if isinstance(getattr(base, "_kwargs", None), dict) else None
    if seed is None:
        seq = getattr(getattr(getattr(base, "rng", None), "bit_generator", None), "seed_seq", None)
        seed = getattr(seq, "entropy", None) if isinstance(getattr(seq, "entropy", None), int) else None
    return int(default if seed is None else seed)


def observation_transforms(cfg: DictConfig, base: EnvBase, seed: int | None = None) -> list:
    """What the policy's observations go through: degradations (in sensor units), then scaling, then histories.

    ``cfg.degradation.stack`` (named entries, see conf/degradation/) becomes one seeded Compose
    (:func:`torcsrl.transforms.make_stack`): its generators are seeded from ``seed``, by default the
    base env's own seed (train: ``seed + 1000 (worker + 1)``, validation: ``eval.seed``), so every
    worker draws its own weather and a run with the same config and seed sees the same draws.
    The race env's sensors are in SI / TORCS units; ``env.normalize`` divides them by
    :func:`torcsrl.transforms.obs_scale` (about [-1, 1]) after any degradation.
    """
    out: list = []
    degradation = cfg.get("degradation")
    stack = degradation.get("stack") if isinstance(degradation, DictConfig) else None
    if stack and any(v is not None for v in stack.values()):
        seed0 = env_seed(base, int(cfg.seed)) if seed is None else int(seed)
        out.append(make_stack(OmegaConf.to_container(stack, resolve=True), seed=derive_seed(seed0, "degradation")))
    if cfg.env.name == "race" and cfg.env.get("normalize", True):
        keys = [k for k in NORMALIZED_KEYS if k in base.observation_spec.keys()]
        if keys:
            n_beams = base.observation_spec["rangefinder"].shape[-1] if "rangefinder" in keys else 19
            out.append(normalize_transform(keys, n_beams))
    stacked = frame_history(cfg)
    if stacked:  # last: every frame of a stack as the car saw it (degraded, scaled)
        out.append(FrameStack(cfg.frame_stack, [k for k in stacked if k in base.observation_spec.keys()]))
    history = state_history(cfg)
    if history:  # the last K readings of the on-board state, scaled (how the car feels the road's grip)
        keys = [k for k in history if k in base.observation_spec.keys()]
        if keys:
            out.append(FrameStack(int(cfg.state_history), keys, dim=-1))
    return out


def make_train_env(cfg: DictConfig, worker: int = -1, policy_loader: Callable[[str], Any] | None = None) -> EnvBase:
    """The training env of worker ``worker`` (-1: the in-process collector), with the sensors of ``env.sensors`` and of
    ``critic_obs_keys`` (asymmetric actor-critic; validation envs have ``env.sensors`` only): the observation transforms,
    and for the worker processes of TorchRL's MultiSyncCollector InitTracker + RewardSum (the in-process
    :class:`~torcsrl.utils.collector.StepCollector` keeps those two entries itself, cheaper). Without any transform,
    the base env itself. ``policy_loader``: :func:`build_base_env`'s."""
    override: dict = {"seed": int(cfg.seed) + 1000 * (worker + 1), "device": "cpu"}
    extra = [k for k in (critic_obs_keys(cfg) or []) if k not in cfg.env.sensors]
    if extra:  # asymmetric actor-critic: the env also produces what only the critic sees
        override["sensors"] = (*cfg.env.sensors, *extra)
    tracks = cfg.collector.worker_tracks
    if tracks:
        override["track"] = tracks[max(worker, 0) % len(tracks)]
    base = build_base_env(cfg.env.name, env_kwargs(cfg.env, **override), policy_loader)
    return transformed(base, [*observation_transforms(cfg, base), *([InitTracker(), RewardSum()] if worker >= 0 else [])])


def make_eval_envs(cfg: DictConfig, policy_loader: Callable[[str], Any] | None = None) -> dict[str, EnvBase]:
    """The validation env(s): one car, the validation overrides, its own seed; the observation transforms (rewards
    are summed by the validation). ``{"": env}``; with ``eval.per_track`` one env per track of the validation
    track list (``eval.env.track``, else ``env.track``), keyed by track name. ``policy_loader``: :func:`build_base_env`'s.

    Validation is a time trial from the grid (Summers's protocol) even when training spawns cars at
    random points (``env.start=random``, ``env.spawn_jitter``); ``eval.env`` overrides that too."""
    override = {}
    if cfg.env.get("start") is not None:
        override["start"] = "grid"
    if cfg.env.get("spawn_jitter") is not None:
        override["spawn_jitter"] = [0.0, 0.0]
    override.update(OmegaConf.to_container(cfg.eval.env, resolve=True) or {})
    override.update(num_cars=1, seed=int(cfg.eval.seed), device="cpu", lap_limit=cfg.eval.lap_limit, max_steps=int(cfg.eval.max_steps))
    kwargs = env_kwargs(cfg.env, **override)
    if not cfg.eval.get("per_track", False):
        return {"": _eval_env(cfg, kwargs, policy_loader)}
    if cfg.env.name != "race":
        raise ValueError(f"eval.per_track=true validates on each track of env.track; env.name={cfg.env.name!r} has no tracks "
                         "(use env=race, or eval.per_track=false)")
    # the race env's track registry (pybullet): imported only for per-track validation
    from torcsrl.envs import tracks
    from torcsrl.envs.race import RaceCore

    spec = kwargs.get("track", inspect.signature(RaceCore).parameters["track"].default)
    names = list(dict.fromkeys(tracks.resolve(list(spec) if isinstance(spec, (list, tuple)) else spec)))
    kwargs.pop("procedural", None)  # one env per NAMED track: no pool of generated tracks beside it
    return {name: _eval_env(cfg, {**kwargs, "track": name}, policy_loader) for name in names}


def _eval_env(cfg: DictConfig, kwargs: dict, policy_loader: Callable[[str], Any] | None) -> EnvBase:
    base = build_base_env(cfg.env.name, kwargs, policy_loader)
    return transformed(base, observation_transforms(cfg, base))


# ---------------------------------------------------------------------------------------
# the record
# ---------------------------------------------------------------------------------------
def obs_layout(env: EnvBase, keys: list[str] | None) -> str | None:
    """``key:shape,...`` of ``keys`` in ``env`` (None for None)."""
    if keys is None:
        return None
    nb = len(env.batch_size)
    return ",".join(f"{k}:{'x'.join(str(d) for d in env.observation_spec[k].shape[nb:])}" for k in keys)


def expected_meta(cfg: DictConfig, env: EnvBase, obs_keys: list[str]) -> dict:
    """What a checkpoint must have been written for: algorithm, observation layout (the actor's), action size."""
    return {"algo": cfg.algo.name, "obs_layout": obs_layout(env, obs_keys), "action_dim": int(env.action_spec.shape[-1])}


def pipeline_record(cfg: DictConfig, env: EnvBase) -> dict[str, Any]:
    """What an observation of this config means, for checkpoints and demonstrations: layout, action size,
    the scaling :func:`observation_transforms` applies (``scales``: the divisors per key), the degradation
    stack, control rate, physics substeps, car and action mode. A policy is fed, and demonstrations are
    mixed in, only where these are equal (:class:`torcsrl.policies.CheckpointPolicy`,
    :func:`torcsrl.training.demos.load_demos`)."""
    obs_keys = actor_obs_keys(cfg)
    meta = expected_meta(cfg, env, obs_keys)
    normalize = bool(cfg.env.get("normalize", True)) and cfg.env.name == "race"
    scales = {}
    if normalize:
        nb = len(env.batch_size)
        for k in NORMALIZED_KEYS:
            if k in env.observation_spec.keys() and k in obs_keys:  # what the policy reads (a teacher may read more)
                scales[k] = [float(x) for x in obs_scale(k, int(env.observation_spec[k].shape[nb:][-1]))]
    deg = cfg.get("degradation")
    stack = OmegaConf.to_container(deg.stack, resolve=True) if isinstance(deg, DictConfig) and deg.get("stack") else None
    stack = {k: v for k, v in (stack or {}).items() if v is not None}
    return {"obs_layout": meta["obs_layout"], "action_dim": meta["action_dim"], "normalize": normalize, "scales": scales,
            "degradation": stack, "control_hz": cfg.env.get("control_hz"), "substeps": cfg.env.get("substeps"),
            "vehicle": cfg.env.get("vehicle"), "action_mode": cfg.env.get("action_mode"), "frame_stack": int(cfg.get("frame_stack", 1) or 1),
            "state_history": int(cfg.get("state_history", 1) or 1)}


# ---------------------------------------------------------------------------------------
# config check
# ---------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def env_signature(name: str) -> dict[str, inspect.Parameter]:
    """Keyword arguments an env accepts: make_env + RaceCore (race) or make_toy_env (toy)."""
    # the env modules (pybullet) only when a config names them
    if name == "race":
        # deferred: pybullet loads with the race env only (the toy env needs none)
        from torcsrl.envs import make_env
        from torcsrl.envs.race import RaceCore

        params = dict(inspect.signature(RaceCore.__init__).parameters)
        params.update(inspect.signature(make_env).parameters)
    else:
        # deferred: the toy env, only for env=toy
        from torcsrl.envs.toy import make_toy_env

        params = dict(inspect.signature(make_toy_env).parameters)
    return {k: p for k, p in params.items() if k != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)}


def unknown_key(path: str, key: str, allowed, source: str) -> str:
    """The config-check line of an unknown ``key`` at ``path``: the closest allowed key, every allowed one, where they are documented."""
    allowed = sorted(str(a) for a in allowed)
    close = difflib.get_close_matches(str(key), allowed, n=1)
    hint = f" (did you mean {path.rsplit('.', 1)[0] + '.' if '.' in path else ''}{close[0]}?)" if close else ""
    return f"{path}: unknown key{hint}; allowed: {', '.join(allowed)} ({source})"


def is_number(v: Any) -> bool:
    """An int or float, not a bool."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def check(c: Mapping) -> list[str]:
    """The pipeline's problems in the plain (resolved) training config ``c``, as config-check lines: the critic's keys,
    the frame and state histories, the env settings (``env``, ``eval.env``, ``collector.worker_tracks``) and the
    degradation stack."""
    out: list[str] = []
    _check_critic_obs_keys(c, out)
    _check_frame_stack(c, out)
    _check_state_history(c, out)
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
    return out


def _check_critic_obs_keys(c: Mapping, out: list[str]) -> None:
    """``critic_obs_keys`` (asymmetric actor-critic): null, or sensor names, for the actor-critic algorithms (demonstrations
    then keep the critic's keys too: :func:`torcsrl.training.demos.write_demos`; folders without them are refused when loaded)."""
    keys = c.get("critic_obs_keys")
    if keys is None:
        return
    from torcsrl.envs.sensors import SENSOR_NAMES  # the sensors' module (pybullet) only when the critic has keys of its own

    if not isinstance(keys, list) or not keys or not all(isinstance(k, str) for k in keys):
        out.append(f"critic_obs_keys: expected a non-empty list of sensors or null, got {keys!r}; allowed sensors: {', '.join(SENSOR_NAMES)}")
        return
    bad = [k for k in keys if k not in SENSOR_NAMES]
    if bad:
        out.append(f"critic_obs_keys: unknown sensor(s) {bad}; allowed: {', '.join(SENSOR_NAMES)}")
    algo = (c.get("algo") or {}).get("name") if isinstance(c.get("algo"), Mapping) else None
    if algo in IMITATION:
        out.append(f"critic_obs_keys: algo={algo} has no critic; allowed: null, or an actor-critic algo (ddpg, td3, d4pg, sac, ppo)")


def _check_frame_stack(c: Mapping, out: list[str]) -> None:
    """``frame_stack``: an integer 1..16; above 1 the actor must see an image (pixels or depth), and PPO's value network is
    not stacked (one frame)."""
    _check_stack(c, out, "frame_stack", 16, "frames per stack", IMAGE_KEYS, "image observations",
                 "sensors with pixels (sensors=camera | pixels | both)", "frame stacks")


def _check_state_history(c: Mapping, out: list[str]) -> None:
    """``state_history``: an integer 1..100; above 1 the actor must see ``state`` or ``telemetry`` (what is stacked); PPO's
    actor and value network both see the history."""
    _check_stack(c, out, "state_history", 100, "readings of the on-board state", HISTORY_KEYS, "the on-board state",
                 "sensors with state or telemetry", "histories")


def _check_stack(c: Mapping, out: list[str], name: str, most: int, unit: str, stackable: tuple[str, ...], what: str,
                 sensors_hint: str, plural: str) -> None:
    """A stack setting ``name`` (``frame_stack``, ``state_history``): an integer 1..``most``; above 1 the actor must see
    one of ``stackable`` (and, for ``frame_stack``, the algo must not be PPO)."""
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
    if algo == "ppo" and name == "frame_stack":
        out.append(f"{name}={k}: algo=ppo is not built for {plural} yet; allowed: {name}=1 with algo=ppo, or an "
                   "off-policy or imitation algo (ddpg, td3, d4pg, sac, bc, dagger)")


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

    sig = env_signature(name)
    race_sig = env_signature("race")
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
            out.append(unknown_key(key(k), k, allowed, f"torcsrl.envs.{'make_env / RaceCore' if name == 'race' else 'toy.make_toy_env'}"))
    # numbers and flags: typed by the signature's defaults
    for k, v in env.items():
        if not mine(k) or k not in sig or v is None:
            continue
        d = sig[k].default
        if isinstance(d, bool) and not isinstance(v, bool):
            out.append(f"{key(k)}: expected a boolean, got {v!r}")
        elif is_number(d) and not is_number(v):
            out.append(f"{key(k)}: expected {'an integer' if isinstance(d, int) else 'a number'}, got {v!r}")
    if "normalize" in env and mine("normalize") and not isinstance(env["normalize"], bool):
        out.append(f"{key('normalize')}: expected a boolean, got {env['normalize']!r}")
    for k in ("num_cars", "max_steps", "substeps"):
        v = env.get(k)
        if mine(k) and v is not None and is_number(v) and (int(v) != v or v < 1):
            out.append(f"{key(k)}: must be a positive integer, got {v!r}")
    v = env.get("lap_limit")
    if mine("lap_limit") and v is not None and (not is_number(v) or int(v) != v or v < 1):
        out.append(f"{key('lap_limit')}: must be a positive integer or null, got {v!r}")
    if name == "race":
        _check_race_env(env, key, mine, out)
    else:
        _check_toy_env(env, path, key, mine, out)


def _check_race_env(env: Mapping, key, mine, out: list[str]) -> None:
    """The race env's settings against its registries (tracks, surfaces, sensors, rewards, cars, camera, traffic); the
    opponents' policies are loaded by :func:`torcsrl.config.problems` (a layer above: they are policies)."""
    # the race env's modules (pybullet) only when a config names env=race
    from torcsrl.envs import surfaces, tracks
    from torcsrl.envs.race import ACTION_MODES, START_MODES, episode_setting_problems
    from torcsrl.envs.rewards import Reward
    from torcsrl.envs.sensors import check_sensors
    from torcsrl.envs.tracks.procedural import ProceduralSpec
    from torcsrl.envs.traffic import TrafficError, TrafficSpec
    from torcsrl.envs.vehicle import VehicleParams, available_vehicles

    if mine("track") and env.get("track") is not None:
        try:
            tracks.resolve(list(env["track"]) if isinstance(env["track"], list) else env["track"])
        except (ValueError, tracks.TrackError) as err:
            sets = ", ".join(f"set:{s}" for s in sorted(tracks.track_sets()))
            out.append(f"{key('track')}: {err}; sets: {sets}; or a list of those")
    if mine("procedural") and env.get("procedural") is not None:
        try:
            ProceduralSpec.from_config(env["procedural"])
        except (ValueError, TypeError) as err:
            out.append(f"{key('procedural')}: {err}")
    if mine("surface"):
        for s in as_list(env.get("surface"), atoms=(str, Mapping)):
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
    given = {k: env[k] for k in ("spawn_jitter", "offtrack_grace_s", "no_progress_s", "backwards_m") if k in env and mine(k)}
    for k, msg in episode_setting_problems(**given):
        out.append(f"{key(k)}: {msg}")
    if mine("start") and env.get("start") is not None and env["start"] not in START_MODES:
        out.append(f"{key('start')}: unknown start {env['start']!r}; allowed: {', '.join(START_MODES)}")
    if mine("action_mode") and env.get("action_mode") is not None and env["action_mode"] not in ACTION_MODES:
        out.append(f"{key('action_mode')}: unknown action_mode {env['action_mode']!r}; allowed: {', '.join(ACTION_MODES)}")
    if mine("vehicle") and env.get("vehicle") is not None:
        if env["vehicle"] not in available_vehicles():
            out.append(f"{key('vehicle')}: unknown vehicle {env['vehicle']!r}; allowed: {', '.join(available_vehicles())}")
    if mine("vehicle_overrides") and env.get("vehicle_overrides"):
        fields = {f.name for f in dataclasses.fields(VehicleParams)} - {"name"}
        vo = env["vehicle_overrides"]
        if not isinstance(vo, Mapping):
            out.append(f"{key('vehicle_overrides')}: expected a mapping {{parameter: value}}, got {vo!r}")
        else:
            for k in vo:
                if k not in fields:
                    out.append(unknown_key(f"{key('vehicle_overrides')}.{k}", k, fields, "torcsrl.envs.vehicle.VehicleParams"))
    if mine("camera"):
        _check_camera(env.get("camera"), key("camera"), out)
    if mine("traffic") and env.get("traffic") is not None:
        try:
            TrafficSpec.from_config(env["traffic"])
        except TrafficError as err:
            out.append(f"{key('traffic')}: {err}")


def _check_camera(cam: Any, path: str, out: list[str]) -> None:
    if cam is None:
        return
    if not isinstance(cam, Mapping):
        out.append(f"{path}: expected a mapping of camera settings or null, got {cam!r}")
        return
    from torcsrl.envs.camera import MOUNTS, RENDERERS, CarCameras  # the camera (pybullet) only when a config has one

    params = {k: p for k, p in inspect.signature(CarCameras.__init__).parameters.items() if k not in ("self", "client_id", "sim")}
    for k, v in cam.items():
        if k not in params:
            out.append(unknown_key(f"{path}.{k}", k, params, "torcsrl.envs.camera.CarCameras"))
        elif k in ("height", "width", "every") and not (is_number(v) and int(v) == v and v >= 1):
            out.append(f"{path}.{k}: must be a positive integer, got {v!r}")
        elif k == "mount" and isinstance(v, str) and v not in MOUNTS:
            out.append(f"{path}.mount: unknown mount {v!r}; allowed: {', '.join(MOUNTS)}")
        elif k == "renderer" and isinstance(v, str) and v not in RENDERERS:
            out.append(f"{path}.renderer: unknown renderer {v!r}; allowed: {', '.join(RENDERERS)}")


def _check_toy_env(env: Mapping, path: str, key, mine, out: list[str]) -> None:
    """The toy env checks its own arguments and is cheap to build: build it (no pybullet)."""
    # the toy env's module only when a config names env=toy
    from torcsrl.envs import surfaces
    from torcsrl.envs.toy import TRACKS, make_toy_env

    sig = env_signature("toy")
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
    if deg is None:
        return
    if not isinstance(deg, Mapping):
        out.append(f"degradation: expected a mapping {{severity, stack}}, got {deg!r}")
        return
    for k in deg:
        if k not in ("severity", "p", "stack"):
            out.append(unknown_key(f"degradation.{k}", k, ("severity", "p", "stack"), "conf/degradation/none.yaml"))
    _severity_ok(deg.get("severity"), "degradation.severity", out)
    prob = deg.get("p")
    if prob is not None and (isinstance(prob, bool) or not is_number(prob) or not 0.0 < float(prob) <= 1.0):
        out.append(f"degradation.p={prob!r}: the probability that each effect of the stack is on in an episode; allowed: 0 < p <= 1")
        return  # the entries that refer to it would each repeat the line
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
        if "severity" in e and not _severity_ok(e["severity"], f"{path}.severity", out):
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


def _severity_ok(sev: Any, path: str, out: list[str]) -> bool:
    """A severity is an integer in 1..5 or a range [lo, hi] within it (drawn per episode, :func:`torcsrl.transforms.check_severity`);
    None = the default."""
    if sev is None:
        return True
    try:
        check_severity(sev, path)
    except (TypeError, ValueError):
        out.append(f"{path}: severity must be an integer in 1..5 or a range [lo, hi] within it, got {sev!r}")
        return False
    return True

