"""Frame stacks (``frame_stack: K``): the env's ``FrameStack`` gives the actor K frames along channels; the replay ring
stores every frame once and rebuilds the same stacks when sampling (episode starts, episode ends, a wrapped ring, a
dump written at K = 1); the policy's own history (evaluation on one-frame envs) is the env's stack."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torcsrl.transforms import FrameStack, stack_frames
from torcsrl.utils.replay import ReplayBuffer

K = 3
FS = 2


def _stacked_rollout(steps: int, cars: int, k: int = K, hw: int = 6, seed: int = 0) -> TensorDict:
    """``[cars, steps]`` transitions whose ``pixels`` are the stacks a FrameStack env gives (oldest frame first, the
    episode's first frame repeated after every reset), episodes ending every 5th step of car 0 and every 4th of car 1."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, 256, (cars, steps + 1, 3, hw, hw), dtype=torch.uint8, generator=g)
    finals = torch.randint(0, 256, (cars, steps, 3, hw, hw), dtype=torch.uint8, generator=g)
    done = torch.zeros(cars, steps, 1, dtype=torch.bool)
    for c, every in enumerate((5, 4)[:cars]):
        done[c, every - 1::every] = True
    obs = torch.empty(cars, steps, 3 * k, hw, hw, dtype=torch.uint8)
    nxt = torch.empty_like(obs)
    for c in range(cars):
        hist = None
        for t in range(steps):
            hist = stack_frames(hist, frames[c, t], k)
            obs[c, t] = hist
            if done[c, t]:
                nxt[c, t] = torch.cat([hist[3:], finals[c, t]], 0)
                hist = None  # the next step is a reset: K copies of its frame
            else:
                nxt[c, t] = torch.cat([hist[3:], frames[c, t + 1]], 0)
    state = torch.randn(cars, steps + 1, 4, generator=g)
    n = {"pixels": nxt, "state": state[:, 1:], "reward": torch.randn(cars, steps, 1, generator=g), "done": done,
         "terminated": done.clone(), "truncated": torch.zeros_like(done)}
    return TensorDict({"pixels": obs, "state": state[:, :-1], "action": torch.rand(cars, steps, 2, generator=g),
                       "next": TensorDict(n, batch_size=[cars, steps])}, batch_size=[cars, steps])


@pytest.mark.parametrize("cars", [1, 2])
def test_the_ring_stores_each_frame_once_and_rebuilds_the_env_stacks(cars):
    ro = _stacked_rollout(23, cars)
    rb = ReplayBuffer(1000, 8, ["pixels", "state"], streams=cars, history={"pixels": K})
    for t in range(23):  # one env step at a time, as the collector writes them
        rb.extend(ro[:, t])
    plain = ReplayBuffer(1000, 8, ["pixels", "state"], streams=cars)
    plain.extend(ro[:, :1].apply(lambda x: x[..., -3:, :, :] if x.dtype == torch.uint8 else x))
    assert rb._rows["pixels"].shape[1:] == (3, 6, 6)  # one frame per row
    assert rb.bytes_per_transition == plain.bytes_per_transition  # K does not multiply the bytes
    got = rb[:]
    want = ro.transpose(0, 1).reshape(-1)  # ring order: step-major over the cars
    assert torch.equal(got["pixels"], want["pixels"])
    assert torch.equal(got["next", "pixels"], want["next", "pixels"])  # episode ends: the row's stack + the final frame
    assert bool(want["next", "done"].any())


def test_a_wrapped_ring_pads_only_its_oldest_rows():
    ro = _stacked_rollout(40, 1)
    rb = ReplayBuffer(10, 4, ["pixels", "state"], history={"pixels": K})
    rb.extend(ro[0])
    got, want = rb[:], ro[0, -10:]
    assert torch.equal(got["next", "pixels"], want["next", "pixels"])
    # the oldest kept row lost the frames before it: its stack repeats its own frame (unless it starts an episode anyway)
    assert torch.equal(got["pixels"][0], torch.cat([want["pixels"][0, -3:]] * K, 0))
    assert torch.equal(got["pixels"][K - 1:], want["pixels"][K - 1:])


def test_a_dump_written_at_one_frame_is_sampled_at_any_stack(tmp_path):
    ro = _stacked_rollout(30, 1)
    one = ReplayBuffer(100, 4, ["pixels", "state"])
    one.extend(ro[0].apply(lambda x: x[..., -3:, :, :] if x.dtype == torch.uint8 else x))  # what a K = 1 run stores
    one.dumps(tmp_path / "d")
    back = ReplayBuffer(100, 4, ["pixels", "state"], history={"pixels": K})
    back.loads(tmp_path / "d")
    assert torch.equal(back[:]["pixels"], ro[0]["pixels"]) and torch.equal(back[:]["next", "pixels"], ro[0]["next", "pixels"])


def test_a_stack_of_the_wrong_size_or_key_is_refused_in_one_line():
    with pytest.raises(ValueError, match="does not store") as err:
        ReplayBuffer(10, 4, ["state"], history={"pixels": K})
    assert "\n" not in str(err.value)
    rb = ReplayBuffer(10, 4, ["pixels", "state"], history={"pixels": 4})
    with pytest.raises(ValueError, match="not a stack of 4 frames"):
        rb.extend(_stacked_rollout(3, 1, k=3)[0, :1])  # 9 channels are not 4 frames of 3
    with pytest.raises(ValueError, match=">= 2"):
        FrameStack(1, ["pixels"])


def test_frame_stack_env_and_the_policy_history_agree_across_a_reset():
    from torcsrl.envs import make_env
    from torcsrl.transforms import LeanTransformedEnv
    from torchrl.envs import Compose
    from torchrl.envs.utils import step_mdp

    kw = dict(track="oval", sensors=("pixels", "telemetry"), camera={"width": 32, "height": 24}, seed=3, max_steps=4)
    raw, env = make_env(**kw), LeanTransformedEnv(make_env(**kw), Compose(FrameStack(K, ["pixels"])))
    try:
        assert env.observation_spec["pixels"].shape == (3 * K, 24, 32)
        a, b = env.reset(), raw.reset()
        hist = None
        for t in range(7):  # an episode of 4 steps, then a reset, then more
            hist = stack_frames(hist, b["pixels"], K)
            assert torch.equal(a["pixels"], hist), t
            act = torch.tensor([0.1 * (t % 3 - 1), 0.6])
            a, b = env.step(a.set("action", act)), raw.step(b.set("action", act))
            if bool(a["next", "done"]):
                a, b, hist = env.reset(), raw.reset(), None
            else:
                a, b = step_mdp(a), step_mdp(b)
        # exact resume: the frames held for the next stack are part of the env's saved state
        fs = env.transform[0]
        state = fs.get_sim_state()
        before = a["pixels"].clone()
        fs.set_sim_state({k: torch.zeros_like(v) for k, v in state.items()})
        fs.set_sim_state(state)
        nxt = env.step(a.set("action", torch.tensor([0.0, 0.5])))["next", "pixels"]
        assert torch.equal(nxt[:-3], before[3:])
    finally:
        env.close()
        raw.close()


def test_a_frame_stacked_pixel_td3_run_resumes_exactly(tmp_path):
    """Two cars (their episodes end apart: partial resets of the stacks), TD3 on 2-frame stacks: stopped at a checkpoint
    and resumed, it logs what the uninterrupted run logs (the FrameStack's held frames are in the checkpoint). The
    checkpoint (160 frames) falls inside a log window (every 100): the episodes booked before it count in the resumed
    run's next line too."""
    from _compose import compose_config

    from torcsrl.training import train
    from torcsrl.utils.logging import read_csv_metric

    def run(*ov):
        return compose_config("env=race", "debug=smoke", "sensors=camera", "env.camera.width=32", "env.camera.height=32",
                              "algo.encoder.cnn_channels=[8,8]", "algo.encoder.cnn_kernels=[4,3]", "algo.encoder.cnn_strides=[2,2]",
                              "algo.batch_size=16", f"frame_stack={FS}", "env.track=oval", "env.num_cars=2", "env.max_steps=30", "eval.max_steps=20",
                              "checkpoint.every_frames=160", "collector.frames_per_batch=20", "learner.warmup_frames=60",
                              "collector.init_random_frames=40", *ov)

    ref = train(run("total_frames=320", f"run_dir={tmp_path / 'ref'}"))
    train(run("total_frames=160", f"run_dir={tmp_path / 'cut'}"))
    res = train(run("total_frames=320", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    assert ref["episodes"] >= 4
    for k in ("frames", "updates", "episodes", "loss/qvalue", "eval/reward"):
        assert res[k] == ref[k], k
    for m in ("loss/qvalue", "train/episode_reward"):
        assert read_csv_metric(tmp_path / "cut", m) == read_csv_metric(tmp_path / "ref", m), m
