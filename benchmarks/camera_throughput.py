"""Camera throughput: frames/s of the camera sensor and of a pixel env step, against CarRacing-v3.

    python benchmarks/camera_throughput.py [--track hairpins] [--frames 300] [--peers /tmp/peers]

Measures, on one CPU thread:

* camera frames/s at 64, 84 and 128 px (hood), and 84 px chase / top-down, driving along a real
  track (every frame a new pose 0.4 m further on, as at 20 m/s and 50 Hz): TinyRenderer, plus
  EGL when a GPU is present;
* a *pixel env step* estimate: one control step of the car (``CarFleet.step``, 4 physics
  substeps, surfaces under the wheels from the track) plus one 84 px hood frame, with a simple
  lane-keeping driver; and the env's simulation core (``RaceCore.step``: physics, Frenet
  location, rangefinder, rewards, episode rules) without and with 84 px pixels + depth, when those
  modules exist (the TorchRL wrapper's TensorDict work comes on top);
* Gymnasium's ``CarRacing-v3`` (96x96 pixels) steps/s in the same run, if Box2D and pygame import
  (``--peers`` adds a folder with them to ``sys.path``, for this process only).

Each figure is the best of ``--repeats`` timed runs (least disturbed by other processes; the
machine may be shared). Prints a table with ratios to CarRacing-v3 and to the 200 steps/s goal.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core, before numpy loads
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import pybullet as p  # noqa: E402

from torcsrl.envs import tracks  # noqa: E402
from torcsrl.envs.camera import Camera, gpu_available, setup_renderer  # noqa: E402
from torcsrl.envs.world import build_world  # noqa: E402

GOAL_STEPS_PER_S = 200.0
STEP_M = 0.4  # [m] pose advance per frame: 20 m/s at 50 Hz
Z_COM = 0.45  # [m] default car's centre-of-mass height at rest


def _best_rate(fn, n: int, repeats: int) -> float:
    """Best calls/s of ``fn(i)`` over ``repeats`` runs of ``n`` calls (after a short warm-up)."""
    for i in range(min(20, n)):
        fn(i)
    best = 0.0
    for r in range(repeats):
        t0 = time.perf_counter()
        for i in range(n):
            fn(r * n + i)
        best = max(best, n / (time.perf_counter() - t0))
    return best


def camera_rates(track_name: str, renderer: str, n: int, repeats: int) -> tuple[list[tuple[str, float]], str]:
    """Frames/s of the camera along the track, per resolution and mount."""
    cid = p.connect(p.DIRECT)
    try:
        rend = setup_renderer(cid, renderer)
        track = tracks.load(track_name)
        world = build_world(cid, track)
        info = (f"{track_name}: {track.length:.0f} m, {len(world.chunks)} chunks, {len(world.bodies)} bodies, "
                f"{world.num_triangles} triangles, ground map {world.ground.nbytes / 1e6:.1f} MB")
        s = np.arange(n * (repeats + 1) + 20) * STEP_M
        xy = track.to_world(s, 0.0)
        yaw = track.heading(s)
        out = []
        for size, mount in ((64, "hood"), (84, "hood"), (128, "hood"), (84, "chase"), (84, "top")):
            cam = Camera(cid, size, size, mount=mount, renderer=rend, worlds=[world])

            def frame(i, cam=cam):
                cam.render([xy[i, 0], xy[i, 1], Z_COM], yaw[i])

            out.append((f"camera {rend.name} {size}x{size} {mount}", _best_rate(frame, n, repeats)))
        return out, info
    finally:
        p.disconnect(cid)


def pixel_env_rates(track_name: str, n: int, repeats: int) -> list[tuple[str, float]]:
    """Control steps/s of one car with and without an 84 px hood frame per step."""
    try:
        from torcsrl.envs.vehicle import CarFleet, make_ground
    except ImportError as err:
        print(f"(no vehicle module: {err}; pixel env step not measured)")
        return []
    cid = p.connect(p.DIRECT)
    try:
        rend = setup_renderer(cid, "tiny")
        track = tracks.load(track_name)
        ground = make_ground(cid)
        fleet = CarFleet(cid, 1)
        world = build_world(cid, track, ground_body=ground)
        cam = Camera(cid, 84, 84, mount="hood", renderer=rend, worlds=[world], vehicle=fleet.params)
        state = {"s": 0.0}

        def reset() -> None:
            xy0, yaw0 = track.start_pose()
            fleet.reset([0], xy0[None], [yaw0], [10.0])
            state["s"] = 0.0

        def drive() -> None:
            """A lane-keeping driver: steer towards the centreline 12 m ahead, hold ~20 m/s."""
            pos = fleet.pos[0]
            s, d = track.project(pos[None, :2], s_hint=np.array([state["s"]]))
            s, d = float(s[0]), float(d[0])
            state["s"] = s
            wl, wr = track.width(s)
            if not (-wr - 1.0 < d < wl + 1.0) or fleet.flipped[0]:
                reset()
                return
            target = track.to_world(s + 12.0, 0.0)
            err = math.atan2(target[1] - pos[1], target[0] - pos[0]) - float(fleet.yaw[0])
            err = (err + math.pi) % (2 * math.pi) - math.pi
            steer = max(-1.0, min(1.0, 2.5 * err))
            speed = float(fleet.speed[0])
            fleet.set_wheel_surfaces(track.surface_at(fleet.wheel_xy[0], s_hint=np.full(4, s))[None, :])
            fleet.step([steer], [0.6 if speed < 20.0 else 0.0], [0.0])

        def physics(i):
            drive()

        def pixel_step(i):
            drive()
            cam.render(fleet.pos[0], rot=fleet.rotation[0])

        reset()
        phys = _best_rate(physics, n, repeats)
        reset()
        pix = _best_rate(pixel_step, n, repeats)
        return [("car control step (physics + surfaces)", phys), ("pixel env step 84x84 (car step + camera)", pix)]
    finally:
        p.disconnect(cid)


def race_core_rates(track_name: str, n: int, repeats: int) -> list[tuple[str, float]]:
    """Steps/s of the env's simulation core (``RaceCore``) without and with 84 px pixels + depth."""
    try:
        from torcsrl.envs.race import RaceCore
    except ImportError as err:
        print(f"(no race core: {err}; env steps not measured)")
        return []
    out = []
    for label, sensors, cam in (("env core step, rangefinder + state", ("rangefinder", "state"), None),
                                ("env core step + pixels + depth 84x84", ("rangefinder", "state", "pixels", "depth"),
                                 {"width": 84, "height": 84, "renderer": "tiny"})):
        core = RaceCore(track=track_name, sensors=sensors, camera=cam, seed=0, max_steps=10_000)
        try:
            core.reset()

            def step(i, core=core):
                fleet, track = core.fleet, core.car_tracks[0]
                pos = fleet.pos[0]
                target = track.to_world(float(core.s[0]) + 12.0, 0.0)
                err = math.atan2(target[1] - pos[1], target[0] - pos[0]) - float(fleet.yaw[0])
                err = (err + math.pi) % (2 * math.pi) - math.pi
                pedal = 0.6 if float(fleet.speed[0]) < 20.0 else 0.0
                core.step(np.array([[max(-1.0, min(1.0, 2.5 * err)), pedal]]))
                if core.terminated[0] or core.truncated[0]:
                    core.reset()

            out.append((label, _best_rate(step, n, repeats)))
        finally:
            core.close()
    return out


