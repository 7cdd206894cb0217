"""PPO's clipped surrogate (Schulman et al. 2017): TorchRL's ``ClipPPOLoss``, computed on plain tensors.

:class:`ClipPPOLoss` IS TorchRL's ``ClipPPOLoss`` (a subclass: the same buffers, parameters and state-dict keys, the
same ``GAE`` value estimator, the same output keys) with its per-minibatch forward rewritten for speed on CPU.
TorchRL's forward builds TensorDicts per call, swaps the functional parameters into the networks (``to_module``),
builds and validates a ``TanhNormal`` through ``ProbabilisticActor``: a PPO update of a minibatch of 64 with 256x256
networks takes ~9.5 ms of CPU on the project's machine that way, ~3.3 ms this way, of which ~2 ms are the networks'
matmuls and Adam (``benchmarks/ppo_paths.py``). Here:

* the networks (:class:`~torcsrl.nets.TanhGaussianActor`, :class:`~torcsrl.nets.ValueNet`) are called on tensors;
* a rollout is unpacked ONCE into a :class:`PPOBatch` of tensors (:meth:`ClipPPOLoss.batch`), which the loop shuffles
  once an epoch and slices into minibatches; what does not depend on the weights is computed there, once: each
  encoder's observation scaling and running statistics (:meth:`~torcsrl.nets.ObsEncoder.prepare`; the statistics
  stand still during the epochs), and the stored action's tanh pre-image ``atanh(a)`` and change-of-variables term;
* the public :meth:`~ClipPPOLoss.actor_loss` and :meth:`~ClipPPOLoss.value_loss` take a :class:`PPOBatch` and are the
  update's fast path (not wrapped in TorchRL's exploration-mode contexts: :class:`~torcsrl.objectives.base.DirectLossMeta`);
  ``forward`` keeps TorchRL's interface (a TensorDict in, TorchRL's keys out).

What is computed is TorchRL's, operation for operation and in the same order, so the floats are the same (tested:
every output term and both networks' gradients; ``benchmarks/ppo_paths.py`` trains both paths side by side and finds
the parameters bit-identical after several iterations):

* ``log pi(a|s)`` of the stored action as ``TanhNormal.log_prob``: ``x = atanh(clamp(a, +-(1 - 1e-6)))`` (TorchRL's
  ``SafeTanhTransform`` inverse; the affine map first when the bounds are not [-1, 1]), the Gaussian's log-density
  at ``x`` summed over action dims, minus ``sum log|da/dx|``. The behaviour log-probability in the batch is what
  TorchRL's ``ProbabilisticActor`` stores: scored at the pre-tanh draw ``u`` itself, not at ``atanh(tanh(u))``; the
  two differ by rounding, and a lot where tanh saturates (``|u|`` > ~7.6), as in TorchRL;
* advantages standardised per minibatch: ``(A - mean) / max(std, 1e-6)``, unbiased std (``normalize_advantage``);
* ``r = exp(log pi - log pi_old)``; objective ``-mean(min(r A, clip(r, 1 - eps, 1 + eps) A))`` with the clip applied
  to ``log r`` as TorchRL does (``[log1p(-eps), log1p(eps)]``); ``clip_fraction``: the share of clipped ``log r``;
  ``kl_approx = mean(log pi_old - log pi)``;
* the entropy bonus ``-entropy_coeff * mean(H)``: a tanh-Gaussian has no closed-form entropy; TorchRL estimates it
  by ONE reparameterised draw per sample, ``H = -log pi(u)``, ``u = loc + eps * scale`` scored at ``u`` itself
  (``TanhNormal.rsample_and_log_prob``), an unbiased estimate of the entropy of the squashed distribution (a
  change of variables keeps ``-E log p``); so does this loss, with the same draw from torch's global generator (same
  count, same order: the same ``H``). With ``entropy_coeff = 0`` (the default) the estimate is still drawn and
  logged, without a graph: TorchRL's ``0 * H`` adds exact zeros to the gradients;
* the value loss ``critic_coeff * mean((V(s) - V_target)^2)`` (``loss_critic_type``: TorchRL's ``distance_loss``).

Where it differs from TorchRL: the options PPO here does not use are not available (value clipping, a proximal
``delay_actor`` policy, importance-ratio caps, advantage ``ValueNorm``, per-head entropy coefficients, composite
action spaces, loss masks, ``separate_losses``): the constructor does not take them. ``forward`` flattens the batch
first, so its diagnostics over the batch (``ESS``, ``explained_variance``) are one number where TorchRL gives one per
trailing index of a ``[N, T]`` batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, dispatch
from torch import distributions as D
from torch import nn
from torch.distributions.utils import _sum_rightmost
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss as _TorchRLClipPPOLoss
from torchrl.objectives.utils import distance_loss

from torcsrl.nets import TanhGaussianActor, ValueNet
from torcsrl.objectives.base import DirectLossMeta

_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))  # torch's Normal.log_prob constant, computed as torch does


class _DistParams(nn.Module):
    """The actor's (loc, std) of the pre-tanh Gaussian, for TorchRL's ``TanhNormal``."""

    def __init__(self, actor: TanhGaussianActor):
        super().__init__()
        self.actor = actor

    def forward(self, *obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.actor.dist(*obs)


def probabilistic_actor(actor: TanhGaussianActor, obs_keys: list[str], low: torch.Tensor, high: torch.Tensor) -> ProbabilisticActor:
    """``actor`` as TorchRL's ``ProbabilisticActor`` over ``TanhNormal(loc, std, low, high)`` (writes ``loc``, ``scale``,
    ``action`` and ``action_log_prob``): TorchRL's view of the policy, which :class:`ClipPPOLoss` holds (its state-dict
    keys) and the tests compare against."""
    low, high = low.to(actor.a_mid.device), high.to(actor.a_mid.device)
    params = TensorDictModule(_DistParams(actor), in_keys=list(obs_keys), out_keys=["loc", "scale"])
    return ProbabilisticActor(params, in_keys=["loc", "scale"], distribution_class=TanhNormal,
                              distribution_kwargs={"low": low, "high": high}, return_log_prob=True)


def normal_log_prob(loc: torch.Tensor, scale: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``sum_i log N(x_i; loc_i, scale_i)`` over the last dim, as ``Independent(Normal(loc, scale), 1).log_prob(x)``."""
    return (-((x - loc) ** 2) / (2 * scale**2) - scale.log() - _LOG_SQRT_2PI).sum(-1)


