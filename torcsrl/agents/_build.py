"""Builders shared by the agents, and the factories the off-policy agents share as they are.

``ddpg.py``, ``td3.py``, ``d4pg.py`` and ``sac.py`` import :func:`make_actor` (not SAC), :func:`make_target_updater`,
:func:`make_exploration` (not SAC) and :func:`make_optimizers` (SAC extends it) from here and write only the
factories in which their algorithms differ (the critic, the loss, the update's schedule). ``cfg`` is the ``algo``
config node (``conf/algo/base.yaml`` documents every knob and its unit). Sizes and bounds come from the env's specs.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule, SoftUpdate

from torcsrl.agents.exploration import ActionNoise, BehaviourPolicy, DeviceActorModule, ParamNoiseActor, StochasticBrake
from torcsrl.envs.sensors import PRIVILEGED_SLOTS, STATE_SLOTS, TELEMETRY_SLOTS
from torcsrl.nets import Critic, DeterministicActor, ObsEncoder, shift_pad, split_obs_keys


def action_bounds(env: EnvBase) -> tuple[torch.Tensor, torch.Tensor]:
    """(low, high) of one car's action, from the env's action spec."""
    spec = env.action_spec
    n = spec.shape[-1]
    low = spec.space.low.reshape(-1, n)[0].float().clone()
    high = spec.space.high.reshape(-1, n)[0].float().clone()
    return low, high


def encoder(cfg: Any, env: EnvBase, obs_keys: list[str], obs_norm: bool = False) -> ObsEncoder:
    e = cfg.encoder
    return ObsEncoder(env.observation_spec, obs_keys, cnn_channels=tuple(e.cnn_channels), feature_dim=int(e.feature_dim),
                      cnn_kernels=e.get("cnn_kernels"), cnn_strides=e.get("cnn_strides"), obs_norm=obs_norm)


def actor(cfg: Any, env: EnvBase, obs_keys: list[str]) -> DeterministicActor:
    """mu(s); with ``algo.grip_estimate > 0`` (imitation only) it carries a grip head of ``algo.grip_hidden`` reading
    ``algo.grip_inputs`` (all the features, or the state history only), its MLP the newest ``algo.actor_readings`` of
    that history (all when null) beside the estimate (:func:`grip_layout`)."""
    low, high = action_bounds(env)
    enc = encoder(cfg, env, obs_keys)
    if float(cfg.get("grip_estimate", 0.0) or 0.0) <= 0:
        return DeterministicActor(enc, low, high, tuple(cfg.actor_hidden))
    grip_in, policy_in = grip_layout(enc, str(cfg.get("grip_inputs", "all")), cfg.get("actor_readings"))
    return DeterministicActor(enc, low, high, tuple(cfg.actor_hidden), grip_hidden=tuple(cfg.get("grip_hidden", (64,))),
                              grip_inputs=grip_in, policy_inputs=policy_in)


def grip_layout(enc: ObsEncoder, grip_inputs: str = "all", actor_readings: int | None = None) -> tuple[list[int] | None, list[int] | None]:
    """(the feature indices a grip head reads, those the actor's MLP reads) of an encoder whose vector features hold a
    state history (``state`` / ``telemetry`` as K readings, oldest first: ``state_history``). ``grip_inputs``: ``all``
    (None) or ``history`` (every reading of the history keys); ``actor_readings`` R: the MLP reads every feature but
    the history keys' readings older than the newest R (None: all). ValueError (one line) when the features hold no
    history to select from."""
    one = {"state": len(STATE_SLOTS), "telemetry": len(TELEMETRY_SLOTS)}
    if grip_inputs not in ("all", "history"):
        raise ValueError(f"algo.grip_inputs={grip_inputs!r}; allowed: all (every feature), history (the state history only)")
    start, hist, old = 0, [], set()
    for k, d in zip(enc.vec_keys, enc.vec_dims):
        if k in one:
            hist.extend(range(start, start + d))
            if actor_readings is not None:
                old.update(range(start, start + max(0, d - int(actor_readings) * one[k])))
        start += d
    if not hist and (grip_inputs == "history" or actor_readings is not None):
        raise ValueError(f"algo.grip_inputs={grip_inputs} / actor_readings={actor_readings} select from a state history, which the "
                         f"actor's observations ({', '.join(enc.keys)}) do not hold; allowed: grip_inputs=all, actor_readings=null, "
                         "or observations with state / telemetry")
    grip_in = hist if grip_inputs == "history" else None
    policy_in = None if actor_readings is None else [i for i in range(enc.out_dim) if i not in old]
    return grip_in, policy_in


def critic(cfg: Any, env: EnvBase, obs_keys: list[str], num_nets: int, out_dim: int) -> Critic:
    low, _ = action_bounds(env)
    return Critic(encoder(cfg, env, obs_keys), low.numel(), tuple(cfg.critic_hidden), num_nets=num_nets, out_dim=out_dim)


def loss_kwargs(cfg: Any, env: EnvBase, obs_keys: list[str], critic_obs_keys: list[str] | None = None) -> dict:
    """Keyword arguments shared by the losses; ``critic_obs_keys``: what the critic sees when it is not what the actor
    sees (asymmetric actor-critic; ``None`` or the same list: shared)."""
    low, high = action_bounds(env)
    _, img = split_obs_keys(env.observation_spec, obs_keys)
    out = dict(obs_keys=list(obs_keys), image_keys=img, action_low=low, action_high=high, gamma=float(cfg.gamma),
               augment_shift=shift_pad(cfg.encoder.augment_shift))
    if critic_obs_keys is not None and list(critic_obs_keys) != list(obs_keys):
        _, cimg = split_obs_keys(env.observation_spec, critic_obs_keys)
        out.update(critic_obs_keys=list(critic_obs_keys), critic_image_keys=cimg)
    return out


def value_support(cfg: Any) -> tuple[float, float]:
    """(v_min, v_max) of the categorical critic: from the config, else +-reward_scale / (1 - gamma)."""
    bound = float(cfg.reward_scale) / (1.0 - float(cfg.gamma))
    v_min = -bound if cfg.v_min is None else float(cfg.v_min)
    v_max = bound if cfg.v_max is None else float(cfg.v_max)
    return v_min, v_max


class FusedSoftUpdate(SoftUpdate):
    """TorchRL's ``SoftUpdate`` (``target <- (1 - tau) target + tau online``) as ONE ``torch._foreach_lerp_``
    over the target and online tensors, collected once: TorchRL's ``step`` walks its TensorDicts on every
    call (~0.5 ms per step for a TD3 agent on the project's CPU; this: ~0.05 ms). Same values."""

    def __init__(self, loss_module: LossModule, *, tau: float):
        super().__init__(loss_module, tau=tau)
        targets, sources = [], []
        for key, src in self._sources.items(True, True):
            key = key if isinstance(key, tuple) else (key,)
            targets.append(self._targets.get(("target_" + key[0], *key[1:])).data)
            sources.append(src.data)
        self._lists = (targets, sources)

    @torch.no_grad()
    def step(self) -> None:
        torch._foreach_lerp_(self._lists[0], self._lists[1], 1.0 - self.eps)


def target_updater(cfg: Any, loss: LossModule) -> SoftUpdate:
    """Soft target updates: ``target <- (1 - tau) target + tau online`` (:class:`FusedSoftUpdate`)."""
    return FusedSoftUpdate(loss, tau=float(cfg.tau))


def exploration(cfg: Any, actor_net: DeterministicActor, env: EnvBase, obs_keys: list[str]) -> BehaviourPolicy:
    """The behaviour policy: actor -> noise (-> stochastic brake). Deterministic under DETERMINISTIC exploration.
    It reads and writes CPU tensors (the envs' device) wherever the actor lives (:class:`DeviceActorModule`)."""
    e = cfg.exploration
    low, high = action_bounds(env)
    if e.kind == "param":
        mods = [ParamNoiseActor(actor_net, obs_keys, sigma=float(e.param_sigma), target_distance=float(e.param_target_distance),
                                resample_frames=int(e.param_resample_frames))]
    else:
        device = next(actor_net.parameters()).device
        mods = [TensorDictModule(actor_net, in_keys=list(obs_keys), out_keys=["action"]) if device.type == "cpu" else
                DeviceActorModule(actor_net, list(obs_keys), ["action"], device)]
        if e.kind in ("ou", "gaussian"):
            mods.append(ActionNoise(e.kind, low, high, sigma=list_or_float(e.sigma), theta=list_or_float(e.theta), mu=list_or_float(e.mu),
                                    dt=float(e.dt), clip=None if e.clip is None else float(e.clip), anneal_frames=int(e.anneal_frames),
                                    scale_end=float(e.scale_end)))
        elif e.kind != "none":
            raise ValueError(f"unknown exploration kind {e.kind!r}; known: gaussian, ou, param, none")
    b = cfg.stochastic_brake
    if b.enabled:
        mods.append(StochasticBrake(prob=float(b.prob), mu=float(b.mu), sigma=float(b.sigma)))
    return BehaviourPolicy(*mods)


def list_or_float(x: Any) -> float | list[float]:
    try:
        return [float(v) for v in x]
    except TypeError:
        return float(x)


class FusedAdam(torch.optim.Adam):
    """``torch.optim.Adam(fused=True)`` whose ``step`` calls the fused kernel on lists collected once.

    torch's ``step`` regroups the parameters, gradients and states on every call (~65 us of Python
    per call on the project's CPU, 1.5 calls per TD3 step); this does that once and then runs exactly
    torch's fused path (``_foreach_add_`` on the step counts, ``_fused_adam_``): same values, same
    state dict. Falls back to torch's ``step`` for anything else (closures, missing gradients, amsgrad).
    """

    def __init__(self, params, **kwargs):
        super().__init__(params, fused=True, **kwargs)
        self._lists = None

    def load_state_dict(self, state_dict) -> None:
        super().load_state_dict(state_dict)
        self._lists = None

    def step(self, closure=None):
        return self.fast_step() if closure is None else super().step(closure)

    def zero_grad(self, set_to_none: bool = True) -> None:
        if not set_to_none:
            return super().zero_grad(set_to_none)
        for group in self.param_groups:
            for p in group["params"]:
                p.grad = None

    @torch.no_grad()
    def fast_step(self) -> None:
        """``step()`` without the profiling wrapper torch installs around ``step`` (~30 us)."""
        group = self.param_groups[0]
        if len(self.param_groups) != 1 or group["amsgrad"] or group["maximize"] or group["differentiable"]:
            return super().step()
        params = group["params"]
        grads = [p.grad for p in params]
        if self._lists is None or any(g is None for g in grads):
            out = super().step()
            if all(p in self.state for p in params):
                st = [self.state[p] for p in params]
                self._lists = ([s["exp_avg"] for s in st], [s["exp_avg_sq"] for s in st], [s["step"] for s in st])
            return out
        exp_avgs, exp_avg_sqs, steps = self._lists
        beta1, beta2 = group["betas"]
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], steps, amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2,
                           weight_decay=group["weight_decay"], eps=group["eps"], maximize=False, grad_scale=None, found_inf=None)
        return None


