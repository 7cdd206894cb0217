"""Train a racing driver: ``python -m torcsrl.train [algo=td3|ddpg|d4pg|sac|ppo] [env=race|toy] [overrides]``.

``main`` is a thin Hydra wrapper; :func:`train` does the work and returns the final metrics, so
tests call it directly on a config composed with Hydra's ``compose`` API. The loop reads in the
order the algorithm runs: env, agent (actor, critic), loss + target updater, behaviour policy,
collector, buffer, optimisers; then collect -> extend -> update -> log -> validate -> checkpoint.

``cfg.env`` holds exactly the keyword arguments of ``torcsrl.envs.make_env`` plus ``name``
(``race`` or ``toy``); null values are left to make_env's defaults, and ``seed``/``device`` are
added here (worker ``i`` of a multi-process collector gets ``seed + 1000 (i + 1)`` and, if
``collector.worker_tracks`` is set, its own track).

Resuming (``checkpoint.resume=latest`` or a path) restores networks, targets, optimisers,
counters, every RNG (python, numpy, torch, the envs' generators), the exploration state, the
collector's in-flight episode and the replay buffer: on CPU with the in-process collector (and an
env with ``get_sim_state``, like the toy env) the resumed run continues exactly as the
uninterrupted one would have.

A curriculum (``curriculum=guppy|robust``, :mod:`torcsrl.curriculum`) trains in stages: the envs are built from the
current stage's config, and after a validation that meets the stage's criterion :func:`enter_stage` rebuilds the
training env, its collector and the validation envs from the next stage's; the stage, its validations and the
promotions are in every checkpoint, so a resumed run resumes the stage.

Speed (``benchmarks/train_throughput.py``; the loop's hot path allocates little and reads no
config): the in-process collector is :class:`~torcsrl.utils.collector.StepCollector` (TorchRL's
``Collector`` semantics without its per-step bookkeeping; ``MultiSyncCollector`` for worker
processes), the replay memory :class:`~torcsrl.utils.replay.ReplayBuffer` (each observation
stored once, n-step returns formed when sampling, index gathers), the update
``torcsrl.agents._build.update`` (fused twin critics, detached critic in the actor loss, fused
Adam and one ``_foreach_lerp_`` for the targets, no ``.item()``: metrics are read when logged).
With ``frames_per_batch`` F and ``utd_ratio`` U, each batch of F frames is followed by F x U
gradient steps: F = one env step (the default) updates after every step, like SB3 / CleanRL;
a larger F acts F frames with the same weights (policy lag < F steps) for the same data per update.
"""

from __future__ import annotations

import functools
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import MultiSyncCollector
from torchrl.envs import Compose, EnvBase, InitTracker, RewardSum
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torcsrl import agents
from torcsrl.curriculum import Curriculum, CurriculumError
from torcsrl.utils.checkpoint import (
    CheckpointError,
    checkpoint_path,
    latest_checkpoint,
    load_checkpoint,
    prune,
    resume_from,
    save_checkpoint,
    save_dir_atomically,
)
from torcsrl.utils.collector import StepCollector
from torcsrl.utils.faults import claim_run_dir, cli_error, graceful_termination, writable_folder
from torcsrl.utils.replay import ReplayBuffer
from torcsrl.utils.logging import Progress, log_metrics, make_loggers, truncate_csv_after
from torcsrl.utils.seeding import rng_state, seed_everything, set_rng_state
from torcsrl.utils.threads import configure_threads

# ---------------------------------------------------------------------------------------
# environments
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


def build_base_env(name: str, kwargs: dict) -> EnvBase:
    """``torcsrl.envs.make_env(**kwargs)`` for ``race``, ``make_toy_env(**kwargs)`` for ``toy`` (imported lazily)."""
    if name == "toy":
        from torcsrl.envs.toy import make_toy_env

        return make_toy_env(**kwargs)
    if name == "gym":  # any Gymnasium id (benchmarks): GymEnv(id), observation key "observation"
        from torchrl.envs import GymEnv

        env = GymEnv(kwargs["id"], device=kwargs.get("device", "cpu"))
        if kwargs.get("seed") is not None:
            env.set_seed(int(kwargs["seed"]))
        return env
    if name == "race":
        try:
            from torcsrl.envs import make_env
        except ImportError as err:
            raise RuntimeError(f"env.name=race needs torcsrl.envs.make_env, which cannot be imported ({err}); use env=toy meanwhile") from None
        return make_env(**kwargs)
    raise ValueError(f"unknown env.name {name!r}; known: race, toy, gym")


def make_train_env(cfg: DictConfig, worker: int = -1) -> EnvBase:
    """The training env of worker ``worker`` (-1: the in-process collector), with the sensors of ``env.sensors`` and of
    ``critic_obs_keys`` (asymmetric actor-critic; validation envs have ``env.sensors`` only): the observation transforms,
    and for the worker processes of TorchRL's MultiSyncCollector InitTracker + RewardSum (the in-process
    :class:`StepCollector` keeps those two entries itself, cheaper). Without any transform, the base env
    itself (an empty ``TransformedEnv`` still clones every step's input: ~0.1 ms)."""
    override: dict = {"seed": int(cfg.seed) + 1000 * (worker + 1), "device": "cpu"}
    extra = [k for k in (critic_obs_keys(cfg) or []) if k not in cfg.env.sensors]
    if extra:  # asymmetric actor-critic: the env also produces what only the critic sees
        override["sensors"] = (*cfg.env.sensors, *extra)
    tracks = cfg.collector.worker_tracks
    if tracks:
        override["track"] = tracks[max(worker, 0) % len(tracks)]
    base = build_base_env(cfg.env.name, env_kwargs(cfg.env, **override))
    transforms = [*observation_transforms(cfg, base), *([InitTracker(), RewardSum()] if worker >= 0 else [])]
    return _transformed(base, transforms)


def _transformed(base: EnvBase, transforms: list) -> EnvBase:
    """``base`` under ``transforms`` (:class:`~torcsrl.transforms.LeanTransformedEnv`: no per-step input
    copy for observation-only stacks), or ``base`` itself when there are none."""
    if not transforms:
        return base
    from torcsrl.transforms import LeanTransformedEnv

    return LeanTransformedEnv(base, Compose(*transforms))


