"""Expert demonstrations in the project's replay format, with DART noise; and the DAgger labeller.

``python -m torcsrl.demos [train overrides] demos.frames=50000 [demos.out=DIR]`` composes the training
config (``conf/train.yaml``: the same env, track distribution, sensors and observation pipeline a run
of that config trains on) and drives the scripted expert (:class:`torcsrl.policies.ExpertPolicy`) in
it (or, with ``demos.teacher=sensor``, the observation-explainable :class:`torcsrl.policies.SensorDriver`), writing every
transition into a :class:`~torcsrl.utils.replay.ReplayBuffer` folder (:func:`write_demos`). A training
run with ``demos.frames > 0`` writes them itself into ``<run_dir>/demos`` first (:func:`make_demos`);
``demos.path=DIR`` reuses a folder.

* **What is stored.** The observations exactly as the policy sees them (after the run's degradation
  stack and scaling: the same :func:`torcsrl.pipeline.observation_transforms`), the action *executed*
  (``action``: what the reward and the next observation followed from, for off-policy RL) and the
  expert's own action at that state (``expert_action``: the label for behaviour cloning).
* **DART** (Laskey et al. 2017): each episode draws a noise level ``sigma ~ U(0, sigma_max)``; the
  executed action is the expert's plus ``N(0, sigma^2)`` (clipped to [-1, 1]), so the data holds
  states off the expert's line and the expert's corrections from them.
* **DAgger** (Ross et al. 2011): :func:`label_rollouts` with a learner drives the learner's action
  (with probability ``1 - beta``) and stores the expert's label of the states the learner reaches.
* The expert reads the clean ``state`` (kept as ``state_clean`` before any degradation or scaling)
  and the lap position ``info/distFromStart``; it never reads the rangefinder.

``demos.json`` beside the buffer records the observation layout, the action size and the observation
pipeline; :func:`load_demos` refuses a folder whose layout or pipeline differs from the run's, with
one line naming both. :func:`check` is the demonstrations' part of the config check.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import step_mdp

from torcsrl.envs.sensors import PRIVILEGED_SLOTS, RANGE_M
from torcsrl.pipeline import (
    build_base_env,
    env_kwargs,
    frame_history,
    frame_layout,
    observation_transforms,
    pipeline_record,
    stored_keys,
    transformed,
)
from torcsrl.policies import (
    RACER_SPECS,
    EpisodeContext,
    ExpertPolicy,
    PolicyError,
    SensorDriver,
    SensorRacer,
    load_policy,
    racer_gains,
    sight_teacher,
)
from torcsrl.transforms import KeepClean
from torcsrl.utils.checkpoint import save_dir_atomically
from torcsrl.utils.replay import ReplayBuffer

__all__ = ["DemoError", "DemoPool", "EXTRA_KEYS", "PRIVILEGED_SLOTS", "TEACHERS", "check", "known_teacher", "make_demo_env",
           "make_teacher", "make_demos", "mixed_sample", "privileged_target", "label_rollouts", "write_demos", "load_demos"]

META = "demos.json"
EXTRA_KEYS = ("expert_action", "privileged")
#: Teachers that label demonstrations (:func:`make_teacher`).
TEACHERS = ("expert", "expert_centre", "sensor", "sensor_grip", "sensor_fast", "racer", "racer_bold", *RACER_SPECS,
            "sensor_sight[:<metres>]", "sensor_fast_sight[:<metres>]")


def known_teacher(name: str) -> bool:
    """Whether ``name`` is one of :data:`TEACHERS`: a plain name as listed, or a parametrised one (``racer_safe[:<gamma>]``
    listed) bare or with any ``:<value>`` (the value is checked where the teacher is built)."""
    base = name.split(":", 1)[0]
    return any(t.startswith(base + "[:") if "[:" in t else t == name for t in TEACHERS)


class DemoError(ValueError):
    """Demonstrations that cannot be used by this run (one line)."""


def check(c: Mapping) -> list[str]:
    """The demonstrations' problems in the plain training config ``c``, as config-check lines: an unknown teacher."""
    demos = c.get("demos")
    if isinstance(demos, Mapping) and "teacher" in demos and not known_teacher(str(demos["teacher"])):
        return [f"demos.teacher: unknown teacher {demos['teacher']!r}; allowed: {', '.join(TEACHERS)}"]
    return []


