"""Observation encoders: vector and image observations -> one feature vector, and DrQ's random shift.

Shapes come from the env's specs, never from YAML (STYLE §3):

* vector observations (float, one dimension per sample: ``"rangefinder"``, ``"state"``) are
  concatenated and mapped to [-1, 1] with the bounds of their ``Bounded`` spec (entries with
  infinite bounds pass through unscaled), then, with ``obs_norm`` (PPO), standardised by running
  statistics (:class:`RunningNorm`, updated by the training loop and saved with the network);
* image observations (three dimensions per sample: ``"pixels"`` uint8 [3,H,W], ``"depth"``
  float [1,H,W]) are stacked along channels and go through a small CNN (DrQ-style: 3x3 convs,
  then a linear layer, LayerNorm and tanh) whose feature vector is concatenated to the vectors.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torchrl.data import Bounded, Composite

def _finite_bounds(spec) -> tuple[torch.Tensor, torch.Tensor] | None:
    if isinstance(spec, Bounded):
        lo, hi = spec.space.low.float(), spec.space.high.float()
        if torch.isfinite(lo).all() and torch.isfinite(hi).all():
            return lo, hi
    return None


def split_obs_keys(obs_spec: Composite, keys: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split observation keys into vector keys (1 dim per sample) and image keys (3 dims per sample)."""
    vec, img = [], []
    nb = len(obs_spec.shape)
    for k in keys:
        if k not in obs_spec.keys():
            raise ValueError(f"observation key {k!r} is not in the env's observation spec {sorted(obs_spec.keys())}")
        nd = len(obs_spec[k].shape) - nb
        if nd == 1:
            vec.append(k)
        elif nd == 3:
            img.append(k)
        else:
            raise ValueError(f"observation {k!r} has {nd} dims per sample; expected 1 (vector) or 3 (image)")
    return vec, img


