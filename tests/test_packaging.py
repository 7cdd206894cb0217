"""A plain (non-editable) install carries the Hydra configs: ``python -m torcsrl.train`` works from a wheel."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_link_reaches_the_top_level_conf():
    from torcsrl.utils.hydra_app import CONF_DIR

    assert CONF_DIR.resolve() == (ROOT / "conf").resolve()
    assert (CONF_DIR / "train.yaml").is_file() and (CONF_DIR / "algo" / "td3.yaml").is_file()


def _can_build_wheels() -> bool:
    """setuptools >= 68 (pyproject's build requirement) and a bdist_wheel (setuptools >= 70.1 has its own)."""
    try:
        from importlib.metadata import version

        v = tuple(int(x) for x in version("setuptools").split(".")[:2])
    except Exception:
        return False
    return v >= (70, 1) or (v >= (68, 0) and importlib.util.find_spec("wheel") is not None)


@pytest.mark.skipif(not _can_build_wheels(), reason="building a wheel offline needs setuptools >= 70.1 (or >= 68 with wheel) here")
def test_wheel_install_composes_the_training_config(tmp_path):
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "dist")],
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("torcsrl-*.whl")
    site = tmp_path / "site"
    inst = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
                          capture_output=True, text=True, timeout=300)
    assert inst.returncode == 0, inst.stderr[-2000:]
    assert (site / "torcsrl" / "conf" / "train.yaml").is_file() and not (site / "torcsrl" / "conf").is_symlink()
    # from a folder outside the checkout, with the installed copy first on the path
    run = subprocess.run([sys.executable, "-m", "torcsrl.train", "--cfg", "job", "algo=ddpg"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300, env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)})
    assert run.returncode == 0, run.stderr[-2000:]
    assert "name: ddpg" in run.stdout
    where = subprocess.run([sys.executable, "-c", "import torcsrl.config as c; print(c.__file__); print(c.CONF_DIR)"], cwd=tmp_path,
                           capture_output=True, text=True, env={"PYTHONPATH": str(site)})
    assert where.stdout.splitlines()[0].startswith(str(site)), where.stdout
