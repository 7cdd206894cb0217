"""``python -m torcsrl.report``: see :mod:`torcsrl.report.app`."""

import sys

from torcsrl.report.app import main

if __name__ == "__main__":
    sys.exit(main())
