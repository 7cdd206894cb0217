"""The imitation loop of ``algo=bc`` and ``algo=dagger`` (``python -m torcsrl.train algo=bc demos.frames=...``).

Reads like :func:`torcsrl.train.train`, without a critic: env (for the specs and validation), actor,
demonstrations (:func:`torcsrl.train.make_demos`), then fit -> validate -> checkpoint; DAgger repeats
(drive the learner with the expert mixed in, label with the expert, refit on everything) for
``demos.dagger_rounds`` rounds, the expert's share ``beta`` halving each round. ``init.actor`` starts the actor from
a checkpoint's (a student distilled before: same observations and scaling); with DAgger rounds, round 0 then only
validates it and every later round refits it on everything. Checkpoints hold the
actor in the same format as the RL agents', so ``evaluate``, ``report`` and ``policies export`` take them
as they are.

With a curriculum (``curriculum=...``, :mod:`torcsrl.curriculum`; ``algo=dagger`` only) the DAgger rounds follow its
stages: the demonstrations are written in the first stage's env, every round drives the current stage's env and is
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
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModule

__all__ = ["train"]


def train(cfg: DictConfig) -> dict[str, Any]:
    from torcsrl import agents
    from torcsrl.agents._build import bc_step
    from torcsrl.agents.exploration import DeviceActorModule
    from torcsrl.agents.networks import split_obs_keys
    from torcsrl.nets import shift_pad
    from torcsrl.demos import EXTRA_KEYS, PRIVILEGED_SLOTS, DemoError, label_rollouts, make_demo_env, mixed_sample
    from torcsrl.objectives.common import ObsUnpacker
    from torcsrl.curriculum import Curriculum
    from torcsrl.train import (_log_promotion, _run_dir, _set_sim_state, _sim_state, _write_curriculum, expected_meta, frame_history,
                               init_actor, make_demos, make_eval_envs, make_train_env, pipeline_record, validate_all)
    from torcsrl.utils.checkpoint import CheckpointError, checkpoint_path, latest_checkpoint, prune, save_checkpoint, save_dir_atomically
    from torcsrl.utils.logging import log_metrics, make_loggers, truncate_csv_after
    from torcsrl.utils.replay import ReplayBuffer
    from torcsrl.utils.seeding import rng_state, seed_everything, set_rng_state
    from torcsrl.utils.threads import configure_threads

    algo = str(cfg.algo.name)
    run_dir = _run_dir(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_dir = run_dir / "checkpoints"
    configure_threads(cfg.threads, 0)
    seed_everything(int(cfg.seed))
    agent = agents.get(algo)
    obs_keys = list(cfg.obs_keys or cfg.env.sensors)
    env = make_train_env(cfg)
    t_start = time.perf_counter()
    eval_envs: dict = {}
    loggers: list = []
    device = torch.device(str(cfg.device))  # the actor and its batches (device=cuda); envs and buffers stay on the CPU
    try:
        actor = agent.make_actor(cfg.algo, env, obs_keys)
        meta = {**expected_meta(cfg, env, obs_keys), "pipeline": pipeline_record(cfg, env)}
        ck = _resume_checkpoint(cfg, ckpt_dir, meta) if cfg.checkpoint.get("resume") else None
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
        eval_envs = make_eval_envs(curriculum.config(cfg))
        if curriculum.active:
            _write_curriculum(curriculum, run_dir)
            print(f"[torcsrl] curriculum: stage {curriculum.stage} {curriculum.name!r} of {', '.join(curriculum.names)}", file=sys.stderr)
        loggers = make_loggers(cfg.logger.backends, run_dir, cfg.logger.exp_name, cfg.logger.wandb_project, cfg.logger.wandb_mode)
        _, img = split_obs_keys(env.observation_spec, obs_keys)
        net = SimpleNamespace(actor_network=actor, obs=ObsUnpacker(obs_keys, img, shift_pad(cfg.algo.encoder.augment_shift)))
        policy = TensorDictModule(actor, in_keys=obs_keys, out_keys=["action"]) if device.type == "cpu" else \
            DeviceActorModule(actor, obs_keys, ["action"], device)
        learner = actor if device.type == "cpu" else (lambda *obs: actor(*(o.to(device) for o in obs)).cpu())
        buffers = [demos]
        aux_w = float(cfg.algo.get("aux_privileged", 0.0))
        aux = None
        grip_w = float(cfg.algo.get("grip_estimate", 0.0) or 0.0)
        if grip_w > 0 and "privileged" not in demos.extra_keys:
            raise DemoError(f"algo.grip_estimate={grip_w} regresses the rows' privileged mu, which the demonstrations hold no column of "
                            f"(extra keys {demos.extra_keys}); allowed: demonstrations written by this version, or grip_estimate=0")
        if aux_w > 0:  # auxiliary task: the encoder's features regress the teacher's privileged view (PRIVILEGED_SLOTS)
            if "privileged" not in demos.extra_keys:
                raise DemoError(f"algo.aux_privileged={aux_w} regresses the rows' privileged view, which the demonstrations hold no "
                                f"column of (extra keys {demos.extra_keys}); allowed: demonstrations written by this version, or aux_privileged=0")
            head = torch.nn.Linear(actor.encoder.out_dim, len(PRIVILEGED_SLOTS)).to(device)
            optim["actor"].add_param_group({"params": list(head.parameters())})
            aux = (head, aux_w)
        near_car, slow = _near_car(cfg, obs_keys), _slow(cfg, obs_keys)
        rounds = int(cfg.demos.dagger_rounds) if algo == "dagger" else 0
        steps_per_fit, batch_size, precision = int(cfg.algo.bc_steps), int(cfg.algo.batch_size), str(cfg.algo.precision)
        successor = float(cfg.algo.smooth.temporal) > 0  # only CAPS's temporal term reads the next observation
        lr_schedule = str(cfg.algo.get("bc_lr_schedule", "constant"))
        updates = frames = first = 0
        result: dict[str, Any] = {}
        rehearse = curriculum.rehearse  # an earlier stage's env driven beside every later round (conf/curriculum/none.yaml)
        round_rows = int(cfg.demos.dagger_frames) + (rehearse.frames if rehearse is not None else 0)
        new_rows = lambda: ReplayBuffer(round_rows, batch_size, obs_keys, extra_keys=EXTRA_KEYS,  # noqa: E731
                                        history=frame_history(cfg))
        rows_dir = run_dir / "dagger"
        if ck is not None:  # continue after the checkpoint's round, as the uninterrupted run would
            actor.load_state_dict(ck["actor"])
            for k, o in optim.items():
                o.load_state_dict(ck["optim"][k])
            if aux is not None:
                aux[0].load_state_dict(ck["aux_head"])
            updates, frames, first = int(ck["counters"]["updates"]), int(ck["counters"]["frames"]), int(ck["counters"]["round"]) + 1
            for rnd in range(1, first):  # the relabelled rows of the rounds before
                path = rows_dir / f"round_{rnd:03d}"
                if not (path / "meta.json").is_file():
                    raise CheckpointError(f"checkpoint {ck['path']} is after DAgger round {first - 1}, but {path} (round {rnd}'s "
                                          "relabelled rows) is missing; allowed: a run written with checkpoint.buffer=true, or a fresh run_dir")
                agg = new_rows()
                try:
                    agg.loads(path)
                except ValueError as err:
                    raise CheckpointError(str(err)) from None
                buffers.append(agg)
            for name, e in eval_envs.items():
                if name in ck.get("eval_envs", {}):
                    _set_sim_state(e, ck["eval_envs"][name])
            truncate_csv_after(run_dir, updates)
            set_rng_state(ck["rng"])
            print(f"[torcsrl] resumed from {ck['path']} after DAgger round {first - 1} ({updates} updates)", file=sys.stderr)

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
                    frames += rehearsed.frames
                    log_metrics(loggers, {"train/rehearsal_episodes": rstats["episodes"],
                                          "train/rehearsal_terminated": rstats["terminated"]}, updates)
                buffers.append(agg)
                if cfg.checkpoint.buffer:  # kept for a resume (the demonstrations are in their own folder already)
                    save_dir_atomically(rows_dir / f"round_{rnd:03d}", lambda d: agg.dumps(d))  # noqa: B023
                frames += int(cfg.demos.dagger_frames)
                log_metrics(loggers, {"train/dagger_round": rnd, "train/dagger_beta": beta, "train/episodes": stats["episodes"],
                                      "train/terminated": stats["terminated"]}, updates)
            t0 = time.perf_counter()
            # a fresh schedule per fit: the cosine restarts from actor_lr every DAgger round (SGDR-style)
            sched = None
            if lr_schedule == "cosine":
                for g in optim["actor"].param_groups:  # back to actor_lr (torch's cosine is chained: it starts from the current lr)
                    g["lr"] = g.setdefault("initial_lr", g["lr"])
                sched = torch.optim.lr_scheduler.CosineAnnealingLR(optim["actor"], steps_per_fit)
            fit = steps_per_fit if not (rnd == 0 and started is not None and rounds > 0) else 0  # DAgger on top of init.actor
            if started is not None and rnd == 0:
                print(f"[torcsrl] actor from {started}" + ("; DAgger rounds refit it (round 0 only validates it)" if fit == 0 else ""),
                      file=sys.stderr)
            for i in range(fit):
                bc, smooth = bc_step(net, optim, mixed_sample(buffers, batch_size, successor).to(device), precision, cfg.algo, aux, near_car, slow)
                if sched is not None:
                    with warnings.catch_warnings():  # FusedAdam.fast_step bypasses the step counter torch's check reads
                        warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step\\(\\)` before")
                        sched.step()
                updates += 1
                if updates % int(cfg.logger.every_frames) == 0:
                    log_metrics(loggers, {"loss/bc": float(bc), **{k: float(v) for k, v in smooth.items()}, "time/updates_per_s": (i + 1) / (time.perf_counter() - t0),
                                          "train/actor_lr": optim["actor"].param_groups[0]["lr"],
                                          "train/frames": frames, "train/buffer_size": sum(len(b) for b in buffers)}, updates)
            bc = float("nan") if fit == 0 else bc
            actor.eval()
            ev = validate_all(eval_envs, policy, int(cfg.eval.episodes), int(cfg.eval.max_steps))
            actor.train()
            log_metrics(loggers, {**ev, **({"train/stage": curriculum.stage} if curriculum.active else {})}, updates)
            print(f"[torcsrl] {algo} round {rnd}: loss/bc {float(bc):.4f}, eval/laps {ev['eval/laps']:.2f}, eval/reward {ev['eval/reward']:.1f}"
                  + (f", stage {curriculum.name!r}" if curriculum.active else ""), file=sys.stderr)
            payload = {"meta": meta, "actor": actor.state_dict(), "config": OmegaConf.to_yaml(cfg),
                       "counters": {"updates": updates, "frames": frames, "round": rnd},
                       "optim": {k: o.state_dict() for k, o in optim.items()}, **({"aux_head": aux[0].state_dict()} if aux else {})}
            if curriculum.active:
                promotion = curriculum.observe(ev, frames)
                if promotion is not None:  # the next round drives the next stage's env; its validation envs now
                    for e in eval_envs.values():
                        e.close()
                    eval_envs = make_eval_envs(curriculum.config(cfg))
                    _log_promotion(loggers, promotion, curriculum, run_dir, step=updates)
                payload["curriculum"] = curriculum.state_dict()
            payload["eval_envs"] = {name: _sim_state(e) for name, e in eval_envs.items()}
            payload["rng"] = rng_state()  # last: the state the next round starts from
            save_checkpoint(checkpoint_path(ckpt_dir, updates), payload)
            prune(ckpt_dir, int(cfg.checkpoint.keep))
            result = {"loss/bc": float(bc), **ev, **({"train/stage": curriculum.stage, "train/stage_name": curriculum.name}
                                                      if curriculum.active else {})}
    finally:
        for e in (env, *eval_envs.values()):
            if not e.is_closed:
                e.close()
        for lg in loggers:
            for f in getattr(getattr(lg, "experiment", None), "files", {}).values():
                f.close()
    wall = time.perf_counter() - t_start
    ck = latest_checkpoint(ckpt_dir)
    print(f"[torcsrl] done: {updates} updates in {wall:.1f} s; last checkpoint: {ck}\n"
          f"[torcsrl] evaluate: python -m torcsrl.evaluate --policy {run_dir} --track set:train --surface asphalt dirt --laps 10   # compare runs here\n"
          f"[torcsrl] held-out, once a driver is chosen (never select on it): python -m torcsrl.evaluate --policy {run_dir} "
          "--track set:heldout --surface asphalt dirt --laps 10", file=sys.stderr)
    return {"frames": frames, "updates": updates, "episodes": 0, "wall_s": wall, "run_dir": str(run_dir),
            "checkpoint": str(ck) if ck else None, **result}


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


def _near_car(cfg: DictConfig, obs_keys: list[str]) -> tuple[float, float] | None:
    """``(weight, reach)`` of :func:`torcsrl.agents._build.bc_step` from ``algo.bc_near_car_weight`` and
    ``algo.bc_near_car_m`` (the reach in metres, converted to the stored units of ``opponents``: /200 m when
    ``env.normalize``), or None when the weight is 1. ValueError (one line) when the actor reads no opponents sensor."""
    weight = _row_weight(cfg, "bc_near_car_weight", obs_keys, "opponents", "the opponents sensor")
    if weight is None:
        return None
    from torcsrl.envs.sensors import obs_scale

    reach_m = float(cfg.algo.get("bc_near_car_m", 15.0))
    return weight, reach_m / float(obs_scale("opponents")[0]) if _normalised(cfg) else reach_m


def _slow(cfg: DictConfig, obs_keys: list[str]) -> tuple[float, float, int, int] | None:
    """``(weight, below, slot, reading)`` of :func:`torcsrl.agents._build.bc_step` from ``algo.bc_slow_weight`` and
    ``algo.bc_slow_kmh`` (the speed in km/h, converted to the stored units of ``state``: divided by its scale when
    ``env.normalize``), or None when the weight is 1. ValueError (one line) when the actor reads no ``state``."""
    weight = _row_weight(cfg, "bc_slow_weight", obs_keys, "state", "the state's speedX_kmh")
    if weight is None:
        return None
    from torcsrl.envs.sensors import STATE_SCALE, STATE_SLOTS

    below = float(cfg.algo.get("bc_slow_kmh", 5.0))
    return (weight, below / float(STATE_SCALE["speedX_kmh"]) if _normalised(cfg) else below, STATE_SLOTS.index("speedX_kmh"),
            len(STATE_SLOTS))


def _resume_checkpoint(cfg: DictConfig, ckpt_dir: Path, meta: dict) -> dict:
    """The checkpoint an imitation run resumes from (``checkpoint.resume``: ``latest`` or a path), checked against this
    run's observations; its path under ``"path"``. CheckpointError (one line) when there is none, it is corrupt (naming
    the previous good one) or it was written before imitation runs could resume."""
    from torcsrl.train import _check_same_env
    from torcsrl.utils.checkpoint import CheckpointError, resume_from

    path, ck = resume_from(cfg.checkpoint.resume, ckpt_dir, meta)
    _check_same_env(cfg, ck, path)  # e.g. a resume command without the run's env.surface=[...]
    saved = OmegaConf.create(ck["config"]) if ck.get("config") else None
    if saved is not None and "demos" in saved and str(saved.demos.get("teacher")) != str(cfg.demos.get("teacher")):
        raise CheckpointError(f"checkpoint {path} was relabelled by demos.teacher={saved.demos.get('teacher')}, this config has "
                              f"{cfg.demos.get('teacher')}; allowed: the checkpoint's teacher, or a fresh run_dir")
    missing = [k for k in ("optim", "rng") if k not in ck] + ([] if "round" in ck.get("counters", {}) else ["counters.round"])
    if missing:
        raise CheckpointError(f"checkpoint {path} holds no {', '.join(missing)} (an imitation checkpoint written before imitation "
                              "runs could resume, or another loop's); allowed: a checkpoint of this version's algo=bc / dagger, or a fresh run_dir")
    return {**ck, "path": path}
