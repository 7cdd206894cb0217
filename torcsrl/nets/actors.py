"""Actors: the deterministic mu(s) of DDPG, TD3 and D4PG, and the tanh-Gaussian policy of SAC and PPO.

Both map an :class:`~torcsrl.nets.encoders.ObsEncoder`'s features through an MLP and a tanh into the
action bounds, and both are called the same way for evaluation: ``actor(*obs) -> action``, deterministic
(the tanh-Gaussian actor's mean action), so validation, evaluation, the report and export treat every
algorithm's driver alike (:class:`torcsrl.policies.CheckpointPolicy`).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from torcsrl.nets.encoders import ObsEncoder, mlp, mlp_forward

class _GripInputs(nn.Module):
    """What an actor's MLP reads: the encoder's features, or a selection of them (``policy_inputs``), and beside them,
    with a grip head (``grip_hidden``), the head's estimate of the road's friction mu from ``grip_inputs`` (detached:
    only its own loss trains the head). Shared by :class:`DeterministicActor` and :class:`TanhGaussianActor`, so a
    grip student's network is the tanh-Gaussian policy's mean as it is (PPO started from a DAgger student)."""

    def _build_inputs(self, encoder: ObsEncoder, grip_hidden: Sequence[int] | None, grip_inputs: Sequence[int] | None,
                      policy_inputs: Sequence[int] | None) -> int:
        """Set up the selections and the grip head; returns the MLP's input size."""
        for name, idx in (("grip_inputs", grip_inputs), ("policy_inputs", policy_inputs)):
            if idx is not None and (len(idx) == 0 or min(idx) < 0 or max(idx) >= encoder.out_dim):
                raise ValueError(f"{type(self).__name__}: {name} must index the encoder's {encoder.out_dim} features; got {len(idx)} "
                                 f"indices in [{min(idx, default=None)}, {max(idx, default=None)}]")
            # rebuilt from the config with the actor (not in the state dict: checkpoints stay as they were)
            self.register_buffer(f"_{name}", None if idx is None else torch.as_tensor(list(idx), dtype=torch.long), persistent=False)
        self._selects = policy_inputs is not None  # a plain attribute: act() reads no buffer unless it selects
        n_grip = encoder.out_dim if grip_inputs is None else len(grip_inputs)
        self.grip_head = None if grip_hidden is None else mlp(n_grip, grip_hidden, 1)
        return (encoder.out_dim if policy_inputs is None else len(policy_inputs)) + (self.grip_head is not None)

    def grip(self, x: torch.Tensor) -> torch.Tensor:
        """The grip head's estimate of the road's mu ``[..., 1]`` from the encoder's features ``x`` (a grip actor)."""
        if self.grip_head is None:
            raise AttributeError("this actor has no grip head (built without grip_hidden: algo.grip_estimate=0)")
        return mlp_forward(self.grip_head, x if self._grip_inputs is None else x.index_select(-1, self._grip_inputs))

    def _linears(self) -> list[nn.Linear]:
        """The linear layers of the policy MLP ``self.net``, in order (cached)."""
        lins = self.__dict__.get("_lins")
        if lins is None:
            lins = self.__dict__["_lins"] = [m for m in self.net if isinstance(m, nn.Linear)]
        return lins

    def mlp_input(self, x: torch.Tensor, grip: torch.Tensor | None = None) -> torch.Tensor:
        """The MLP's input from the encoder's features ``x``: the selected features, and a grip actor's estimate
        (``grip``, computed here when not given), detached."""
        if self.grip_head is not None and grip is None:
            grip = self.grip(x)
        if self._selects:
            x = x.index_select(-1, self._policy_inputs)
        if self.grip_head is not None:
            x = torch.cat([x, grip.detach().to(x.dtype)], -1)
        return x


class DeterministicActor(_GripInputs):
    """mu(s): encoder -> MLP -> tanh, rescaled to the action bounds ``[low, high]``.

    Args:
        encoder: an :class:`ObsEncoder` (owned by the actor; the critic has its own).
        action_low, action_high: action bounds (from the env's action spec).
        hidden: hidden layer sizes.
        grip_hidden: hidden sizes of a grip-estimate head (``None``: none). With one, the actor is RMA's (Kumar et al.
            2021) base policy and adaptation module in one network: the head estimates the road's friction
            coefficient mu [-] from the encoder's features (a state history carries it: wheel spin against speed) and
            the MLP reads the features and that estimate. The estimate enters the MLP detached: only its own loss
            (:func:`torcsrl.agents._build.bc_step`, ``algo.grip_estimate``: the rows' privileged mu) trains the head,
            so it stays an estimate of mu that a researcher can read (:meth:`grip`) rather than one more hidden unit.
        grip_inputs: the feature indices the grip head reads (``None``: all), e.g. a long state history only.
        policy_inputs: the feature indices the MLP reads beside the estimate (``None``: all), e.g. the newest readings of
            that history: RMA's split, a long history for the adaptation module and a short one for the policy.
    """

    def __init__(self, encoder: ObsEncoder, action_low: torch.Tensor, action_high: torch.Tensor, hidden: Sequence[int],
                 grip_hidden: Sequence[int] | None = None, grip_inputs: Sequence[int] | None = None,
                 policy_inputs: Sequence[int] | None = None):
        super().__init__()
        self.encoder = encoder
        n_in = self._build_inputs(encoder, grip_hidden, grip_inputs, policy_inputs)
        self.net = mlp(n_in, hidden, action_low.numel())
        self.register_buffer("a_mid", ((action_high + action_low) / 2).float())
        self.register_buffer("a_half", ((action_high - action_low) / 2).float())
        self._unit = bool((self.a_mid == 0).all() and (self.a_half == 1).all())

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        return self.act(self.encoder(*obs))

    def act(self, x: torch.Tensor, grip: torch.Tensor | None = None) -> torch.Tensor:
        """The action from the encoder's features ``x`` (``forward`` = ``act(encoder(*obs))``); a grip actor reads
        ``grip`` (its :meth:`grip` of ``x``, computed here when not given) beside them, detached."""
        x = self.mlp_input(x, grip)
        *hidden, last = self._linears()
        for lin in hidden:  # self.net, without a module call per layer (~5 us each)
            x = F.linear(x, lin.weight, lin.bias).relu_()
        a = torch.tanh(F.linear(x, last.weight, last.bias))
        return a if self._unit else self.a_mid + self.a_half * a