def optimizers(cfg: Any, loss: LossModule) -> dict[str, torch.optim.Optimizer]:
    """One Adam per network (:class:`FusedAdam`, torch's fused CPU/CUDA kernel, when ``fused_adam``)."""
    kw = dict(weight_decay=float(cfg.weight_decay))
    adam = FusedAdam if cfg.fused_adam else torch.optim.Adam
    return {
        "actor": adam(list(loss.actor_network.parameters()), lr=float(cfg.actor_lr), **kw),
        "critic": adam(list(loss.qvalue_network.parameters()), lr=float(cfg.critic_lr), **kw),
    }


def _step(opt: torch.optim.Optimizer) -> None:
    fast = getattr(opt, "fast_step", None)
    fast() if fast is not None else opt.step()


@torch.no_grad()
def clip_grad_norm(params: list[torch.Tensor], max_norm: float) -> torch.Tensor:
    """``torch.nn.utils.clip_grad_norm_(params, max_norm)`` for parameters of one device and dtype, without its
    grouping and checks (~40 us a call on the project's CPU): ``g *= min(1, max_norm / (|g|_2 + 1e-6))`` with one
    norm over all gradients, the same operations (``_foreach_norm``, ``vector_norm`` of the stacked norms,
    ``_foreach_mul_``), hence the same values. Returns the total norm."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.zeros(())
    total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2.0)), 2.0)
    torch._foreach_mul_(grads, torch.clamp(float(max_norm) / (total + 1e-6), max=1.0))
    return total


#: ``algo.precision`` -> the autocast dtype of the updates (None: plain float32).
PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16}


def precision_context(precision: str, device: torch.device):
    """The autocast context of ``algo.precision`` for losses computed on ``device``.

    ``bfloat16``: mixed precision — matmuls and convolutions run in bfloat16 with float32
    accumulation; weights (online and target), gradients, optimiser state, the critics' output
    layers (Q values, D4PG logits) and the losses stay float32. Fast only where the hardware has
    bfloat16 units (x86 AVX512-BF16 or AMX, recent GPUs); elsewhere expect it to be slower.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"algo.precision={precision!r} is not known; allowed: {', '.join(PRECISIONS)}")
    dtype = PRECISIONS[precision]
    return contextlib.nullcontext() if dtype is None else torch.autocast(device_type=torch.device(device).type, dtype=dtype)


