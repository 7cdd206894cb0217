"""Builders shared by the three agents; ``ddpg.py``, ``td3.py`` and ``d4pg.py`` call them with their differences.

``cfg`` is the ``algo`` config node (``conf/algo/base.yaml`` documents every knob and its unit).
Sizes and bounds come from the env's specs.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule, SoftUpdate

from torcsrl.agents.exploration import ActionNoise, ParamNoiseActor, StochasticBrake
from torcsrl.agents.networks import Critic, DeterministicActor, ObsEncoder, split_obs_keys


def action_bounds(env: EnvBase) -> tuple[torch.Tensor, torch.Tensor]:
    """(low, high) of one car's action, from the env's action spec."""
    spec = env.action_spec
    n = spec.shape[-1]
    low = spec.space.low.reshape(-1, n)[0].float().clone()
    high = spec.space.high.reshape(-1, n)[0].float().clone()
    return low, high


def encoder(cfg: Any, env: EnvBase, obs_keys: list[str]) -> ObsEncoder:
    return ObsEncoder(env.observation_spec, obs_keys, cnn_channels=tuple(cfg.encoder.cnn_channels), feature_dim=int(cfg.encoder.feature_dim))


def actor(cfg: Any, env: EnvBase, obs_keys: list[str]) -> DeterministicActor:
    low, high = action_bounds(env)
    return DeterministicActor(encoder(cfg, env, obs_keys), low, high, tuple(cfg.actor_hidden))


def critic(cfg: Any, env: EnvBase, obs_keys: list[str], num_nets: int, out_dim: int) -> Critic:
    low, _ = action_bounds(env)
    return Critic(encoder(cfg, env, obs_keys), low.numel(), tuple(cfg.critic_hidden), num_nets=num_nets, out_dim=out_dim)


def loss_kwargs(cfg: Any, env: EnvBase, obs_keys: list[str]) -> dict:
    low, high = action_bounds(env)
    _, img = split_obs_keys(env.observation_spec, obs_keys)
    return dict(obs_keys=list(obs_keys), image_keys=img, action_low=low, action_high=high, gamma=float(cfg.gamma),
                augment_shift=int(cfg.encoder.augment_shift))


def value_support(cfg: Any) -> tuple[float, float]:
    """(v_min, v_max) of the categorical critic: from the config, else +-reward_scale / (1 - gamma)."""
    bound = float(cfg.reward_scale) / (1.0 - float(cfg.gamma))
    v_min = -bound if cfg.v_min is None else float(cfg.v_min)
    v_max = bound if cfg.v_max is None else float(cfg.v_max)
    return v_min, v_max


def target_updater(cfg: Any, loss: LossModule) -> SoftUpdate:
    """TorchRL's SoftUpdate: ``target <- (1 - tau) target + tau online``."""
    return SoftUpdate(loss, tau=float(cfg.tau))


def exploration(cfg: Any, actor_net: DeterministicActor, env: EnvBase, obs_keys: list[str]) -> TensorDictSequential:
    """The behaviour policy: actor -> noise (-> stochastic brake). Deterministic under DETERMINISTIC exploration."""
    e = cfg.exploration
    low, high = action_bounds(env)
    if e.kind == "param":
        mods = [ParamNoiseActor(actor_net, obs_keys, sigma=float(e.param_sigma), target_distance=float(e.param_target_distance),
                                resample_frames=int(e.param_resample_frames))]
    else:
        mods = [TensorDictModule(actor_net, in_keys=list(obs_keys), out_keys=["action"])]
        if e.kind in ("ou", "gaussian"):
            mods.append(ActionNoise(e.kind, low, high, sigma=list_or_float(e.sigma), theta=list_or_float(e.theta), mu=list_or_float(e.mu),
                                    dt=float(e.dt), clip=None if e.clip is None else float(e.clip), anneal_frames=int(e.anneal_frames),
                                    scale_end=float(e.scale_end)))
        elif e.kind != "none":
            raise ValueError(f"unknown exploration kind {e.kind!r}; known: gaussian, ou, param, none")
    b = cfg.stochastic_brake
    if b.enabled:
        mods.append(StochasticBrake(prob=float(b.prob), mu=float(b.mu), sigma=float(b.sigma)))
    return TensorDictSequential(*mods)


def list_or_float(x: Any) -> float | list[float]:
    try:
        return [float(v) for v in x]
    except TypeError:
        return float(x)


def optimizers(cfg: Any, loss: LossModule) -> dict[str, torch.optim.Optimizer]:
    """One Adam per network (fused kernel on CPU when ``fused_adam``)."""
    kw = dict(weight_decay=float(cfg.weight_decay))
    if cfg.fused_adam:
        kw["fused"] = True
    return {
        "actor": torch.optim.Adam(list(loss.actor_network.parameters()), lr=float(cfg.actor_lr), **kw),
        "critic": torch.optim.Adam(list(loss.qvalue_network.parameters()), lr=float(cfg.critic_lr), **kw),
    }


def update(loss: LossModule, optim: dict, updater: SoftUpdate, batch, n_update: int, policy_delay: int, grad_clip: float | None) -> dict:
    """One gradient step: critic every call; actor and targets every ``policy_delay`` calls.

    Returns tensors (``loss/...``), and writes the per-sample priority into ``batch``.
    """
    lq, meta = loss.value_loss(batch)
    optim["critic"].zero_grad(set_to_none=True)
    lq.backward()
    if grad_clip:
        torch.nn.utils.clip_grad_norm_(loss.qvalue_network.parameters(), grad_clip)
    optim["critic"].step()
    batch.set(loss.tensor_keys.priority, meta.pop("td_error").unsqueeze(-1))
    out = {"loss/qvalue": lq.detach(), **{f"loss/{k}": v for k, v in meta.items()}}
    if n_update % policy_delay == 0:
        la, meta_a = loss.actor_loss(batch)
        optim["actor"].zero_grad(set_to_none=True)
        la.backward()
        if grad_clip:
            torch.nn.utils.clip_grad_norm_(loss.actor_network.parameters(), grad_clip)
        optim["actor"].step()
        updater.step()
        out["loss/actor"] = la.detach()
        out.update({f"loss/{k}": v for k, v in meta_a.items()})
    return out
