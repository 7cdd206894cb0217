"""PPO's two code paths side by side: TorchRL's (``ClipPPOLoss`` forward on TensorDict minibatches, ``ProbabilisticActor``
collecting) vs ours (:mod:`torcsrl.objectives.ppo` on tensors, :class:`~torcsrl.agents.ppo.PPOPolicy` collecting).

One process, two copies of everything (race env, networks, optimisers, torch RNG state), identical at the start; each
round runs one PPO iteration of each (``--cars`` x ``--rollout`` frames: collect, GAE, ``--epochs`` epochs of shuffled
minibatches of ``--minibatch``, observation statistics), alternating which goes first. Timed in PROCESS CPU seconds
(the box is shared: wall-clock figures drift with the load; CPU time does far less), split into collection (env steps
+ policy) and update (GAE + minibatch updates + statistics). The two paths compute the same numbers: the script also
reports the largest parameter difference between the two copies after the last round (0.0: bitwise the same run).

``--paths`` picks the contenders (the first is the reference of the ratios): ``torchrl``, ``ours`` and ``ours+bf16``
(ours with ``algo.precision=bfloat16``: mixed-precision updates), e.g. ``--paths ours ours+bf16`` times PPO's update in
float32 and in bfloat16, interleaved in one process.

    python benchmarks/ppo_paths.py [--cars 16] [--rollout 128] [--rounds 4] [--threads 1] [--paths torchrl ours]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from torchrl.modules import ValueOperator  # noqa: E402
from torchrl.objectives import ClipPPOLoss as TorchRLClipPPOLoss  # noqa: E402
from torchrl.objectives import ValueEstimators  # noqa: E402

from torcsrl import agents  # noqa: E402
from torcsrl.agents import _build  # noqa: E402
from torcsrl.objectives.ppo import probabilistic_actor  # noqa: E402
from torcsrl.training.common import make_networks, plain  # noqa: E402
from torcsrl.pipeline import make_train_env
from torcsrl.utils.collector import StepCollector  # noqa: E402


def torchrl_update(cfg, loss, optim, batch) -> dict:
    """The update before this path existed: TorchRL's ``ClipPPOLoss`` forward on a TensorDict minibatch."""
    with _build.precision_context(cfg.precision, batch.device or "cpu"):
        td = loss(batch)
    total = td["loss_critic"] + (td["loss_objective"] + td["loss_entropy"])
    opts = [optim["actor"], optim["critic"]]
    for o in opts:
        o.zero_grad(set_to_none=True)
    total.backward()
    if cfg.grad_clip:
        torch.nn.utils.clip_grad_norm_([p for o in opts for p in o.param_groups[0]["params"]], cfg.grad_clip)
    for o in opts:
        _build._step(o)
    return {"loss/objective": td["loss_objective"].detach(), "loss/critic": td["loss_critic"].detach()}


