"""A racer's side guard (:class:`SideGuard`): any policy that reads ``opponents`` and ``state``, its steering corrected
while a car is beside it. A hand-written rule at inference, named as such (``side_guard:...``, ``+guard``)."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase

from torcsrl.envs.traffic import OPPONENT_RANGE_M, sector_directions
from torcsrl.policies.base import EpisodeContext, Policy, PolicyError, code_fingerprint, state_slot

__all__ = ["SideGuard", "parse_guard_values"]


class SideGuard(Policy):
    """A racer's side guard: any policy that reads ``opponents`` and ``state``, with its steering corrected while the
    opponents sensor shows a car *beside* it — the car's centre within ``reach_m`` ahead or behind along the heading
    and less than ``clear_m`` to one side (sector k's centre ``175 - 10 k`` degrees counter-clockwise from the heading,
    as :class:`SensorRacer` reads it). For the nearest such car (least lateral distance):

    - steering toward it is scaled by ``toward`` (0: none, 1: unchanged);
    - ``gain_per_m`` x the lateral shortfall under ``clear_m`` [m] is steered away from it — unless the car is already
      ``edge_tp`` or more out on that side (``trackPos``, +1 the left edge), so the guard never pushes it off the road.

    The pedal(s) stay the policy's. With no car beside, the action is the policy's own, bit for bit. It acts on the
    contacts the race books count *alongside* and *behind* — a car level with it, or the one it has just passed, that
    the racer's students close on sideways (the teacher aims at the road's centre where neither side of a car has room).

    Specs: ``side_guard[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy spec>`` (defaults :attr:`DEFAULTS`), e.g.
    ``side_guard:racer_safe:1.27:8:9`` or ``side_guard:3:0.05:a.pt+b.pt@medoid``, or by name (any of :attr:`DEFAULTS`),
    ``side_guard(clear_m=3,reach_m=6):racer_safe``; an ensemble file exported with a
    guard (``python -m torcsrl.policies ensemble ... --side-guard <clear m>[:<gain>[:<edge>]]``) loads as one: the
    shipped ``reference_racer`` (its four students' medoid behind the default guard)."""

    PREFIX = "side_guard"
    #: The guard's settings unless a spec or file names them: lateral room kept [m], steering per metre short of it
    #: [-/m], how far ahead or behind a car counts as beside [m], the factor on steering toward it, the trackPos
    #: beyond which it does not push further out.
    DEFAULTS = {"clear_m": 2.6, "gain_per_m": 0.04, "reach_m": 5.5, "toward": 0.5, "edge_tp": 0.75}
    #: The values a spec may give, in order.
    SPEC_VALUES = ("clear_m", "gain_per_m", "edge_tp")

    def __init__(self, inner: Policy, clear_m: float = 2.6, gain_per_m: float = 0.04, reach_m: float = 5.5,
                 toward: float = 0.5, edge_tp: float = 0.75, spec: str | None = None) -> None:
        vals = {"clear_m": clear_m, "gain_per_m": gain_per_m, "reach_m": reach_m, "toward": toward, "edge_tp": edge_tp}
        bad = {k: v for k, v in vals.items() if not (math.isfinite(float(v)) and float(v) >= 0.0)}
        if bad or float(toward) > 1.0 or float(edge_tp) > 1.0:
            raise PolicyError(f"side guard settings {vals} out of range; allowed: clear_m, gain_per_m, reach_m >= 0, "
                              "toward and edge_tp in [0, 1]")
        missing = [k for k in ("opponents", "state") if k not in inner.obs_keys]
        if missing:
            raise PolicyError(f"side guard around {inner.spec or inner.name!r}: it reads {', '.join(missing)}, which that "
                              f"policy does not ({', '.join(inner.obs_keys) or 'no observation keys'}); allowed: racers "
                              "that read opponents and state (e.g. reference_racer, racer_safe)")
        if isinstance(inner, SideGuard):
            raise PolicyError(f"side guard around {inner.spec!r}, which already drives behind one; allowed: one guard "
                              "(reference_racer has one: guard its students, python -m torcsrl.policies member ...)")
        self.inner = inner
        self.settings = {k: float(v) for k, v in vals.items()}
        self.obs_keys, self.action_dim = inner.obs_keys, inner.action_dim
        self.obs_shapes = dict(getattr(inner, "obs_shapes", {}))
        self.env_overrides = dict(inner.env_overrides)
        self.name = f"{inner.name}+guard"
        self.spec = spec or f"{self.PREFIX}:{self.settings['clear_m']:g}:{self.settings['gain_per_m']:g}:{self.settings['edge_tp']:g}:{inner.spec}"
        self.fingerprint = hashlib.sha256(f"{inner.fingerprint}|{code_fingerprint(SideGuard)}|{sorted(self.settings.items())}".encode()).hexdigest()
        self._cos, self._sin = (torch.from_numpy(v).float() for v in sector_directions())
        self._free = OPPONENT_RANGE_M - 1e-3
        self._near_m = math.hypot(self.settings["reach_m"], self.settings["clear_m"])  # no car beside is farther [m]
        self.tp_slot = state_slot("trackPos")  # trackPos in the state vector

    @classmethod
    def from_settings(cls, inner: Policy, settings: Mapping[str, Any] | None = None, spec: str | None = None) -> SideGuard:
        """The guard around ``inner`` with ``settings`` (any of :attr:`DEFAULTS`, the rest default): how a spec, the
        CLI, :func:`~torcsrl.policies.files.export_ensemble` and a guarded file build one. :class:`PolicyError` (one
        line) for an unknown key or a value that is not a number."""
        settings = dict(settings or {})
        unknown = sorted(set(settings) - set(cls.DEFAULTS))
        try:
            vals = {k: float(v) for k, v in settings.items()}
        except (TypeError, ValueError):
            vals = None
        if unknown or vals is None:
            raise PolicyError(f"side guard settings {settings!r} are not known numbers; allowed: {', '.join(cls.DEFAULTS)} "
                              "(numbers; the rest default)")
        return cls(inner, **{**cls.DEFAULTS, **vals}, spec=spec)

    @classmethod
    def split_spec(cls, spec: str) -> tuple[dict[str, float], str]:
        """``side_guard[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy spec>`` -> ``(settings, policy spec)``: the
        leading numbers are the settings (:attr:`SPEC_VALUES`), the rest the spec of the policy guarded;
        :class:`PolicyError` (one line) when no policy is named."""
        rest = spec[len(cls.PREFIX) + 1:]
        vals: dict[str, float] = {}
        while len(vals) < len(cls.SPEC_VALUES):
            head, sep, tail = rest.partition(":")
            try:
                v = float(head)
            except ValueError:
                break
            if not sep:
                break
            vals[cls.SPEC_VALUES[len(vals)]] = v
            rest = tail
        if not rest:
            raise PolicyError(f"side guard spec {spec!r} names no policy; allowed: "
                              f"{cls.PREFIX}[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy spec>, e.g. {cls.PREFIX}:racer_safe:1.27:8:9")
        return vals, rest

    def reset(self, ctx: EpisodeContext) -> None:
        self.inner.reset(ctx)

    def forget_rows(self, rows: list[int]) -> None:
        self.inner.forget_rows(rows)

    def check_env(self, env) -> None:
        self.inner.check_env(env)

    def correct(self, action: torch.Tensor, opponents: torch.Tensor, track_pos: torch.Tensor) -> torch.Tensor:
        """The guarded action from the policy's ``action [B, A]``, the ``opponents`` sectors ``[B, 36]`` [m] and
        ``trackPos [B]``."""
        g = self.settings
        x, y = opponents * self._cos, opponents * self._sin  # ahead, left [m]
        beside = (x.abs() < g["reach_m"]) & (y.abs() < g["clear_m"]) & (opponents < self._free)
        rows = beside.any(-1)
        if not bool(rows.any()):
            return action
        k = torch.where(beside, y.abs(), torch.full_like(y, math.inf)).argmin(-1, keepdim=True)
        yk = y.gather(-1, k).squeeze(-1)
        side = torch.sign(yk)  # +1: the car is on the left (steering + is left)
        steer = action[..., 0]
        guarded = torch.where(steer * side > 0, steer * g["toward"], steer)
        room = track_pos * -side < g["edge_tp"]
        shortfall = (g["clear_m"] - yk.abs()).clamp(min=0.0)
        guarded = torch.where(room, guarded - side * g["gain_per_m"] * shortfall, guarded).clamp(-1.0, 1.0)
        out = action.clone()
        out[..., 0] = torch.where(rows, guarded, steer)
        return out

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        opp = td.get("opponents")
        if not bool((opp < self._near_m).any()):  # no car within reach of beside on any row: the policy's own action
            return self.inner(td)
        opp = opp.reshape(-1, opp.shape[-1]).float().clone()
        tp = td.get("state").reshape(opp.shape[0], -1)[:, self.tp_slot].float().clone()  # read before the policy runs
        td = self.inner(td)
        act = td.get("action")
        td.set("action", self.correct(act.reshape(opp.shape[0], -1), opp, tp).reshape(act.shape))
        return td

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "guard": dict(self.settings), "inner": self.inner.describe()}


def parse_guard_values(text: str) -> dict[str, float]:
    """``"<clear m>[:<gain per m>[:<edge tp>]]"`` -> SideGuard settings (:attr:`SideGuard.SPEC_VALUES`);
    :class:`PolicyError` (one line) if they are not 1-3 numbers."""
    parts = str(text).split(":")
    try:
        vals = [float(v) for v in parts]
    except ValueError:
        vals = []
    if not 1 <= len(vals) <= len(SideGuard.SPEC_VALUES) or len(vals) != len(parts):
        raise PolicyError(f"side guard values {text!r} are not <clear m>[:<gain per m>[:<edge tp>]] (1 to 3 numbers, e.g. 2.6 or 3:0.05)")
    return dict(zip(SideGuard.SPEC_VALUES, vals))
