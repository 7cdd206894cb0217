"""ReplayBuffer extra per-row keys (the demonstrations' expert labels): stored, sampled, dumped and checked."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torcsrl.utils.replay import ReplayBuffer


def _step(t: int, done: bool = False) -> TensorDict:
    obs = torch.full((1, 3), float(t))
    nxt = TensorDict({"obs": obs + 1, "reward": torch.full((1, 1), float(t)), "done": torch.tensor([[done]]),
                      "terminated": torch.tensor([[done]]), "truncated": torch.tensor([[False]])}, batch_size=[1])
    return TensorDict({"obs": obs, "action": torch.full((1, 2), float(t)), "expert_action": torch.full((1, 2), -float(t)),
                       "next": nxt}, batch_size=[1])


def test_extra_keys_travel_with_their_rows(tmp_path):
    rb = ReplayBuffer(100, 16, ["obs"], extra_keys=["expert_action"])
    for t in range(20):
        rb.extend(_step(t, done=t % 7 == 6))
    b = rb.sample()
    assert torch.equal(b["expert_action"], -b["action"])  # each label stays with its own row
    assert torch.equal(b["obs"][:, :1].expand(-1, 2), b["action"])
    rb.dumps(tmp_path / "d")
    back = ReplayBuffer(100, 16, ["obs"], extra_keys=["expert_action"])
    back.loads(tmp_path / "d")
    assert torch.equal(back[:]["expert_action"], rb[:]["expert_action"])
    plain = ReplayBuffer(100, 16, ["obs"])
    with pytest.raises(ValueError, match="extra keys"):
        plain.loads(tmp_path / "d")


def test_without_extra_keys_the_layout_is_unchanged():
    rb = ReplayBuffer(10, 4, ["obs"])
    step = _step(1)
    del step["expert_action"]
    rb.extend(step)
    rb.extend(_step(2).exclude("expert_action"))
    assert set(rb.sample().keys()) == {"obs", "action", "index", "next"}


def test_a_dump_is_a_function_of_the_steps_written_not_of_uninitialised_memory(tmp_path):
    """The row after the newest step holds its next observation only; the rest of that row was never written (its
    storage is torch.empty). Two buffers fed the same steps write the same files whatever that memory held (seen: the
    same seed's demonstrations differed in one stray action value, so their checksums did)."""
    import json

    sums = []
    for k, junk in enumerate((2.0, -2.0)):
        rb = ReplayBuffer(100, 16, ["obs"], extra_keys=["expert_action"])
        for t in range(20):
            rb.extend(_step(t, done=t % 7 == 6))
        rb._rows["action"][20] = junk  # what uninitialised memory may hold
        rb._rows["reward"][20] = junk
        rb.dumps(tmp_path / f"d{k}")
        sums.append(json.loads((tmp_path / f"d{k}" / "meta.json").read_text())["checksums"])
        back = ReplayBuffer(100, 16, ["obs"], extra_keys=["expert_action"])
        back.loads(tmp_path / f"d{k}")
        assert torch.equal(back[:]["action"], rb[:]["action"])  # the steps written are untouched
    assert sums[0] == sums[1]


def test_sampling_without_the_successor_draws_the_same_rows_and_leaves_next_out():
    """``successor=False`` (imitation's batches): the same random rows as a full sample, every key of the step itself
    equal, no ``next``; so a DAgger fit that skips ``next`` trains on the very batches it did before."""
    from torcsrl.training.demos import DemoPool, mixed_sample

    bufs = []
    for n in (30, 12, 9):
        rb = ReplayBuffer(100, 16, ["obs"], extra_keys=["expert_action"])
        for t in range(n):
            rb.extend(_step(100 * len(bufs) + t, done=t % 7 == 6))
        bufs.append(rb)
    torch.manual_seed(5)
    full = bufs[0].sample()
    torch.manual_seed(5)
    lean = bufs[0].sample(successor=False)
    assert "next" in full.keys() and set(lean.keys()) == {"obs", "action", "expert_action", "index"}
    assert all(torch.equal(lean[k], full[k]) for k in lean.keys())
    for sample in (lambda s: mixed_sample(bufs, 24, s), lambda s: DemoPool(bufs).sample(24, s)):
        torch.manual_seed(6)
        full = sample(True)
        torch.manual_seed(6)
        lean = sample(False)
        assert "next" in full.keys() and "next" not in lean.keys() and lean.batch_size == full.batch_size == torch.Size([24])
        assert all(torch.equal(lean[k], full[k]) for k in lean.keys())
        assert {int(v) // 100 for v in lean["obs"][:, 0]} == {0, 1, 2}  # every buffer drawn from, in proportion
