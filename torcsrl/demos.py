"""Write expert demonstrations: ``python -m torcsrl.demos [train overrides] demos.frames=50000 [demos.out=DIR]``.

The Hydra entry of :func:`torcsrl.training.demos.write_demos`: the training config (``conf/train.yaml``) is composed
and checked (:func:`torcsrl.config.validate`), and the config's teacher drives its env into ``demos.out`` (default
``outputs/demos/<time>``). Bad input ends with one line ``torcsrl.demos: error: ...`` (exit 2).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch
from omegaconf import DictConfig

from torcsrl.config import validate
from torcsrl.training.demos import write_demos

__all__ = ["main"]


def main() -> None:
    import hydra  # Hydra's app machinery only for the command line

    @hydra.main(config_path="conf", config_name="train", version_base="1.3")
    def _main(cfg: DictConfig) -> None:
        try:
            validate(cfg)
            out = cfg.demos.out or str(Path("outputs") / "demos" / time.strftime("%Y-%m-%d_%H-%M-%S"))
            torch.set_num_threads(1)
            write_demos(cfg, out)
            print(f"[torcsrl.demos] train on them: python -m torcsrl.train demos.path={out} ...", file=sys.stderr)
        except ValueError as err:
            print(f"torcsrl.demos: error: {err}", file=sys.stderr)
            sys.exit(2)

    _main()


if __name__ == "__main__":
    main()
