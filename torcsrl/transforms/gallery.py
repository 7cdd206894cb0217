"""Gallery: what every degradation looks like at severities 1..5.

    python -m torcsrl.transforms.gallery --out DIR [--frame FILE.png | --frame module:function]
                                         [--sizes 64 84] [--seed 0]

Writes into DIR:

* ``camera_<size>.png``: camera degradations (rows) × clean, s1..s5 (columns), per frame size;
* ``presets_<size>.png``: the weather presets, camera view;
* ``rangefinder.png``: each rangefinder degradation at s1..s5, clean beams (line) vs degraded
  (dots), range against beam angle;
* ``state.png``: the state degradations over an episode, one slot clean vs degraded.

Each cell is the last step of a short episode (so latency, held frames and stuck beams show).
The frame source is pluggable: the synthetic road frame by default; ``--frame camera`` for the
env's hood camera (pybullet, CPU renderer, with depth; :func:`hood_frame`); an image file (no
depth: camera fog then uses its row proxy); or a ``module:function`` called as
``function(H, W)`` returning pixels uint8 [3, H, W] or (pixels, depth [1, H, W] metres).
Python: :func:`make_gallery`.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tensordict import TensorDict

from .registry import PRESETS, applies_to, degradation_names, make_degradation, make_preset
from .synthetic import road_sequence, track_scans

__all__ = ["make_gallery", "load_frame_source", "hood_frame"]

FrameFn = Callable[[int, int], "torch.Tensor | tuple[torch.Tensor, torch.Tensor | None]"]

# Shorter episodes are enough for most; these knobs make slow faults visible in a short clip.
_GALLERY_PARAMS = {"rangefinder.stuck": {"onset_max": 5}, "camera.droplets": {"refresh": 0.0}}
T_STEPS = 12


def hood_frame(H: int, W: int, scene: str = "oval_straight"):
    """The env's hood camera on one of ``torcsrl.envs.gallery.SCENES`` (square frames only)."""
    if H != W:
        raise ValueError("hood_frame renders square frames")
    # deferred: the scene renderer (pybullet), only when a gallery is drawn
    from torcsrl.envs.gallery import SCENES, render_scene

    by_name = {s.name: s for s in SCENES}
    if scene not in by_name:
        raise ValueError(f"unknown scene {scene!r}; known: {sorted(by_name)}")
    out = render_scene(by_name[scene], size=H, obs_size=H)
    pix = torch.from_numpy(out["hood"].copy()).permute(2, 0, 1).contiguous().to(torch.uint8)
    depth = torch.from_numpy(out["depth"].copy()).to(torch.float32).unsqueeze(0)
    return pix, depth