def actor_regularisers(loss: LossModule, batch, action: torch.Tensor, q: torch.Tensor, la: torch.Tensor, reg: Any) -> tuple[torch.Tensor, dict]:
    """The actor loss with its optional terms (``reg``: the ``algo`` config; ``reg.n_demo``: the last rows of
    the batch that are demonstrations, with their labels under ``expert_action``).

    * **TD3+BC** (Fujimoto & Gu 2021), ``bc_weight`` > 0: ``-Q / mean|Q| + bc_weight * |mu(s) - a*|^2`` over
      the demonstration rows (``bc_weight`` 0.4 is their alpha = 2.5).
    * **CAPS** (Mysore et al. 2021): temporal ``smooth.temporal * |mu(s) - mu(s')|^2`` and spatial
      ``smooth.spatial * |mu(s) - mu(s + N(0, smooth.spatial_sigma^2))|^2`` (image observations are not
      perturbed).
    Returns (loss, metrics): ``loss/bc``, ``loss/smooth_temporal``, ``loss/smooth_spatial`` when active.
    """
    out: dict[str, torch.Tensor] = {}
    bc_w = float(getattr(reg, "bc_weight", 0.0) or 0.0)
    n_demo = int(getattr(reg, "n_demo", 0) or 0)
    if bc_w > 0 and n_demo > 0:
        target = batch.get("expert_action")[-n_demo:]
        bc = (action[-n_demo:].float() - target).pow(2).sum(-1).mean()
        la = la / q.abs().mean().clamp_min(1e-6) + bc_w * bc
        out["loss/bc"] = bc.detach()
    sm = getattr(reg, "smooth", None)
    if sm is not None and (float(sm.temporal) > 0 or float(sm.spatial) > 0):
        actor_net = loss.actor_network
        if float(sm.temporal) > 0:
            nxt = loss.obs(batch, nxt=True)
            lt = (actor_net(*nxt).float() - action.float()).pow(2).sum(-1).mean()
            la = la + float(sm.temporal) * lt
            out["loss/smooth_temporal"] = lt.detach()
        if float(sm.spatial) > 0:
            obs = loss.obs(batch)
            img = loss.obs.image_keys
            noisy = [x if (k in img or not x.is_floating_point()) else x + float(sm.spatial_sigma) * torch.randn_like(x)
                     for k, x in zip(loss.obs.keys, obs)]
            ls = (actor_net(*noisy).float() - action.float()).pow(2).sum(-1).mean()
            la = la + float(sm.spatial) * ls
            out["loss/smooth_spatial"] = ls.detach()
    return la, out


