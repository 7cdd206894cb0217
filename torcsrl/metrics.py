"""Driving and robustness metrics: pure functions on numbers, arrays and rows of episode results.

Nothing here touches an env. The definitions follow ``DEGRADATIONS.md`` ("Robustness metrics"):
for a policy pi, corruption c and severity s (0 = clean),

* **LCR** (lap completion rate): the fraction of episodes that drove all their N laps without
  termination (:func:`lap_completion_rate`); ``DE = 1 - LCR`` is the driving error.
* **NR** (normalised return): ``(R - R_random) / (R_clean - R_random)``
  (:func:`normalized_return`); undefined (NaN) where the policy is no better than random on the
  clean track. **mRR** is the mean NR over c and s >= 1 (:func:`mean_resilience_rate`).
* **CE_c** = ``sum_s DE_pi(c, s) / sum_s DE_ref(c, s)`` over s >= 1 against a pinned reference
  policy; **mCE** is its mean over c; **relative CE_c** first subtracts each policy's own clean
  DE (:func:`corruption_error`, :func:`mce`). When the reference never fails under c: CE_c = 1
  if pi never fails either, +inf otherwise.
* **AUSC_c**: area under NR(s) (clipped to [0, 1]) over the tested severities, divided by
  their span, so 1 = no loss at any severity (:func:`ausc`).
* **Breaking severity**: the smallest tested s with LCR < 0.5, None if none
  (:func:`breaking_severity`). **Worst case**: the corruption with the lowest mean NR over
  s >= 1 (:func:`worst_case`).
* 95 % percentile **bootstrap** intervals over episodes, seeded (:func:`bootstrap`,
  :func:`bootstrap_ci`). Episodes are paired across cells by (track, surface, episode): every
  policy saw the same start and the same degradation draws (common random numbers), so a
  resample picks the same units in every cell.

:func:`robustness_summary` applies all of these to the rows of a report grid.

Units: returns in reward units, lap times [s], distances [m] (per km where named so), steering in
normalised action units [-1, 1].
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "CLEAN",
    "normalized_return",
    "lap_completion_rate",
    "mean_resilience_rate",
    "corruption_error",
    "mce",
    "ausc",
    "breaking_severity",
    "worst_case",
    "bootstrap",
    "bootstrap_ci",
    "steering_oscillation",
    "off_track_events",
    "lap_time_stats",
    "robustness_summary",
]

#: The corruption name of the clean (severity 0) cells.
CLEAN = "none"


# --------------------------------------------------------------------------------------------
# Scalars and arrays
# --------------------------------------------------------------------------------------------
def normalized_return(r, r_random, r_clean, min_gap: float = 1e-6):
    """NR = (R - R_random) / (R_clean - R_random), elementwise (NumPy broadcasting).

    NaN where ``R_clean - R_random <= min_gap`` (a policy no better than random on the clean
    track has no scale to normalise by). Returns a float for scalar inputs.
    """
    r, r_random, r_clean = (np.asarray(x, dtype=float) for x in (r, r_random, r_clean))
    gap = r_clean - r_random
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(gap > min_gap, (r - r_random) / np.where(gap > min_gap, gap, 1.0), np.nan)
    return float(out) if out.ndim == 0 else out


def lap_completion_rate(success: Iterable[bool]) -> float:
    """Fraction of episodes that completed their laps without termination (NaN if none)."""
    s = np.asarray(list(success), dtype=float)
    return float(s.mean()) if s.size else math.nan


def mean_resilience_rate(nr) -> float:
    """mRR: the mean of NR over corruptions and severities >= 1 (``nr``: array [C, S>=1] or a
    mapping ``{c: {s: nr}}``; NaN entries are skipped)."""
    if isinstance(nr, Mapping):
        vals = [v for by_s in nr.values() for s, v in by_s.items() if int(s) >= 1]
    else:
        vals = np.asarray(nr, dtype=float).ravel().tolist()
    vals = np.asarray(vals, dtype=float)
    vals = vals[~np.isnan(vals)]
    return float(vals.mean()) if vals.size else math.nan


def corruption_error(de, de_ref, de_clean: float | None = None, de_ref_clean: float | None = None) -> float:
    """CE_c = sum_s DE(s) / sum_s DE_ref(s) over the severities >= 1 given (arrays [S]).

    With ``de_clean`` and ``de_ref_clean`` it is the *relative* CE: each policy's clean DE is
    subtracted from each of its severities first (ImageNet-C's relative mCE). A zero
    denominator gives 1.0 when the numerator is zero too (both never fail) and +inf otherwise.
    """
    de = np.asarray(de, dtype=float)
    de_ref = np.asarray(de_ref, dtype=float)
    if de.shape != de_ref.shape:
        raise ValueError(f"DE arrays differ in shape: {de.shape} vs reference {de_ref.shape}")
    ok = ~(np.isnan(de) | np.isnan(de_ref))
    if not ok.any():
        return math.nan
    if de_clean is not None or de_ref_clean is not None:
        if de_clean is None or de_ref_clean is None or math.isnan(de_clean) or math.isnan(de_ref_clean):
            return math.nan
        de = de - de_clean
        de_ref = de_ref - de_ref_clean
    num = float(de[ok].sum())
    den = float(de_ref[ok].sum())
    if abs(den) < 1e-12:
        return 1.0 if abs(num) < 1e-12 else math.copysign(math.inf, num)
    return num / den


def mce(ces: Iterable[float]) -> float:
    """Mean corruption error: the mean of CE_c over corruptions (NaN entries skipped)."""
    v = np.asarray(list(ces), dtype=float)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else math.nan


def ausc(severities: Sequence[int], nr: Sequence[float]) -> float:
    """Area under the severity curve NR(s), NR clipped to [0, 1], by the trapezoid rule over the
    tested severities (which must include 0, the clean run), divided by their span: 1 = no loss.

    NaN if any NR is NaN or fewer than two severities were tested.
    """
    s = np.asarray(severities, dtype=float)
    y = np.asarray(nr, dtype=float)
    if s.shape != y.shape:
        raise ValueError(f"severities {s.shape} and NR {y.shape} differ in shape")
    order = np.argsort(s)
    s, y = s[order], y[order]
    if len(s) < 2 or np.isnan(y).any():
        return math.nan
    if s[0] != 0:
        raise ValueError(f"AUSC needs the clean run (severity 0) among the severities, got {s.tolist()}")
    y = np.clip(y, 0.0, 1.0)
    area = float(np.sum((y[1:] + y[:-1]) * np.diff(s) / 2.0))
    return area / float(s[-1] - s[0])


def breaking_severity(severities: Sequence[int], lcr: Sequence[float], threshold: float = 0.5) -> int | None:
    """The smallest tested severity whose LCR is below ``threshold`` (None: it never breaks)."""
    for s, v in sorted(zip(severities, lcr)):
        if not math.isnan(float(v)) and float(v) < threshold:
            return int(s)
    return None


def worst_case(nr_by_corruption: Mapping[str, float]) -> tuple[str | None, float]:
    """(corruption, NR) with the lowest NR (NaN values skipped; (None, NaN) if all are NaN)."""
    items = [(c, float(v)) for c, v in nr_by_corruption.items() if not math.isnan(float(v))]
    if not items:
        return None, math.nan
    return min(items, key=lambda kv: kv[1])


def bootstrap(fn: Callable[[np.ndarray], float], n_units: int, n_boot: int = 1000, ci: float = 0.95,
              seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of a statistic of ``n_units`` paired units.

    ``fn(idx)`` computes the statistic on the units ``idx`` (an int array, with repeats). The
    draws come from ``numpy.random.default_rng(seed)``: the same seed gives the same interval.
    Returns (lo, hi); (v, v) for a single unit, (NaN, NaN) for none.
    """
    if n_units <= 0:
        return math.nan, math.nan
    if n_units == 1 or n_boot <= 0:
        v = float(fn(np.arange(n_units)))
        return v, v
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n_units, size=(n_boot, n_units))
    stats = np.array([fn(i) for i in idx], dtype=float)
    stats = stats[~np.isnan(stats)]
    if not stats.size:
        return math.nan, math.nan
    return _percentiles(stats, ci)


