"""Train a racing driver: ``python -m torcsrl.train [algo=td3|ddpg|d4pg|sac|ppo|bc|dagger] [env=race|toy] [overrides]``.

The Hydra entry: it checks the config (:func:`torcsrl.config.validate`), holds the run folder, writes the run
records (``config.yaml``, ``git_rev.txt``, ``metrics.json``) and runs :func:`torcsrl.training.train`, which dispatches
on ``algo`` to :mod:`torcsrl.training.offpolicy`, :mod:`~torcsrl.training.onpolicy` or
:mod:`~torcsrl.training.imitation`. Bad input ends the run with one line ``torcsrl.train: error: ...`` (exit 2);
Ctrl-C or SIGTERM stops the collector's workers and prints the command that resumes the run. The value a sweeper
(Optuna) optimises is ``optimized_metric`` of the final metrics.
"""

from __future__ import annotations

import sys

from typing import Any

from torcsrl.utils.faults import cli_error

__all__ = ["main_entry"]


def main_entry() -> None:
    import hydra  # Hydra's app machinery only for the command line

    @hydra.main(config_path="conf", config_name="train", version_base="1.3")  # torcsrl/conf -> conf/ (torcsrl.utils.hydra_app.CONF_DIR)
    def main(cfg: Any) -> float | None:
        # deferred: the training stack (torch, torchrl, pybullet: ~10 s) loads after Hydra has composed the config, so
        # --help and an unknown group option or key answer at once
        from torcsrl.config import objective, save_run_info, validate, write_metrics
        from torcsrl.training import train
        from torcsrl.training.common import resolve_run_dir, resume_command
        from torcsrl.utils.checkpoint import CheckpointError, latest_checkpoint
        from torcsrl.utils.faults import claim_run_dir, graceful_termination

        run_dir = None
        try:
            with graceful_termination():  # SIGTERM as Ctrl-C: train's finally blocks stop the collector's workers
                validate(cfg)  # unknown keys, wrong types, unknown names, severities: before anything is built (train checks too)
                run_dir = resolve_run_dir(cfg)
                with claim_run_dir(run_dir, resume=bool(cfg.checkpoint.resume), overwrite=bool(cfg.overwrite)):  # before config.yaml
                    save_run_info(cfg, run_dir)  # config.yaml (resolved) + git_rev.txt
                    result = train(cfg)
                    write_metrics(run_dir, result)  # metrics.json, read by python -m torcsrl.sweep
                return objective(result, cfg.get("optimized_metric"))  # the value a sweeper (Optuna) optimises
        except (CheckpointError, ValueError, RuntimeError) as err:
            if isinstance(err, RuntimeError) and not isinstance(err, CheckpointError) and "cannot be imported" not in str(err):
                raise
            sys.exit(cli_error("torcsrl.train", err))
        except OSError as err:
            sys.exit(cli_error("torcsrl.train", err))
        except KeyboardInterrupt as err:
            last = latest_checkpoint(run_dir / "checkpoints") if run_dir is not None else None
            resume = (f"; last checkpoint {last}; resume: {resume_command(run_dir)}"
                      if last else "; no checkpoint was written yet")
            sys.exit(cli_error("torcsrl.train", err, stopped=f"workers stopped{resume}"))

    main()


if __name__ == "__main__":
    main_entry()
