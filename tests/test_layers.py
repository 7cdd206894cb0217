"""The import rules beside the layer contract (``lint-imports``, pyproject's ``[tool.importlinter]``):

- no module imports a private name (``_name``) of another module, nor a private module (``_name.py``) of another
  package;
- the layer contract itself holds (``lint-imports`` run as CI runs it).
"""

from __future__ import annotations

import ast
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "torcsrl"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _absolute(module: str, node: ast.ImportFrom, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports() -> list[str]:
    """``file:line: what`` for every import of another module's private name or another package's private module."""
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        module = _module_name(path)
        package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                src = _absolute(module, node, path.name == "__init__.py")
                if not src.startswith("torcsrl"):
                    continue
                src_parts = src.split(".")
                private_mod = [i for i, p in enumerate(src_parts) if _private(p)]
                if private_mod and ".".join(src_parts[: private_mod[0]]) != package \
                        and not package.startswith(".".join(src_parts[: private_mod[0]]) + "."):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: private module {src}")
                for alias in node.names:
                    own_submodule = (src == package or package.startswith(src + ".")) and \
                        (ROOT.joinpath(*src.split("."), alias.name + ".py").is_file() or
                         ROOT.joinpath(*src.split("."), alias.name, "__init__.py").is_file())
                    if _private(alias.name) and src != module and not own_submodule:
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {src}.{alias.name}")
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    parts = alias.name.split(".")
                    if parts[0] == "torcsrl" and any(_private(p) for p in parts):
                        first = next(i for i, p in enumerate(parts) if _private(p))
                        owner = ".".join(parts[:first])
                        if package != owner and not package.startswith(owner + "."):
                            bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: private module {alias.name}")
    return bad


def test_no_module_imports_a_private_name_of_another():
    assert private_imports() == []


def test_the_checker_sees_a_private_import(tmp_path, monkeypatch):
    """The check itself can fail: a module importing another's private name is reported."""
    pkg = tmp_path / "torcsrl"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from torcsrl.sub._impl import thing\n")  # its own package: allowed
    (pkg / "sub" / "_impl.py").write_text("thing = 1\n_hidden = 2\n")
    (pkg / "other.py").write_text("from torcsrl.sub._impl import _hidden\nfrom .sub import thing\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    monkeypatch.setattr(__import__(__name__), "PKG", pkg)
    assert private_imports() == ["torcsrl/other.py:1: private module torcsrl.sub._impl",
                                 "torcsrl/other.py:1: torcsrl.sub._impl._hidden"]


@pytest.mark.skipif(shutil.which("lint-imports") is None, reason="import-linter is part of the dev extra")
def test_the_layer_contract_holds():
    proc = subprocess.run(["lint-imports"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:]