def observation_transforms(cfg: DictConfig, base: EnvBase, seed: int | None = None) -> list:
    """What the policy's observations go through: degradations (in sensor units), then scaling.

    ``cfg.degradation.stack`` (named entries, see conf/degradation/) becomes one seeded Compose
    (:func:`torcsrl.transforms.make_stack`): its generators are seeded from ``seed``, by default the
    base env's own seed (train: ``seed + 1000 (worker + 1)``, validation: ``eval.seed``), so every
    worker draws its own weather and a run with the same config and seed sees the same draws.
    The race env's sensors are in SI / TORCS units; ``env.normalize`` divides them by
    :func:`torcsrl.envs.sensors.obs_scale` (about [-1, 1]) after any degradation.
    """
    out: list = []
    degradation = cfg.get("degradation")
    stack = degradation.get("stack") if isinstance(degradation, DictConfig) else None
    if stack and any(v is not None for v in stack.values()):
        from torcsrl.transforms import derive_seed, make_stack

        env_seed = _env_seed(base, int(cfg.seed)) if seed is None else int(seed)
        out.append(make_stack(OmegaConf.to_container(stack, resolve=True), seed=derive_seed(env_seed, "degradation")))
    if cfg.env.name == "race" and cfg.env.get("normalize", True):
        from torcsrl.envs.sensors import normalize_transform

        keys = [k for k in ("rangefinder", "state", "telemetry", "opponents") if k in base.observation_spec.keys()]
        if keys:
            n_beams = base.observation_spec["rangefinder"].shape[-1] if "rangefinder" in keys else 19
            out.append(normalize_transform(keys, n_beams))
    stacked = frame_history(cfg)
    if stacked:  # last: every frame of a stack as the car saw it (degraded, scaled)
        from torcsrl.transforms import FrameStack

        out.append(FrameStack(cfg.frame_stack, [k for k in stacked if k in base.observation_spec.keys()]))
    history = state_history(cfg)
    if history:  # the last K readings of the on-board state, scaled (how the car feels the road's grip)
        from torcsrl.transforms import FrameStack

        keys = [k for k in history if k in base.observation_spec.keys()]
        if keys:
            out.append(FrameStack(int(cfg.state_history), keys, dim=-1))
    return out


def state_history(cfg: DictConfig) -> dict[str, int]:
    """``{vector key: K}`` of the keys the actor sees as their last K readings (``state_history`` > 1), else ``{}``."""
    k = int(cfg.get("state_history", 1) or 1)
    if k <= 1:
        return {}
    from torcsrl.transforms import HISTORY_KEYS

    return {key: k for key in list(cfg.obs_keys or cfg.env.sensors) if key in HISTORY_KEYS}


def frame_history(cfg: DictConfig) -> dict[str, int]:
    """``{image key: K}`` of the stored keys the actor sees stacked (``frame_stack`` > 1), else ``{}``."""
    k = int(cfg.get("frame_stack", 1) or 1)
    if k <= 1:
        return {}
    from torcsrl.transforms import IMAGE_KEYS

    return {key: k for key in stored_keys(cfg) if key in IMAGE_KEYS}


