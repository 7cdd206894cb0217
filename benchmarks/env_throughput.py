"""Env throughput: torcsrl's faces beside the raw physics of the same car and installed peers.

    python benchmarks/env_throughput.py [--steps 3000] [--quick] [--race] [--raw-only]

The first table is the env against raw pybullet in the same run: ``gym.make("torcsrl/Race-v0")`` with its default
arguments, uniform random actions, reset when an episode ends, beside pybullet's racecar URDF (pybullet_data, 50 Hz
x 5 substeps of 240 Hz) with 19 ray tests of 200 m per step (``rayTestBatch``, the TORCS rangefinder's fan; the car is
carried back across the plane before it drives off its edge, where it would fall and step 2.5x faster), in
interleaved rounds (best of each). The ratio env / raw is printed step-only (reset time excluded) and with resets, with
the mean reset cost; goal: >= 2.0x. ``--raw-only`` prints just that table. Where the env's step goes:
``benchmarks/env_profile.py``.

One process, one thread, everything measured in the same run (ratios are what to compare; the
machine is shared and absolute figures move). Observations: rangefinder + state. Peers are
measured only when installed (``pip install -e ".[bench]"``): gymnasium CarRacing-v3 (needs box2d)
and highway-env racetrack-v0 with its lidar observation.

Goals: >= 2,000 steps/s for one car; >= 5,000 car-steps/s batched at N = 32; the env's
overhead (env step - raw physics step) <= 1.5x the raw physics step of its own car. Both the
overhead ratio and the plain env/physics ratio are printed. The raw physics of 32 cars is measured
with the cars overlapping on one spot, as the env's cars do on a shared grid.

``--race``: a 4-car race env (1 learner + 3 scripted experts at 85 % pace, chassis colliding, the
opponents sensor on) beside the one-car env, in car-steps/s (every simulated car counts); goal >= 0.5x. Also a
batched race (N = 8 learners, each with its 3 opponents).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


def _rate(step, n: int, reset=None, repeats: int = 3) -> float:
    """Best-of-``repeats`` steps/s of ``step()`` called ``n`` times."""
    best = 0.0
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            if step() and reset is not None:
                reset()
        best = max(best, n / (time.perf_counter() - t0))
    return best


def raw_physics(n_cars: int, steps: int) -> float:
    import pybullet as p

    from torcsrl.envs.vehicle import CarFleet, make_ground

    cid = p.connect(p.DIRECT)
    make_ground(cid)
    fleet = CarFleet(cid, n_cars)
    fleet.reset(np.arange(n_cars), np.zeros((n_cars, 2)), np.zeros(n_cars), 20.0)  # overlapping, as on a grid
    steer, thr, brk = np.zeros(n_cars), np.full(n_cars, 0.3), np.zeros(n_cars)
    i = [0]

    def step():
        fleet.step(steer, thr, brk)
        i[0] += 1
        if i[0] % 500 == 0:  # keep the car on the flat ground near the origin, as the env does
            fleet.reset(np.arange(n_cars), np.zeros((n_cars, 2)), np.zeros(n_cars), 20.0)  # overlapping, as on a grid
        return False

    r = _rate(step, steps) * n_cars
    p.disconnect(cid)
    return r


RAYS = 19
RAY_LEN_M = 200.0


def make_raw_racecar():
    """pybullet_data's racecar URDF driven by random actions, 19 rays of 200 m cast from it each step
    (:func:`physics_throughput.make_racecar`; the raw car never ends an episode)."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from physics_throughput import make_racecar

    return make_racecar(rays=RAYS, ray_len_m=RAY_LEN_M)


def make_default_gym_env():
    """``gym.make("torcsrl/Race-v0")`` with its default arguments and uniform random actions (seeded); ``step()``
    returns whether the episode ended, ``reset()`` starts the next one."""
    import gymnasium as gym

    import torcsrl.envs  # noqa: F401

    env = gym.make("torcsrl/Race-v0")
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, size=(4096, 2)).astype(np.float32)
    k = [0]

    def step() -> bool:
        _, _, te, tr, _ = env.step(actions[k[0] % 4096])
        k[0] += 1
        return te or tr

    return step, env.reset, env.close


