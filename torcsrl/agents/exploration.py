"""Exploration for deterministic policies, as TensorDict modules placed after the actor.

Every module here acts only when TorchRL's exploration type is RANDOM (the collectors' default);
under ``set_exploration_type(ExplorationType.DETERMINISTIC)`` (validation) the actor's action
passes through untouched. All randomness comes from torch's global generator, which the
training loop seeds and checkpoints; per-episode state lives in the collector's tensordict
(reset by TorchRL's ``InitTracker`` flag ``"is_init"``), per-run state in module buffers.

* :class:`ActionNoise` — ``kind="ou"``: an Ornstein-Uhlenbeck process per action dimension,
  ``x <- x + theta (mu - x) dt + sigma sqrt(dt) N(0, 1)`` with per-dimension theta, mu, sigma
  (Andersson et al.'s TORCS setting, after Lau 2016: steer theta .6 mu 0 sigma .3, throttle
  theta 1 mu .5 sigma .3, dt = 1 step). ``kind="gaussian"``: ``N(0, sigma^2)`` clipped to
  ``[-clip, clip]`` (TD3). Both can be annealed linearly over ``anneal_frames`` to ``scale_end``.
  TorchRL's ``OrnsteinUhlenbeckProcessModule``/``AdditiveGaussianModule`` take one scalar
  theta/mu/sigma for all dimensions and no noise clip, hence this module.
* :class:`StochasticBrake` — Lau's stochastic braking: with probability ``prob`` per step the
  throttle/brake command is replaced by a brake of ``mu + sigma N(0,1)`` (in [0, 1]).
* :class:`BehaviourPolicy` — the chain actor -> noise (-> brake) as a ``TensorDictSequential``,
  with :meth:`BehaviourPolicy.act`, the same computation without TensorDict dispatch wrappers
  for the in-process collector (~0.1-0.2 ms per env step less on the project's CPU).
* :class:`ParamNoiseActor` — parameter-space noise (Plappert et al. 2017): acts with a
  perturbed copy of the actor (Gaussian weight noise of std ``sigma``, resampled every
  ``resample_frames`` frames) and adapts ``sigma`` so the action-space distance between the
  perturbed and clean policies stays near ``target_distance``.
* :class:`PolicySample` — a stochastic actor's own exploration (SAC): while exploring, an action drawn from the
  tanh-Gaussian policy; otherwise its mean action.
* :class:`DeviceActorModule` — the actor's ``TensorDictModule`` when the actor lives on another device
  than the env (``device=cuda``): observations go to the actor's device, the action comes back to the CPU.
"""

from __future__ import annotations

import copy
import math
from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type


def obs_on(td: TensorDictBase, keys: Sequence[str], device: torch.device) -> tuple[list[torch.Tensor], bool]:
    """The observations ``keys`` of ``td`` on the actor's ``device`` (a copy only off the CPU), and whether that is the CPU."""
    obs = [td.get(k) for k in keys]
    on_cpu = device.type == "cpu"
    return (obs if on_cpu else [o.to(device, non_blocking=True) for o in obs]), on_cpu


def exploring() -> bool:
    t = exploration_type()
    return t is None or t == ExplorationType.RANDOM


