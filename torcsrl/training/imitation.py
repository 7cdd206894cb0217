"""The imitation loop of ``algo=bc`` and ``algo=dagger`` (``python -m torcsrl.train algo=bc demos.frames=...``).

Reads like the off-policy loop, without a critic: env (for the specs and validation), actor,
demonstrations (:func:`torcsrl.training.demos.make_demos`), then fit -> validate -> checkpoint; DAgger repeats
(drive the learner with the expert mixed in, label with the expert, refit on everything) for
``demos.dagger_rounds`` rounds, the expert's share ``beta`` halving each round. ``init.actor`` starts the actor from
a checkpoint's (a student distilled before: same observations and scaling); with DAgger rounds, round 0 then only
validates it and every later round refits it on everything. Checkpoints hold the
actor in the same format as the RL agents', so ``evaluate``, ``report`` and ``policies export`` take them
as they are.

With a curriculum (``curriculum=...``, :mod:`torcsrl.training.curriculum`; ``algo=dagger`` only) the DAgger rounds follow
its stages: the demonstrations are written in the first stage's env, every round drives the current stage's env and is
validated in its validation envs, and the stage's criterion reads each round's validation (one validation per round);
a promotion rebuilds the validation envs. With ``curriculum.rehearse: {stage, frames}`` every round after that stage
also drives ``frames`` in the rehearsed stage's env into the round's rows (``train/rehearsal_episodes``).
``train/stage`` is logged, ``<run_dir>/curriculum.json`` holds the promotions, and every checkpoint the curriculum's
state.

Resuming (``checkpoint.resume=latest`` or a path) continues after the checkpoint's round: the actor, its optimiser,
the global generators, the curriculum's stage and the validation envs' state come back, the demonstrations are read
again from their folder and each earlier DAgger round's relabelled rows from ``<run_dir>/dagger/round_<k>`` (written
atomically after every round's rollouts when ``checkpoint.buffer`` is on), so a killed run resumes exactly (CPU).
"""

from __future__ import annotations

import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModule
from torchrl.envs import EnvBase

from torcsrl import agents
from torcsrl.agents.bc import bc_step
from torcsrl.agents.exploration import DeviceActorModule
from torcsrl.envs.sensors import PRIVILEGED_SLOTS, STATE_SCALE, STATE_SLOTS
from torcsrl.nets import shift_pad, split_obs_keys
from torcsrl.objectives.common import ObsUnpacker
from torcsrl.pipeline import actor_obs_keys, expected_meta, frame_history, make_eval_envs, make_train_env, pipeline_record
from torcsrl.policies import load_policy
from torcsrl.training.common import (
    check_same_env,
    close_loop,
    init_actor,
    log_promotion,
    resolve_run_dir,
    set_sim_state,
    sim_state,
    validate_all,
    write_curriculum,
)
from torcsrl.training.curriculum import Curriculum
from torcsrl.training.demos import EXTRA_KEYS, DemoError, label_rollouts, make_demo_env, make_demos, mixed_sample
from torcsrl.transforms import obs_scale
from torcsrl.utils.checkpoint import (
    CheckpointError,
    checkpoint_path,
    latest_checkpoint,
    prune,
    resume_from,
    save_checkpoint,
    save_dir_atomically,
)
from torcsrl.utils.logging import log_metrics, make_loggers, truncate_csv_after
from torcsrl.utils.replay import ReplayBuffer
from torcsrl.utils.seeding import rng_state, seed_everything, set_rng_state
from torcsrl.utils.threads import configure_threads

__all__ = ["train", "ImitationState", "save", "resume", "near_car_setting", "slow_setting"]


