"""Env workers as Ray actors: ``collector.ray=<address>`` with ``collector.num_workers=W``.

The same W worker envs the local multiprocess collectors build (:func:`torcsrl.pipeline.make_train_env`, worker ``i``
seeded from ``seed`` and ``i``), each in a Ray actor of one CPU that runs a TorchRL ``Collector``, coordinated by
TorchRL's :class:`~torchrl.collectors.distributed.RayCollector`:

* ``sync=True`` (the off-policy loop, and PPO with ``collector.policy_lag=0``): every batch is one batch of every worker,
  stacked along a leading worker dim, as ``MultiSyncCollector(cat_results="stack")`` gives it;
* ``sync=False`` (PPO with ``collector.policy_lag=1``): each worker's batch as it arrives; a worker starts its next
  rollout when the learner asks for the next batch, the others keep driving during the update.

Weights reach the workers through Ray's object store: :meth:`RayRollouts.update_policy_weights_` puts the learner
policy's parameters AND buffers (the observation statistics) once and queues them on every actor, ahead of its next
collection, so every batch after an update is collected with it (TorchRL's default Ray scheme opens a Gloo process
group between the learner and every actor, which needs open ports between the nodes; the object store does not).

Addresses are those of the report's ``ray=``: ``local`` starts a Ray instance here with W CPUs, ``auto`` /
``host:port`` / ``ray://host:port`` join a cluster. Bad input fails before any worker starts, in one line: ray not
installed, an address nobody answers, more workers than the cluster has CPUs. A worker that dies mid-run (its node
lost) stops the run with one line naming the worker and how to resume from the last checkpoint; nothing hangs.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase

from torcsrl.utils.ray_session import RayError, import_ray, ray_session

__all__ = ["RayRollouts", "make_ray_collector", "RayWorkerLost"]


class RayWorkerLost(RuntimeError):
    """A Ray collector worker died (its node was lost, or it was killed): one line, the run is resumable."""


def _object_store_weights():
    """TorchRL's object-store weight updater, bound to the collector that registers it (built lazily: TorchRL calls a
    constructor with no arguments and then ``register_collector``)."""
    from torchrl.collectors.weight_update import RayWeightUpdater  # deferred: its import warns of a deprecation

    class ObjectStoreWeights(RayWeightUpdater):
        def __init__(self):  # noqa: D401 - bound in register_collector
            pass

        def register_collector(self, collector):  # noqa: ANN001
            super().register_collector(collector)
            RayWeightUpdater.__init__(self, collector.policy_weights, collector.remote_collectors, 0)

    return ObjectStoreWeights()


class RayRollouts:
    """Batches from W Ray actors (see the module docstring); the interface of the local worker collectors the loops
    drive: iteration, :meth:`update_policy_weights_`, :meth:`shutdown`, and :meth:`worker_policy_states` for checks."""

    def __init__(self, collector, workers: int, connection: contextlib.ExitStack, where: str, *, sync: bool = True,
                 join_cars: bool = False, resume_hint: str = ""):
        self.collector = collector
        self.workers = workers
        self.lag = int(not sync)
        self.join_cars = join_cars
        self._connection = connection  # closes the Ray connection make_ray_collector opened
        self.where = where
        self.resume_hint = resume_hint
        self._batches = None

    def __iter__(self):
        self._batches = iter(self.collector)
        return self

    def _next(self) -> TensorDictBase:
        ray = import_ray()
        try:
            return next(self._batches)
        except (ray.exceptions.RayActorError, ray.exceptions.ActorDiedError, ray.exceptions.NodeDiedError) as err:
            first = str(err).strip().splitlines()[0][:200] if str(err).strip() else type(err).__name__
            raise RayWorkerLost(f"a Ray collector worker on {self.where} died ({type(err).__name__}: {first}); the last "
                                f"checkpoint is intact{'; resume: ' + self.resume_hint if self.resume_hint else ''}") from None

    def __next__(self) -> TensorDictBase:
        if self.lag:  # W worker batches as they arrive (PPO with policy_lag=1), joined along the cars
            return joined_along_cars([self._next() for _ in range(self.workers)])
        data = self._next()  # [workers, cars a worker, T]; one car a worker: [workers, T]
        data.names = None
        return data.flatten(0, 1) if self.join_cars and data.ndim == 3 else data

    def update_policy_weights_(self) -> None:
        self.collector.update_policy_weights_()

    def cpu_s(self) -> float:
        """CPU seconds of local worker processes: none (the actors' CPU is the cluster's)."""
        return 0.0

    def worker_policy_states(self) -> list[dict]:
        """The policy ``state_dict()`` each actor holds (after the queued weight updates have run)."""
        ray = import_ray()
        return [s["policy_state_dict"] for s in ray.get([c.state_dict.remote() for c in self.collector.remote_collectors])]

    def worker_nodes(self) -> list[str]:
        """The Ray node id each actor runs on (where the workers were placed), from the cluster's actor table."""
        from ray._private import state  # deferred: optional (ray); the public state API needs the dashboard

        return [(state.actors(c._actor_id.hex()) or {}).get("Address", {}).get("NodeID", "") for c in self.collector.remote_collectors]

    def shutdown(self) -> None:
        try:
            with contextlib.suppress(Exception):
                self.collector.shutdown(shutdown_ray=False)
        finally:
            self._connection.close()


