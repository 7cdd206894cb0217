"""Entry points as Hydra apps that keep their short flags: ``evaluate`` and ``report``.

``python -m torcsrl.<app> [key=value ...] [--flag value ...]`` composes ``conf/<app>.yaml`` with the
overrides (Hydra's grammar: ``track=[kidney,alpine]``, ``+key=...`` is refused by the app's check)
and runs the app in this process, writing where ``out`` says (default: a time-stamped folder under
``outputs/<app>/``). The argparse-style flags users typed before (``--policy X --track a b``) are
aliases: :func:`flags_to_overrides` turns each into its override, so both spellings can be mixed.

``-m`` / ``--multirun`` hands the same overrides to Hydra's own ``@hydra.main``: sweeps
(``track=kidney,alpine degradation=rangefinder.fog,state.latency``) run on the configured launcher
(``hydra/launcher=parallel`` joblib, ``slurm`` submitit, ``ray_local`` Ray), each job writing into
its own Hydra job folder; ``python -m torcsrl.report --from-dir <sweep folder>`` reads them all.

Bad input fails before any work with ONE line ``torcsrl.<app>: error: ...`` (exit status 2): an
unknown key or flag, a value of the wrong type, and everything the app itself checks.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["CONF_DIR", "AppError", "flags_to_overrides", "compose", "check_keys", "is_multirun", "run_multirun"]

#: The Hydra config tree: ``conf/`` at the top of the repository, reached through the package's
#: ``torcsrl/conf`` link (a wheel holds a copy there), so ``python -m torcsrl.train`` finds it in a
#: checkout, an editable install and a plain ``pip install`` alike.
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


class AppError(ValueError):
    """Bad command line or config for an app (one line)."""


def _quote(v: str) -> str:
    if re.fullmatch(r"-?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?", v) or v in ("null", "true", "false"):  # numbers stay numbers
        return v
    return "'" + v.replace("\\", "\\\\").replace("'", "\\'") + "'"


def flags_to_overrides(argv: Sequence[str], flags: Mapping[str, tuple[str, str]]) -> list[str]:
    """Hydra overrides from a command line mixing ``key=value`` overrides and the app's flags.

    ``flags``: ``{"--flag": (key, kind)}``, kind ``one`` (one value), ``many`` (one or more: a list),
    ``true`` / ``false`` (a switch setting the key). ``--flag=value`` works too. Anything else passes
    through as an override (``-m`` / ``--multirun`` included).
    """
    out: list[str] = []
    i = 0
    argv = list(argv)
    while i < len(argv):
        a = argv[i]
        if not a.startswith("--") or a == "--multirun":
            if a not in ("-m", "--multirun") and "=" not in a:
                raise AppError(f"unexpected argument {a!r}; overrides are key=value (keys: conf/*.yaml), flags --name value")
            out.append(a)
            i += 1
            continue
        name, eq, val = a.partition("=")
        if name not in flags:
            known = " ".join(sorted(flags))
            raise AppError(f"unknown flag {name}; flags: {known}; or key=value overrides of the config")
        key, kind = flags[name]
        i += 1
        if kind in ("true", "false"):
            if eq:
                raise AppError(f"{name} takes no value")
            out.append(f"{key}={kind}")
            continue
        vals = [val] if eq else []
        while i < len(argv) and not eq and not argv[i].startswith("--") and (kind == "many" or not vals):
            if vals and re.fullmatch(r"[+~]?[A-Za-z_][\w.]*=.*", argv[i]):  # the next override starts
                break
            vals.append(argv[i])
            i += 1
        if not vals:
            raise AppError(f"{name} needs a value")
        out.append(f"{key}={_quote(vals[0])}" if kind == "one" else f"{key}=[{','.join(_quote(v) for v in vals)}]")
    return out


def is_multirun(overrides: Sequence[str]) -> bool:
    return any(o in ("-m", "--multirun") for o in overrides)


def compose(config_name: str, overrides: Sequence[str]):
    """``conf/<config_name>.yaml`` composed with ``overrides`` (AppError, one line, when Hydra refuses)."""
    # deferred: Hydra and OmegaConf (~0.3 s) load when a config is composed, not for --help
    from hydra import compose as _compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name=config_name):
            return _compose(config_name=config_name, overrides=list(overrides))
    except (HydraException, OmegaConfBaseException, ValueError) as err:
        lines = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
        raise AppError("; ".join(dict.fromkeys(lines[:1] + lines[-1:])) or type(err).__name__) from None


def check_keys(cfg: Any, config_name: str, types: Mapping[str, tuple[type, ...]] | None = None) -> dict[str, Any]:
    """The app config as a plain dict (``hydra`` left out), checked against ``conf/<config_name>.yaml``:
    an unknown key (``+key=...``) and a value of the wrong type (``types``) are AppErrors naming the key
    and what is allowed. Nothing is listed twice: the known keys are the YAML's own."""
    from omegaconf import OmegaConf  # deferred: see compose

    d = OmegaConf.to_container(cfg, resolve=True)
    d.pop("hydra", None)
    ref = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / f"{config_name}.yaml"), resolve=False)
    known = sorted(k for k in ref if k not in ("defaults", "hydra"))
    bad = sorted(set(d) - set(known))
    if bad:
        raise AppError(f"unknown key(s) {bad} in the {config_name} config; known: {', '.join(known)}")
    for key, allowed in (types or {}).items():
        v = d.get(key)
        if v is None and type(None) in allowed:
            continue
        if isinstance(v, bool) and bool not in allowed:
            ok = False
        else:
            ok = isinstance(v, allowed)
        if not ok:
            names = "/".join("null" if t is type(None) else t.__name__ for t in allowed)
            raise AppError(f"{key} must be {names}, got {v!r}")
    return d


def run_multirun(config_name: str, overrides: Sequence[str], job: Callable[[Any, Path], Any], prog: str) -> int:
    """Run ``job(cfg, job_folder)`` for every job of a Hydra multirun of ``conf/<config_name>.yaml``
    (``@hydra.main``: sweeps and launchers). A job's bad input ends it with one line (exit 2)."""
    # deferred: see compose
    import hydra
    from hydra.core.hydra_config import HydraConfig

    @hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base="1.3")
    def _main(cfg) -> Any:
        return job(cfg, Path(HydraConfig.get().runtime.output_dir))

    argv = sys.argv
    sys.argv = [prog, *overrides]
    try:
        _main()
    finally:
        sys.argv = argv
    return 0
