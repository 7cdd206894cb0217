"""The on-policy loop (``algo=ppo``): collect a batch of rollouts, then several epochs of minibatches.

It reads in the order PPO runs, beside the off-policy loop (:mod:`torcsrl.training.offpolicy`; the pieces they share are
:mod:`torcsrl.training.common`'s): env (``env.num_cars`` cars in one world), agent (tanh-Gaussian actor, value network), loss
(TorchRL's ``ClipPPOLoss`` with ``GAE``, computed on tensors: :mod:`torcsrl.objectives.ppo`), collector (batches
of ``rollout_steps`` steps of every car, ``[cars, rollout_steps]``: :class:`~torcsrl.utils.collector.StepCollector` in
this process, or with ``collector.num_workers`` W >= 1 :class:`WorkerRollouts`, W processes of ``env.num_cars / W``
cars each, the policy's weights and observation statistics synced to them before every rollout; with
``collector.policy_lag=1`` they collect the next rollout during the update, APPO-style), optimisers; then
per batch: GAE advantages and value targets -> the batch as tensors (:meth:`~torcsrl.objectives.ppo.ClipPPOLoss.batch`)
-> ``epochs`` passes of shuffled minibatches of ``batch_size`` (:func:`torcsrl.agents.ppo.update`; one permutation an
epoch, the minibatches are its slices) -> the observation statistics take in the batch (after the epochs, so the update
sees the statistics the batch was collected with) -> the workers' policies synced -> log -> periodic deterministic
validation (the mean action) -> checkpoint.

Resuming restores networks (observation statistics included), optimisers, counters, every RNG, the collector's
in-flight step and the env's simulation: on CPU with an env that has ``get_sim_state`` a resumed run continues exactly
as the uninterrupted one would have. A checkpoint is written only between batches, so no rollout is ever half-kept.
With worker processes (as in the off-policy loop) a checkpoint keeps no in-flight episodes: a resumed run restores the
networks, optimisers, counters and the learner's RNG, and its workers start fresh episodes from their seeds.
"""

from __future__ import annotations

import functools
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.collectors import MultiAsyncCollector, MultiSyncCollector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torcsrl import agents
from torcsrl.agents.exploration import DeviceActorModule
from torcsrl.agents.ppo import log_std_start
from torcsrl.pipeline import actor_obs_keys, expected_meta, make_eval_envs, make_train_env, pipeline_record
from torcsrl.policies import load_policy
from torcsrl.training.common import (
    Counters,
    TrainState,
    TrainWindow,
    advance,
    check_same_env,
    close_loop,
    collector_state,
    finish_resume,
    make_networks,
    plain,
    restore_collector,
    restore_eval_envs,
    resume_command,
    sim_state,
    validate_all,
    wall_budget_s,
)
from torcsrl.training.ray_collectors import RayRollouts, joined_along_cars, make_ray_collector
from torcsrl.utils.checkpoint import checkpoint_path, latest_checkpoint, prune, resume_from, save_checkpoint
from torcsrl.utils.collector import StepCollector
from torcsrl.utils.logging import Progress, log_metrics, make_loggers
from torcsrl.utils.seeding import rng_state, seed_everything
from torcsrl.utils.threads import configure_threads, process_cpu_s

__all__ = ["train", "update", "set_learning_rates", "WorkerRollouts", "make_rollout_collector", "worker_config", "save", "resume"]


