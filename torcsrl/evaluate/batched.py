"""Batched episodes: the episodes of several cells of one (policy, track, surface) as cars of ONE env.

A report cell is ``episodes`` episodes of one degradation at one severity; the cells that share a
policy and a track differ only in the weather. :func:`run_batch` drives all of them at once:
one :func:`torcsrl.envs.make_env` with ``num_cars = cells × episodes`` (N cars in one pybullet
world, the physics vectorised over them), the policy once per step on the whole batch, and each
cell's degradation stack once per step on its own rows.

Every car keeps the seeds of the one-car path (:func:`torcsrl.evaluate.protocol.run_cell`), so a
batched episode is the SAME episode, bit for bit (tested in ``tests/test_batched_eval.py``):

* **starts**: car ``i`` is reset alone, right after the env's generator is seeded with its
  episode's env seed ``seed_for(seed, "env", track, surface, e)`` — the draws a one-car env
  seeded so makes (random start, spawn jitter);
* **weather**: each cell's stack draws per row (:meth:`torcsrl.transforms.Degradation.set_row_seeds`),
  row ``e`` from the generator a one-car stack seeded with ``seed_for(seed, "degradation", name,
  severity, e)`` would use;
* **physics**: each car's dynamics do not depend on the other cars (they never collide; the numpy
  and the per-car backends compute the same numbers);
* **policy**: a batched matrix product does not give the same float32 bits as one row at a time
  (other kernels, other summation orders), so the actor runs as one matrix-vector product per row
  (:func:`row_linear`: ``baddbmm`` over the rows, equal to the one-car ``F.linear``);
* **books**: the one :class:`~torcsrl.evaluate.protocol.EpisodeBook` of the one-car path.

Supported policies: checkpoint actors on vector observations (rangefinder, state), which is what a
robustness grid drives thousands of times. Others (the expert, scripted drivers, the random
baseline, camera actors) drive one car at a time through :func:`run_cell`
(:func:`supports_batch` says which).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from tensordict import TensorDict

from torcsrl import metrics
from torcsrl.evaluate.protocol import (Degradation, EpisodeBook, default_max_steps, env_sensors, parse_degradation,
                                       seed_for)
from torcsrl.policies import Policy

__all__ = ["supports_batch", "row_linear", "RowActor", "run_batch"]


class _PerCarDraws:
    """Stands in for the env's generator during the one reset of all cars: the k-th draw of car ``i``
    comes from ``gens[i]``, the generator a one-car env seeded with car ``i``'s episode seed has.

    :meth:`torcsrl.envs.race.RaceCore.reset` draws, per car in car order, its start arc length
    (``start="random"``) and its spawn jitter (``spawn_jitter``), all with ``uniform``; a track or a
    surface drawn per episode (``integers``, ``random``) never happens here: a batch is one track on one
    surface. Any other use fails loudly rather than give other numbers than the one-car path.
    """

    def __init__(self, gens: Sequence[np.random.Generator], per_car: int) -> None:
        self.gens = list(gens)
        self.per_car = int(per_car)
        self.k = 0

    def uniform(self, low: float = 0.0, high: float = 1.0, size: Any = None) -> Any:
        if size is not None or self.per_car == 0:
            raise RuntimeError("batched reset: unexpected draw from the env's generator")
        g = self.gens[self.k // self.per_car]
        self.k += 1
        return g.uniform(low, high)

    def __getattr__(self, name: str) -> Any:
        raise RuntimeError(f"batched reset: the env drew with {name!r}; a batch must be one track on one surface")


def supports_batch(policy: Policy) -> bool:
    """True when ``policy`` can drive a batch and stay equal to its one-car self: a stateless checkpoint
    actor (:class:`~torcsrl.agents.networks.DeterministicActor`) on vector observations only."""
    from torcsrl.agents.networks import DeterministicActor
    from torcsrl.policies import CheckpointPolicy

    return (isinstance(policy, CheckpointPolicy) and type(policy.actor) is DeterministicActor
            and not policy.actor.encoder.img_keys and type(policy).__call__ is CheckpointPolicy.__call__)


def row_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``F.linear(x, weight, bias)`` for ``x [B, in]`` computed one row at a time (one ``baddbmm``),
    so that row ``i`` has the bits ``F.linear(x[i:i+1], weight, bias)`` has, whatever ``B``."""
    b = x.shape[0]
    wt = weight.t()
    return torch.baddbmm(bias.expand(b, 1, -1), x.unsqueeze(1), wt.expand(b, *wt.shape)).squeeze(1)


