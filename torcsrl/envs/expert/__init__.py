"""Scripted reference driver and the physical lap-time limit (:mod:`torcsrl.envs.expert.driver`)."""

from __future__ import annotations

from torcsrl.envs.expert.driver import *  # noqa: F401,F403
from torcsrl.envs.expert.driver import G, LIMIT_LENGTH_WEIGHTS, LINES, plot_run  # noqa: F401