@dataclass
class ImitationState:
    """What an imitation checkpoint saves and a resume restores, as one object: the ``actor``, its ``optim`` dict (and the
    auxiliary ``aux_head``, ``algo.aux_privileged``), the ``curriculum`` (its stage), the validation envs, the counters
    (``updates``, ``frames`` and the last finished DAgger ``round``) and the rows relabelled by each DAgger round
    (``rows``; the demonstrations are read again from their folder). The global generators' state is read when saving."""

    cfg: DictConfig
    run_dir: Path
    meta: dict
    actor: torch.nn.Module
    optim: dict
    curriculum: Curriculum
    eval_envs: dict[str, EnvBase]
    aux_head: torch.nn.Module | None = None
    rows: list = field(default_factory=list)
    updates: int = 0
    frames: int = 0
    round: int = -1

    @property
    def ckpt_dir(self) -> Path:
        return self.run_dir / "checkpoints"

    @property
    def rows_dir(self) -> Path:
        return self.run_dir / "dagger"


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit ``algo=bc`` (one fit) or ``algo=dagger`` (a fit, then ``demos.dagger_rounds`` rounds) on the demonstrations;
    returns the final metrics (and where things were written)."""
    algo = str(cfg.algo.name)
    run_dir = resolve_run_dir(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    configure_threads(cfg.threads, 0)
    seed_everything(int(cfg.seed))
    agent = agents.get(algo)
    obs_keys = actor_obs_keys(cfg)
    env = make_train_env(cfg, policy_loader=load_policy)
    t_start = time.perf_counter()
    eval_envs: dict = {}
    loggers: list = []
    device = torch.device(str(cfg.device))  # the actor and its batches (device=cuda); envs and buffers stay on the CPU
    state = None
    try:
        actor = agent.make_actor(cfg.algo, env, obs_keys)
        meta = {**expected_meta(cfg, env, obs_keys), "pipeline": pipeline_record(cfg, env)}
        ck = resume_checkpoint(cfg, run_dir / "checkpoints", meta) if cfg.checkpoint.get("resume") else None
        init = cfg.get("init")
        started = init_actor(str(init.actor), actor, cfg, env, obs_keys) if ck is None and init is not None and init.get("actor") else None
        actor = actor.to(device)
        optim = agent.make_optimizers(cfg.algo, actor)
        curriculum = Curriculum.from_config(cfg)  # DAgger rounds follow its stages (none: cfg itself)
        if ck is not None and ck.get("curriculum") is not None:
            curriculum.load_state_dict(ck["curriculum"], where=f"checkpoint {ck['path']}")
        demos = make_demos(curriculum.config(cfg, stage=0), env, run_dir)
        if demos is None:
            raise ValueError(f"algo={algo} imitates demonstrations: set demos.frames > 0 (written for this run) or demos.path")
        eval_envs = make_eval_envs(curriculum.config(cfg), load_policy)
        if curriculum.active:
            write_curriculum(curriculum, run_dir)
            print(f"[torcsrl] curriculum: stage {curriculum.stage} {curriculum.name!r} of {', '.join(curriculum.names)}", file=sys.stderr)
        loggers = make_loggers(cfg.logger.backends, run_dir, cfg.logger.exp_name, cfg.logger.wandb_project, cfg.logger.wandb_mode)
        _, img = split_obs_keys(env.observation_spec, obs_keys)
        net = SimpleNamespace(actor_network=actor, obs=ObsUnpacker(obs_keys, img, shift_pad(cfg.algo.encoder.augment_shift)))
        policy = TensorDictModule(actor, in_keys=obs_keys, out_keys=["action"]) if device.type == "cpu" else \
            DeviceActorModule(actor, obs_keys, ["action"], device)
        learner = actor if device.type == "cpu" else (lambda *obs: actor(*(o.to(device) for o in obs)).cpu())
        aux = make_aux_head(cfg, actor, optim, demos, device)
        state = ImitationState(cfg=cfg, run_dir=run_dir, meta=meta, actor=actor, optim=optim, curriculum=curriculum,
                               eval_envs=eval_envs, aux_head=aux[0] if aux else None)
        near_car, slow = near_car_setting(cfg, obs_keys), slow_setting(cfg, obs_keys)
        rounds = int(cfg.demos.dagger_rounds) if algo == "dagger" else 0
        steps_per_fit, batch_size, precision = int(cfg.algo.bc_steps), int(cfg.algo.batch_size), str(cfg.algo.precision)
        successor = float(cfg.algo.smooth.temporal) > 0  # only CAPS's temporal term reads the next observation
        lr_schedule = str(cfg.algo.get("bc_lr_schedule", "constant"))
        result: dict[str, Any] = {}
        rehearse = curriculum.rehearse  # an earlier stage's env driven beside every later round (conf/curriculum/none.yaml)
        round_rows = int(cfg.demos.dagger_frames) + (rehearse.frames if rehearse is not None else 0)
        new_rows = lambda: ReplayBuffer(round_rows, batch_size, obs_keys, extra_keys=EXTRA_KEYS,  # noqa: E731
                                        history=frame_history(cfg))
        if ck is not None:  # continue after the checkpoint's round, as the uninterrupted run would
            resume(state, ck, new_rows)
        first = state.round + 1

        def drive(stage_cfg: DictConfig, seed: int, n: int, rows, beta: float) -> dict[str, float]:
            """``n`` frames of ``stage_cfg``'s env into ``rows``: the learner drives (the teacher's noisy action with
            probability ``beta``), the teacher labels every state."""
            denv = make_demo_env(stage_cfg, seed)
            try:
                actor.eval()
                return label_rollouts(denv, n, rows, sigma_max=float(cfg.demos.sigma_max), learner=learner, beta=beta, seed=seed,
                                      obs_keys=obs_keys, teacher=str(cfg.demos.teacher))
            finally:
                actor.train()
                denv.close()

        print(f"[torcsrl] imitation ({algo}) on {len(demos)} demonstration frames, {rounds} DAgger rounds; outputs in {run_dir}", file=sys.stderr)
        for rnd in range(first, rounds + 1):
            if rnd > 0:  # DAgger: the learner drives (the expert's noisy action with probability beta), the expert labels
                beta = float(cfg.demos.dagger_beta) * 0.5 ** (rnd - 1)
                agg = new_rows()
                stats = drive(curriculum.config(cfg), int(cfg.seed) + 31 * rnd, int(cfg.demos.dagger_frames), agg, beta)
                rehearsed = curriculum.rehearsal()
                if rehearsed is not None:  # the rehearsed stage's env, its own seed
                    rstats = drive(curriculum.rehearsal_config(cfg), int(cfg.seed) + 31 * rnd + 17, rehearsed.frames, agg, beta)
                    state.frames += rehearsed.frames
                    log_metrics(loggers, {"train/rehearsal_episodes": rstats["episodes"],
                                          "train/rehearsal_terminated": rstats["terminated"]}, state.updates)
                state.rows.append(agg)
                if cfg.checkpoint.buffer:  # kept for a resume (the demonstrations are in their own folder already)
                    save_dir_atomically(state.rows_dir / f"round_{rnd:03d}", lambda d: agg.dumps(d))  # noqa: B023
                state.frames += int(cfg.demos.dagger_frames)
                log_metrics(loggers, {"train/dagger_round": rnd, "train/dagger_beta": beta, "train/episodes": stats["episodes"],
                                      "train/terminated": stats["terminated"]}, state.updates)
            # fit: on the demonstrations and every round's rows (DAgger on top of init.actor: round 0 only validates it)
            fit = steps_per_fit if not (rnd == 0 and started is not None and rounds > 0) else 0
            if started is not None and rnd == 0:
                print(f"[torcsrl] actor from {started}" + ("; DAgger rounds refit it (round 0 only validates it)" if fit == 0 else ""),
                      file=sys.stderr)
            sched = make_lr_schedule(optim["actor"], lr_schedule, steps_per_fit)
            t0 = time.perf_counter()
            buffers = [demos, *state.rows]
            for i in range(fit):
                bc, smooth = bc_step(net, optim, mixed_sample(buffers, batch_size, successor).to(device), precision, cfg.algo, aux, near_car, slow)
                if sched is not None:
                    with warnings.catch_warnings():  # FusedAdam.fast_step bypasses the step counter torch's check reads
                        warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step\\(\\)` before")
                        sched.step()
                state.updates += 1
                if state.updates % int(cfg.logger.every_frames) == 0:
                    log_metrics(loggers, {"loss/bc": float(bc), **{k: float(v) for k, v in smooth.items()}, "time/updates_per_s": (i + 1) / (time.perf_counter() - t0),
                                          "train/actor_lr": optim["actor"].param_groups[0]["lr"],
                                          "train/frames": state.frames, "train/buffer_size": sum(len(b) for b in buffers)}, state.updates)
            bc = float("nan") if fit == 0 else bc
            # validate
            actor.eval()
            ev = validate_all(state.eval_envs, policy, int(cfg.eval.episodes), int(cfg.eval.max_steps))
            actor.train()
            log_metrics(loggers, {**ev, **({"train/stage": curriculum.stage} if curriculum.active else {})}, state.updates)
            print(f"[torcsrl] {algo} round {rnd}: loss/bc {float(bc):.4f}, eval/laps {ev['eval/laps']:.2f}, eval/reward {ev['eval/reward']:.1f}"
                  + (f", stage {curriculum.name!r}" if curriculum.active else ""), file=sys.stderr)
            # promote (the next round drives the next stage's env; its validation envs now)
            if curriculum.active:
                promotion = curriculum.observe(ev, state.frames)
                if promotion is not None:
                    for e in state.eval_envs.values():
                        e.close()
                    state.eval_envs = eval_envs = make_eval_envs(curriculum.config(cfg), load_policy)
                    log_promotion(loggers, promotion, curriculum, run_dir, step=state.updates)
            # checkpoint
            state.round = rnd
            save(state)
            result = {"loss/bc": float(bc), **ev, **({"train/stage": curriculum.stage, "train/stage_name": curriculum.name}
                                                      if curriculum.active else {})}
    finally:
        close_loop((env, *(state.eval_envs if state is not None else eval_envs).values()), loggers)
    wall = time.perf_counter() - t_start
    ck = latest_checkpoint(run_dir / "checkpoints")
    print(f"[torcsrl] done: {state.updates} updates in {wall:.1f} s; last checkpoint: {ck}\n"
          f"[torcsrl] evaluate: python -m torcsrl.evaluate --policy {run_dir} --track set:train --surface asphalt dirt --laps 10   # compare runs here\n"
          f"[torcsrl] held-out, once a driver is chosen (never select on it): python -m torcsrl.evaluate --policy {run_dir} "
          "--track set:heldout --surface asphalt dirt --laps 10", file=sys.stderr)
    return {"frames": state.frames, "updates": state.updates, "episodes": 0, "wall_s": wall, "run_dir": str(run_dir),
            "checkpoint": str(ck) if ck else None, **result}


def make_aux_head(cfg: DictConfig, actor, optim: dict, demos, device: torch.device) -> tuple[torch.nn.Module, float] | None:
    """``(head, weight)`` of the auxiliary task (``algo.aux_privileged`` > 0): the encoder's features regress the teacher's
    privileged view (:data:`~torcsrl.envs.sensors.PRIVILEGED_SLOTS`), the head's parameters added to the actor's
    optimiser; None when off. DemoError (one line) when the demonstrations hold no privileged column that
    ``algo.aux_privileged`` or ``algo.grip_estimate`` needs."""
    aux_w = float(cfg.algo.get("aux_privileged", 0.0))
    grip_w = float(cfg.algo.get("grip_estimate", 0.0) or 0.0)
    if grip_w > 0 and "privileged" not in demos.extra_keys:
        raise DemoError(f"algo.grip_estimate={grip_w} regresses the rows' privileged mu, which the demonstrations hold no column of "
                        f"(extra keys {demos.extra_keys}); allowed: demonstrations written by this version, or grip_estimate=0")
    if aux_w <= 0:
        return None
    if "privileged" not in demos.extra_keys:
        raise DemoError(f"algo.aux_privileged={aux_w} regresses the rows' privileged view, which the demonstrations hold no "
                        f"column of (extra keys {demos.extra_keys}); allowed: demonstrations written by this version, or aux_privileged=0")
    head = torch.nn.Linear(actor.encoder.out_dim, len(PRIVILEGED_SLOTS)).to(device)
    optim["actor"].add_param_group({"params": list(head.parameters())})
    return head, aux_w


def make_lr_schedule(opt: torch.optim.Optimizer, schedule: str, steps: int):
    """The learning-rate schedule of one fit (``algo.bc_lr_schedule``): None (constant), or a cosine from ``actor_lr`` to 0
    over ``steps`` that restarts every DAgger round (SGDR-style)."""
    if schedule != "cosine":
        return None
    for g in opt.param_groups:  # back to actor_lr (torch's cosine is chained: it starts from the current lr)
        g["lr"] = g.setdefault("initial_lr", g["lr"])
    return torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)


def _row_weight(cfg: DictConfig, key: str, obs_keys: list[str], sensor: str, by: str) -> float | None:
    """``algo.<key>``, a per-row weight of the imitation loss read from observation ``sensor``: None when it is 1;
    ValueError (one line) when the actor does not read ``sensor``."""
    weight = float(cfg.algo.get(key, 1.0))
    if weight == 1.0:
        return None
    if sensor not in obs_keys:
        raise ValueError(f"algo.{key}={weight} weighs the rows by {by}, which the actor does not read (its keys {obs_keys}); "
                         f"allowed: 1.0, or env.sensors with {sensor}")
    return weight


def _normalised(cfg: DictConfig) -> bool:
    return cfg.env.name == "race" and bool(cfg.env.get("normalize", True))


def near_car_setting(cfg: DictConfig, obs_keys: list[str]) -> tuple[float, float] | None:
    """``(weight, reach)`` of :func:`torcsrl.agents.bc.bc_step` from ``algo.bc_near_car_weight`` and
    ``algo.bc_near_car_m`` (the reach in metres, converted to the stored units of ``opponents``: /200 m when
    ``env.normalize``), or None when the weight is 1. ValueError (one line) when the actor reads no opponents sensor."""
    weight = _row_weight(cfg, "bc_near_car_weight", obs_keys, "opponents", "the opponents sensor")
    if weight is None:
        return None
    reach_m = float(cfg.algo.get("bc_near_car_m", 15.0))
    return weight, reach_m / float(obs_scale("opponents")[0]) if _normalised(cfg) else reach_m


def slow_setting(cfg: DictConfig, obs_keys: list[str]) -> tuple[float, float, int, int] | None:
    """``(weight, below, slot, reading)`` of :func:`torcsrl.agents.bc.bc_step` from ``algo.bc_slow_weight`` and
    ``algo.bc_slow_kmh`` (the speed in km/h, converted to the stored units of ``state``: divided by its scale when
    ``env.normalize``), or None when the weight is 1. ValueError (one line) when the actor reads no ``state``."""
    weight = _row_weight(cfg, "bc_slow_weight", obs_keys, "state", "the state's speedX_kmh")
    if weight is None:
        return None
    below = float(cfg.algo.get("bc_slow_kmh", 5.0))
    return (weight, below / float(STATE_SCALE["speedX_kmh"]) if _normalised(cfg) else below, STATE_SLOTS.index("speedX_kmh"),
            len(STATE_SLOTS))


# ---------------------------------------------------------------------------------------
# checkpoint
# ---------------------------------------------------------------------------------------
def save(state: ImitationState) -> Path:
    """The checkpoint after ``state.round`` (at its update count; the oldest beyond ``checkpoint.keep`` pruned): the actor
    in the RL agents' format, its optimiser, the counters, the curriculum's stage, the validation envs' simulations and
    the global generators' state (last: the state the next round starts from)."""
    cfg = state.cfg
    payload = {"meta": state.meta, "actor": state.actor.state_dict(), "config": OmegaConf.to_yaml(cfg),
               "counters": {"updates": state.updates, "frames": state.frames, "round": state.round},
               "optim": {k: o.state_dict() for k, o in state.optim.items()},
               **({"aux_head": state.aux_head.state_dict()} if state.aux_head is not None else {})}
    if state.curriculum.active:
        payload["curriculum"] = state.curriculum.state_dict()
    payload["eval_envs"] = {name: sim_state(e) for name, e in state.eval_envs.items()}
    payload["rng"] = rng_state()
    path = checkpoint_path(state.ckpt_dir, state.updates)
    save_checkpoint(path, payload)
    prune(state.ckpt_dir, int(cfg.checkpoint.keep))
    return path


