"""Learning benchmark: wall-clock and env steps to the first clean lap and to a clean 10-lap run, per seed.

A *clean lap* is a validation episode (deterministic policy, Summers's protocol) that completes at
least one lap without leaving the track; a *clean 10-lap run* completes 10 laps. For each seed the
harness trains in chunks of ``--chunk`` env steps (resuming from the previous chunk's checkpoint,
so the curve is the one an uninterrupted run would give), validates after every chunk and records
the first chunk end at which each milestone is met.

    python benchmarks/learning.py --env race --algo td3 --seeds 0 1 2 --budget 1000000
    python benchmarks/learning.py --env toy --algo td3 --seeds 0 --budget 20000 --chunk 2000   # quick check

Extra Hydra overrides go after ``--``: ``python benchmarks/learning.py -- env.track=... algo.actor_lr=1e-4``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402

from torcsrl.training import train  # noqa: E402


def run_seed(env: str, algo: str, seed: int, budget: int, chunk: int, overrides: list[str], out: Path,
             eval_max_steps: int = 10_000, max_wall_s: float | None = None) -> dict:
    run_dir = out / f"{algo}_{env}_seed{seed}"
    found = {"first_clean_lap": None, "clean_10_laps": None}
    wall = 0.0
    frames = 0
    while frames < budget and found["clean_10_laps"] is None and (max_wall_s is None or wall < max_wall_s):
        target = min(budget, frames + chunk)
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            cfg = compose("train", overrides=[
                f"algo={algo}", f"env={env}", f"seed={seed}", f"run_dir={run_dir}", f"total_frames={target}",
                "eval.every_episodes=1000000000", "eval.lap_limit=10", f"eval.max_steps={eval_max_steps}", f"checkpoint.every_frames={chunk}", "progress=false",
                *(["checkpoint.resume=latest"] if frames else []), *overrides,
            ])
        t = time.perf_counter()
        r = train(cfg)
        wall += time.perf_counter() - t
        frames = r["frames"]
        from torcsrl.pipeline import make_eval_envs
        from torcsrl.training.common import validate_all  # the same deterministic validation as in training
        import torch

        from torcsrl import agents
        from torcsrl.utils.checkpoint import load_checkpoint

        ck = load_checkpoint(r["checkpoint"])
        envs_v = make_eval_envs(cfg)
        env_v = next(iter(envs_v.values()))
        ag = agents.get(cfg.algo.name)
        keys = list(cfg.obs_keys or cfg.env.sensors)
        actor = ag.make_actor(cfg.algo, env_v, keys)
        sd = ck.get("actor") or {k[len("actor_network_params."):]: v for k, v in ck["loss"].items() if k.startswith("actor_network_params.")}
        actor.load_state_dict(sd)
        from tensordict.nn import TensorDictModule

        policy = TensorDictModule(actor, in_keys=keys, out_keys=["action"])  # deterministic: SAC's and PPO's mean action
        with torch.no_grad():
            ev = validate_all(envs_v, policy, 1, int(cfg.eval.max_steps))
        for e in envs_v.values():
            e.close()
        laps = ev.get("eval/laps_min", ev["eval/laps"])  # with eval.per_track: the worst track
        if laps >= 1 and found["first_clean_lap"] is None:
            found["first_clean_lap"] = (frames, wall)
        if laps >= 10:
            found["clean_10_laps"] = (frames, wall)
        print(f"[learning] {algo} seed {seed}: {frames:>8} steps, {wall:8.1f} s training wall-clock, "
              f"validation: {laps} of 10 laps, return {ev['eval/reward']:.1f}", flush=True)
    return {"seed": seed, **found, "frames": frames, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="race", choices=["race", "toy"])
    ap.add_argument("--algo", default="td3", choices=["ddpg", "td3", "d4pg", "sac", "ppo"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--budget", type=int, default=1_000_000, help="env steps per seed at most")
    ap.add_argument("--chunk", type=int, default=10_000, help="env steps between milestone checks")
    ap.add_argument("--eval-max-steps", type=int, default=10_000,
                    help="step cap of the 10-lap validation run (10 laps of the oval at 10 Hz take ~5,000 steps)")
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="stop a seed once its training wall-clock passes this [min] (the goals' 30-minute budgets)")
    ap.add_argument("--out", default=None, help="folder for the runs (default: a temporary folder)")
    ap.add_argument("overrides", nargs="*", help="extra Hydra overrides (after --)")
    a = ap.parse_args()
    out = Path(a.out or tempfile.mkdtemp(prefix="torcsrl_learning_"))
    rows = [run_seed(a.env, a.algo, s, a.budget, a.chunk, a.overrides, out, a.eval_max_steps,
                     None if a.max_minutes is None else 60.0 * a.max_minutes) for s in a.seeds]

    def fmt(m):
        return "not reached" if m is None else f"{m[0]:>9} steps {m[1]:8.1f} s"

    cap = "" if a.max_minutes is None else f" or {a.max_minutes:g} min of training"
    print(f"\n{a.algo} on env={a.env}, budget {a.budget} steps{cap}, checked every {a.chunk} steps; runs in {out}")
    print(f"{'seed':>4} | {'first clean lap':>26} | {'clean 10-lap run':>26}")
    for r in rows:
        print(f"{r['seed']:>4} | {fmt(r['first_clean_lap']):>26} | {fmt(r['clean_10_laps']):>26}")


if __name__ == "__main__":
    main()
