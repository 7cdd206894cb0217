"""Pictures of time trials: top-down trajectories coloured by speed, camera GIFs."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

def plot_trajectory(track, trace: Mapping[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """Top-down PNG: track edges, the path coloured by speed [km/h] (colour bar), start line, and a
    red cross where the episode was terminated (if it was)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    s, tp, v = (np.asarray(trace[k], dtype=float) for k in ("s", "track_pos", "speed_kmh"))
    wl, wr = track.width(s)
    d = np.where(tp >= 0, tp * wl, tp * wr)
    xy = np.asarray(track.to_world(s, d), dtype=float).reshape(-1, 2)
    span = np.ptp(np.vstack([track.left_edge, track.right_edge]), axis=0)  # [m] x, y extent
    fig, ax = plt.subplots(figsize=(7.5, float(np.clip(6.5 * span[1] / max(span[0], 1.0) + 1.2, 3.0, 9.0))))
    for edge in (track.left_edge, track.right_edge):
        closed = np.vstack([edge, edge[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.35", lw=0.8)
    start = np.stack([track.to_world(0.0, float(track.w_left[0])), track.to_world(0.0, -float(track.w_right[0]))])
    ax.plot(start[:, 0], start[:, 1], color="k", lw=2.5)
    if len(xy) > 1:
        segs = np.stack([xy[:-1], xy[1:]], axis=1)
        lc = LineCollection(segs, cmap="plasma", linewidths=2.0)
        lc.set_array(v[1:])
        lc.set_clim(0, max(50.0, float(np.nanmax(v))))
        ax.add_collection(lc)
        from mpl_toolkits.axes_grid1 import make_axes_locatable

        ax.set_aspect("equal")
        ax.autoscale_view()
        cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.1)
        fig.colorbar(lc, cax=cax, label="speed [km/h]")
        if trace.get("terminated"):
            ax.plot(xy[-1, 0], xy[-1, 1], "x", color="red", ms=14, mew=3, label="terminated")
            ax.legend(loc="upper right")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or track.name, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def write_gif(frames: np.ndarray, path: str | Path, fps: int = 10) -> Path | None:
    """Animated GIF from frames ``[T, 3, H, W]`` uint8 (PIL); None when PIL is missing."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - PIL ships with matplotlib
        return None
    imgs = []
    for f in frames:
        a = np.transpose(np.asarray(f), (1, 2, 0)).astype(np.uint8)
        scale = max(1, 160 // max(a.shape[0], 1))
        img = Image.fromarray(a).resize((a.shape[1] * scale, a.shape[0] * scale), Image.NEAREST)
        imgs.append(img)
    if not imgs:
        return None
    path = Path(path)
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=int(1000 / fps), loop=0)
    return path