def resume(state: ImitationState, ck: dict, new_rows) -> None:
    """Restore ``state`` from the checkpoint ``ck`` (:func:`resume_checkpoint`): the actor, its optimiser (and auxiliary
    head), the counters, each earlier DAgger round's relabelled rows (``new_rows()`` makes an empty round), the
    validation envs' simulations, the CSV logs cut after its update and the global generators' state.
    CheckpointError (one line) when a round's rows are missing."""
    state.actor.load_state_dict(ck["actor"])
    for k, o in state.optim.items():
        o.load_state_dict(ck["optim"][k])
    if state.aux_head is not None:
        state.aux_head.load_state_dict(ck["aux_head"])
    state.updates, state.frames, state.round = int(ck["counters"]["updates"]), int(ck["counters"]["frames"]), int(ck["counters"]["round"])
    for rnd in range(1, state.round + 1):  # the relabelled rows of the rounds before
        path = state.rows_dir / f"round_{rnd:03d}"
        if not (path / "meta.json").is_file():
            raise CheckpointError(f"checkpoint {ck['path']} is after DAgger round {state.round}, but {path} (round {rnd}'s "
                                  "relabelled rows) is missing; allowed: a run written with checkpoint.buffer=true, or a fresh run_dir")
        agg = new_rows()
        try:
            agg.loads(path)
        except ValueError as err:
            raise CheckpointError(str(err)) from None
        state.rows.append(agg)
    for name, e in state.eval_envs.items():
        if name in ck.get("eval_envs", {}):
            set_sim_state(e, ck["eval_envs"][name])
    truncate_csv_after(state.run_dir, state.updates)
    set_rng_state(ck["rng"])
    print(f"[torcsrl] resumed from {ck['path']} after DAgger round {state.round} ({state.updates} updates)", file=sys.stderr)


