"""Degradation robustness reports: policies × tracks × degradations × severities 0..5.

``python -m torcsrl.report`` (no arguments) drives the shipped reference driver
(:data:`torcsrl.policies.REFERENCE_POLICY`; the scripted expert until it ships) on 2 held-out
tracks × 4 degradations × severities 0, 1, 3, 5 × 1 episode of 1 lap: a few minutes on a laptop.

``python -m torcsrl.report --policy A.pt B.pt --reference A.pt --tracks set:heldout
--degradations rangefinder.fog state.latency --severities 0 1 2 3 4 5 --episodes 5 --workers 8``

Every cell (policy, track, surface, degradation, severity) runs ``episodes`` episodes of ``laps``
laps with :func:`torcsrl.evaluate.run_cell`: episode ``e`` starts from the env seed
``seed_for(seed, "env", track, surface, e)`` and its degradation draws come from
``seed_for(seed, "degradation", name, severity, e)`` — the same for every policy (common random
numbers), so differences between policies are not weather luck. Severity 0 (the clean run) is
one cell per (policy, track, surface), shared by every degradation. The uniform random policy's
clean cells give R_random for the normalised return. A degradation that touches none of a
policy's observation keys cannot change its driving: that policy's clean episodes stand in for
those cells (flagged ``reused_clean``).

Cells run in parallel processes (``--workers``), or as Ray tasks on a local Ray instance or a
cluster (``ray=local|auto|host:port``, :mod:`torcsrl.utils.ray_session`), and each is cached as one JSON file in
``<out>/cells/`` (or ``--cache``), named by a hash of the policy's bytes, the cell and the
config: an interrupted report re-run with the same folder skips the cells already done, and a
changed policy file or config (laps, episodes, seed, step cap, env settings) recomputes them.

Outputs (``--out``): ``robustness.json`` (config, config hash, every cell with its seeds, the
metrics), ``robustness.csv`` (one row per episode), ``robustness_summary.csv`` (per policy ×
degradation × severity), ``REPORT.md`` and a self-contained ``report.html`` (a summary line,
a leaderboard, per-degradation tables grouped by sensor and effect, the plots inline),
``nr_heatmap.png`` (NR over degradation × severity, one panel per policy) and
``severity_curves.png`` (NR against severity per degradation, one line per policy, 95 % bands).
Metric definitions: :mod:`torcsrl.metrics`.

``--from-dir DIR`` builds the report from results already on disk instead: every
``evaluation.json`` under DIR (e.g. the jobs of a Hydra multirun of ``torcsrl.evaluate``, one
per track/degradation/severity) and every cached cell JSON.

The package: :mod:`~torcsrl.report.grid` (the config, the cells, the checks of the counts),
:mod:`~torcsrl.report.runner` (running the cells: batched as cars of one env per policy and track, cached, in worker
processes or Ray tasks), :mod:`~torcsrl.report.results` (reading rows back, the metrics and the files),
:mod:`~torcsrl.report.plots` and :mod:`~torcsrl.report.app` (the app). The names below load their module on first
use: ``import torcsrl.report`` (and ``--help``) loads neither torch nor pybullet.
"""

from torcsrl.utils.lazy import lazy_exports

__all__ = [
    "DEFAULT_DEGRADATIONS",
    "DEFAULT_TRACKS",
    "DEFAULT_SEVERITIES",
    "EFFECT_FAMILIES",
    "ReportConfig",
    "run_report",
    "build_report",
    "read_rows",
    "main",
]

#: Each name of the package and the module that defines it.
_HOMES = {
    **dict.fromkeys(("DEFAULT_DEGRADATIONS", "DEFAULT_SEVERITIES", "DEFAULT_TRACKS", "EFFECT_FAMILIES", "RANDOM", "Cell",
                     "ReportConfig", "check_counts", "code_hash", "expand_degradations", "sensor_and_family"), "grid"),
    **dict.fromkeys(("default_policies", "prepare", "run_report"), "runner"),
    **dict.fromkeys(("plot_heatmap", "plot_severity_curves"), "plots"),
    **dict.fromkeys(("build_report", "read_rows"), "results"),
    "main": "app",
}
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
