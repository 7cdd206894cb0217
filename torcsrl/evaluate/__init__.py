"""Time trials: a deterministic policy drives N laps per track; tables, JSON, CSV and pictures.

``python -m torcsrl.evaluate --policy SPEC --track set:heldout [--surface asphalt dirt] [--laps 10]``

For every track (and surface) the policy (:func:`torcsrl.policies.load_policy`: a checkpoint,
``reference``, ``expert``, ``sensor``, ``heuristic`` or ``random``) drives ``episodes`` episodes of ``laps``
laps (the env's ``lap_limit``: the episode ends, truncated, after the last lap; leaving the track,
driving backwards, stalling or flipping terminates it). Starts are seeded: episode ``e`` of
track ``t`` on surface ``u`` resets the env with ``seed_for(seed, "env", t, u, e)`` (the grid
start is the same every time; ``--start random`` draws the arc length from that seed). With a
degradation, its draws come from ``seed_for(seed, "degradation", name, severity, e)``, the same
for every policy (common random numbers).

Per track it reports (Summers 2022, Tables 7.1/7.2): laps completed of N, success (all N laps
without termination), fastest and mean lap [s] (mean over the flying laps 2..N), mean speed
[km/h] (distance / time), off-track events, steering oscillation (mean |delta steer| per step and
sign flips per km), the return, and the fastest lap relative to the scripted expert's fastest
lap and to the physical-limit lap time (:func:`torcsrl.envs.expert.limit_lap_time`).

Outputs (``out_dir``): ``evaluation.json`` (config, per-track summary, every episode),
``evaluation.csv`` (per track), ``episodes.csv``, ``evaluation.md`` (the table), one
``trajectory_<track>_<surface>.png`` per track (top-down path coloured by speed), and
``camera_<track>_<surface>.gif`` when the policy observes pixels.

Bookkeeping reads only the env's outputs: ``info`` (lap, lap times, distances) and the clean
``state`` (kept aside as ``state_clean`` before any degradation), never a degraded reading.

The package: :mod:`~torcsrl.evaluate.spec` (what an evaluation runs: the grid, degradations, seeds and step caps,
checked before anything heavy loads), :mod:`~torcsrl.evaluate.protocol` (the episode protocol: lap accounting,
termination reasons; one car), :mod:`~torcsrl.evaluate.batched` (many episodes as cars of one batched env, equal
episode for episode to the one-car path), :mod:`~torcsrl.evaluate.trial` (time trials) and
:mod:`~torcsrl.evaluate.race` (races), :mod:`~torcsrl.evaluate.workers` (worker processes),
:mod:`~torcsrl.evaluate.results` (summaries, tables, JSON / CSV, reading results back),
:mod:`~torcsrl.evaluate.plots` (trajectories, GIFs) and :mod:`~torcsrl.evaluate.app` (the app).

The names below load their module on first use: ``import torcsrl.evaluate`` (and ``--help``) loads neither torch
nor pybullet.
"""

from torcsrl.utils.lazy import lazy_exports

__all__ = [
    "Degradation",
    "EpisodeBook",
    "EvalError",
    "PROTOCOL_VERSION",
    "evaluate",
    "run_cell",
    "run_episode",
    "seed_for",
    "parse_degradation",
    "validate_grid",
    "expert_reference",
    "plot_trajectory",
    "summary_table",
    "main",
]

#: Each name of the package and the module that defines it.
_HOMES = {
    **dict.fromkeys(("PROTOCOL_VERSION", "Degradation", "EvalError", "default_max_steps", "parse_degradation", "seed_for",
                     "validate_grid"), "spec"),
    **dict.fromkeys(("EpisodeBook", "check_policy_env", "env_sensors", "expert_reference", "make_cell_env", "run_cell",
                     "run_episode"), "protocol"),
    **dict.fromkeys(("markdown_table", "read_evaluations", "summarise_track", "summary_table", "write_csv", "write_json"),
                    "results"),
    **dict.fromkeys(("plot_trajectory", "write_gif"), "plots"),
    "evaluate": "trial",
    "map_tasks": "workers",
    "main": "app",
}
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