def bc_step(loss: LossModule, optim: dict, batch, precision: str = "float32", reg: Any = None,
            aux: tuple[torch.nn.Module, float] | None = None,
            near_car: tuple[float, float] | None = None,
            slow: tuple[float, float, int, int] | None = None) -> tuple[torch.Tensor, dict]:
    """One behaviour-cloning step of the actor: ``|mu(s) - a*|^2`` on a demonstration batch, plus the CAPS
    terms of ``reg`` (the ``algo`` config; :func:`actor_regularisers`) when they are on.

    ``aux=(head, weight)`` adds ``weight * mean |head(features) - privileged|^2``: the actor's encoder features
    regress the teacher's privileged view stored in the batch (:data:`torcsrl.envs.sensors.PRIVILEGED_SLOTS`), an
    auxiliary task that makes a camera encoder learn the road's geometry; the head is not part of the actor.

    ``reg.bc_pedal_expectile`` = tau != 0.5 fits the pedal (action 1) by expectile regression: an error above the
    label (too little braking) weighs ``2 (1 - tau)``, one below ``2 tau`` (tau = 0.5 is the squared error).

    ``reg.grip_estimate`` = w > 0 (an actor with a grip head: :class:`~torcsrl.nets.DeterministicActor`) adds
    ``w * mean (grip(features) - mu)^2``, the head regressing the friction coefficient under the car in each row
    (``privileged[..., surfaceMu]``); logged as ``loss/grip`` (its mean squared error [mu^2]).

    ``near_car=(weight, reach)`` weighs each row's regression error by ``weight`` where the row's ``opponents`` sensor
    reads a car nearer than ``reach`` (in the stored units of the key: normalised by 200 m when ``env.normalize``) and 1
    elsewhere, a weighted mean (the loss stays on the squared-error scale): the rows in traffic, where a student's
    wrong pedal is a contact, count ``weight`` times as much (``algo.bc_near_car_weight``, :func:`near_car_weights`);
    ``loss/near_car_rows`` logs their share of the batch.

    ``slow=(weight, below, slot, reading)`` weighs each row's error by ``weight`` where the car's forward speed, slot
    ``slot`` of the newest ``reading``-slot reading at the end of the row's ``state`` (a state history is its readings
    concatenated, newest last), is below ``below`` (the key's stored units) — the rows at a standstill or crawling,
    where the teacher creeps off (round a hairpin, from a grid before a bend) and a student that brakes there instead
    never moves again (``algo.bc_slow_weight``, :func:`slow_weights`); ``loss/slow_rows`` logs their share. With
    ``near_car`` too a row's weight is the product.

    Returns (the regression loss, the smoothness metrics ``loss/smooth_*``, ``loss/aux``, ``loss/grip``,
    ``loss/near_car_rows`` and ``loss/slow_rows``), detached.
    """
    grip_w = float(getattr(reg, "grip_estimate", 0.0) or 0.0) if reg is not None else 0.0
    with precision_context(precision, batch.device or "cpu"):
        actor = loss.actor_network
        obs = loss.obs(batch)
        feats = actor.encoder(*obs) if (aux is not None or grip_w > 0) else None
        grip = actor.grip(feats) if grip_w > 0 else None
        action = actor(*obs) if feats is None else actor.act(feats, grip)
        err = action.float() - batch.get("expert_action")
        tau = float(getattr(reg, "bc_pedal_expectile", 0.5) if reg is not None else 0.5)
        if tau != 0.5:  # expectile regression of the pedal: braking too little (err > 0) weighs (1 - tau) / tau as much
            w = torch.where(err[..., 1] > 0, 2.0 * (1.0 - tau), 2.0 * tau)
            per_row = err[..., 0].pow(2) + w * err[..., 1].pow(2) + err[..., 2:].pow(2).sum(-1)
        else:
            per_row = err.pow(2).sum(-1)
        near, rw = {}, None
        if near_car is not None:
            rw = near_car_weights(batch.get("opponents"), *near_car)
            near = {"loss/near_car_rows": (rw != 1.0).float().mean()}
        if slow is not None:
            sw = slow_weights(batch.get("state"), *slow)
            near["loss/slow_rows"] = (sw != 1.0).float().mean()
            rw = sw if rw is None else rw * sw
        bc = per_row.mean() if rw is None else (rw * per_row).sum() / rw.sum()
        total, extra = (bc, {}) if reg is None else actor_regularisers(loss, batch, action, None, bc, reg)
        extra = {**extra, **near}
        if aux is not None:
            head, weight = aux
            la = (head(feats).float() - batch.get("privileged")).pow(2).mean()
            total = total + float(weight) * la
            extra = {**extra, "loss/aux": la.detach()}
        if grip is not None:
            i = PRIVILEGED_SLOTS.index("surfaceMu")
            mu = batch.get("privileged")[..., i:i + 1]
            lg = (grip.float() - mu).pow(2).mean()
            total = total + grip_w * lg
            extra = {**extra, "loss/grip": lg.detach()}
    optim["actor"].zero_grad(set_to_none=True)
    total.backward()
    _step(optim["actor"])
    return bc.detach(), extra


