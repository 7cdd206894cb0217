"""What every training loop shares: counters, the log window, validation, networks, run folders, checkpoint state.

* :class:`Counters` (all in the checkpoint) and :class:`TrainWindow` (episodes booked from collected batches, one
  log line's rates and returns);
* :func:`validate` / :func:`validate_all`: Summers's deterministic validation, one episode loop with evaluate and
  report (:func:`torcsrl.evaluate.protocol.drive_episode`);
* :func:`make_networks` / :func:`init_actor`: actor, critic and loss of an actor-critic agent, the actor optionally
  started from a checkpoint's;
* :class:`TrainState`: what a checkpoint of an RL loop saves and a resume restores, as one object; the pieces both RL
  loops' ``save`` and ``resume`` use (:func:`collector_state`, :func:`restore_collector`, :func:`restore_eval_envs`,
  :func:`finish_resume`), the simulation state of an env and its degradations (:func:`sim_state`,
  :func:`set_sim_state`) and the check that a resumed run drives the checkpoint's env (:func:`check_same_env`);
* the run folder (:func:`resolve_run_dir`), the resume command (:func:`resume_command`), curriculum promotions
  (:func:`log_promotion`, :func:`write_curriculum`) and the loop's teardown (:func:`close_loop`).
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torcsrl.evaluate.protocol import drive_episode, lap_keys
from torcsrl.pipeline import critic_obs_keys, expected_meta, pipeline_record
from torcsrl.training.curriculum import Curriculum
from torcsrl.utils.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint
from torcsrl.utils.logging import log_metrics, truncate_csv_after
from torcsrl.utils.seeding import set_rng_state

__all__ = ["Counters", "TrainWindow", "TrainState", "validate", "validate_all", "plain", "make_networks", "init_actor",
           "resolve_run_dir", "resume_command", "RESUME_MUST_MATCH", "check_same_env", "sim_state", "set_sim_state",
           "collector_state", "restore_collector", "restore_eval_envs", "finish_resume", "log_promotion", "write_curriculum",
           "advance", "wall_budget_s", "close_loop"]


# ---------------------------------------------------------------------------------------
# counters and the log window
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

    @classmethod
    def start(cls, cfg: DictConfig) -> Counters:
        """A fresh run's counters: the first validation, checkpoint and log line scheduled from ``cfg``."""
        return cls(next_eval=int(cfg.eval.every_episodes), next_ckpt=int(cfg.checkpoint.every_frames) or int(cfg.total_frames),
                   next_log=int(cfg.logger.every_frames))


def advance(next_at: int, now: int, every: int) -> int:
    """The next time a periodic event is due: ``next_at`` moved on by ``every`` until it is past ``now``."""
    while next_at <= now:
        next_at += every
    return next_at


def wall_budget_s(cfg: DictConfig) -> float:
    """The loop's wall-clock budget [s] (``max_minutes``; 0: none)."""
    return 60.0 * float(cfg.max_minutes) if cfg.get("max_minutes") else 0.0


class TrainWindow:
    """The training logs' bookkeeping shared by the off-policy loop and PPO's: episodes finished in collected batches,
    and one log line's window (steps/s, updates/s since the last line)."""

    def __init__(self, counters: Counters) -> None:
        self.t_start, self.cpu_start = time.perf_counter(), time.process_time()
        self.t, self.frames, self.updates = self.t_start, counters.frames, counters.updates
        self.rewards: list[float] = counters.window_rewards  # the counters' own lists: they go into every checkpoint
        self.laps: list[float] = counters.window_laps

    def book(self, data, counters: Counters) -> None:
        """Count the episodes that end in ``data`` (a collected batch) and keep their returns and laps."""
        done = data["next", "done"].squeeze(-1)
        if done.any():
            self.rewards += data["next", "episode_reward"].squeeze(-1)[done].tolist()
            lap_key, _ = lap_keys(data["next"])
            if lap_key is not None:
                self.laps += data["next", lap_key].squeeze(-1)[done].tolist()
            counters.episodes += int(done.sum())

    def steps_per_s(self, counters: Counters) -> float:
        return (counters.frames - self.frames) / max(time.perf_counter() - self.t, 1e-9)

    def log(self, loggers, progress, counters: Counters, last: dict, **extra) -> None:
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


