"""Pixel training throughput: env frames/s and updates/s of the camera student (DAgger/BC) and of asymmetric TD3.

    python benchmarks/pixel_train_throughput.py [--frames 600] [--updates 60] [--batch 128] [--rounds 2]

The configs are the experiments' own (``experiment=camera_distill``, ``experiment=camera_asym``: 64x64 hood camera +
telemetry, Nature-DQN-shaped CNN, DrQ shifts), on one named training track, one torch thread:

* **camera student (BC update)**: frames/s of a DAgger round (:func:`torcsrl.demos.label_rollouts`: the student
  drives, the privileged teacher ``sensor_grip`` labels, the transition is stored); updates/s of
  :func:`torcsrl.agents._build.bc_step` on batches of ``--batch`` from those frames (DrQ shifts on);
* **asymmetric TD3**: frames/s of the training env (camera + the critic's rangefinder + state) driven by the
  behaviour policy, each step stored in the replay buffer (the in-process collector's work); updates/s of the TD3
  update (critic every step, actor every 2) on batches of ``--batch`` sampled from it;
* peers, same batch: **symmetric pixel TD3** (the critics see the camera set too: a CNN in the critic) and
  **rangefinder TD3** (the default vector agent).

``loop frames/s`` is the rate of a loop that collects one frame and makes ``utd`` updates per frame:
``1 / (1/frames_per_s + utd/updates_per_s)`` (derived from the two measured rates). Each figure is the best of
``--rounds`` (contenders interleaved; the machine may be shared, so the load is printed; ratios compare runs seconds
apart). GPU figures: the same command with ``--device cuda`` where there is one (updates only move there).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from torcsrl import agents  # noqa: E402
from torcsrl.training.offpolicy import make_buffer  # noqa: E402
from torcsrl.training.common import make_networks, plain
from torcsrl.pipeline import make_train_env

TRACK = ["env.track=oval", "env.procedural=null", "eval.env={}", "eval.per_track=false"]


def cfg_for(*overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("train", overrides=[*TRACK, *overrides])


def _rate(n: int, fn) -> float:
    t0 = time.perf_counter()
    for i in range(n):
        fn(i)
    return n / (time.perf_counter() - t0)


def student(frames: int, updates: int, batch: int, device: torch.device) -> tuple[float, float]:
    """(DAgger frames/s, BC updates/s) of the camera student of experiment=camera_distill."""
    from torcsrl.agents._build import bc_step
    from torcsrl.nets import split_obs_keys
    from torcsrl.training.demos import EXTRA_KEYS, label_rollouts, make_demo_env
    from torcsrl.objectives.common import ObsUnpacker
    from torcsrl.utils.replay import ReplayBuffer

    cfg = cfg_for("experiment=camera_distill", f"algo.batch_size={batch}")
    keys = list(cfg.env.sensors)
    env = make_demo_env(cfg, 1)
    try:
        actor = agents.get("dagger").make_actor(cfg.algo, env, keys)
        buf = ReplayBuffer(frames, batch, keys, extra_keys=EXTRA_KEYS)
        actor.eval()
        t0 = time.perf_counter()
        with torch.no_grad():
            label_rollouts(env, frames, buf, learner=actor, beta=0.0, seed=1, obs_keys=keys, teacher=str(cfg.demos.teacher))
        fps = frames / (time.perf_counter() - t0)
        actor.train()
    finally:
        env.close()
    actor.to(device)
    optim = agents.get("dagger").make_optimizers(cfg.algo, actor)
    _, img = split_obs_keys(env.observation_spec, keys)
    net = SimpleNamespace(actor_network=actor, obs=ObsUnpacker(keys, img, int(cfg.algo.encoder.augment_shift)))
    for _ in range(3):
        bc_step(net, optim, buf.sample().to(device))
    ups = _rate(updates, lambda i: bc_step(net, optim, buf.sample().to(device)))
    return fps, ups


def actor_critic(overrides: list[str], frames: int, updates: int, batch: int, device: torch.device) -> tuple[float, float]:
    """(collect frames/s, update/s) of an actor-critic config: env + behaviour policy + buffer, then sampled updates."""
    cfg = cfg_for(*overrides, f"algo.batch_size={batch}", f"buffer.size={frames + 10}")
    agent = agents.get(cfg.algo.name)
    keys = list(cfg.obs_keys or cfg.env.sensors)
    env = make_train_env(cfg)
    try:
        actor, critic, loss = make_networks(cfg, agent, env, keys, device)
        updater = agent.make_target_updater(cfg.algo, loss)
        policy = agent.make_exploration(cfg.algo, actor, env, keys)
        optim = agent.make_optimizers(cfg.algo, loss)
        buf = make_buffer(cfg, Path("/nonexistent"))
        state = {"td": env.reset()}

        def collect(_):
            with torch.no_grad():
                td = policy.act(state["td"])
            out, state["td"] = env.step_and_maybe_reset(td)
            buf.extend(out)

        for _ in range(5):
            collect(0)
        fps = _rate(frames, collect)
    finally:
        env.close()
    hot = plain(cfg.algo)
    hot.n_demo, hot.bc_weight = 0, 0.0

    def update(i):
        agent.update(hot, loss, optim, updater, buf.sample().to(device), i)

    for i in range(4):
        update(i)
    if device.type == "cuda":
        torch.cuda.synchronize()
    ups = _rate(updates, update)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return fps, ups


CONTENDERS = {
    "camera student (DAgger/BC)": None,
    "asymmetric TD3 (camera actor, state critic)": ["experiment=camera_asym"],
    "symmetric pixel TD3 (CNN in the critic too)": ["experiment=camera_asym", "critic_obs_keys=null"],
    "rangefinder TD3": ["algo=td3", "sensors=rangefinder", "threads=1"],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=600, help="env frames per measurement")
    ap.add_argument("--updates", type=int, default=60, help="gradient steps per measurement")
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--utd", type=float, default=1.0, help="updates per frame of the derived loop rate")
    ap.add_argument("--device", default="cpu", help="where the updates run (cpu | cuda)")
    ap.add_argument("--only", nargs="*", default=None, help="contender names (substrings) to run")
    args = ap.parse_args(argv)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    torch.set_num_threads(1)
    device = torch.device(args.device)
    names = [n for n in CONTENDERS if not args.only or any(s in n for s in args.only)]
    best: dict[str, list[float]] = {n: [0.0, 0.0] for n in names}
    loads = [os.getloadavg()[0]]
    for r in range(args.rounds):
        for name in (names if r % 2 == 0 else names[::-1]):
            torch.manual_seed(r)
            ov = CONTENDERS[name]
            f, u = student(args.frames, args.updates, args.batch, device) if ov is None else \
                actor_critic(ov, args.frames, args.updates, args.batch, device)
            best[name] = [max(best[name][0], f), max(best[name][1], u)]
            print(f"# round {r}: {name}: {f:.0f} frames/s, {u:.1f} updates/s", file=sys.stderr)
        loads.append(os.getloadavg()[0])
    ref = best.get("symmetric pixel TD3 (CNN in the critic too)", [0, 0])[1]
    print(f"# pixel training throughput: batch {args.batch}, 64x64 camera, one torch thread, updates on {device}; "
          f"best of {args.rounds} rounds; 1-min load {min(loads):.2f}..{max(loads):.2f} on {os.cpu_count()} cores (shared machine)")
    print(f"| contender | env frames/s | updates/s (batch {args.batch}) | loop frames/s at utd {args.utd:g} | updates/s vs symmetric pixel TD3 |")
    print("|---|---|---|---|---|")
    for name in names:
        f, u = best[name]
        loop = 1.0 / (1.0 / f + args.utd / u)
        ratio = f"{u / ref:.2f}x" if ref else "-"
        print(f"| {name} | {f:.0f} | {u:.1f} | {loop:.1f} | {ratio} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