class ActionNoise(TensorDictModuleBase):
    """Additive OU or clipped Gaussian noise, per action dimension (see module docstring).

    Args:
        kind: ``"ou"`` or ``"gaussian"``.
        action_low, action_high: action bounds; noisy actions are clipped into them.
        sigma: noise std per dimension (or one value for all) [action units].
        theta: OU mean-reversion rate per dimension [1/step] (``kind="ou"``).
        mu: OU long-run mean per dimension [action units] (``kind="ou"``).
        dt: OU time step [steps].
        clip: Gaussian noise clip c (``None``: no clip).
        anneal_frames: frames over which the noise scale decays linearly from 1 to ``scale_end`` (0 = constant).
        scale_end: final noise scale.
    """

    NOISE_KEY = "_ou_noise"

    def __init__(
        self,
        kind: str,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        sigma: float | Sequence[float],
        theta: float | Sequence[float] = 0.15,
        mu: float | Sequence[float] = 0.0,
        dt: float = 1.0,
        clip: float | None = None,
        anneal_frames: int = 0,
        scale_end: float = 1.0,
        action_key: str = "action",
        is_init_key: str = "is_init",
    ):
        super().__init__()
        if kind not in ("ou", "gaussian"):
            raise ValueError(f"unknown noise kind {kind!r}; known: ou, gaussian")
        n = action_low.numel()

        def vec(x, name):
            t = torch.as_tensor(x, dtype=torch.float32).flatten()
            if t.numel() == 1:
                t = t.expand(n).clone()
            if t.numel() != n:
                raise ValueError(f"exploration {name} has {t.numel()} values; the action has {n} dimensions")
            return t

        self.kind, self.dt, self.clip = kind, float(dt), clip
        self.register_buffer("sigma", vec(sigma, "sigma"))
        self.register_buffer("theta", vec(theta, "theta"))
        self.register_buffer("mu", vec(mu, "mu"))
        self.register_buffer("low", action_low.float().flatten().clone())
        self.register_buffer("high", action_high.float().flatten().clone())
        self.register_buffer("frames", torch.zeros((), dtype=torch.long))
        self.anneal_frames, self.scale_end = int(anneal_frames), float(scale_end)
        self.action_key, self.is_init_key = action_key, is_init_key
        self.in_keys = [action_key, is_init_key] if kind == "ou" else [action_key]
        self.out_keys = [action_key, self.NOISE_KEY] if kind == "ou" else [action_key]

    def scale(self) -> float:
        """Current noise scale (1 down to ``scale_end`` over ``anneal_frames``)."""
        if self.anneal_frames <= 0:
            return 1.0
        f = min(1.0, float(self.frames) / self.anneal_frames)
        return 1.0 + f * (self.scale_end - 1.0)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if not exploring():
            return td
        a = td.get(self.action_key)
        if self.kind == "gaussian":
            noise = torch.randn_like(a).mul_(self.sigma)
            if self.clip is not None:
                noise = noise.clamp_(-self.clip, self.clip)
        else:
            prev = td.get(self.NOISE_KEY, None)
            if prev is None:
                prev = torch.zeros_like(a)
            init = td.get(self.is_init_key, None)
            if init is not None:
                prev = torch.where(init.reshape(*init.shape[:-1], 1).expand_as(prev), torch.zeros_like(prev), prev)
            noise = prev + self.theta * (self.mu - prev) * self.dt + self.sigma * math.sqrt(self.dt) * torch.randn_like(a)
            td.set(self.NOISE_KEY, noise)
        scale = self.scale()
        td.set(self.action_key, torch.clamp(a + noise if scale == 1.0 else a + scale * noise, self.low, self.high))
        self.frames += a.numel() // a.shape[-1]
        return td


class StochasticBrake(TensorDictModuleBase):
    """Lau's stochastic braking: with probability ``prob`` a step brakes with strength ``mu + sigma N(0,1)``.

    Args:
        prob: probability per step [-].
        mu, sigma: brake strength mean and std, in [0, 1] of full braking.
        dim: index of the throttle/brake action dimension (< 0 = brake).
    """

    def __init__(self, prob: float = 0.1, mu: float = 0.2, sigma: float = 0.1, dim: int = 1, action_key: str = "action"):
        super().__init__()
        if not 0 <= prob <= 1:
            raise ValueError(f"stochastic brake prob must be in [0, 1], got {prob}")
        self.prob, self.mu, self.sigma, self.dim = float(prob), float(mu), float(sigma), int(dim)
        self.action_key = action_key
        self.in_keys = [action_key]
        self.out_keys = [action_key]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if not exploring():
            return td
        a = td.get(self.action_key).clone()
        u = torch.rand(a.shape[:-1], device=a.device)
        strength = (self.mu + self.sigma * torch.randn(a.shape[:-1], device=a.device)).clamp(0.0, 1.0)
        a[..., self.dim] = torch.where(u < self.prob, -strength, a[..., self.dim])
        td.set(self.action_key, a)
        return td