def make_demo_env(cfg: DictConfig, seed: int):
    """One car in the run's env (its tracks, procedural pool, surfaces), with the clean ``rangefinder`` and
    ``state`` kept as ``*_clean`` ahead of the run's observation transforms. The teacher reads those; they are
    added to the env when the run's sensors lack them (a camera student's teacher sees the full state: privileged
    distillation), and the student reads only its own ``obs_keys``."""
    if cfg.env.name != "race":
        raise DemoError(f"demonstrations need the race env (the expert drives a track); env.name={cfg.env.name!r}")
    sensors = list(cfg.env.sensors)
    need = ("rangefinder", "state")  # the teacher's inputs and the rows' privileged targets (PRIVILEGED_SLOTS)
    missing = tuple(k for k in need if k not in sensors)
    extra = {"sensors": tuple(sensors) + missing} if missing else {}
    kw = env_kwargs(cfg.env, seed=int(seed), device="cpu", num_cars=1,
                    max_steps=int(cfg.demos.episode_steps) if cfg.get("demos") else int(cfg.env.max_steps), **extra)
    base = build_base_env("race", kw, load_policy)
    clean = [k for k in ("rangefinder", "state", "opponents") if k in base.observation_spec.keys()]
    return transformed(base, [KeepClean(clean), *observation_transforms(cfg, base, seed=int(seed))])


@torch.no_grad()
def make_teacher(name: str):
    """The labelling policy: ``expert`` (:class:`~torcsrl.policies.ExpertPolicy`, racing line + speed profile from the
    track map), ``sensor`` (:class:`~torcsrl.policies.SensorDriver`, a function of the observation alone) or
    ``sensor_grip`` (the same driver told the friction under the car, ``("info", "surfaceMu")``: it brakes for
    the surface it is on — privileged knowledge a camera student can see and a rangefinder student cannot), reading
    the clean readings kept under ``*_clean``."""
    if name == "expert":
        return ExpertPolicy(state_key="state_clean")
    if name == "expert_centre":
        return ExpertPolicy(state_key="state_clean", line="centre")
    if name == "sensor":
        return SensorDriver(rangefinder_key="rangefinder_clean", state_key="state_clean")
    if name == "sensor_grip":
        return SensorDriver(decel_per_mu=SensorDriver.GRIP_DECEL_PER_MU, rangefinder_key="rangefinder_clean", state_key="state_clean")
    if name == "sensor_fast":
        return SensorDriver(**SensorDriver.FAST, rangefinder_key="rangefinder_clean", state_key="state_clean")
    if name in ("racer", "racer_bold"):  # reads the clean opponents sectors where the env has them (else: sensor_fast)
        bold = SensorRacer.BOLD if name == "racer_bold" else {}
        return SensorRacer(rangefinder_key="rangefinder_clean", state_key="state_clean", opponents_key="opponents_clean", **bold)
    try:
        racer = racer_gains(name)  # racer_safe / racer_clean / racer_keep / racer_yield: racer_bold with a low-grip margin
    except PolicyError as err:
        raise DemoError(f"demos.teacher={err}") from None
    if racer is not None:
        return SensorRacer(rangefinder_key="rangefinder_clean", state_key="state_clean", opponents_key="opponents_clean", **racer)
    try:
        sight = sight_teacher(name, rangefinder_key="rangefinder_clean", state_key="state_clean")
    except PolicyError as err:
        raise DemoError(f"demos.teacher={err}") from None
    if sight is not None:
        return sight
    raise DemoError(f"demos.teacher={name!r} is not known; allowed: {', '.join(TEACHERS)}")


def privileged_target(td) -> torch.Tensor:
    """The ``privileged`` row of a step (:data:`~torcsrl.envs.sensors.PRIVILEGED_SLOTS`) from the clean readings the teacher reads."""
    rf, st = td.get("rangefinder_clean"), td.get("state_clean")
    mu = td.get(("info", "surfaceMu")).reshape(*st.shape[:-1], 1).to(st.dtype)
    return torch.cat([rf / RANGE_M, st[..., :1] / np.pi, st[..., 1:2], mu], -1)


