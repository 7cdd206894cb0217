"""Stand-in sensor readings: a road-like camera frame with a consistent depth map, and
rangefinder scans of a curved track. Used by the gallery, the benchmark and the tests (which
must run without pybullet). Deterministic (no randomness). The gallery can show the env's real
hood camera instead (``--frame camera``).
"""

from __future__ import annotations

import math

import torch

__all__ = ["road_frame", "road_sequence", "track_scan", "track_scans"]

SKY_FAR = 1000.0  # depth of the sky [m]


def road_frame(
    H: int = 84,
    W: int = 84,
    *,
    t: float = 0.0,
    cam_height: float = 8.0,
    pitch: float = 3.0,
    vfov: float = 60.0,
    road_half_width: float = 6.0,
    curvature: float = 1 / 300,
    car: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A synthetic camera frame and its depth: (pixels uint8 [3, H, W], depth float [1, H, W] m,
    z-depth along the optical axis, sky = 1000 m).

    A pinhole camera ``cam_height`` metres up (high, like a chase camera, so the road reads as a
    trapezoid), pitched ``pitch`` degrees down: sky gradient, green grass, a grey road bending
    with ``curvature`` [1/m], white edge lines, a dashed centre line that moves with ``t``
    (metres driven) and a dark red car 25 m ahead.
    """
    f = 0.5 / math.tan(math.radians(vfov) / 2)  # focal length in units of H
    ys = (torch.arange(H, dtype=torch.float64) + 0.5) / H
    xs = (torch.arange(W, dtype=torch.float64) + 0.5) / W
    a = torch.atan((ys - 0.5) / f)  # below the optical axis
    theta = (a + math.radians(pitch)).view(H, 1)  # below the horizontal
    ground = theta > 1e-6
    r = torch.where(ground, cam_height / torch.sin(theta).clamp_min(1e-9), torch.full_like(theta, SKY_FAR))
    z = torch.where(ground, r * torch.cos(a).view(H, 1), torch.full_like(theta, SKY_FAR)).clamp(max=SKY_FAR)
    D = r * torch.cos(theta)  # forward distance along the ground
    x_img = (xs.view(1, W) - 0.5) * (W / H)  # in units of H
    X = x_img * z / f  # lateral position [m]
    rel = (X - 0.5 * curvature * D * D).abs()
    horizon = 0.5 - f * math.tan(math.radians(pitch))
    img = torch.empty(3, H, W, dtype=torch.float64)
    sky_t = (ys / max(horizon, 1e-6)).clamp(0, 1).view(H, 1)
    sky = [0.45 + 0.3 * sky_t, 0.62 + 0.22 * sky_t, 0.88 + 0.07 * sky_t]
    stripe = 0.04 * torch.sin(D * 0.8) * torch.exp(-D / 30.0)  # grass texture, fading out
    grass = [0.22 + stripe, 0.48 + stripe, 0.16 + 0.5 * stripe]
    road = 0.42 - 0.04 * (D / 200).clamp(max=1)
    on_road = rel <= road_half_width
    edge = (rel > road_half_width - 0.35) & on_road
    dash = (rel < 0.12) & (torch.remainder(D + t, 6.0) < 3.0)
    for c in range(3):
        g = torch.where(on_road, road, grass[c]).expand(H, W)
        g = torch.where(edge | dash, torch.full_like(g, 0.92), g)
        img[c] = torch.where(ground, g, sky[c].expand(H, W))
    depth = z.expand(H, W).clone()
    if car:
        dc, xc_off, w, h = 25.0, 1.5, 1.8, 1.3
        Xcar = 0.5 * curvature * dc * dc + xc_off
        ph = math.radians(pitch)
        y_bot = 0.5 + f * math.tan(math.atan(cam_height / dc) - ph)
        y_top = 0.5 + f * math.tan(math.atan((cam_height - h) / dc) - ph)
        zc = dc * math.cos(ph)  # roughly: z-depth of the car's back
        x0 = 0.5 + (Xcar - w / 2) * f / zc * (H / W)
        x1 = 0.5 + (Xcar + w / 2) * f / zc * (H / W)
        X_, Y_ = xs.view(1, W), ys.view(H, 1)
        inside = (X_ >= x0) & (X_ <= x1) & (Y_ >= y_top) & (Y_ <= y_bot)
        win = inside & (Y_ < y_top + 0.35 * (y_bot - y_top))
        for c, v in enumerate((0.55, 0.08, 0.08)):
            img[c] = torch.where(inside, torch.full_like(img[c], v), img[c])
            img[c] = torch.where(win, torch.full_like(img[c], 0.12), img[c])
        depth = torch.where(inside, torch.full_like(depth, zc), depth)
    pixels = (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
    return pixels, depth.to(torch.float32).unsqueeze(0)


def road_sequence(T: int, H: int = 84, W: int = 84, speed: float = 0.8, **kw):
    """T frames driving along: (pixels [T, 3, H, W], depth [T, 1, H, W])."""
    frames = [road_frame(H, W, t=i * speed, **kw) for i in range(T)]
    return torch.stack([p for p, _ in frames]), torch.stack([d for _, d in frames])


def track_scan(
    offset: float = 0.0,
    radius: float = 150.0,
    *,
    half_width: float = 6.0,
    n_beams: int = 19,
    max_range: float = 200.0,
) -> torch.Tensor:
    """Ranges [n_beams] from a car ``offset`` metres left of the centreline of a left-hand bend
    of ``radius`` metres, facing along the track. Beam i points at linspace(-90, 90)[i] degrees
    from the heading, positive to the left. The track edges are the walls; no return beyond
    ``max_range``."""
    ang = torch.deg2rad(torch.linspace(-90.0, 90.0, n_beams, dtype=torch.float64))
    # car at origin heading +x; bend centre to the left at (0, radius - offset)
    c = torch.tensor([0.0, radius - offset], dtype=torch.float64)
    u = torch.stack([torch.cos(ang), torch.sin(ang)], -1)  # x ahead, y left
    best = torch.full((n_beams,), max_range, dtype=torch.float64)
    for rho in (radius - half_width, radius + half_width):
        # |t u - c|² = rho²  →  t² - 2 t (u·c) + |c|² - rho² = 0
        b = u @ c
        disc = b * b - (c @ c - rho * rho)
        ok = disc >= 0
        sq = disc.clamp_min(0).sqrt()
        for tt in (b - sq, b + sq):
            hit = ok & (tt > 1e-6)
            best = torch.where(hit, torch.minimum(best, tt), best)
    return best.clamp(max=max_range).to(torch.float32)


def track_scans(T: int, n_beams: int = 19) -> torch.Tensor:
    """T scans [T, n_beams] of a car weaving through bends of changing radius."""
    out = []
    for i in range(T):
        off = 3.0 * math.sin(0.15 * i)
        radius = 60.0 + 1500.0 * (0.5 + 0.5 * math.cos(0.05 * i))
        out.append(track_scan(off, radius, n_beams=n_beams))
    return torch.stack(out)