class ParamNoiseActor(TensorDictModuleBase):
    """Acts with a perturbed copy of ``actor`` while exploring (Plappert et al. 2017).

    Args:
        actor: the online actor (``forward(*obs) -> action``); it is read, never modified.
        in_keys: observation keys in the actor's order.
        sigma: initial weight-noise std.
        target_distance: desired RMS action distance between perturbed and clean policy [action units].
        adapt: multiplicative sigma adaptation factor (> 1).
        resample_frames: frames between two perturbations.
    """

    def __init__(self, actor: nn.Module, in_keys: Sequence[str], sigma: float = 0.05, target_distance: float = 0.2,
                 adapt: float = 1.01, resample_frames: int = 100, action_key: str = "action"):
        super().__init__()
        self.actor = actor
        self.perturbed = copy.deepcopy(actor).requires_grad_(False)
        self.in_keys = list(in_keys)
        self.out_keys = [action_key]
        self.action_key = action_key
        self.target_distance, self.adapt, self.resample_frames = float(target_distance), float(adapt), int(resample_frames)
        self.register_buffer("sigma", torch.tensor(float(sigma)))
        self.register_buffer("frames", torch.zeros((), dtype=torch.long))
        self.register_buffer("last_resample", torch.full((), -1, dtype=torch.long))
        self._device = next(actor.parameters()).device  # the actor's (device=cuda: observations go there, actions come back)

    @torch.no_grad()
    def _resample(self) -> None:
        for p, q in zip(self.actor.parameters(), self.perturbed.parameters()):
            q.copy_(p + self.sigma * torch.randn_like(p))
        for b, c in zip(self.actor.buffers(), self.perturbed.buffers()):
            c.copy_(b)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs = [td.get(k) for k in self.in_keys]
        on_cpu = self._device.type == "cpu"
        if not on_cpu:
            obs = [o.to(self._device, non_blocking=True) for o in obs]
        if not exploring():
            td.set(self.action_key, self.actor(*obs) if on_cpu else self.actor(*obs).to("cpu"))
            return td
        with torch.no_grad():
            if int(self.last_resample) < 0 or int(self.frames - self.last_resample) >= self.resample_frames:
                self._resample()
                self.last_resample.copy_(self.frames)
            a_p = self.perturbed(*obs)
            a = self.actor(*obs)
            dist = (a_p - a).pow(2).mean().sqrt()
            self.sigma.mul_(self.adapt if dist < self.target_distance else 1.0 / self.adapt)
        td.set(self.action_key, a_p if on_cpu else a_p.to("cpu"))
        self.frames += max(1, a.numel() // a.shape[-1])
        return td


class PolicySample(TensorDictModuleBase):
    """Acts with a draw from a stochastic actor (``actor.sample(*obs) -> (action, log_prob, mean)``, SAC's
    :class:`~torcsrl.nets.TanhGaussianActor`) while exploring, with its deterministic action ``actor(*obs)`` otherwise.
    Draws come from torch's global generator (seeded and checkpointed by the training loop)."""

    def __init__(self, actor: nn.Module, in_keys: Sequence[str], action_key: str = "action"):
        super().__init__()
        self.actor = actor
        self.in_keys, self.out_keys, self.action_key = list(in_keys), [action_key], action_key
        self._device = next(actor.parameters()).device

    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs, on_cpu = obs_on(td, self.in_keys, self._device)
        a = self.actor.sample(*obs)[0] if exploring() else self.actor(*obs)
        td.set(self.action_key, a if on_cpu else a.to("cpu"))
        return td


class DeviceActorModule(TensorDictModule):
    """``TensorDictModule(actor, in_keys, out_keys)`` for an actor on ``device`` driving CPU envs: reads the
    observations, moves them to ``device``, writes the action back on the CPU. Same state-dict keys as the
    plain module (the CPU path uses the plain one: no copy per step there)."""

    def __init__(self, module: nn.Module, in_keys, out_keys, device: torch.device):
        super().__init__(module, in_keys=in_keys, out_keys=out_keys)
        self.actor_device = torch.device(device)

    def forward(self, tensordict: TensorDictBase, *args, **kwargs) -> TensorDictBase:
        obs = [tensordict.get(k).to(self.actor_device, non_blocking=True) for k in self.in_keys]
        tensordict.set(self.out_keys[0], self.module(*obs).to("cpu"))
        return tensordict


class BehaviourPolicy(TensorDictSequential):
    """The behaviour policy: actor -> exploration modules, a ``TensorDictSequential`` (state-dict keys,
    TorchRL collectors and ``env.rollout`` see exactly that) with a lean per-step path, :meth:`act`."""

    def act(self, td: TensorDictBase) -> TensorDictBase:
        """``self(td)`` without the dispatch/selection wrappers: plain ``TensorDictModule`` s are called on
        their input tensors, the exploration modules through their ``forward``. Same values, same RNG draws."""
        for m in self.module:
            if type(m) is TensorDictModule:
                td.set(m.out_keys[0], m.module(*[td.get(k) for k in m.in_keys]))
            else:
                td = m.forward(td)
        return td