def label_rollouts(env, frames: int, buffer, *, sigma_max: float = 0.0, learner=None, beta: float = 1.0, seed: int = 0,
                   obs_keys: list[str] | None = None, progress: bool = False, teacher: str = "expert") -> dict[str, float]:
    """Drive ``frames`` env steps and store every transition with the expert's label in ``buffer``.

    Each step the expert (on the clean state) gives ``a*``; the executed action is ``a*`` plus
    ``N(0, sigma^2)`` (``sigma ~ U(0, sigma_max)`` per episode) with probability ``beta``, else the
    ``learner``'s action (DAgger). Returns episode statistics (episodes, laps, off-track ends).
    """
    base = getattr(env, "base_env", env)
    core = base.core
    expert = make_teacher(teacher)
    rng = np.random.default_rng([int(seed), 0x64656D6F])
    gen = torch.Generator().manual_seed(int(seed))
    keys = list(obs_keys or [])
    stats = {"episodes": 0, "terminated": 0, "laps": 0, "frames": 0}

    def new_episode():
        td = env.reset()
        expert.reset(EpisodeContext(track=core.car_tracks[0], seed=int(rng.integers(1 << 31)), dt=float(core.dt)))
        return td, float(rng.uniform(0.0, sigma_max)) if sigma_max > 0 else 0.0

    base.set_seed(int(seed))
    td, sigma = new_episode()
    t0 = time.perf_counter()
    for t in range(int(frames)):
        expert(td)
        label = td.get("action").clone()
        if learner is not None and rng.random() >= beta:
            act = learner(*(td.get(k) for k in keys)).reshape(label.shape)
        else:
            act = label + sigma * torch.randn(label.shape, generator=gen) if sigma > 0 else label.clone()
        td.set("action", act.clamp(-1.0, 1.0))
        td.set("expert_action", label.clamp(-1.0, 1.0))
        td.set("privileged", privileged_target(td))
        td = env.step(td)
        buffer.extend(td)
        nxt = td.get("next")
        if bool(nxt.get("done").reshape(-1)[0]):
            stats["episodes"] += 1
            stats["terminated"] += int(nxt.get("terminated").reshape(-1)[0])
            stats["laps"] += int(nxt.get(("info", "lap")).reshape(-1)[0])
            td, sigma = new_episode()
        else:
            td = step_mdp(td)
        if progress and (t + 1) % 5000 == 0:
            print(f"[torcsrl.demos] {t + 1}/{frames} frames, {stats['episodes']} episodes, "
                  f"{(t + 1) / (time.perf_counter() - t0):.0f} frames/s", file=sys.stderr)
    stats["frames"] = int(frames)
    return stats


def write_demos(cfg: DictConfig, out: str | Path, frames: int | None = None, seed: int | None = None) -> Path:
    """Write ``frames`` (default ``cfg.demos.frames``) DART demonstrations of the expert in the env of
    ``cfg`` to the folder ``out`` (replay buffer + ``demos.json``); returns ``out``."""
    d = cfg.demos
    frames = int(d.frames if frames is None else frames)
    if frames < 1:
        raise DemoError(f"demos.frames must be >= 1 to write demonstrations, got {frames}")
    seed = int(cfg.seed) + 7777 if seed is None else int(seed)
    out = Path(out)
    obs_keys = stored_keys(cfg)  # the actor's keys, and the critic's own where it sees more (asymmetric actor-critic)
    env = make_demo_env(cfg, seed)
    try:
        buffer = ReplayBuffer(frames, 1, obs_keys, extra_keys=EXTRA_KEYS, history=frame_history(cfg))
        t0 = time.perf_counter()
        stats = label_rollouts(env, frames, buffer, sigma_max=float(d.sigma_max), seed=seed, progress=True, teacher=str(d.teacher))
        record = pipeline_record(cfg, env)
    finally:
        env.close()
    buffer.dumps(out)
    meta = {"record": record, "frames": frames, "teacher": str(d.teacher), "sigma_max": float(d.sigma_max), "seed": seed, "stats": stats,
            "tracks": OmegaConf.to_container(cfg.env.track, resolve=True) if OmegaConf.is_config(cfg.env.track) else cfg.env.track,
            "procedural": OmegaConf.to_container(cfg.env.procedural, resolve=True) if OmegaConf.is_config(cfg.env.get("procedural")) else None,
            "surface": OmegaConf.to_container(cfg.env.surface, resolve=True) if OmegaConf.is_config(cfg.env.surface) else cfg.env.surface,
            "wall_s": time.perf_counter() - t0}
    (out / META).write_text(json.dumps(meta, indent=1))
    print(f"[torcsrl.demos] wrote {frames} frames ({stats['episodes']} episodes, {stats['terminated']} off the road) to {out} "
          f"in {meta['wall_s']:.0f} s", file=sys.stderr)
    return out


