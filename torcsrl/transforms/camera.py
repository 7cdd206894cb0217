"""Camera degradations: "pixels" uint8 [*B, 3, H, W] (and, where it makes sense, "depth" float
[*B, 1, H, W] in metres).

* Pixels stay uint8 (a float image in [0, 1] stays float). Work is done in float [0, 1], batched
  over envs; no per-image Python loops (motion blur loops over a few direction groups).
* Every length is a fraction of the image size, so 64, 84 and 128 px frames show the same
  weather. Sparse layers (rain streaks, snow flakes, mud) are drawn on a 64-row canvas and
  resized to the frame.
* Episode effects (mud, occlusion, droplets, glare, the motion-blur direction) are drawn at reset
  for the envs being reset; their masks are rendered once and cached until the next draw.
* Depth: fog (no return beyond the visibility), noise (relative), occlusion and mud (no return:
  ``depth_invalid``, default 0) accept a depth key in ``in_keys``; others reject one.
  Keys named in the option ``depth_keys`` (default ("depth",)) are treated as depth.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ._base import Degradation

__all__ = [
    "ImageDegradation",
    "Fog",
    "Rain",
    "Snow",
    "Droplets",
    "Mud",
    "Glare",
    "Darkness",
    "MotionBlur",
    "ImageNoise",
    "Occlusion",
    "CANVAS_ROWS",
]

#: rows of the canvas on which sparse layers (streaks, flakes, mud) are drawn
CANVAS_ROWS = 64

_BASE_OPTS = {"depth_keys": ("depth",), "depth_invalid": 0.0}


def to_float(x: torch.Tensor) -> torch.Tensor:
    """uint8 [0, 255] → float32 [0, 1] (a float image is returned as float32, unchanged)."""
    if x.dtype == torch.uint8:
        return x.to(torch.float32).mul_(1.0 / 255.0)
    return x.to(torch.float32)


def from_float(y: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """float [0, 1] → ``dtype`` (uint8: rounded to nearest; float: clamped to [0, 1])."""
    if dtype == torch.uint8:
        return y.mul_(255.0).add_(0.5).clamp_(0.0, 255.0).to(torch.uint8)
    return y.clamp_(0.0, 1.0).to(dtype)


def _resize(layer: torch.Tensor, H: int, W: int) -> torch.Tensor:
    if layer.shape[-2:] == (H, W):
        return layer
    down = H < layer.shape[-2]
    return F.interpolate(layer, size=(H, W), mode="bilinear", align_corners=False, antialias=down)


def _canvas(H: int, W: int) -> tuple[int, int]:
    return CANVAS_ROWS, max(1, round(CANVAS_ROWS * W / H))


def _splat(N: int, hc: int, wc: int, ys, xs, vals, radius=None) -> torch.Tensor:
    """Adds point values at canvas coordinates (ys, xs) [N, ...] → canvas [N, 1, hc, wc].

    With ``radius`` ([N, ...], canvas pixels) each point is a soft disc: its value spread over
    the 5x5 neighbourhood with weight clamp(1.5 - d / radius, 0, 1)."""
    yi = ys.round().long()
    xi = xs.round().long()
    if radius is not None:
        o = torch.arange(-2, 3, device=ys.device)
        oy = o.view(5, 1).expand(5, 5).reshape(-1)
        ox = o.view(1, 5).expand(5, 5).reshape(-1)
        yi = yi.unsqueeze(-1) + oy
        xi = xi.unsqueeze(-1) + ox
        dist = torch.sqrt((yi - ys.unsqueeze(-1)) ** 2 + (xi - xs.unsqueeze(-1)) ** 2)
        vals = vals.unsqueeze(-1) * (1.5 - dist / radius.unsqueeze(-1)).clamp(0.0, 1.0)
    ok = (yi >= 0) & (yi < hc) & (xi >= 0) & (xi < wc)
    vals = vals * ok
    flat = (yi.clamp(0, hc - 1) * wc + xi.clamp(0, wc - 1)) + (
        torch.arange(N, device=ys.device).view(N, *([1] * (yi.ndim - 1))) * (hc * wc)
    )
    canvas = torch.zeros(N * hc * wc, device=ys.device, dtype=torch.float32)
    canvas.index_put_((flat.reshape(-1),), vals.reshape(-1).to(torch.float32), accumulate=True)
    return canvas.view(N, 1, hc, wc)


class ImageDegradation(Degradation):
    """Base of the camera degradations (see the module docstring)."""

    sensor = "camera"
    default_in_keys = ("pixels",)
    options = dict(_BASE_OPTS)
    supports_depth: bool = False

    def _is_depth(self, key) -> bool:
        return key in tuple(self.opts["depth_keys"])

    def _check_options(self):
        for k in self.in_keys:
            if self._is_depth(k) and not self.supports_depth:
                raise ValueError(
                    f"{type(self).__name__} does not degrade depth ({k!r}); depth-aware camera "
                    "degradations: fog, noise, occlusion, mud, frame_drop, latency"
                )

    def _check_spec(self, key, spec):
        if len(spec.shape) < 3:
            raise TypeError(
                f"{type(self).__name__}: {key!r} must be an image [..., C, H, W], got shape "
                f"{tuple(spec.shape)}"
            )
        if not self._is_depth(key) and spec.dtype not in (torch.uint8, torch.float32, torch.float16, torch.float64):
            raise TypeError(f"{type(self).__name__}: {key!r} must be uint8 or float, got {spec.dtype}")

    #: envs per chunk: the float working set of a chunk stays in cache (and no large
    #: temporary is allocated), about twice as fast as whole-batch ops at batch 256
    chunk: int = 16

    def _degrade(self, x, key, st, reset):
        B = st["_B"]
        nb = len(B)
        self._prepare(x, st)
        if self._is_depth(key):
            return self._depth(x, st, nb)
        N = B.numel()
        if nb == 0 or N <= self.chunk:
            f = to_float(x)
            if x.dtype != torch.uint8:
                f = f.clone()
            return from_float(self._image(f, st, nb), x.dtype)
        xs = x.reshape((N,) + x.shape[nb:])
        out = torch.empty_like(xs)
        flat = {
            k: v.reshape((N,) + v.shape[nb:])
            for k, v in st.items()
            if isinstance(v, torch.Tensor) and v.shape[:nb] == B
        }
        c = self.chunk
        for i in range(0, N, c):
            sub = dict(st)
            for k, v in flat.items():
                sub[k] = v[i : i + c]
            n = min(c, N - i)
            sub["_B"] = torch.Size([n])
            f = to_float(xs[i : i + c])
            if x.dtype != torch.uint8:
                f = f.clone()
            g = self._image(f, sub, 1)
            if x.dtype == torch.uint8:
                out[i : i + c].copy_(g.mul_(255.0).add_(0.5).clamp_(0.0, 255.0))
            else:
                out[i : i + c].copy_(g.clamp_(0.0, 1.0))
        return out.reshape(x.shape)

    def _prepare(self, x, st) -> None:
        """Hook: whole-batch work before the chunks (render cached episode layers)."""

    def _image(self, f, st, nb):
        raise NotImplementedError

    def _depth(self, d, st, nb):
        raise NotImplementedError

    # env-level layers ([N_env, 1, H, W]) broadcast over a tensor [*B, ..., C, H, W]
    @staticmethod
    def layer_view(layer: torch.Tensor, f: torch.Tensor, B: torch.Size) -> torch.Tensor:
        extra = f.ndim - len(B) - 3
        return layer.reshape(tuple(B) + (1,) * extra + tuple(layer.shape[-3:]))

    # cached episode masks -----------------------------------------------------------
    def _prepare(self, x, st) -> None:
        if "dirty" in st:  # classes with an episode layer
            H, W = x.shape[-2:]
            layer = self._episode_layer(st, H, W, x.device)
            st["_layer"] = layer.reshape(tuple(st["_B"]) + tuple(layer.shape[1:]))

    def _episode_layer(self, st, H, W, device) -> torch.Tensor:
        """The cached per-env episode layer [N, 1, H, W], re-rendered for redrawn envs."""
        cache = st.setdefault("cache", {})
        dirty = st["dirty"].reshape(-1)
        if cache and bool(dirty.any()):
            idx = dirty.nonzero().squeeze(1)
            for (h, w), layer in cache.items():
                layer[idx] = self._render(st, idx, h, w)
        st["dirty"] = torch.zeros_like(st["dirty"])
        layer = cache.get((H, W))
        if layer is None:
            N = dirty.numel()
            layer = cache[(H, W)] = self._render(st, torch.arange(N, device=device), H, W)
        return layer

    def _render(self, st, idx, H, W) -> torch.Tensor:
        raise NotImplementedError

    @staticmethod
    def rows(st, name, idx):
        v = st[name]
        nb = len(st["_B"])
        return v.reshape((-1,) + tuple(v.shape[nb:]))[idx]


def _grid(H: int, W: int, device):
    """Pixel-centre coordinates as fractions: ys [H, 1] of H, xs [1, W] of W."""
    ys = (torch.arange(H, device=device, dtype=torch.float32) + 0.5) / H
    xs = (torch.arange(W, device=device, dtype=torch.float32) + 0.5) / W
    return ys.view(H, 1), xs.view(1, W)


def ground_distance(
    H: int, cam_height: float, pitch: float, vfov: float, device=None, z_depth: bool = False
) -> torch.Tensor:
    """Distance [m] to the flat ground seen by each image row [H] (inf at and above the horizon)
    for a pinhole camera ``cam_height`` metres up, pitched ``pitch`` degrees down, with a vertical
    field of view of ``vfov`` degrees: the ray length, or with ``z_depth`` the depth along the
    optical axis (what a depth camera reports)."""
    ys = (torch.arange(H, device=device, dtype=torch.float64) + 0.5) / H
    f = 0.5 / math.tan(math.radians(vfov) / 2)
    a = torch.atan((ys - 0.5) / f)  # angle below the optical axis
    theta = a + math.radians(pitch)  # angle below the horizontal
    r = cam_height / torch.sin(theta).clamp_min(1e-9)
    if z_depth:
        r = r * torch.cos(a)
    return torch.where(theta > 1e-6, r, torch.full_like(r, float("inf"))).to(torch.float32)


# ------------------------------------------------------------------------ fog
class Fog(ImageDegradation):
    """``camera.fog``: I = J·t + A·(1 − t), t = exp(−β·d), d = depth / ``depth_scale`` (100 m)
    clipped to [0, 1]; airlight A = 0.8 (or an RGB triple). β = 0.3, 0.7, 1.2, 2.0, 3.0.

    d comes from the depth image when the tensordict has ``depth_key`` ("depth"); otherwise from
    a row-based proxy: the flat ground seen by the camera (``cam_height`` 1.07 m, ``pitch`` 8°
    down, ``vfov`` 60°: the env's hood mount), the sky far. With "depth" in ``in_keys`` the depth
    image loses the pixels whose contrast falls below 5 % (t < 0.05): they read
    ``depth_invalid``.
    """

    name = "camera.fog"
    ladder = {"beta": (0.3, 0.7, 1.2, 2.0, 3.0)}
    options = {
        **_BASE_OPTS,
        "airlight": 0.8,
        "depth_key": "depth",
        "depth_scale": 100.0,
        "cam_height": 1.07,
        "pitch": 8.0,
        "vfov": 60.0,
        "t_min": 0.05,
    }
    stochastic = False
    supports_depth = True

    def _run(self, td, st, reset, pairs=None):
        d = td.get(self.opts["depth_key"], None)
        st["_depth_now"] = d
        try:
            return super()._run(td, st, reset, pairs)
        finally:
            st.pop("_depth_now", None)

    def _dnorm(self, d):
        d = torch.nan_to_num(d, nan=float("inf"), posinf=float("inf"))
        d = torch.where(d > 0, d, torch.full_like(d, float("inf")))
        return (d / float(self.opts["depth_scale"])).clamp_(max=1.0)

    def _transmission(self, f, st, nb):
        """t = exp(−β·d) broadcastable against ``f`` [*B, ..., C, H, W]."""
        H = f.shape[-2]
        d = st.get("_depth_now")
        if d is not None and d.shape[-2:] == f.shape[-2:]:
            dn = self._dnorm(d.to(f.device, torch.float32))  # [*B, ..., 1, H, W]
            return torch.exp(-self.bview(st["beta"], dn, nb) * dn)
        o = self.opts
        g = ground_distance(H, o["cam_height"], o["pitch"], o["vfov"], f.device)
        dn = (g / float(o["depth_scale"])).clamp(max=1.0).view(H, 1)  # row proxy
        return torch.exp(-self.bview(st["beta"], f, nb) * dn)  # [*B, ..., 1, H, 1]

    def _airlight(self, f):
        A = self.opts["airlight"]
        if isinstance(A, (int, float)):
            return float(A)
        return torch.as_tensor(A, dtype=f.dtype, device=f.device).view(3, 1, 1)

    def _image(self, f, st, nb):
        t = self._transmission(f, st, nb)
        A = self._airlight(f)
        # J·t + A(1 − t) = A + (J − A)·t
        return f.sub_(A).mul_(t).add_(A)

    def _depth(self, d, st, nb):
        t = torch.exp(-self.bview(st["beta"], d, nb) * self._dnorm(d))
        return d.masked_fill(t < float(self.opts["t_min"]), float(self.opts["depth_invalid"]))


# ------------------------------------------------------------------------ rain / snow
class Rain(ImageDegradation):
    """``camera.rain``: slanted streaks + dimming. ``density`` streaks per canvas pixel,
    ``length`` as a fraction of H, ``dim`` the brightness gain. The wind slant is drawn per env
    at each reset (|angle| <= ``max_angle`` = 20°); the streaks are redrawn every step."""

    name = "camera.rain"
    ladder = {
        "density": (0.002, 0.004, 0.008, 0.015, 0.03),
        "length": (0.06, 0.08, 0.10, 0.12, 0.15),
        "dim": (0.95, 0.9, 0.85, 0.8, 0.75),
    }
    kinds = {"density": "prob", "dim": "prob"}
    options = {**_BASE_OPTS, "max_angle": 20.0, "opacity": 0.7, "color": 0.85}
    episodic = True

    def _draw_faults(self, p, B, device):
        a = math.radians(float(self.opts["max_angle"]))
        return {"angle": (self.rand(B, device) * 2 - 1) * a}

    def _streaks(self, st, H, W, device) -> torch.Tensor:
        hc, wc = _canvas(H, W)
        N = st["severity"].numel()
        dens = st["density"].reshape(N)
        M = max(1, math.ceil(float(dens.max()) * hc * wc))
        T = max(2, math.ceil(float(st["length"].max()) * hc) + 1)
        u = self.rand((N, M, 3), device)
        L = st["length"].reshape(N, 1, 1) * hc
        y0 = u[..., 0:1] * (hc + L) - L
        x0 = u[..., 1:2] * wc
        inten = 0.6 + 0.4 * u[..., 2:3]
        valid = (torch.arange(M, device=device).view(1, M, 1) < (dens * hc * wc).view(N, 1, 1))
        t = torch.arange(T, device=device, dtype=torch.float32).view(1, 1, T)
        ang = st["angle"].reshape(N, 1, 1)
        ys = y0 + t * torch.cos(ang)
        xs = x0 + t * torch.sin(ang)
        vals = inten * valid * (t <= L)
        layer = _splat(N, hc, wc, ys, xs, vals).clamp_(max=1.0)
        return _resize(layer, H, W)

    def _image(self, f, st, nb):
        H, W = f.shape[-2:]
        s = self.layer_view(self._streaks(st, H, W, f.device), f, st["_B"])
        f = f.mul_(self.bview(st["dim"], f, nb))
        a = s * float(self.opts["opacity"])
        # f + a·(c − f)
        return f.add_(a * (float(self.opts["color"]) - f))


class Snow(ImageDegradation):
    """``camera.snow``: flakes (``density`` per canvas pixel, redrawn every step) and whitening
    (the scene washed towards white by ``whiten``)."""

    name = "camera.snow"
    ladder = {
        "density": (0.005, 0.01, 0.02, 0.035, 0.05),
        "whiten": (0.05, 0.1, 0.2, 0.3, 0.35),
    }
    kinds = {"density": "prob", "whiten": "prob"}
    options = {**_BASE_OPTS, "white": 0.9}

    def _flakes(self, st, H, W, device) -> torch.Tensor:
        hc, wc = _canvas(H, W)
        N = st["severity"].numel()
        dens = st["density"].reshape(N)
        M = max(1, math.ceil(float(dens.max()) * hc * wc))
        u = self.rand((N, M, 4), device)
        valid = torch.arange(M, device=device).view(1, M) < (dens * hc * wc).view(N, 1)
        inten = valid * (0.7 + 0.3 * u[..., 2])
        radius = 0.6 + 1.2 * u[..., 3] ** 2  # canvas px: mostly small flakes, a few big ones
        layer = _splat(N, hc, wc, u[..., 0] * hc, u[..., 1] * wc, inten, radius).clamp_(max=1.0)
        return _resize(layer, H, W)

    def _image(self, f, st, nb):
        H, W = f.shape[-2:]
        w = self.bview(st["whiten"], f, nb)
        white = float(self.opts["white"])
        f = f.mul_(1 - w).add_(w * white)
        fl = self.layer_view(self._flakes(st, H, W, f.device), f, st["_B"])
        return f.add_(fl * (1.0 - f))


# ------------------------------------------------------------------------ lens effects
class Droplets(ImageDegradation):
    """``camera.droplets``: soft discs on the lens (``count``, ``radius`` × the shorter side),
    inside which the scene is blurred and lifted. The drops stay for the episode; each env's set
    is replaced with probability ``refresh`` per step (0.02: about once a second)."""

    name = "camera.droplets"
    ladder = {"count": (2, 4, 6, 9, 12), "radius": (0.04, 0.06, 0.08, 0.10, 0.12)}
    kinds = {"count": "int"}
    options = {**_BASE_OPTS, "refresh": 0.02, "lift": 0.25, "edge": 0.25}
    episodic = True

    def _check_options(self):
        super()._check_options()
        if not 0 <= float(self.opts["refresh"]) <= 1:
            raise ValueError("Droplets: refresh is a probability in [0, 1]")
        self.n_max = max(1, int(self._ladder["count"].max()))

    def _drops(self, B, device):
        return self.rand(tuple(B) + (self.n_max, 3), device)

    def _draw_faults(self, p, B, device):
        return {"drops": self._drops(B, device), "dirty": torch.ones(B, dtype=torch.bool, device=device)}

    def _begin_step(self, st, reset):
        r = float(self.opts["refresh"])
        if reset is None and r > 0:
            ref = self.rand(st["_B"], st["_dev"]) < r
            new = self._drops(st["_B"], st["_dev"])
            st["drops"] = torch.where(ref[..., None, None], new, st["drops"])
            st["dirty"] = st["dirty"] | ref

    def _render(self, st, idx, H, W):
        drops = self.rows(st, "drops", idx)  # [n, K, 3]
        count = self.rows(st, "count", idx)
        rad = self.rows(st, "radius", idx)
        n, K = drops.shape[:2]
        ys, xs = _grid(H, W, drops.device)
        side = min(H, W)
        cy = drops[..., 0].view(n, K, 1, 1)
        cx = drops[..., 1].view(n, K, 1, 1)
        r = (rad.view(n, 1, 1, 1) * (0.6 + 0.6 * drops[..., 2].view(n, K, 1, 1))) * side
        valid = torch.arange(K, device=drops.device).view(1, K) < count.view(n, 1)
        edge = (r * float(self.opts["edge"])).clamp_min(0.75)
        out = torch.zeros(n, 1, H, W, device=drops.device)
        for j in range(min(K, int(count.max()) if n else 0)):  # running max: one mask per env
            dy = (ys.view(1, 1, H, 1) - cy[:, j : j + 1]) * H
            dx = (xs.view(1, 1, 1, W) - cx[:, j : j + 1]) * W
            dist = torch.sqrt(dy * dy + dx * dx)
            m = ((r[:, j : j + 1] - dist) / edge[:, j : j + 1]).clamp_(0.0, 1.0)
            out = torch.maximum(out, m * valid[:, j].view(n, 1, 1, 1))
        return out

    def _image(self, f, st, nb):
        H, W = f.shape[-2:]
        m = self.layer_view(st["_layer"], f, st["_B"])
        C = f.shape[-3]
        f4 = f.reshape(-1, C, H, W)
        k = max(2, round(min(H, W) / 12))
        blur = F.interpolate(
            F.avg_pool2d(f4, k, stride=k, ceil_mode=True), size=(H, W), mode="bilinear", align_corners=False
        ).reshape(f.shape)
        lift = float(self.opts["lift"])
        inside = blur.mul_(1 - lift).add_(lift)
        # f·(1 − m) + inside·m = f + m·(inside − f)
        return f.add_(m * inside.sub_(f))


class Mud(ImageDegradation):
    """``camera.mud``: opaque brown blobs on the lens covering ``area`` of the frame (2..30 %),
    for the whole episode. Blob shapes are low-frequency noise thresholded at the area's
    quantile, biased towards the bottom of the lens (spray comes from the road)."""

    name = "camera.mud"
    ladder = {"area": (0.02, 0.05, 0.10, 0.18, 0.30)}
    kinds = {"area": "prob"}
    options = {**_BASE_OPTS, "color": (0.32, 0.24, 0.15), "bottom_bias": 0.4, "softness": 0.04}
    episodic = True
    supports_depth = True
    _octaves = ((3, 1.0), (6, 0.5), (12, 0.25))

    def _draw_faults(self, p, B, device):
        n = sum(g * g for g, _ in self._octaves)
        return {
            "field": self.rand(tuple(B) + (n,), device),
            "shade": 0.8 + 0.4 * self.rand(B, device),
            "dirty": torch.ones(B, dtype=torch.bool, device=device),
        }

    def _render(self, st, idx, H, W):
        field = self.rows(st, "field", idx)
        area = self.rows(st, "area", idx)
        n = field.shape[0]
        hc, wc = _canvas(H, W)
        v = torch.zeros(n, 1, hc, wc, device=field.device)
        o = 0
        for g, amp in self._octaves:
            grid = field[:, o : o + g * g].view(n, 1, g, g)
            o += g * g
            v += amp * F.interpolate(grid, size=(hc, wc), mode="bicubic", align_corners=False)
        ys = (torch.arange(hc, device=field.device, dtype=torch.float32) + 0.5) / hc
        v += float(self.opts["bottom_bias"]) * ys.view(1, 1, hc, 1)
        flat = v.view(n, -1)
        srt = flat.sort(dim=1).values
        k = ((1.0 - area) * (flat.shape[1] - 1)).round().long().clamp(0, flat.shape[1] - 1)
        thr = srt.gather(1, k.view(n, 1)).view(n, 1, 1, 1)
        soft = float(self.opts["softness"])
        m = torch.sigmoid((v - thr) / soft)
        m = torch.where(area.view(n, 1, 1, 1) > 0, m, torch.zeros_like(m))
        return _resize(m, H, W)

    def _image(self, f, st, nb):
        H, W = f.shape[-2:]
        m = self.layer_view(st["_layer"], f, st["_B"])
        color = torch.as_tensor(self.opts["color"], dtype=f.dtype, device=f.device).view(-1, 1, 1)
        c = color * self.bview(st["shade"], f, nb)
        return f.add_(m * (c - f))

    def _depth(self, d, st, nb):
        H, W = d.shape[-2:]
        m = self.layer_view(st["_layer"], d, st["_B"])
        return d.masked_fill(m > 0.5, float(self.opts["depth_invalid"]))


class Occlusion(ImageDegradation):
    """``camera.occlusion``: 1..3 dark rectangles (tape, a wiper, a sticker) covering ``area`` of
    the frame (2..30 %) for the whole episode."""

    name = "camera.occlusion"
    ladder = {"area": (0.02, 0.05, 0.10, 0.18, 0.30)}
    kinds = {"area": "prob"}
    options = {**_BASE_OPTS, "max_rects": 3}
    episodic = True
    supports_depth = True

    def _draw_faults(self, p, B, device):
        K = int(self.opts["max_rects"])
        return {
            "rects": self.rand(tuple(B) + (K, 3), device),
            "nrect": self.randint(1, K + 1, B, device),
            "gray": 0.05 + 0.3 * self.rand(B, device),
            "dirty": torch.ones(B, dtype=torch.bool, device=device),
        }

    def _render(self, st, idx, H, W):
        rects = self.rows(st, "rects", idx)
        k = self.rows(st, "nrect", idx).float()
        area = self.rows(st, "area", idx)
        n, K = rects.shape[:2]
        a = (area / k).view(n, 1)  # each rectangle's share of the frame
        aspect = torch.exp((rects[..., 2] * 2 - 1) * math.log(2.0))  # w/h in (1/2, 2)
        w = torch.sqrt(a * aspect).clamp(max=1.0)
        h = (a / w).clamp(max=1.0)
        cx = w / 2 + rects[..., 0] * (1 - w)
        cy = h / 2 + rects[..., 1] * (1 - h)
        ys, xs = _grid(H, W, rects.device)
        inx = (xs.view(1, 1, 1, W) - cx.view(n, K, 1, 1)).abs() <= w.view(n, K, 1, 1) / 2
        iny = (ys.view(1, 1, H, 1) - cy.view(n, K, 1, 1)).abs() <= h.view(n, K, 1, 1) / 2
        valid = torch.arange(K, device=rects.device).view(1, K, 1, 1) < k.view(n, 1, 1, 1)
        m = (inx & iny & valid).any(1, keepdim=True)
        return m.to(torch.float32)

    def _image(self, f, st, nb):
        H, W = f.shape[-2:]
        m = self.layer_view(st["_layer"], f, st["_B"])
        g = self.bview(st["gray"], f, nb)
        return torch.where(m > 0.5, g.expand_as(f), f)

    def _depth(self, d, st, nb):
        H, W = d.shape[-2:]
        m = self.layer_view(st["_layer"], d, st["_B"])
        return d.masked_fill(m > 0.5, float(self.opts["depth_invalid"]))


class Glare(ImageDegradation):
    """``camera.glare``: the sun (or floodlights) in the upper half of the frame: a radial bloom
    of ``radius`` × W plus a veil over the whole frame, of ``strength``. Sun position drawn per
    env at each reset."""

    name = "camera.glare"
    ladder = {"strength": (0.3, 0.5, 0.7, 0.85, 1.0), "radius": (0.10, 0.15, 0.20, 0.28, 0.35)}
    kinds = {"strength": "prob", "radius": "pos"}
    options = {**_BASE_OPTS, "veil": 0.25, "tint": (1.0, 0.96, 0.85)}
    episodic = True

    def _draw_faults(self, p, B, device):
        u = self.rand(tuple(B) + (2,), device)
        return {"sun_x": 0.1 + 0.8 * u[..., 0], "sun_y": 0.02 + 0.38 * u[..., 1]}

    def _image(self, f, st, nb):
        H, W = f.shape[-2:]
        ys, xs = _grid(H, W, f.device)
        r = self.bview(st["radius"], f, nb)
        # distances in units of W (round bloom whatever the aspect)
        gy = torch.exp(-(((ys * H / W) - self.bview(st["sun_y"] * H / W, f, nb)) / r) ** 2)
        gx = torch.exp(-((xs - self.bview(st["sun_x"], f, nb)) / r) ** 2)
        s = self.bview(st["strength"], f, nb)
        g = (gy * gx + float(self.opts["veil"])) * s
        tint = torch.as_tensor(self.opts["tint"], dtype=f.dtype, device=f.device).view(-1, 1, 1)
        g = (g * tint).clamp_(max=1.0)
        return f.add_(g * (1.0 - f))


class Darkness(ImageDegradation):
    """``camera.darkness``: low light, gain·x^γ plus Gaussian read noise σ (every step).

    gain = .7, .5, .38, .28, .2; γ = 1.2, 1.4, 1.6, 1.8, 2.0; σ = .01, .02, .03, .045, .06.
    (The catalogue's draft s3..s5, gain .35/.25/.15 with γ up to 2.5, left a blank frame at s5:
    lane lines under 10/255; these keep them visible above the read noise.)
    The read noise is one value per pixel shared by its colour channels (luminance noise).
    On uint8 frames the tone curve is a per-env 256-entry look-up table.
    """

    name = "camera.darkness"
    ladder = {
        "gain": (0.7, 0.5, 0.38, 0.28, 0.2),
        "gamma": (1.2, 1.4, 1.6, 1.8, 2.0),
        "sigma": (0.01, 0.02, 0.03, 0.045, 0.06),
    }
    kinds = {"gain": "nonneg", "gamma": "pos"}

    def _noise(self, f, st, nb):
        shape = f.shape[:-3] + (1,) + f.shape[-2:]
        return self.randn(shape, f.device).mul_(self.bview(st["sigma"], f, nb))

    def _image(self, f, st, nb):
        y = f.pow_(self.bview(st["gamma"], f, nb)).mul_(self.bview(st["gain"], f, nb))
        return y.add_(self._noise(f, st, nb))

    def _degrade(self, x, key, st, reset):
        B = st["_B"]
        nb = len(B)
        if x.dtype != torch.uint8 or nb == 0:
            return super()._degrade(x, key, st, reset)
        N = B.numel()
        levels = torch.arange(256, dtype=torch.float32, device=x.device) / 255.0
        lut = levels.pow(st["gamma"].reshape(N, 1)).mul_(st["gain"].reshape(N, 1)).mul_(255.0)
        lut = lut.reshape(-1)
        sigma = st["sigma"].reshape(N) * 255.0
        xs = x.reshape((N, -1) + x.shape[-3:])
        out = torch.empty_like(xs)
        c = self.chunk
        for i in range(0, N, c):
            xc = xs[i : i + c]
            n = xc.shape[0]
            off = (torch.arange(i, i + n, device=x.device) * 256).view(n, 1, 1, 1, 1)
            y = torch.take(lut, xc.long().add_(off))
            noise = self.randn(xc.shape[:-3] + (1,) + xc.shape[-2:], x.device)
            y.addcmul_(noise, sigma[i : i + n].view(n, 1, 1, 1, 1))
            out[i : i + c].copy_(y.add_(0.5).clamp_(0.0, 255.0))
        return out.reshape(x.shape)


class ImageNoise(ImageDegradation):
    """``camera.noise``: additive Gaussian noise, σ = .08, .12, .18, .26, .38 (the ImageNet-C
    ladder). On depth: relative noise d·(1 + N(0, ``depth_rel``·σ))."""

    name = "camera.noise"
    ladder = {"sigma": (0.08, 0.12, 0.18, 0.26, 0.38)}
    options = {**_BASE_OPTS, "depth_rel": 0.25}
    supports_depth = True

    def _image(self, f, st, nb):
        return f.addcmul_(self.randn(f.shape, f.device), self.bview(st["sigma"], f, nb))

    def _depth(self, d, st, nb):
        s = self.bview(st["sigma"], d, nb) * float(self.opts["depth_rel"])
        y = d * (1.0 + s * self.randn(d.shape, d.device))
        return torch.where(d > 0, y.clamp_min(0.0), d)


class MotionBlur(ImageDegradation):
    """``camera.motion_blur``: a line kernel of ``length`` × W (.03 .. .15) along a direction
    drawn per env at each reset (``direction="random"``), or fixed: ``direction=<degrees>``
    (0 = horizontal, as a yawing car sees). Directions are binned to 16 and each bin is blurred
    with shifted copies, so the cost is one pass per kernel tap."""

    name = "camera.motion_blur"
    ladder = {"length": (0.03, 0.05, 0.08, 0.11, 0.15)}
    options = {**_BASE_OPTS, "direction": "random", "bins": 16}
    episodic = True

    def _check_options(self):
        super()._check_options()
        d = self.opts["direction"]
        if d != "random" and not isinstance(d, (int, float)):
            raise ValueError("MotionBlur: direction is 'random' or an angle in degrees")

    def _draw_faults(self, p, B, device):
        d = self.opts["direction"]
        if d == "random":
            return {"theta": self.rand(B, device) * math.pi}
        return {"theta": torch.full(B, math.radians(float(d)) % math.pi, device=device)}

    def _degrade(self, x, key, st, reset):
        """Envs sorted by direction bin; each bin blurred in chunks of ``chunk`` envs."""
        B = st["_B"]
        nb = len(B)
        N = B.numel()
        C, H, W = x.shape[-3:]
        xs = x.reshape(N, -1, C, H, W)  # env, frames of that env
        bins = int(self.opts["bins"])
        b = (st["theta"].reshape(N) / math.pi * bins).round().long() % bins
        Lpx = st["length"].reshape(N) * W  # kernel length in pixels
        order = torch.argsort(b, stable=True)
        sorted_b = b[order].tolist()
        xs_s = xs.index_select(0, order)
        L_s = Lpx[order]
        out_s = torch.empty_like(xs_s)
        i = 0
        while i < N:
            j = i
            while j < N and sorted_b[j] == sorted_b[i] and j - i < self.chunk:
                j += 1
            f = to_float(xs_s[i:j])
            if x.dtype != torch.uint8:
                f = f.clone()
            g = self._blur(f, sorted_b[i] * math.pi / bins, L_s[i:j])
            if x.dtype == torch.uint8:
                out_s[i:j].copy_(g.mul_(255.0).add_(0.5).clamp_(0.0, 255.0))
            else:
                out_s[i:j].copy_(g.clamp_(0.0, 1.0))
            i = j
        return torch.empty_like(xs).index_copy_(0, order, out_s).reshape(x.shape)

    @staticmethod
    def _blur(sub: torch.Tensor, th: float, L: torch.Tensor) -> torch.Tensor:
        """Line blur of ``sub`` [n, F, C, H, W] along angle ``th``, lengths ``L`` [n] px."""
        n = sub.shape[0]
        C, H, W = sub.shape[-3:]
        R = int(math.floor(float(L.max()) / 2 + 0.5))
        taps = list(range(-R, R + 1))
        # box weights, antialiased at the ends so the length is continuous in pixels
        t = torch.tensor(taps, dtype=torch.float32, device=sub.device).abs()
        w = (L.view(n, 1) / 2 + 0.5 - t.view(1, -1)).clamp(0.0, 1.0)
        w = w / w.sum(1, keepdim=True)
        offs = [(round(tp * math.sin(th)), round(tp * math.cos(th))) for tp in taps]
        m = max(max(abs(dy), abs(dx)) for dy, dx in offs)
        pad = F.pad(sub.reshape(-1, C, H, W), (m, m, m, m), mode="replicate")
        pad = pad.view(sub.shape[:-2] + (H + 2 * m, W + 2 * m))
        same = bool((w == w[:1]).all())
        acc = torch.zeros_like(sub)
        for j, (dy, dx) in enumerate(offs):
            sl = pad[..., m + dy : m + dy + H, m + dx : m + dx + W]
            if same:
                wj = float(w[0, j])
                if wj > 0:
                    acc.add_(sl, alpha=wj)
            else:
                acc.addcmul_(sl, w[:, j].view(n, 1, 1, 1, 1))
        return acc