def carracing_rate(n: int, repeats: int, peers: str | None) -> float | None:
    """CarRacing-v3 steps/s (96x96 pixel observations), or None if it cannot be imported."""
    if peers and os.path.isdir(peers) and peers not in sys.path:
        sys.path.append(peers)
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    try:
        import gymnasium as gym

        env = gym.make("CarRacing-v3")
    except Exception as err:  # Box2D / pygame missing
        print(f"(CarRacing-v3 not available: {type(err).__name__}: {err})")
        return None
    try:
        env.reset(seed=0)
        action = np.array([0.0, 0.3, 0.0], dtype=np.float32)
        steps = {"k": 0}

        def step(i):
            _, _, term, trunc, _ = env.step(action)
            steps["k"] += 1
            if term or trunc:
                env.reset(seed=steps["k"])

        return _best_rate(step, n, repeats)
    finally:
        env.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--track", default="hairpins", help="track to drive along")
    parser.add_argument("--frames", type=int, default=300, help="frames / steps per timed run")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per figure (best is kept)")
    parser.add_argument("--peers", default="/tmp/peers", help="extra sys.path folder with Box2D + pygame")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if "torch" in sys.modules:  # not needed here, but keep any torch work on one thread too
        sys.modules["torch"].set_num_threads(1)

    t_start = time.perf_counter()
    rows, info = camera_rates(args.track, "tiny", args.frames, args.repeats)
    if gpu_available():
        try:
            egl_rows, _ = camera_rates(args.track, "egl", args.frames, args.repeats)
            rows += egl_rows
        except Exception as err:  # the plugin may still fail on an odd driver setup
            print(f"(EGL not measured: {err})")
    rows += pixel_env_rates(args.track, args.frames, args.repeats)
    rows += race_core_rates(args.track, args.frames, args.repeats)
    ref = carracing_rate(args.frames, args.repeats, args.peers)
    if ref is not None:
        rows.append(("CarRacing-v3 step (96x96 pixels)", ref))

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print()
    print(f"camera throughput — {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"load avg {load[0]:.2f} (shared machines give noisy figures); 1 thread; "
          f"best of {args.repeats} x {args.frames}")
    print(f"world {info}")
    header = f"{'what':44s} {'per s':>9s} {'ms':>7s} {'vs goal':>8s}" + (f" {'vs CarRacing':>13s}" if ref else "")
    print(header)
    print("-" * len(header))
    for name, rate in rows:
        line = f"{name:44s} {rate:9.0f} {1000.0 / rate:7.2f} {rate / GOAL_STEPS_PER_S:7.2f}x"
        if ref:
            line += f" {rate / ref:12.2f}x"
        print(line)
    print(f"(goal: a pixel env of >= {GOAL_STEPS_PER_S:.0f} steps/s at 84x84 on one core; "
          f"benchmark took {time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