class RowActor:
    """A checkpoint policy's deterministic actor on a batch, row for row equal to the one-car policy."""

    def __init__(self, policy: Policy) -> None:
        if not supports_batch(policy):
            raise ValueError(f"policy {policy.name!r} ({type(policy).__name__}) cannot drive a batch")
        self.policy = policy
        self.actor = policy.actor
        self.keys = tuple(policy.obs_keys)
        self.div = dict(policy.obs_divisors)

    @torch.no_grad()
    def __call__(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        act = self.actor
        x = act.encoder(*(obs[k] / self.div[k] if k in self.div else obs[k] for k in self.keys))
        *hidden, last = act._linears()
        if x.shape[0] == 1:  # one car: exactly the one-car policy's kernels
            for lin in hidden:
                x = F.linear(x, lin.weight, lin.bias).relu_()
            a = torch.tanh(F.linear(x, last.weight, last.bias))
        else:
            for lin in hidden:
                x = row_linear(x, lin.weight, lin.bias).relu_()
            a = torch.tanh(row_linear(x, last.weight, last.bias))
        return a if act._unit else act.a_mid + act.a_half * a


@torch.no_grad()
def run_batch(policy: Policy, track: str, surface: str | None, degradations: Sequence[Any], *, episodes: int = 1,
              laps: int = 1, seed: int = 0, max_steps: int | None = None, env_kwargs: Mapping[str, Any] | None = None,
              ) -> list[list[dict[str, Any]]]:
    """Drive ``episodes`` episodes of every degradation in ``degradations`` (None / severity 0 = the
    clean cell) on one track as cars of one env; returns one list of rows per degradation, each row
    what :func:`torcsrl.evaluate.protocol.run_cell` returns for that cell and episode."""
    from torcsrl.envs import make_env
    from torcsrl.envs import tracks as _tracks
    from torcsrl.transforms import seed_degradation_rows

    degs: list[Degradation] = [parse_degradation(d) for d in degradations]
    if not degs:
        return []
    episodes = int(episodes)
    geom = _tracks.load(track, surface=surface)
    surface_name = surface or geom.default_surface
    hz = {**dict(env_kwargs or {}), **policy.env_overrides}.get("control_hz", 50.0)
    steps = int(max_steps) if max_steps else default_max_steps(geom.length, laps, 1.0 / float(hz))
    cars = [(c, e) for c in range(len(degs)) for e in range(episodes)]
    n = len(cars)
    kw = dict(env_kwargs or {})
    kw.update({k: v for k, v in policy.env_overrides.items() if k != "sensors"})
    sensors = env_sensors(policy)
    env = make_env(track=track, surface=surface, lap_limit=int(laps), max_steps=steps, num_cars=n, batched=True,
                   sensors=sensors, **kw)
    try:
        core = env.core
        core.scalar_locate_max_cars = n  # every car located as a one-car env locates it (the same numbers)
        env_seeds = [seed_for(seed, "env", track, surface_name, e) for e in range(episodes)]
        deg_seeds = [[seed_for(seed, "degradation", d.name, d.severity, e) for e in range(episodes)] if not d.clean else None
                     for d in degs]
        # one reset of every car; the generator a car's start draws come from is the one-car env's
        per_car = int(core.start == "random") + int(core.spawn_jitter[0] != 0) + int(core.spawn_jitter[1] != 0)
        core.rng = _PerCarDraws([np.random.default_rng(env_seeds[e]) for _, e in cars], per_car)
        td = env.reset()
        core.rng = np.random.default_rng(seed)
        stacks = []
        for c, d in enumerate(degs):
            if d.clean:
                stacks.append(None)
                continue
            t = d.build()
            seed_degradation_rows(t, deg_seeds[c])
            stacks.append(t)
        spans = [(c * episodes, (c + 1) * episodes) for c in range(len(degs))]
        actor = RowActor(policy)
        book = EpisodeBook(n, laps)
        empty = TensorDict({}, batch_size=[episodes])

        def observe(obs_td, first: bool) -> dict[str, torch.Tensor]:
            """The policy's view: each cell's rows through its own stack."""
            parts: dict[str, list[torch.Tensor]] = {k: [] for k in sensors}
            for (r0, r1), t in zip(spans, stacks):
                sub = TensorDict._new_unsafe({k: obs_td.get(k)[r0:r1] for k in sensors}, batch_size=torch.Size([r1 - r0]))
                if t is not None:
                    sub = t._reset(empty, sub) if first else t._call(sub)
                for k in sensors:
                    parts[k].append(sub.get(k))
            return {k: torch.cat(v) if len(v) > 1 else v[0] for k, v in parts.items()}

        obs = observe(td, True)
        nxt = td
        stop = torch.tensor([0.0, -1.0])
        for _ in range(steps):
            action = actor(obs)
            action[torch.from_numpy(~book.active)] = stop  # cars whose episode ended brake to a halt, off the books
            td = env.step(TensorDict._new_unsafe({"action": action}, batch_size=torch.Size([n])))
            nxt = td.get("next")
            book.record(action, nxt, core.reason)
            if not book.active.any():
                break
            obs = observe(nxt, False)
        book.close(nxt, core.reason)
        dt = float(core.dt)
        out: list[list[dict[str, Any]]] = []
        for c, d in enumerate(degs):
            rows = []
            for e in range(episodes):
                i = c * episodes + e
                rows.append({"policy": policy.name, "policy_fingerprint": policy.fingerprint, "track": track,
                             "surface": surface_name, "corruption": d.name if not d.clean else metrics.CLEAN,
                             "severity": 0 if d.clean else d.severity, "episode": e, "env_seed": env_seeds[e],
                             "degradation_seed": deg_seeds[c][e] if deg_seeds[c] is not None else None, "max_steps": steps,
                             **book.row(i, dt)})
            out.append(rows)
        return out
    finally:
        env.close()