def _percentiles(stats: np.ndarray, ci: float) -> tuple[float, float]:
    """The central ``ci`` interval of bootstrap statistics (no interpolation across an infinity)."""
    a = (1.0 - ci) / 2.0
    method = "linear" if np.isfinite(stats).all() else "inverted_cdf"
    lo, hi = np.quantile(stats, [a, 1.0 - a], method=method)
    return float(lo), float(hi)


def bootstrap_ci(x: Sequence[float], n_boot: int = 1000, ci: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of ``x`` (NaN entries dropped first), seeded."""
    v = np.asarray(x, dtype=float)
    v = v[~np.isnan(v)]
    if v.size == 0:
        return math.nan, math.nan
    if v.size == 1 or n_boot <= 0:
        return float(v.mean()), float(v.mean())
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, v.size, size=(n_boot, v.size))].mean(axis=1)
    return _percentiles(means, ci)


def steering_oscillation(steer: Sequence[float], distance_m: float, deadband: float = 0.02) -> tuple[float, float]:
    """(mean |delta steer| per step, steering sign flips per km).

    A flip is a change of sign between consecutive steering commands outside ``deadband``
    (commands with |steer| <= deadband are skipped). ``distance_m`` is the distance driven
    [m]; flips per km are NaN when it is not positive.
    """
    a = np.asarray(steer, dtype=float)
    mean_abs = float(np.abs(np.diff(a)).mean()) if a.size > 1 else 0.0
    signs = np.sign(a[np.abs(a) > deadband])
    flips = int(np.count_nonzero(signs[1:] != signs[:-1])) if signs.size > 1 else 0
    per_km = flips / (distance_m / 1000.0) if distance_m > 0 else math.nan
    return mean_abs, per_km


def off_track_events(track_pos: Sequence[float]) -> int:
    """Number of times the car's centre went from on the track (|trackPos| <= 1) to off it."""
    off = np.abs(np.asarray(track_pos, dtype=float)) > 1.0
    if not off.size:
        return 0
    return int(off[0]) + int(np.count_nonzero(off[1:] & ~off[:-1]))


def lap_time_stats(lap_times: Sequence[float]) -> dict[str, float]:
    """Fastest lap and mean lap [s]. The mean is over the flying laps (2..N) when there are at
    least two laps (lap 1 starts from rest), else lap 1; NaN when no lap was completed."""
    t = [float(x) for x in lap_times]
    if not t:
        return {"fastest_lap": math.nan, "mean_lap": math.nan}
    flying = t[1:] if len(t) > 1 else t
    return {"fastest_lap": min(t), "mean_lap": float(np.mean(flying))}


# --------------------------------------------------------------------------------------------
# A report grid
# --------------------------------------------------------------------------------------------
def _nanmean(x, axis=None):
    """``np.nanmean`` without the "mean of empty slice" warning (an all-NaN cell is a legitimate NaN)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(np.asarray(x, dtype=float), axis=axis)


def _num(x: float | None) -> float | None:
    """NaN -> None (JSON null); other floats (inf included) unchanged."""
    if x is None:
        return None
    x = float(x)
    if math.isnan(x):
        return None
    return x


def robustness_summary(
    rows: Sequence[Mapping[str, Any]],
    *,
    policies: Sequence[str] | None = None,
    reference: str | None = None,
    random_policy: str = "random",
    corruptions: Sequence[str] | None = None,
    severities: Sequence[int] | None = None,
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
    break_threshold: float = 0.5,
) -> dict[str, Any]:
    """Every robustness metric of every policy, from per-episode rows.

    Each row is one episode: ``policy``, ``track``, ``surface``, ``corruption`` (:data:`CLEAN`
    for severity 0), ``severity``, ``episode``, ``return``, ``success`` (all laps, no
    termination). The clean rows of a policy serve as severity 0 of every corruption. Rows of
    ``random_policy`` give R_random per (track, surface). ``reference`` (default: the first
    policy) is the CE denominator. Bootstrap intervals resample the units (track, surface,
    episode) jointly across cells (and across the policy and the reference, for CE).

    Returns a nested dict (floats; NaN where undefined) — see the keys below in the code.
    """
    rows = [r for r in rows]
    notes: list[str] = []
    all_policies = sorted({r["policy"] for r in rows if r["policy"] != random_policy})
    policies = list(policies) if policies is not None else all_policies
    if not policies:
        raise ValueError("no policy rows to summarise (only the random baseline, or nothing)")
    reference = reference if reference is not None else policies[0]
    if corruptions is None:
        corruptions = sorted({r["corruption"] for r in rows if r["corruption"] != CLEAN})
    corruptions = list(corruptions)
    if severities is None:
        severities = sorted({int(r["severity"]) for r in rows} | {0})
    severities = sorted({int(s) for s in severities} | {0})
    sev_pos = {s: i for i, s in enumerate(severities)}
    c_pos = {c: i for i, c in enumerate(corruptions)}
    units = sorted({(r["track"], r.get("surface") or "", int(r["episode"])) for r in rows if r["policy"] != random_policy})
    u_pos = {u: i for i, u in enumerate(units)}
    tracks = sorted({(u[0], u[1]) for u in units})
    t_pos = {t: i for i, t in enumerate(tracks)}
    unit_track = np.array([t_pos[(u[0], u[1])] for u in units], dtype=int)
    C, S, U = len(corruptions), len(severities), len(units)

    # R_random per (track, surface)
    r_random = np.full(len(tracks), np.nan)
    for t, i in t_pos.items():
        v = [float(r["return"]) for r in rows if r["policy"] == random_policy and (r["track"], r.get("surface") or "") == t]
        if v:
            r_random[i] = float(np.mean(v))
    if np.isnan(r_random).any():
        missing = [f"{t[0]}/{t[1] or 'default'}" for t, i in t_pos.items() if np.isnan(r_random[i])]
        notes.append(f"no {random_policy!r} episodes for {', '.join(missing)}: NR is undefined there")

    def arrays(p: str):
        ret = np.full((C, S, U), np.nan)
        suc = np.full((C, S, U), np.nan)
        for r in rows:
            if r["policy"] != p:
                continue
            u = u_pos.get((r["track"], r.get("surface") or "", int(r["episode"])))
            if u is None:
                continue
            s = int(r["severity"])
            if r["corruption"] == CLEAN or s == 0:
                cs = range(C)
                si = sev_pos[0]
            elif r["corruption"] in c_pos and s in sev_pos:
                cs = [c_pos[r["corruption"]]]
                si = sev_pos[s]
            else:
                continue
            for ci_ in cs:
                ret[ci_, si, u] = float(r["return"])
                suc[ci_, si, u] = float(bool(r["success"]))
        # clean return per (track, surface): the NR scale
        clean = np.full(len(tracks), np.nan)
        vals: dict[int, list[float]] = {}
        for r in rows:
            if r["policy"] == p and (r["corruption"] == CLEAN or int(r["severity"]) == 0):
                t = (r["track"], r.get("surface") or "")
                if t in t_pos:
                    vals.setdefault(t_pos[t], []).append(float(r["return"]))
        for i, v in vals.items():
            clean[i] = float(np.mean(v))
        nr = normalized_return(ret, r_random[unit_track][None, None, :], clean[unit_track][None, None, :])
        return ret, suc, np.asarray(nr, dtype=float), clean

    data = {p: arrays(p) for p in set(policies) | {reference}}
    s_hi = np.array([s >= 1 for s in severities])

    def clean_rows(p):
        return [r for r in rows if r["policy"] == p and (r["corruption"] == CLEAN or int(r["severity"]) == 0)]

    out_p: dict[str, Any] = {}
    for k, p in enumerate(policies):
        ret, suc, nr, clean = data[p]
        ret_r, suc_r, _, _ = data[reference]
        bseed = seed + 7919 * k
        cr = clean_rows(p)
        clean_info = {
            "return": _num(np.mean([float(r["return"]) for r in cr])) if cr else None,
            "lcr": _num(lap_completion_rate(bool(r["success"]) for r in cr)) if cr else None,
            "episodes": len(cr),
        }
        lcr_cs = _nanmean(suc, axis=2) if U else np.full((C, S), np.nan)
        nr_cs = _nanmean(nr, axis=2) if U else np.full((C, S), np.nan)
        lcr_ref = _nanmean(suc_r, axis=2) if U else np.full((C, S), np.nan)
        per_c: dict[str, Any] = {}
        ce_list, rce_list, ausc_list = [], [], []
        for c, ci_ in c_pos.items():
            de = 1.0 - lcr_cs[ci_]
            de_ref = 1.0 - lcr_ref[ci_]
            ce = corruption_error(de[s_hi], de_ref[s_hi]) if s_hi.any() else math.nan
            rce = corruption_error(de[s_hi], de_ref[s_hi], float(de[sev_pos[0]]), float(de_ref[sev_pos[0]])) if s_hi.any() else math.nan
            a = ausc(severities, nr_cs[ci_]) if S > 1 else math.nan
            ce_list.append(ce)
            rce_list.append(rce)
            ausc_list.append(a)
            sev_out = {}
            for s, si in sev_pos.items():
                cell_nr = nr[ci_, si]
                cell_suc = suc[ci_, si]
                sev_out[str(s)] = {
                    "nr": _num(nr_cs[ci_, si]),
                    "nr_ci": [_num(v) for v in bootstrap_ci(cell_nr, n_boot, ci, bseed + 31 * ci_ + si)],
                    "lcr": _num(lcr_cs[ci_, si]),
                    "lcr_ci": [_num(v) for v in bootstrap_ci(cell_suc, n_boot, ci, bseed + 31 * ci_ + si + 1)],
                    "return": _num(_nanmean(ret[ci_, si])),
                    "n": int(np.count_nonzero(~np.isnan(cell_suc))),
                }
            per_c[c] = {
                "ce": _num(ce),
                "relative_ce": _num(rce),
                "ausc": _num(a),
                "breaking_severity": breaking_severity(severities, lcr_cs[ci_], break_threshold),
                "mean_nr": _num(_nanmean(nr_cs[ci_][s_hi])) if s_hi.any() else None,
                "severities": sev_out,
            }

        def mrr_of(idx):
            return mean_resilience_rate(_nanmean(nr[:, :, idx], axis=2)[:, s_hi])

        def mce_of(idx, relative=False):
            a = 1.0 - _nanmean(suc[:, :, idx], axis=2)
            b = 1.0 - _nanmean(suc_r[:, :, idx], axis=2)
            vals = []
            for ci_ in range(C):
                if relative:
                    vals.append(corruption_error(a[ci_, s_hi], b[ci_, s_hi], float(a[ci_, sev_pos[0]]), float(b[ci_, sev_pos[0]])))
                else:
                    vals.append(corruption_error(a[ci_, s_hi], b[ci_, s_hi]))
            return mce(vals)

        mrr = mrr_of(np.arange(U)) if U and C and s_hi.any() else math.nan
        m_ce = mce(ce_list)
        m_rce = mce(rce_list)
        wc_name, wc_val = worst_case({c: (per_c[c]["mean_nr"] if per_c[c]["mean_nr"] is not None else math.nan) for c in corruptions})
        worst_by_s = {}
        for s, si in sev_pos.items():
            if s == 0:
                continue
            n_, v_ = worst_case({c: float(nr_cs[c_pos[c], si]) for c in corruptions})
            worst_by_s[str(s)] = {"corruption": n_, "nr": _num(v_)}
        breaks = [(per_c[c]["breaking_severity"], c) for c in corruptions if per_c[c]["breaking_severity"] is not None]
        out_p[p] = {
            "clean": clean_info,
            "mrr": _num(mrr),
            "mrr_ci": [_num(v) for v in bootstrap(mrr_of, U, n_boot, ci, bseed + 1)] if U and C and s_hi.any() else [None, None],
            "mce": _num(m_ce),
            "mce_ci": [_num(v) for v in bootstrap(mce_of, U, n_boot, ci, bseed + 2)] if U and C and s_hi.any() else [None, None],
            "relative_mce": _num(m_rce),
            "mean_ausc": _num(mce(ausc_list)),
            "worst_case": {"corruption": wc_name, "nr": _num(wc_val)},
            "worst_case_by_severity": worst_by_s,
            "first_break": {"corruption": min(breaks)[1], "severity": min(breaks)[0]} if breaks else None,
            "corruptions": per_c,
        }
    return {
        "policies": out_p,
        "reference": reference,
        "random_policy": random_policy,
        "r_random": {f"{t[0]}/{t[1]}": _num(r_random[i]) for t, i in t_pos.items()},
        "corruptions": corruptions,
        "severities": severities,
        "units": len(units),
        "n_boot": n_boot,
        "ci": ci,
        "bootstrap_seed": seed,
        "notes": notes,
    }
