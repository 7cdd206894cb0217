"""``python -m torcsrl.evaluate``: see :mod:`torcsrl.evaluate.app`."""

import sys

from torcsrl.evaluate.app import main

if __name__ == "__main__":
    sys.exit(main())
