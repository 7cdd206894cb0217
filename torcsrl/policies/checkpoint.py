"""The deterministic actor of one torcsrl checkpoint as a policy (:class:`CheckpointPolicy`), and the policy file
:func:`export_policy` writes from a training checkpoint (actor weights, meta and config: what the shipped drivers
are)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule

from torcsrl.policies.base import EpisodeContext, Policy, PolicyError, file_fingerprint
from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

__all__ = ["DYNAMICS_KEYS", "CheckpointPolicy", "export_policy", "parse_layout"]

#: Env settings a trained policy is bound to (they define its control problem); evaluation uses the
#: checkpoint's values: control rate, physics substeps, car, rangefinder beams.
DYNAMICS_KEYS = ("control_hz", "substeps", "vehicle", "vehicle_overrides", "rangefinder_angles_deg", "rangefinder_range_m")


def parse_layout(layout: str) -> dict[str, tuple[int, ...]]:
    """A checkpoint's ``obs_layout`` (``"rangefinder:19,pixels:3x64x96"``) as ``{key: shape}``."""
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
        # deferred: omegaconf, torchrl, the agents and the transforms (heavy) only once a checkpoint is read
        from omegaconf import OmegaConf
        from torchrl.data import Bounded, Composite, Unbounded

        from torcsrl import agents
        from torcsrl.transforms import HISTORY_KEYS, IMAGE_KEYS, obs_scale

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
            layout = parse_layout(meta["obs_layout"])
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
            from torcsrl.transforms import stack_frames  # deferred: torchrl (heavy), as in __init__

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


def export_policy(checkpoint: str | Path, out: str | Path) -> Path:
    """Write the deterministic actor of ``checkpoint`` (weights, meta, config; no optimiser,
    buffer or RNG state) to ``out`` — the format of the shipped reference driver."""
    pol = CheckpointPolicy(checkpoint)
    meta = {k: v for k, v in pol.meta.items() if k not in ("format", "version")}
    meta.update(kind="policy", source=Path(checkpoint).name)
    return save_checkpoint(out, {"meta": meta, "actor": pol.actor.state_dict(), "config": pol.config_yaml})
