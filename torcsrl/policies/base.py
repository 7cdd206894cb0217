"""What every policy is: :class:`Policy` (``td -> td`` writing ``"action"``), :class:`PolicyError`, the
:class:`EpisodeContext` a policy is reset with, and the fingerprints report caches are keyed by."""

from __future__ import annotations

import hashlib
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tensordict import TensorDictBase

from torcsrl.envs.sensors import STATE_SLOTS

__all__ = ["Policy", "PolicyError", "EpisodeContext", "file_fingerprint", "code_fingerprint", "state_slot"]


class PolicyError(ValueError):
    """A policy that cannot be loaded or does not fit the env (one-line message)."""


@dataclass
class EpisodeContext:
    """What a policy may know at the start of an episode.

    Attributes:
        track: the :class:`~torcsrl.envs.track.Track` being driven (with its surface).
        seed: a seed for the policy's own randomness in this episode.
        episode: the episode index within the cell.
        dt: the env's control step [s].
    """

    track: Any
    seed: int = 0
    episode: int = 0
    dt: float = 0.02


def file_fingerprint(path: str | Path) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def code_fingerprint(*objs: Any) -> str:
    """sha256 (hex) of the source of ``objs`` (classes, modules; the ``repr`` of anything without source): a built-in
    driver's fingerprint, so that a change to its code or gains gives it a new one."""
    h = hashlib.sha256()
    for o in objs:
        try:
            src = inspect.getsource(o)
        except (OSError, TypeError):
            src = repr(o)
        h.update(src.encode())
    return h.hexdigest()


def state_slot(name: str) -> int:
    """Where ``name`` sits in the ``state`` observation (:data:`torcsrl.envs.sensors.STATE_SLOTS`)."""
    return STATE_SLOTS.index(name)


class Policy:
    """Base class: ``policy(td)`` writes ``"action"`` into ``td`` and returns it.

    Attributes:
        name: short label for tables and file names.
        spec: what :func:`~torcsrl.policies.load_policy` was given.
        obs_keys: observation keys the policy reads.
        env_overrides: :func:`torcsrl.envs.make_env` keywords the policy needs.
        fingerprint: hash of the policy's bytes (file or code).
        action_dim: size of the action it writes.
    """

    name: str = "policy"
    spec: str = ""
    obs_keys: tuple[str, ...] = ()
    env_overrides: dict[str, Any]
    fingerprint: str = ""
    action_dim: int = 2

    def reset(self, ctx: EpisodeContext) -> None:
        """Called at the start of every episode, after the env reset."""

    def forget_rows(self, rows: list[int]) -> None:
        """Rows ``rows`` of the batch this policy drives start a new episode (a partial reset): a policy that keeps
        readings between steps forgets theirs. Stateless policies ignore it."""

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError

    def check_env(self, env) -> None:
        """Raise :class:`PolicyError` (one line) if ``env`` lacks an observation key or its shapes
        or action size differ from what the policy was built for."""
        spec = env.observation_spec
        nb = len(env.batch_size)
        have = set(spec.keys(True, True))
        missing = [k for k in self.obs_keys if k not in have]
        if missing:
            want = self.layout_hint() or ", ".join(self.obs_keys)
            raise PolicyError(f"policy {self.name!r} reads {missing}, which the env does not produce: it expects {want}, "
                              f"the env has {sorted(map(str, have))}")
        for k, shape in getattr(self, "obs_shapes", {}).items():
            got = tuple(spec[k].shape[nb:])
            if got != tuple(shape):
                raise PolicyError(f"policy {self.name!r} was built for {k} of shape {tuple(shape)}, the env gives {got} "
                                  f"({self.spec}: {self.layout_hint()})")
        adim = int(env.action_spec.shape[-1])
        if adim != self.action_dim:
            raise PolicyError(f"policy {self.name!r} writes {self.action_dim} action values, the env takes {adim}")

    def layout_hint(self) -> str:
        """The observation layout the policy was built for, ``key:shape`` (``rangefinder:19, state:11``)."""
        return ", ".join(f"{k}:{'x'.join(map(str, s))}" for k, s in getattr(self, "obs_shapes", {}).items())

    def describe(self) -> dict[str, Any]:
        """JSON-friendly identity (stored with every result)."""
        return {"name": self.name, "spec": self.spec, "kind": type(self).__name__, "fingerprint": self.fingerprint,
                "obs_keys": list(self.obs_keys)}