def near_car_weights(opponents: torch.Tensor, weight: float, reach: float) -> torch.Tensor:
    """Per-row weights of the imitation loss: ``weight`` where the nearest car of the ``opponents`` sensor (36 sectors,
    TORCS's convention: the free reading is the sensor's range) is nearer than ``reach`` (the key's units), else 1.
    ``opponents``: [B, 36]; returns [B] in float32."""
    near = (opponents.float().amin(-1) < float(reach)).float()
    return 1.0 + (float(weight) - 1.0) * near


def slow_weights(state: torch.Tensor, weight: float, below: float, slot: int, reading: int) -> torch.Tensor:
    """Per-row weights of the imitation loss: ``weight`` where the forward speed — slot ``slot`` of the newest reading
    (the last ``reading`` values of ``state`` [B, K * reading], a history of K readings, newest last) — is below
    ``below`` (the key's units), else 1. Returns [B] in float32."""
    speed = state.float()[..., state.shape[-1] - int(reading) + int(slot)]
    return 1.0 + (float(weight) - 1.0) * (speed < float(below)).float()


def update(loss: LossModule, optim: dict, updater: SoftUpdate, batch, n_update: int, policy_delay: int, grad_clip: float | None,
           precision: str = "float32", reg: Any = None, actor: bool = True) -> dict:
    """One gradient step: critic every call; actor (SAC: and its temperature) and targets every ``policy_delay`` calls.

    Returns tensors (``loss/...``; no ``.item()``: the loop reads them when it logs). When the batch
    comes from a prioritized buffer (it has ``priority_weight``), the per-sample priority is written
    into it. ``precision``: ``"float32"`` or ``"bfloat16"`` (:func:`precision_context`). ``reg``: the
    ``algo`` config, for the actor's optional terms (:func:`actor_regularisers`); ``actor=False``
    updates the critic only (critic pre-training on demonstrations).
    """
    prioritized = loss.tensor_keys.priority_weight in batch.keys()
    with precision_context(precision, batch.device or "cpu"):
        lq, meta = loss.value_loss(batch, td_error=prioritized)
    optim["critic"].zero_grad(set_to_none=True)
    lq.backward()
    if grad_clip:
        torch.nn.utils.clip_grad_norm_(loss.qvalue_network.parameters(), grad_clip)
    _step(optim["critic"])
    if prioritized:
        batch.set(loss.tensor_keys.priority, meta.pop("td_error").unsqueeze(-1))
    out = {"loss/qvalue": lq.detach(), **{f"loss/{k}": v for k, v in meta.items()}}
    if actor and n_update % policy_delay == 0:
        with precision_context(precision, batch.device or "cpu"):
            la, meta_a = loss.actor_loss(batch)
            action, q, log_prob = meta_a.pop("_action"), meta_a.pop("_q"), meta_a.pop("_log_prob", None)
            if reg is not None:
                la, meta_r = actor_regularisers(loss, batch, action, q, la, reg)
                meta_a.update({k.split("/", 1)[1]: v for k, v in meta_r.items()})
        optim["actor"].zero_grad(set_to_none=True)
        la.backward()
        if grad_clip:
            torch.nn.utils.clip_grad_norm_(loss.actor_network.parameters(), grad_clip)
        _step(optim["actor"])
        if log_prob is not None:  # SAC: the temperature follows the policy's entropy
            lt = loss.alpha_loss(log_prob)
            optim["alpha"].zero_grad(set_to_none=True)
            lt.backward()
            _step(optim["alpha"])
            out["loss/alpha_loss"] = lt.detach()
        updater.step()
        out["loss/actor"] = la.detach()
        out.update({f"loss/{k}": v for k, v in meta_a.items()})
    return out


# ---------------------------------------------------------------------------------------
# the factories DDPG, TD3 and D4PG share as they are (``from torcsrl.agents._build import ...``)
# ---------------------------------------------------------------------------------------
def make_actor(cfg: Any, env: EnvBase, obs_keys: list[str]):
    """mu(s) -> action in the env's bounds (:class:`~torcsrl.nets.DeterministicActor`)."""
    return actor(cfg, env, obs_keys)


def make_target_updater(cfg: Any, loss):
    """Soft target updates (:class:`FusedSoftUpdate`)."""
    return target_updater(cfg, loss)


def make_exploration(cfg: Any, actor, env: EnvBase, obs_keys: list[str]):
    """Actor -> action noise (``algo.exploration``) -> stochastic brake (:func:`exploration`)."""
    return exploration(cfg, actor, env, obs_keys)


def make_optimizers(cfg: Any, loss):
    """One Adam per network (:func:`optimizers`)."""
    return optimizers(cfg, loss)