class SquashedGaussian:
    """TorchRL's ``TanhNormal(loc, scale, low, high)`` as the pieces PPO needs, on tensors, with TorchRL's own transform
    (``SafeTanhTransform``, composed with the affine map onto ``[low, high]`` when that is not [-1, 1]): the same
    operations in the same order as TorchRL's distribution, hence the same floats, without building one per call.

    Args:
        low, high: action bounds ``[A]``.
    """

    def __init__(self, low: torch.Tensor, high: torch.Tensor):
        self.transform = TanhNormal(torch.zeros_like(low), torch.ones_like(low), low=low, high=high).transforms[0]
        # TorchRL composes the affine map only when the bounds are not [-1, 1]; then t is SafeTanhTransform alone
        self._unit = not isinstance(self.transform, D.ComposeTransform)
        self._lim = 1.0 - torch.finfo(low.dtype).resolution

    def squash(self, u: torch.Tensor) -> torch.Tensor:
        """The action ``t(u)`` of pre-tanh values: ``tanh(u)`` clamped to ``+-(1 - 1e-6)`` (``SafeTanhTransform``), then
        the affine map onto the bounds. Without gradients and with unit bounds: the same operations without the
        transform's autograd node."""
        if self._unit and not (u.requires_grad and torch.is_grad_enabled()):
            return u.tanh().clamp_(-self._lim, self._lim)
        return self.transform(u)

    def preimage(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x, log_det) of actions ``[..., A]``: the pre-tanh value TorchRL's ``log_prob`` scores (``[..., A]``) and the
        change of variables ``-sum log|da/dx|`` (``[...]``), so that ``log pi(a) = log_det + normal_log_prob(x)``
        (``TransformedDistribution.log_prob``'s loop, once: neither part depends on the network)."""
        t = self.transform
        x = t.inv(action)
        return x, 0.0 - _sum_rightmost(t.log_abs_det_jacobian(x, action), 1 - t.domain.event_dim)

    def log_prob(self, loc: torch.Tensor, scale: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``TanhNormal(loc, scale).log_prob(action)`` ``[...]``."""
        x, log_det = self.preimage(action)
        return log_det + normal_log_prob(loc, scale, x)

    def rsample_and_log_prob(self, loc: torch.Tensor, scale: torch.Tensor, sample_shape: tuple[int, ...] = (),
                             sample: bool = True) -> tuple[torch.Tensor | None, torch.Tensor]:
        """(a, log pi(a)) of a reparameterised draw ``a = t(u)``, ``u = loc + eps * scale``, ``eps ~ N(0, 1)`` from torch's
        global generator, the log-density scored at ``u`` itself (``TanhNormal.rsample_and_log_prob``: what TorchRL's
        ``ProbabilisticActor`` stores while collecting, and its Monte-Carlo entropy). Shapes ``[*sample_shape, ..., A]``
        and ``[*sample_shape, ...]``. ``sample=False``: the log-density only (``a`` is None where the bounds are
        [-1, 1]: tanh's Jacobian needs only ``u``)."""
        u = loc + torch.empty((*sample_shape, *loc.shape), dtype=loc.dtype, device=loc.device).normal_() * scale
        a = self.squash(u) if sample or not self._unit else None
        lp = normal_log_prob(loc, scale, u)  # before the Jacobian, as TorchRL: the same gradient accumulation order
        if self._unit:  # TanhTransform.log_abs_det_jacobian, written out
            ladj = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))
        else:
            ladj = self.transform.log_abs_det_jacobian(u, a)
        return a, lp - _sum_rightmost(ladj, 1)

    def mode(self, loc: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``t(loc)`` (``TanhNormal.deterministic_sample``)."""
        return self.squash(loc)

    def entropy_estimate(self, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """``-log pi`` of one reparameterised draw, scored at its pre-tanh value ``[...]``: TorchRL's Monte-Carlo entropy
        of a ``TanhNormal`` (``samples_mc_entropy=1``: ``-rsample_and_log_prob((1,))[1].mean(0)``)."""
        return -self.rsample_and_log_prob(loc, scale, (1,), sample=False)[1].mean(0)


@dataclass
class PPOBatch:
    """A rollout (or a minibatch of it) as the tensors :class:`ClipPPOLoss` reads, flat ``[B, ...]``.

    ``batch[idx]`` indexes every tensor once (a permutation: a shuffled copy; a slice: views).

    Attributes:
        actor_in, critic_in: the actor's and the value network's inputs, prepared by their encoders
            (:meth:`~torcsrl.nets.ObsEncoder.prepare`: vector observations scaled and standardised, images as they are,
            the same image tensors in both).
        preimage: the stored actions' pre-tanh values ``[B, A]`` and ``log_det`` their change-of-variables term
            ``[B]`` (:meth:`SquashedGaussian.preimage`).
        log_prob: ``log pi_old(a|s)`` of the behaviour policy ``[B]``.
        advantage: GAE advantages ``[B, 1]``; value_target: the value network's targets ``[B, 1]``.
        next_actor_in: the actor's inputs of the next observations, prepared alike (only where the CAPS temporal term
            reads them: :meth:`ClipPPOLoss.smoothness`; else empty).
    """

    actor_in: tuple[torch.Tensor, ...]
    critic_in: tuple[torch.Tensor, ...]
    preimage: torch.Tensor
    log_det: torch.Tensor
    log_prob: torch.Tensor
    advantage: torch.Tensor
    value_target: torch.Tensor
    next_actor_in: tuple[torch.Tensor, ...] = ()

    def __len__(self) -> int:
        return self.log_prob.shape[0]

    def __getitem__(self, idx) -> "PPOBatch":
        done: dict[int, torch.Tensor] = {}

        def take(t: torch.Tensor) -> torch.Tensor:
            out = done.get(id(t))
            if out is None:
                out = done[id(t)] = t[idx]
            return out

        return PPOBatch(tuple(take(t) for t in self.actor_in), tuple(take(t) for t in self.critic_in), self.preimage[idx],
                        self.log_det[idx], self.log_prob[idx], self.advantage[idx], self.value_target[idx],
                        tuple(take(t) for t in self.next_actor_in))


class ClipPPOLoss(_TorchRLClipPPOLoss, metaclass=DirectLossMeta):
    """TorchRL's ``ClipPPOLoss`` over a tanh-Gaussian actor and a state-value network, computed on tensors (see the
    module docstring for what it computes and how it differs).

    Args:
        actor_network: the policy (:class:`~torcsrl.nets.TanhGaussianActor`: ``dist(*obs) -> (loc, std)``).
        critic_network: V(s) (:class:`~torcsrl.nets.ValueNet`: ``forward(*obs) -> [B, 1]``).

    Keyword Args:
        obs_keys: observation keys, in the order the actor takes them (and the value network, unless ``critic_obs_keys``).
        critic_obs_keys: what the value network sees when it differs from the actor's (an asymmetric critic: e.g. the
            privileged ``road`` sensor beside the actor's keys; only the value estimates and the value loss read it).
        action_low, action_high: action bounds ``[A]`` (the ``TanhNormal``'s).
        clip_epsilon: clip of the probability ratio [-].
        entropy_coeff: weight of the entropy bonus [-].
        critic_coeff: weight of the value loss [-].
        loss_critic_type: ``"l2"`` | ``"smooth_l1"`` | ``"l1"`` (TorchRL's ``distance_loss``).
        normalize_advantage: standardise the advantages per minibatch.
    """

    def __init__(self, actor_network: TanhGaussianActor, critic_network: ValueNet, *, obs_keys: list[str], action_low: torch.Tensor,
                 action_high: torch.Tensor, clip_epsilon: float = 0.2, entropy_coeff: float = 0.0, critic_coeff: float = 1.0,
                 loss_critic_type: str = "l2", normalize_advantage: bool = True, critic_obs_keys: list[str] | None = None) -> None:
        if not hasattr(actor_network, "dist"):
            raise ValueError(f"PPO needs a stochastic actor (TanhGaussianActor); got {type(actor_network).__name__}")
        policy = probabilistic_actor(actor_network, obs_keys, action_low, action_high)
        ckeys = list(critic_obs_keys or obs_keys)
        super().__init__(policy, ValueOperator(critic_network, in_keys=ckeys), clip_epsilon=float(clip_epsilon),
                         entropy_coeff=float(entropy_coeff), critic_coeff=float(critic_coeff), loss_critic_type=loss_critic_type,
                         normalize_advantage=bool(normalize_advantage))
        # the plain networks (their parameters are the ones TorchRL's functional copies hold): not submodules, so the
        # state dict keeps TorchRL's keys
        self.__dict__["actor"], self.__dict__["critic"] = actor_network, critic_network
        self.obs_keys = list(obs_keys)
        self.critic_obs_keys = ckeys  # what the value network sees (an asymmetric critic: more than the actor)
        low, high = action_low.to(actor_network.a_mid.device), action_high.to(actor_network.a_mid.device)
        self.squash = SquashedGaussian(low.float(), high.float())
        self.with_next = False  # True: batch() also prepares the next observations (the CAPS temporal term reads them)

    # the rollout as tensors ------------------------------------------------------------
    @torch.no_grad()
    def batch(self, tensordict: TensorDictBase) -> PPOBatch:
        """A rollout (any batch shape; advantages and value targets already there: run ``value_estimator`` first) as a
        flat :class:`PPOBatch` on the networks' device, with each network's observations prepared by its encoder
        (vector scaling and running statistics applied ONCE: they stand still while the epochs run; the loop updates
        them afterwards)."""
        flat = tensordict.reshape(-1)
        dev = self.actor.a_mid.device
        keys = self.tensor_keys
        obs = [flat.get(k).to(dev) for k in self.obs_keys]
        x, log_det = self.squash.preimage(flat.get(keys.action).to(dev))
        nxt = self.actor.encoder.prepare(*[flat.get(("next", k)).to(dev) for k in self.obs_keys]) if self.with_next else ()
        cobs = obs if self.critic_obs_keys == self.obs_keys else [flat.get(k).to(dev) for k in self.critic_obs_keys]
        return PPOBatch(self.actor.encoder.prepare(*obs), self.critic.encoder.prepare(*cobs), x, log_det,
                        flat.get(keys.sample_log_prob).to(dev).reshape(-1), flat.get(keys.advantage).to(dev),
                        flat.get(keys.value_target).to(dev), tuple(nxt))

    def smoothness(self, batch: PPOBatch, temporal: float = 0.0, spatial: float = 0.0, sigma: float = 0.02) -> tuple[torch.Tensor, dict]:
        """The CAPS terms (Mysore et al. 2021) on the policy's deterministic action ``mu(s) = t(loc(s))`` (what
        evaluation drives), as the off-policy actors have them (:func:`torcsrl.agents._build.actor_regularisers`):
        ``temporal * |mu(s) - mu(s')|^2`` (``s'`` the next observation: needs ``with_next``) and
        ``spatial * |mu(s) - mu(s + N(0, sigma^2))|^2`` on the prepared (standardised) vector inputs, images unperturbed.
        Returns (the weighted sum, ``loss/smooth_temporal`` / ``loss/smooth_spatial`` detached); gradients reach the actor."""
        def mean_action(inputs: tuple[torch.Tensor, ...]) -> torch.Tensor:
            return self.squash.mode(self.actor.dist_params(self.actor.encoder.features(*inputs))[0])

        mu = mean_action(batch.actor_in)
        total = mu.new_zeros(())
        out: dict[str, torch.Tensor] = {}
        if temporal > 0:
            if not batch.next_actor_in:
                raise ValueError("the CAPS temporal term needs the next observations in the batch: set ClipPPOLoss.with_next = True")
            lt = (mean_action(batch.next_actor_in) - mu).pow(2).sum(-1).mean()
            total = total + temporal * lt
            out["loss/smooth_temporal"] = lt.detach()
        if spatial > 0:
            noisy = tuple(x + sigma * torch.randn_like(x) if x.is_floating_point() and x.dim() <= 2 else x for x in batch.actor_in)
            ls = (mean_action(noisy) - mu).pow(2).sum(-1).mean()
            total = total + spatial * ls
            out["loss/smooth_spatial"] = ls.detach()
        return total, out

    def _entropy_weighted(self) -> bool:
        """``entropy_coeff != 0``, read from the buffer again only when it changes (it may be scheduled)."""
        c = self.entropy_coeff
        key = (id(c), c._version)
        if self.__dict__.get("_coeff_key") != key:
            self.__dict__["_coeff_nonzero"], self.__dict__["_coeff_key"] = bool(c != 0), key
        return self.__dict__["_coeff_nonzero"]

    def _bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """TorchRL's ``_clip_bounds`` ``(log1p(-eps), log1p(eps))``, recomputed only when ``clip_epsilon`` changes."""
        e = self.clip_epsilon
        key = (id(e), e._version)
        if self.__dict__.get("_bounds_key") != key:
            self.__dict__["_bounds_val"], self.__dict__["_bounds_key"] = self._clip_bounds, key
        return self.__dict__["_bounds_val"]

    # the two losses (the update's fast path) --------------------------------------------
    def actor_loss(self, batch: PPOBatch) -> tuple[torch.Tensor, dict]:
        """``loss_objective + loss_entropy`` (clipped surrogate and entropy bonus); gradients reach the actor only.

        The metadata (detached): ``loss_objective``, ``loss_entropy``, ``entropy``, ``kl_approx``, ``clip_fraction``,
        and ``_log_weight`` ``[B, 1]`` (``log pi - log pi_old``, for :meth:`forward`'s diagnostics)."""
        loss_objective, loss_entropy, meta = self._actor_terms(batch)
        return loss_objective + loss_entropy, meta

    def _actor_terms(self, batch: PPOBatch) -> tuple[torch.Tensor, torch.Tensor, dict]:
        adv = batch.advantage
        if self.normalize_advantage and adv.numel() > 1:  # TorchRL's _standardize (eps: float32 resolution)
            adv = (adv - adv.mean()) / adv.std().clamp_min(1e-6)
        loc, scale = self.actor.dist_params(self.actor.encoder.features(*batch.actor_in))
        log_prob = batch.log_det + normal_log_prob(loc, scale, batch.preimage)
        prev = batch.log_prob
        log_weight = (log_prob - prev).unsqueeze(-1)
        gain1 = log_weight.exp() * adv
        clipped = log_weight.clamp(*self._bounds())
        gain2 = clipped.exp() * adv
        loss_objective = (-torch.stack([gain1, gain2], -1).min(dim=-1).values).mean()
        if self._entropy_weighted():
            entropy = self.squash.entropy_estimate(loc, scale)
        else:  # the same draw and value; TorchRL's 0 x H adds exact zeros to the gradients
            with torch.no_grad():
                entropy = self.squash.entropy_estimate(loc, scale)
        loss_entropy = (-self.entropy_coeff * entropy.unsqueeze(-1)).mean()
        with torch.no_grad():
            meta = {"loss_objective": loss_objective.detach(), "loss_entropy": loss_entropy.detach(), "entropy": entropy.detach().mean(),
                    "kl_approx": (prev - log_prob.detach()).mean(), "clip_fraction": (clipped != log_weight).to(log_weight.dtype).mean(),
                    "_log_weight": log_weight.detach()}
        return loss_objective, loss_entropy, meta

    def value_loss(self, batch: PPOBatch) -> tuple[torch.Tensor, dict]:
        """``critic_coeff * mean(distance(V_target, V(s)))``; gradients reach the value network only. Metadata: the
        predictions ``_value`` ``[B, 1]``, detached."""
        value = self.critic.value(self.critic.encoder.features(*batch.critic_in))
        loss = (self.critic_coeff * distance_loss(batch.value_target, value, loss_function=self.loss_critic_type)).mean()
        return loss, {"_value": value.detach()}

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """TorchRL's interface and output keys: ``loss_objective``, ``loss_entropy``, ``loss_critic`` (with their
        graphs), ``clip_fraction``, ``entropy``, ``kl_approx``, ``explained_variance``, ``ESS``, ``max_ratio``,
        ``mean_ratio``; advantages are computed first when the batch has none, as TorchRL does. The training update
        calls :meth:`actor_loss` and :meth:`value_loss` on a :class:`PPOBatch` instead."""
        if tensordict.get(self.tensor_keys.advantage, None) is None:
            tensordict = tensordict.clone(False)
            with torch.no_grad():
                self.value_estimator(tensordict)
        batch = self.batch(tensordict)
        loss_objective, loss_entropy, meta = self._actor_terms(batch)
        loss_critic, meta_v = self.value_loss(batch)
        with torch.no_grad():
            lw = meta["_log_weight"].squeeze(-1)
            ratio = lw.exp()
            tgt, pred = batch.value_target, meta_v["_value"]
            eps = torch.finfo(tgt.dtype).eps
            ev = 1.0 - torch.var(tgt - pred, correction=0, dim=0) / (torch.var(tgt, correction=0, dim=0) + eps)
            ess = (2 * lw.logsumexp(0) - (2 * lw).logsumexp(0)).exp() / lw.shape[0]
        return TensorDict(loss_objective=loss_objective, clip_fraction=meta["clip_fraction"], kl_approx=meta["kl_approx"],
                          entropy=meta["entropy"], loss_entropy=loss_entropy, loss_critic=loss_critic, explained_variance=ev,
                          ESS=ess, max_ratio=ratio.max(), mean_ratio=ratio.mean())