def _timed(step, n: int, reset=None) -> tuple[float, float, int]:
    """(seconds in ``step``, seconds in ``reset``, resets) over ``n`` steps."""
    t_step = t_reset = 0.0
    resets = 0
    clock = time.perf_counter
    for _ in range(n):
        t0 = clock()
        done = step()
        t1 = clock()
        t_step += t1 - t0
        if done and reset is not None:
            reset()
            t_reset += clock() - t1
            resets += 1
    return t_step, t_reset, resets


def vs_raw(steps: int, rounds: int = 5) -> dict[str, float]:
    """The env against the raw racecar + rays, interleaved rounds, best of each."""
    raw_step, raw_close = make_raw_racecar()
    env_step, env_reset, env_close = make_default_gym_env()
    _timed(raw_step, 50)
    _timed(env_step, 50, env_reset)
    best = {"raw": 0.0, "env_step": 0.0, "env_all": 0.0}
    reset_s, resets = 0.0, 0
    for _ in range(rounds):
        t, _, _ = _timed(raw_step, steps)
        best["raw"] = max(best["raw"], steps / t)
        t_step, t_reset, n_reset = _timed(env_step, steps, env_reset)
        best["env_step"] = max(best["env_step"], steps / t_step)
        best["env_all"] = max(best["env_all"], steps / (t_step + t_reset))
        reset_s, resets = reset_s + t_reset, resets + n_reset
    raw_close()
    env_close()
    best["reset_us"] = 1e6 * reset_s / resets if resets else float("nan")
    best["resets"] = resets
    return best


def print_vs_raw(r: dict[str, float], steps: int, rounds: int) -> None:
    print(f"\nenv vs raw pybullet, one thread, {rounds} interleaved rounds of {steps} steps (best of each)")
    print(f"{'what':62s} {'steps/s':>9s}")
    print(f"{'raw: pybullet racecar URDF (50 Hz x 5 x 240 Hz) + 19 rays':62s} {r['raw']:9.0f}")
    print(f"{'torcsrl/Race-v0, defaults, random actions, step only':62s} {r['env_step']:9.0f}")
    print(f"{'torcsrl/Race-v0, defaults, random actions, resets included':62s} {r['env_all']:9.0f}")
    print(f"  ratio env / raw, step only:      {r['env_step'] / r['raw']:5.2f}x   (goal >= 2.0x)")
    print(f"  ratio env / raw, resets included: {r['env_all'] / r['raw']:5.2f}x   (goal >= 2.0x)")
    print(f"  reset: {r['reset_us']:.0f} us each ({int(r['resets'])} resets)")


def gym_env(steps: int) -> float:
    import gymnasium as gym

    import torcsrl.envs  # noqa: F401

    env = gym.make("torcsrl/Race-v0", track="road_flow", disable_env_checker=True)
    env.reset(seed=0)
    a = np.array([0.0, 0.3], np.float32)

    def step():
        _, _, te, tr, _ = env.step(a)
        return te or tr

    r = _rate(step, steps, lambda: env.reset())
    env.close()
    return r


def torchrl_env(n_cars: int, steps: int, traffic: dict | None = None) -> float:
    """car-steps/s of the TorchRL env (with ``traffic``: every car of the race counts, opponents included)."""
    from torcsrl.envs import make_env

    kw = {} if traffic is None else {"traffic": traffic, "sensors": ("rangefinder", "state", "opponents")}
    env = make_env(track="road_flow", num_cars=n_cars, seed=0, batched=n_cars > 1, **kw)
    td = env.reset()
    shape = (n_cars, 2) if n_cars > 1 else (2,)
    td["action"] = torch.tensor([0.0, 0.3]).expand(shape).clone()
    state = {"td": td}

    def step():
        _, nxt = env.step_and_maybe_reset(state["td"])
        nxt["action"] = state["td"]["action"]
        state["td"] = nxt
        return False

    r = _rate(step, steps) * env.core.n
    env.close()
    return r


RACE = {"opponents": 3, "driver": {"kind": "expert", "pace": 0.85}, "start": "grid", "order": "random"}


def car_racing(steps: int) -> float | None:
    try:
        import gymnasium as gym

        env = gym.make("CarRacing-v3")
    except Exception:
        return None
    env.reset(seed=0)
    a = np.array([0.0, 0.3, 0.0], np.float32)

    def step():
        _, _, te, tr, _ = env.step(a)
        return te or tr

    r = _rate(step, steps, lambda: env.reset(), repeats=1)
    env.close()
    return r


