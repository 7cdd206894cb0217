"""torcsrl.policies.base and the package's shape: the fingerprints, the policy's env check, every name the package
exports, and the layers (each module imports only those below it; the env layer imports no policies)."""

from __future__ import annotations

import ast
import hashlib
import inspect
from pathlib import Path

import pytest

import torcsrl
from torcsrl.envs.sensors import STATE_SLOTS
from torcsrl.policies import PolicyError, RandomPolicy, code_fingerprint, file_fingerprint, load_policy, state_slot

PACKAGE = Path(torcsrl.__file__).resolve().parent
#: The modules of torcsrl.policies, bottom to top: a module imports only modules before it.
LAYERS = ("base", "checkpoint", "ensemble", "guard", "files", "scripted", "teachers", "registry", "cli", "__main__", "__init__")
#: What ``from torcsrl.policies import ...`` gave before the package was split (and still gives).
EXPORTED = ("BUILTIN_POLICIES", "CheckpointPolicy", "DYNAMICS_KEYS", "EnsemblePolicy", "EpisodeContext", "ExpertPolicy",
            "HeuristicPolicy", "Policy", "PolicyError", "RACER_SPECS", "RACER_VALUES_FORM", "REFERENCE_CAMERA_POLICY",
            "REFERENCE_POLICY", "REFERENCE_RACER_POLICY", "REFERENCE_RL_POLICY", "RandomPolicy", "SensorDriver", "SensorRacer",
            "SideGuard", "export_ensemble", "export_member", "export_policy", "file_fingerprint", "is_ensemble_spec",
            "load_policy", "main", "parse_guard_values", "racer_gains", "sector_directions")


def test_fingerprints_hash_the_file_bytes_and_the_drivers_code(tmp_path):
    f = tmp_path / "x.bin"
    f.write_bytes(b"torcsrl" * 1000)
    assert file_fingerprint(f) == hashlib.sha256(b"torcsrl" * 1000).hexdigest()
    assert code_fingerprint(RandomPolicy) == hashlib.sha256(inspect.getsource(RandomPolicy).encode()).hexdigest()
    assert load_policy("random").fingerprint == code_fingerprint(RandomPolicy)
    assert code_fingerprint("not code") == hashlib.sha256(b"'not code'").hexdigest()  # no source: its repr
    assert state_slot("trackPos") == STATE_SLOTS.index("trackPos")


def test_check_env_names_what_the_env_lacks_in_one_line():
    from torcsrl.envs import make_env

    pol = load_policy("racer")  # reads rangefinder, state and opponents
    env = make_env(track="oval", sensors=("rangefinder", "state"), control_hz=10, substeps=20)
    try:
        with pytest.raises(PolicyError, match=r"policy 'racer' reads \['opponents'\], which the env does not produce") as err:
            pol.check_env(env)
        assert "\n" not in str(err.value)
        load_policy("sensor").check_env(env)  # fits
        assert load_policy("sensor").layout_hint() == "rangefinder:19"
    finally:
        env.close()


def test_every_name_the_module_exported_still_imports():
    import torcsrl.policies as P

    missing = [n for n in EXPORTED if not hasattr(P, n)]
    assert not missing
    assert set(P.__all__) <= set(dir(P)) and not [n for n in P.__all__ if n.startswith("_")]


def _imports(path: Path) -> list[tuple[str, list[str], bool]]:
    """(module, names, at module level) of every ``import`` / ``from ... import`` in ``path``."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom) and n.module:
            out.append((n.module, [a.name for a in n.names], id(n) in top))
        elif isinstance(n, ast.Import):
            out.extend((a.name, [], id(n) in top) for a in n.names)
    return out


def test_the_package_imports_in_one_direction_and_no_private_names():
    mods = sorted(p.stem for p in (PACKAGE / "policies").glob("*.py"))
    assert sorted(LAYERS) == mods, "a new module of torcsrl.policies: give it its place in LAYERS"
    for name in LAYERS:
        for mod, names, _ in _imports(PACKAGE / "policies" / f"{name}.py"):
            if mod.startswith("torcsrl.policies."):
                below = mod.split(".")[2]
                assert LAYERS.index(below) < LAYERS.index(name), f"torcsrl.policies.{name} imports {mod}, a module above it"
            if mod.startswith("torcsrl"):
                assert mod != "torcsrl.policies", f"torcsrl.policies.{name} imports the package itself"
                private = [n for n in names if n.startswith("_") and n != "__version__"]
                assert not private, f"torcsrl.policies.{name} imports {private} from {mod}"


def test_the_env_layer_imports_no_policies():
    for path in sorted((PACKAGE / "envs").rglob("*.py")):
        for mod, _, _ in _imports(path):
            assert not mod.startswith("torcsrl.policies"), f"{path.relative_to(PACKAGE)} imports {mod}"
        assert "torcsrl.policies import" not in path.read_text(), path
