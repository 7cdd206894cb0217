"""Where the one-car env's step and reset spend their time, in µs per call, by timing the parts in place.

    python benchmarks/env_profile.py [--steps 5000] [--track oval] [--surface asphalt]

``gym.make("torcsrl/Race-v0")`` with its default arguments (or the track and surface given), uniform random actions
(seeded), reset when an episode ends; one process, one thread. Each part below is wrapped by a timer (~0.2 µs each,
so the parts add up to a little more than the plain step). Nested parts are indented under the part that calls them;
"gymnasium face" is what ``RaceEnv.step`` and its wrappers add around ``RaceCore.step`` (the observation and info
dicts, the action check). For the env's speed against raw pybullet use ``benchmarks/env_throughput.py --raw-only``.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

#: (label, "module:Class.method", depth): the parts timed, in the order they are printed.
STEP_PARTS = (
    ("RaceCore.step", "torcsrl.envs.race.core:RaceCore.step", 0),
    ("action sanitising", "torcsrl.envs.race.core:RaceCore.sanitize", 1),
    ("car physics (CarFleet.step)", "torcsrl.envs.vehicle.fleet:CarFleet.step", 1),
    ("reading the bodies' frames", "torcsrl.envs.vehicle.python_backend:PythonBackend._read_frames", 2),
    ("publishing the state arrays", "torcsrl.envs.vehicle.python_backend:PythonBackend._publish_frames", 2),
    ("locating the car and wheels", "torcsrl.envs.race.core:RaceCore._locate", 1),
    ("episode books + reward (1 car)", "torcsrl.envs.race.core:RaceCore._book_one", 1),
    ("observation", "torcsrl.envs.race.core:RaceCore._observe", 1),
    ("rangefinder rays", "torcsrl.envs.sensors:Rangefinder.read", 2),
    ("gym info dict", "torcsrl.envs.race.gym_env:RaceEnv._info", 0),
    ("gym observation dict", "torcsrl.envs.race.gym_env:RaceEnv._obs", 0),
)
RESET_PARTS = (("RaceCore.reset", "torcsrl.envs.race.core:RaceCore.reset", 0),)


def _wrap(spec: str, acc: dict, key: str) -> tuple:
    """Time ``spec``'s method into ``acc[key]``; returns what :func:`_unwrap` needs to put the method back."""
    import importlib

    mod_name, qual = spec.split(":")
    cls_name, meth = qual.split(".")
    cls = getattr(importlib.import_module(mod_name), cls_name)
    cls = next(c for c in cls.__mro__ if meth in c.__dict__)  # the class (or mixin) that defines it
    f = cls.__dict__[meth]
    clock = time.perf_counter

    def timed(*a, **k):
        t0 = clock()
        try:
            return f(*a, **k)
        finally:
            acc[key] += clock() - t0

    setattr(cls, meth, timed)
    return cls, meth, f


def _unwrap(wrapped: list) -> None:
    for cls, meth, f in reversed(wrapped):
        setattr(cls, meth, f)


def profile(steps: int, track: str | None = None, surface: str | None = None) -> dict:
    """µs per step of each part (and per reset), the plain step's µs, and the resets."""
    import gymnasium as gym

    import torcsrl.envs  # noqa: F401

    kw = {k: v for k, v in (("track", track), ("surface", surface)) if v is not None}
    acc = {label: 0.0 for label, _, _ in STEP_PARTS + RESET_PARTS}
    wrapped = [_wrap(spec, acc, label) for label, spec, _ in STEP_PARTS + RESET_PARTS]
    try:
        return _profile(gym.make("torcsrl/Race-v0", **kw), steps, acc)
    finally:
        _unwrap(wrapped)


def _profile(env, steps: int, acc: dict) -> dict:
    """Drive ``env`` (warm-up, then ``steps`` timed steps) with the timers on; µs per step of each part."""
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, size=(4096, 2)).astype(np.float32)
    for i in range(200):
        if any(env.step(actions[i])[2:4]):
            env.reset()
    for k in acc:
        acc[k] = 0.0
    resets, t_step = 0, 0.0
    clock = time.perf_counter
    for i in range(steps):
        t0 = clock()
        _, _, te, tr, _ = env.step(actions[i % 4096])
        t_step += clock() - t0
        if te or tr:
            env.reset()
            resets += 1
    env.close()
    out = {label: 1e6 * acc[label] / steps for label, _, _ in STEP_PARTS}
    out["env.step"] = 1e6 * t_step / steps
    out["RaceCore.reset"] = 1e6 * acc["RaceCore.reset"] / resets if resets else float("nan")
    out["resets"] = resets
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--track", default=None, help="a track name or set (default: the env's default)")
    ap.add_argument("--surface", default=None)
    args = ap.parse_args(argv)
    r = profile(args.steps, args.track, args.surface)
    step = r["env.step"]
    print(f"one-car env, {args.steps} random-action steps, {r['resets']} resets, one thread")
    print(f"{'part':44s} {'us/step':>8s} {'% step':>7s}")
    print(f"{'env.step (gymnasium face, all of it)':44s} {step:8.1f} {100.0:6.1f}%")
    for label, _, depth in STEP_PARTS:
        print(f"{'  ' * (depth + 1) + label:44s} {r[label]:8.1f} {100 * r[label] / step:6.1f}%")
    face = step - r["RaceCore.step"]
    print(f"{'  gymnasium face (env.step - RaceCore.step)':44s} {face:8.1f} {100 * face / step:6.1f}%")
    print(f"{'reset (RaceCore.reset), us per reset':44s} {r['RaceCore.reset']:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