def resume_checkpoint(cfg: DictConfig, ckpt_dir: Path, meta: dict) -> dict:
    """The checkpoint an imitation run resumes from (``checkpoint.resume``: ``latest`` or a path), checked against this
    run's observations; its path under ``"path"``. CheckpointError (one line) when there is none, it is corrupt (naming
    the previous good one) or it was written before imitation runs could resume."""
    path, ck = resume_from(cfg.checkpoint.resume, ckpt_dir, meta)
    check_same_env(cfg, ck, path)  # e.g. a resume command without the run's env.surface=[...]
    saved = OmegaConf.create(ck["config"]) if ck.get("config") else None
    if saved is not None and "demos" in saved and str(saved.demos.get("teacher")) != str(cfg.demos.get("teacher")):
        raise CheckpointError(f"checkpoint {path} was relabelled by demos.teacher={saved.demos.get('teacher')}, this config has "
                              f"{cfg.demos.get('teacher')}; allowed: the checkpoint's teacher, or a fresh run_dir")
    missing = [k for k in ("optim", "rng") if k not in ck] + ([] if "round" in ck.get("counters", {}) else ["counters.round"])
    if missing:
        raise CheckpointError(f"checkpoint {path} holds no {', '.join(missing)} (an imitation checkpoint written before imitation "
                              "runs could resume, or another loop's); allowed: a checkpoint of this version's algo=bc / dagger, or a fresh run_dir")
    return {**ck, "path": path}