def load_demos(path: str | Path, record: dict[str, Any], batch_size: int, n_steps: int = 1, gamma: float = 0.99,
               keys: list[str] | None = None, history: dict[str, int] | None = None):
    """The demonstrations in ``path`` as a :class:`~torcsrl.utils.replay.ReplayBuffer`; :class:`DemoError`
    (one line) when the folder is missing, its observation layout / pipeline differs from ``record``, or its rows
    lack one of ``keys`` (what the run's transitions keep: an asymmetric critic's keys too). ``history``: the run's
    frame stacks (``{"pixels": K}``); the rows hold one frame each, so a folder written at any K is sampled at this one."""
    path = Path(path)
    try:
        meta = json.loads((path / META).read_text())
        buf_meta = json.loads((path / "meta.json").read_text())
    except (OSError, ValueError):
        raise DemoError(f"{path} is not a demonstration folder (no readable {META} / meta.json; write one with python -m torcsrl.demos)") from None
    theirs = meta["record"]
    if int(theirs.get("state_history") or 1) != int(record.get("state_history") or 1):  # rows hold the whole history
        raise DemoError(f"demonstrations {path} were written with state_history={int(theirs.get('state_history') or 1)}; this run has "
                        f"state_history={int(record.get('state_history') or 1)}; allowed: the folder's, or write them with this run's config")
    mine_frames = frame_layout(record.get("obs_layout"), record.get("frame_stack") or 1)
    their_frames = frame_layout(theirs.get("obs_layout"), theirs.get("frame_stack") or 1)
    if their_frames != mine_frames:  # one frame of each: the stack is a way of sampling the rows
        raise DemoError(f"demonstrations {path} were written with frames of {their_frames!r}; this run's frames are {mine_frames!r}")
    for k in ("action_dim", "normalize", "scales", "degradation", "control_hz", "substeps", "vehicle", "action_mode"):
        if theirs.get(k) != record.get(k):
            raise DemoError(f"demonstrations {path} were written with {k}={theirs.get(k)!r}; this run has {k}={record.get(k)!r}")
    missing = [k for k in (keys or []) if k not in buf_meta["obs_keys"]]
    if missing:
        raise DemoError(f"demonstrations {path} hold {list(buf_meta['obs_keys'])}; this run also needs {missing} (an asymmetric "
                        "critic's keys): write them with this run's config (python -m torcsrl.demos <its overrides>, or demos.frames=N)")
    buf = ReplayBuffer(int(buf_meta["capacity"]), int(batch_size), list(buf_meta["obs_keys"]), streams=int(buf_meta["streams"]),
                       n_steps=int(n_steps), gamma=float(gamma), extra_keys=list(buf_meta.get("extra_keys", [])),
                       history={k: v for k, v in (history or {}).items() if k in buf_meta["obs_keys"]})
    if "expert_action" not in buf.extra_keys:
        raise DemoError(f"demonstrations {path} hold no expert_action labels (extra keys {buf.extra_keys})")
    buf.loads(path)
    if len(buf) == 0:
        raise DemoError(f"demonstrations {path} are empty")
    return buf


def mixed_sample(buffers: list, batch_size: int, successor: bool = True):
    """A batch drawn from several buffers in proportion to their sizes (the keys they all hold); ``successor=False``:
    without ``next`` (:meth:`ReplayBuffer.sample`: the same rows)."""
    sizes = [len(b) for b in buffers]
    total = sum(sizes)
    counts = [batch_size * s // total for s in sizes]
    counts[0] += batch_size - sum(counts)
    parts = [b.sample(c, successor) for b, c in zip(buffers, counts) if c > 0]
    if len(parts) == 1:
        return parts[0]
    common = set(parts[0].keys(True, True)).intersection(*(p.keys(True, True) for p in parts[1:]))
    return torch.cat([p.select(*common) for p in parts], 0)


class DemoPool:
    """Several demonstration folders sampled as one (``demos.path=[DIR, DIR, ...]``): every batch draws from each
    folder in proportion to its rows, so shards written in parallel (``python -m torcsrl.demos seed=<k>`` on each
    core) train like one folder of their total size. Holds the keys all folders hold."""

    def __init__(self, buffers: list):
        if not buffers:
            raise DemoError("demos.path is an empty list; allowed: a folder or a list of folders written by python -m torcsrl.demos")
        self.buffers = list(buffers)
        self.batch_size = self.buffers[0].batch_size
        self.extra_keys = [k for k in self.buffers[0].extra_keys if all(k in b.extra_keys for b in self.buffers[1:])]

    def __len__(self) -> int:
        return sum(len(b) for b in self.buffers)

    def sample(self, batch_size: int | None = None, successor: bool = True):
        return mixed_sample(self.buffers, int(batch_size or self.batch_size), successor)


def make_demos(cfg: DictConfig, env, run_dir: Path) -> ReplayBuffer | DemoPool | None:
    """The demonstrations this run learns from, or None.

    ``demos.path``: a folder written by ``python -m torcsrl.demos``, or a list of them (shards written in parallel,
    sampled as one :class:`DemoPool`); else ``demos.frames > 0`` writes that many DART frames of the
    expert in this run's env into ``<run_dir>/demos`` (once: a resumed run reuses them), with the critic's own keys
    where it sees more than the actor (``critic_obs_keys``: TD3+BC / RLPD on an asymmetric actor-critic).
    Refused (one line) when their observation layout or pipeline differs from this run's, or they lack a key it stores."""
    d = cfg.get("demos")
    if d is None or (d.path in (None, "") and int(d.frames) <= 0):
        return None
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
