"""The off-policy loop (``algo=ddpg|td3|d4pg|sac``): collect -> extend -> update -> log -> validate -> checkpoint.

:func:`train` reads in the order the algorithm runs: env, agent (actor, critic), loss + target updater, behaviour
policy, buffer, demonstrations, collector, validation envs; then per batch of collected frames: the batch into the
replay buffer, ``frames x utd_ratio`` gradient steps (:class:`Learner`), a log line, the periodic deterministic
validation, a checkpoint.

Resuming (``checkpoint.resume=latest`` or a path, :func:`resume`) restores networks, targets, optimisers,
counters, every RNG (python, numpy, torch, the envs' generators), the exploration state, the
collector's in-flight episode and the replay buffer: on CPU with the in-process collector (and an
env with ``get_sim_state``, like the toy env) the resumed run continues exactly as the
uninterrupted one would have.

A curriculum (``curriculum=guppy|robust``, :mod:`torcsrl.training.curriculum`) trains in stages: the envs are built from
the current stage's config, and after a validation that meets the stage's criterion :func:`enter_stage` rebuilds the
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
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from torchrl.collectors import MultiSyncCollector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torcsrl import agents
from torcsrl.agents.bc import bc_step
from torcsrl.pipeline import (
    actor_obs_keys,
    critic_obs_keys,
    expected_meta,
    frame_history,
    make_eval_envs,
    make_train_env,
    obs_layout,
    pipeline_record,
    stored_keys,
)
from torcsrl.policies import load_policy
from torcsrl.training.common import (
    RESUME_MUST_MATCH,
    Counters,
    TrainState,
    TrainWindow,
    advance,
    check_same_env,
    close_loop,
    collector_state,
    finish_resume,
    log_promotion,
    make_networks,
    plain,
    restore_collector,
    restore_eval_envs,
    resume_command,
    sim_state,
    validate_all,
    wall_budget_s,
    write_curriculum,
)
from torcsrl.training.curriculum import Curriculum, CurriculumError
from torcsrl.training.demos import make_demos
from torcsrl.training.ray_collectors import make_ray_collector
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
from torcsrl.utils.faults import writable_folder
from torcsrl.utils.logging import Progress, log_metrics, make_loggers
from torcsrl.utils.replay import ReplayBuffer
from torcsrl.utils.seeding import rng_state, seed_everything
from torcsrl.utils.threads import configure_threads

__all__ = ["train", "Learner", "make_buffer", "make_collector", "enter_stage", "sample_batch", "pretrain", "streams", "save",
           "resume"]


def train(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train ``cfg.algo`` (ddpg, td3, d4pg, sac) on ``cfg.env`` in ``run_dir`` (held by :func:`torcsrl.training.train`);
    returns the final metrics (and where things were written)."""
    if cfg.buffer.storage == "disk":
        writable_folder(cfg.buffer.path or run_dir / "buffer", "buffer.path")
    ckpt_dir = run_dir / "checkpoints"
    threads = configure_threads(cfg.threads, int(cfg.collector.num_workers))
    seed_everything(int(cfg.seed))
    agent = agents.get(cfg.algo.name)
    obs_keys = actor_obs_keys(cfg)
    total = int(cfg.total_frames)
    device = torch.device(str(cfg.device))  # networks, losses, sampled batches; envs, collector and buffer stay on the CPU

    curriculum = Curriculum.from_config(cfg)  # conf/curriculum: ordered stages of env overrides (none: cfg itself)
    if cfg.checkpoint.resume:
        resume_stage(cfg, ckpt_dir, curriculum)  # an exact resume resumes the checkpoint's stage
    stage_cfg = curriculum.config(cfg)  # the env, validation and degradation settings of the current stage
    env = make_train_env(stage_cfg, policy_loader=load_policy)
    actor, critic, loss = make_networks(cfg, agent, env, obs_keys, device)
    target_updater = agent.make_target_updater(cfg.algo, loss)
    policy = agent.make_exploration(cfg.algo, actor, env, obs_keys)
    optim = agent.make_optimizers(cfg.algo, loss)
    buffer = make_buffer(cfg, run_dir)
    demos = make_demos(curriculum.config(cfg, stage=0), env, run_dir)  # written (once) in the first stage's env
    collector = make_collector(stage_cfg, env, policy)
    eval_envs = make_eval_envs(stage_cfg, load_policy)
    meta = {**expected_meta(cfg, env, obs_keys), "critic_obs_layout": obs_layout(env, critic_obs_keys(cfg))}
    state = TrainState(cfg=cfg, run_dir=run_dir, meta=meta, loss=loss, optim=optim, collector=collector, env=env,
                       eval_envs=eval_envs, threads=threads, counters=Counters.start(cfg), actor=actor, critic=critic,
                       policy=policy, buffer=buffer, curriculum=curriculum)
    if cfg.buffer.load:
        buffer.loads(str(cfg.buffer.load))
    if cfg.checkpoint.resume:
        state.counters = resume(state)
    counters = state.counters
    # cfg.logger["backends"], not .backends: Hydra's joblib launcher cloudpickles the entry's functions by value (it
    # runs as __main__), and an attribute named "backends" in a function that also uses `torch` makes cloudpickle try
    # to pickle the torch.backends module object, which cannot be pickled.
    loggers = make_loggers(cfg.logger["backends"], run_dir, cfg.logger.exp_name, cfg.logger.wandb_project, cfg.logger.wandb_mode)
    progress = Progress(total, enabled=bool(cfg.progress))
    print(f"[torcsrl] training {cfg.algo.name} on env={cfg.env.name} for {total} steps; outputs in {run_dir}", file=sys.stderr)
    if curriculum.active:
        write_curriculum(curriculum, run_dir)
        print(f"[torcsrl] curriculum: stage {curriculum.stage} {curriculum.name!r} of {', '.join(curriculum.names)}", file=sys.stderr)

    learner = Learner(cfg, agent, loss, optim, target_updater, buffer, demos, device)
    last: dict[str, Any] = {}
    if demos is not None and not counters.pretrained:
        last = pretrain(agent, learner.hot, loss, optim, target_updater, demos, int(cfg.demos.pretrain_steps),
                        int(cfg.demos.critic_pretrain_steps), str(cfg.algo.precision), device)
        counters.pretrained = True
    warmup, utd, multi = int(cfg.learner.warmup_frames), float(cfg.learner.utd_ratio), int(cfg.collector.num_workers) > 0
    log_every, eval_every, ckpt_every = int(cfg.logger.every_frames), int(cfg.eval.every_episodes), int(cfg.checkpoint.every_frames) or total
    eval_metrics: dict[str, float] = {}
    window = TrainWindow(counters)
    t_start = window.t_start
    max_wall_s = wall_budget_s(cfg)  # the loop's budget (demos and pre-training come before)
    try:
        batches = iter(state.collector)
        while counters.frames < total:
            if max_wall_s and time.perf_counter() - t_start > max_wall_s:  # the wall-clock budget: stop with a checkpoint
                print(f"[torcsrl] wall-clock budget of {cfg.max_minutes} min reached at {counters.frames} steps", file=sys.stderr)
                save(state)
                break
            # collect -> extend
            data = next(batches)
            window.book(data, counters)
            buffer.extend(data)
            counters.frames += data.numel()

            # update (configurable update-to-data ratio after the warm-up)
            if counters.frames >= warmup and len(buffer) >= learner.batch_size - learner.n_demo:
                counters.owed_updates += utd * data.numel()
                if learner.learn(int(counters.owed_updates), counters):
                    last = learner.merged
                counters.owed_updates -= int(counters.owed_updates)
                if multi:
                    state.collector.update_policy_weights_()

            # log
            if counters.frames >= counters.next_log:
                window.log(loggers, progress, counters, last, **{"train/buffer_size": len(buffer)},
                           **({"train/stage": curriculum.stage} if curriculum.active else {}))
                counters.next_log = advance(counters.next_log, counters.frames, log_every)

            # periodic deterministic validation
            if counters.episodes >= counters.next_eval:
                eval_metrics = validate_all(state.eval_envs, policy, int(cfg.eval.episodes), int(cfg.eval.max_steps))
                log_metrics(loggers, eval_metrics, counters.frames)
                progress.eval_text = f"reward {eval_metrics['eval/reward']:.2f}, laps {eval_metrics['eval/laps']:.1f}"
                counters.next_eval = advance(counters.next_eval, counters.episodes, eval_every)
                promotion = curriculum.observe(eval_metrics, counters.frames, counters.episodes)
                if promotion:  # the next stage: rebuild the training env, its collector and the validation envs
                    enter_stage(state, curriculum.config(cfg))
                    batches = iter(state.collector)
                    log_promotion(loggers, promotion, curriculum, run_dir)

            # checkpoint
            if counters.frames >= counters.next_ckpt or counters.frames >= total:
                counters.next_ckpt = advance(counters.next_ckpt, counters.frames, ckpt_every)  # first: a resumed run does not save again at once
                save(state)
        progress.update(counters.frames, window.steps_per_s(counters), force=True)
        if cfg.buffer.save_at_end:
            save_dir_atomically(run_dir / "buffer_final", lambda d: buffer.dumps(str(d)))
    finally:
        close_loop((state.env, *state.eval_envs.values()), loggers, state.collector, progress)
    wall = time.perf_counter() - t_start
    newest = latest_checkpoint(ckpt_dir)
    result = {
        "frames": counters.frames,
        "updates": counters.updates,
        "episodes": counters.episodes,
        "wall_s": wall,
        "bytes_per_transition": buffer.bytes_per_transition,
        "bytes_per_final": buffer.bytes_per_final,
        "run_dir": str(run_dir),
        "checkpoint": str(newest) if newest else None,
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


# ---------------------------------------------------------------------------------------
# buffer, collector, updates
# ---------------------------------------------------------------------------------------
def streams(cfg: DictConfig) -> int:
    """Parallel trajectories per env step: cars per env x env processes."""
    return max(1, int(cfg.env.get("num_cars", 1) or 1)) * max(1, int(cfg.collector.num_workers))


def make_buffer(cfg: DictConfig, run_dir: Path) -> ReplayBuffer:
    """Replay ring (``torcsrl/utils/replay.py``): every observation stored once (the actor's and the critic's keys,
    :func:`~torcsrl.pipeline.stored_keys`), n-step returns formed when sampling, RAM or memory-mapped disk storage,
    optionally prioritized."""
    b = cfg.buffer
    return ReplayBuffer(int(b.size), int(cfg.algo.batch_size), stored_keys(cfg), streams=streams(cfg),
                        n_steps=int(cfg.algo.n_steps), gamma=float(cfg.algo.gamma), storage=str(b.storage),
                        path=b.path or Path(run_dir) / "buffer", prioritized=bool(b.prioritized), alpha=float(b.alpha), beta=float(b.beta),
                        history=frame_history(cfg))


def make_collector(cfg: DictConfig, env: EnvBase, policy, collected: int = 0) -> StepCollector | MultiSyncCollector:
    """In-process :class:`StepCollector` (num_workers = 0) or TorchRL's MultiSyncCollector over ``num_workers`` env processes
    (with ``collector.ray`` set: the same workers as Ray actors, :func:`~torcsrl.training.ray_collectors.make_ray_collector`).
    ``collected``: frames collected before (a curriculum stage's new collector): they count towards ``init_random_frames``."""
    c = cfg.collector
    fpb = int(c.frames_per_batch or max(1, env.batch_size.numel()))  # null: one env step of every car
    if int(c.num_workers) == 0:
        collector = StepCollector(env, policy, fpb, int(c.init_random_frames))
        collector.frames = int(collected)
        return collector
    fns = [functools.partial(make_train_env, cfg, i, load_policy) for i in range(int(c.num_workers))]
    random_frames = max(0, int(c.init_random_frames) - int(collected))
    if c.get("ray"):  # the same worker envs as Ray actors (torcsrl.training.ray_collectors); random frames counted per worker
        return make_ray_collector(str(c.ray), fns, policy, fpb, exploration_type=ExplorationType.RANDOM,
                                  init_random_frames=-(-random_frames // len(fns)), resume_hint="checkpoint.resume=latest")
    return MultiSyncCollector(fns, policy, frames_per_batch=fpb * int(c.num_workers), total_frames=-1,
                              init_random_frames=random_frames,
                              exploration_type=ExplorationType.RANDOM,
                              # the learner keeps cfg.threads (TorchRL otherwise sets max(1, threads - workers) silently)
                              num_threads=torch.get_num_threads(), num_sub_threads=1)


def enter_stage(state: TrainState, cfg: DictConfig) -> None:
    """Move ``state`` to a new curriculum stage, ``cfg`` being the stage's config
    (:meth:`torcsrl.training.curriculum.Curriculum.config`): a new training env, its collector and the validation envs;
    the old ones are closed. The running episodes end here as time-limit truncations
    (:meth:`ReplayBuffer.end_episodes`): bootstrapped from their last observation, never joined to the new env's first.
    Networks, optimisers, buffer and exploration noise carry on (a stage never changes what they see)."""
    state.buffer.end_episodes()
    state.collector.shutdown()
    for e in (state.env, *state.eval_envs.values()):
        if not e.is_closed:
            e.close()
    state.env = make_train_env(cfg, policy_loader=load_policy)
    state.collector = make_collector(cfg, state.env, state.policy, collected=state.counters.frames)
    state.eval_envs = make_eval_envs(cfg, load_policy)


def sample_batch(buffer: ReplayBuffer, demos: ReplayBuffer | None, n_demo: int):
    """A training batch: all from ``buffer``, or (RLPD's symmetric sampling) ``n_demo`` demonstration rows
    LAST after the online ones; every row then carries ``expert_action`` (the online rows their own action)."""
    if demos is None or n_demo <= 0:
        return buffer.sample()
    on = buffer.sample(buffer.batch_size - n_demo)
    on.set("expert_action", on.get("action"))
    return torch.cat([on, demos.sample(n_demo).select(*on.keys(), strict=False)], 0)  # demo-only keys ("privileged") dropped


class Learner:
    """The gradient steps of the off-policy loop: a batch sampled (:func:`sample_batch`), moved to the networks'
    device, one ``agent.update`` (the critic alone for the first ``learner.critic_warmup_updates``), the priorities
    updated (prioritized replay). ``merged`` keeps the latest value of every loss key over the updates (what a log line
    shows): TD3's actor loss (and its TD3+BC terms) survive the critic-only steps of its policy delay. The hot loop
    reads plain values only (an OmegaConf lookup costs ~10 us)."""

    def __init__(self, cfg: DictConfig, agent, loss, optim: dict, target_updater, buffer: ReplayBuffer, demos, device: torch.device):
        self.agent, self.loss, self.optim, self.target_updater, self.buffer, self.demos = agent, loss, optim, target_updater, buffer, demos
        self.device, self.on_device = device, device.type != "cpu"
        self.batch_size = int(cfg.algo.batch_size)
        self.n_demo = int(round(self.batch_size * float(cfg.demos.ratio))) if demos is not None else 0
        self.critic_warmup = int(cfg.learner.get("critic_warmup_updates", 0) or 0)
        self.prioritized = bool(cfg.buffer.prioritized)
        self.hot = plain(cfg.algo)
        self.hot.n_demo, self.hot.bc_weight = self.n_demo, float(cfg.demos.bc_weight) if demos is not None else 0.0
        self.merged: dict[str, Any] = {}

    def learn(self, n: int, counters: Counters) -> bool:
        """``n`` gradient steps (``counters.updates`` counts them); whether any was taken."""
        for _ in range(n):
            batch = sample_batch(self.buffer, self.demos, self.n_demo)
            if self.on_device:
                batch = batch.to(self.device, non_blocking=True)
            if counters.updates >= self.critic_warmup:
                self.merged.update(self.agent.update(self.hot, self.loss, self.optim, self.target_updater, batch, counters.updates))
            else:  # the critic learns the (initialised) actor's values first
                self.merged.update(self.agent.update(self.hot, self.loss, self.optim, self.target_updater, batch, counters.updates,
                                                     actor=False))
                self.target_updater.step()
            if self.prioritized:
                self.buffer.update_tensordict_priority(batch)
            counters.updates += 1
        return n > 0


def pretrain(agent, hot, loss, optim, target_updater, demos: ReplayBuffer, bc_steps: int, critic_steps: int, precision: str,
             device: torch.device = torch.device("cpu")) -> dict:
    """Behaviour-clone the actor on the demonstrations, then fit the critic to it (actor frozen), targets synced."""
    out = {}
    for _ in range(int(bc_steps)):
        out["loss/bc"], _ = bc_step(loss, optim, demos.sample(successor=False).to(device), precision)  # no next: a plain BC loss
    with torch.no_grad():  # targets start as the pre-trained actor
        for tgt, src in zip(*target_updater._lists):
            tgt.copy_(src)
    for i in range(int(critic_steps)):
        out.update(agent.update(hot, loss, optim, target_updater, demos.sample().to(device), i, actor=False))
    return out


def _track_arg(track) -> str:
    """``--track`` words for the training track(s)."""
    names = list(track) if isinstance(track, (list, tuple, ListConfig)) else [track]
    return " ".join(str(t) for t in names)


# ---------------------------------------------------------------------------------------
# checkpoint
# ---------------------------------------------------------------------------------------
def save(state: TrainState) -> Path:
    """A checkpoint of ``state`` at its frame count (the oldest beyond ``checkpoint.keep`` pruned): networks, targets,
    optimisers, behaviour policy (exploration state), counters, RNGs, the in-process collector's in-flight step and its
    env's simulation, the validation envs' simulations, the replay buffer (``checkpoint.buffer``), the curriculum's stage."""
    cfg, counters, curriculum = state.cfg, state.counters, state.curriculum
    path = checkpoint_path(state.ckpt_dir, counters.frames)
    stage_cfg = curriculum.config(cfg) if curriculum is not None else cfg  # this curriculum stage's env settings
    buffer_dir = None
    if cfg.checkpoint.buffer:
        buffer_dir = save_dir_atomically(path.with_name(path.stem + "_buffer"), lambda d: state.buffer.dumps(str(d))).name
    in_process = isinstance(state.collector, StepCollector)  # worker processes or Ray actors: no in-flight state kept
    payload = {
        "meta": {**state.meta, "pipeline": pipeline_record(stage_cfg, state.env)},
        "counters": asdict(counters),
        "loss": state.loss.state_dict(),
        "optim": {k: o.state_dict() for k, o in state.optim.items()},
        "policy": state.policy.state_dict(),
        "rng": rng_state(),
        "collector": collector_state(state.collector, state.env, in_process),
        "eval_envs": {name: sim_state(e) for name, e in state.eval_envs.items()},
        "buffer_dir": buffer_dir,
        "threads": state.threads,
        "config": OmegaConf.to_yaml(cfg),
    }
    if curriculum is not None and curriculum.active:  # the stage, its validations, the promotions; its env settings
        payload["curriculum"] = {**curriculum.state_dict(), "config": OmegaConf.to_yaml(
            {k: OmegaConf.to_container(stage_cfg[k], resolve=True) for k in RESUME_MUST_MATCH if k in stage_cfg})}
    save_checkpoint(path, payload)
    prune(state.ckpt_dir, int(cfg.checkpoint.keep))
    return path


def resume(state: TrainState) -> Counters:
    """Restore ``state`` from the checkpoint ``checkpoint.resume`` names (its replay buffer verified first); returns the
    checkpoint's counters. CheckpointError (one line) when it was written for another env or other validation envs."""
    cfg = state.cfg
    path, ck = resume_from(cfg.checkpoint.resume, state.ckpt_dir, state.meta, check=_buffer_intact)  # its replay buffer too
    check_same_env(cfg, ck, path)
    state.loss.load_state_dict(ck["loss"])
    for k, o in state.optim.items():
        o.load_state_dict(ck["optim"][k])
    state.policy.load_state_dict(ck["policy"])
    if ck["collector"] and "carrier" in ck["collector"]:  # written by TorchRL's Collector (before StepCollector)
        ck["collector"]["state"] = {"frames": ck["collector"]["state"]["frames"], "carrier": ck["collector"]["carrier"]}
    if ck["collector"] and isinstance(state.collector, StepCollector):
        restore_collector(state.collector, state.env, ck["collector"])
    else:
        print("[torcsrl] resuming a multi-process collector: worker episodes restart (exact resume needs num_workers=0)", file=sys.stderr)
    restore_eval_envs(state.eval_envs, ck["eval_envs"] if "eval_envs" in ck else {"": ck["eval_env"]}, path)  # "eval_env": before per-track validation
    if ck["buffer_dir"]:
        try:
            state.buffer.loads(str(path.parent / ck["buffer_dir"]), verified=True)  # checked above
        except ValueError as err:  # e.g. a TorchRL-format buffer from before torcsrl.utils.replay
            raise CheckpointError(f"checkpoint {path}: its replay buffer cannot be restored ({err})") from None
    return finish_resume(ck, path, state.run_dir)


def resume_stage(cfg: DictConfig, ckpt_dir: Path, curriculum: Curriculum) -> None:
    """Put ``curriculum`` in the stage of the checkpoint this run resumes from, before the envs are built.
    CheckpointError (one line) when the checkpoint was written under other stages, or its stage's env settings differ
    from this config's at that stage. A checkpoint that cannot be read is left to :func:`resume` to report."""
    path = latest_checkpoint(ckpt_dir) if cfg.checkpoint.resume == "latest" else Path(cfg.checkpoint.resume)
    if path is None or not path.is_file():
        return
    try:
        ck = load_checkpoint(path)
    except CheckpointError:
        return
    saved = ck.get("curriculum")
    try:
        curriculum.load_state_dict(saved, where=f"checkpoint {path}")
    except CurriculumError as err:
        raise CheckpointError(str(err)) from None
    if saved:
        check_same_env(curriculum.config(cfg), {"config": saved["config"]}, path)


def _buffer_intact(path: Path) -> None:
    """ValueError unless the replay buffer dump of the checkpoint ``path`` (if it has one) passes its checksums."""
    ck = load_checkpoint(path)
    if ck.get("buffer_dir"):
        ReplayBuffer.verify(path.parent / ck["buffer_dir"])