class TanhGaussianActor(_GripInputs):
    """pi(a|s): encoder -> MLP -> (loc, std) of a Gaussian, squashed by tanh into the action bounds ``[low, high]``.

    ``forward(*obs)`` is the DETERMINISTIC action ``mid + half * tanh(loc)`` (evaluation, export, validation);
    :meth:`sample` draws ``a = mid + half * tanh(loc + std * eps)`` with the reparameterisation trick and returns its
    log-density (SAC); :meth:`dist` gives (loc, std) for TorchRL's ``TanhNormal`` (PPO).

    Args:
        encoder: an :class:`ObsEncoder` (owned by the actor).
        action_low, action_high: action bounds (from the env's action spec).
        hidden: hidden layer sizes.
        state_dependent_std: the std is an output of the network (SAC, log std squashed into
            ``[log_std_min, log_std_max]`` as in CleanRL/SpinningUp) or one learnt parameter per action dimension
            (PPO, SB3's and TorchRL's default for PPO; starts at ``exp(log_std_init)``).
        log_std_min, log_std_max, log_std_init: bounds and start of ``log std`` [log action units]; ``log_std_init``
            may give one start per action dimension (e.g. ``[-1.0, 0.0]``: a quieter steer than pedal).
        grip_hidden, grip_inputs, policy_inputs: a grip head and input selections, as :class:`DeterministicActor`'s
            (a state-independent std only): the mean is then a grip student's network, the head kept as it was loaded
            (its estimate enters the MLP detached; nothing in PPO's loss trains it).
    """

    def __init__(self, encoder: ObsEncoder, action_low: torch.Tensor, action_high: torch.Tensor, hidden: Sequence[int],
                 state_dependent_std: bool = True, log_std_min: float = -5.0, log_std_max: float = 2.0,
                 log_std_init: float | Sequence[float] = 0.0, grip_hidden: Sequence[int] | None = None,
                 grip_inputs: Sequence[int] | None = None, policy_inputs: Sequence[int] | None = None):
        super().__init__()
        self.encoder = encoder
        n = action_low.numel()
        self.action_dim = n
        self.state_dependent_std = bool(state_dependent_std)
        if self.state_dependent_std and (grip_hidden is not None or policy_inputs is not None):
            raise ValueError("TanhGaussianActor: a grip head or input selection needs a state-independent std (PPO's)")
        n_in = self._build_inputs(encoder, grip_hidden, grip_inputs, policy_inputs)
        self.net = mlp(n_in, hidden, 2 * n if self.state_dependent_std else n)
        if not self.state_dependent_std:
            init = torch.as_tensor(log_std_init, dtype=torch.float32)
            if init.numel() not in (1, n):
                raise ValueError(f"log_std_init={list(init.flatten().tolist())}: one number, or one per action dimension ({n})")
            self.log_std = nn.Parameter(init.flatten().expand(n).clone() if init.numel() == 1 else init.flatten().clone())
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)
        self.register_buffer("a_mid", ((action_high + action_low) / 2).float())
        self.register_buffer("a_half", ((action_high - action_low) / 2).float())
        self._unit = bool((self.a_mid == 0).all() and (self.a_half == 1).all())

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        return self.act(self.encoder(*obs))

    def act(self, x: torch.Tensor) -> torch.Tensor:
        """The deterministic action from the encoder's features ``x``: ``mid + half * tanh(loc)``."""
        a = torch.tanh(mlp_forward(self.net, self.mlp_input(x))[..., : self.action_dim])
        return a if self._unit else self.a_mid + self.a_half * a

    def dist_params(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(loc, std) of the pre-tanh Gaussian from the encoder's features ``x``."""
        out = mlp_forward(self.net, self.mlp_input(x))
        if self.state_dependent_std:
            loc, log_std = out.chunk(2, -1)
            log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (torch.tanh(log_std) + 1)
        else:
            loc, log_std = out, self.log_std.clamp(self.log_std_min, self.log_std_max).expand_as(out)
        return loc, log_std.exp()

    def dist(self, *obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(loc, std) of the pre-tanh Gaussian at ``obs``."""
        return self.dist_params(self.encoder(*obs))

    def sample(self, *obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(a, log pi(a|s), deterministic action), ``a`` reparameterised (gradients flow through it).

        ``log pi(a|s) = log N(u; loc, std) - sum log(half * (1 - tanh(u)^2))`` with ``u`` the pre-tanh draw, the
        Jacobian term in the stable form ``2 (log 2 - u - softplus(-2u))``; the same density as TorchRL's
        ``TanhNormal(loc, std, low, high).log_prob(a)`` (tested)."""
        loc, std = self.dist(*obs)
        eps = torch.randn_like(loc)
        u = loc + std * eps
        logp = (-0.5 * eps.pow(2) - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        logp = logp - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)
        a, a_det = torch.tanh(u), torch.tanh(loc)
        if not self._unit:
            a, a_det = self.a_mid + self.a_half * a, self.a_mid + self.a_half * a_det
            logp = logp - self.a_half.log().sum()
        return a, logp, a_det
