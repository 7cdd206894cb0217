"""``python -m torcsrl.policies``: the command line (:func:`torcsrl.policies.cli.main`)."""

import sys

from torcsrl.policies.cli import main

if __name__ == "__main__":
    sys.exit(main())
