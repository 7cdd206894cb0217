"""The evaluate app: time trials of a policy over tracks x surfaces, written as JSON, CSV, Markdown and PNG.

The app checks its arguments (:func:`check_config`) before it loads the episode machinery (torch, TorchRL and pybullet,
through :mod:`~torcsrl.evaluate.trial` and :mod:`~torcsrl.evaluate.race`): ``--help`` and a bad argument answer at once.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torcsrl.evaluate.spec import Degradation, EvalError, parse_degradation
from torcsrl.utils.faults import cli_error, graceful_termination
from torcsrl.utils.hydra_app import AppError, check_keys, compose, flags_to_overrides, is_multirun, run_multirun

__all__ = ["FLAGS", "TYPES", "check_config", "run_config", "run_checked", "main", "one_torch_thread", "policy_errors"]

#: The flags of earlier versions, aliases of the config's keys (conf/evaluate.yaml).
FLAGS = {"--policy": ("policy", "one"), "--track": ("tracks", "many"), "--tracks": ("tracks", "many"),
         "--surface": ("surfaces", "many"), "--surfaces": ("surfaces", "many"), "--laps": ("laps", "one"),
         "--episodes": ("episodes", "one"), "--seed": ("seed", "one"), "--degradation": ("corruption", "one"),
         "--severity": ("severity", "one"), "--max-steps": ("max_steps", "one"), "--start": ("start", "one"),
         "--expert-laps": ("expert_laps", "one"), "--no-plots": ("plots", "false"), "--workers": ("workers", "one"),
         "--out": ("out", "one"), "--mode": ("mode", "one"), "--opponents": ("opponents", "one"), "--pace": ("pace", "one"),
         "--side-gap": ("side_gap_m", "one")}
#: Types of the config's values (checked before anything runs).
TYPES = {"policy": (str,), "tracks": (str, list), "surfaces": (str, list, type(None)), "laps": (int,), "episodes": (int,),
         "seed": (int,), "corruption": (str, type(None)), "severity": (int, type(None)), "max_steps": (int, type(None)),
         "start": (str,), "expert_laps": (int,), "plots": (bool,), "workers": (int,), "out": (str, type(None)),
         "mode": (str,), "opponents": (int,), "pace": (float, int, list), "side_gap_m": (float, int)}


def policy_errors() -> tuple[type[Exception], ...]:
    """``(PolicyError,)`` once :mod:`torcsrl.policies` is loaded, else ``()`` (nothing raises it before): what the apps
    catch besides their own errors, without loading the policies (and torch) for a bad argument."""
    err = getattr(sys.modules.get("torcsrl.policies"), "PolicyError", None)
    return (err,) if err is not None else ()


def check_config(cfg: Any) -> tuple[dict[str, Any], Degradation | None]:
    """(settings, degradation or None) of a composed ``conf/evaluate.yaml``, checked before anything runs: unknown
    keys, types, start, the degradation's name and severity, mode; EvalError (one line) otherwise."""
    try:
        c = check_keys(cfg, "evaluate", TYPES)
    except AppError as err:
        raise EvalError(str(err)) from None
    if c["start"] not in ("grid", "random"):
        raise EvalError(f"start must be grid or random, got {c['start']!r}")
    deg = parse_degradation(c["corruption"], c["severity"]) if c["corruption"] else None
    if not c["corruption"] and c["severity"] not in (None, 0):
        raise EvalError(f"severity={c['severity']} needs a degradation (corruption=<name>, --degradation <name>)")
    if c["mode"] not in ("trial", "race"):
        raise EvalError(f"mode must be trial or race, got {c['mode']!r}")
    if c["mode"] == "race" and deg is not None:
        raise EvalError("mode=race drives clean sensors; allowed: corruption=null with mode=race")
    return c, deg


