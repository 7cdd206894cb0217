"""The project's Hydra configs composed for tests: one helper for every test file (``tests/conftest.py`` puts this
folder on ``sys.path``, so ``from _compose import compose_config`` works from the sub-folders too)."""

from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir

CONF = str(Path(__file__).resolve().parents[1] / "conf")


def compose_config(*overrides: str, name: str = "train", hydra: bool = False):
    """``conf/<name>.yaml`` composed with ``overrides`` (as the command line gives them); ``hydra=True`` keeps the
    ``hydra`` node (``return_hydra_config``)."""
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(name, overrides=list(overrides), return_hydra_config=hydra)