def highway_racetrack(steps: int) -> float | None:
    try:
        import gymnasium as gym
        import highway_env  # noqa: F401

        env = gym.make("racetrack-v0", config={"observation": {"type": "LidarObservation"}})
    except Exception:
        return None
    env.reset(seed=0)
    a = env.action_space.sample() * 0

    def step():
        _, _, te, tr, _ = env.step(a)
        return te or tr

    r = _rate(step, steps, lambda: env.reset(), repeats=1)
    env.close()
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=3000, help="control steps per measurement")
    ap.add_argument("--quick", action="store_true", help="fewer steps and no peers (a smoke run)")
    ap.add_argument("--race", action="store_true", help="only the race comparison: 4-car race env vs the 1-car env")
    ap.add_argument("--raw-only", action="store_true", help="only the table of the env against raw pybullet")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds of the env-vs-raw table")
    args = ap.parse_args(argv)
    n = 300 if args.quick else args.steps
    if not args.race:
        rounds = 1 if args.quick else args.rounds
        print_vs_raw(vs_raw(n, rounds), n, rounds)
        if args.raw_only:
            return 0
    if args.race:
        one = torchrl_env(1, n)
        race = torchrl_env(1, n, RACE)
        race8 = torchrl_env(8, max(50, n // 8), RACE)
        print(f"\n{'what':55s} {'rate':>10s}  unit")
        print(f"{'TorchRL env, 1 car':55s} {one:10.0f}  car-steps/s")
        print(f"{'TorchRL race env, 1 learner + 3 experts (4 cars)':55s} {race:10.0f}  car-steps/s")
        print(f"{'TorchRL batched race, 8 learners x 4 cars':55s} {race8:10.0f}  car-steps/s")
        print(f"\n  4-car race / 1-car env: {race / one:5.2f}x car-steps/s   (goal >= 0.5x)")
        return 0
    rows: list[tuple[str, float | None, str]] = []
    phys1 = raw_physics(1, n)
    rows.append(("raw physics, 1 car (CarFleet, 50 Hz, 4 x 200 Hz)", phys1, "car-steps/s"))
    g = gym_env(n)
    rows.append(("gymnasium RaceEnv, 1 car", g, "steps/s"))
    t1 = torchrl_env(1, n)
    rows.append(("TorchRL env, 1 car", t1, "steps/s"))
    batched = {}
    for k in (1, 8, 32):
        batched[k] = torchrl_env(k, max(50, n // k))
        rows.append((f"TorchRL batched env, N = {k}", batched[k], "car-steps/s"))
    phys32 = raw_physics(32, max(50, n // 32))
    rows.append(("raw physics, 32 cars", phys32, "car-steps/s"))
    if not args.quick:
        rows.append(("peer: CarRacing-v3 (gymnasium, box2d)", car_racing(min(n, 1000)), "steps/s"))
        rows.append(("peer: highway-env racetrack-v0, lidar", highway_racetrack(min(n, 300)), "steps/s"))
    print(f"\n{'what':55s} {'rate':>10s}  unit")
    for name, rate, unit in rows:
        print(f"{name:55s} {('%10.0f' % rate) if rate else '   (n/a)'}  {unit}")
    print("\nratios")
    print(f"  env overhead / raw physics step, 1 car (gymnasium): {phys1 / g - 1:5.2f}x   (goal <= 1.5x: "
          "overhead = env step - physics step)")
    print(f"  env step / raw physics step, 1 car (gymnasium): {phys1 / g:5.2f}x")
    print(f"  env step / raw physics step, 1 car (TorchRL):   {phys1 / t1:5.2f}x")
    print(f"  batched N=32 env / raw physics N=32:            {phys32 / batched[32]:5.2f}x")
    print(f"  gymnasium env, 1 car:        {g:8.0f} steps/s     (goal >= 2,000)")
    print(f"  batched env, N = 32:         {batched[32]:8.0f} car-steps/s (goal >= 5,000)")
    for name, rate, _ in rows:
        if name.startswith("peer") and rate:
            print(f"  gymnasium RaceEnv / {name[6:]}: {g / rate:5.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