class RunningNorm(nn.Module):
    """Standardises ``[..., D]`` features by running mean and variance (Welford / Chan's parallel merge), clipped to
    ``[-clip, clip]``: the observation normalisation of PPO (SB3's ``VecNormalize``, TorchRL's ``VecNorm``), kept INSIDE
    the network so a checkpoint carries its statistics and evaluation feeds the actor exactly what it learnt on.

    The statistics move only in :meth:`update` (the training loop calls it on each collected batch), in place: TorchRL's
    losses hold the same tensors (``convert_to_functional``) and see every update. Float64 statistics, float32 output.
    """

    def __init__(self, dim: int, clip: float = 10.0, eps: float = 1e-8):
        super().__init__()
        self.clip, self.eps = float(clip), float(eps)
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("var", torch.ones(dim, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).double()
        n = float(x.shape[0])
        if n == 0:
            return
        b_mean, b_var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = b_mean - self.mean
        m2 = self.var * self.count + b_var * n + delta.pow(2) * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self.mean.to(x.dtype), (self.var + self.eps).sqrt().to(x.dtype)
        return ((x - mean) / std).clamp(-self.clip, self.clip)  # not in place: GAE runs the critic under vmap


class ObsEncoder(nn.Module):
    """Observation tensors (in ``keys`` order) -> one feature vector ``[B, out_dim]``.

    Args:
        obs_spec: the env's observation spec (batch dims of the env are ignored).
        keys: observation keys fed to the network, in the order ``forward`` receives them.
        cnn_channels: channels of the conv layers.
        feature_dim: size of the image feature vector.
        cnn_kernels: kernel size of each conv layer (default 3 for all: DrQ's encoder).
        cnn_strides: stride of each conv layer (default 2 for the first, 1 for the rest). DrQ's encoder costs
            ~33 MFLOP per 64x64 frame; a Nature-DQN-shaped one (kernels 8, 4, 3, strides 4, 2, 1) ~2 MFLOP, which
            is what makes camera training fit a CPU budget.
        obs_norm: standardise the vector features by running statistics (:class:`RunningNorm`; PPO).
    """

    def __init__(self, obs_spec: Composite, keys: Sequence[str], cnn_channels: Sequence[int] = (32, 32, 32), feature_dim: int = 50,
                 cnn_kernels: Sequence[int] | None = None, cnn_strides: Sequence[int] | None = None, obs_norm: bool = False):
        super().__init__()
        self.keys = list(keys)
        self.vec_keys, self.img_keys = split_obs_keys(obs_spec, keys)
        self._vec_pos = [self.keys.index(k) for k in self.vec_keys]
        self._img_pos = [self.keys.index(k) for k in self.img_keys]
        nb = len(obs_spec.shape)
        los, his, self.vec_dim = [], [], 0
        self.vec_dims: list[int] = []  # per vector key, in vec_keys order: its slice of the features
        for k in self.vec_keys:
            s = obs_spec[k]
            n = s.shape[-1]
            self.vec_dims.append(int(n))
            b = _finite_bounds(s)
            if b is None:
                lo, hi = -torch.ones(n), torch.ones(n)
            else:
                lo, hi = b[0].reshape(-1, n)[0], b[1].reshape(-1, n)[0]
            los.append(lo)
            his.append(hi)
            self.vec_dim += n
        if self.vec_keys:
            lo, hi = torch.cat(los), torch.cat(his)
            self.register_buffer("vec_mid", (hi + lo) / 2)
            self.register_buffer("vec_inv_half", 2.0 / (hi - lo).clamp_min(1e-6))
        self.img_dim = 0
        if self.img_keys:
            shapes = [tuple(obs_spec[k].shape[nb:]) for k in self.img_keys]
            if len({s[1:] for s in shapes}) != 1:
                raise ValueError(f"image observations must share H, W; got {dict(zip(self.img_keys, shapes))}")
            scales = []
            for k, shp in zip(self.img_keys, shapes):
                s = obs_spec[k]
                if s.dtype == torch.uint8:
                    scales.append(torch.full((shp[0],), 1.0 / 255.0))
                else:
                    b = _finite_bounds(s)
                    hi = 1.0 if b is None else float(b[1].abs().max().clamp_min(1e-6))
                    scales.append(torch.full((shp[0],), 1.0 / hi))
            self.register_buffer("img_scale", torch.cat(scales)[:, None, None])
            c, h, w = sum(s[0] for s in shapes), shapes[0][1], shapes[0][2]
            n = len(cnn_channels)
            kernels = [3] * n if cnn_kernels is None else [int(k) for k in cnn_kernels]
            strides = [2] + [1] * (n - 1) if cnn_strides is None else [int(k) for k in cnn_strides]
            if len(kernels) != n or len(strides) != n:
                raise ValueError(f"encoder: {n} conv channels need as many kernels and strides; got kernels {kernels}, strides {strides}")
            hi, wi = h, w
            for i, (k, st) in enumerate(zip(kernels, strides)):
                if hi < k or wi < k:
                    raise ValueError(f"encoder: a {h}x{w} (HxW) image is too small for the conv stack (kernels {kernels}, strides "
                                     f"{strides}): layer {i} gets {hi}x{wi} for a {k}x{k} kernel; allowed: a larger camera "
                                     "(env.camera.height / width) or smaller algo.encoder.cnn_kernels / cnn_strides")
                hi, wi = (hi - k) // st + 1, (wi - k) // st + 1
            layers, ci = [], c
            for co, k, st in zip(cnn_channels, kernels, strides):
                layers += [nn.Conv2d(ci, co, k, stride=st), nn.ReLU()]
                ci = co
            self.cnn = nn.Sequential(*layers, nn.Flatten())
            with torch.no_grad():
                n_flat = self.cnn(torch.zeros(1, c, h, w)).shape[-1]
            self.img_head = nn.Sequential(nn.Linear(n_flat, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())
            self.img_dim = feature_dim
        self.out_dim = self.vec_dim + self.img_dim
        self.norm = RunningNorm(self.vec_dim) if obs_norm and self.vec_dim else None
        self._one_vec = len(self.keys) == 1 and len(self.vec_keys) == 1 and self.norm is None

    def vector(self, *obs: torch.Tensor) -> torch.Tensor:
        """The vector observations, concatenated and scaled to about [-1, 1] by their spec bounds (before ``norm``)."""
        v = obs[self._vec_pos[0]] if len(self._vec_pos) == 1 else torch.cat([obs[i] for i in self._vec_pos], -1)
        return (v - self.vec_mid) * self.vec_inv_half

    def update_norm(self, *obs: torch.Tensor) -> None:
        """Fold a batch of observations into the running statistics (no-op without ``obs_norm``)."""
        if self.norm is not None:
            self.norm.update(self.vector(*obs))

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        if self._one_vec:  # the common case, without the bookkeeping below
            return (obs[0] - self.vec_mid) * self.vec_inv_half
        return self.features(*self.prepare(*obs))

    def prepare(self, *obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The part of ``forward`` without parameters: (the vector features, scaled and standardised, if any, then the
        image observations as given). ``features(*prepare(*obs))`` is ``forward(*obs)``, the same operations; a
        batch prepared once serves every pass over it while the statistics stand still (PPO's epochs)."""
        if self._one_vec:
            return ((obs[0] - self.vec_mid) * self.vec_inv_half,)
        out = []
        if self.vec_keys:
            v = self.vector(*obs)
            out.append(v if self.norm is None else self.norm(v))
        out.extend(obs[i] for i in self._img_pos)
        return tuple(out)

    def features(self, *prepared: torch.Tensor) -> torch.Tensor:
        """The feature vector ``[B, out_dim]`` of :meth:`prepare`'s output (the image CNN, the concatenation)."""
        if not self.img_keys:
            return prepared[0]
        parts = [prepared[0]] if self.vec_keys else []
        imgs = prepared[len(parts):]
        x = imgs[0] if len(imgs) == 1 else torch.cat([i.float() for i in imgs], -3)
        batch = x.shape[:-3]
        x = x.reshape(-1, *x.shape[-3:]).float() * self.img_scale - 0.5
        parts.append(self.img_head(self.cnn(x)).reshape(*batch, -1))
        return parts[0] if len(parts) == 1 else torch.cat(parts, -1)


def mlp(in_dim: int, hidden: Sequence[int], out_dim: int) -> nn.Sequential:
    """ReLU MLP with PyTorch's default initialisation (in-place ReLUs: one allocation less per layer)."""
    layers, d = [], in_dim
    for h in hidden:
        layers += [nn.Linear(d, h), nn.ReLU(inplace=True)]
        d = h
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def mlp_forward(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``net(x)`` for an :func:`mlp` without a module call per layer (~5 us each on the project's CPU): the same
    operations (``linear``, in-place ``relu``), so the same values and gradients. Forward hooks on the layers are not
    run."""
    lins = net.__dict__.get("_lins")
    if lins is None:
        lins = net.__dict__["_lins"] = [m for m in net if isinstance(m, nn.Linear)]
    *hidden, last = lins
    for lin in hidden:
        x = F.linear(x, lin.weight, lin.bias).relu_()
    return F.linear(x, last.weight, last.bias)


def shift_pad(value: Any) -> tuple[int, int]:
    """``encoder.augment_shift`` as ``(rows, cols)`` pads [pixels]: an int shifts both ways (DrQ); ``[rows, cols]``
    shifts each axis by its own amount, e.g. ``[4, 0]``: vertical only (a driving camera's pitch), leaving the
    horizontal position, which is the heading a steering label answers, untouched. ValueError (one line) otherwise."""
    vals = [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else list(value) if isinstance(value, Sequence) and not isinstance(value, str) else None
    if vals is None or len(vals) not in (1, 2) or any(isinstance(v, bool) or not float(v).is_integer() or v < 0 for v in vals):
        raise ValueError(f"encoder.augment_shift={value!r}: expected a pad in pixels >= 0 (both axes) or [rows, cols]")
    return (int(vals[0]), int(vals[-1]))


def random_shift(img: torch.Tensor, pad: int | tuple[int, int], generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ random-shift augmentation: replicate-pad by ``pad`` pixels (an int, or ``(rows, cols)``), crop back at a
    random offset per sample.

    Works on any dtype (uint8 frames stay uint8). ``img``: ``[B, C, H, W]``.
    """
    py, px = (pad, pad) if isinstance(pad, int) else pad
    if py <= 0 and px <= 0:
        return img
    b, c, h, w = img.shape
    x = img if img.is_floating_point() else img.float()
    padded = nn.functional.pad(x, (px, px, py, py), mode="replicate")
    if py == px:
        off = torch.randint(0, 2 * py + 1, (b, 2), generator=generator, device=img.device)
    else:  # each axis from its own range
        off = torch.stack([torch.randint(0, 2 * p + 1, (b,), generator=generator, device=img.device) for p in (py, px)], 1)
    rows = off[:, 0:1] + torch.arange(h, device=img.device)  # [B, H] rows of the padded image
    cols = off[:, 1:2] + torch.arange(w, device=img.device)  # [B, W]
    # one gather over the flattened padded frame: 3.3x faster than 4-tensor advanced indexing (26 -> 8 ms for
    # 128 frames of 3x64x96 on one CPU thread), the same result
    flat = (rows[:, :, None] * (w + 2 * px) + cols[:, None, :]).reshape(b, 1, h * w).expand(b, c, h * w)
    out = padded.reshape(b, c, -1).gather(2, flat).reshape(b, c, h, w)
    return out if img.is_floating_point() else out.to(img.dtype)