class Path_:
    """One copy of the PPO stack and its RNG state; ``iteration()`` -> (collection CPU s, update CPU s)."""

    def __init__(self, cfg, fast: bool, precision: str = "float32"):
        torch.manual_seed(int(cfg.seed))
        self.cfg, self.fast, self.hot = cfg, fast, plain(cfg.algo)
        self.hot.precision = precision
        self.agent = agents.get("ppo")
        self.keys = list(cfg.env.sensors)
        self.env = make_train_env(cfg)
        self.actor, self.critic, self.loss = make_networks(cfg, self.agent, self.env, self.keys, torch.device("cpu"))
        if fast:
            policy = self.agent.make_exploration(cfg.algo, self.actor, self.env, self.keys)
        else:  # TorchRL's loss and policy around the same networks
            low, high = _build.action_bounds(self.env)
            policy = probabilistic_actor(self.actor, self.keys, low, high)
            a = cfg.algo
            self.loss = TorchRLClipPPOLoss(probabilistic_actor(self.actor, self.keys, low, high), ValueOperator(self.critic, in_keys=self.keys),
                                           clip_epsilon=float(a.clip_epsilon), entropy_coeff=float(a.entropy_coef),
                                           critic_coeff=float(a.value_coef), loss_critic_type="l2", normalize_advantage=True)
            self.loss.make_value_estimator(ValueEstimators.GAE, gamma=float(a.gamma), lmbda=float(a.gae_lambda))
        self.optim = self.agent.make_optimizers(cfg.algo, self.loss)
        self.collector = iter(StepCollector(self.env, policy, max(1, self.env.batch_size.numel()) * int(cfg.algo.rollout_steps)))
        self.rng = torch.get_rng_state()

    def iteration(self) -> tuple[float, float]:
        torch.set_rng_state(self.rng)
        epochs, mb = int(self.cfg.algo.epochs), int(self.cfg.algo.batch_size)
        t0 = time.process_time()
        data = next(self.collector)
        t1 = time.process_time()
        with torch.no_grad():
            self.loss.value_estimator(data)
        if self.fast:
            batch = self.loss.batch(data)
            n = len(batch)
            for _ in range(epochs):
                shuffled = batch[torch.randperm(n)]
                for s in range(0, n, mb):
                    self.agent.update(self.hot, self.loss, self.optim, None, shuffled[s:s + mb], 0)
        else:
            flat = data.reshape(-1)
            for _ in range(epochs):
                for idx in torch.randperm(flat.numel()).split(mb):
                    torchrl_update(self.hot, self.loss, self.optim, flat[idx])
        for m in (self.actor, self.critic):
            m.encoder.update_norm(*[data.get(k) for k in self.keys])
        t2 = time.process_time()
        self.rng = torch.get_rng_state()
        return t1 - t0, t2 - t1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cars", type=int, default=16)
    ap.add_argument("--rollout", type=int, default=128, help="env steps per car per rollout")
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--minibatch", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=4, help="iterations of each path (after one warm-up iteration each)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--paths", nargs="+", default=["torchrl", "ours"], choices=["torchrl", "ours", "ours+bf16"],
                    help="contenders, the first the reference of the ratios")
    ap.add_argument("overrides", nargs="*", help="extra Hydra overrides of the training config")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[
            "algo=ppo", "env.track=oval", f"env.num_cars={a.cars}", f"algo.rollout_steps={a.rollout}", f"algo.batch_size={a.minibatch}",
            f"algo.epochs={a.epochs}", "algo.actor_hidden=[256,256]", "algo.critic_hidden=[256,256]", f"run_dir={tempfile.mkdtemp()}",
            f"threads={a.threads}", *a.overrides])
    if len(set(a.paths)) < 2:
        raise SystemExit("--paths: name at least two different contenders")
    paths = {k: Path_(cfg, fast=k != "torchrl", precision="bfloat16" if k.endswith("+bf16") else "float32") for k in dict.fromkeys(a.paths)}
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in paths}
    for r in range(a.rounds + 1):
        order = list(paths) if r % 2 == 0 else list(reversed(paths))
        for k in order:
            t = paths[k].iteration()
            if r > 0:  # round 0 warms up
                times[k].append(t)
    frames = a.cars * a.rollout
    print(f"PPO iteration = {a.cars} cars x {a.rollout} steps = {frames} frames, {a.epochs} epochs x minibatch {a.minibatch} "
          f"({a.epochs * -(-frames // a.minibatch)} updates), 256x256, {a.threads} thread(s); median of {a.rounds} rounds, process CPU s")
    print(f"{'path':>9} {'collect s':>10} {'update s':>10} {'total s':>10} {'frames/CPU s':>13}")
    med = {}
    for k, ts in times.items():
        c, u = statistics.median(t[0] for t in ts), statistics.median(t[1] for t in ts)
        med[k] = (c, u)
        print(f"{k:>9} {c:10.3f} {u:10.3f} {c + u:10.3f} {frames / (c + u):13.0f}")
    ref, *others = list(paths)
    c0, u0 = med[ref]
    for k in others:
        c1, u1 = med[k]
        print(f"ratio {ref}/{k}: collect {c0 / c1:.2f}x, update {u0 / u1:.2f}x, total {(c0 + u0) / (c1 + u1):.2f}x")
        with torch.no_grad():
            diff = max(float((p - q).abs().max()) for p, q in zip(paths[ref].actor.parameters(), paths[k].actor.parameters()))
            diff_c = max(float((p - q).abs().max()) for p, q in zip(paths[ref].critic.parameters(), paths[k].critic.parameters()))
        print(f"largest parameter difference {ref} vs {k} after {a.rounds + 1} iterations of each: actor {diff:.3g}, critic {diff_c:.3g}")


if __name__ == "__main__":
    main()
