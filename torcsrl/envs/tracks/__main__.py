"""Look at tracks.

    python -m torcsrl.envs.tracks list
    python -m torcsrl.envs.tracks plot oval [--surface dirt] [--out oval.png]
    python -m torcsrl.envs.tracks plot --generated 7 [--length 2500 --corners 9]
    python -m torcsrl.envs.tracks plot --procedural 7 [--difficulty 0.8] [--out proc7.png]
    python -m torcsrl.envs.tracks library --out docs/img/tracks.png
    python -m torcsrl.envs.tracks procedural --out docs/img/procedural_tracks.png
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from torcsrl.envs import surfaces as _surf
from torcsrl.envs import tracks


def _draw(ax, track, curvature_ax=None, title: str | None = None) -> None:
    # deferred: matplotlib only when a figure is drawn
    from matplotlib.collections import LineCollection, PolyCollection

    m = len(track)
    nxt = np.roll(np.arange(m), -1)
    quads = np.stack([track.left_edge, track.left_edge[nxt], track.right_edge[nxt], track.right_edge], axis=1)
    ax.add_collection(PolyCollection(quads, facecolors=_surf.COLORS[track.surface_ids], edgecolors="none"))
    ax.plot(*np.vstack([track.left_edge, track.left_edge[:1]]).T, color="k", lw=0.6)
    ax.plot(*np.vstack([track.right_edge, track.right_edge[:1]]).T, color="k", lw=0.6)
    k = np.abs(track.kappa)
    pts = np.vstack([track.xy, track.xy[:1]])
    segs = np.stack([pts[:-1], pts[1:]], axis=1)
    lc = LineCollection(segs, cmap="plasma", norm=_curv_norm(), lw=1.0)
    lc.set_array(np.maximum(k, 1e-4))
    ax.add_collection(lc)
    start = np.stack([track.to_world(0.0, track.w_left[0] + 2), track.to_world(0.0, -track.w_right[0] - 2)])
    ax.plot(*start.T, color="red", lw=2.5, label="start/finish")
    p0, yaw = track.start_pose()
    span = max(np.ptp(track.xy[:, 0]), np.ptp(track.xy[:, 1]))
    ax.annotate("", xy=p0 + 0.06 * span * np.array([np.cos(yaw), np.sin(yaw)]), xytext=p0,
                arrowprops=dict(arrowstyle="->", color="red", lw=1.5))
    ax.set_aspect("equal")
    ax.autoscale()
    ax.set_facecolor(_surf.COLORS[_surf.GRASS_ID] * 0.5 + 0.5)
    s = track.summary()
    ax.set_title(title or f"{track.name}: {s['length_m'] / 1000:.2f} km, {s['width_m']:.0f} m wide, "
                          f"min R {s['min_radius_m']:.0f} m", fontsize=9)
    ax.tick_params(labelsize=7)
    if curvature_ax is not None:
        curvature_ax.plot(track.s, track.kappa, lw=0.8)
        curvature_ax.set_xlabel("s [m]")
        curvature_ax.set_ylabel("curvature [1/m]")
        curvature_ax.grid(alpha=0.3)
    return lc


def _curv_norm():
    # deferred: matplotlib only when a figure is drawn
    from matplotlib.colors import LogNorm

    return LogNorm(vmin=1e-3, vmax=0.06)


def _legend(fig) -> None:
    # deferred: matplotlib only when a figure is drawn
    from matplotlib.patches import Patch

    handles = [Patch(color=_surf.COLORS[i], label=n) for i, n in enumerate(_surf.SURFACE_NAMES)]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)


def plot_track(track, out: str) -> str:
    """Write a PNG of one track: surfaces, edges, start line, centreline coloured by curvature."""
    # deferred: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(8, 9))
    ax = fig.add_axes([0.08, 0.33, 0.84, 0.62])
    cax = fig.add_axes([0.1, 0.08, 0.84, 0.18])
    lc = _draw(ax, track, cax)
    fig.colorbar(lc, ax=ax, label="|curvature| [1/m]", shrink=0.7)
    _legend(fig)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_library(out: str) -> str:
    """Write one PNG showing every bundled track."""
    # deferred: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = tracks.names()
    cols = 4
    rows = int(np.ceil(len(names) / cols))
    fig, axs = plt.subplots(rows, cols, figsize=(4 * cols, 3.6 * rows))
    sets = tracks.track_sets()
    for ax, name in zip(axs.ravel(), names):
        t = tracks.load(name)
        tag = "train" if name in sets.get("train", []) else "held-out" if name in sets.get("heldout", []) else ""
        _draw(ax, t, title=f"{name} ({tag}) {t.length / 1000:.1f} km")
    for ax in axs.ravel()[len(names):]:
        ax.axis("off")
    _legend(fig)
    fig.suptitle("torcsrl bundled tracks (centreline coloured by curvature; red: start/finish)")
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def plot_procedural(out: str, seeds: tuple[int, ...] = (1, 2, 3),
                    difficulties: tuple[float, ...] = (0.0, 0.33, 0.66, 1.0)) -> str:
    """Write one PNG of procedural circuits: a row per difficulty, a column per seed."""
    # deferred: matplotlib only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = len(difficulties), len(seeds)
    fig, axs = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.4 * rows), squeeze=False)
    for r, d in enumerate(difficulties):
        for c, seed in enumerate(seeds):
            t = tracks.generate_circuit(seed, d)
            s = t.summary()
            w = t.w_left + t.w_right
            features = t.description.split(": ", 1)[-1].replace("decreasing-radius bends", "decreasing")
            _draw(axs[r, c], t, title=f"proc seed {seed}, difficulty {d:.2f}: {t.length / 1000:.2f} km, "
                                       f"{w.min():.0f}-{w.max():.0f} m wide, min R {s['min_radius_m']:.0f} m"
                                       f"\n{features}")
            axs[r, c].title.set_fontsize(8)
    _legend(fig)
    fig.suptitle("torcsrl procedural circuits, generate_circuit(seed, difficulty) "
                 "(centreline coloured by curvature; red: start/finish)")
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torcsrl.envs.tracks", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="bundled tracks and track sets")
    p = sub.add_parser("plot", help="PNG of one track")
    p.add_argument("name", nargs="?", help="bundled track name")
    p.add_argument("--generated", type=int, metavar="SEED", help="plot a procedural track instead")
    p.add_argument("--procedural", type=int, metavar="SEED", help="plot a procedural circuit (generate_circuit)")
    p.add_argument("--difficulty", type=float, default=None,
                   help="procedural circuit difficulty in [0, 1] (default: drawn from the seed)")
    p.add_argument("--length", type=float, default=3000.0, help="generated lap length [m]")
    p.add_argument("--corners", type=int, default=10)
    p.add_argument("--min-radius", type=float, default=25.0, help="[m]")
    p.add_argument("--width", type=float, default=12.0, help="[m]")
    p.add_argument("--surface", default=None)
    p.add_argument("--out", default=None)
    lib = sub.add_parser("library", help="one PNG of every bundled track")
    lib.add_argument("--out", default="tracks.png")
    proc = sub.add_parser("procedural", help="one PNG of procedural circuits at four difficulties")
    proc.add_argument("--out", default="procedural_tracks.png")
    proc.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args(argv)
    try:
        if args.cmd == "list":
            for name in tracks.names():
                s = tracks.load(name).summary()
                print(f"{name:16s} {s['length_m'] / 1000:5.2f} km  {s['width_m']:4.1f} m  min R {s['min_radius_m']:6.1f} m  "
                      f"{s['surface']:8s} {s['character']}")
            for k, v in tracks.track_sets().items():
                print(f"set:{k}: {', '.join(v)}")
            return 0
        if args.cmd == "library":
            print(plot_library(args.out))
            return 0
        if args.cmd == "procedural":
            print(plot_procedural(args.out, tuple(args.seeds)))
            return 0
        if args.procedural is not None:
            t = tracks.generate_circuit(args.procedural, args.difficulty, surface=args.surface or "asphalt")
        elif args.generated is not None:
            t = tracks.generate(args.generated, length_m=args.length, corners=args.corners,
                                min_radius_m=args.min_radius, width_m=args.width, surface=args.surface or "asphalt")
        elif args.name:
            t = tracks.load(args.name, surface=args.surface)
        else:
            ap.error("give a track name, --generated SEED or --procedural SEED")
        print(plot_track(t, args.out or f"{t.name}.png"))
        return 0
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
