"""``python -m torcsrl.envs.expert``: :func:`torcsrl.envs.expert.cli.main`; a bad track, surface or vehicle name
ends in one line on stderr (exit status 2)."""

from __future__ import annotations

import sys

from torcsrl.envs.expert.cli import main

if __name__ == "__main__":
    try:
        sys.exit(main())
    except ValueError as exc:  # bad track / surface / vehicle name: one clear line
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
