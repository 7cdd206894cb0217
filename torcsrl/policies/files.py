"""Policy files: reading any of them (:func:`load_policy_file`: a training checkpoint, a policy file, a run folder's
newest checkpoint, an ensemble file, a guarded ensemble file) and writing the ensemble kinds (:func:`export_ensemble`,
:func:`export_member`; one actor: :func:`~torcsrl.policies.checkpoint.export_policy`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from torcsrl.policies.base import Policy, PolicyError, file_fingerprint
from torcsrl.policies.checkpoint import CheckpointPolicy
from torcsrl.policies.ensemble import EnsemblePolicy
from torcsrl.policies.guard import SideGuard
from torcsrl.utils.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint, save_checkpoint

__all__ = ["load_policy_file", "ensemble_of_files", "export_ensemble", "export_member"]


def load_policy_file(s: str | Path, name: str | None = None) -> Policy:
    """The policy of one checkpoint or policy file (or a run folder: its newest checkpoint): :class:`CheckpointPolicy`,
    or :class:`EnsemblePolicy` for an ensemble file (:func:`export_ensemble`), behind a :class:`SideGuard` when the
    file was exported with one. :class:`PolicyError` (one line) for a missing, corrupt or unusable file."""
    path = Path(s)
    if not path.exists():
        raise PolicyError(f"policy file {str(s)!r} does not exist (a checkpoint, a policy file or a run folder)")
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


def ensemble_of_files(files: Sequence[str | Path], reduce: str = "mean") -> EnsemblePolicy:
    """The :class:`EnsemblePolicy` of single checkpoints, run folders or one-actor policy files ``files`` (what the spec
    ``a.pt+b.pt[+...][@reduce]`` loads); :class:`PolicyError` (one line) for a member that is itself an ensemble."""
    members = [load_policy_file(x) for x in files]
    for m in members:
        if isinstance(m, (EnsemblePolicy, SideGuard)):
            what = "an ensemble" if isinstance(m, EnsemblePolicy) else "a guarded ensemble"
            raise PolicyError(f"ensemble member {m.spec} is itself {what}; allowed: single checkpoints, run folders or policy files "
                              "(python -m torcsrl.policies member <file> <i> <out> writes one member)")
    return EnsemblePolicy(members, reduce=reduce or "mean")


def export_ensemble(checkpoints: list[str | Path], out: str | Path, reduce: str = "mean",
                    guard: Mapping[str, float] | None = None) -> Path:
    """Write an ensemble of checkpoints' actors (each member's weights, meta and config; no optimiser, buffer or RNG
    state) to ONE policy file that :func:`load_policy_file` (and so :func:`~torcsrl.policies.load_policy`) drives as
    :class:`EnsemblePolicy` (how a shipped driver can be an ensemble). The members are checked as the spec
    ``a.pt+b.pt@reduce`` checks them. ``guard``: :class:`SideGuard` settings (any of :attr:`SideGuard.DEFAULTS`; the
    rest default) the file drives behind."""
    ens = ensemble_of_files(checkpoints, reduce)  # the checks: 2+, one layout, a known reduce
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