def train(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train ``algo=ppo`` on ``cfg.env`` in ``run_dir`` (held by :func:`torcsrl.training.train`); returns the final metrics."""
    workers = int(cfg.collector.num_workers)
    threads = configure_threads(cfg.threads, workers)
    seed_everything(int(cfg.seed))
    agent = agents.get(cfg.algo.name)
    obs_keys = actor_obs_keys(cfg)
    total = int(cfg.total_frames)
    device = torch.device(str(cfg.device))

    env = make_train_env(worker_config(cfg, workers), policy_loader=load_policy)  # with workers: one worker's cars (specs and the pipeline record only)
    actor, critic, loss = make_networks(cfg, agent, env, obs_keys, device)
    policy = agent.make_exploration(cfg.algo, actor, env, obs_keys)
    optim = agent.make_optimizers(cfg.algo, loss)
    cars = max(1, env.batch_size.numel()) * max(1, workers)
    collector = make_rollout_collector(cfg, env, policy, workers, threads)
    eval_envs = make_eval_envs(cfg, load_policy)
    eval_policy = TensorDictModule(actor, in_keys=obs_keys, out_keys=["action"]) if device.type == "cpu" else \
        DeviceActorModule(actor, obs_keys, ["action"], device)  # the mean action (CPU envs, actor on device)
    state = TrainState(cfg=cfg, run_dir=run_dir, meta=expected_meta(cfg, env, obs_keys), loss=loss, optim=optim,
                       collector=collector, env=env, eval_envs=eval_envs, threads=threads, counters=Counters.start(cfg),
                       actor=actor, critic=critic, policy=policy)
    if cfg.checkpoint.resume:
        state.counters = resume(state)
        collector.update_policy_weights_()  # worker processes: they act with the restored weights and statistics
    counters = state.counters
    loggers = make_loggers(cfg.logger["backends"], run_dir, cfg.logger.exp_name, cfg.logger.wandb_project, cfg.logger.wandb_mode)
    progress = Progress(total, enabled=bool(cfg.progress))
    print(f"[torcsrl] training ppo on env={cfg.env.name} ({cars} cars) for {total} steps; outputs in {run_dir}", file=sys.stderr)

    hot = plain(cfg.algo)
    epochs, minibatch = int(cfg.algo.epochs), int(cfg.algo.batch_size)
    target_kl = None if cfg.algo.get("target_kl") is None else float(cfg.algo.target_kl)
    base_lrs = {k: float(cfg.algo[f"{k}_lr"]) for k in optim}  # actor_lr, critic_lr: what lr_schedule scales
    std_schedule = log_std_schedule(actor, cfg.algo, total)
    std_schedule(counters.frames)  # the first rollout's std (a resumed run: the std its next rollout had)
    log_every, eval_every, ckpt_every = int(cfg.logger.every_frames), int(cfg.eval.every_episodes), int(cfg.checkpoint.every_frames) or total
    encoders = [(m.encoder, keys) for m, keys in ((actor, obs_keys), (critic, loss.critic_obs_keys)) if m.encoder.norm is not None]
    last: dict[str, Any] = {}
    eval_metrics: dict[str, float] = {}
    window = TrainWindow(counters)
    t_start = window.t_start
    max_wall_s = wall_budget_s(cfg)
    try:
        batches = iter(collector)
        while counters.frames < total:
            if max_wall_s and time.perf_counter() - t_start > max_wall_s:
                print(f"[torcsrl] wall-clock budget of {cfg.max_minutes} min reached at {counters.frames} steps", file=sys.stderr)
                save(state)
                break
            # collect a batch of rollouts: [cars, rollout_steps] (one car: [rollout_steps])
            data = next(batches)
            window.book(data, counters)
            counters.frames += data.numel()
            if device.type != "cpu":  # the rollout joins the networks (device=cuda): GAE, minibatches, statistics
                data = data.to(device, non_blocking=True)

            # update: epochs of shuffled minibatches of the rollout, then the observation statistics and the workers' policies
            set_learning_rates(optim, base_lrs, str(cfg.algo.get("lr_schedule", "constant")), counters.frames - data.numel(), total)
            last = update(agent, hot, loss, optim, data, epochs, minibatch, counters, target_kl) or last
            for enc, keys in encoders:
                enc.update_norm(*[data.get(k) for k in keys])
            std_schedule(counters.frames)  # the next rollout's std, sent with the weights
            collector.update_policy_weights_()

            # log
            if counters.frames >= counters.next_log:
                window.log(loggers, progress, counters, last, **({"time/worker_cpu_s": collector.cpu_s()} if workers else {}))
                counters.next_log = advance(counters.next_log, counters.frames, log_every)

            # periodic deterministic validation (the policy's mean action)
            if counters.episodes >= counters.next_eval:
                eval_metrics = validate_all(eval_envs, eval_policy, int(cfg.eval.episodes), int(cfg.eval.max_steps))
                log_metrics(loggers, eval_metrics, counters.frames)
                progress.eval_text = f"reward {eval_metrics['eval/reward']:.2f}, laps {eval_metrics['eval/laps']:.1f}"
                counters.next_eval = advance(counters.next_eval, counters.episodes, eval_every)

            # checkpoint
            if counters.frames >= counters.next_ckpt or counters.frames >= total:
                counters.next_ckpt = advance(counters.next_ckpt, counters.frames, ckpt_every)
                save(state)
        progress.update(counters.frames, window.steps_per_s(counters), force=True)
    finally:
        close_loop((env, *eval_envs.values()), loggers, collector, progress)
    wall = time.perf_counter() - t_start
    newest = latest_checkpoint(state.ckpt_dir)
    result = {"frames": counters.frames, "updates": counters.updates, "episodes": counters.episodes, "wall_s": wall,
              "run_dir": str(run_dir), "checkpoint": str(newest) if newest else None,
              **{k: float(v) for k, v in last.items()}, **eval_metrics}
    print(f"[torcsrl] done: {counters.frames} steps, {counters.episodes} episodes in {wall:.1f} s; outputs in {run_dir}\n"
          f"[torcsrl] resume: {resume_command(run_dir, 'total_frames=<more>')}", file=sys.stderr)
    return result


def update(agent, hot, loss, optim: dict, data: TensorDictBase, epochs: int, minibatch: int, counters: Counters,
           target_kl: float | None = None) -> dict:
    """PPO's update on one rollout: GAE advantages and value targets with the networks that collected it, then ``epochs``
    passes of shuffled minibatches of ``minibatch`` rows (the rollout as tensors once, shuffled once an epoch, sliced:
    views). With ``target_kl`` the epochs stop at the first minibatch whose approximate KL to the collecting policy
    exceeds ``1.5 * target_kl`` (SB3's rule; that minibatch's step is taken). Returns the last minibatch's metrics (with
    ``target_kl``: and ``train/epochs``, the epochs begun); empty when the rollout held no minibatch."""
    last: dict = {}
    with torch.no_grad():
        loss.value_estimator(data)
    batch = loss.batch(data)
    n = len(batch)
    for epoch in range(epochs):
        shuffled = batch[torch.randperm(n)]
        for start in range(0, n, minibatch):
            last = agent.update(hot, loss, optim, None, shuffled[start:start + minibatch], counters.updates)
            counters.updates += 1
            if target_kl is not None:
                last["train/epochs"] = torch.tensor(float(epoch + 1))
                if float(last["loss/kl_approx"]) > 1.5 * target_kl:
                    return last
    return last


def set_learning_rates(optim: dict, base_lrs: dict[str, float], schedule: str, frames: int, total: int) -> None:
    """``algo.lr_schedule`` before a rollout's update, ``frames`` the steps collected before that rollout: ``constant``
    leaves the optimisers alone; ``linear`` sets each to its base rate x ``(1 - frames / total)`` (CleanRL's
    ``anneal_lr``: the first update at the full rate, the rate reaching 0 at ``total_frames``). A function of the frame
    count, so a resumed run continues the same schedule."""
    if schedule == "constant":
        return
    if schedule != "linear":
        raise ValueError(f"algo.lr_schedule={schedule!r}: unknown schedule; allowed: constant, linear")
    frac = max(0.0, 1.0 - frames / max(1, total))
    for name, opt in optim.items():
        for group in opt.param_groups:
            group["lr"] = base_lrs[name] * frac


def log_std_schedule(actor, algo: DictConfig, total: int):
    """``algo.log_std_end``: a function of the frames collected that sets the actor's (state-independent) log std to
    ``log_std_init + (log_std_end - log_std_init) * min(1, frames / total)`` and keeps it out of the gradient, so the
    noise a rollout explores with is a schedule (annealed exploration) rather than learnt. It is set after an update,
    before the rollout it acts in, so PPO's ratio compares against the std that collected the data. ``null``: the std
    is learnt, and the function does nothing."""
    end = algo.get("log_std_end")
    if end is None:
        return lambda frames: None
    log_std = getattr(actor, "log_std", None)
    if not isinstance(log_std, torch.nn.Parameter):
        raise ValueError("algo.log_std_end: the actor has no state-independent log std to schedule; allowed: null")
    log_std.requires_grad_(False)
    start, end = log_std_start(algo.log_std_init, log_std.numel()), float(end)

    def set_std(frames: int) -> None:
        log_std.copy_(start + (end - start) * min(1.0, frames / max(1, total)))

    return set_std


def worker_config(cfg: DictConfig, workers: int) -> DictConfig:
    """``cfg`` with ``env.num_cars`` the cars of ONE of ``workers`` worker processes (``cfg`` itself without workers):
    ``env.num_cars`` stays the total, split evenly (a ValueError in one line when it does not divide;
    :func:`torcsrl.training.validate` refuses it before that)."""
    if workers < 1:
        return cfg
    cars = int(cfg.env.get("num_cars") or 1)
    if cars % workers:
        raise ValueError(f"collector.num_workers={workers}: algo=ppo splits env.num_cars={cars} cars evenly over the worker processes; "
                         f"allowed: a divisor of {cars} ({', '.join(str(d) for d in range(1, cars + 1) if cars % d == 0)}), or 0")
    return OmegaConf.merge(cfg, {"env": {"num_cars": cars // workers}})


def _worker_env(cfg: DictConfig, worker: int) -> EnvBase:
    """Worker ``worker``'s env, built in its process: :func:`~torcsrl.pipeline.make_train_env` (seed ``seed + 1000 (worker + 1)``),
    after seeding the process's torch generator (the policy's action draws) with the same seed."""
    torch.manual_seed(int(cfg.seed) + 1000 * (worker + 1))
    return make_train_env(cfg, worker, load_policy)


class WorkerRollouts:
    """PPO's batches from worker processes: TorchRL's ``MultiSyncCollector`` over ``workers`` batched envs of
    ``env.num_cars / workers`` cars, each collecting ``rollout_steps`` steps of its cars with the current policy, the
    batches of the workers joined along the cars: ``[num_cars, rollout_steps]`` (worker 0's cars first), as the
    in-process :class:`~torcsrl.utils.collector.StepCollector` gives them, so GAE runs along time per car.

    ``lag=1`` (``collector.policy_lag=1``): TorchRL's ``MultiAsyncCollector`` instead. A worker starts its next rollout
    as soon as it has handed one over, so the workers collect rollout k+1 while the learner updates on rollout k (the
    update and the env run on different cores at once). Each batch is ``workers`` worker batches as they arrive, joined
    along the cars (a batch may then hold two consecutive rollouts of one fast worker's cars: every row is still one
    car's contiguous steps). Rollout k+1 starts with the weights of update k-1; update k's weights reach the workers
    while they drive it (TorchRL's shared-memory sync applies them as they arrive). Every step carries the
    log-probability of its action as drawn, so PPO's ratio is taken against the policy that acted: the clipped
    objective with one rollout of policy lag, as in asynchronous PPO (APPO). Not bit-reproducible: where in a rollout
    the new weights land depends on timing.

    :meth:`update_policy_weights_` gives the workers the learner policy's parameters AND buffers (the observation
    statistics of :class:`~torcsrl.nets.RunningNorm`): TorchRL's shared-memory weight sync copies them into the shared
    buffers and waits for each worker to apply them. The loop calls it after every update (and after a resume), and
    the workers collect only when asked (``MultiSyncCollector``), so every rollout is collected with the weights of the
    update before it, as in one process."""

    def __init__(self, collector: MultiSyncCollector | MultiAsyncCollector, workers: int = 1):
        self.collector = collector
        self.lag = int(isinstance(collector, MultiAsyncCollector))
        self.workers = workers
        self._batches = None

    def __iter__(self):
        self._batches = iter(self.collector)
        return self

    def __next__(self) -> TensorDictBase:
        if self.lag:  # one worker's batch at a time, [cars a worker, T] (one car a worker: [T]): join `workers` of them
            return joined_along_cars([next(self._batches) for _ in range(self.workers)])
        data = next(self._batches)  # [workers, cars a worker, T]; one car a worker: [workers, T]
        data.names = None
        return data.flatten(0, 1) if data.ndim == 3 else data

    def update_policy_weights_(self) -> None:
        self.collector.update_policy_weights_()

    def cpu_s(self) -> float:
        """CPU seconds the worker processes have used so far (summed; ``time/worker_cpu_s`` in the logs)."""
        return sum(process_cpu_s(p.pid) for p in self.collector.procs)

    def worker_policy_states(self) -> list[dict]:
        """The ``state_dict()`` of each worker's policy, as the workers hold it (tests, checks)."""
        return self.collector.map_fn("policy.state_dict")

    def shutdown(self) -> None:
        self.collector.shutdown()


def make_rollout_collector(cfg: DictConfig, env: EnvBase, policy, workers: int, threads: int) -> StepCollector | WorkerRollouts | RayRollouts:
    """Batches of ``algo.rollout_steps`` steps of every car: in this process (:class:`StepCollector` on ``env``,
    ``collector.num_workers=0``) or from ``workers`` processes (:class:`WorkerRollouts`; ``env`` is then one worker's env,
    built here for its specs; with ``collector.ray`` set, :class:`~torcsrl.training.ray_collectors.RayRollouts`, the same
    workers as Ray actors). This process keeps its ``threads`` torch threads; each worker runs one."""
    steps_per_car = int(cfg.algo.rollout_steps)
    per_env = max(1, env.batch_size.numel()) * steps_per_car
    if workers < 1:
        return StepCollector(env, policy, per_env)
    wcfg = worker_config(cfg, workers)
    fns = [functools.partial(_worker_env, wcfg, i) for i in range(workers)]
    lag = int(cfg.collector.get("policy_lag", 0) or 0)
    if cfg.collector.get("ray"):  # the same worker envs as Ray actors (torcsrl.training.ray_collectors)
        return make_ray_collector(str(cfg.collector.ray), fns, policy, per_env, sync=not lag, exploration_type=ExplorationType.RANDOM,
                                  join_cars=True, resume_hint="checkpoint.resume=latest")
    common = dict(total_frames=-1, exploration_type=ExplorationType.RANDOM, num_threads=threads, num_sub_threads=1)
    if lag:  # the workers collect the next rollout during the update
        return WorkerRollouts(MultiAsyncCollector(fns, policy, frames_per_batch=per_env, **common), workers)
    return WorkerRollouts(MultiSyncCollector(fns, policy, frames_per_batch=per_env * workers, cat_results="stack", **common), workers)


def save(state: TrainState) -> Path:
    """A checkpoint of ``state`` at its frame count (the oldest beyond ``checkpoint.keep`` pruned): networks (observation
    statistics included), optimisers, counters, RNGs, the in-process collector's in-flight step and its env's simulation,
    the validation envs' simulations. Written only between batches: no rollout is ever half-kept."""
    cfg = state.cfg
    path = checkpoint_path(state.ckpt_dir, state.counters.frames)
    save_checkpoint(path, {
        "meta": {**state.meta, "pipeline": pipeline_record(cfg, state.env)},
        "counters": asdict(state.counters),
        "loss": state.loss.state_dict(),
        "actor": state.actor.state_dict(),  # what CheckpointPolicy and init.actor load (observation statistics included)
        "critic": state.critic.state_dict(),
        "optim": {k: o.state_dict() for k, o in state.optim.items()},
        "rng": rng_state(),
        # worker processes: their in-flight episodes are not kept (a resumed run restarts them), as for the off-policy loop
        "collector": collector_state(state.collector, state.env, isinstance(state.collector, StepCollector)),
        "eval_envs": {name: sim_state(e) for name, e in state.eval_envs.items()},
        "buffer_dir": None,
        "threads": state.threads,
        "config": OmegaConf.to_yaml(cfg),
    })
    prune(state.ckpt_dir, int(cfg.checkpoint.keep))
    return path


def resume(state: TrainState) -> Counters:
    """Restore ``state`` from the checkpoint ``checkpoint.resume`` names; returns the checkpoint's counters."""
    cfg = state.cfg
    path, ck = resume_from(cfg.checkpoint.resume, state.ckpt_dir, state.meta)
    check_same_env(cfg, ck, path)
    state.loss.load_state_dict(ck["loss"])
    state.actor.load_state_dict(ck["actor"])  # in place: the loss holds the same tensors
    state.critic.load_state_dict(ck["critic"])
    for k, o in state.optim.items():
        o.load_state_dict(ck["optim"][k])
    if not isinstance(state.collector, StepCollector) or not ck["collector"]:
        print("[torcsrl] resuming with (or from) worker processes: the in-flight episodes restart "
              "(exact resume needs collector.num_workers=0 before and after)", file=sys.stderr)
    else:
        restore_collector(state.collector, state.env, ck["collector"])
    restore_eval_envs(state.eval_envs, ck["eval_envs"], path,
                      f"checkpoint {path} validated on other envs than this config (eval.per_track / the track list changed)")
    return finish_resume(ck, path, state.run_dir)
