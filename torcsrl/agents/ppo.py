"""PPO (Schulman et al. 2017): TorchRL's ``ClipPPOLoss`` (computed on tensors) with GAE, a tanh-Gaussian policy and
observation normalisation.

The factories every agent has (``make_actor`` ... ``update``), for an on-policy learner: the actor is the
tanh-Gaussian :class:`~torcsrl.nets.TanhGaussianActor` with one learnt std per action dimension (SB3's and TorchRL's
PPO), the distribution TorchRL's ``TanhNormal``; the critic is a state-value network :class:`~torcsrl.nets.ValueNet`;
both standardise their vector observations by running statistics (``obs_norm``, :class:`~torcsrl.nets.RunningNorm`,
saved with the networks so evaluation feeds the policy what it learnt on). The loss is
:class:`torcsrl.objectives.ppo.ClipPPOLoss`: TorchRL's, the same numbers, without TensorDicts per minibatch. There
are no target networks (``make_target_updater`` returns None) and no exploration noise (the policy samples itself:
:class:`PPOPolicy`). ``update`` is one minibatch step of the clipped surrogate + value + entropy losses; the loop that
collects rollouts of the batched env and runs epochs of minibatches is :func:`torcsrl.onpolicy.train`. Defaults:
``conf/algo/ppo.yaml``.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.objectives import ValueEstimators

from torcsrl.agents import _build
from torcsrl.agents.exploration import exploring, obs_on
from torcsrl.nets import TanhGaussianActor, ValueNet
from torcsrl.objectives.ppo import ClipPPOLoss, PPOBatch, SquashedGaussian

NAME = "ppo"


class PPOPolicy(TensorDictModuleBase):
    """The rollout policy: an action drawn from ``TanhNormal(loc, std, low, high)`` and its log-probability, written
    under ``"action"`` and ``"action_log_prob"`` (what the loss reads), from tensors.

    The same draws (torch's global generator, one ``N(0, 1)`` per action dimension) and the same numbers as TorchRL's
    ``ProbabilisticActor`` over ``TanhNormal`` with ``return_log_prob=True`` (tested): the log-probability of a fresh
    draw is scored at its pre-tanh value ``u`` (``TanhNormal.rsample_and_log_prob``), while the loss re-scores the stored
    action at ``atanh(a)``, as TorchRL's does; the two agree up to rounding except where tanh saturates (``|u|`` > ~7.6).
    What differs: ~0.5 ms of CPU a step of 16 cars with 256x256 networks instead of ~1.6 ms (no TensorDict modules, no
    distribution object, no argument validation); the Gaussian's ``loc`` and ``scale`` are not written into the
    rollout (nothing reads them); and outside any exploration context it samples, as the project's other exploration
    modules do (:mod:`torcsrl.agents.exploration`; TorchRL's module acts deterministically there). Under
    ``ExplorationType.DETERMINISTIC``: the mode ``tanh(loc)``, with its log-probability at ``atanh``. Observations go
    to the actor's device, actions come back to the CPU (``device=cuda``).

    Args:
        actor: the policy network (``dist(*obs) -> (loc, std)``).
        obs_keys: observation keys in the actor's order.
        low, high: action bounds ``[A]``.
    """

    def __init__(self, actor: TanhGaussianActor, obs_keys: list[str], low: torch.Tensor, high: torch.Tensor,
                 action_key: str = "action", log_prob_key: str = "action_log_prob"):
        super().__init__()
        self.actor = actor
        self._device = actor.a_mid.device
        self.squash = SquashedGaussian(low.to(self._device).float(), high.to(self._device).float())
        self.in_keys, self.out_keys = list(obs_keys), [action_key, log_prob_key]
        self.action_key, self.log_prob_key = action_key, log_prob_key

    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs, on_cpu = obs_on(td, self.in_keys, self._device)
        loc, scale = self.actor.dist(*obs)
        if exploring():
            action, log_prob = self.squash.rsample_and_log_prob(loc, scale)
        else:
            action = self.squash.mode(loc)
            log_prob = self.squash.log_prob(loc, scale, action)
        td.set(self.action_key, action if on_cpu else action.to("cpu"))
        td.set(self.log_prob_key, log_prob if on_cpu else log_prob.to("cpu"))
        return td

    act = forward  # the collector's lean per-step call


def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """pi(a|s): tanh-Gaussian in the env's bounds, one learnt std per action dimension; ``actor(*obs)`` is its mean action.
    With ``algo.grip_estimate > 0`` it has a grip student's shape (:func:`torcsrl.agents._build.actor`): the grip head
    and input selections of ``algo.grip_*`` / ``actor_readings``, to be loaded from the student (``init.actor``)."""
    low, high = _build.action_bounds(env)
    enc = _build.encoder(cfg, env, obs_keys, obs_norm=bool(cfg.obs_norm))
    grip: dict = {}
    if float(cfg.get("grip_estimate", 0.0) or 0.0) > 0:  # a grip student's shape (init.actor), its head kept as loaded
        grip_in, policy_in = _build.grip_layout(enc, str(cfg.get("grip_inputs", "all")), cfg.get("actor_readings"))
        grip = dict(grip_hidden=tuple(cfg.get("grip_hidden", (64,))), grip_inputs=grip_in, policy_inputs=policy_in)
    return TanhGaussianActor(enc, low, high, tuple(cfg.actor_hidden), state_dependent_std=False,
                             log_std_init=log_std_start(cfg.log_std_init, low.numel()), **grip)


def log_std_start(v: Any, action_dim: int) -> torch.Tensor:
    """``algo.log_std_init`` as ``[action_dim]`` floats: one number for every action, or one per action (a list of
    ``action_dim``); ValueError in one line otherwise. The actor's start, and the start of ``algo.log_std_end``'s schedule."""
    vals = [float(v)] if isinstance(v, (int, float)) else [float(x) for x in v]
    if len(vals) not in (1, action_dim):
        raise ValueError(f"algo.log_std_init={vals}: one number, or one per action dimension ({action_dim})")
    return torch.tensor(vals * action_dim if len(vals) == 1 else vals)


def make_critic(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """V(s): the state value (its own encoder and observation statistics)."""
    return ValueNet(_build.encoder(cfg, env, obs_keys, obs_norm=bool(cfg.obs_norm)), tuple(cfg.critic_hidden))


def make_loss(cfg: Any, actor, critic, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None):
    """TorchRL's ``ClipPPOLoss`` (clipped surrogate, l2 value loss, entropy bonus, advantages normalised per minibatch)
    on tensors (:class:`~torcsrl.objectives.ppo.ClipPPOLoss`), with TorchRL's ``GAE(gamma, gae_lambda)`` as its value
    estimator; ``critic_obs_keys``: what the value network sees when not the actor's keys (an asymmetric critic)."""
    low, high = _build.action_bounds(env)
    loss = ClipPPOLoss(actor, critic, obs_keys=list(obs_keys), action_low=low, action_high=high, clip_epsilon=float(cfg.clip_epsilon),
                       entropy_coeff=float(cfg.entropy_coef), critic_coeff=float(cfg.value_coef), loss_critic_type="l2",
                       normalize_advantage=True, critic_obs_keys=None if critic_obs_keys is None else list(critic_obs_keys))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=float(cfg.gamma), lmbda=float(cfg.gae_lambda))
    sm = getattr(cfg, "smooth", None)
    loss.with_next = sm is not None and float(sm.temporal) > 0  # the CAPS temporal term reads the next observations
    return loss


def make_target_updater(cfg: Any, loss):
    """None: PPO has no target networks."""
    return None


def make_exploration(cfg: Any, actor, env: EnvBase, obs_keys: list[str]):
    """The policy itself (:class:`PPOPolicy`): a sample and its log-probability while exploring (``algo.exploration``
    must be ``none``)."""
    low, high = _build.action_bounds(env)
    return PPOPolicy(actor, obs_keys, low, high)


def make_optimizers(cfg: Any, loss):
    """One Adam for the actor (``actor_lr``), one for the value network (``critic_lr``)."""
    adam = _build.FusedAdam if cfg.fused_adam else torch.optim.Adam
    kw = dict(weight_decay=float(cfg.weight_decay))
    return {"actor": adam(list(loss.actor_network.parameters()), lr=float(cfg.actor_lr), **kw),
            "critic": adam(list(loss.critic_network.parameters()), lr=float(cfg.critic_lr), **kw)}


def update(cfg: Any, loss: ClipPPOLoss, optim, updater, batch: PPOBatch | TensorDictBase, n_update: int, actor: bool = True) -> dict:
    """One minibatch step on ``batch`` (a :class:`~torcsrl.objectives.ppo.PPOBatch` slice of
    :meth:`ClipPPOLoss.batch <torcsrl.objectives.ppo.ClipPPOLoss.batch>`, or a TensorDict with advantages and value
    targets: :func:`torcsrl.onpolicy.train`): clipped surrogate + ``value_coef`` x value loss + ``entropy_coef`` x entropy
    bonus, gradients clipped to ``grad_clip`` (one norm over both networks: SB3's ``max_grad_norm``); ``actor=False``:
    the value network only. Returns detached tensors (``loss/...``; the loop reads them when it logs)."""
    if isinstance(batch, TensorDictBase):
        batch = loss.batch(batch)
    with _build.precision_context(cfg.precision, loss.actor.a_mid.device):
        lc, _ = loss.value_loss(batch)
        la, meta = loss.actor_loss(batch) if actor else (None, None)
        sm = getattr(cfg, "smooth", None)
        smooth_out: dict = {}
        if actor and sm is not None and (float(sm.temporal) > 0 or float(sm.spatial) > 0):  # CAPS on the mean action
            ls, smooth_out = loss.smoothness(batch, float(sm.temporal), float(sm.spatial), float(sm.spatial_sigma))
            la = la + ls
    total = lc + la if actor else lc
    opts = [optim["actor"], optim["critic"]] if actor else [optim["critic"]]
    for o in opts:
        o.zero_grad(set_to_none=True)
    total.backward()
    if cfg.grad_clip:
        _build.clip_grad_norm([p for o in opts for p in o.param_groups[0]["params"]], cfg.grad_clip)
    for o in opts:
        _build._step(o)
    out = {"loss/critic": lc.detach()}
    if actor:
        out.update({"loss/objective": meta["loss_objective"], "loss/entropy": meta["entropy"], "loss/kl_approx": meta["kl_approx"],
                    "loss/clip_fraction": meta["clip_fraction"], **smooth_out})
    return out