def frame_layout(layout: str | None, frames: int) -> str | None:
    """An ``obs_layout`` (``key:CxHxW,...``) with the image keys' channels of ONE frame (``frames`` = K of a stack)."""
    if layout is None or int(frames) <= 1:
        return layout
    from torcsrl.transforms import IMAGE_KEYS

    parts = []
    for part in str(layout).split(","):
        k, _, shp = part.partition(":")
        dims = shp.split("x")
        if k in IMAGE_KEYS and dims and dims[0].isdigit():
            dims[0] = str(int(dims[0]) // int(frames))
        parts.append(f"{k}:{'x'.join(dims)}")
    return ",".join(parts)


def pipeline_record(cfg: DictConfig, env: EnvBase) -> dict[str, Any]:
    """What an observation of this config means, for checkpoints and demonstrations: layout, action size,
    the scaling :func:`observation_transforms` applies (``scales``: the divisors per key), the degradation
    stack, control rate, physics substeps, car and action mode. A policy is fed, and demonstrations are
    mixed in, only where these are equal (:class:`torcsrl.policies.CheckpointPolicy`, :func:`torcsrl.demos.load_demos`)."""
    obs_keys = list(cfg.obs_keys or cfg.env.sensors)
    meta = expected_meta(cfg, env, obs_keys)
    normalize = bool(cfg.env.get("normalize", True)) and cfg.env.name == "race"
    scales = {}
    if normalize:
        from torcsrl.envs.sensors import obs_scale

        nb = len(env.batch_size)
        for k in ("rangefinder", "state", "telemetry", "opponents"):
            if k in env.observation_spec.keys() and k in obs_keys:  # what the policy reads (a teacher may read more)
                scales[k] = [float(x) for x in obs_scale(k, int(env.observation_spec[k].shape[nb:][-1]))]
    deg = cfg.get("degradation")
    stack = OmegaConf.to_container(deg.stack, resolve=True) if isinstance(deg, DictConfig) and deg.get("stack") else None
    stack = {k: v for k, v in (stack or {}).items() if v is not None}
    return {"obs_layout": meta["obs_layout"], "action_dim": meta["action_dim"], "normalize": normalize, "scales": scales,
            "degradation": stack, "control_hz": cfg.env.get("control_hz"), "substeps": cfg.env.get("substeps"),
            "vehicle": cfg.env.get("vehicle"), "action_mode": cfg.env.get("action_mode"), "frame_stack": int(cfg.get("frame_stack", 1) or 1),
            "state_history": int(cfg.get("state_history", 1) or 1)}


def _env_seed(base: EnvBase, default: int) -> int:
    """The seed ``base`` was built with: the race env keeps its kwargs, the toy env its numpy SeedSequence."""
    seed = getattr(base, "_kwargs", {}).get("seed") if isinstance(getattr(base, "_kwargs", None), dict) else None
    if seed is None:
        seq = getattr(getattr(getattr(base, "rng", None), "bit_generator", None), "seed_seq", None)
        seed = getattr(seq, "entropy", None) if isinstance(getattr(seq, "entropy", None), int) else None
    return int(default if seed is None else seed)


def make_eval_envs(cfg: DictConfig) -> dict[str, EnvBase]:
    """The validation env(s): one car, the validation overrides, its own seed; no transforms (rewards
    are summed here). ``{"": env}``; with ``eval.per_track`` one env per track of the validation
    track list (``eval.env.track``, else ``env.track``), keyed by track name.

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
        return {"": _eval_env(cfg, kwargs)}
    if cfg.env.name != "race":
        raise ValueError(f"eval.per_track=true validates on each track of env.track; env.name={cfg.env.name!r} has no tracks "
                         "(use env=race, or eval.per_track=false)")
    import inspect

    from torcsrl.envs import tracks
    from torcsrl.envs.race import RaceCore

    spec = kwargs.get("track", inspect.signature(RaceCore).parameters["track"].default)
    names = list(dict.fromkeys(tracks.resolve(list(spec) if isinstance(spec, (list, tuple)) else spec)))
    kwargs.pop("procedural", None)  # one env per NAMED track: no pool of generated tracks beside it
    return {name: _eval_env(cfg, {**kwargs, "track": name}) for name in names}


def _eval_env(cfg: DictConfig, kwargs: dict) -> EnvBase:
    base = build_base_env(cfg.env.name, kwargs)
    return _transformed(base, observation_transforms(cfg, base))


# ---------------------------------------------------------------------------------------
# buffer and collector
# ---------------------------------------------------------------------------------------
def streams(cfg: DictConfig) -> int:
    """Parallel trajectories per env step: cars per env x env processes."""
    return max(1, int(cfg.env.get("num_cars", 1) or 1)) * max(1, int(cfg.collector.num_workers))


def critic_obs_keys(cfg: DictConfig) -> list[str] | None:
    """What the critic sees when it is not what the actor sees (``critic_obs_keys``: asymmetric actor-critic), else None."""
    keys = cfg.get("critic_obs_keys")
    if not keys:
        return None
    keys = list(keys)
    return None if keys == list(cfg.obs_keys or cfg.env.sensors) else keys


def stored_keys(cfg: DictConfig) -> list[str]:
    """The observation keys a transition keeps: the actor's, then the critic's own (asymmetric actor-critic)."""
    keys = list(cfg.obs_keys or cfg.env.sensors)
    return keys + [k for k in (critic_obs_keys(cfg) or []) if k not in keys]


def make_buffer(cfg: DictConfig, run_dir: Path) -> ReplayBuffer:
    """Replay ring (``torcsrl/utils/replay.py``): every observation stored once (the actor's and the critic's keys,
    :func:`stored_keys`), n-step returns formed when sampling, RAM or memory-mapped disk storage, optionally prioritized."""
    b = cfg.buffer
    return ReplayBuffer(int(b.size), int(cfg.algo.batch_size), stored_keys(cfg), streams=streams(cfg),
                        n_steps=int(cfg.algo.n_steps), gamma=float(cfg.algo.gamma), storage=str(b.storage),
                        path=b.path or Path(run_dir) / "buffer", prioritized=bool(b.prioritized), alpha=float(b.alpha), beta=float(b.beta),
                        history=frame_history(cfg))


def make_demos(cfg: DictConfig, env: EnvBase, run_dir: Path) -> ReplayBuffer | None:
    """The demonstrations this run learns from (:mod:`torcsrl.demos`), or None.

    ``demos.path``: a folder written by ``python -m torcsrl.demos``, or a list of them (shards written in parallel,
    sampled as one :class:`~torcsrl.demos.DemoPool`); else ``demos.frames > 0`` writes that many DART frames of the
    expert in this run's env into ``<run_dir>/demos`` (once: a resumed run reuses them), with the critic's own keys
    where it sees more than the actor (``critic_obs_keys``: TD3+BC / RLPD on an asymmetric actor-critic).
    Refused (one line) when their observation layout or pipeline differs from this run's, or they lack a key it stores."""
    d = cfg.get("demos")
    if d is None or (d.path in (None, "") and int(d.frames) <= 0):
        return None
    from torcsrl.demos import DemoPool, load_demos, write_demos

    if cfg.buffer.prioritized:
        raise ValueError("demos with buffer.prioritized=true are not supported (the demo rows have no priorities); use one or the other")
    record = pipeline_record(cfg, env)
    kw = dict(n_steps=int(cfg.algo.n_steps), gamma=float(cfg.algo.gamma), keys=stored_keys(cfg), history=frame_history(cfg))
    if d.path is not None and not isinstance(d.path, str):  # a list of shards
        return DemoPool([load_demos(p, record, int(cfg.algo.batch_size), **kw) for p in d.path])
    path = Path(d.path) if d.path else Path(run_dir) / "demos"
    if not d.path and not (path / "demos.json").is_file():
        save_dir_atomically(path, lambda tmp: write_demos(cfg, tmp))
    return load_demos(path, record, int(cfg.algo.batch_size), **kw)


def sample_batch(buffer: ReplayBuffer, demos: ReplayBuffer | None, n_demo: int):
    """A training batch: all from ``buffer``, or (RLPD's symmetric sampling) ``n_demo`` demonstration rows
    LAST after the online ones; every row then carries ``expert_action`` (the online rows their own action)."""
    if demos is None or n_demo <= 0:
        return buffer.sample()
    on = buffer.sample(buffer.batch_size - n_demo)
    on.set("expert_action", on.get("action"))
    return torch.cat([on, demos.sample(n_demo).select(*on.keys(), strict=False)], 0)  # demo-only keys ("privileged") dropped


def pretrain(agent, hot, loss, optim, target_updater, demos: ReplayBuffer, bc_steps: int, critic_steps: int, precision: str,
             device: torch.device = torch.device("cpu")) -> dict:
    """Behaviour-clone the actor on the demonstrations, then fit the critic to it (actor frozen), targets synced."""
    from torcsrl.agents._build import bc_step

    out = {}
    for _ in range(int(bc_steps)):
        out["loss/bc"], _ = bc_step(loss, optim, demos.sample(successor=False).to(device), precision)  # no next: a plain BC loss
    with torch.no_grad():  # targets start as the pre-trained actor
        for tgt, src in zip(*target_updater._lists):
            tgt.copy_(src)
    for i in range(int(critic_steps)):
        out.update(agent.update(hot, loss, optim, target_updater, demos.sample().to(device), i, actor=False))
    return out


def make_networks(cfg: DictConfig, agent, env: EnvBase, obs_keys: list[str], device: torch.device):
    """(actor, critic, loss) on ``device`` (``cfg.device``): the actor on ``obs_keys`` (started from ``init.actor``
    when set), the critic on :func:`critic_obs_keys` (the actor's when null), the loss over both. Built on the CPU and
    moved before the loss is made, so the loss's target copies are made on ``device`` too."""
    ckeys = critic_obs_keys(cfg)
    actor = agent.make_actor(cfg.algo, env, obs_keys)
    init = cfg.get("init")
    if init is not None and init.get("actor"):
        init_actor(str(init.actor), actor, cfg, env, obs_keys)
    critic = agent.make_critic(cfg.algo, env, ckeys or obs_keys)
    actor.to(device)
    critic.to(device)
    loss = agent.make_loss(cfg.algo, actor, critic, env, obs_keys, ckeys).to(device)
    return actor, critic, loss


def init_actor(spec: str, actor: torch.nn.Module, cfg: DictConfig, env: EnvBase, obs_keys: list[str]) -> Path:
    """Load the actor weights of the checkpoint ``spec`` (a training checkpoint, a policy file, or a run folder: its
    newest checkpoint) into ``actor``: e.g. an asymmetric TD3 actor started from the distilled camera student.

    ValueError (one line) unless the checkpoint's actor saw this run's observation layout, with the same scaling, and
    acted with the same action size, and its network has this actor's shape."""
    path = Path(spec)
    if path.is_dir():
        found = latest_checkpoint(path / "checkpoints") or latest_checkpoint(path)
        if found is None:
            raise ValueError(f"init.actor={spec}: the folder holds no checkpoint (nor checkpoints/ckpt_*.pt); allowed: a checkpoint "
                             "file, a policy file, or a run folder with checkpoints")
        path = found
    elif not path.is_file():
        raise ValueError(f"init.actor={spec}: no such file or folder; allowed: a checkpoint file, a policy file, or a run folder")
    ck = load_checkpoint(path)
    meta, want = ck["meta"], expected_meta(cfg, env, obs_keys)
    if meta.get("kind") == "ensemble":
        raise ValueError(f"init.actor={path}: an ensemble of {len(ck.get('members', []))} students, not one actor; allowed: one of its "
                         f"members (python -m torcsrl.policies member {path} <index> <out.pt>), a checkpoint, or a run folder")
    if meta.get("obs_layout") != want["obs_layout"] or meta.get("action_dim") != want["action_dim"]:
        raise ValueError(f"init.actor={path}: its actor sees {meta.get('obs_layout')!r} with {meta.get('action_dim')} action dims; "
                         f"this run's actor sees {want['obs_layout']!r} with {want['action_dim']}; allowed: a checkpoint of the "
                         "same observation set (obs_keys / env.sensors, camera size) and action size")
    rec = meta.get("pipeline")
    mine = pipeline_record(cfg, env)["scales"]
    if rec is not None and dict(rec.get("scales") or {}) != mine:
        raise ValueError(f"init.actor={path}: its observations were scaled for {sorted(rec.get('scales') or {})}, this run's for "
                         f"{sorted(mine)}; allowed: a checkpoint trained with the same env.normalize")
    if "actor" in ck:
        sd = ck["actor"]
    else:
        prefix = "actor_network_params."
        sd = {k[len(prefix):]: v for k, v in (ck.get("loss") or {}).items() if k.startswith(prefix)}
    try:
        actor.load_state_dict(sd, strict=True)
    except RuntimeError as err:
        first = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
        raise ValueError(f"init.actor={path}: its actor network differs from this run's ({first[1] if len(first) > 1 else first[0]}); "
                         "allowed: the same algo.actor_hidden and algo.encoder as the checkpoint's config") from None
    print(f"[torcsrl] actor initialised from {path}", file=sys.stderr)
    return path


def make_collector(cfg: DictConfig, env: EnvBase, policy, collected: int = 0) -> StepCollector | MultiSyncCollector:
    """In-process :class:`StepCollector` (num_workers = 0) or TorchRL's MultiSyncCollector over ``num_workers`` env processes.
    ``collected``: frames collected before (a curriculum stage's new collector): they count towards ``init_random_frames``."""
    c = cfg.collector
    fpb = int(c.frames_per_batch or max(1, env.batch_size.numel()))  # null: one env step of every car
    if int(c.num_workers) == 0:
        collector = StepCollector(env, policy, fpb, int(c.init_random_frames))
        collector.frames = int(collected)
        return collector
    fns = [functools.partial(make_train_env, cfg, i) for i in range(int(c.num_workers))]
    return MultiSyncCollector(fns, policy, frames_per_batch=fpb * int(c.num_workers), total_frames=-1,
                              init_random_frames=max(0, int(c.init_random_frames) - int(collected)),
                              exploration_type=ExplorationType.RANDOM,
                              # the learner keeps cfg.threads (TorchRL otherwise sets max(1, threads - workers) silently)
                              num_threads=torch.get_num_threads(), num_sub_threads=1)


def enter_stage(cfg: DictConfig, frames: int, env: EnvBase, collector, eval_envs: dict[str, EnvBase], policy, buffer: ReplayBuffer):
    """(env, collector, eval_envs) of a new curriculum stage, ``cfg`` being the stage's config
    (:meth:`torcsrl.curriculum.Curriculum.config`); the old ones are closed. The running episodes end here as time-limit
    truncations (:meth:`ReplayBuffer.end_episodes`): bootstrapped from their last observation, never joined to the new
    env's first. Networks, optimisers, buffer and exploration noise carry on (a stage never changes what they see)."""
    buffer.end_episodes()
    collector.shutdown()
    for e in (env, *eval_envs.values()):
        if not e.is_closed:
            e.close()
    env = make_train_env(cfg)
    return env, make_collector(cfg, env, policy, collected=frames), make_eval_envs(cfg)


# ---------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------
class TrainWindow:
    """The training logs' bookkeeping shared by the off-policy loop and PPO's (:mod:`torcsrl.onpolicy`): episodes
    finished in collected batches, and one log line's window (steps/s, updates/s since the last line)."""

    def __init__(self, counters) -> None:
        self.t_start, self.cpu_start = time.perf_counter(), time.process_time()
        self.t, self.frames, self.updates = self.t_start, counters.frames, counters.updates
        self.rewards: list[float] = counters.window_rewards  # the counters' own lists: they go into every checkpoint
        self.laps: list[float] = counters.window_laps

    def book(self, data, counters) -> None:
        """Count the episodes that end in ``data`` (a collected batch) and keep their returns and laps."""
        done = data["next", "done"].squeeze(-1)
        if done.any():
            self.rewards += data["next", "episode_reward"].squeeze(-1)[done].tolist()
            lap_key, _ = _lap_keys(data["next"])
            if lap_key is not None:
                self.laps += data["next", lap_key].squeeze(-1)[done].tolist()
            counters.episodes += int(done.sum())

    def steps_per_s(self, counters) -> float:
        return (counters.frames - self.frames) / max(time.perf_counter() - self.t, 1e-9)

    def log(self, loggers, progress, counters, last: dict, **extra) -> None:
        """Log ``last`` (the latest value of each loss key), the counters, ``extra``, the window's rates and the mean return
        and laps of the episodes booked since the last line; then start a new window."""
        now = time.perf_counter()
        sps = self.steps_per_s(counters)
        metrics = {k: float(v) for k, v in last.items()}
        metrics.update({"train/frames": counters.frames, "train/episodes": counters.episodes, **extra,
                        "time/steps_per_s": sps, "time/updates_per_s": (counters.updates - self.updates) / max(now - self.t, 1e-9),
                        "time/elapsed_s": now - self.t_start, "time/cpu_s": time.process_time() - self.cpu_start})
        if self.rewards:
            metrics["train/episode_reward"] = sum(self.rewards) / len(self.rewards)
            if self.laps:
                metrics["train/laps"] = sum(self.laps) / len(self.laps)
            self.rewards.clear()
            self.laps.clear()
        log_metrics(loggers, {k: v for k, v in metrics.items() if not k.startswith("time/")}, counters.frames)
        log_metrics(loggers, {k: v for k, v in metrics.items() if k.startswith("time/")}, counters.frames)
        progress.update(counters.frames, sps)
        self.t, self.frames, self.updates = now, counters.frames, counters.updates


def _lap_keys(td: TensorDictBase) -> tuple:
    """(completed-laps key, last-lap-time key): :func:`torcsrl.evaluate.protocol.lap_keys`."""
    from torcsrl.evaluate.protocol import lap_keys

    return lap_keys(td)


@torch.no_grad()
def validate_all(envs: dict[str, EnvBase], policy, episodes: int, max_steps: int) -> dict[str, float]:
    """:func:`validate` on each validation env (:func:`make_eval_envs`).

    One env: its metrics. One per track: ``eval/<track>/{reward,laps,lap_time,lap_time_mean}`` for
    each, and over the tracks ``eval/reward`` and ``eval/laps`` (means), ``eval/laps_min`` (the worst
    track: it equals the lap limit only when every track was driven clean) and ``eval/lap_time``
    (mean of the tracks' fastest laps; NaN unless every track has a timed lap).
    """
    if list(envs) == [""]:
        return validate(envs[""], policy, episodes, max_steps)
    per = {name: validate(env, policy, episodes, max_steps) for name, env in envs.items()}
    out = {f"eval/{name}/{k.split('/', 1)[1]}": v for name, m in per.items() for k, v in m.items()}
    n = len(per)
    out["eval/reward"] = sum(m["eval/reward"] for m in per.values()) / n
    out["eval/laps"] = sum(m["eval/laps"] for m in per.values()) / n
    out["eval/laps_min"] = min(m["eval/laps"] for m in per.values())
    out["eval/lap_time"] = sum(m["eval/lap_time"] for m in per.values()) / n  # NaN if any track has none
    if all("eval/collisions" in m for m in per.values()):
        out["eval/collisions"] = sum(m["eval/collisions"] for m in per.values()) / n
    return out


@torch.no_grad()
def validate(env: EnvBase, policy, episodes: int, max_steps: int) -> dict[str, float]:
    """Summers's protocol: deterministic policy, no noise, nothing stored, no updates. Each episode is
    :func:`torcsrl.evaluate.protocol.drive_episode`, the one episode loop evaluate and report use too
    (lap accounting, step cap, termination); the return is the float64 sum of the step rewards. In a race
    (``env.traffic``) also ``eval/collisions``: contacts begun with another car per episode."""
    from torcsrl.evaluate.protocol import drive_episode

    rewards, laps, lap_times, collisions = [], [], [], []
    traffic = getattr(getattr(getattr(env, "base_env", env), "core", None), "traffic", None)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            book, _ = drive_episode(env, policy, 1, max_steps)
            rewards.append(book.ret[0])
            laps.append(book.prev_lap[0])
            lap_times += book.lap_times[0]
            if traffic is not None:
                collisions.append(int(traffic.collisions[0]))  # the learner's (car 0's) count, booked until its episode ended
    out = {
        "eval/reward": sum(rewards) / len(rewards),
        "eval/laps": sum(laps) / len(laps),
        "eval/lap_time": min(lap_times) if lap_times else float("nan"),
        "eval/lap_time_mean": sum(lap_times) / len(lap_times) if lap_times else float("nan"),
    }
    if traffic is not None:
        out["eval/collisions"] = sum(collisions) / len(collisions)
    return out


# ---------------------------------------------------------------------------------------
# checkpoint state
# ---------------------------------------------------------------------------------------
@dataclass
class Counters:
    """Loop counters (all in the checkpoint)."""

    frames: int = 0  # env steps collected
    updates: int = 0  # gradient steps taken
    episodes: int = 0  # training episodes finished
    owed_updates: float = 0.0  # fractional updates carried between batches (utd_ratio)
    next_eval: int = 0  # validate when episodes >= next_eval
    next_ckpt: int = 0  # checkpoint when frames >= next_ckpt
    next_log: int = 0  # log when frames >= next_log
    pretrained: bool = False  # demonstration pre-training (demos.pretrain_steps, critic_pretrain_steps) done
    # returns and laps of the episodes finished since the last log line (its mean is logged there): kept across a
    # checkpoint, so a resumed run logs the same train/episode_reward as the uninterrupted one
    window_rewards: list = field(default_factory=list)
    window_laps: list = field(default_factory=list)


def _stateful_transforms(env: EnvBase) -> list:
    """The env's transforms that carry running state (degradations), in a fixed order."""
    t = getattr(env, "transform", None)
    return [m for m in t.modules() if hasattr(m, "get_sim_state")] if t is not None else []


def _sim_state(env: EnvBase) -> dict | None:
    """The base env's simulation state and every degradation's generator and running state, or
    None when the base env cannot save its simulation."""
    base = getattr(env, "base_env", env)
    if not hasattr(base, "get_sim_state"):
        return None
    return {"base": base.get_sim_state(), "transforms": [m.get_sim_state() for m in _stateful_transforms(env)]}


def _set_sim_state(env: EnvBase, state: dict | None) -> None:
    base = getattr(env, "base_env", env)
    if state is None or not hasattr(base, "set_sim_state"):
        return
    if not (isinstance(state, dict) and set(state) == {"base", "transforms"}):  # before transforms were saved
        base.set_sim_state(state)
        return
    base.set_sim_state(state["base"])
    mods = _stateful_transforms(env)
    if len(mods) != len(state["transforms"]):
        raise CheckpointError(f"checkpoint holds the state of {len(state['transforms'])} degradation transforms; "
                              f"this run's config has {len(mods)}")
    for m, st in zip(mods, state["transforms"]):
        m.set_sim_state(st)


def expected_meta(cfg: DictConfig, env: EnvBase, obs_keys: list[str]) -> dict:
    """What a checkpoint must have been written for: algorithm, observation layout (the actor's), action size."""
    return {"algo": cfg.algo.name, "obs_layout": _layout(env, obs_keys), "action_dim": int(env.action_spec.shape[-1])}


def _layout(env: EnvBase, keys: list[str] | None) -> str | None:
    """``key:shape,...`` of ``keys`` in ``env`` (None for None)."""
    if keys is None:
        return None
    nb = len(env.batch_size)
    return ",".join(f"{k}:{'x'.join(str(d) for d in env.observation_spec[k].shape[nb:])}" for k in keys)


# ---------------------------------------------------------------------------------------
# the loop
# ---------------------------------------------------------------------------------------
def plain(node: DictConfig) -> SimpleNamespace:
    """A config node as nested ``SimpleNamespace`` of plain values (attribute access without OmegaConf's cost)."""
    def conv(v):
        return SimpleNamespace(**{k: conv(x) for k, x in v.items()}) if isinstance(v, dict) else v

    return conv(OmegaConf.to_container(node, resolve=True))


#: Command-line overrides a resume must not repeat (the resume sets its own run_dir / checkpoint.resume).
_RESUME_DROPS = ("run_dir", "checkpoint.resume", "overwrite", "hydra.")


def resume_command(run_dir: Path | str, extra: str = "") -> str:
    """The shell command that resumes the run in ``run_dir``: this run's own command-line overrides (read from Hydra,
    so ``experiment=racer seed=1 env.surface=[...]`` come back; without them the resumed config would differ from the
    checkpoint's) + ``run_dir=<run_dir> checkpoint.resume=latest`` (+ ``extra``, e.g. ``total_frames=<more>``)."""
    import shlex  # noqa: PLC0415

    try:
        from hydra.core.hydra_config import HydraConfig  # noqa: PLC0415

        task = list(HydraConfig.get().overrides.task)
    except ValueError:  # not under @hydra.main: the caller passed a config, not a command line
        task = []
    keep = [o for o in task if not o.lstrip("+~").startswith(_RESUME_DROPS)]
    parts = ["python", "-m", "torcsrl.train", *keep, f"run_dir={run_dir}", "checkpoint.resume=latest"]
    return " ".join(shlex.quote(p) for p in parts) + (f" {extra}" if extra else "")


def _run_dir(cfg: DictConfig) -> Path:
    if cfg.run_dir:
        return Path(cfg.run_dir)
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except ValueError:  # not under @hydra.main
        return Path("outputs") / "train" / cfg.algo.name / time.strftime("%Y-%m-%d_%H-%M-%S")


def train(cfg: DictConfig) -> dict[str, Any]:
    """Train ``cfg.algo`` on ``cfg.env``; returns the final metrics (and where things were written).

    The config is checked first (:func:`torcsrl.config.validate`: unknown keys, wrong types, unknown
    names, severities): a ``ConfigError`` naming every problem, before anything is built. The run folder
    is then held for this run alone (:func:`torcsrl.utils.faults.claim_run_dir`: a lock, and a folder
    holding another run is refused unless ``checkpoint.resume`` or ``overwrite=true``)."""
    from torcsrl.config import validate as check_config

    check_config(cfg)
    run_dir = _run_dir(cfg)
    if not cfg.run_dir:  # pin the folder (a time stamp outside Hydra) for everything that asks for it below
        cfg = cfg.copy()
        with open_dict(cfg):
            cfg.run_dir = str(run_dir)
    with claim_run_dir(run_dir, resume=bool(cfg.checkpoint.resume), overwrite=bool(cfg.get("overwrite", False))):
        if cfg.algo.name in agents.IMITATION:  # BC / DAgger: no critic, no collector (torcsrl/imitation.py)
            from torcsrl.imitation import train as imitate

            return imitate(cfg)
        if cfg.algo.name in agents.ON_POLICY:  # PPO: rollouts, then epochs of minibatches (torcsrl/onpolicy.py)
            from torcsrl.onpolicy import train as train_on_policy

            return train_on_policy(cfg, run_dir)
        return _train(cfg, run_dir)


def _train(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """:func:`train`'s loop, in the folder it holds."""
    if cfg.buffer.storage == "disk":
        writable_folder(cfg.buffer.path or run_dir / "buffer", "buffer.path")
    ckpt_dir = run_dir / "checkpoints"
    threads = configure_threads(cfg.threads, int(cfg.collector.num_workers))
    seed_everything(int(cfg.seed))
    agent = agents.get(cfg.algo.name)
    obs_keys = list(cfg.obs_keys or cfg.env.sensors)
    total = int(cfg.total_frames)
    device = torch.device(str(cfg.device))  # networks, losses, sampled batches; envs, collector and buffer stay on the CPU
    on_device = device.type != "cpu"

    curriculum = Curriculum.from_config(cfg)  # conf/curriculum: ordered stages of env overrides (none: cfg itself)
    if cfg.checkpoint.resume:
        _resume_stage(cfg, ckpt_dir, curriculum)  # an exact resume resumes the checkpoint's stage
    stage_cfg = curriculum.config(cfg)  # the env, validation and degradation settings of the current stage
    env = make_train_env(stage_cfg)
    actor, critic, loss = make_networks(cfg, agent, env, obs_keys, device)
    target_updater = agent.make_target_updater(cfg.algo, loss)
    policy = agent.make_exploration(cfg.algo, actor, env, obs_keys)
    optim = agent.make_optimizers(cfg.algo, loss)
    buffer = make_buffer(cfg, run_dir)
    demos = make_demos(curriculum.config(cfg, stage=0), env, run_dir)  # written (once) in the first stage's env
    collector = make_collector(stage_cfg, env, policy)
    eval_envs = make_eval_envs(stage_cfg)
    meta = {**expected_meta(cfg, env, obs_keys), "critic_obs_layout": _layout(env, critic_obs_keys(cfg))}
    counters = Counters(next_eval=int(cfg.eval.every_episodes), next_ckpt=int(cfg.checkpoint.every_frames) or total,
                        next_log=int(cfg.logger.every_frames))
    if cfg.buffer.load:
        buffer.loads(str(cfg.buffer.load))
    if cfg.checkpoint.resume:
        counters = _resume(cfg, ckpt_dir, meta, loss, optim, policy, collector, env, eval_envs, buffer, run_dir)
    # cfg.logger["backends"], not .backends: Hydra's joblib launcher cloudpickles this module's functions by value (it
    # runs as __main__), and an attribute named "backends" in a function that also uses `torch` makes cloudpickle try
    # to pickle the torch.backends module object, which cannot be pickled.
    loggers = make_loggers(cfg.logger["backends"], run_dir, cfg.logger.exp_name, cfg.logger.wandb_project, cfg.logger.wandb_mode)
    progress = Progress(total, enabled=bool(cfg.progress))
    multi = int(cfg.collector.num_workers) > 0
    print(f"[torcsrl] training {cfg.algo.name} on env={cfg.env.name} for {total} steps; outputs in {run_dir}", file=sys.stderr)
    if curriculum.active:
        _write_curriculum(curriculum, run_dir)
        print(f"[torcsrl] curriculum: stage {curriculum.stage} {curriculum.name!r} of {', '.join(curriculum.names)}", file=sys.stderr)

    # plain values for the hot loop (an OmegaConf lookup costs ~10 us)
    hot = plain(cfg.algo)
    warmup, batch_size, utd = int(cfg.learner.warmup_frames), int(cfg.algo.batch_size), float(cfg.learner.utd_ratio)
    critic_warmup = int(cfg.learner.get("critic_warmup_updates", 0) or 0)
    n_demo = int(round(batch_size * float(cfg.demos.ratio))) if demos is not None else 0
    last: dict[str, Any] = {}
    # the latest value of every loss key over the online updates (what a log line shows): TD3's actor loss (and its
    # TD3+BC terms) survive the critic-only steps of its policy delay; pre-training's keys end at the first update
    merged: dict[str, Any] = {}
    hot.n_demo, hot.bc_weight = n_demo, float(cfg.demos.bc_weight) if demos is not None else 0.0
    if demos is not None and not counters.pretrained:
        last = pretrain(agent, hot, loss, optim, target_updater, demos, int(cfg.demos.pretrain_steps), int(cfg.demos.critic_pretrain_steps),
                        str(cfg.algo.precision), device)
        counters.pretrained = True
    prioritized = bool(cfg.buffer.prioritized)
    eval_metrics: dict[str, float] = {}
    window = TrainWindow(counters)
    t_start = window.t_start
    max_wall_s = 60.0 * float(cfg.max_minutes) if cfg.get("max_minutes") else 0.0  # the loop's budget (demos and pre-training come before)
    try:
        batches = iter(collector)
        while counters.frames < total:
            if max_wall_s and time.perf_counter() - t_start > max_wall_s:  # the wall-clock budget: stop with a checkpoint
                print(f"[torcsrl] wall-clock budget of {cfg.max_minutes} min reached at {counters.frames} steps", file=sys.stderr)
                _save(cfg, ckpt_dir, meta, counters, loss, optim, policy, collector, env, eval_envs, buffer, threads, curriculum)
                break
            # collect -> extend
            data = next(batches)
            window.book(data, counters)
            buffer.extend(data)
            counters.frames += data.numel()

            # update (configurable update-to-data ratio after the warm-up)
            if counters.frames >= warmup and len(buffer) >= batch_size - n_demo:
                counters.owed_updates += utd * data.numel()
                for _ in range(int(counters.owed_updates)):
                    batch = sample_batch(buffer, demos, n_demo)
                    if on_device:
                        batch = batch.to(device, non_blocking=True)
                    if counters.updates >= critic_warmup:
                        merged.update(agent.update(hot, loss, optim, target_updater, batch, counters.updates))
                    else:  # the critic learns the (initialised) actor's values first
                        merged.update(agent.update(hot, loss, optim, target_updater, batch, counters.updates, actor=False))
                        target_updater.step()
                    last = merged
                    if prioritized:
                        buffer.update_tensordict_priority(batch)
                    counters.updates += 1
                counters.owed_updates -= int(counters.owed_updates)
                if multi:
                    collector.update_policy_weights_()

            # log
            if counters.frames >= counters.next_log:
                window.log(loggers, progress, counters, last, **{"train/buffer_size": len(buffer)},
                           **({"train/stage": curriculum.stage} if curriculum.active else {}))
                while counters.next_log <= counters.frames:
                    counters.next_log += int(cfg.logger.every_frames)

            # periodic deterministic validation
            if counters.episodes >= counters.next_eval:
                eval_metrics = validate_all(eval_envs, policy, int(cfg.eval.episodes), int(cfg.eval.max_steps))
                log_metrics(loggers, eval_metrics, counters.frames)
                progress.eval_text = f"reward {eval_metrics['eval/reward']:.2f}, laps {eval_metrics['eval/laps']:.1f}"
                while counters.next_eval <= counters.episodes:
                    counters.next_eval += int(cfg.eval.every_episodes)
                promotion = curriculum.observe(eval_metrics, counters.frames, counters.episodes)
                if promotion:  # the next stage: rebuild the training env, its collector and the validation envs
                    env, collector, eval_envs = enter_stage(curriculum.config(cfg), counters.frames, env, collector, eval_envs,
                                                            policy, buffer)
                    batches = iter(collector)
                    _log_promotion(loggers, promotion, curriculum, run_dir)

            # checkpoint
            if counters.frames >= counters.next_ckpt or counters.frames >= total:
                every = int(cfg.checkpoint.every_frames) or total
                while counters.next_ckpt <= counters.frames:  # advanced first: a resumed run does not save again at once
                    counters.next_ckpt += every
                _save(cfg, ckpt_dir, meta, counters, loss, optim, policy, collector, env, eval_envs, buffer, threads, curriculum)
        progress.update(counters.frames, window.steps_per_s(counters), force=True)
        if cfg.buffer.save_at_end:
            save_dir_atomically(run_dir / "buffer_final", lambda d: buffer.dumps(str(d)))
    finally:
        progress.close()
        collector.shutdown()
        for e in (env, *eval_envs.values()):
            if not e.is_closed:
                e.close()
        for lg in loggers if "loggers" in locals() else []:
            exp = getattr(lg, "experiment", None)
            for f in getattr(exp, "files", {}).values():
                f.close()
    wall = time.perf_counter() - t_start
    result = {
        "frames": counters.frames,
        "updates": counters.updates,
        "episodes": counters.episodes,
        "wall_s": wall,
        "bytes_per_transition": buffer.bytes_per_transition,
        "bytes_per_final": buffer.bytes_per_final,
        "run_dir": str(run_dir),
        "checkpoint": str(latest_checkpoint(ckpt_dir)) if latest_checkpoint(ckpt_dir) else None,
        **{k: float(v) for k, v in last.items()},
        **eval_metrics,
        **({"train/stage": curriculum.stage, "train/stage_name": curriculum.name} if curriculum.active else {}),
    }
    print(f"[torcsrl] done: {counters.frames} steps, {counters.episodes} episodes in {wall:.1f} s; outputs in {run_dir}\n"
          f"[torcsrl] last checkpoint: {result['checkpoint']}\n"
          f"[torcsrl] resume: {resume_command(run_dir, 'total_frames=<more>')}", file=sys.stderr)
    if cfg.env.name == "race" and result["checkpoint"]:
        print(f"[torcsrl] evaluate: python -m torcsrl.evaluate --policy {run_dir} --track {_track_arg(cfg.env.track)} --laps 10   # compare runs here\n"
              f"[torcsrl] held-out, once a driver is chosen (never select on it): python -m torcsrl.evaluate --policy {run_dir} "
              "--track set:heldout --surface asphalt dirt --laps 10", file=sys.stderr)
    return result


def _track_arg(track) -> str:
    """``--track`` words for the training track(s)."""
    names = list(track) if isinstance(track, (list, tuple, ListConfig)) else [track]
    return " ".join(str(t) for t in names)


def _log_promotion(loggers, event: dict, curriculum: Curriculum, run_dir: Path, step: int | None = None) -> None:
    """A promotion: ``train/stage`` and ``curriculum/promotion`` (the number that met the criterion) logged at ``step``
    (default: its frame; the imitation loop logs against updates), a line on stderr, and ``<run_dir>/curriculum.json``
    rewritten (stages, current stage, every promotion)."""
    log_metrics(loggers, {"train/stage": event["stage"], "curriculum/promotion": event["value"]},
                event["frames"] if step is None else int(step))
    print(f"[torcsrl] curriculum: promoted from {event['from']!r} to stage {event['stage']} {event['to']!r} at {event['frames']} frames "
          f"({event['criterion']}: {event['value']:.3g} after {event['validations']} validations)", file=sys.stderr)
    _write_curriculum(curriculum, run_dir)


def _write_curriculum(curriculum: Curriculum, run_dir: Path) -> None:
    import json

    tmp = Path(run_dir) / "curriculum.json.tmp"
    tmp.write_text(json.dumps(curriculum.summary(), indent=2) + "\n")
    tmp.replace(Path(run_dir) / "curriculum.json")


def _resume_stage(cfg: DictConfig, ckpt_dir: Path, curriculum: Curriculum) -> None:
    """Put ``curriculum`` in the stage of the checkpoint this run resumes from, before the envs are built.
    CheckpointError (one line) when the checkpoint was written under other stages, or its stage's env settings differ
    from this config's at that stage. A checkpoint that cannot be read is left to :func:`_resume` to report."""
    path = latest_checkpoint(ckpt_dir) if cfg.checkpoint.resume == "latest" else Path(cfg.checkpoint.resume)
    if path is None or not path.is_file():
        return
    try:
        ck = load_checkpoint(path)
    except CheckpointError:
        return
    state = ck.get("curriculum")
    try:
        curriculum.load_state_dict(state, where=f"checkpoint {path}")
    except CurriculumError as err:
        raise CheckpointError(str(err)) from None
    if state:
        _check_same_env(curriculum.config(cfg), {"config": state["config"]}, path)


def _save(cfg, ckpt_dir, meta, counters, loss, optim, policy, collector, env, eval_envs, buffer, threads,
          curriculum: Curriculum | None = None) -> Path:
    path = checkpoint_path(ckpt_dir, counters.frames)
    stage_cfg = curriculum.config(cfg) if curriculum is not None else cfg  # this curriculum stage's env settings
    buffer_dir = None
    if cfg.checkpoint.buffer:
        buffer_dir = save_dir_atomically(path.with_name(path.stem + "_buffer"), lambda d: buffer.dumps(str(d))).name
    multi = isinstance(collector, MultiSyncCollector)
    payload = {
        "meta": {**meta, "pipeline": pipeline_record(stage_cfg, env)},
        "counters": asdict(counters),
        "loss": loss.state_dict(),
        "optim": {k: o.state_dict() for k, o in optim.items()},
        "policy": policy.state_dict(),
        "rng": rng_state(),
        "collector": {} if multi else {"state": collector.state_dict(), "env": _sim_state(env)},
        "eval_envs": {name: _sim_state(e) for name, e in eval_envs.items()},
        "buffer_dir": buffer_dir,
        "threads": threads,
        "config": OmegaConf.to_yaml(cfg),
    }
    if curriculum is not None and curriculum.active:  # the stage, its validations, the promotions; its env settings
        payload["curriculum"] = {**curriculum.state_dict(), "config": OmegaConf.to_yaml(
            {k: OmegaConf.to_container(stage_cfg[k], resolve=True) for k in RESUME_MUST_MATCH if k in stage_cfg})}
    save_checkpoint(path, payload)
    prune(ckpt_dir, int(cfg.checkpoint.keep))
    return path


def _resume(cfg, ckpt_dir, meta, loss, optim, policy, collector, env, eval_envs, buffer, run_dir) -> Counters:
    path, ck = resume_from(cfg.checkpoint.resume, ckpt_dir, meta, check=_buffer_intact)  # its replay buffer too
    _check_same_env(cfg, ck, path)
    loss.load_state_dict(ck["loss"])
    for k, o in optim.items():
        o.load_state_dict(ck["optim"][k])
    policy.load_state_dict(ck["policy"])
    if ck["collector"] and "carrier" in ck["collector"]:  # written by TorchRL's Collector (before StepCollector)
        ck["collector"]["state"] = {"frames": ck["collector"]["state"]["frames"], "carrier": ck["collector"]["carrier"]}
    if ck["collector"] and ck["collector"]["env"] is not None:
        collector.load_state_dict(ck["collector"]["state"])
        _set_sim_state(env, ck["collector"]["env"])
    elif ck["collector"]:  # the env cannot restore its simulation: keep its fresh episode, not the checkpoint's observation
        collector.load_state_dict(ck["collector"]["state"], carrier=False)
        print("[torcsrl] this env has no get_sim_state: the in-flight episode restarts (exact resume needs it)", file=sys.stderr)
    else:
        print("[torcsrl] resuming a multi-process collector: worker episodes restart (exact resume needs num_workers=0)", file=sys.stderr)
    saved = ck["eval_envs"] if "eval_envs" in ck else {"": ck["eval_env"]}  # "eval_env": before per-track validation
    if set(saved) != set(eval_envs):
        raise CheckpointError(f"checkpoint {path} validated on {sorted(saved) if list(saved) != [''] else 'one env'}, this config on "
                              f"{sorted(eval_envs) if list(eval_envs) != [''] else 'one env'} (eval.per_track / the track list changed)")
    for name, e in eval_envs.items():
        _set_sim_state(e, saved[name])
    if ck["buffer_dir"]:
        try:
            buffer.loads(str(path.parent / ck["buffer_dir"]), verified=True)  # checked above
        except ValueError as err:  # e.g. a TorchRL-format buffer from before torcsrl.utils.replay
            raise CheckpointError(f"checkpoint {path}: its replay buffer cannot be restored ({err})") from None
    if ck["threads"] != torch.get_num_threads():
        print(f"[torcsrl] using the checkpoint's {ck['threads']} threads (float results depend on it)", file=sys.stderr)
        torch.set_num_threads(int(ck["threads"]))
    counters = Counters(**ck["counters"])
    truncate_csv_after(run_dir, counters.frames)
    set_rng_state(ck["rng"])
    print(f"[torcsrl] resumed from {path} at {counters.frames} steps", file=sys.stderr)
    return counters


#: Config sections whose every value shapes the simulation a checkpoint restores (the env's and the degradations' state).
RESUME_MUST_MATCH = ("env", "degradation")


def _check_same_env(cfg: DictConfig, ck: dict, path: Path) -> None:
    """CheckpointError naming the differences when this run's env (or degradation) settings are not the checkpoint's:
    resuming restores the saved simulation into this run's env, which must be the same env."""
    saved_yaml = ck.get("config")
    if not saved_yaml:
        return
    saved = OmegaConf.create(saved_yaml)
    diffs: list[str] = []

    def flat(x: Any, pre: str) -> dict[str, Any]:
        if isinstance(x, dict):
            out: dict[str, Any] = {}
            for k, v in x.items():
                out.update(flat(v, f"{pre}.{k}"))
            return out or {pre: {}}
        return {pre: x}

    for section in RESUME_MUST_MATCH:
        try:
            old = flat(OmegaConf.to_container(saved[section], resolve=True) if section in saved else {}, section)
        except Exception:  # noqa: BLE001 - an interpolation of the old config that no longer resolves
            continue
        new = flat(OmegaConf.to_container(cfg[section], resolve=True) if section in cfg else {}, section)
        for k in sorted(set(old) | set(new)):
            if old.get(k) != new.get(k):
                diffs.append(f"{k}={old.get(k)!r} in the checkpoint, {new.get(k)!r} here")
    if diffs:
        more = f" (and {len(diffs) - 3} more)" if len(diffs) > 3 else ""
        raise CheckpointError(f"checkpoint {path} was written for another env: {'; '.join(diffs[:3])}{more}; resuming restores its "
                              "simulation into this run's env; allowed: the checkpoint's env settings, or a fresh run_dir")


def _buffer_intact(path: Path) -> None:
    """ValueError unless the replay buffer dump of the checkpoint ``path`` (if it has one) passes its checksums."""
    ck = load_checkpoint(path)
    if ck.get("buffer_dir"):
        ReplayBuffer.verify(path.parent / ck["buffer_dir"])


def main_entry() -> None:
    import hydra

    @hydra.main(config_path="conf", config_name="train", version_base="1.3")  # torcsrl/conf -> conf/ (torcsrl.config.CONF_DIR)
    def main(cfg: DictConfig) -> float | None:
        from torcsrl.config import objective, save_run_info, validate, write_metrics

        run_dir = None
        try:
            with graceful_termination():  # SIGTERM as Ctrl-C: train's finally blocks stop the collector's workers
                validate(cfg)  # unknown keys, wrong types, unknown names, severities: before anything is built (train checks too)
                run_dir = _run_dir(cfg)
                with claim_run_dir(run_dir, resume=bool(cfg.checkpoint.resume), overwrite=bool(cfg.overwrite)):  # before config.yaml
                    save_run_info(cfg, run_dir)  # config.yaml (resolved) + git_rev.txt
                    result = train(cfg)
                    write_metrics(run_dir, result)  # metrics.json, read by python -m torcsrl.sweep
                return objective(result, cfg.get("optimized_metric"))  # the value a sweeper (Optuna) optimises
        except (CheckpointError, ValueError, RuntimeError) as err:
            if isinstance(err, RuntimeError) and not isinstance(err, CheckpointError) and "cannot be imported" not in str(err):
                raise
            sys.exit(cli_error("torcsrl.train", err))
        except OSError as err:
            sys.exit(cli_error("torcsrl.train", err))
        except KeyboardInterrupt as err:
            last = latest_checkpoint(run_dir / "checkpoints") if run_dir is not None else None
            resume = (f"; last checkpoint {last}; resume: {resume_command(run_dir)}"
                      if last else "; no checkpoint was written yet")
            sys.exit(cli_error("torcsrl.train", err, stopped=f"workers stopped{resume}"))

    main()


if __name__ == "__main__":
    main_entry()
