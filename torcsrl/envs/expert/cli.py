"""The expert's command line: ``python -m torcsrl.envs.expert --track NAME --surface dirt --laps 10
[--control-hz 10] [--plot out.png]`` drives a fleet of one on a ground plane, with the surface under each wheel
from the track, and prints lap times beside the limit and the rate they were driven at; ``--all`` prints the table
for every bundled track on asphalt and dirt.
"""

from __future__ import annotations

import argparse

import numpy as np

from torcsrl.envs import surfaces as surf
from torcsrl.envs import tracks
from torcsrl.envs.expert.driver import DriveResult, default_substeps, drive
from torcsrl.envs.expert.line import LINES
from torcsrl.envs.track import Track
from torcsrl.envs.vehicle import VehicleParams

__all__ = ["main", "plot_run"]


def plot_run(result: DriveResult, track: Track, path: str) -> None:
    """Top-down trajectory coloured by speed [km/h], with the track edges, to a PNG."""
    import matplotlib  # deferred: matplotlib (~0.5 s) only for --plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: as above
    from matplotlib.collections import LineCollection  # deferred: as above

    fig, ax = plt.subplots(figsize=(8, 8))
    for edge in (track.left_edge, track.right_edge):
        closed = np.vstack([edge, edge[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.3", lw=0.8)
    pts = result.xy
    segs = np.stack([pts[:-1], pts[1:]], axis=1)
    lc = LineCollection(segs, cmap="viridis", linewidths=1.5)
    lc.set_array(result.speed[:-1] * 3.6)
    ax.add_collection(lc)
    fig.colorbar(lc, ax=ax, label="speed [km/h]", shrink=0.8)
    best = f"best lap {result.best_lap:.2f} s" if result.lap_times else "no lap"
    ax.set_title(f"{track.name} on {result.surface}: {best} (limit {result.limit:.2f} s)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _row(r: DriveResult) -> str:
    flying = r.lap_times[1:] or r.lap_times
    mean = float(np.mean(flying)) if flying else float("nan")
    return (f"{r.track:15s} {r.surface:8s} {len(r.lap_times):>4d} {r.lap_times[0] if r.lap_times else float('nan'):>8.2f} "
            f"{r.best_lap:>8.2f} {mean:>8.2f} {r.limit:>8.2f} {r.best_lap / r.limit:>6.3f} {r.max_offset_ratio:>7.2f} "
            f"{r.wheels_off:>6d} {'yes' if r.completed else 'NO':>5s} {r.wall_s:>6.0f}")


_HEADER = (f"{'track':15s} {'surface':8s} {'laps':>4s} {'lap1 s':>8s} {'best s':>8s} {'mean s':>8s} {'limit s':>8s} "
           f"{'ratio':>6s} {'max|d|/w':>7s} {'wheels':>6s} {'done':>5s} {'wall s':>6s}")


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns a process exit status (1 if a run left the track or fell short)."""
    parser = argparse.ArgumentParser(prog="python -m torcsrl.envs.expert",
                                     description="Drive the scripted expert and compare with the physical-limit lap time.")
    parser.add_argument("--track", default="road_flow", help=f"track name ({', '.join(tracks.names())})")
    parser.add_argument("--surface", default=None, help=f"road surface for the whole track ({', '.join(surf.ROAD_SURFACES)}); "
                                                        "default: the track's own")
    parser.add_argument("--laps", type=int, default=10)
    parser.add_argument("--vehicle", default="default", help="vehicle parameter file")
    parser.add_argument("--mu-margin", type=float, default=0.85, help="fraction of mu the expert's speed profile uses")
    parser.add_argument("--line", default="racing", choices=LINES)
    parser.add_argument("--control-hz", type=float, default=50.0,
                        help="control rate [Hz] the expert drives at (the training env: 10); physics at >= 200 Hz")
    parser.add_argument("--substeps", type=int, default=None,
                        help="physics substeps per control step (default: 200 Hz physics, e.g. 4 at 50 Hz, 20 at 10 Hz)")
    parser.add_argument("--plot", default=None, help="write a top-down trajectory PNG coloured by speed")
    parser.add_argument("--all", action="store_true", help="every bundled track on asphalt and dirt: print a table")
    args = parser.parse_args(argv)
    if args.laps < 1:
        parser.error("--laps must be >= 1")
    if args.control_hz <= 0:
        parser.error("--control-hz must be > 0")
    params = VehicleParams.load(args.vehicle)
    substeps = default_substeps(args.control_hz) if args.substeps is None else args.substeps
    rate = f"{args.control_hz:g} Hz control, {substeps} substeps ({args.control_hz * substeps:g} Hz physics)"

    if args.all:
        print(f"expert at {rate}, {args.laps} laps from a standing start")
        print(_HEADER)
        ok = True
        for name in tracks.names():
            for surface in ("asphalt", "dirt"):
                r = drive(tracks.load(name, surface=surface), args.laps, params, args.mu_margin, args.line,
                          control_hz=args.control_hz, substeps=substeps)
                ok &= r.clean
                print(_row(r), flush=True)
        return 0 if ok else 1

    track = tracks.load(args.track, surface=args.surface)
    r = drive(track, args.laps, params, args.mu_margin, args.line, control_hz=args.control_hz, substeps=substeps)
    print(f"{track.name} on {r.surface} ({track.length:.0f} m), {len(r.lap_times)}/{args.laps} laps at {rate}, "
          f"physical limit {r.limit:.2f} s (point mass, quasi-steady state)")
    for i, t in enumerate(r.lap_times, 1):
        print(f"  lap {i:2d}: {t:7.2f} s   ({t / r.limit:.3f} x limit){'  standing start' if i == 1 else ''}")
    print(f"max |d| / half-width {r.max_offset_ratio:.2f}; steps with a wheel on grass: {r.wheels_off} "
          f"(closest wheel to an edge {r.min_wheel_margin_m:+.2f} m); "
          f"{'completed' if r.completed else 'NOT completed'}; wall {r.wall_s:.1f} s")
    if r.lap_times:
        print(f"reference lap (best): {r.best_lap:.2f} s at {args.control_hz:g} Hz control")
    if args.plot:
        plot_run(r, track, args.plot)
        print(f"wrote {args.plot}")
    return 0 if r.clean else 1