def run_config(cfg: Any, out: str | Path | None = None, verbose: bool = True) -> dict[str, Any]:
    """:func:`~torcsrl.evaluate.trial.evaluate` (or, ``mode=race``, :func:`~torcsrl.evaluate.race.evaluate_race`)
    from a composed ``conf/evaluate.yaml``, checked first (:func:`check_config`); ``out`` (a multirun's job folder)
    wins over ``cfg.out``."""
    c, deg = check_config(cfg)
    return run_checked(c, deg, out, verbose)


def run_checked(c: dict[str, Any], deg: Degradation | None, out: str | Path | None = None,
                verbose: bool = True) -> dict[str, Any]:
    """:func:`run_config` from settings :func:`check_config` has passed."""
    # deferred: the episode machinery (policies, torch, TorchRL, pybullet) loads once the arguments are checked
    from torcsrl.evaluate import race, trial
    from torcsrl.policies import is_ensemble_spec

    spec = str(c["policy"])  # an ensemble spec (a.pt+b.pt@reduce) is named after its member count, as EnsemblePolicy
    name = f"ensemble{spec.count('+') + 1}" if is_ensemble_spec(spec) else Path(spec).stem
    out = out or c["out"] or str(Path("outputs") / "evaluate" / name / time.strftime("%Y-%m-%d_%H-%M-%S"))
    if c["mode"] == "race":
        return race.evaluate_race(c["policy"], c["tracks"], c["surfaces"], laps=c["laps"], seed=c["seed"], out_dir=out,
                                  episodes=c["episodes"], opponents=c["opponents"], pace=c["pace"],
                                  env_kwargs={"start": c["start"]}, max_steps=c["max_steps"], plots=c["plots"],
                                  verbose=verbose, workers=c["workers"], side_gap_m=c["side_gap_m"])
    return trial.evaluate(c["policy"], c["tracks"], c["surfaces"], laps=c["laps"], seed=c["seed"], out_dir=out,
                          degradation=deg, episodes=c["episodes"], max_steps=c["max_steps"], env_kwargs={"start": c["start"]},
                          expert_laps=c["expert_laps"], plots=c["plots"], workers=c["workers"], verbose=verbose)


def one_torch_thread() -> None:
    """One torch thread for this process (an app's episodes run in worker processes or one after another)."""
    import torch  # deferred: torch loads after the arguments are checked

    torch.set_num_threads(1)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torcsrl.evaluate [key=value ...] [--flag value ...] [-m]`` (see conf/evaluate.yaml)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__.split("\n\n")[0] + "\n\nusage: python -m torcsrl.evaluate [key=value ...] [-m]; keys and defaults: "
              "conf/evaluate.yaml; flags: " + " ".join(FLAGS))
        return 0
    try:
        overrides = flags_to_overrides(argv, FLAGS)
        if is_multirun(overrides):
            return run_multirun("evaluate", overrides, _multirun_job, "torcsrl.evaluate")
        c, deg = check_config(compose("evaluate", overrides))
        one_torch_thread()
        with graceful_termination():
            res = run_checked(c, deg)
    except (EvalError, *policy_errors(), AppError, OSError, KeyboardInterrupt) as err:
        return cli_error("torcsrl.evaluate", err, stopped="its worker processes were stopped (run it again for the full evaluation)")
    out = Path(res["files"][0]).parent
    print((out / ("race.md" if (out / "race.md").exists() and not (out / "evaluation.md").exists() else "evaluation.md")).read_text())
    print(f"evaluation: {out}")
    return 0


def _multirun_job(cfg: Any, job_dir: Path) -> None:
    """One job of ``python -m torcsrl.evaluate -m ...``: its outputs in its own Hydra job folder."""
    try:
        c, deg = check_config(cfg)
        one_torch_thread()
        with graceful_termination():
            run_checked(c, deg, out=job_dir)
    except (EvalError, *policy_errors(), OSError) as err:
        sys.exit(cli_error("torcsrl.evaluate", err))


if __name__ == "__main__":
    sys.exit(main())
