"""Batched episodes: the episodes of several cells of one (policy, track, surface) as cars of ONE env.

A report cell is ``episodes`` episodes of one degradation at one severity; the cells that share a
policy and a track differ only in the weather. :func:`run_batch` drives them as cars of ONE
:func:`torcsrl.envs.make_env` (N cars in pybullet worlds of :data:`CARS_PER_WORLD`, the physics
vectorised over them): the cars form groups of ``episodes`` cars, each group drives one cell, a car
whose episode has ended is parked (out of the physics), and a group whose episodes have all ended is
reset (alone) to drive the next cell waiting. The policy runs once per step on the whole batch, each
cell's degradation stack once per step on its group's rows.

Every car keeps the seeds of the one-car path (:func:`torcsrl.evaluate.protocol.run_cell`), and a
batched episode is the SAME episode as its one-car run in what the policy sees and does (float32
observations, actions, rows; tested in ``tests/test_batched_eval.py``), though not in the last bits of
the float64 physics (see *physics*), as long as no two cars of the batch touch the ground with their
chassis in the same physics substep (see *The exceptions* below):

* **starts**: a reset draws each car's start (random start arc length, spawn jitter) from the
  generator a one-car env seeded with its episode's env seed ``seed_for(seed, "env", track,
  surface, e)`` would use (:class:`_PerCarDraws`);
* **weather**: each cell's stack draws per row (:meth:`torcsrl.transforms.Degradation.set_row_seeds`),
  row ``e`` from the generator a one-car stack seeded with ``seed_for(seed, "degradation", name,
  severity, e)`` would use;
* **physics**: a car's dynamics do not depend on the other cars (they never collide), but the numpy
  backend that moves all cars at once does not reproduce the per-car path's float64 bits (batched
  matrix products sum in another order, and the number of rows changes the kernel): the state
  differs from the first step by ~1e-16 relative, far below what the float32 observations resolve.
  Rarely that reaches the float32 bits: on a reduced grid of ``benchmarks/report_throughput.py`` 8 of 88 episodes
  had one beam one float32 ulp off (return ~4e-10 relative), so a row may differ in its last digit. Every car is
  located on its track by the one-car env's chord walk (``RaceCore.scalar_locate_max_cars``;
  :meth:`Track.track_points` walks every car at once with the walk's bits; the windowed projection may put a car
  standing exactly on the start line at s = L - ε instead of 0). The cars are dealt over pybullet worlds of
  :data:`CARS_PER_WORLD` (``RaceCore(cars_per_world=...)``): a car moves in its world as it would in
  one shared world, and the collision broadphase of cars that drive the same line stays cheap;
* **policy**: a batched matrix product does not give the same float32 bits as one row at a time
  (other kernels, other summation orders), so the actor runs as one matrix-vector product per row
  (:func:`row_linear`: ``baddbmm`` over the rows, equal to the one-car ``F.linear``);
* **books**: the one :class:`~torcsrl.evaluate.protocol.EpisodeBook` of the one-car path.

The exceptions: a chassis that touches the ground (hard cornering or braking at the suspension's bump
stop, a car leaving the road; the car model gives the body a collision box) makes a contact that pybullet's solver solves
together with the contacts other cars have in the same substep, so those cars' numbers differ from
their one-car runs in the last bits from then on, and their episodes diverge like any chaotic
trajectory (``minimumSolverIslandSize=1`` does not separate them). On the grid of
``benchmarks/report_throughput.py`` (which counts them) this touched 0 (248 cars at once) and 19 (64 cars, refilled)
of the 248 kidney episodes, and some rallycross ones; the seeds, and with them common random numbers, are
unaffected. And when the chord-by-chord walk that locates a car on its track fails for one car (far off the road),
``RaceCore`` locates every car of that step by the vectorised projection, which may differ from the walk in the
last bits.

Supported policies: checkpoint actors on vector observations (rangefinder, state, opponents; with a state
history and a grip head too), which is what a robustness grid drives thousands of times. Others (the expert, scripted drivers, the random
baseline, camera actors) drive one car at a time through :func:`run_cell`
(:func:`supports_batch` says which).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from tensordict import TensorDict

from torcsrl import metrics
from torcsrl.envs import make_env
from torcsrl.envs import tracks as _tracks
from torcsrl.evaluate.protocol import EpisodeBook, env_sensors
from torcsrl.evaluate.spec import Degradation, default_max_steps, parse_degradation, seed_for
from torcsrl.nets import DeterministicActor, TanhGaussianActor
from torcsrl.policies import CheckpointPolicy, EnsemblePolicy, Policy, SideGuard
from torcsrl.transforms import seed_degradation_rows, stack_frames

__all__ = ["supports_batch", "row_linear", "RowActor", "EnsembleRowActor", "GuardRowActor", "row_actor", "run_batch", "CARS_PER_WORLD"]

#: Cars per pybullet world of a batch (``RaceCore(cars_per_world=...)``): the cars of a grid drive the same line, and in
#: one world the collision broadphase's cost of their overlapping boxes grows with the square of their number.
CARS_PER_WORLD = 32


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
    """True when ``policy`` can drive a batch and stay equal to its one-car self: a checkpoint actor
    (:class:`~torcsrl.nets.DeterministicActor`, with or without a grip head, or PPO's
    :class:`~torcsrl.nets.TanhGaussianActor`, whose mean action is the same MLP + tanh) on vector observations only, a
    ``state_history`` included (:class:`RowActor` keeps each row's readings and restarts them with its group)."""
    if isinstance(policy, SideGuard):  # a side guard around such a policy (or ensemble): its correction is row-wise
        return type(policy).__call__ is SideGuard.__call__ and supports_batch(policy.inner)
    if isinstance(policy, EnsemblePolicy):  # an ensemble of such actors: each member batched, combined row for row
        return type(policy).__call__ is EnsemblePolicy.__call__ and all(supports_batch(m) for m in policy.members)
    actor = getattr(policy, "actor", None)
    deterministic = type(actor) is DeterministicActor or (type(actor) is TanhGaussianActor and not actor.state_dependent_std)
    return (isinstance(policy, CheckpointPolicy) and deterministic
            and not policy.actor.encoder.img_keys and not policy._stacked and type(policy).__call__ is CheckpointPolicy.__call__)


def row_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``F.linear(x, weight, bias)`` for ``x [B, in]`` computed one row at a time (one ``baddbmm``),
    so that row ``i`` has the bits ``F.linear(x[i:i+1], weight, bias)`` has, whatever ``B``. A layer with ONE output (a
    grip head's last) is a dot product per row, whose summation order no batched kernel reproduces: one call a row."""
    b = x.shape[0]
    if weight.shape[0] == 1:
        return torch.stack([F.linear(x[i], weight, bias) for i in range(b)])
    wt = weight.t()
    return torch.baddbmm(bias.expand(b, 1, -1), x.unsqueeze(1), wt.expand(b, *wt.shape)).squeeze(1)


class RowActor:
    """A checkpoint policy's deterministic actor on a batch, row for row equal to the one-car policy: its observation
    scaling, its state history (each row's last ``state_history`` readings, restarted by :meth:`forget` as a one-car
    policy's by ``reset``), its grip head and input selections (:meth:`DeterministicActor.act`), every linear layer one
    row at a time (:func:`row_linear`). :func:`row_actor` picks it or, for an ensemble, :class:`EnsembleRowActor`."""

    def __init__(self, policy: Policy) -> None:
        if not supports_batch(policy):
            raise ValueError(f"policy {policy.name!r} ({type(policy).__name__}) cannot drive a batch")
        self.policy = policy
        self.actor = policy.actor
        self.keys = tuple(policy.obs_keys)
        self.div = dict(policy.obs_divisors)
        self.history_keys = tuple(policy._vec_stacked)
        self.k = int(policy.state_history)
        self._history: dict[str, torch.Tensor] = {}
        self._fresh: list[int] = []

    def forget(self, rows: Sequence[int]) -> None:
        """Rows that start a new episode: at the next call their histories repeat their first reading."""
        self._fresh = sorted(set(self._fresh) | {int(r) for r in rows})

    def _stack(self, k: str, x: torch.Tensor, fresh: list[int]) -> torch.Tensor:
        """Row for row what :meth:`CheckpointPolicy._act` keeps: the last ``state_history`` readings of ``k``."""
        self._history[k] = stack = stack_frames(self._history.get(k), x, self.k, dim=-1, restart=fresh)
        return stack

    @torch.no_grad()
    def __call__(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        act = self.actor
        xs = [obs[k] / self.div[k] if k in self.div else obs[k] for k in self.keys]
        if self.history_keys:
            fresh, self._fresh = self._fresh, []
            xs = [self._stack(k, x, fresh) if k in self.history_keys else x for k, x in zip(self.keys, xs)]
        x = act.encoder(*xs)
        lin = F.linear if x.shape[0] == 1 else row_linear  # one car: exactly the one-car policy's kernels

        def mlp(layers: Sequence[torch.nn.Linear], h: torch.Tensor, last_act: bool) -> torch.Tensor:
            *hidden, out = layers
            for layer in hidden:
                h = lin(h, layer.weight, layer.bias).relu_()
            h = lin(h, out.weight, out.bias)
            return torch.tanh(h) if last_act else h

        if act.grip_head is not None:
            gx = x if act._grip_inputs is None else x.index_select(-1, act._grip_inputs)
            grip = mlp([m for m in act.grip_head if isinstance(m, torch.nn.Linear)], gx, False)
        if act._selects:
            x = x.index_select(-1, act._policy_inputs)
        if act.grip_head is not None:
            x = torch.cat([x, grip.to(x.dtype)], -1)
        a = mlp(act._linears(), x, True)
        return a if act._unit else act.a_mid + act.a_half * a


class EnsembleRowActor:
    """An ensemble on a batch: one :class:`RowActor` per member (each row its own history), the members' actions
    combined by the ensemble's reduce (:meth:`EnsemblePolicy.combine`) — row for row what the one-car ensemble does."""

    def __init__(self, policy: Policy) -> None:
        if not supports_batch(policy):
            raise ValueError(f"policy {policy.name!r} ({type(policy).__name__}) cannot drive a batch")
        self.policy, self.reduce = policy, policy.reduce
        self.members = [RowActor(m) for m in policy.members]

    def forget(self, rows: Sequence[int]) -> None:
        for m in self.members:
            m.forget(rows)

    @torch.no_grad()
    def __call__(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return EnsemblePolicy.combine(torch.stack([m(obs) for m in self.members]), self.reduce, self.policy.near_rows(obs))


class GuardRowActor:
    """A :class:`~torcsrl.policies.SideGuard` on a batch: the guarded policy's batched actor, each row's steering
    corrected by that row's own opponents and trackPos (:meth:`SideGuard.correct`, row-wise) — row for row what the
    one-car guard does."""

    def __init__(self, policy: Policy) -> None:
        if not supports_batch(policy):
            raise ValueError(f"policy {policy.name!r} ({type(policy).__name__}) cannot drive a batch")
        self.policy, self.inner = policy, row_actor(policy.inner)

    def forget(self, rows: Sequence[int]) -> None:
        self.inner.forget(rows)

    @torch.no_grad()
    def __call__(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return self.policy.correct(self.inner(obs), obs["opponents"].float(), obs["state"][:, self.policy.tp_slot].float())


def row_actor(policy: Policy) -> RowActor | EnsembleRowActor | GuardRowActor:
    """The batched actor of ``policy``: :class:`GuardRowActor` for a side guard, :class:`EnsembleRowActor` for an
    ensemble, else :class:`RowActor`."""
    if isinstance(policy, SideGuard):
        return GuardRowActor(policy)
    return EnsembleRowActor(policy) if isinstance(policy, EnsemblePolicy) else RowActor(policy)


@torch.no_grad()
def run_batch(policy: Policy, track: str, surface: str | None, degradations: Sequence[Any], *, episodes: int = 1,
              laps: int = 1, seed: int = 0, max_steps: int | None = None, env_kwargs: Mapping[str, Any] | None = None,
              max_cars: int | None = None) -> list[list[dict[str, Any]]]:
    """Drive ``episodes`` episodes of every degradation in ``degradations`` (None / severity 0 = the
    clean cell) on one track as cars of one env; returns one list of rows per degradation, each row
    what :func:`torcsrl.evaluate.protocol.run_cell` returns for that cell and episode.

    The env has up to ``max_cars`` cars (default: every episode at once), in groups of ``episodes`` cars:
    a group drives the episodes of one cell side by side, and when all of them have ended it is reset
    (alone) to drive the next cell waiting, so that cars do not idle while the slowest episode of the
    grid finishes (continuous batching). Of the groups that fit, it makes the fewest that drive the cells
    in as many rounds (11 cells and room for 8 groups: 6 groups, not 8 of which 5 would idle the second
    round). Cars whose episode has ended are parked (:meth:`RaceCore.park`: out of the physics, nearly
    free) until their group restarts; their steps are not booked. Episodes of one grid can differ in length
    by 10x (a crash in 50 steps, a slow car truncated at the step cap), so idle cars are the rule.
    """
    degs: list[Degradation] = [parse_degradation(d) for d in degradations]
    if not degs:
        return []
    E = int(episodes)
    geom = _tracks.load(track, surface=surface)
    surface_name = surface or geom.default_surface
    hz = {**dict(env_kwargs or {}), **policy.env_overrides}.get("control_hz", 50.0)
    steps = int(max_steps) if max_steps else default_max_steps(geom.length, laps, 1.0 / float(hz))
    groups = max(1, min(len(degs), (int(max_cars) if max_cars else len(degs) * E) // E))
    rounds = -(-len(degs) // groups)
    groups = -(-len(degs) // rounds)  # the fewest groups that drive the cells in as many rounds: none idles a round
    n = groups * E
    kw = {"cars_per_world": CARS_PER_WORLD, **dict(env_kwargs or {})}
    kw.update({k: v for k, v in policy.env_overrides.items() if k != "sensors"})
    sensors = env_sensors(policy)
    env = make_env(track=track, surface=surface, lap_limit=int(laps), max_steps=steps, num_cars=n, batched=True,
                   sensors=sensors, **kw)
    try:
        core = env.core
        core.scalar_locate_max_cars = n  # every car located as a one-car env locates it (the same numbers)
        env_seeds = [seed_for(seed, "env", track, surface_name, e) for e in range(E)]
        per_car = int(core.start == "random") + int(core.spawn_jitter[0] != 0) + int(core.spawn_jitter[1] != 0)
        actor = row_actor(policy)
        empty = TensorDict({}, batch_size=[E])
        spans = [slice(g * E, (g + 1) * E) for g in range(groups)]
        queue = deque(range(len(degs)))
        cell_of: list[int | None] = [None] * groups
        stack_of: list[Any] = [None] * groups
        book_of: list[EpisodeBook | None] = [None] * groups
        seeds_of: list[list[int] | None] = [None] * groups
        results: list[list[dict[str, Any]] | None] = [None] * len(degs)
        dt = float(core.dt)

        def reset(gs: list[int], full: bool) -> Any:
            """Reset the cars of groups ``gs`` (all cars when ``full``), each with its episode's start draws."""
            core.rng = _PerCarDraws([np.random.default_rng(env_seeds[i % E]) for g in gs for i in range(spans[g].start, spans[g].stop)],
                                    per_car)
            try:
                if full:
                    return env.reset()
                mask = torch.zeros(n, 1, dtype=torch.bool)
                for g in gs:
                    mask[spans[g]] = True
                return env.reset(TensorDict({"_reset": mask}, batch_size=[n]))
            finally:
                core.rng = np.random.default_rng(seed)

        def start(g: int) -> None:
            c = queue.popleft()
            d = degs[c]
            cell_of[g] = c
            book_of[g] = EpisodeBook(E, laps)
            seeds_of[g] = [seed_for(seed, "degradation", d.name, d.severity, e) for e in range(E)] if not d.clean else None
            stack_of[g] = None
            if not d.clean:
                t = d.build()
                seed_degradation_rows(t, seeds_of[g])
                stack_of[g] = t

        def view(src: Mapping[str, torch.Tensor], g: int, first: bool) -> dict[str, torch.Tensor]:
            """Group ``g``'s rows of ``src`` (sensor -> [n, ...]) as its policy sees them (through its cell's stack)."""
            sub = TensorDict._new_unsafe({k: src[k][spans[g]] for k in sensors}, batch_size=torch.Size([E]))
            t = stack_of[g]
            if t is not None:
                sub = t._reset(empty, sub) if first else t._call(sub)
            return {k: sub.get(k) for k in sensors}

        for g in range(groups):
            start(g)
        td = reset(list(range(groups)), full=True)
        src = {k: td.get(k) for k in sensors}
        views = [view(src, g, True) for g in range(groups)]
        stop = torch.tensor([0.0, -1.0])
        can_park = core.fleet.backend == "numpy"
        while any(cell_of[g] is not None for g in range(groups)):
            obs = {k: torch.cat([v[k] for v in views]) if groups > 1 else views[0][k] for k in sensors}
            action = actor(obs)
            idle = np.ones(n, dtype=bool)
            for g in range(groups):
                if book_of[g] is not None:
                    idle[spans[g]] = ~book_of[g].active
            action[torch.from_numpy(idle)] = stop  # cars whose episode has ended: off the books
            if can_park and (idle & ~core.parked).any():  # ... and out of the physics until their group restarts
                core.park(np.flatnonzero(idle & ~core.parked))
            td = env.step(TensorDict._new_unsafe({"action": action}, batch_size=torch.Size([n])))
            nxt = td.get("next")
            finished = []
            lists = EpisodeBook.step_lists(action, nxt)
            for g in range(groups):
                book = book_of[g]
                if book is None:
                    continue
                book.record_lists(lists, nxt, core.reason, rows=spans[g])
                if not book.active.any() or max(book.steps) >= steps:
                    book.close(nxt, core.reason, rows=spans[g])
                    c, d = cell_of[g], degs[cell_of[g]]
                    results[c] = [{"policy": policy.name, "policy_fingerprint": policy.fingerprint, "track": track,
                                   "surface": surface_name, "corruption": d.name if not d.clean else metrics.CLEAN,
                                   "severity": 0 if d.clean else d.severity, "episode": e, "env_seed": env_seeds[e],
                                   "degradation_seed": seeds_of[g][e] if seeds_of[g] is not None else None,
                                   "max_steps": steps, **book.row(e, dt)} for e in range(E)]
                    cell_of[g], book_of[g], stack_of[g] = None, None, None
                    finished.append(g)
            restart = []
            for g in finished:
                if queue:
                    start(g)
                    restart.append(g)
            fresh = reset(restart, full=False) if restart else None
            if restart:  # a stateful policy's readings restart with the episodes
                actor.forget([i for g in restart for i in range(spans[g].start, spans[g].stop)])
            fresh = {k: fresh.get(k) for k in sensors} if fresh is not None else None
            src = {k: nxt.get(k) for k in sensors}
            views = [view(fresh, g, True) if g in restart else
                     view(src, g, False) if cell_of[g] is not None else {k: src[k][spans[g]] for k in sensors}
                     for g in range(groups)]
        return [r if r is not None else [] for r in results]
    finally:
        env.close()
