"""Camera transitions in the replay buffer: each frame stored ONCE, as uint8, in RAM and on disk, and a dump/load round
trip gives back the same bytes for frames and next frames (episode ends included: the final frame table)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torcsrl.utils.replay import ReplayBuffer

KEYS = ["pixels", "telemetry", "rangefinder", "state"]  # the camera actor's set + the asymmetric critic's


def _camera_rollout(steps: int, cars: int, hw: int = 16, seed: int = 0) -> TensorDict:
    """``[cars, steps]`` transitions with random uint8 frames, each next frame the following step's frame except at
    episode ends (every 5th step of car 0, every 7th of car 1), where a reset frame follows."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, 256, (cars, steps + 1, 3, hw, hw), dtype=torch.uint8, generator=g)
    finals = torch.randint(0, 256, (cars, steps, 3, hw, hw), dtype=torch.uint8, generator=g)
    vec = {k: torch.randn(cars, steps + 1, n, generator=g) for k, n in (("telemetry", 9), ("rangefinder", 19), ("state", 11))}
    done = torch.zeros(cars, steps, 1, dtype=torch.bool)
    for c, every in enumerate((5, 7)[:cars]):
        done[c, every - 1::every] = True
    nxt = {"pixels": torch.where(done[..., None, None], finals, frames[:, 1:]), "reward": torch.randn(cars, steps, 1, generator=g),
           "done": done, "terminated": done.clone(), "truncated": torch.zeros_like(done)}
    nxt.update({k: v[:, 1:] for k, v in vec.items()})
    return TensorDict({"pixels": frames[:, :-1], **{k: v[:, :-1] for k, v in vec.items()}, "action": torch.rand(cars, steps, 2, generator=g),
                       "next": TensorDict(nxt, batch_size=[cars, steps])}, batch_size=[cars, steps])


@pytest.mark.parametrize("storage", ["ram", "disk"])
def test_uint8_frames_round_trip_extend_dumps_loads_sample(tmp_path, storage):
    ro = _camera_rollout(30, cars=2)
    rb = ReplayBuffer(1000, 16, KEYS, streams=2, storage=storage, path=tmp_path / "mm")
    rb.extend(ro)
    assert rb._rows["pixels"].dtype == torch.uint8 and rb._finals["pixels"].dtype == torch.uint8
    # one frame per row (no next frame stored with it), + 4 x 9..19 floats, action, reward, 3 flags, the finals pointer
    assert rb.bytes_per_transition == 3 * 16 * 16 + 4 * (9 + 19 + 11) + 4 * 2 + 4 + 3 + 4
    assert rb.finals_written == int(ro["next", "done"].sum())  # one final frame per finished episode, nothing else
    if storage == "disk":
        sizes = [p.stat().st_size for p in (tmp_path / "mm").rglob("pixels.memmap")]
        assert sizes == [rb.rows * 3 * 16 * 16] * 2  # the rows and finals tables, one uint8 byte per pixel on disk
    rb.dumps(tmp_path / "dump")
    back = ReplayBuffer(1000, 16, KEYS, streams=2)
    back.loads(tmp_path / "dump")
    torch.manual_seed(3)
    a = rb.sample(64)
    torch.manual_seed(3)
    b = back.sample(64)
    for key in ("pixels", ("next", "pixels")):
        assert a[key].dtype == b[key].dtype == torch.uint8
        assert torch.equal(a[key], b[key]), key
    # and they are the rollout's own frames: obs and next obs (final frames at episode ends)
    flat = ro.transpose(0, 1).reshape(-1)  # ring row order: step-major over the 2 cars
    idx = a["index"] % back.rows
    assert torch.equal(a["pixels"], flat["pixels"][idx]) and torch.equal(a["next", "pixels"], flat["next", "pixels"][idx])
    assert torch.equal(a["next", "state"], flat["next", "state"][idx])
    assert bool(a["next", "done"].any()), "the batch should include episode ends (final frames)"
