"""Render hood-camera frames with one renderer (tiny | egl) in this process; save them; time frames/s.

    python benchmarks/gpu/egl_frames.py RENDERER OUTDIR [--frames N] [--repeats R] [--track hairpins]

Writes OUTDIR/frames_RENDERER.npz (world-only frames at a fixed pose, per size) as soon as they exist,
then OUTDIR/frames_RENDERER_car.npz (the same pose with a second car 12 m ahead), and
OUTDIR/rates_RENDERER.json (frames/s per size, driving along the track 0.4 m per frame, as
benchmarks/camera_throughput.py does). Run each renderer in its own process: a crash of the EGL
plugin then loses only its own part.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import pybullet as p  # noqa: E402

from torcsrl.envs import tracks  # noqa: E402
from torcsrl.envs.camera import Camera, setup_renderer  # noqa: E402
from torcsrl.envs.world import build_world  # noqa: E402

SIZES = ((96, 64), (84, 84), (64, 64), (128, 128))
Z_COM = 0.45
STEP_M = 0.4
S0 = 40.0  # [m] along the track: the comparison pose


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("renderer")
    ap.add_argument("outdir")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--track", default="hairpins")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    os.makedirs(a.outdir, exist_ok=True)
    cid = p.connect(p.DIRECT)
    t0 = time.perf_counter()
    rend = setup_renderer(cid, a.renderer)  # raises RendererUnavailable for egl without a GPU
    print(f"[{a.renderer}] renderer set up: {rend.name} (plugin id {rend.plugin_id}) in {time.perf_counter() - t0:.2f} s",
          flush=True)
    track = tracks.load(a.track)
    world = build_world(cid, track)
    cams = {f"{w}x{h}": Camera(cid, w, h, mount="hood", renderer=rend, worlds=[world]) for w, h in SIZES}
    xy0 = track.to_world(np.array([S0]), 0.0).reshape(-1)
    yaw0 = float(np.asarray(track.heading(np.array([S0]))).reshape(-1)[0])
    pose = [float(xy0[0]), float(xy0[1]), Z_COM]
    out = {}
    for k, cam in cams.items():
        rgb, depth = cam.render(pose, yaw0)
        out[f"rgb_{k}"], out[f"depth_{k}"] = rgb, depth
    np.savez(os.path.join(a.outdir, f"frames_{a.renderer}.npz"), **out)
    print(f"[{a.renderer}] saved world-only frames at s={S0} m of {a.track}", flush=True)

    # frames/s along the track, per size
    n, reps = a.frames, a.repeats
    s = S0 + np.arange(n * (reps + 1) + 20) * STEP_M
    xy = track.to_world(s, 0.0)
    yaw = np.asarray(track.heading(s)).reshape(-1)
    rates = {"renderer": rend.name, "track": a.track, "frames": n, "repeats": reps}
    for k, cam in cams.items():
        for i in range(20):
            cam.render([xy[i, 0], xy[i, 1], Z_COM], yaw[i])
        best = 0.0
        for r in range(reps):
            t = time.perf_counter()
            for i in range(n):
                j = 20 + r * n + i
                cam.render([xy[j, 0], xy[j, 1], Z_COM], yaw[j])
            best = max(best, n / (time.perf_counter() - t))
        rates[f"fps_{k}"] = best
        print(f"[{a.renderer}] {k} hood: {best:.0f} frames/s (best of {reps} x {n})", flush=True)
    with open(os.path.join(a.outdir, f"rates_{a.renderer}.json"), "w") as f:
        json.dump(rates, f, indent=1)

    # the same pose with a car 12 m ahead (a body drawn by the renderer itself)
    try:
        from torcsrl.envs.vehicle import CarFleet

        fleet = CarFleet(cid, 1)
        xy1 = track.to_world(np.array([S0 + 12.0]), 0.0).reshape(1, 2)
        yaw1 = float(np.asarray(track.heading(np.array([S0 + 12.0]))).reshape(-1)[0])
        fleet.reset([0], xy1, [yaw1], [0.0])
        out = {}
        for k, cam in cams.items():
            rgb, depth = cam.render(pose, yaw0)
            out[f"rgb_{k}"], out[f"depth_{k}"] = rgb, depth
        np.savez(os.path.join(a.outdir, f"frames_{a.renderer}_car.npz"), **out)
        print(f"[{a.renderer}] saved frames with a car 12 m ahead", flush=True)
    except Exception as err:  # noqa: BLE001
        print(f"[{a.renderer}] car-ahead frames failed: {type(err).__name__}: {err}", flush=True)
    rend.close()
    p.disconnect(cid)
    return 0


if __name__ == "__main__":
    sys.exit(main())
