"""Training-loop throughput: our DDPG / TD3 / D4PG / SAC loops vs Stable-Baselines3 (TD3; SAC for SAC) on Pendulum-v1,
and our PPO vs SB3's PPO with its ``SubprocVecEnv`` on the race env at the same number of cars (``--algos ppo``).

Same settings for all: 256x256 actor and critic, batch 256, one gradient step per env step
(TD3: actor every 2), one env, after a warm-up of random steps. Steps/s are env steps per
wall-clock second of the whole loop (collect + store + sample + update), measured after the
warm-up, for each torch thread count asked for.

A contender ``<algo>+bf16`` runs ``<algo>`` with ``algo.precision=bfloat16`` (mixed-precision
updates; fast only where the CPU has bfloat16 units, which the header line reports); ``ppo+w2`` runs PPO with
``collector.num_workers=2`` (the same ``--cars`` split over 2 worker processes); they combine: ``ppo+w2+bf16``;
``ppo+w1+lag`` adds ``collector.policy_lag=1`` (the worker collects the next rollout while the learner updates).

The box is shared, so absolute figures drift with the load. What counts is the RATIO to SB3
measured side by side: each round runs every contender once (SB3 first on even rounds, last
on odd ones), a round's ratios compare runs seconds apart, and the table gives the median
over rounds. SB3 is used when importable (``pip install stable-baselines3``, the ``[bench]``
extra; a ``--target /tmp/peers`` install is picked up too).

PPO (``--algos ppo``): env frames per wall second while training on the oval (the training config's 10 Hz race env,
``--cars`` cars: ours in one batched world, or ``ppo+wN`` in N worker processes of ``--cars / N`` cars; SB3's as
``SubprocVecEnv`` processes of ``torcsrl/Race-v0``), rollouts of ``--ppo-rollout`` steps a car, 10 epochs of minibatches
of 64, 256x256 nets, compared with SB3 PPO at the same settings. CPU seconds are summed over the processes: ours with
its workers (``time/worker_cpu_s``), SB3's with its ``SubprocVecEnv`` processes.

    python benchmarks/train_throughput.py [--steps 1500] [--warmup 500] [--threads 1 2] [--rounds 3] [--algos td3 sac d4pg td3+bf16]
    python benchmarks/train_throughput.py --algos ppo ppo+w2 ppo+w2+bf16 --cars 16 --steps 8192 --threads 1 [--ppo-rollout 128]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
if os.path.isdir("/tmp/peers"):
    sys.path.append("/tmp/peers")

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from torcsrl.training import train  # noqa: E402
from torcsrl.utils.logging import read_csv_metric  # noqa: E402
from torcsrl.utils.threads import process_cpu_s  # noqa: E402

TARGETS = {"td3": 1.25, "d4pg": 1.0, "sac": 1.1, "ppo": 3.0}
#: The SB3 peer of each of our algorithms (at the same settings).
PEER = {"ddpg": "TD3", "td3": "TD3", "d4pg": "TD3", "sac": "SAC", "ppo": "PPO"}


def cpu_bf16() -> str:
    """Which bfloat16 units this CPU has (from /proc/cpuinfo), e.g. ``avx512_bf16``; ``none`` if none."""
    try:
        flags = set(open("/proc/cpuinfo").read().split())
    except OSError:
        return "unknown"
    found = sorted(f for f in flags if f in ("avx512_bf16", "amx_bf16", "avx_ne_convert"))
    return ", ".join(found) or "none"


def ours(name: str, threads: int, steps: int, warmup: int, extra: list[str], cars: int = 1, rollout: int = 128) -> tuple[float, float]:
    """(steps per wall second, steps per CPU second) of ``torcsrl.train.train`` after the warm-up (from its log; CPU
    seconds of the learner and, with workers, of its worker processes).

    ``name``: an algorithm, with ``+bf16`` for its mixed-precision updates and (PPO) ``+w<N>`` for N worker processes,
    ``+lag`` for one rollout of policy lag, ``+numpy`` / ``+python`` / ``+numba`` for the car physics' backend."""
    algo, *variants = name.split("+")
    for v in variants:
        if v == "bf16":
            extra = [*extra, "algo.precision=bfloat16"]
        elif v[:1] == "w" and v[1:].isdigit() and algo == "ppo":
            extra = [*extra, f"collector.num_workers={int(v[1:])}"]
        elif v == "lag" and algo == "ppo":
            extra = [*extra, "collector.policy_lag=1"]
        elif v in ("numpy", "python", "numba") and algo == "ppo":  # the car physics' backend (default: auto)
            extra = [*extra, f"env.vehicle_backend={v}"]
        else:
            raise SystemExit(f"unknown contender {name!r}; allowed: <algo>, <algo>+bf16, ppo+w<N>[+lag][+bf16][+numpy|+python|+numba]")
    run = tempfile.mkdtemp(prefix=f"tp_{algo}_")
    every = max(50, steps // 5)
    if algo == "ppo":  # the race env, cars in one world; frames counted over all cars
        every = cars * rollout
        warmup = every  # the first rollout (and its update) is the warm-up
        env = ["env.track=oval", f"env.num_cars={cars}", f"algo.rollout_steps={rollout}", "algo.batch_size=64", "algo.epochs=10"]
    else:
        env = ["env.name=gym", "+env.id=Pendulum-v1", "env.sensors=[observation]", "algo.batch_size=256", "collector.frames_per_batch=1"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[
            f"algo={algo}", *env, f"run_dir={run}",
            f"threads={threads}", f"total_frames={warmup + steps}", f"collector.init_random_frames={0 if algo == 'ppo' else warmup}",
            f"learner.warmup_frames={warmup}",
            "algo.actor_hidden=[256,256]", "algo.critic_hidden=[256,256]", "eval.every_episodes=1000000",
            "checkpoint.every_frames=0", "checkpoint.buffer=false", f"logger.every_frames={every}", "progress=false",
            "buffer.size=100000",
            *(["algo.exploration.sigma=0.2", "algo.exploration.theta=0.15", "algo.exploration.mu=0.0"] if algo == "ddpg" else []),
            *extra,
        ])
    train(cfg)
    wall = [(s, v) for s, v in read_csv_metric(Path(run), "time/elapsed_s") if s >= warmup + every]
    cpu = [(s, v) for s, v in read_csv_metric(Path(run), "time/cpu_s") if s >= warmup + every]
    workers = dict(read_csv_metric(Path(run), "time/worker_cpu_s"))  # PPO's worker processes
    cpu = [(s, v + workers.get(s, 0.0)) for s, v in cpu]
    shutil.rmtree(run, ignore_errors=True)
    return (wall[-1][0] - wall[0][0]) / (wall[-1][1] - wall[0][1]), (cpu[-1][0] - cpu[0][0]) / (cpu[-1][1] - cpu[0][1])


def _race_env():
    """The training config's race env for SB3's worker processes: oval, 10 Hz, 20 substeps, observations normalised as ours."""
    import gymnasium as gym
    import numpy as np

    import torcsrl  # noqa: F401  (registers torcsrl/Race-v0)
    from torcsrl.transforms import obs_scale

    env = gym.make("torcsrl/Race-v0", track="oval", control_hz=10, substeps=20)
    div = {k: np.asarray(obs_scale(k, env.observation_space[k].shape[-1]), dtype=np.float32) for k in ("rangefinder", "state")}
    env = gym.wrappers.TransformObservation(env, lambda o: {k: (o[k] / div[k]).astype(np.float32) for k in div},
                                            gym.spaces.Dict({k: env.observation_space[k] for k in div}))
    return gym.wrappers.FlattenObservation(env)


class SB3:
    """One SB3 model per thread count (TD3 or SAC on Pendulum-v1; PPO on ``cars`` race-env processes), learning
    ``steps`` more env steps per call."""

    def __init__(self, algo: str, threads: int, warmup: int, cars: int = 1, rollout: int = 128):
        import gymnasium as gym
        import stable_baselines3 as sb3

        torch.set_num_threads(threads)
        self.algo = algo
        if algo == "PPO":
            from stable_baselines3.common.vec_env import SubprocVecEnv

            self.venv = SubprocVecEnv([_race_env] * cars)
            self.m = sb3.PPO("MlpPolicy", self.venv, n_steps=rollout, batch_size=64, n_epochs=10, seed=0, device="cpu",
                             policy_kwargs=dict(net_arch=[256, 256]))
            warmup = cars * rollout
        else:
            self.m = getattr(sb3, algo)("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=warmup, batch_size=256, buffer_size=100000,
                                        policy_kwargs=dict(net_arch=[256, 256]), seed=0, device="cpu")
        self.m.learn(warmup + 50)
        self.threads = threads

    def cpu_s(self) -> float:
        """CPU seconds of this process and (PPO) of its ``SubprocVecEnv`` env processes."""
        procs = getattr(getattr(self, "venv", None), "processes", [])
        return time.process_time() + sum(process_cpu_s(p.pid) for p in procs)

    def __call__(self, steps: int) -> tuple[float, float]:
        torch.set_num_threads(self.threads)
        t, c = time.perf_counter(), self.cpu_s()
        self.m.learn(steps, reset_num_timesteps=False)
        return steps / (time.perf_counter() - t), steps / (self.cpu_s() - c)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1500, help="measured env steps per run")
    ap.add_argument("--warmup", type=int, default=500, help="random steps before updates start")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--rounds", type=int, default=3, help="rounds of side-by-side runs (median reported)")
    ap.add_argument("--algos", nargs="+", default=["td3", "ddpg", "d4pg", "sac"])
    ap.add_argument("--cars", type=int, default=16, help="PPO: cars (ours: one batched world; SB3: SubprocVecEnv processes)")
    ap.add_argument("--ppo-rollout", type=int, default=128, help="PPO: env steps per car per rollout")
    ap.add_argument("--no-sb3", action="store_true", help="our contenders only (no SB3 runs, no ratios)")
    ap.add_argument("overrides", nargs="*", help="extra Hydra overrides for our runs (after --)")
    a = ap.parse_args()
    try:
        if a.no_sb3:
            raise ImportError
        import stable_baselines3  # noqa: F401

        have_sb3 = True
    except ImportError:
        have_sb3 = False
        if not a.no_sb3:
            print("stable-baselines3 is not installed (pip install stable-baselines3): ratios are left out", file=sys.stderr)
    peers = {PEER[k.partition("+")[0]] for k in a.algos}
    if len(peers) != 1:
        raise SystemExit(f"--algos {' '.join(a.algos)} compare with different SB3 peers ({', '.join(sorted(peers))}); run them separately")
    peer_name = peers.pop()
    table = []
    for th in a.threads:
        load0 = os.getloadavg()[0]
        peer = SB3(peer_name, th, a.warmup, a.cars, a.ppo_rollout) if have_sb3 else None
        runs: dict[str, list[float]] = {k: [] for k in ["sb3", *a.algos]}
        ratios: dict[str, list[float]] = {k: [] for k in a.algos}
        cpu_ratios: dict[str, list[float]] = {k: [] for k in a.algos}
        for r in range(a.rounds):
            order = ["sb3", *a.algos] if r % 2 == 0 else [*a.algos, "sb3"]
            got = {}
            for name in order:
                if name == "sb3":
                    if peer is not None:
                        got[name] = peer(a.steps)
                else:
                    got[name] = ours(name, th, a.steps, a.warmup, a.overrides, a.cars, a.ppo_rollout)
            for k, v in got.items():
                runs[k].append(v[0])
            if "sb3" in got:
                for k in a.algos:
                    ratios[k].append(got[k][0] / got["sb3"][0])
                    cpu_ratios[k].append(got[k][1] / got["sb3"][1])
            print(f"[threads {th} round {r}] " + ", ".join(f"{k} {v[0]:.1f} steps/s ({v[1]:.1f} per CPU-s)" for k, v in got.items())
                  + f"; load {os.getloadavg()[0]:.2f}", file=sys.stderr)
        if peer is not None and peer_name == "PPO":
            peer.venv.close()
        table.append((th, load0, os.getloadavg()[0], runs, ratios, cpu_ratios))

    setting = (f"race env (oval, 10 Hz), {a.cars} cars, rollouts of {a.ppo_rollout} steps a car, 10 epochs of minibatches of 64, 256x256"
               if peer_name == "PPO" else f"Pendulum-v1, 256x256, batch 256, UTD 1, {a.steps} steps after {a.warmup} warm-up")
    print(f"\n{setting}; env steps/s and ratio to SB3 {peer_name}, "
          f"median of {a.rounds} side-by-side rounds (cpu: ratio of steps per CPU-second, summed over each side's processes; "
          f"meaningful at 1 thread); "
          f"CPU bfloat16 units: {cpu_bf16()}")
    head = f"{'threads':>7} | {'load':>9} | {'SB3 ' + peer_name:>8} | " + " | ".join(f"{k.upper():>8} {'ratio':>6} {'cpu':>5}" for k in a.algos)
    print(head)
    for th, l0, l1, runs, ratios, cpu_ratios in table:
        sb = f"{statistics.median(runs['sb3']):8.1f}" if runs["sb3"] else f"{'n/a':>8}"
        cells = []
        for k in a.algos:
            rt = f"{statistics.median(ratios[k]):6.2f} {statistics.median(cpu_ratios[k]):5.2f}" if ratios[k] else f"{'-':>6} {'-':>5}"
            cells.append(f"{statistics.median(runs[k]):8.1f} {rt}")
        print(f"{th:>7} | {l0:4.1f}-{l1:<4.1f} | {sb} | " + " | ".join(cells))
    print("targets: " + ", ".join(f"{k.upper()} >= {v} x SB3 {PEER[k]}" for k, v in TARGETS.items()) + " (steps/s, float32)")


if __name__ == "__main__":
    main()