def make_ray_collector(address: str, fns: list[Callable[[], Any]], policy, frames_per_worker: int, *, sync: bool = True,
                       init_random_frames: int = 0, exploration_type=None, join_cars: bool = False,
                       resume_hint: str = "") -> RayRollouts:
    """W = ``len(fns)`` Ray actors, actor ``i`` driving ``fns[i]()`` and collecting ``frames_per_worker`` frames a batch
    (``init_random_frames`` of them uniform random first, counted per worker); a batch is one of every worker, stacked
    (``sync``; ``join_cars``: ``[W, cars, T]`` flattened to ``[W cars, T]``, PPO's layout), or W worker batches as they
    arrive joined along the cars (``sync=False``, PPO's ``policy_lag=1``). Ray is the one at ``address`` (checked
    first)."""
    from torchrl.collectors.distributed import RayCollector  # deferred: needs ray

    workers = len(fns)
    connection = contextlib.ExitStack()
    try:
        ray, info = connection.enter_context(ray_session(address, num_cpus=workers))
        if info.cpus < workers:
            raise RayError(f"collector.num_workers={workers}: {info.describe()} cannot hold {workers} workers of one CPU "
                           f"each; allowed: at most {info.cpus} (or a larger cluster)")
        kwargs: dict[str, Any] = {"init_random_frames": int(init_random_frames)}
        if exploration_type is not None:
            kwargs["exploration_type"] = exploration_type
        collector = RayCollector(fns, policy, frames_per_batch=frames_per_worker * workers if sync else frames_per_worker,
                                 total_frames=2**62, sync=sync, num_collectors=workers,
                                 remote_configs={"num_cpus": 1, "num_gpus": 0}, collector_kwargs=kwargs,
                                 weight_updater=_object_store_weights)
    except BaseException:
        connection.close()
        raise
    return RayRollouts(collector, workers, connection, info.describe(), sync=sync, join_cars=join_cars, resume_hint=resume_hint)


def joined_along_cars(parts: list[TensorDictBase]) -> TensorDictBase:
    """Worker batches ``[cars, T]`` (one car: ``[T]``) joined along the cars, worker by worker: PPO's ``[cars, T]``
    from lagged workers, local (:class:`~torcsrl.training.onpolicy.WorkerRollouts`) or on Ray."""
    for part in parts:
        part.names = None
    return torch.stack(parts, 0) if parts[0].ndim == 1 else torch.cat(parts, 0)
