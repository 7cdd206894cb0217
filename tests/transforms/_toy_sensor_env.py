"""A pybullet-free toy TorchRL env with the race env's four observation keys and specs.

Readings are smooth functions of (per-env phase, step) so they change every step (latency and
holds are visible), and one env in a batch goes "off the track" (all beams -1) now and then.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from torcsrl.transforms.synthetic import road_frame

N_BEAMS = 19
N_STATE = 12
OMEGA = 0.3  # rad/step: slow enough that a delay of 8 steps is still < half a period


class ToySensorEnv(EnvBase):
    """batch_size [] or [N]; keys "rangefinder" [19] m (-1 off track), "state" [12],
    "pixels" uint8 [3, H, W], "depth" [1, H, W] m, "opponents" [36] m (200 = free sector). ``fixed_phase`` makes every env (and every
    seed) produce the same clean readings, to isolate the transforms' own randomness."""

    def __init__(
        self,
        batch_size=(),
        H: int = 32,
        W: int = 32,
        max_steps: int = 50,
        fixed_phase: bool = False,
        offtrack: bool = True,
        seed: int | None = 0,
    ):
        super().__init__(batch_size=torch.Size(batch_size))
        bs = self.batch_size
        self.H, self.W, self.max_steps = H, W, max_steps
        self.fixed_phase = fixed_phase
        self.offtrack = offtrack
        self.observation_spec = Composite(
            rangefinder=Bounded(-1.0, 200.0, shape=(*bs, N_BEAMS), dtype=torch.float32),
            state=Unbounded(shape=(*bs, N_STATE), dtype=torch.float32),
            pixels=Bounded(0, 255, shape=(*bs, 3, H, W), dtype=torch.uint8),
            depth=Unbounded(shape=(*bs, 1, H, W), dtype=torch.float32),
            opponents=Bounded(0.0, 200.0, shape=(*bs, 36), dtype=torch.float32),
            shape=bs,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*bs, 2))
        self.reward_spec = Unbounded(shape=(*bs, 1))
        self.full_done_spec = Composite(
            done=Categorical(2, shape=(*bs, 1), dtype=torch.bool),
            terminated=Categorical(2, shape=(*bs, 1), dtype=torch.bool),
            truncated=Categorical(2, shape=(*bs, 1), dtype=torch.bool),
            shape=bs,
        )
        pix, depth = road_frame(H, W)
        self._pix = pix.float()
        self._depth = depth
        self._rng = torch.Generator()
        self._phase = torch.zeros(bs)
        self._t = torch.zeros(bs, dtype=torch.long)
        if seed is not None:
            self.set_seed(seed)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._rng.manual_seed(int(seed))

    def _obs(self) -> dict:
        bs = self.batch_size
        ph = self._phase
        t = self._t.float()
        a = (ph + OMEGA * t).unsqueeze(-1)  # [*B, 1]
        beams = torch.linspace(-1.5, 1.5, N_BEAMS)
        rng = 5.0 + 95.0 * (0.5 + 0.5 * torch.sin(a + beams) * torch.cos(0.5 * beams))
        if self.offtrack and bs.numel() > 1:
            off = (self._t % 7 == 3).reshape(-1)
            off[1:] = False  # env 0 leaves the track every 7 steps
            rng = torch.where(off.reshape(*bs, 1), torch.full_like(rng, -1.0), rng)
        k = torch.arange(N_STATE, dtype=torch.float32)
        scale = torch.tensor([0.2, 0.8, 30.0, 2.0, 0.5] + [90.0] * 4 + [6000.0, 3.0, 1.0])
        state = scale * torch.sin(a + 0.7 * k)
        gain = (0.75 + 0.25 * torch.sin(a)).reshape(*bs, 1, 1, 1)
        pixels = (self._pix * gain).round().clamp(0, 255).to(torch.uint8)
        depth = self._depth * (1.0 + 0.1 * torch.sin(a)).reshape(*bs, 1, 1, 1)
        sect = torch.arange(36, dtype=torch.float32)
        opp = 10.0 + 90.0 * (0.5 + 0.5 * torch.sin(a + 0.4 * sect))
        opp = torch.where(torch.sin(a + 0.9 * sect) > 0.3, opp, torch.full_like(opp, 200.0))  # cars in some sectors
        return {"rangefinder": rng, "state": state, "pixels": pixels, "depth": depth, "opponents": opp}

    def _done(self) -> dict:
        bs = self.batch_size
        trunc = (self._t >= self.max_steps).reshape(*bs, 1)
        return {"done": trunc.clone(), "terminated": torch.zeros_like(trunc), "truncated": trunc}

    def _reset(self, tensordict=None, **kwargs):
        bs = self.batch_size
        mask = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones(bs, dtype=torch.bool) if mask is None else mask.reshape(bs)
        if self.fixed_phase:
            new_phase = torch.zeros(bs)
        else:
            new_phase = torch.rand(bs, generator=self._rng) * 2 * math.pi
        self._phase = torch.where(mask, new_phase, self._phase)
        self._t = torch.where(mask, torch.zeros_like(self._t), self._t)
        return TensorDict({**self._obs(), **self._done()}, bs)

    def _step(self, tensordict):
        self._t = self._t + 1
        out = TensorDict(
            {**self._obs(), **self._done(), "reward": torch.zeros(*self.batch_size, 1)},
            self.batch_size,
        )
        return out