# ---------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------
@torch.no_grad()
def validate_all(envs: dict[str, EnvBase], policy, episodes: int, max_steps: int) -> dict[str, float]:
    """:func:`validate` on each validation env (:func:`torcsrl.pipeline.make_eval_envs`).

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
# networks
# ---------------------------------------------------------------------------------------
def plain(node: DictConfig) -> SimpleNamespace:
    """A config node as nested ``SimpleNamespace`` of plain values (attribute access without OmegaConf's cost)."""
    def conv(v):
        return SimpleNamespace(**{k: conv(x) for k, x in v.items()}) if isinstance(v, dict) else v

    return conv(OmegaConf.to_container(node, resolve=True))


def make_networks(cfg: DictConfig, agent, env: EnvBase, obs_keys: list[str], device: torch.device):
    """(actor, critic, loss) on ``device`` (``cfg.device``): the actor on ``obs_keys`` (started from ``init.actor``
    when set), the critic on :func:`~torcsrl.pipeline.critic_obs_keys` (the actor's when null), the loss over both.
    Built on the CPU and moved before the loss is made, so the loss's target copies are made on ``device`` too."""
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
    own_std = getattr(actor, "log_std", None)
    if isinstance(own_std, torch.nn.Parameter) and "log_std" not in sd:
        # a deterministic actor (TD3, BC, DAgger) starting PPO's tanh-Gaussian: its network is the mean (the same
        # tanh squash onto the bounds); the std starts where this run's algo.log_std_init puts it
        sd = {**sd, "log_std": own_std.detach().clone()}
    try:
        actor.load_state_dict(sd, strict=True)
    except RuntimeError as err:
        first = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
        raise ValueError(f"init.actor={path}: its actor network differs from this run's ({first[1] if len(first) > 1 else first[0]}); "
                         "allowed: the same algo.actor_hidden and algo.encoder as the checkpoint's config") from None
    print(f"[torcsrl] actor initialised from {path}", file=sys.stderr)
    return path


# ---------------------------------------------------------------------------------------
# run folder, resume command, curriculum promotions
# ---------------------------------------------------------------------------------------
def resolve_run_dir(cfg: DictConfig) -> Path:
    """The run's folder: ``run_dir``, else Hydra's output folder, else (outside ``@hydra.main``) a time-stamped
    ``outputs/train/<algo>/<time>``."""
    if cfg.run_dir:
        return Path(cfg.run_dir)
    try:
        from hydra.core.hydra_config import HydraConfig  # Hydra's runtime only where a run has no run_dir

        return Path(HydraConfig.get().runtime.output_dir)
    except ValueError:  # not under @hydra.main
        return Path("outputs") / "train" / cfg.algo.name / time.strftime("%Y-%m-%d_%H-%M-%S")


#: Command-line overrides a resume must not repeat (the resume sets its own run_dir / checkpoint.resume).
RESUME_DROPS = ("run_dir", "checkpoint.resume", "overwrite", "hydra.")


def resume_command(run_dir: Path | str, extra: str = "") -> str:
    """The shell command that resumes the run in ``run_dir``: this run's own command-line overrides (read from Hydra,
    so ``experiment=racer seed=1 env.surface=[...]`` come back; without them the resumed config would differ from the
    checkpoint's) + ``run_dir=<run_dir> checkpoint.resume=latest`` (+ ``extra``, e.g. ``total_frames=<more>``)."""
    try:
        from hydra.core.hydra_config import HydraConfig  # Hydra's runtime only when the command is printed

        task = list(HydraConfig.get().overrides.task)
    except ValueError:  # not under @hydra.main: the caller passed a config, not a command line
        task = []
    keep = [o for o in task if not o.lstrip("+~").startswith(RESUME_DROPS)]
    parts = ["python", "-m", "torcsrl.train", *keep, f"run_dir={run_dir}", "checkpoint.resume=latest"]
    return " ".join(shlex.quote(p) for p in parts) + (f" {extra}" if extra else "")


def log_promotion(loggers, event: dict, curriculum: Curriculum, run_dir: Path, step: int | None = None) -> None:
    """A promotion: ``train/stage`` and ``curriculum/promotion`` (the number that met the criterion) logged at ``step``
    (default: its frame; the imitation loop logs against updates), a line on stderr, and ``<run_dir>/curriculum.json``
    rewritten (stages, current stage, every promotion)."""
    log_metrics(loggers, {"train/stage": event["stage"], "curriculum/promotion": event["value"]},
                event["frames"] if step is None else int(step))
    print(f"[torcsrl] curriculum: promoted from {event['from']!r} to stage {event['stage']} {event['to']!r} at {event['frames']} frames "
          f"({event['criterion']}: {event['value']:.3g} after {event['validations']} validations)", file=sys.stderr)
    write_curriculum(curriculum, run_dir)


def write_curriculum(curriculum: Curriculum, run_dir: Path) -> None:
    """``<run_dir>/curriculum.json``: the stages, the current stage and the promotions (written atomically)."""
    tmp = Path(run_dir) / "curriculum.json.tmp"
    tmp.write_text(json.dumps(curriculum.summary(), indent=2) + "\n")
    tmp.replace(Path(run_dir) / "curriculum.json")


def close_loop(envs, loggers, collector=None, progress=None) -> None:
    """A loop's teardown: the progress line, the collector (its worker processes), every env still open and the
    loggers' files."""
    if progress is not None:
        progress.close()
    if collector is not None:
        collector.shutdown()
    for e in envs:
        if not e.is_closed:
            e.close()
    for lg in loggers:
        for f in getattr(getattr(lg, "experiment", None), "files", {}).values():
            f.close()


# ---------------------------------------------------------------------------------------
# checkpoint state
# ---------------------------------------------------------------------------------------
@dataclass
class TrainState:
    """What a checkpoint of an RL loop saves and a resume restores, as one object: the networks (``actor``, ``critic``,
    the ``loss`` holding both and their targets, the behaviour ``policy``), the ``optim`` dict, the ``buffer``, the
    ``collector`` and the envs it drives, the ``counters``, the torch ``threads`` the run computes with, the
    ``curriculum`` (its stage) and the run's ``cfg``, ``run_dir`` and ``meta`` (what a checkpoint must have been written
    for). The global generators' state is read when saving (:func:`torcsrl.utils.seeding.rng_state`)."""

    cfg: DictConfig
    run_dir: Path
    meta: dict
    loss: torch.nn.Module
    optim: dict
    collector: Any
    env: EnvBase
    eval_envs: dict[str, EnvBase]
    threads: int
    counters: Counters
    actor: torch.nn.Module | None = None
    critic: torch.nn.Module | None = None
    policy: torch.nn.Module | None = None
    buffer: Any = None
    curriculum: Curriculum | None = None

    @property
    def ckpt_dir(self) -> Path:
        return self.run_dir / "checkpoints"


#: Config sections whose every value shapes the simulation a checkpoint restores (the env's and the degradations' state).
RESUME_MUST_MATCH = ("env", "degradation")


def check_same_env(cfg: DictConfig, ck: dict, path: Path) -> None:
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


def _stateful_transforms(env: EnvBase) -> list:
    """The env's transforms that carry running state (degradations, frame stacks), in a fixed order."""
    t = getattr(env, "transform", None)
    return [m for m in t.modules() if hasattr(m, "get_sim_state")] if t is not None else []


def sim_state(env: EnvBase) -> dict | None:
    """The base env's simulation state and every degradation's generator and running state, or
    None when the base env cannot save its simulation."""
    base = getattr(env, "base_env", env)
    if not hasattr(base, "get_sim_state"):
        return None
    return {"base": base.get_sim_state(), "transforms": [m.get_sim_state() for m in _stateful_transforms(env)]}


def set_sim_state(env: EnvBase, state: dict | None) -> None:
    """Restore what :func:`sim_state` saved (nothing when ``state`` is None or the env cannot restore a simulation)."""
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


def collector_state(collector, env: EnvBase, in_process: bool) -> dict:
    """The checkpoint's ``collector`` entry: the in-process collector's state (its in-flight step) and its env's
    simulation; ``{}`` for worker processes (their in-flight episodes are not kept: a resumed run restarts them)."""
    return {"state": collector.state_dict(), "env": sim_state(env)} if in_process else {}


def restore_collector(collector, env: EnvBase, saved: dict) -> bool:
    """Restore the in-process collector and its env from the checkpoint's ``collector`` entry ``saved``. False when the
    env has no ``get_sim_state``: the collector keeps its fresh episode (not the checkpoint's observation) and a line
    says so."""
    if saved["env"] is not None:
        collector.load_state_dict(saved["state"])
        set_sim_state(env, saved["env"])
        return True
    collector.load_state_dict(saved["state"], carrier=False)
    print("[torcsrl] this env has no get_sim_state: the in-flight episode restarts (exact resume needs it)", file=sys.stderr)
    return False


def restore_eval_envs(eval_envs: dict[str, EnvBase], saved: dict, path: Path, what: str | None = None) -> None:
    """The validation envs' simulations from the checkpoint's ``eval_envs`` entry; CheckpointError (``what``, else one
    naming both sets of envs) when the checkpoint validated on other envs."""
    if set(saved) != set(eval_envs):
        raise CheckpointError(what or f"checkpoint {path} validated on {sorted(saved) if list(saved) != [''] else 'one env'}, this "
                              f"config on {sorted(eval_envs) if list(eval_envs) != [''] else 'one env'} (eval.per_track / the track list changed)")
    for name, e in eval_envs.items():
        set_sim_state(e, saved[name])


def finish_resume(ck: dict, path: Path, run_dir: Path) -> Counters:
    """The last steps of a resume: the checkpoint's torch threads (float results depend on them), its counters, the
    CSV logs cut after its frame, and the global generators' state (last: the state the next step starts from)."""
    if ck["threads"] != torch.get_num_threads():
        print(f"[torcsrl] using the checkpoint's {ck['threads']} threads (float results depend on it)", file=sys.stderr)
        torch.set_num_threads(int(ck["threads"]))
    counters = Counters(**ck["counters"])
    truncate_csv_after(run_dir, counters.frames)
    set_rng_state(ck["rng"])
    print(f"[torcsrl] resumed from {path} at {counters.frames} steps", file=sys.stderr)
    return counters

