"""ParallelEnv (2 workers) with a representative stack: one degradation of each kind (step
noise, episode fault, temporal, camera episodic/step, state). Worker start-up is slow, so one
ParallelEnv serves all checks; the full per-name matrix runs in-process
(test_transform_contract.py)."""

from __future__ import annotations


import torch
from torchrl.envs import Compose, ParallelEnv, TransformedEnv, check_env_specs

from _toy_sensor_env import ToySensorEnv
from torcsrl.transforms import (
    BeamNoise,
    DeadBeams,
    DegradedEnv,
    FrameDrop,
    KeepClean,
    Latency,
    Mud,
    Rain,
    StateBias,
    seed_degradations,
)

KEYS = ["rangefinder", "state", "pixels"]


def make_worker_env():
    # fixed_phase: every worker reads the same clean values, so any difference between the
    # workers' degraded readings comes from the transforms' own (independently seeded) draws
    stack = Compose(
        KeepClean(KEYS),
        BeamNoise(3),
        DeadBeams(5),
        Latency(2, in_keys=["rangefinder"]),
        Rain(3),
        Mud(4),
        FrameDrop(5),
        StateBias(4),
    )
    return DegradedEnv(ToySensorEnv([], fixed_phase=True, offtrack=False), stack)


def test_parallel_env_two_workers():
    penv = ParallelEnv(2, make_worker_env, mp_start_method="fork")
    try:
        check_env_specs(penv, seed=0)

        def run(seed):
            penv.set_seed(seed)
            return penv.rollout(6, break_when_any_done=False)

        a, b = run(3), run(3)
        assert torch.equal(a["next", "pixels"], b["next", "pixels"]), "same seed, same weather"
        for k in KEYS:
            assert torch.equal(a[k + "_clean"][0], a[k + "_clean"][1])  # identical clean input
            assert not torch.equal(a["next", k][0], a["next", k][1]), f"workers share weather on {k}"
        # outer stack on the batched env: per-element draws across the batch dim
        outer = TransformedEnv(penv, Compose(KeepClean(["rangefinder"], suffix="_raw"), BeamNoise(4, seed=0)))
        td = outer.rollout(3, break_when_any_done=False)
        assert td.batch_size == (2, 3)
        dev = td["next", "rangefinder"] - td["next", "rangefinder_raw"]
        assert not torch.equal(dev[0], dev[1])
        assert seed_degradations(outer, 1) == 1
    finally:
        penv.close()
