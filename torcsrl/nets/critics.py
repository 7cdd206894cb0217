"""Critics: fused Q(s, a) ensembles (DDPG, TD3, D4PG, SAC) and the state-value network V(s) of PPO.

A critic *ensemble* (TD3's and SAC's twin critics, or one critic for DDPG/D4PG) is ONE network whose
linear layers hold stacked weights ``[E, in, out]``: the E members run in one batched matmul
(``torch.baddbmm``) instead of E separate networks — this is what makes our TD3 loop faster
than TorchRL's stock ``TD3Loss`` (which runs the members through ``vmap``) on CPU. The actor
loss needs only member 0 (DDPG, TD3, D4PG) or the minimum of the members (SAC), evaluated through
:meth:`Critic.member` / :meth:`Critic.detached` with detached weights, so no critic weight gradient
is ever computed there.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn

from torcsrl.nets.encoders import ObsEncoder, mlp, mlp_forward

class EnsembleLinear(nn.Module):
    """E independent linear layers run as one batched matmul: ``[E,B,in] -> [E,B,out]``.

    A 2-D input ``[B, in]`` is shared by all members (expanded without a copy). Each member is
    initialised like ``nn.Linear``. (Measured on the project's CPU: one ``baddbmm`` over the
    members is ~5 % faster than separate ``nn.Linear`` critics forward + backward; a single GEMM
    over the members' weights side by side, then a transpose, was ~10 % slower.)
    """

    def __init__(self, ensemble: int, in_dim: int, out_dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(ensemble, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(ensemble, 1, out_dim))
        bound = 1.0 / math.sqrt(in_dim)
        with torch.no_grad():
            for e in range(ensemble):
                w = torch.empty(out_dim, in_dim)
                nn.init.kaiming_uniform_(w, a=math.sqrt(5))
                self.weight[e].copy_(w.t())
            self.bias.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 2:
            x = x.expand(self.weight.shape[0], *x.shape)
        return ensemble_linear(x, self.weight, self.bias)


class _MemberDot(torch.autograd.Function):
    """``[E,B,H] x [E,H,1] + [E,1,1] -> [E,B,1]``: an ensemble's scalar output layer, one ``mv`` per member.

    ``torch.baddbmm`` takes a slow batched path when the output has one column (measured on the
    project's CPU, E = 2, B = H = 256, 1 thread: 90 us forward and 150 us forward + backward,
    against 20 and 100 here). Same values up to float32 rounding; exact gradients of the same maths.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x, w)
        return torch.stack([torch.mv(x[e], w[e, :, 0]) for e in range(x.shape[0])]).unsqueeze_(-1).add_(b)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        x, w = ctx.saved_tensors
        gx = g * w.transpose(1, 2) if ctx.needs_input_grad[0] else None
        gw = torch.stack([torch.mv(x[e].t(), g[e, :, 0]) for e in range(x.shape[0])]).unsqueeze_(-1) if ctx.needs_input_grad[1] else None
        gb = g.sum(1, keepdim=True) if ctx.needs_input_grad[2] else None
        return gx, gw, gb


def ensemble_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``x @ weight + bias`` per ensemble member: ``[E,B,in] x [E,in,out] -> [E,B,out]`` (the fastest kernel for the shape)."""
    if weight.shape[-1] == 1 and weight.shape[0] > 1 and x.dtype == weight.dtype:
        return _MemberDot.apply(x, weight, bias)
    return torch.baddbmm(bias, x, weight)


def _addmm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    return torch.addmm(bias, x, weight)


def _in_weight_dtype(layer, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``layer(x, weight, bias)`` in the weights' dtype: under bfloat16 autocast (``algo.precision``) the
    critics' output layer still computes Q values and logits in float32."""
    if x.dtype == weight.dtype:
        return layer(x, weight, bias)
    with torch.autocast(x.device.type, enabled=False):
        return layer(x.to(weight.dtype), weight, bias)


class Critic(nn.Module):
    """Q(s, a) ensemble: encoder(s) ++ a -> E fused MLPs -> ``[E, B, out_dim]``.

    ``out_dim`` is 1 for DDPG/TD3/SAC and the number of atoms (logits) for the D4PG categorical critic.
    Under bfloat16 autocast (``algo.precision=bfloat16``) the hidden layers run in bfloat16 and the
    output layer in float32, so Q values and logits are always float32.
    """

    def __init__(self, encoder: ObsEncoder, action_dim: int, hidden: Sequence[int], num_nets: int = 1, out_dim: int = 1):
        super().__init__()
        self.encoder = encoder
        self.num_nets, self.out_dim = num_nets, out_dim
        dims = [encoder.out_dim + action_dim, *hidden, out_dim]
        self.layers = nn.ModuleList(EnsembleLinear(num_nets, a, b) for a, b in zip(dims[:-1], dims[1:]))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        """``forward(*obs, action) -> [E, B, out_dim]``."""
        *obs, action = inputs
        x = torch.cat([self.encoder(*obs), action], -1)
        x = x.expand(self.num_nets, *x.shape)
        *hidden, head = self.layers
        for layer in hidden:  # EnsembleLinear.forward, inlined
            x = ensemble_linear(x, layer.weight, layer.bias).relu_()
        return _in_weight_dtype(ensemble_linear, x, head.weight, head.bias)

    def member(self, *inputs: torch.Tensor, index: int = 0) -> torch.Tensor:
        """Member ``index`` alone, with DETACHED weights (for the actor loss): ``[B, out_dim]``.

        Gradients flow to the inputs (the action) but never into the critic's parameters.
        """
        *obs, action = inputs
        with torch.no_grad():
            feat = self.encoder(*obs)
        x = torch.cat([feat, action], -1)
        *hidden, head = self.layers
        for layer in hidden:
            x = torch.addmm(layer.bias[index].detach(), x, layer.weight[index].detach()).relu_()
        return _in_weight_dtype(_addmm, x, head.weight[index].detach(), head.bias[index].detach())




    def detached(self, *inputs: torch.Tensor) -> torch.Tensor:
        """Every member with DETACHED weights (SAC's actor loss: the minimum of the twins): ``[E, B, out_dim]``.

        Gradients flow to the inputs (the action) but never into the critic's parameters.
        """
        *obs, action = inputs
        with torch.no_grad():
            feat = self.encoder(*obs)
        x = torch.cat([feat, action], -1)
        x = x.expand(self.num_nets, *x.shape)
        *hidden, head = self.layers
        for layer in hidden:
            x = ensemble_linear(x, layer.weight.detach(), layer.bias.detach()).relu_()
        return _in_weight_dtype(ensemble_linear, x, head.weight.detach(), head.bias.detach())

class ValueNet(nn.Module):
    """V(s): encoder -> MLP -> ``[B, 1]``, the state-value network of PPO (its own encoder, as SB3's default)."""

    def __init__(self, encoder: ObsEncoder, hidden: Sequence[int]):
        super().__init__()
        self.encoder = encoder
        self.net = mlp(encoder.out_dim, hidden, 1)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        return self.value(self.encoder(*obs))

    def value(self, x: torch.Tensor) -> torch.Tensor:
        """V ``[B, 1]`` from the encoder's features ``x`` (``forward`` = ``value(encoder(*obs))``)."""
        return mlp_forward(self.net, x)
