"""Scripted reference driver and the physical lap-time limit.

* :func:`racing_line`: a minimum-curvature line inside the track (squared curvature linearised in
  the centreline's Frenet frame: a bound-constrained quadratic programme, solved by projected
  Newton steps), optionally traded against length, or the centreline.
* :func:`speed_profile`: quasi-steady-state point-mass speed along a line: the cornering limit
  ``v^2 |kappa| m = mu (m g + downforce)``, then a forward pass (acceleration limited by the
  friction circle, the engine's peak wheel power, drag and rolling resistance) and a backward pass
  (braking limited by the friction circle, helped by drag and rolling resistance), both around
  the closed loop.
* :func:`limit_lap_time`: the "physical limit" — the flying-lap time of that point mass (same
  mass, mu, power, drag, downforce as the car; all four tyres' grip available for driving and
  braking) on the fastest of the centreline and a few lines between minimum curvature and
  minimum length. Quasi-steady state, so a reference rather than a strict bound (the true
  minimum-time line differs a little, and transients are ignored).
* :class:`ExpertDriver`: Stanley-style path tracking (curvature feed-forward, heading and
  cross-track feedback, the heading measured against the front axle's filtered slip angle) on the
  minimum-curvature line plus a speed controller that feeds the profile's acceleration forward
  through a model of the engine and brakes, on a derated profile (``mu_margin`` of the grip,
  driven-axle traction that also holds the speed in bends, gentle braking in bends), with a
  TORCS-robot-style traction-control throttle filter. It reads only what the car exposes (pose,
  velocities, wheel spin) and works at any control rate (the training env's 10 Hz or 50 Hz).
* CLI: ``python -m torcsrl.envs.expert --track NAME --surface dirt --laps 10 [--control-hz 10]
  [--plot out.png]`` drives a fleet of one on a ground plane, with the surface under each wheel
  from the track, and prints lap times beside the limit and the rate they were driven at;
  ``--all`` prints the table for every bundled track on asphalt and dirt.
  ``benchmarks/expert_sweep.py`` drives it on hundreds of generated tracks.

Modules: :mod:`~torcsrl.envs.expert.line`, :mod:`~torcsrl.envs.expert.profile` (speed profile, limit lap time),
:mod:`~torcsrl.envs.expert.driver` (:class:`ExpertDriver`, :func:`drive`), :mod:`~torcsrl.envs.expert.cli`
(``python -m torcsrl.envs.expert``).
"""

from __future__ import annotations

from torcsrl.envs.expert.cli import main, plot_run
from torcsrl.envs.expert.driver import DriveResult, ExpertDriver, default_substeps, drive
from torcsrl.envs.expert.line import LINES, RacingLine, racing_line
from torcsrl.envs.expert.profile import G, LIMIT_LENGTH_WEIGHTS, limit_lap_time, speed_profile

__all__ = [
    "RacingLine",
    "racing_line",
    "speed_profile",
    "limit_lap_time",
    "ExpertDriver",
    "DriveResult",
    "drive",
    "default_substeps",
    "main",
    "plot_run",
    "LINES",
    "LIMIT_LENGTH_WEIGHTS",
    "G",
]