def load_frame_source(spec: str | None) -> FrameFn | None:
    """``None`` → synthetic; ``"camera"`` or ``"camera:<scene>"`` → the env's hood camera;
    ``path.png`` → that image (resized); ``module:function``."""
    if spec is None:
        return None
    if spec == "camera" or spec.startswith("camera:"):
        scene = spec.split(":", 1)[1] if ":" in spec else "oval_straight"
        return lambda H, W: hood_frame(H, W, scene)
    if ":" in spec and not Path(spec).exists():
        mod, fn = spec.split(":", 1)
        return getattr(importlib.import_module(mod), fn)
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(f"--frame {spec}: no such file (or module:function)")

    def from_file(H: int, W: int):
        # deferred: OpenCV only when an image is written
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"cannot read image {path}")
        img = cv2.cvtColor(cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        return torch.from_numpy(img).permute(2, 0, 1).contiguous()

    return from_file


def _sequence(frame_fn: FrameFn | None, H: int, W: int, T: int):
    if frame_fn is None:
        return road_sequence(T, H, W)
    out = frame_fn(H, W)
    pix, depth = out if isinstance(out, tuple) else (out, None)
    pix = pix.to(torch.uint8)
    if pix.shape[-2:] != (H, W):
        raise ValueError(f"frame source returned {tuple(pix.shape)}, expected [3, {H}, {W}]")
    pixs = pix.unsqueeze(0).expand(T, *pix.shape).clone()
    depths = None if depth is None else depth.unsqueeze(0).expand(T, *depth.shape).clone()
    return pixs, depths


def _episode(transform, data: dict[str, torch.Tensor], T: int) -> TensorDict:
    """Run ``transform`` along a [1, T] episode and return the last step."""
    td = TensorDict({k: v.unsqueeze(0) for k, v in data.items()}, [1, T])
    td.refine_names(None, "time")
    out = transform(td)
    return out[0, -1]


def _camera_grid(rows, frame_fn, H, W, seed, path, title):
    # deferred: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pixs, depths = _sequence(frame_fn, H, W, T_STEPS)
    data = {"pixels": pixs}
    if depths is not None:
        data["depth"] = depths
    fig, axes = plt.subplots(len(rows), 6, figsize=(6 * 1.6, len(rows) * 1.6), squeeze=False)
    for r, (label, make) in enumerate(rows):
        axes[r, 0].imshow(pixs[-1].permute(1, 2, 0).numpy(), interpolation="nearest")
        for s in range(1, 6):
            t = make(s, seed)
            out = _episode(t, data, T_STEPS)
            axes[r, s].imshow(out["pixels"].permute(1, 2, 0).numpy(), interpolation="nearest")
        axes[r, 0].set_ylabel(label, fontsize=8)
    for c, name in enumerate(["clean"] + [f"s{s}" for s in range(1, 6)]):
        axes[0, c].set_title(name, fontsize=9)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _rangefinder_plot(seed, path):
    # deferred: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T = 30
    scans = track_scans(T).flip(0)  # ends on the widest bend: long beams, fog shows
    angles = torch.linspace(-90, 90, scans.shape[-1]).numpy()
    names = degradation_names("rangefinder")
    fig, axes = plt.subplots(len(names), 5, figsize=(5 * 2.4, len(names) * 1.5), squeeze=False, sharey=True)
    for r, n in enumerate(names):
        for s in range(1, 6):
            t = make_degradation(n, s, seed=seed, **_GALLERY_PARAMS.get(n, {}))
            out = _episode(t, {"rangefinder": scans}, T)["rangefinder"]
            ax = axes[r, s - 1]
            ax.plot(angles, scans[-1].numpy(), "-", color="0.6", lw=1.2, label="clean")
            ax.plot(angles, out.numpy(), "o", color="tab:red", ms=2.5, label="degraded")
            ax.set_yscale("symlog", linthresh=10)
            ax.set_ylim(0, 230)
            ax.tick_params(labelsize=6)
            if r == 0:
                ax.set_title(f"s{s}", fontsize=9)
        axes[r, 0].set_ylabel(n.split(".", 1)[1], fontsize=8)
    axes[0, 0].legend(fontsize=6, loc="upper left")
    fig.suptitle("rangefinder: range [m] vs beam angle [deg], clean (line) vs degraded (dots)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _state_plot(seed, path):
    # deferred: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T = 60
    tt = torch.arange(T, dtype=torch.float32)
    # a speed-like slot (m/s) and an angle-like slot (rad)
    state = torch.stack([20 + 10 * torch.sin(tt / 9), 0.2 * torch.sin(tt / 5)], -1)
    names = degradation_names("state")
    fig, axes = plt.subplots(len(names), 2, figsize=(9, len(names) * 1.6), squeeze=False)
    for r, n in enumerate(names):
        for c, s in enumerate((2, 5)):
            t = make_degradation(n, s, seed=seed)
            td = TensorDict({"state": state.unsqueeze(0)}, [1, T])
            td.refine_names(None, "time")
            out = t(td)["state"][0]
            ax = axes[r, c]
            ax.plot(state[:, 0].numpy(), color="0.6", lw=1.2)
            ax.plot(out[:, 0].numpy(), color="tab:red", lw=0.8)
            ax.set_title(f"{n} s{s} (speed slot)", fontsize=8)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def make_gallery(
    out: str | Path,
    frame_fn: FrameFn | None = None,
    sizes: Sequence[int] = (64, 84),
    seed: int = 0,
) -> list[Path]:
    """Writes the gallery PNGs into ``out``; returns their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    cam = [
        (n.split(".", 1)[1], (lambda n: lambda s, seed: make_degradation(
            n, s, _cam_keys(n), seed=seed, optional=True, **_GALLERY_PARAMS.get(n, {})))(n))
        for n in degradation_names("camera")
    ]
    presets = [(p, (lambda p: lambda s, seed: make_preset(p, s, seed=seed))(p)) for p in PRESETS]
    for size in sizes:
        p = out / f"camera_{size}.png"
        _camera_grid(cam, frame_fn, size, size, seed, p, f"camera degradations, {size}x{size} px")
        written.append(p)
        p = out / f"presets_{size}.png"
        _camera_grid(presets, frame_fn, size, size, seed, p, f"weather presets (camera view), {size}x{size} px")
        written.append(p)
    p = out / "rangefinder.png"
    _rangefinder_plot(seed, p)
    written.append(p)
    p = out / "state.png"
    _state_plot(seed, p)
    written.append(p)
    return written


def _cam_keys(name: str) -> list[str]:
    return list(applies_to(name))


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m torcsrl.transforms.gallery", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument(
        "--frame",
        default=None,
        help="camera[:scene] (the env's hood camera), an image file, or module:function "
        "(default: synthetic road)",
    )
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 84])
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    for p in make_gallery(a.out, load_frame_source(a.frame), a.sizes, a.seed):
        print(p)


if __name__ == "__main__":
    main()
