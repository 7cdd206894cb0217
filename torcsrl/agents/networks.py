"""Moved to :mod:`torcsrl.nets` (below both agents/ and objectives/); this name stays for existing imports."""

from torcsrl.nets import *  # noqa: F401,F403
from torcsrl.nets import __all__  # noqa: F401
