"""The race simulation core and its gymnasium face (:mod:`torcsrl.envs.race.core`)."""

from __future__ import annotations

from torcsrl.envs.race.core import *  # noqa: F401,F403
