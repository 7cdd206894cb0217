"""Policies for evaluation: a checkpoint's deterministic actor, ensembles of them, the scripted drivers and teachers.

:func:`load_policy` turns a *spec* into a :class:`Policy`, a callable ``td -> td`` that writes ``"action"`` (a
TensorDictModule-like object; :meth:`CheckpointPolicy.as_module` gives the actual ``TensorDictModule``). The specs
(a checkpoint path, ``reference``, ``expert``, ``racer_safe:1.27:8:9`` or ``racer_safe(gamma=1.27,decel=8)``,
``a.pt+b.pt@medoid``, ``side_guard:<policy>``, ...) are listed in :mod:`torcsrl.policies.registry`.

Each policy says which observation keys it reads (``obs_keys``) and which env settings it needs (``env_overrides``:
sensors, camera size, action mode); the evaluator builds the env from them and calls :meth:`Policy.check_env` before
any work, so a checkpoint written for another observation layout fails with ONE line (:class:`PolicyError`).
``fingerprint`` is a hash of the policy's file bytes (or of the code of a built-in driver): report caches are keyed
by it.

The package, bottom to top (a module imports only those above it in this list):

- :mod:`~torcsrl.policies.base`: :class:`Policy`, :class:`PolicyError`, :class:`EpisodeContext`, the fingerprints;
- :mod:`~torcsrl.policies.checkpoint`: :class:`CheckpointPolicy` (one checkpoint's actor), :func:`export_policy`;
- :mod:`~torcsrl.policies.ensemble`: :class:`EnsemblePolicy`;
- :mod:`~torcsrl.policies.guard`: :class:`SideGuard`;
- :mod:`~torcsrl.policies.files`: reading any policy file or run folder, writing ensemble files;
- :mod:`~torcsrl.policies.scripted`: :class:`ExpertPolicy`, :class:`HeuristicPolicy`, :class:`RandomPolicy`;
- :mod:`~torcsrl.policies.teachers`: :class:`SensorDriver`, :class:`SensorRacer`;
- :mod:`~torcsrl.policies.registry`: the specs, :func:`load_policy`;
- :mod:`~torcsrl.policies.cli`: ``python -m torcsrl.policies export CKPT OUT`` writes a policy file (what the shipped
  reference driver is), ``... ensemble OUT A B ... --reduce cautious`` an ensemble file, ``... member FILE I OUT``
  one of its members, ``... info SPEC`` prints what a spec loads.
"""

from torcsrl.envs.traffic import sector_directions
from torcsrl.policies.base import EpisodeContext, Policy, PolicyError, code_fingerprint, file_fingerprint, state_slot
from torcsrl.policies.checkpoint import DYNAMICS_KEYS, CheckpointPolicy, export_policy, parse_layout
from torcsrl.policies.cli import main
from torcsrl.policies.ensemble import EnsemblePolicy
from torcsrl.policies.files import ensemble_of_files, export_ensemble, export_member, load_policy_file
from torcsrl.policies.guard import SideGuard, parse_guard_values
from torcsrl.policies.registry import (
    BUILTIN_POLICIES,
    GUARD_VALUES,
    NAMED_VALUES,
    RACER_SPECS,
    RACER_VALUES,
    RACER_VALUES_FORM,
    REFERENCE_CAMERA_POLICY,
    REFERENCE_POLICY,
    REFERENCE_RACER_POLICY,
    REFERENCE_PPO_POLICY,
    REFERENCE_RL_POLICY,
    SIGHT_VALUES,
    is_ensemble_spec,
    load_policy,
    racer_gains,
    sight_teacher,
    split_named_spec,
)
from torcsrl.policies.scripted import ExpertPolicy, HeuristicPolicy, RandomPolicy
from torcsrl.policies.teachers import SensorDriver, SensorRacer

__all__ = [
    "BUILTIN_POLICIES",
    "REFERENCE_CAMERA_POLICY",
    "REFERENCE_RACER_POLICY",
    "REFERENCE_POLICY",
    "REFERENCE_PPO_POLICY",
    "REFERENCE_RL_POLICY",
    "DYNAMICS_KEYS",
    "RACER_VALUES_FORM",
    "RACER_SPECS",
    "RACER_VALUES",
    "SIGHT_VALUES",
    "GUARD_VALUES",
    "NAMED_VALUES",
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
    "load_policy_file",
    "export_policy",
    "EnsemblePolicy",
    "ensemble_of_files",
    "export_ensemble",
    "export_member",
    "file_fingerprint",
    "code_fingerprint",
    "state_slot",
    "parse_layout",
    "parse_guard_values",
    "sector_directions",
    "racer_gains",
    "sight_teacher",
    "split_named_spec",
    "is_ensemble_spec",
    "main",
]
