"""Policies for evaluation: a checkpoint's deterministic actor, the scripted expert, random actions.

:func:`load_policy` turns a *spec* into a :class:`Policy`, a callable ``td -> td`` that writes
``"action"`` (a TensorDictModule-like object; :meth:`CheckpointPolicy.as_module` gives the
actual ``TensorDictModule``):

============================  =================================================================
spec                          policy
============================  =================================================================
``path/to/ckpt.pt``           the deterministic actor of a torcsrl checkpoint: a training
                              checkpoint (``torcsrl.train``) or a policy file written by
                              :func:`export_policy` (actor weights + config only)
``reference``                 the shipped reference driver, :data:`REFERENCE_POLICY`
``reference-td3``             the shipped RL (TD3) driver, :data:`REFERENCE_RL_POLICY`
``reference_racer``           the shipped racing driver (rangefinder + state + opponents, asphalt and
                              dirt; a medoid ensemble of four students behind a side guard),
                              :data:`REFERENCE_RACER_POLICY`
``reference_camera``          the shipped camera-only driver (hood camera + telemetry),
                              :data:`REFERENCE_CAMERA_POLICY` (also ``reference-camera``)
``expert``                    the scripted expert (:mod:`torcsrl.envs.expert`: pure pursuit on
                              a racing line + speed profile) driven from the ``state``
                              observation and ``info/distFromStart`` (an observation adapter:
                              degrading ``state`` degrades it; the rangefinder it ignores)
``expert_centre``             the same expert on the track's centre line (its speed profile too)
``sensor_fast``               :class:`SensorDriver` with ``SensorDriver.FAST`` (grip-aware, ~1.08x the
                              expert's lap on training tracks)
``sensor_fast_sight[:<m>]``   the fast camera teacher: ``SensorDriver.CAMERA_FAST`` planning on at most
                              80 m (or ``<m>``) of free road (~1.19x the expert on training tracks)
``racer``                     :class:`SensorRacer`: ``sensor_fast`` that passes (or lifts for) the
                              cars its ``opponents`` sensor shows: the race student's teacher
``racer_bold``                the same with ``SensorRacer.BOLD`` (passes more, collides more)
``racer_safe[:<gamma>[:<d>[:<f>[:<m>]]]]`` ``racer_bold`` braking at ``9 mu^gamma`` m/s^2 (gamma 2): as
                              bold on asphalt, a margin on low grip; ``<d>`` in place of 9: a margin on asphalt
                              too; ``<f>``: the rate while a car is within 60 m (or ``<m>``): pushes in a fight
``racer_clean[:<gamma>...]``  ``racer_safe`` with a 1.5-lane following corridor near bends (fewer contacts)
``racer_keep[:<gamma>...]``   ``racer_safe`` that finishes a pass on the side it is on (holds its lane when
                              that side is taken, never crosses the passed car's path)
``racer_yield[:<gamma>...]``  ``racer_safe`` that completes a pass before the braking zone of the bend
                              ahead or gives it up (holds its lane, brakes to drop behind)
``heuristic``                 a sensor-only driver in the style of the TORCS SCR sample robot:
                              steers from ``angle`` / ``trackPos`` and the longest rangefinder
                              beam, picks its speed from the free distance ahead
``sensor``                    :class:`SensorDriver`: a stateless rangefinder + state driver (target
                              speed from the free distance ahead, traction control) whose choices the
                              observation explains: the imitation teacher of ``demos.teacher=sensor``
``sensor_grip``               the same driver told the friction under the car (``info/surfaceMu``):
                              the privileged teacher of the camera driver (``demos.teacher=sensor_grip``)
``random``                    uniform random actions in [-1, 1], seeded per episode (R_random)
``a.pt+b.pt[+...][@reduce]``  :class:`EnsemblePolicy`: the checkpoints drive as one, their actions
                              combined by ``mean`` (default), ``median``, ``cautious`` (mean
                              steering, the most cautious pedal), ``medoid`` (per row one
                              member's whole action, nearest the median) or ``guarded[:<m>]``
                              (the medoid, with the most cautious pedal while a car is within
                              m metres ahead); an ensemble file written by
                              :func:`export_ensemble` loads the same way
``side_guard[:<c>[:<g>[:<e>]]]:<spec>``  :class:`SideGuard`: a racer (any spec that reads opponents
                              and state) whose steering keeps ``c`` m (2.6) of lateral room from a
                              car beside it: steering toward it halved, ``g`` (0.04) per metre short
                              steered away, never beyond trackPos ``e`` (0.75); nothing else changed
============================  =================================================================

Each policy says which observation keys it reads (``obs_keys``) and which env settings it needs
(``env_overrides``: sensors, camera size, action mode); the evaluator builds the env from them and
calls :meth:`Policy.check_env` before any work, so a checkpoint written for another observation
layout fails with ONE line (:class:`PolicyError`). ``fingerprint`` is a hash of the policy's
file bytes (or of the code of a built-in driver): report caches are keyed by it.

CLI: ``python -m torcsrl.policies export CKPT OUT`` writes a policy file (what the shipped
reference driver is); ``python -m torcsrl.policies ensemble OUT A B ... --reduce cautious`` writes
an ensemble file; ``python -m torcsrl.policies info SPEC`` prints what a spec loads.
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

__all__ = [
    "BUILTIN_POLICIES",
    "REFERENCE_CAMERA_POLICY",
    "REFERENCE_RACER_POLICY",
    "REFERENCE_POLICY",
    "Policy",
    "PolicyError",
    "EpisodeContext",
    "CheckpointPolicy",
    "ExpertPolicy",
    "SensorRacer",
    "SideGuard",
    "HeuristicPolicy",
    "SensorDriver",
    "RandomPolicy",
    "load_policy",
    "export_policy",
    "EnsemblePolicy",
    "export_ensemble",
    "file_fingerprint",
]

#: Env settings a trained policy is bound to (they define its control problem); evaluation uses the
#: checkpoint's values: control rate, physics substeps, car, rangefinder beams.
DYNAMICS_KEYS = ("control_hz", "substeps", "vehicle", "vehicle_overrides", "rangefinder_angles_deg", "rangefinder_range_m")

#: Where the shipped reference driver lives (a policy file written by :func:`export_policy`): the best driver made by
#: the generalisation recipe (``reference_dagger.md`` beside it: command, selection on training tracks, figures).
REFERENCE_POLICY = Path(__file__).resolve().parent / "assets" / "reference_dagger.pt"
#: The shipped RL (TD3) driver, ``reference-td3`` (``reference_td3.md``).
REFERENCE_RL_POLICY = Path(__file__).resolve().parent / "assets" / "reference_td3.pt"
#: The shipped camera-only driver, ``reference_camera`` (``reference_camera.md``: command, selection, figures).
REFERENCE_CAMERA_POLICY = Path(__file__).resolve().parent / "assets" / "reference_camera.pt"
#: The shipped racing driver, ``reference_racer`` (``reference_racer.md``: command, selection, figures).
REFERENCE_RACER_POLICY = Path(__file__).resolve().parent / "assets" / "reference_racer.pt"
#: The values a parametrised racer teacher takes (:data:`_RACER_VALUES`, all optional, in order).
RACER_VALUES_FORM = "[:<gamma>[:<decel>[:<fight decel>[:<fight m>[:<clear m>[:<abandon m>]]]]]]"
#: The parametrised racer teachers (:func:`racer_gains`) as listed in :data:`BUILTIN_POLICIES` and ``demos.TEACHERS``.
RACER_SPECS = tuple(f"{base}{RACER_VALUES_FORM}" for base in ("racer_safe", "racer_clean", "racer_keep", "racer_yield"))
#: Names of the built-in policies (anything else is a checkpoint path).
BUILTIN_POLICIES = ("expert", "expert_centre", "heuristic", "sensor", "sensor_grip", "sensor_fast", "sensor_sight[:<metres>]",
                    "sensor_fast_sight[:<metres>]", "racer", "racer_bold", *RACER_SPECS, "random", "reference", "reference-td3",
                    "reference_camera", "reference_racer", "side_guard[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy>")


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


def _code_fingerprint(*objs: Any) -> str:
    h = hashlib.sha256()
    for o in objs:
        try:
            src = inspect.getsource(o)
        except (OSError, TypeError):
            src = repr(o)
        h.update(src.encode())
    return h.hexdigest()


class Policy:
    """Base class: ``policy(td)`` writes ``"action"`` into ``td`` and returns it.

    Attributes:
        name: short label for tables and file names.
        spec: what :func:`load_policy` was given.
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
            want = self._layout_hint() or ", ".join(self.obs_keys)
            raise PolicyError(f"policy {self.name!r} reads {missing}, which the env does not produce: it expects {want}, "
                              f"the env has {sorted(map(str, have))}")
        for k, shape in getattr(self, "obs_shapes", {}).items():
            got = tuple(spec[k].shape[nb:])
            if got != tuple(shape):
                raise PolicyError(f"policy {self.name!r} was built for {k} of shape {tuple(shape)}, the env gives {got} "
                                  f"({self.spec}: {self._layout_hint()})")
        adim = int(env.action_spec.shape[-1])
        if adim != self.action_dim:
            raise PolicyError(f"policy {self.name!r} writes {self.action_dim} action values, the env takes {adim}")

    def _layout_hint(self) -> str:
        return ", ".join(f"{k}:{'x'.join(map(str, s))}" for k, s in getattr(self, "obs_shapes", {}).items())

    def describe(self) -> dict[str, Any]:
        """JSON-friendly identity (stored with every result)."""
        return {"name": self.name, "spec": self.spec, "kind": type(self).__name__, "fingerprint": self.fingerprint,
                "obs_keys": list(self.obs_keys)}


