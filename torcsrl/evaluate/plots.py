"""Pictures of time trials and races: top-down trajectories (coloured by speed, or per car with contacts), camera GIFs."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection
from mpl_toolkits.axes_grid1 import make_axes_locatable
from PIL import Image

matplotlib.use("Agg")  # files only, no display


def plot_trajectory(track, trace: Mapping[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """Top-down PNG: track edges, the path coloured by speed [km/h] (colour bar), start line, and a
    red cross where the episode was terminated (if it was)."""
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
        ax.set_aspect("equal")
        ax.autoscale_view()
        cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.1)
        fig.colorbar(lc, cax=cax, label="speed [km/h]")
        if trace.get("terminated"):
            ax.plot(xy[-1, 0], xy[-1, 1], "x", color="red", ms=14, mew=3, label="terminated")
            ax.legend(loc="upper right")
    return _save_top_down(fig, ax, path, title or track.name)


def _save_top_down(fig, ax, path: str | Path, title: str) -> Path:
    """Finish a top-down plot (equal axes in metres, the title) and write it as a PNG."""
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def write_gif(frames: np.ndarray, path: str | Path, fps: int = 10) -> Path | None:
    """Animated GIF from frames ``[T, 3, H, W]`` uint8 (PIL, a matplotlib dependency); None without frames."""
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


#: The race plot's marker of a learner's contact by where the other car was (:data:`Traffic.CONTACT_SIDES`).
_SIDE_MARKERS = {"ahead": "^", "alongside": "D", "behind": "v"}


def plot_race(track, trace: Mapping[str, object], path: str | Path, title: str = "") -> Path:
    """Top-down PNG of a race: every car's trajectory in its own colour (the learner thick, labelled), grid positions
    as dots, each collision (a contact begun) on the car involved: the learner's by where the other car was (a
    triangle up: ahead, a diamond: alongside, a triangle down: behind; :data:`Traffic.CONTACT_SIDES`), the opponents'
    as black crosses. ``trace``: ``xy [steps, cars, 2]`` (track frame), ``hits`` [(step, car[, side])] (a hit without
    a side: a cross), ``learner`` (car index)."""
    from torcsrl.envs.traffic import Traffic  # deferred: pybullet; the time trials' and the report's plots need none

    xy = np.asarray(trace["xy"], dtype=float)
    learner = int(trace.get("learner", 0))
    span = np.ptp(np.vstack([track.left_edge, track.right_edge]), axis=0)
    fig, ax = plt.subplots(figsize=(7.5, float(np.clip(6.5 * span[1] / max(span[0], 1.0) + 1.2, 3.0, 9.0))))
    for edge in (track.left_edge, track.right_edge):
        closed = np.vstack([edge, edge[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.35", lw=0.8)
    start = np.stack([track.to_world(0.0, float(track.w_left[0])), track.to_world(0.0, -float(track.w_right[0]))])
    ax.plot(start[:, 0], start[:, 1], color="k", lw=2.5)
    colors = plt.get_cmap("tab10")
    if xy.ndim == 3 and len(xy):
        for c in range(xy.shape[1]):
            lw, z = (3.2, 2) if c == learner else (1.2, 3)  # opponents on top: they share the learner's line
            label = "learner" if c == learner else f"opponent {c}"
            ax.plot(xy[:, c, 0], xy[:, c, 1], color=colors(c % 10), lw=lw, zorder=z, label=label, alpha=0.9)
            ax.plot(xy[0, c, 0], xy[0, c, 1], "o", color=colors(c % 10), ms=5, zorder=4)
        hits = [(int(h[0]), int(h[1]), h[2] if len(h) > 2 else None) for h in (trace.get("hits") or [])]
        at = lambda t, c: xy[min(t, len(xy) - 1), c]  # noqa: E731
        # a contact marks each car in it: the learner's by side, the rest (and any without a side) as crosses
        for side in Traffic.CONTACT_SIDES:
            marker = _SIDE_MARKERS[side]
            pts = [at(t, c) for t, c, s in hits if c == learner and s == side]
            if pts:
                pts = np.array(pts)
                ax.plot(pts[:, 0], pts[:, 1], marker, color="k", mfc="w", ms=8, mew=2.0, zorder=6,
                        label=f"learner's contact, other car {side} ({len(pts)})")
        rest = [at(t, c) for t, c, s in hits if c != learner or s is None]
        if rest:
            rest = np.array(rest)
            n_own = sum(1 for _, c, s in hits if c == learner and s is None)
            ax.plot(rest[:, 0], rest[:, 1], "x", color="k", ms=9, mew=2.2, zorder=5,
                    label=f"contact begun ({len(rest) - n_own} of opponents" + (f", {n_own} of the learner)" if n_own else ")"))
        # below the axes: inside, a fixed corner can hide the very contact the plot is for
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, fontsize=8, frameon=False)
    return _save_top_down(fig, ax, path, title or track.name)
