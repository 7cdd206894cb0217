"""Several students of one observation layout driving as one (:class:`EnsemblePolicy`): each member acts, a reduce
combines their actions. The files that hold an ensemble are read and written by :mod:`torcsrl.policies.files`."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase

from torcsrl.policies.base import EpisodeContext, Policy, PolicyError
from torcsrl.policies.checkpoint import CheckpointPolicy

__all__ = ["EnsemblePolicy"]


class EnsemblePolicy(Policy):
    """Several students of one observation layout driving as one: each member acts on the observation (its own frame
    history and observation scaling), and ``reduce`` combines their actions:

    - ``mean``: the mean action (the usual ensemble);
    - ``median``: the per-dimension median (mid-point of the middle two for an even count);
    - ``cautious``: the mean steering and the most cautious pedal of the members (the least throttle or most brake;
      with ``action_mode=separate``: the least throttle and the most brake). Where the members disagree about braking
      (the camera students differ exactly where a bend is not yet clear in the image) it brakes;
    - ``medoid``: one member's whole action, per row the one nearest (L1) the per-dimension median (ties: the first
      member). Every command is some member's own: where members pass a car on different sides the mean steers
      between them, into it (racers: the mean of six seeds collided 1.46 times a race on the asphalt training races,
      more than any member, 0.62-1.38);
    - ``guarded[:<m>]`` (racers; default :attr:`GUARD_M` m): the ``medoid``, but while the ``opponents`` sensor shows
      a car ahead (a sector whose centre lies within 90 degrees of the heading: SCR sectors 9-26) closer than ``m``
      metres, the pedal is the most cautious member's (as ``cautious``; the steering stays the medoid's). Alone (every
      sector free, 200 m) it drives exactly as ``medoid``; behind a car, where the members disagree about when to brake,
      it brakes with the earliest.

    Specs: ``a.pt+b.pt[+...][@mean|@median|@cautious|@medoid|@guarded[:<m>]]`` (default mean), or an ensemble file
    written by :func:`~torcsrl.policies.files.export_ensemble` (``python -m torcsrl.policies ensemble OUT A B ... --reduce
    cautious``)."""

    REDUCE = ("mean", "median", "cautious", "medoid", "guarded")
    #: ``guarded``'s default distance [m] to a car ahead within which the most cautious member's pedal is taken.
    GUARD_M = 30.0
    #: The SCR opponents sectors that look ahead (centre ``175 - 10 k`` degrees within 90 of the heading).
    AHEAD_SECTORS = slice(9, 27)

    def __init__(self, members: list[CheckpointPolicy], reduce: str = "mean", name: str | None = None,
                 spec: str | None = None, fingerprint: str | None = None) -> None:
        if len(members) < 2:
            raise PolicyError(f"an ensemble needs at least 2 checkpoints; got {len(members)}")
        reduce, self.guard_m = self.parse_reduce(reduce)
        first = members[0]

        def setting(m: CheckpointPolicy) -> tuple:  # unset (None) camera fields are the defaults: equal to absent ones
            env = {k: ({a: b for a, b in v.items() if b is not None} if isinstance(v, dict) else v) for k, v in m.env_overrides.items()}
            return sorted(m.obs_keys), m.obs_shapes, m.action_dim, env

        for m in members[1:]:
            if setting(m) != setting(first):
                raise PolicyError(f"ensemble members must read the same observations with the same env settings: {m.spec} "
                                  f"({m.layout_hint()}, {m.env_overrides}) differs from {first.spec} ({first.layout_hint()}, {first.env_overrides})")
        self.members, self.reduce = list(members), reduce
        self.obs_keys, self.obs_shapes, self.action_dim = first.obs_keys, dict(first.obs_shapes), first.action_dim
        if self.guard_m is not None and "opponents" not in self.obs_keys:
            raise PolicyError(f"ensemble reduce={reduce!r} reads the opponents sensor, which its members do not "
                              f"({first.layout_hint()}); allowed for them: {', '.join(r for r in self.REDUCE if r != 'guarded')}")
        self.env_overrides = dict(first.env_overrides)
        self.spec = spec or "+".join(m.spec for m in members) + ("" if reduce == "mean" else f"@{reduce}")
        self.name = name or f"ensemble{len(members)}"
        self.fingerprint = fingerprint or hashlib.sha256("|".join([*(m.fingerprint for m in members), reduce]).encode()).hexdigest()

    def reset(self, ctx: EpisodeContext | None = None) -> None:
        for m in self.members:
            m.reset(ctx)

    def forget_rows(self, rows: list[int]) -> None:
        for m in self.members:
            m.forget_rows(rows)

    @classmethod
    def parse_reduce(cls, reduce: str) -> tuple[str, float | None]:
        """``(reduce, guard_m)`` from a reduce name (``guarded[:<m>]`` normalised to ``guarded:<m>``, ``guard_m`` None
        for the others); :class:`PolicyError` (one line) for an unknown name or a distance that is not positive."""
        name, sep, arg = str(reduce).partition(":")
        allowed = f"allowed: {', '.join(cls.REDUCE[:-1])}, guarded[:<m>] (a distance in metres, default {cls.GUARD_M:g})"
        if name not in cls.REDUCE or (sep and name != "guarded"):
            raise PolicyError(f"ensemble reduce={reduce!r} is not known; {allowed}")
        if name != "guarded":
            return name, None
        try:
            guard = float(arg) if sep else cls.GUARD_M
        except ValueError:
            raise PolicyError(f"ensemble reduce={reduce!r}: the guard distance must be a number of metres; {allowed}") from None
        if not (math.isfinite(guard) and guard > 0.0):
            raise PolicyError(f"ensemble reduce={reduce!r}: the guard distance must be positive [m], got {guard:g}")
        return f"guarded:{guard:g}", guard

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        acts = torch.stack([m._act(*(td.get(k) for k in m.obs_keys)) for m in self.members])  # [members, ..., A]
        td.set("action", self.combine(acts, self.reduce, self.near_rows(td)))
        return td

    def near_rows(self, obs: Mapping[str, torch.Tensor] | TensorDictBase) -> torch.Tensor | None:
        """``guarded``: per row, whether the ``opponents`` sensor shows a car ahead closer than the guard [bool, ...];
        None for the other reduces."""
        if self.guard_m is None:
            return None
        return obs.get("opponents")[..., self.AHEAD_SECTORS].min(-1).values < self.guard_m

    @staticmethod
    def combine(acts: torch.Tensor, reduce: str, near: torch.Tensor | None = None) -> torch.Tensor:
        """The members' actions ``acts [members, ..., A]`` combined by ``reduce`` (see the class docstring);
        ``near [...]`` (``guarded``): the rows with a car close ahead, where the most cautious pedal is taken."""
        if reduce.startswith("guarded"):
            if near is None:
                raise PolicyError("ensemble reduce 'guarded' needs the rows with a car close ahead (near); got none")
            act = EnsemblePolicy.combine(acts, "medoid")
            safe = EnsemblePolicy.combine(acts, "cautious")
            near = near.to(torch.bool).unsqueeze(-1)
            act[..., 1:] = torch.where(near, safe[..., 1:], act[..., 1:])  # the pedal(s); the steering stays the medoid's
            return act
        if reduce == "mean":
            return acts.mean(0)
        if reduce == "median":
            return acts.quantile(0.5, dim=0)
        if reduce == "medoid":
            idx = (acts - acts.quantile(0.5, dim=0)).abs().sum(-1).argmin(0)  # [...]: per row, the nearest member
            return acts.gather(0, idx[None, ..., None].expand(1, *acts.shape[1:])).squeeze(0)
        if reduce == "cautious":
            act = acts.mean(0)
            act[..., 1] = acts[..., 1].min(0).values  # combined pedal (+ throttle, - brake) or throttle: the least
            if acts.shape[-1] == 3:
                act[..., 2] = acts[..., 2].max(0).values  # brake: the most
            return act
        EnsemblePolicy.parse_reduce(reduce)  # raises: not known
        raise PolicyError(f"ensemble reduce={reduce!r} is not known")  # pragma: no cover (parse_reduce raised)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "reduce": self.reduce, "members": [m.describe() for m in self.members]}
