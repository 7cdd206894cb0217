"""Throughput of the sensor degradations (torcsrl.transforms), one CPU thread.

    python benchmarks/degradation_throughput.py [--peers DIR] [--reps N] [--env-reps N] [--only-env]

Prints three tables:

1. camera: images/s for every pixel degradation on 84x84 uint8 frames, severity 3,
   * ``step B=1`` / ``step B=256``: inside an env (``_call``: episode draws already made,
     step noise drawn each call) — the goal is >= 2,000 images/s at B=256;
   * ``fresh B=256``: a replay-buffer sample (``forward``: new episode draws and masks for
     every call).
2. rangefinder / state: the cost per env-step of the full stack (every rangefinder degradation
   at severity 3 composed, likewise for state) at B=256 and B=1 — goal <= 20 us per env-step at
   B=256 — and each degradation alone.
3. in the race env, one car (rangefinder + state): the env step with each weather preset, each
   rangefinder step-noise degradation alone and the full rangefinder and state stacks, against the
   bare env step — the goal is one rangefinder degradation costing <= 15 % of the env's own step at
   B=1 (median of ``--env-reps`` rounds of 100 steps, the envs interleaved round by round so that a
   shared machine slows them alike; ``--only-env`` prints this table alone).
4. peers (albumentations, imagecorruptions), per frame, only where importable. ``--peers DIR``
   (or $TORCSRL_PEERS) appends a folder of separately installed packages to ``sys.path``.

Deterministic inputs and seeds; times are the median of ``--reps`` timings after one warm-up,
in process CPU time (robust to other jobs on a shared machine; ``--wall`` for wall clock).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import Compose

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torcsrl.transforms import degradation_names, make_degradation  # noqa: E402
from torcsrl.transforms.synthetic import road_frame, track_scans  # noqa: E402

H = W = 84
GOAL_IMG_S = 2000
GOAL_RF_US = 20.0
GOAL_B1_SHARE = 0.15


CLOCK = time.process_time  # CPU time of this process: other jobs on a shared machine barely move it


def _median_time(fn, reps: int, inner: int = 1) -> float:
    """Median seconds per call of ``fn`` over ``reps`` timings of ``inner`` calls each."""
    fn()  # warm-up
    ts = []
    for _ in range(reps):
        t0 = CLOCK()
        for _ in range(inner):
            fn()
        ts.append((CLOCK() - t0) / inner)
    return statistics.median(ts)


def _camera_td(B: int) -> TensorDict:
    pix, depth = road_frame(H, W)
    return TensorDict(
        {"pixels": pix.expand(B, -1, -1, -1).clone(), "depth": depth.expand(B, -1, -1, -1).clone()}, [B]
    )


def _env_step_fn(t, td):
    """Steady-state env step: reset once, then time ``_call`` on a shallow copy."""
    t._reset(td.empty(), td.clone(False))
    return lambda: t._call(td.clone(False))


def bench_camera(reps: int) -> list[tuple]:
    rows = []
    td1, td256 = _camera_td(1), _camera_td(256)
    for name in degradation_names("camera"):
        t = make_degradation(name, 3, seed=0)
        s1 = _median_time(_env_step_fn(t, td1), reps, inner=40)
        t = make_degradation(name, 3, seed=0)
        s256 = _median_time(_env_step_fn(t, td256), reps)
        t = make_degradation(name, 3, seed=0)
        f256 = _median_time(lambda: t(td256.clone(False)), reps)
        rows.append((name, 1 / s1, 256 / s256, 256 / f256))
    return rows


def bench_vector(sensor: str, key: str, data_fn, reps: int) -> tuple[list, list]:
    stack_rows, single_rows = [], []
    names = degradation_names(sensor)
    for B in (256, 1):
        td = TensorDict({key: data_fn(B)}, [B])
        stack = Compose(*[make_degradation(n, 3, seed=i) for i, n in enumerate(names)])
        dt = _median_time(_env_step_fn(stack, td), reps, inner=20)
        stack_rows.append((f"{sensor} stack ({len(names)})", B, dt * 1e6, dt * 1e6 / B))
    for n in names:
        us = []
        for B in (256, 1):
            td = TensorDict({key: data_fn(B)}, [B])
            t = make_degradation(n, 3, seed=0)
            us.append(_median_time(_env_step_fn(t, td), reps, inner=20) * 1e6)
        single_rows.append((n, *us))
    return stack_rows, single_rows


# ------------------------------------------------------------------------ peers
def load_baseline(folder: str):
    """Another copy of ``torcsrl/transforms`` (e.g. ``git archive <rev> torcsrl/transforms | tar -x -C DIR``, then
    ``DIR/torcsrl/transforms``) imported as the package ``baseline_transforms``: the in-env table then times its
    stacks beside this checkout's, interleaved in one process on the same env code."""
    import importlib.util

    init = Path(folder) / "__init__.py"
    spec = importlib.util.spec_from_file_location("baseline_transforms", init, submodule_search_locations=[str(folder)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["baseline_transforms"] = mod
    spec.loader.exec_module(mod)
    return mod


def bench_env_b1(reps: int, steps: int = 100, baseline=None) -> list[tuple]:
    """(stack, degradations acting on the env's keys, us per env step, overhead vs the bare env) in the race
    env, B=1. Presets are built whole; their camera parts find no camera and pass. Every env is built first,
    then timed in turns (``reps`` rounds of ``steps`` steps each, the envs interleaved), so that other jobs
    on a shared machine slow them alike; the median of the rounds, in ``CLOCK`` time."""
    from torcsrl.envs import make_env
    from torcsrl.transforms import DegradedEnv, make_preset

    stacks = {"(none)": None}
    for p in ("rain", "fog", "snow", "dust"):
        stacks[f"weather.{p}"] = lambda p=p: make_preset(p, 3, seed=0)
    for n in ("rangefinder.noise", "rangefinder.dropout", "rangefinder.fog", "rangefinder.rain", "rangefinder.snow"):
        stacks[n] = lambda n=n: make_degradation(n, 3, seed=0)
    wrappers = {name: DegradedEnv for name in stacks}
    if baseline is not None:  # the same stacks from the baseline copy, in its own DegradedEnv
        for name in [k for k in stacks if k != "(none)"]:
            if name.startswith("weather."):
                stacks[f"{name} (baseline)"] = lambda p=name[8:]: baseline.make_preset(p, 3, seed=0)
            else:
                stacks[f"{name} (baseline)"] = lambda n=name: baseline.make_degradation(n, 3, seed=0)
            wrappers[f"{name} (baseline)"] = baseline.DegradedEnv
    for sensor in ("rangefinder", "state"):
        stacks[f"{sensor} stack"] = lambda sensor=sensor: Compose(
            *[make_degradation(n, 3, seed=i) for i, n in enumerate(degradation_names(sensor))])
    stacks["rangefinder + state stacks"] = lambda: Compose(
        *[make_degradation(n, 3, seed=i) for i, n in enumerate(degradation_names("rangefinder") + degradation_names("state"))])
    envs, tds, applied = {}, {}, {}
    wrappers = {**{name: DegradedEnv for name in stacks}, **wrappers}
    for name, make in stacks.items():
        base = make_env(track="oval", sensors=("rangefinder", "state"), max_steps=100_000, seed=0)
        env = base if make is None else wrappers[name](base, make())
        present = set(base.observation_spec.keys())
        applied[name] = 0 if make is None else sum(1 for t in env.transform.modules()
                                                   if hasattr(t, "get_sim_state") and any(k in present for k in t.in_keys))
        td = env.reset()
        act = env.action_spec.zero()
        act[..., -1] = 0.3  # some throttle: the car drives, episodes end and reset now and then
        td.set("action", act)
        envs[name], tds[name] = env, (td, act)

    def run(name: str) -> float:
        env, (td, act) = envs[name], tds[name]
        t0 = CLOCK()
        for _ in range(steps):
            _, td = env.step_and_maybe_reset(td)
            td.set("action", act)
        tds[name] = (td, act)
        return (CLOCK() - t0) / steps

    for name in envs:  # warm-up
        run(name)
    times: dict[str, list[float]] = {name: [] for name in envs}
    for _ in range(reps):
        for name in envs:
            times[name].append(run(name))
    for env in envs.values():
        env.close()
    bare = statistics.median(times["(none)"]) * 1e6
    rows = []
    for name in envs:
        us = statistics.median(times[name]) * 1e6
        rows.append((name, applied[name], us, (us - bare) / bare))
    return rows


def _peer_frames(n: int):
    import numpy as np

    pix, _ = road_frame(H, W)
    img = pix.permute(1, 2, 0).numpy()
    return [np.ascontiguousarray(img) for _ in range(n)]


def bench_albumentations(n: int) -> list[tuple]:
    try:
        import albumentations as A
    except Exception as e:  # noqa: BLE001
        return [("albumentations", f"not importable ({type(e).__name__})", None)]
    import numpy as np

    np.random.seed(0)
    frames = _peer_frames(n)
    cases = {
        "fog": A.RandomFog(fog_coef_range=(0.3, 0.3), alpha_coef=0.08, p=1.0),
        "rain": A.RandomRain(p=1.0),
        "snow": A.RandomSnow(p=1.0),
        "glare": A.RandomSunFlare(p=1.0),
        "darkness": A.RandomBrightnessContrast(brightness_limit=(-0.5, -0.5), p=1.0),
        "motion_blur": A.MotionBlur(blur_limit=(7, 7), p=1.0),
        "noise": A.GaussNoise(std_range=(0.18, 0.18), p=1.0),
        "occlusion": A.CoarseDropout(p=1.0),
    }
    rows = []
    for name, tr in cases.items():
        tr.set_random_seed(0) if hasattr(tr, "set_random_seed") else None

        def run():
            for f in frames:
                tr(image=f)

        try:
            dt = _median_time(run, 1)
            rows.append((f"albumentations {A.__version__}", name, n / dt))
        except Exception as e:  # noqa: BLE001
            rows.append((f"albumentations {A.__version__}", name, f"failed: {type(e).__name__}"))
    return rows


def bench_imagecorruptions(n: int) -> list[tuple]:
    try:
        from imagecorruptions import corrupt
    except Exception as e:  # noqa: BLE001
        return [("imagecorruptions", f"not importable ({type(e).__name__})", None)]
    frames = _peer_frames(n)
    rows = []
    for name in ("fog", "snow", "motion_blur", "gaussian_noise"):

        def run():
            for f in frames:
                corrupt(f, corruption_name=name, severity=3)

        try:
            rows.append(("imagecorruptions", name, n / _median_time(run, 1)))
        except Exception as e:  # noqa: BLE001
            rows.append(("imagecorruptions", name, f"failed: {type(e).__name__}"))
    return rows


# ------------------------------------------------------------------------ main
def _env_table(a) -> None:
    load = os.getloadavg()
    print(f"\n## race env, one car, rangefinder + state: env step with a stack (goal: one rangefinder degradation "
          f"<= {GOAL_B1_SHARE:.0%} of the env step; load average {load[0]:.2f} at the start)")
    print(f"| {'stack':28s} | {'applied':>7s} | {'us per step':>11s} | {'overhead':>8s} | goal |")
    print(f"|{'-' * 30}|{'-' * 9}|{'-' * 13}|{'-' * 10}|------|")
    baseline = load_baseline(a.baseline) if a.baseline else None
    if baseline is not None:
        print(f"(baseline rows: the transforms of {a.baseline}, timed beside this checkout's in the same rounds)")
    for name, n, us, share in bench_env_b1(a.env_reps, baseline=baseline):
        ok = "" if n != 1 else ("ok" if share <= GOAL_B1_SHARE else "MISS")
        print(f"| {name:28s} | {n:7d} | {us:11,.0f} | {share:8.0%} | {ok:4s} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=5, help="timed calls per batch-256 case")
    ap.add_argument("--peers", default=os.environ.get("TORCSRL_PEERS"), help="folder with peer packages")
    ap.add_argument("--no-peers", action="store_true")
    ap.add_argument("--env-reps", type=int, default=30, help="rounds of the in-env table (100 steps per env each)")
    ap.add_argument("--only-env", action="store_true", help="print only the in-env table (B=1 in the race env)")
    ap.add_argument("--baseline", default=None, help="a torcsrl/transforms folder of another revision: its stacks timed beside "
                                                      "these in the in-env table (see load_baseline)")
    ap.add_argument("--wall", action="store_true", help="wall-clock instead of CPU time")
    a = ap.parse_args(argv)
    if a.wall:
        global CLOCK
        CLOCK = time.perf_counter

    torch.set_num_threads(1)
    torch.manual_seed(0)
    t_start = time.perf_counter()
    clock = "wall clock" if a.wall else "process CPU time"
    print(f"torch {torch.__version__}, threads={torch.get_num_threads()}, frames {H}x{W}, severity 3, {clock}")

    if a.only_env:
        _env_table(a)
        print(f"\n(total {time.perf_counter() - t_start:.0f} s wall; one thread; a shared machine adds noise)")
        return
    print(f"\n## camera: images/s (goal >= {GOAL_IMG_S:,} at step B=256)")
    print(f"| {'degradation':22s} | {'step B=1':>9s} | {'step B=256':>10s} | {'fresh B=256':>11s} | goal |")
    print(f"|{'-' * 24}|{'-' * 11}|{'-' * 12}|{'-' * 13}|------|")
    for name, a1, a256, f256 in bench_camera(a.reps):
        ok = "ok" if a256 >= GOAL_IMG_S else "MISS"
        print(f"| {name:22s} | {a1:9,.0f} | {a256:10,.0f} | {f256:11,.0f} | {ok:4s} |")

    print(f"\n## rangefinder and state: per env-step (goal <= {GOAL_RF_US:.0f} us at B=256 for the rangefinder stack)")
    stacks, singles = [], []
    for sensor, key, fn in (
        ("rangefinder", "rangefinder", track_scans),
        ("state", "state", lambda B: torch.linspace(-1, 1, 12).repeat(B, 1) * 10),
    ):
        s, r = bench_vector(sensor, key, fn, a.reps)
        stacks += s
        singles += r
    print(f"| {'stack':22s} | {'B':>4s} | {'us per call':>11s} | {'us per env-step':>15s} |")
    print(f"|{'-' * 24}|{'-' * 6}|{'-' * 13}|{'-' * 17}|")
    for name, B, us, per in stacks:
        print(f"| {name:22s} | {B:4d} | {us:11,.0f} | {per:15,.2f} |")
    print(f"\n| {'degradation (alone)':22s} | {'us/call B=256':>13s} | {'us/call B=1':>11s} |")
    print(f"|{'-' * 24}|{'-' * 15}|{'-' * 13}|")
    for name, u256, u1 in singles:
        print(f"| {name:22s} | {u256:13,.0f} | {u1:11,.0f} |")

    _env_table(a)

    if not a.no_peers:
        for d in [a.peers, "/tmp/peers_albu", "/tmp/peers"]:
            if d and Path(d).is_dir() and d not in sys.path:
                sys.path.append(d)  # appended: the system's torch / numpy keep priority
        print("\n## peers: images/s, one frame at a time, 84x84 (their own default parameters)")
        print(f"| {'library':22s} | {'effect':14s} | {'images/s':>10s} |")
        print(f"|{'-' * 24}|{'-' * 16}|{'-' * 12}|")
        for lib, name, v in bench_albumentations(64) + bench_imagecorruptions(16):
            val = f"{v:10,.0f}" if isinstance(v, float) else ("" if v is None else str(v))
            print(f"| {lib:22s} | {name:14s} | {val:>10s} |")

    print(f"\n(total {time.perf_counter() - t_start:.0f} s wall; one thread; a shared machine adds noise)")


if __name__ == "__main__":
    main()
