"""The TorchRL face of the race: one car (batch_size ``[]``) or N cars in one world (``[N]``).

N cars share one pybullet client and never collide; each has its own track (drawn per episode
from the track list), progress and episode, and done cars are reset individually (partial reset
through the ``"_reset"`` key, as TorchRL's collectors do it). This is the fast path for training.

Keys (per car): the sensor observations (``rangefinder`` [m], ``state``, ``pixels`` uint8,
``depth`` [m]), ``action`` float32 ``[2]`` (or ``[3]``), ``reward`` ``[1]``, ``done`` /
``terminated`` / ``truncated`` ``[1]`` bool, and ``info``: distFromStart, distRaced [m], lap,
curLapTime, lastLapTime, bestLapTime [s], finished, track_slot and the reward terms
``reward_<term>``. See :class:`torcsrl.envs.race.RaceEnv` for the meaning and units of each.

With ``traffic`` (a race, :mod:`torcsrl.envs.traffic`) the batch is the N learners; their opponents drive inside
the env, and ``info`` also holds racePos, overtakes, collisions (ints), damage, impulse [kN s] and gapAhead [m].
A learner's reset restarts its whole race group.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from torcsrl.envs.race import INFO_KEYS, RaceCore
from torcsrl.envs.rewards import REWARD_TERMS
from torcsrl.envs.traffic import OPPONENT_RANGE_M

# order matters: it is the column order of the info array built in _observation
_FLOAT_INFO = ("distFromStart", "distRaced", "curLapTime", "lastLapTime", "bestLapTime", "surfaceMu") + tuple(
    f"reward_{t}" for t in REWARD_TERMS)
assert set(_FLOAT_INFO) | {"lap"} >= set(INFO_KEYS)


class TorchRaceEnv(EnvBase):
    """TorchRL ``EnvBase`` over :class:`~torcsrl.envs.race.RaceCore`.

    Args:
        num_cars: N cars; ``batch_size`` is ``[N]``, or ``[]`` when N = 1 and ``batched`` is False.
        batched: keep a batch dimension for N = 1.
        device: torch device of the output tensors (the simulation runs on the CPU).
        **kwargs: everything else goes to :class:`RaceCore` (track, surface, sensors, reward, …).
    """

    _has_dynamic_specs = False

    def __init__(self, num_cars: int = 1, batched: bool | None = None, device: str | torch.device = "cpu",
                 seed: int | None = None, **kwargs: Any) -> None:
        batched = num_cars > 1 if batched is None else bool(batched)
        if num_cars > 1 and not batched:
            raise ValueError("num_cars > 1 needs batched=True")
        self._kwargs = dict(kwargs, num_cars=num_cars, batched=batched, seed=seed)
        self.core = RaceCore(num_cars=num_cars, seed=seed, **kwargs)
        batch = torch.Size([num_cars]) if batched else torch.Size([])
        super().__init__(device=device, batch_size=batch)
        self._batched = batched
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        c = self.core
        b = self.batch_size
        obs = {}
        for key, shape in c.observation_shapes.items():
            full = (*b, *shape)
            if key == "rangefinder":
                obs[key] = Bounded(-1.0, c.rangefinder.range_m, full, dtype=torch.float32, device=self.device)
            elif key in ("state", "telemetry", "road"):
                obs[key] = Unbounded(full, dtype=torch.float32, device=self.device)
            elif key == "opponents":
                obs[key] = Bounded(0.0, OPPONENT_RANGE_M, full, dtype=torch.float32, device=self.device)
            elif key == "pixels":
                obs[key] = Bounded(0, 255, full, dtype=torch.uint8, device=self.device)
            elif key == "depth":
                obs[key] = Bounded(0.0, float(c.camera.far), full, dtype=torch.float32, device=self.device)
        info = {k: Unbounded((*b, 1), dtype=torch.float32, device=self.device) for k in _FLOAT_INFO}
        info["lap"] = Unbounded((*b, 1), dtype=torch.int64, device=self.device)
        info["track_slot"] = Unbounded((*b, 1), dtype=torch.int64, device=self.device)
        info["finished"] = Categorical(2, (*b, 1), dtype=torch.bool, device=self.device)
        if c.traffic is not None:
            for k in ("racePos", "overtakes", "collisions"):
                info[k] = Unbounded((*b, 1), dtype=torch.int64, device=self.device)
            for k in ("damage", "impulse", "gapAhead"):
                info[k] = Unbounded((*b, 1), dtype=torch.float32, device=self.device)
        obs["info"] = Composite(info, shape=b, device=self.device)
        self.observation_spec = Composite(obs, shape=b, device=self.device)
        self.action_spec = Bounded(-1.0, 1.0, (*b, c.action_dim), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded((*b, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, (*b, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, (*b, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, (*b, 1), dtype=torch.bool, device=self.device),
            shape=b, device=self.device)

    # ------------------------------------------------------------------ helpers
    def _wrap(self, source: dict) -> TensorDict:
        """A TensorDict of freshly made tensors, skipping the checks that cost more than the step."""
        return TensorDict._new_unsafe(source, batch_size=self.batch_size, device=self.device)

    def _t(self, x: np.ndarray) -> torch.Tensor:
        nl = self.core.n_learners
        if len(x) != nl:  # a race: the learners are the first rows
            x = x[:nl]
        t = torch.from_numpy(np.ascontiguousarray(x))
        return t if self._batched else t[0]

    def _observation(self) -> dict[str, Any]:
        c = self.core
        out: dict[str, Any] = {}
        for k, v in c.obs.items():
            out[k] = self._t(v if k == "pixels" else v.astype(np.float32, copy=False))
        cur = np.where(c.lap_timed, c.time - c.lap_start_time, 0.0)
        floats = np.stack([c.s, c.dist_raced, cur, c.last_lap_time, c.best_lap_time, c.fleet.wheel_mu.mean(axis=1), *c.terms], axis=1)
        floats = self._t(floats.astype(np.float32))  # [(N,) len(_FLOAT_INFO)]
        info = {k: floats[..., j:j + 1] for j, k in enumerate(_FLOAT_INFO)}
        ints = self._t(np.stack([c.lap, c.slot], axis=1))
        info["lap"] = ints[..., 0:1]
        info["track_slot"] = ints[..., 1:2]
        info["finished"] = self._t(c.finished[:, None])
        if c.traffic is not None:
            tr = c.traffic
            ints = self._t(np.stack([tr.race_pos, tr.overtakes, tr.collisions], axis=1))
            for j, k in enumerate(("racePos", "overtakes", "collisions")):
                info[k] = ints[..., j:j + 1]
            fl = self._t(np.stack([tr.damage, tr.impulse, tr.gap_ahead], axis=1).astype(np.float32))
            for j, k in enumerate(("damage", "impulse", "gapAhead")):
                info[k] = fl[..., j:j + 1]
        out["info"] = self._wrap(info)
        return out

    # ------------------------------------------------------------------ EnvBase API
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1).cpu().numpy()
            if not self._batched:
                mask = mask[:1]
        if mask is None or mask.all():
            self.core.reset()
        else:
            self.core.reset(mask)
        n = self.core.n_learners
        td = self._observation()
        zeros = np.zeros((n, 1), dtype=bool)
        td.update(done=self._t(zeros), terminated=self._t(zeros.copy()), truncated=self._t(zeros.copy()))
        return self._wrap(td)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action", None)
        if action is None:
            raise KeyError(f"step: the input tensordict has no 'action' entry (keys: {sorted(map(str, tensordict.keys()))}); "
                           f"allowed: a float tensor [{', '.join(map(str, (*self.batch_size, self.core.action_dim)))}] in [-1, 1] under 'action'")
        action = action.detach().cpu().numpy().reshape(self.core.n_learners, -1)
        c = self.core
        c.step(action)
        td = self._observation()
        td["reward"] = self._t(c.rewards[:, None].astype(np.float32))
        td["terminated"] = self._t(c.terminated[:, None])
        td["truncated"] = self._t(c.truncated[:, None])
        td["done"] = self._t((c.terminated | c.truncated)[:, None])
        return self._wrap(td)

    def _set_seed(self, seed: int | None) -> None:
        self.core.seed(seed)

    # ------------------------------------------------------------------ exact resume
    def get_sim_state(self) -> dict[str, Any]:
        """The simulation's whole dynamic state as tensors and plain values (a checkpoint loads it
        with ``weights_only=True``): see :meth:`RaceCore.get_state`."""
        return _to_torch(self.core.get_state())

    def set_sim_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`get_sim_state` into an env made with the same arguments: the next steps
        are bit for bit those the saved env would have taken (CPU)."""
        self.core.set_state(_to_numpy(state))

    def close(self, *, raise_if_closed: bool = True) -> None:
        if getattr(self, "core", None) is not None:
            self.core.close()
        super().close(raise_if_closed=raise_if_closed) if "raise_if_closed" in EnvBase.close.__code__.co_varnames else super().close()

    def __getstate__(self):  # pickling re-creates the world from the constructor arguments
        return {"kwargs": self._kwargs, "device": str(self.device)}

    def __setstate__(self, state):
        kw = dict(state["kwargs"])
        self.__init__(device=state["device"], **kw)


def _to_torch(x: Any) -> Any:
    """numpy arrays -> tensors, recursively (dicts and lists); other values as they are."""
    if isinstance(x, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(x))
    if isinstance(x, dict):
        return {k: _to_torch(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_to_torch(v) for v in x]
    return x


def _to_numpy(x: Any) -> Any:
    """The inverse of :func:`_to_torch` (``rng`` state dicts of ints pass through)."""
    if isinstance(x, torch.Tensor):
        return x.numpy()
    if isinstance(x, dict):
        return {k: _to_numpy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_to_numpy(v) for v in x]
    return x