# --------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------
def _parse_layout(layout: str) -> dict[str, tuple[int, ...]]:
    out = {}
    for part in filter(None, str(layout).split(",")):
        k, _, shp = part.partition(":")
        out[k] = tuple(int(x) for x in shp.split("x") if x)
    return out


class CheckpointPolicy(Policy):
    """The deterministic actor mu(s) of a torcsrl checkpoint (no exploration noise)."""

    def __init__(self, path: str | Path, name: str | None = None, payload: dict[str, Any] | None = None,
                 fingerprint: str | None = None) -> None:
        """``payload``: the checkpoint's contents when already read from ``path`` (or a member of an ensemble file, with
        its own ``fingerprint``); else read from ``path``. ``fingerprint`` defaults to the hash of ``path``'s bytes."""
        from omegaconf import OmegaConf
        from torchrl.data import Bounded, Composite, Unbounded

        from torcsrl import agents
        from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint

        path = Path(path)
        self.path = path
        self.spec = str(path)
        self.name = name or path.stem
        if payload is None:
            try:
                ck = load_checkpoint(path)
            except CheckpointError as err:
                raise PolicyError(str(err)) from None
        else:
            ck = payload
        meta = ck["meta"]
        if meta.get("kind") == "ensemble":
            raise PolicyError(f"{path} is an ensemble of {len(ck.get('members', []))} students, not one actor; load it with "
                              "torcsrl.policies.load_policy (or pass one of its members)")
        try:
            cfg = OmegaConf.create(ck["config"])
            algo = str(meta["algo"])
            layout = _parse_layout(meta["obs_layout"])
            action_dim = int(meta["action_dim"])
        except Exception as err:  # noqa: BLE001 - any malformed header means the same thing
            raise PolicyError(f"checkpoint {path} lacks its config or meta ({type(err).__name__}: {err}); expected one written by torcsrl.train") from None
        env_name = str(cfg.get("env", {}).get("name", "race"))
        if env_name != "race":
            raise PolicyError(f"checkpoint {path} was trained on env {env_name!r} ({meta['obs_layout']}); evaluation drives the race env")
        obs_keys = list(cfg.get("obs_keys") or cfg.env.sensors)
        if sorted(obs_keys) != sorted(layout):
            raise PolicyError(f"checkpoint {path}: obs_keys {obs_keys} do not match its obs_layout {meta['obs_layout']!r}")
        self.obs_keys = tuple(obs_keys)
        # frame_stack > 1: the actor sees K frames of each image key stacked along channels; the policy keeps that history
        # itself (reset every episode, :meth:`reset`), so it drives the one-frame envs of evaluate/report as trained
        from torcsrl.transforms import IMAGE_KEYS

        from torcsrl.transforms import HISTORY_KEYS

        self.frame_stack = int(cfg.get("frame_stack", 1) or 1)
        self._stacked = tuple(k for k in obs_keys if k in IMAGE_KEYS) if self.frame_stack > 1 else ()
        # state_history > 1: the actor sees the last K readings of its on-board state (scaled, then concatenated)
        self.state_history = int(cfg.get("state_history", 1) or 1)
        self._vec_stacked = tuple(k for k in obs_keys if k in HISTORY_KEYS) if self.state_history > 1 else ()
        self._history: dict[str, torch.Tensor] = {}
        self._fresh: list[int] = []  # rows of the batch that restarted (forget_rows) since the last step
        actor_shapes = {k: layout[k] for k in obs_keys}
        for k in self._stacked:
            if actor_shapes[k][0] % self.frame_stack:
                raise PolicyError(f"checkpoint {path}: {k} of {actor_shapes[k]} is not a stack of frame_stack={self.frame_stack} frames")
        for k in self._vec_stacked:
            if actor_shapes[k][-1] % self.state_history:
                raise PolicyError(f"checkpoint {path}: {k} of {actor_shapes[k]} is not a history of state_history={self.state_history} readings")
        self.obs_shapes = {k: (shp[0] // self.frame_stack, *shp[1:]) if k in self._stacked
                           else (*shp[:-1], shp[-1] // self.state_history) if k in self._vec_stacked else shp
                           for k, shp in actor_shapes.items()}
        self.action_dim = action_dim
        self.algo = algo
        specs = {}
        for k, shp in actor_shapes.items():
            dtype = torch.uint8 if k == "pixels" else torch.float32
            specs[k] = Unbounded(shp, dtype=dtype)
        fake_env = SimpleNamespace(observation_spec=Composite(specs, shape=()),
                                   action_spec=Bounded(-1.0, 1.0, (action_dim,), dtype=torch.float32))
        try:
            self.actor = agents.get(algo).make_actor(cfg.algo, fake_env, obs_keys)
        except Exception as err:  # noqa: BLE001
            raise PolicyError(f"checkpoint {path}: cannot rebuild its {algo} actor ({type(err).__name__}: {err})") from None
        if "actor" in ck:
            sd = ck["actor"]
        else:
            prefix = "actor_network_params."
            sd = {k[len(prefix):]: v for k, v in ck.get("loss", {}).items() if k.startswith(prefix)}
        if not sd:
            raise PolicyError(f"checkpoint {path} holds no actor weights (neither 'actor' nor 'loss/actor_network_params')")
        try:
            self.actor.load_state_dict(sd, strict=True)
        except RuntimeError as err:
            first = str(err).strip().splitlines()
            raise PolicyError(f"checkpoint {path}: actor weights do not fit the {algo} actor of its config ({first[1].strip() if len(first) > 1 else first[0]})") from None
        self.actor._unit = bool((self.actor.a_mid == 0).all() and (self.actor.a_half == 1).all())
        self.actor.eval()
        for prm in self.actor.parameters():
            prm.requires_grad_(False)
        camera = cfg.env.get("camera") if any(k in ("pixels", "depth") for k in obs_keys) else None
        self.env_overrides = {"sensors": tuple(obs_keys)}
        if camera:
            self.env_overrides["camera"] = OmegaConf.to_container(camera, resolve=True)
        if action_dim == 3:
            self.env_overrides["action_mode"] = "separate"
        for k in DYNAMICS_KEYS:  # the control problem the policy was trained on (rate, car, beams)
            v = cfg.env.get(k) if env_name == "race" else None
            if v is not None:
                self.env_overrides[k] = OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
        # The observation scaling of training (torcsrl.train.observation_transforms: after any
        # degradation, rangefinder and state divided by sensors.obs_scale when env.normalize).
        self.obs_divisors: dict[str, torch.Tensor] = {}
        if cfg.env.get("normalize", True):
            from torcsrl.envs.sensors import obs_scale

            for k in ("rangefinder", "state", "telemetry", "opponents"):
                if k in self.obs_shapes:
                    self.obs_divisors[k] = torch.as_tensor(obs_scale(k, int(self.obs_shapes[k][-1])))
        rec = meta.get("pipeline")  # written since the pipeline record exists: what the actor was trained on
        if rec is not None:
            mine = {k: [float(x) for x in v.tolist()] for k, v in self.obs_divisors.items()}
            if dict(rec.get("scales") or {}) != mine:
                raise PolicyError(f"checkpoint {path}: its recorded observation scaling {sorted((rec.get('scales') or {}))} differs from "
                                  f"the one rebuilt from its config {sorted(mine)}; it would be fed other observations than it was trained on")
            for k in ("control_hz", "substeps"):
                if rec.get(k) is not None and self.env_overrides.get(k) != rec.get(k):
                    raise PolicyError(f"checkpoint {path}: recorded {k}={rec.get(k)!r}, its config gives {self.env_overrides.get(k)!r}")
        self.pipeline = rec
        self.fingerprint = fingerprint or file_fingerprint(path)
        self.config_yaml = ck["config"]
        self.meta = dict(meta)

    def as_module(self):
        """The policy as a ``TensorDictModule`` over the env's observations (obs keys -> ``"action"``;
        the training's observation scaling included)."""
        from tensordict.nn import TensorDictModule

        return TensorDictModule(self._act, in_keys=list(self.obs_keys), out_keys=["action"])

    def reset(self, ctx: EpisodeContext | None = None) -> None:
        """A new episode: a frame-stacking policy forgets its frames and state readings (the next stack repeats the first)."""
        self._history = {}
        self._fresh = []

    def forget_rows(self, rows: list[int]) -> None:
        """Rows of the batch restart (a partial reset, e.g. one race group of opponents): at the next step their stacks
        repeat their first frame / reading, as the training env's ``CatFrames`` does for a partial reset."""
        self._fresh = sorted(set(self._fresh) | {int(r) for r in rows})

    def _act(self, *obs: torch.Tensor) -> torch.Tensor:
        div = self.obs_divisors
        obs = [x / div[k] if k in div else x for k, x in zip(self.obs_keys, obs)]  # scaled, then stacked (as in training)
        if self._stacked or self._vec_stacked:
            from torcsrl.transforms import stack_frames

            fresh, self._fresh = self._fresh, []
            for i, k in enumerate(self.obs_keys):
                if k not in self._stacked and k not in self._vec_stacked:
                    continue
                kk, dim = (self.frame_stack, -3) if k in self._stacked else (self.state_history, -1)
                # rows that restarted: K copies of their first frame
                obs[i] = self._history[k] = stack_frames(self._history.get(k), obs[i], kk, dim=dim, restart=fresh)
        return self.actor(*obs)

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", self._act(*(td.get(k) for k in self.obs_keys)))
        return td


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
    written by :func:`export_ensemble` (``python -m torcsrl.policies ensemble OUT A B ... --reduce cautious``)."""

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
                                  f"({m._layout_hint()}, {m.env_overrides}) differs from {first.spec} ({first._layout_hint()}, {first.env_overrides})")
        self.members, self.reduce = list(members), reduce
        self.obs_keys, self.obs_shapes, self.action_dim = first.obs_keys, dict(first.obs_shapes), first.action_dim
        if self.guard_m is not None and "opponents" not in self.obs_keys:
            raise PolicyError(f"ensemble reduce={reduce!r} reads the opponents sensor, which its members do not "
                              f"({first._layout_hint()}); allowed for them: {', '.join(r for r in self.REDUCE if r != 'guarded')}")
        self.env_overrides = dict(first.env_overrides)
        self.spec = spec or "+".join(m.spec for m in members) + ("" if reduce == "mean" else f"@{reduce}")
        self.name = name or f"ensemble{len(members)}"
        self.fingerprint = fingerprint or hashlib.sha256("|".join([*(m.fingerprint for m in members), reduce]).encode()).hexdigest()

    @classmethod
    def from_spec(cls, spec: str) -> EnsemblePolicy:
        """``a.pt+b.pt[+...][@reduce]``."""
        files, _, reduce = spec.partition("@")
        members = [_checkpoint_file(x) for x in files.split("+")]
        for m in members:
            if isinstance(m, (EnsemblePolicy, SideGuard)):
                what = "an ensemble" if isinstance(m, EnsemblePolicy) else "a guarded ensemble"
                raise PolicyError(f"ensemble member {m.spec} is itself {what}; allowed: single checkpoints, run folders or policy files "
                                  "(python -m torcsrl.policies member <file> <i> <out> writes one member)")
        return cls(members, reduce=reduce or "mean")

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


def export_ensemble(checkpoints: list[str | Path], out: str | Path, reduce: str = "mean",
                    guard: Mapping[str, float] | None = None) -> Path:
    """Write an ensemble of checkpoints' actors (each member's weights, meta and config; no optimiser, buffer or RNG
    state) to ONE policy file that :func:`load_policy` drives as :class:`EnsemblePolicy` (how a shipped driver can be
    an ensemble). The members are checked as the spec ``a.pt+b.pt@reduce`` checks them. ``guard``: :class:`SideGuard`
    settings (any of :attr:`SideGuard.DEFAULTS`; the rest default) the file drives behind."""
    from torcsrl.utils.checkpoint import save_checkpoint

    ens = EnsemblePolicy.from_spec("+".join(map(str, checkpoints)) + f"@{reduce}")  # the checks: 2+, one layout, a known reduce
    if guard is not None:
        guard = SideGuard.from_settings(ens, guard).settings  # the checks: known keys, ranges, opponents and state read
    pols = ens.members
    members = []
    for pol in pols:
        meta = {k: v for k, v in pol.meta.items() if k not in ("format", "version", "sha256")}
        meta.update(kind="policy", source=Path(pol.path).name)
        members.append({"meta": meta, "actor": pol.actor.state_dict(), "config": pol.config_yaml})
    first = pols[0].meta
    meta = {"kind": "ensemble", "reduce": ens.reduce, "sources": [Path(p.path).name for p in pols],
            "algo": first.get("algo"), "obs_layout": first.get("obs_layout"), "action_dim": first.get("action_dim")}
    if guard is not None:
        meta["guard"] = dict(guard)
    return save_checkpoint(out, {"meta": meta, "members": members})


def export_member(ensemble: str | Path, index: int, out: str | Path) -> Path:
    """Write member ``index`` of an ensemble file (:func:`export_ensemble`) as a one-actor policy file: what
    ``init.actor`` and single-checkpoint tools (``benchmarks/teacher_gap.py``) take. :class:`PolicyError` (one line)
    when ``ensemble`` is not an ensemble file or ``index`` is out of range."""
    from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

    try:
        ck = load_checkpoint(ensemble)
    except CheckpointError as err:
        raise PolicyError(str(err)) from None
    members = ck.get("members") if ck.get("meta", {}).get("kind") == "ensemble" else None
    if not members:
        raise PolicyError(f"{ensemble} is not an ensemble file (python -m torcsrl.policies ensemble writes them)")
    if not 0 <= int(index) < len(members):
        raise PolicyError(f"{ensemble} has members 0..{len(members) - 1}; got {index}")
    m = members[int(index)]
    return save_checkpoint(out, {"meta": dict(m["meta"]), "actor": m["actor"], "config": m["config"]})


def sector_directions() -> tuple[np.ndarray, np.ndarray]:
    """``(cos, sin)`` ``[36]`` of the SCR opponents sectors' centres, ``175 - 10 k`` degrees counter-clockwise from the
    heading (sector 0 straight back from the left, 9 left, 17/18 ahead, 27 right): a car a sector shows at ``r`` m sits
    ``r cos`` ahead and ``r sin`` to the left. What :class:`SensorRacer` and :class:`SideGuard` read the sensor by."""
    from torcsrl.envs.traffic import OPPONENT_SECTORS

    phi = np.radians(175.0 - 10.0 * np.arange(OPPONENT_SECTORS))
    return np.cos(phi), np.sin(phi)


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
    ``side_guard:racer_safe:1.27:8:9`` or ``side_guard:3:0.05:a.pt+b.pt@medoid``; an ensemble file exported with a
    guard (``python -m torcsrl.policies ensemble ... --side-guard <clear m>[:<gain>[:<edge>]]``) loads as one: the
    shipped ``reference_racer`` (the tenth version: its four students' medoid behind the default guard)."""

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
        self.fingerprint = hashlib.sha256(f"{inner.fingerprint}|{_code_fingerprint(SideGuard)}|{sorted(self.settings.items())}".encode()).hexdigest()
        from torcsrl.envs.traffic import OPPONENT_RANGE_M

        self._cos, self._sin = (torch.from_numpy(v).float() for v in sector_directions())
        self._free = OPPONENT_RANGE_M - 1e-3
        self._near_m = math.hypot(self.settings["reach_m"], self.settings["clear_m"])  # no car beside is farther [m]
        self.tp_slot = _state_slot("trackPos")  # trackPos in the state vector

    @classmethod
    def from_settings(cls, inner: Policy, settings: Mapping[str, Any] | None = None, spec: str | None = None) -> SideGuard:
        """The guard around ``inner`` with ``settings`` (any of :attr:`DEFAULTS`, the rest default): how a spec, the
        CLI, :func:`export_ensemble` and a guarded file build one. :class:`PolicyError` (one line) for an unknown key or
        a value that is not a number."""
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
    def from_spec(cls, spec: str) -> SideGuard:
        """``side_guard[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy spec>``: the leading numbers are the settings,
        the rest the policy guarded."""
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
        return cls.from_settings(load_policy(rest), vals, spec=spec)

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


def _checkpoint_file(s: str | Path, name: str | None = None) -> Policy:
    """The policy of one checkpoint or policy file: :class:`CheckpointPolicy`, or :class:`EnsemblePolicy` for an
    ensemble file (:func:`export_ensemble`)."""
    from torcsrl.utils.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint

    path = Path(s)
    if not path.exists():
        raise PolicyError(f"policy {str(s)!r} is neither a checkpoint file that exists nor one of {', '.join(BUILTIN_POLICIES)}")
    if path.is_dir():  # a run folder: its newest checkpoint
        latest = latest_checkpoint(path / "checkpoints") or latest_checkpoint(path)
        if latest is None:
            raise PolicyError(f"policy {str(s)!r} is a folder without checkpoints (ckpt_*.pt in it or in its checkpoints/)")
        path, name = latest, name or Path(s).name
    try:
        ck = load_checkpoint(path)
    except CheckpointError as err:
        raise PolicyError(str(err)) from None
    if ck["meta"].get("kind") != "ensemble":
        return CheckpointPolicy(path, name=name, payload=ck)
    members = ck.get("members")
    if not isinstance(members, list) or len(members) < 2:
        raise PolicyError(f"ensemble file {path} holds no members (expected 2 or more written by export_ensemble)")
    pols = [CheckpointPolicy(path.with_name(f"{path.stem}[{i}]"), payload=m, fingerprint=f"{ck['meta']['sha256']}:{i}")
            for i, m in enumerate(members)]
    ens = EnsemblePolicy(pols, reduce=str(ck["meta"].get("reduce", "mean")), name=name or path.stem, spec=str(path),
                         fingerprint=file_fingerprint(path))
    guard = ck["meta"].get("guard")
    if guard is None:
        return ens
    if not isinstance(guard, Mapping):
        raise PolicyError(f"ensemble file {path} has a guard {guard!r} this version cannot read; allowed: a mapping of {', '.join(SideGuard.DEFAULTS)}")
    pol = SideGuard.from_settings(ens, guard, spec=str(path))
    pol.name, pol.fingerprint = ens.name, ens.fingerprint  # the file is the driver: its name and bytes
    return pol


def export_policy(checkpoint: str | Path, out: str | Path) -> Path:
    """Write the deterministic actor of ``checkpoint`` (weights, meta, config; no optimiser,
    buffer or RNG state) to ``out`` — the format of the shipped reference driver."""
    from torcsrl.utils.checkpoint import save_checkpoint

    pol = CheckpointPolicy(checkpoint)
    meta = {k: v for k, v in pol.meta.items() if k not in ("format", "version")}
    meta.update(kind="policy", source=Path(checkpoint).name)
    return save_checkpoint(out, {"meta": meta, "actor": pol.actor.state_dict(), "config": pol.config_yaml})


# --------------------------------------------------------------------------------------------
# The expert, driven from observations
# --------------------------------------------------------------------------------------------
def _state_slot(name: str) -> int:
    from torcsrl.envs.sensors import STATE_SLOTS

    return STATE_SLOTS.index(name)


class ExpertPolicy(Policy):
    """The scripted expert (:class:`torcsrl.envs.expert.ExpertDriver`) as a policy over observations.

    The driver needs the car's pose, velocities and wheel spin. They are rebuilt each step from
    the ``state`` observation (angle to the track axis, trackPos, speedX/Y [km/h], wheel spin)
    and the lap position ``info/distFromStart`` [m] with the track map: ``d`` = trackPos times
    the half-width on that side, ``(x, y) = to_world(s, d)``, ``yaw = heading(s) + angle``.
    So a degraded ``state`` degrades the expert; it never reads the rangefinder.

    Args:
        mu_margin: fraction of the road's grip the expert's speed profile uses.
        vehicle: vehicle parameter file (must be the env's).
        line: ``"racing"`` (minimum curvature: where it drives depends on the map beyond what the
            rangefinder shows) or ``"centre"`` (the track axis at the centre line's speed profile: a
            rangefinder student can see what it follows; ``expert_centre``).
        state_key: where the raw (un-normalised) ``state`` is read; ``"state_clean"`` under a
            :class:`~torcsrl.transforms.KeepClean` when the policy's ``state`` is scaled or degraded
            (the demonstration writer does this).
    """

    name = "expert"

    def __init__(self, mu_margin: float = 0.85, vehicle: str = "default", state_key: str = "state",
                 line: str = "racing") -> None:
        from torcsrl.envs import expert as _expert
        from torcsrl.envs.vehicle import VehicleParams

        if line not in _expert._LINES:
            raise PolicyError(f"ExpertPolicy line={line!r}; allowed: {', '.join(_expert._LINES)}")
        self.params = VehicleParams.load(vehicle)
        self.mu_margin = float(mu_margin)
        self.line = line
        self.spec = "expert" if line == "racing" else f"expert_{line}"
        self.obs_keys = ("state",)
        self.state_key = state_key
        self.env_overrides = {"sensors": ("state",)}
        self.fingerprint = _code_fingerprint(ExpertPolicy, _expert) + ("" if line == "racing" else f"-{line}")
        self._drivers: dict[tuple[str, str], Any] = {}
        self.driver = None
        self.track = None
        self._i = {n: _state_slot(n) for n in ("angle_rad", "trackPos", "speedX_kmh", "speedY_kmh", "wheelSpinVel_fl")}

    def reset(self, ctx: EpisodeContext) -> None:
        t = ctx.track
        key = (t.name, t.default_surface, round(float(t.length), 3))
        if key not in self._drivers:
            from torcsrl.envs import expert as _expert

            self._drivers[key] = _expert.ExpertDriver(t, self.params, mu_margin=self.mu_margin, line=self.line)
        self.driver = self._drivers[key]
        self.track = t
        self.driver.reset(0.0)
        self._first = True
        self._dt = float(ctx.dt)
        self._prev_yaw: float | None = None

    def _car(self, td: TensorDictBase) -> SimpleNamespace:
        st = td.get(self.state_key).reshape(-1).tolist()
        s = float(td.get(("info", "distFromStart")).reshape(-1)[0])
        t = self.track
        s = s % t.length
        angle, tp = st[self._i["angle_rad"]], st[self._i["trackPos"]]
        wl, wr = t.width(s)
        d = tp * float(wl) if tp >= 0 else tp * float(wr)
        x, y = (float(v) for v in t.to_world(s, d))
        yaw = float(t.heading(s)) + angle
        vx, vy = st[self._i["speedX_kmh"]] / 3.6, st[self._i["speedY_kmh"]] / 3.6
        w0 = self._i["wheelSpinVel_fl"]
        # the yaw rate is not observed: a finite difference of the rebuilt yaw
        yaw_rate = 0.0 if self._prev_yaw is None else ((yaw - self._prev_yaw + math.pi) % (2 * math.pi) - math.pi) / self._dt
        self._prev_yaw = yaw
        c, sn = math.cos(yaw), math.sin(yaw)
        return SimpleNamespace(pos=np.array([[x, y, 0.0]]), yaw=np.array([yaw]), vel_body=np.array([[vx, vy, 0.0]]),
                               vel_world=np.array([[vx * c - vy * sn, vx * sn + vy * c, 0.0]]), yaw_rate=np.array([yaw_rate]),
                               speed=np.array([math.hypot(vx, vy)]), wheel_omega=np.array([st[w0:w0 + 4]]),
                               dt_control=self._dt)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        if self.driver is None:
            raise RuntimeError("ExpertPolicy.reset(ctx) must be called with the episode's track first")
        car = self._car(td)
        if self._first:  # locate the car from scratch once per episode
            s, _ = self.driver.track.project(car.pos[0, :2])
            self.driver.reset(float(s))
            self._first = False
        steer, throttle, brake = self.driver.act(car, 0)
        td.set("action", torch.tensor([steer, throttle - brake], dtype=torch.float32).reshape(*td.batch_size, 2))
        return td


# --------------------------------------------------------------------------------------------
# A sensor-only driver
# --------------------------------------------------------------------------------------------
class HeuristicPolicy(Policy):
    """A rangefinder + state driver in the style of the TORCS SCR sample robot.

    Steering: towards the track axis (``-k_angle * angle - k_pos * trackPos``) plus a pull
    towards the beam that sees furthest ahead (front beams within +-45 deg). Speed: the target is
    ``sqrt(2 a d)`` for the free distance ``d`` straight ahead (median of the three front beams),
    capped; throttle/brake by a proportional controller. Off the track (beams read -1) it steers
    back to the axis slowly.
    """

    name = "heuristic"

    def __init__(self, k_angle: float = 1.6, k_pos: float = 0.35, k_beam: float = 0.9, decel: float = 6.0,
                 v_min_kmh: float = 45.0, v_max_kmh: float = 220.0, max_steer_rad: float | None = None) -> None:
        from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG
        from torcsrl.envs.vehicle import VehicleParams

        self.spec = "heuristic"
        self.obs_keys = ("rangefinder", "state")
        self.env_overrides = {"sensors": ("rangefinder", "state")}
        self.fingerprint = _code_fingerprint(HeuristicPolicy)
        self.k_angle, self.k_pos, self.k_beam = k_angle, k_pos, k_beam
        self.decel = decel
        self.v_min, self.v_max = v_min_kmh / 3.6, v_max_kmh / 3.6
        self.max_steer = max_steer_rad if max_steer_rad is not None else VehicleParams.load("default").max_steer
        self.angles = np.radians(np.asarray(RANGEFINDER_ANGLES_DEG, dtype=float))
        self.front = np.flatnonzero(np.abs(self.angles) <= np.radians(45.0) + 1e-9)
        self.ahead = np.argsort(np.abs(self.angles))[:3]
        self.obs_shapes = {"rangefinder": (len(self.angles),)}
        self._ia, self._ip, self._iv = _state_slot("angle_rad"), _state_slot("trackPos"), _state_slot("speedX_kmh")

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        r = td.get("rangefinder").reshape(-1).numpy()
        st = td.get("state").reshape(-1).numpy()
        angle, tp, v = float(st[self._ia]), float(st[self._ip]), float(st[self._iv]) / 3.6
        steer = -(self.k_angle * angle + self.k_pos * tp)
        if (r >= 0).any():
            f = r[self.front]
            j = int(np.argmax(f))
            steer += self.k_beam * float(self.angles[self.front][j]) * min(1.0, 60.0 / max(float(f[j]), 1.0))
            d = float(np.median(r[self.ahead]))
            v_target = min(self.v_max, max(self.v_min, math.sqrt(2.0 * self.decel * max(d - 10.0, 0.0))))
        else:
            v_target = self.v_min
        steer = max(-1.0, min(1.0, steer / max(self.max_steer, 1e-3) * 0.5))
        err = v_target - v
        tb = max(-1.0, min(1.0, 0.25 * err + (0.1 if err > 0 else 0.0)))
        td.set("action", torch.tensor([steer, tb], dtype=torch.float32).reshape(*td.batch_size, 2))
        return td


class SensorDriver(Policy):
    """A teacher whose every choice the observation explains: a TORCS-SCR-style driver on the rangefinder
    and ``state`` alone, stateless (the action is a function of the current observation), so a network
    can imitate it exactly and DAgger can label any state a learner reaches.

    * **Steering** [rad, then / ``max_steer``]: towards the free space ahead — the beam-length-weighted
      mean direction of the front beams (|angle| <= 60 deg, weights ``(r / 200 m)^p``), pulled less on
      long straights (``* min(1, 60 m / d)``) — minus ``k_axis`` x the course angle to the track axis
      (heading angle + ``k_beta`` x the slip angle ``atan(v_y / v_x)``) minus ``k_pos`` x trackPos.
      Each of the three terms is scaled by ``min(1, v_gain / v)`` with its own ``v_gain_*`` [m/s]: the
      heading a steering command turns in one control step grows as ``v dt / wheelbase``, so a gain that
      is right at 10 m/s makes the loop ring at 25 m/s and 10 Hz (the steering then flips sign every step
      or two: 40-70 flips/km). Only the free-space term needs it (``v_gain_free`` 5 m/s).
    * **Speed target** [m/s]: what can still stop within the free distance ``d`` straight ahead (the
      longest of the three central beams): ``sqrt(2 decel (d - d0))``, clipped to [``v_min``, ``v_max``];
      at (near) full lock (|steer| > ``sat``) a tenth below the current speed.
    * **Pedal**: proportional on the speed error (``k_v``) plus a 0.1 cruise offset that fades in over the
      last ``pedal_ramp_ms`` [m/s] below the target (a step there makes the pedal chatter); traction
      control on the driven (rear) wheels (throttle faded out as their slip exceeds ``slip_max``) and a
      throttle cap while sliding (``max(u_slide, 1 - k_slide |beta|)``).
    * Off the track (beams read -1): back towards the axis at walking pace.

    ``decel`` (4.5 m/s^2) is below the grip of dirt (mu 0.6) and gravel (0.5), so the same driver is safe on asphalt, wet, dirt and
    gravel (and slower than it could be on asphalt: it cannot see the surface). Tuned on the training tracks
    and training-range generated tracks only (``set:train``, ``gen-10001…10008``), at 10 Hz. The first
    version (the teacher of ``reference_dagger.pt``) is ``SensorDriver(**SensorDriver.V1)``.
    """

    #: Braking the grip-aware teacher plans with per unit of friction [m/s^2] (``decel_per_mu``): 7.5 on asphalt,
    #: 5.25 wet, 4.5 dirt (the surface-blind teacher's decel), 3.75 gravel. Screened on training tracks only
    #: (set:train's fast_straights, hairpins, esses + gen-10001/2/4, 2 laps at 10 Hz): 24/24 laps on asphalt, wet,
    #: dirt and gravel at 1.17-1.19x the expert (the surface-blind teacher: 1.45x on asphalt).
    GRIP_DECEL_PER_MU = 7.5
    #: The sight distance [m] of the camera student's teacher (``sensor_sight``): it plans its speed as if it saw no
    #: further than this straight ahead. In the 96x64 hood camera a bend shows only a few tens of metres ahead (a point
    #: 100 m ahead on the road is within one pixel row of the horizon); a teacher that sees 200 m brakes for bends the
    #: student cannot see yet. An observability-matched teacher: its choices are ones the student can infer. Chosen on
    #: the training screen (2026-11-26, set:train + gen-10001..8, one lap, asphalt and dirt): the BC students of
    #: teachers with sight 80 / 100 m lapped 24/26 / 18/26 (the sight-200 teacher's: 17/26), with regression losses
    #: 0.0099 / 0.0107 / 0.0148; the teachers themselves lap 26/26 at 1.40x / 1.33x / 1.26x the expert.
    CAMERA_SIGHT_M = 80.0
    #: The fast teacher (``sensor_fast``): grip-aware braking at 9 m/s^2 per unit mu, a corner speed from the circle
    #: through the farthest free point (``k_corner``), braking towards 8 m/s rather than to a stop at the wall ahead
    #: (``v_corner_ms``), and a 3x stiffer speed loop (``k_v``). Screened on training tracks only (set:train +
    #: gen-10001..4, asphalt, 2 laps at 10 Hz, 2026-11-27): 9/9 laps at a median 1.076x the expert's lap (sensor_grip:
    #: 9/9 at 1.165x) — faster than experts at 85 % pace (1.176x), which a racer must beat (issue #20).
    FAST = {"decel_per_mu": 9.0, "v_corner_ms": 8.0, "k_corner": 0.7, "k_v": 0.3}
    #: The fast camera teacher (``sensor_fast_sight``): the fast gains limited to the camera's sight
    #: (:data:`CAMERA_SIGHT_M`) with a gentler corner speed (``k_corner`` 0.6: at 0.7 it left hairpins on dirt and
    #: gravel). Screened on training tracks only (set:train + gen-10001..4, 2 laps at 10 Hz, 2026-11-27): 36/36 laps on
    #: asphalt, wet, dirt and gravel at a median 1.18-1.20x the expert (``sensor_sight``: 36/36 at 1.31-1.33x; FAST's
    #: k_corner 0.7 at 80 m: 32/36; decel 8 per mu: 36/36 at 1.20-1.24x).
    CAMERA_FAST = {"decel_per_mu": 9.0, "v_corner_ms": 8.0, "k_corner": 0.6, "k_v": 0.3}
    #: The first teacher's gains (no speed scaling, a pedal step, softer traction control, decel 3.5).
    V1 = {"decel": 3.5, "k_v": 0.3, "slip_max": 0.12, "v_gain_free": math.inf, "v_gain_axis": math.inf,
          "v_gain_pos": math.inf, "pedal_ramp_ms": 0.0}

    name = "sensor"

    def __init__(self, decel: float = 4.5, d0: float = 8.0, v_min: float = 4.0, v_max: float = 75.0, k_axis: float = 0.5,
                 k_pos: float = 0.15, k_free: float = 0.8, p: float = 6.0, k_beta: float = -1.0, slip_max: float = 0.05,
                 tc_width: float = 3.0, u_slide: float = 0.3, k_slide: float = 5.0, k_v: float = 0.1, sat: float = 0.9,
                 v_gain_free: float = 5.0, v_gain_axis: float = math.inf, v_gain_pos: float = 15.0,
                 pedal_ramp_ms: float = 1.0, decel_per_mu: float | None = None, sight_m: float | None = None,
                 v_corner_ms: float = 0.0, k_corner: float | None = None, grip_exponent: float = 1.0,
                 vehicle: str = "default", rangefinder_key: str = "rangefinder", state_key: str = "state") -> None:
        from torcsrl.envs.sensors import RANGEFINDER_ANGLES_DEG
        from torcsrl.envs.vehicle import VehicleParams

        prm = VehicleParams.load(vehicle)
        self.spec = "sensor"
        self.obs_keys = ("rangefinder", "state")
        self.env_overrides = {"sensors": ("rangefinder", "state")}
        self.k = SimpleNamespace(decel=decel, d0=d0, v_min=v_min, v_max=v_max, k_axis=k_axis, k_pos=k_pos, k_free=k_free, p=p,
                                 k_beta=k_beta, slip_max=slip_max, tc_width=tc_width, u_slide=u_slide, k_slide=k_slide, k_v=k_v, sat=sat,
                                 v_gain=(float(v_gain_free), float(v_gain_axis), float(v_gain_pos)), pedal_ramp_ms=float(pedal_ramp_ms),
                                 decel_per_mu=None if decel_per_mu is None else float(decel_per_mu),
                                 sight_m=math.inf if sight_m is None else float(sight_m), v_corner=float(v_corner_ms),
                                 k_corner=None if k_corner is None else float(k_corner), grip_exponent=float(grip_exponent))
        if not math.isfinite(float(grip_exponent)) or float(grip_exponent) < 1.0:
            raise ValueError(f"SensorDriver grip_exponent must be a finite number >= 1 (1: braking in proportion to the grip), got {grip_exponent}")
        self.fingerprint = _code_fingerprint(SensorDriver, repr(sorted(vars(self.k).items())))  # code and gains
        if decel_per_mu is not None:
            if not math.isfinite(float(decel_per_mu)) or float(decel_per_mu) <= 0.0:
                raise ValueError(f"SensorDriver decel_per_mu must be a finite braking rate > 0 [m/s^2 per unit mu], got {decel_per_mu}")
            self.spec = f"sensor-grip{float(decel_per_mu):g}"
        if sight_m is not None:
            if not math.isfinite(float(sight_m)) or float(sight_m) <= d0:
                raise ValueError(f"SensorDriver sight_m must be a finite distance > d0 = {d0} m, got {sight_m}")
            self.spec += f"-sight{float(sight_m):g}"
        self.max_steer, self.wheel_r = float(prm.max_steer), float(prm.wheel_radius)
        self.keys = (rangefinder_key, state_key)
        self.ang = np.radians(np.asarray(RANGEFINDER_ANGLES_DEG, dtype=float))
        self.front = np.flatnonzero(np.abs(self.ang) <= np.radians(60.0) + 1e-9)
        self.centre = np.argsort(np.abs(self.ang))[:3]
        self.obs_shapes = {"rangefinder": (len(self.ang),)}
        self._i = {n: _state_slot(n) for n in ("angle_rad", "trackPos", "speedX_kmh", "speedY_kmh", "wheelSpinVel_rl", "wheelSpinVel_rr")}

    def act(self, r: np.ndarray, st: np.ndarray, mu: float | None = None, tp_target: float = 0.0,
            decel_per_mu: float | None = None) -> tuple[float, float]:
        """(steer, throttle_brake) in [-1, 1] from one car's beams [m] and state (raw units); ``mu`` [-], the
        friction under the car, sets the braking it plans with when the driver is grip-aware (``decel_per_mu``, or
        the argument in its place [m/s^2 at mu 1]); ``tp_target`` [trackPos units] is where across the road the
        centring term pulls (0: the axis)."""
        k, i = self.k, self._i
        per_mu = k.decel_per_mu if decel_per_mu is None else decel_per_mu
        decel = k.decel if per_mu is None or mu is None else per_mu * float(mu) ** k.grip_exponent
        v = float(st[i["speedX_kmh"]]) / 3.6
        beta = math.atan2(float(st[i["speedY_kmh"]]) / 3.6, max(v, 5.0))  # slip angle [rad]
        angle, tp = float(st[i["angle_rad"]]) + k.k_beta * beta, float(st[i["trackPos"]])
        if (r < 0).all():  # off the track
            steer_rad, v_t = -(k.k_axis * angle + 0.5 * tp), 0.5 * k.v_min
        else:
            f = np.maximum(r[self.front], 0.0)
            w = (f / 200.0) ** k.p + 1e-9
            theta = float((w * self.ang[self.front]).sum() / w.sum())
            d = min(float(np.max(r[self.centre])), k.sight_m)
            g_free, g_axis, g_pos = (min(1.0, vg / max(v, 1.0)) for vg in k.v_gain)
            steer_rad = (g_free * k.k_free * theta * min(1.0, 60.0 / max(d, 1.0)) - g_axis * k.k_axis * angle
                         - g_pos * k.k_pos * (tp - tp_target))
            v_t = min(k.v_max, max(k.v_min, math.sqrt(k.v_corner ** 2 + 2.0 * decel * max(d - k.d0, 0.0))))
            if k.k_corner is not None:  # the bend it is in: the circle along the heading through the farthest point
                j = int(np.argmax(f))
                sin_t = abs(math.sin(float(self.ang[self.front][j])))
                if sin_t > 1e-3:
                    radius = min(float(f[j]), k.sight_m) / (2.0 * sin_t)
                    v_t = min(v_t, max(k.v_min, math.sqrt(k.k_corner * decel * radius)))
        steer = max(-1.0, min(1.0, steer_rad / self.max_steer))
        if abs(steer) > k.sat:
            v_t = min(v_t, 0.9 * v)
        err = v_t - v
        if k.pedal_ramp_ms > 0.0:
            cruise = 0.1 * min(1.0, max(0.0, 1.0 + err / k.pedal_ramp_ms))
        else:
            cruise = 0.1 if err > 0 else 0.0
        u = max(-1.0, min(1.0, k.k_v * err + cruise))
        if u > 0:  # traction control on the driven wheels, throttle cap while sliding
            spin = 0.5 * (float(st[i["wheelSpinVel_rl"]]) + float(st[i["wheelSpinVel_rr"]])) * self.wheel_r
            slip = (spin - v) / max(v, 3.0)
            if slip > k.slip_max:
                u *= max(0.0, 1.0 - (slip - k.slip_max) / (k.tc_width * k.slip_max))
            u = min(u, max(k.u_slide, 1.0 - k.k_slide * abs(beta)))
        return steer, u

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        r = td.get(self.keys[0]).reshape(-1, len(self.ang)).numpy()
        st = td.get(self.keys[1]).reshape(r.shape[0], -1).numpy()
        if self.k.decel_per_mu is not None:
            mu = td.get(("info", "surfaceMu"), None)
            if mu is None:
                raise ValueError("a grip-aware SensorDriver (decel_per_mu) reads ('info', 'surfaceMu'), which this tensordict lacks")
            mu = mu.reshape(-1).tolist()
        else:
            mu = [None] * r.shape[0]
        out = torch.tensor([self.act(r[j], st[j], mu[j]) for j in range(r.shape[0])], dtype=torch.float32)
        td.set("action", out.reshape(*td.batch_size, 2))
        return td


class SensorRacer(SensorDriver):
    """The race teacher: :class:`SensorDriver` with the fast gains (``SensorDriver.FAST``) that passes the cars its
    ``opponents`` sensor shows (TORCS SCR's 36 sectors, 200 m = free) and lifts or brakes for one it cannot pass yet —
    from the current observation alone (stateless), so a student with the same sensors can imitate it.

    Each car a sector shows sits at ``x = r cos(phi)`` ahead and ``y = r sin(phi)`` left [m] (sector k's centre
    ``phi = 175 - 10 k`` degrees counter-clockwise from the heading). Its place relative to the road ahead is
    ``dy = y - kappa x^2 / 2``, with ``kappa`` the curvature of the circle along the heading through the farthest free
    point (the bend the rangefinder shows), and its trackPos ``tp + dy / w`` (``w`` the half-width the side beams
    read).

    * **Passing**: the car that matters is the nearest ahead (else alongside, to ``rear_m`` behind) with
      ``x < look_m`` and ``|dy| < 2 lane_m``. The racer passes on the side it is already on (from straight behind:
      the roomier side; the other side where a third car is near that line), aiming ``pass_gap_m`` beside it and at
      most ``tp_max`` out, through the centring term's target (``tp_target``), weighted from 0 at ``look_m`` ahead to
      1 at ``full_m`` and fading over ``rear_m`` once passed. It starts a pass only where the road ahead is
      straighter than ``pass_radius_m`` and no bend is near — the free distance straight ahead exceeds its braking
      distance ``v^2 / (2 decel)`` plus ``bend_m`` — and finishes one it is in (``|dy| > 1.5 m``).
    * **Following**: a car more than ``length_m`` ahead (centre to centre; one alongside it steers away from) within
      ``lane_m`` of its path or of the line it heads for makes it lift closer than ``lift_m + lift_s v`` and brake
      (``brake`` of the pedal) closer than ``brake_m + brake_s v`` (``v`` its speed [m/s]). Near a bend and while it
      brakes that corridor is ``bend_lanes`` x ``lane_m`` wide (a car ahead on the racing line turns in across the
      inside: the scripted opponents do not see a car beside them), and with ``yield_alongside`` a car alongside
      but a little ahead counts too (it lets it go first).

    * **Fighting**: with ``fight_decel_per_mu`` [m/s^2 at mu 1] it plans its braking (and corner speed) at that rate
      while a car is within ``fight_m`` [m] (any sector), at its own ``decel_per_mu`` otherwise — a margin when it
      drives alone, the limit in a fight (``racer_safe:<gamma>:<decel>:<fight decel>[:<fight m>]``).

    Without an ``opponents`` key it drives as ``sensor_fast``.
    """

    name = "racer"
    #: ``racer_bold``: never widens the following corridor near bends nor yields to a car alongside (races on the
    #: training tracks, 5 laps against 3 experts at 85 %, 2026-11-27: 11/16 wins, 1.81 collisions a race; the default,
    #: cautious racer: 3/16 wins, 0.81 collisions a race).
    BOLD = {"bend_lanes": 1.0, "yield_alongside": False, "bend_m": -1000.0}
    #: ``racer_safe[:<gamma>]``: ``racer_bold`` planning its braking with ``decel_per_mu * mu ** gamma`` — the same on
    #: asphalt (mu = 1), a margin on low grip that grows as the grip falls (dirt, mu 0.6: 3.2 m/s^2 at gamma 2 against
    #: 5.4 at gamma 1), so a student whose grip estimate runs high still brakes within the road's grip.
    SAFE_GRIP_EXPONENT = 2.0
    #: ``racer_clean[:<gamma>]``: ``racer_safe`` whose following corridor near a bend (and while it brakes) is 1.5 lanes
    #: wide: a car ahead on the racing line turns in across part of the inside. Races on the training tracks (5 laps,
    #: 3 experts at pace drawn from [0.83, 0.87], 3 races a track, seed 0; 2026-11-27): 22/24 finished, 17/24 wins,
    #: 0.75 collisions a race (racer_bold: 21/24, 16/24, 1.08; yielding to a car alongside: 23/24, 18/24, 1.17;
    #: holding its lane while a car is within 30 m, ``hold_lane``: 24/24, 19/24, 1.08).
    CLEAN = {**BOLD, "bend_lanes": 1.5}
    #: ``racer_keep[:<gamma>...]``: ``racer_safe`` that finishes a pass on the side it is on. Once beside the car it
    #: passes (``|dy| > 1.5 m``) it never takes the other side's line (across that car's path), and with no room on its
    #: own side (a third car near that line) it holds its trackPos — the following rules lift or brake for that car —
    #: where ``racer_safe`` aims at the road's centre.
    KEEP = {**BOLD, "keep_side": True}
    #: ``racer_yield[:<gamma>...]``: ``racer_safe`` that completes a pass before the braking zone or gives it up. Within
    #: ``abandon_m`` [m] of its braking point for the bend ahead (the free distance straight ahead less than its
    #: braking distance ``v^2 / (2 decel)`` plus ``abandon_m``) it starts no pass, and beside a car it has not yet
    #: cleared by a car length it holds its lane, braking to drop behind while that car's centre is ahead of its own
    #: (``racer_safe`` and ``racer_keep`` finish the pass into the bend, side by side).
    YIELD = {**BOLD, "abandon_m": 30.0}

    def __init__(self, look_m: float = 60.0, full_m: float = 30.0, rear_m: float = 15.0, pass_gap_m: float = 3.8,
                 tp_max: float = 0.7, lane_m: float = 2.4, length_m: float = 4.5, lift_m: float = 10.0, lift_s: float = 0.8,
                 brake_m: float = 6.0, brake_s: float = 0.5, brake: float = 1.0, pass_radius_m: float = 120.0,
                 bend_m: float = 50.0, bend_lanes: float = 2.5, yield_alongside: bool = True, hold_lane: bool = False,
                 fight_decel_per_mu: float | None = None, fight_m: float = 60.0, clear_m: float = 0.0,
                 keep_side: bool = False, abandon_m: float | None = None, opponents_key: str = "opponents", **kw: Any) -> None:
        from torcsrl.envs.traffic import OPPONENT_RANGE_M

        if fight_decel_per_mu is not None and not (math.isfinite(float(fight_decel_per_mu)) and float(fight_decel_per_mu) > 0.0):
            raise ValueError(f"SensorRacer fight_decel_per_mu must be a positive rate [m/s^2 at mu 1], got {fight_decel_per_mu}")
        if not (math.isfinite(float(fight_m)) and 0.0 < float(fight_m) <= OPPONENT_RANGE_M):
            raise ValueError(f"SensorRacer fight_m must be in (0, {OPPONENT_RANGE_M:g}] m (the opponents sensor's range), got {fight_m}")
        if not (math.isfinite(float(clear_m)) and 0.0 <= float(clear_m) <= 30.0):
            raise ValueError(f"SensorRacer clear_m must be in [0, 30] m, got {clear_m}")
        if abandon_m is not None and not (math.isfinite(float(abandon_m)) and 0.0 <= float(abandon_m) <= OPPONENT_RANGE_M):
            raise ValueError(f"SensorRacer abandon_m must be None (off) or in [0, {OPPONENT_RANGE_M:g}] m, got {abandon_m}")
        super().__init__(**{**SensorDriver.FAST, **kw})
        self.spec = "racer"
        self.obs_keys = ("rangefinder", "state", "opponents")
        # the rate its gains are tuned at (SensorDriver's: 10 Hz, 20 physics substeps), as the students it teaches drive
        self.env_overrides = {"sensors": ("rangefinder", "state", "opponents"), "control_hz": 10.0, "substeps": 20}
        self.opponents_key = opponents_key
        self.race = SimpleNamespace(look_m=look_m, full_m=full_m, rear_m=rear_m, pass_gap_m=pass_gap_m, tp_max=tp_max,
                                    lane_m=lane_m, length_m=length_m, lift_m=lift_m, lift_s=lift_s, brake_m=brake_m, brake_s=brake_s,
                                    brake=brake, pass_radius_m=pass_radius_m, bend_m=bend_m, bend_lanes=bend_lanes,
                                    yield_alongside=bool(yield_alongside), hold_lane=bool(hold_lane),
                                    fight_decel_per_mu=None if fight_decel_per_mu is None else float(fight_decel_per_mu),
                                    fight_m=float(fight_m), clear_m=float(clear_m), keep_side=bool(keep_side),
                                    abandon_m=None if abandon_m is None else float(abandon_m))
        self.fingerprint = _code_fingerprint(SensorDriver, SensorRacer, repr(sorted(vars(self.k).items())),
                                             repr(sorted(vars(self.race).items())))
        self._cos, self._sin = sector_directions()
        self._free = OPPONENT_RANGE_M - 1e-3
        self._side = (int(np.argmin(self.ang)), int(np.argmax(self.ang)))  # the -90 (right) and +90 (left) beams

    def traffic(self, r: np.ndarray, st: np.ndarray, opp: np.ndarray, braking: bool = False) -> tuple[float, float]:
        """``(tp_target, pedal_cap)`` from one car's beams [m], state and opponent sectors [m]: where across the road
        to drive (trackPos units) and the most pedal allowed (1 free, 0 lift, < 0 brake); ``braking``: the car brakes
        for a bend (the following corridor widens, as near a bend)."""
        q = self.race
        seen = np.flatnonzero(opp < self._free)
        if len(seen) == 0 or (r < 0).all():
            return 0.0, 1.0
        tp = float(st[self._i["trackPos"]])
        w = max(0.5 * (max(float(r[self._side[0]]), 0.0) + max(float(r[self._side[1]]), 0.0)), 2.0)  # half-width [m]
        f = np.maximum(r[self.front], 0.0)
        j = int(np.argmax(f))
        kappa = 2.0 * math.sin(float(self.ang[self.front][j])) / max(float(f[j]), 1.0)  # the bend ahead [1/m, + left]
        v = max(float(st[self._i["speedX_kmh"]]) / 3.6, 0.0)
        d_free = float(np.max(r[self.centre]))  # straight ahead [m]
        brake_dist = v * v / (2.0 * (self.k.decel_per_mu or self.k.decel))  # [m] (braking as on mu = 1)
        bend_near = d_free < brake_dist + q.bend_m
        zone = q.abandon_m is not None and d_free < brake_dist + q.abandon_m  # near the braking point: no pass unfinished
        x, y = opp[seen] * self._cos[seen], opp[seen] * self._sin[seen]
        dy = y - 0.5 * kappa * x * x
        tp_o = tp + dy / w
        near = (x > -(q.rear_m + q.clear_m)) & (x < q.look_m) & (np.abs(dy) < 2.0 * q.lane_m)
        target, drop = 0.0, False
        if near.any():
            ahead = near & (x > 0.0)
            pick = ahead if ahead.any() else near
            i = int(np.argmin(np.where(pick, np.abs(x), np.inf)))
            gap = q.pass_gap_m / w
            go_left = dy[i] < 0.0 if abs(dy[i]) > 0.5 else tp_o[i] < 0.0
            left, right = min(tp_o[i] + gap, q.tp_max), max(tp_o[i] - gap, -q.tp_max)
            sides = (left, right) if go_left else (right, left)
            others = (np.arange(len(x)) != i) & (x > -2.0 * q.length_m) & (x < q.full_m)

            def free(a: float) -> bool:  # room beside the car passed, and no other car near that line
                return abs(a - tp_o[i]) >= gap - 1e-6 and not (others & (np.abs(tp_o - a) * w < q.lane_m)).any()

            committed = abs(dy[i]) > 1.5  # already beside it: finish the pass; else start one only where the road is straight
            keep = q.keep_side and committed  # beside it, the other side's line crosses its path
            aim = next((a for a in (sides[:1] if keep else sides) if free(a)), None)
            if zone and committed and float(x[i]) > -q.length_m:  # not clear of it by a car length: give the pass up
                target = max(-q.tp_max, min(q.tp_max, tp))
                drop = float(x[i]) > 0.0  # its centre ahead of ours: brake, let it into the bend first
            elif aim is not None and (committed or (abs(kappa) * q.pass_radius_m < 1.0 and not bend_near and not zone)):
                xi = float(x[i])
                wt = (q.look_m - xi) / (q.look_m - q.full_m) if xi >= 0.0 else (xi + q.clear_m + q.rear_m) / q.rear_m
                target = min(1.0, max(0.0, wt)) * aim
            elif keep or (q.hold_lane and (np.abs(x[near]) < q.full_m).any()):  # no room: keep the lane it is in
                target = max(-q.tp_max, min(q.tp_max, tp))
        cap = -q.brake if drop else 1.0
        braking = braking or bend_near
        lift, brake = q.lift_m + q.lift_s * v, q.brake_m + q.brake_s * v  # [m]
        # near a bend a car ahead may turn in across the car's path: a wider corridor, and one alongside but a little
        # ahead is let go first; on a straight one alongside is steered away from, not braked for
        lane, x_min = (q.lane_m * q.bend_lanes, 0.0 if q.yield_alongside else q.length_m) if braking else (q.lane_m, q.length_m)
        for xa, da, ta in zip(x.tolist(), dy.tolist(), tp_o.tolist()):  # on its path now, or on the line it heads for
            if xa > x_min and (abs(da) < lane or abs(ta - target) * w < lane):
                cap = min(cap, -q.brake if xa < brake else 0.0 if xa < lift else 1.0)
        return target, cap

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        opp_t = td.get(self.opponents_key, None)
        if opp_t is None:
            return super().__call__(td)
        r = td.get(self.keys[0]).reshape(-1, len(self.ang)).numpy()
        st = td.get(self.keys[1]).reshape(r.shape[0], -1).numpy()
        opp = opp_t.reshape(r.shape[0], -1).numpy().astype(np.float64)
        mu = td.get(("info", "surfaceMu"), None)
        if mu is None:
            raise ValueError("the racer (a grip-aware SensorDriver) reads ('info', 'surfaceMu'), which this tensordict lacks")
        mu = mu.reshape(-1).tolist()
        out = []
        q = self.race
        for j in range(r.shape[0]):
            target, cap = self.traffic(r[j], st[j], opp[j])
            fight = q.fight_decel_per_mu is not None and bool((opp[j] < q.fight_m).any())
            steer, u = self.act(r[j], st[j], mu[j], tp_target=target, decel_per_mu=q.fight_decel_per_mu if fight else None)
            if u < 0.0:  # braking for a bend: a car ahead may turn in across its path
                cap = self.traffic(r[j], st[j], opp[j], braking=True)[1]
            out.append((steer, min(u, cap)))
        td.set("action", torch.tensor(out, dtype=torch.float32).reshape(*td.batch_size, 2))
        return td


# --------------------------------------------------------------------------------------------
# Random actions
# --------------------------------------------------------------------------------------------
class RandomPolicy(Policy):
    """Uniform random actions in [-1, 1], from a generator seeded at every episode start."""

    name = "random"

    def __init__(self, action_dim: int = 2) -> None:
        self.spec = "random"
        self.obs_keys = ()
        self.env_overrides = {}
        self.action_dim = int(action_dim)
        self.fingerprint = _code_fingerprint(RandomPolicy)
        self.gen = torch.Generator().manual_seed(0)

    def reset(self, ctx: EpisodeContext) -> None:
        self.gen.manual_seed(int(ctx.seed) & ((1 << 63) - 1))

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        a = torch.rand(*td.batch_size, self.action_dim, generator=self.gen) * 2.0 - 1.0
        td.set("action", a)
        return td


# --------------------------------------------------------------------------------------------
def _sight(name: str) -> float:
    """The sight distance [m] of ``sensor_sight`` / ``sensor_fast_sight`` (:data:`SensorDriver.CAMERA_SIGHT_M`) or
    ``<name>:<metres>``."""
    if ":" not in name:
        return SensorDriver.CAMERA_SIGHT_M
    base, tail = name.split(":", 1)
    try:
        return float(tail)
    except ValueError:
        raise PolicyError(f"{name!r}: the sight distance after '{base}:' must be a number of metres, e.g. {base}:70") from None


def _sight_teacher(name: str, **keys: str) -> SensorDriver | None:
    """The camera teachers: ``sensor_sight[:<m>]`` (grip-aware, ``GRIP_DECEL_PER_MU``) and ``sensor_fast_sight[:<m>]``
    (``SensorDriver.CAMERA_FAST``), each planning on at most ``<m>`` (80) metres of free road; None for other names."""
    for base, gains in (("sensor_sight", {"decel_per_mu": SensorDriver.GRIP_DECEL_PER_MU}),
                        ("sensor_fast_sight", SensorDriver.CAMERA_FAST)):
        if name == base or name.startswith(base + ":"):
            drv = SensorDriver(**gains, sight_m=_sight(name), **keys)
            if base == "sensor_fast_sight":
                drv.spec = drv.name = name
            return drv
    return None


#: The values of ``racer_safe:<gamma>:<decel>:<fight decel>:<fight m>:<clear m>:<abandon m>``, in order: (SensorRacer keyword, what it is,
#: the test it must pass, the allowed range as the error says it).
_RACER_VALUES = (("grip_exponent", "the grip exponent", lambda v: v >= 1.0, ">= 1 (1: braking in proportion to the grip)"),
                 ("decel_per_mu", "the braking rate", lambda v: 0.0 < v <= 12.0, "in (0, 12] m/s^2 at mu 1 (the default: 9)"),
                 ("fight_decel_per_mu", "the braking rate in a fight", lambda v: 0.0 < v <= 12.0, "in (0, 12] m/s^2 at mu 1"),
                 ("fight_m", "the fight distance", lambda v: 0.0 < v <= 200.0, "in (0, 200] m (the opponents sensor's range)"),
                 ("clear_m", "the room kept past a car passed", lambda v: 0.0 <= v <= 30.0, "in [0, 30] m (the default: 0)"),
                 ("abandon_m", "the distance before the braking point with no pass left unfinished", lambda v: 0.0 <= v <= 200.0,
                  "in [0, 200] m (racer_yield's default: 30; none for the others)"))


def racer_gains(name: str) -> dict[str, Any] | None:
    """The :class:`SensorRacer` gains of ``racer_safe`` + :data:`RACER_VALUES_FORM` (and
    ``racer_clean[...]``, ``racer_keep[...]``, ``racer_yield[...]``): ``SensorRacer.BOLD`` / ``CLEAN`` / ``KEEP`` / ``YIELD`` with ``grip_exponent`` gamma (default 2), where given
    ``decel_per_mu`` [m/s^2 at mu 1; the default is ``SensorDriver.FAST``'s 9], ``fight_decel_per_mu`` (the rate while
    a car is within ``fight_m``) and ``fight_m`` [m, default 60] (:data:`_RACER_VALUES`); None for other names;
    :class:`PolicyError` (one line) for a bad value."""
    for base, gains in (("racer_safe", SensorRacer.BOLD), ("racer_clean", SensorRacer.CLEAN), ("racer_keep", SensorRacer.KEEP),
                        ("racer_yield", SensorRacer.YIELD)):
        if name == base or name.startswith(base + ":"):
            form = f"{base}{RACER_VALUES_FORM}, e.g. {base}:2 or {base}:1.27:8:9"
            parts = name.split(":")[1:]
            if len(parts) > len(_RACER_VALUES):
                raise PolicyError(f"{name!r}: at most six values after '{base}': {form}")
            out = {**gains, "grip_exponent": SensorRacer.SAFE_GRIP_EXPONENT}
            for text, (key, what, ok, allowed) in zip(parts, _RACER_VALUES):
                try:
                    v = float(text)
                except ValueError:
                    raise PolicyError(f"{name!r}: {what} must be a number {allowed}, got {text!r}: {form}") from None
                if not math.isfinite(v) or not ok(v):
                    raise PolicyError(f"{name!r}: {what} must be {allowed}, got {v:g}")
                out[key] = v
            return out
    return None


def is_ensemble_spec(spec: str | Path) -> bool:
    """Whether ``spec`` names an ensemble of checkpoints (``a.pt+b.pt[+...][@reduce]``; a file whose name has a ``+``
    is still a file)."""
    return "+" in str(spec) and not Path(str(spec)).exists()


def load_policy(spec: str | Path | Policy) -> Policy:
    """The :class:`Policy` for ``spec`` (see the module docstring); :class:`PolicyError` (one line)
    for a missing, corrupt or unusable checkpoint."""
    if isinstance(spec, Policy):
        return spec
    s = str(spec)
    if s.startswith(SideGuard.PREFIX + ":") and not Path(s).exists():
        return SideGuard.from_spec(s)
    if s == "expert":
        return ExpertPolicy()
    if s == "expert_centre":
        return ExpertPolicy(line="centre")
    if s == "racer":
        return SensorRacer()
    if s == "racer_bold":
        drv = SensorRacer(**SensorRacer.BOLD)
        drv.spec = drv.name = "racer_bold"
        return drv
    kw = racer_gains(s)
    if kw is not None:
        drv = SensorRacer(**kw)
        drv.spec = drv.name = s
        return drv
    if s == "heuristic":
        return HeuristicPolicy()
    if s == "sensor":
        return SensorDriver()
    if s == "sensor_grip":
        return SensorDriver(decel_per_mu=SensorDriver.GRIP_DECEL_PER_MU)
    sight = _sight_teacher(s)
    if sight is not None:
        return sight
    if s == "sensor_fast":
        drv = SensorDriver(**SensorDriver.FAST)
        drv.spec = drv.name = "sensor_fast"
        return drv
    if s == "random":
        return RandomPolicy()
    if s == "reference":
        if not REFERENCE_POLICY.is_file():
            raise PolicyError(f"the reference driver {REFERENCE_POLICY} is not shipped yet; pass a checkpoint path, 'expert' or 'heuristic'")
        return _checkpoint_file(REFERENCE_POLICY, name="reference")
    if s == "reference-td3":
        return _checkpoint_file(REFERENCE_RL_POLICY, name="reference-td3")
    if s in ("reference_racer", "reference-racer"):
        if not REFERENCE_RACER_POLICY.is_file():
            raise PolicyError(f"the racing driver {REFERENCE_RACER_POLICY} is not shipped yet; pass a checkpoint path")
        return _checkpoint_file(REFERENCE_RACER_POLICY, name="reference_racer")
    if s in ("reference_camera", "reference-camera"):
        if not REFERENCE_CAMERA_POLICY.is_file():
            raise PolicyError(f"the camera driver {REFERENCE_CAMERA_POLICY} is not shipped yet; pass a checkpoint path")
        return _checkpoint_file(REFERENCE_CAMERA_POLICY, name="reference_camera")
    if is_ensemble_spec(s):
        return EnsemblePolicy.from_spec(s)
    return _checkpoint_file(s)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torcsrl.policies", description="Inspect or export evaluation policies.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="write a policy file (actor weights + config) from a training checkpoint")
    e.add_argument("checkpoint")
    e.add_argument("out")
    en = sub.add_parser("ensemble", help="write ONE policy file driving several checkpoints as an ensemble (EnsemblePolicy)")
    en.add_argument("out")
    en.add_argument("checkpoints", nargs="+")
    en.add_argument("--reduce", default="mean", help="mean, median, cautious, medoid or guarded[:<m>] (EnsemblePolicy)")
    en.add_argument("--side-guard", default=None, metavar="CLEAR_M[:GAIN[:EDGE]]",
                    help="drive the file behind a SideGuard with these settings (e.g. 2.6; defaults for the rest)")
    mb = sub.add_parser("member", help="write one member of an ensemble file as a one-actor policy file (e.g. for init.actor)")
    mb.add_argument("ensemble")
    mb.add_argument("index", type=int)
    mb.add_argument("out")
    i = sub.add_parser("info", help="print what a policy spec loads")
    i.add_argument("spec")
    args = parser.parse_args(argv)
    try:
        if args.cmd == "export":
            out = export_policy(args.checkpoint, args.out)
            print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB)")
        elif args.cmd == "ensemble":
            guard = None if args.side_guard is None else parse_guard_values(args.side_guard)
            out = export_ensemble(args.checkpoints, args.out, args.reduce, guard=guard)
            pol = load_policy(out)
            print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB): {len(args.checkpoints)} members, reduce={args.reduce}"
                  + (f", side guard {pol.settings}" if isinstance(pol, SideGuard) else ""))
        elif args.cmd == "member":
            out = export_member(args.ensemble, args.index, args.out)
            print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB): member {args.index} of {args.ensemble}")
        else:
            print(load_policy(args.spec).describe())
    except PolicyError as err:
        print(f"torcsrl.policies: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
