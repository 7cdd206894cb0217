"""Results I/O: per-track summaries, tables, strict JSON and CSV, reading results back from disk."""

from __future__ import annotations

import csv
import json
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

# --------------------------------------------------------------------------------------------
# Summaries, tables, pictures
# --------------------------------------------------------------------------------------------
def summarise_track(rows: Sequence[Mapping[str, Any]], ref: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Per-track numbers over its episodes (means, except fastest lap = the minimum)."""
    r0 = rows[0]
    lap_means = [r["mean_lap"] for r in rows if not math.isnan(r["mean_lap"])]
    fastest = min((r["fastest_lap"] for r in rows if not math.isnan(r["fastest_lap"])), default=math.nan)
    out = {
        "track": r0["track"], "surface": r0["surface"], "corruption": r0["corruption"], "severity": r0["severity"],
        "episodes": len(rows), "laps_target": r0["laps_target"],
        "laps": float(np.mean([r["laps"] for r in rows])),
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "fastest_lap": fastest,
        "mean_lap": float(np.mean(lap_means)) if lap_means else math.nan,
        "mean_speed_kmh": float(np.mean([r["mean_speed_kmh"] for r in rows])),
        "off_track_events": int(sum(r["off_track_events"] for r in rows)),
        "terminations": ", ".join(sorted({r["termination"] for r in rows if r["termination"]}
                                         | ({"step limit"} if any(r["truncated"] and not r["finished"] for r in rows) else set()))),
        "steer_abs_delta": float(np.mean([r["steer_abs_delta"] for r in rows])),
        "steer_flips_per_km": float(np.nanmean([r["steer_flips_per_km"] for r in rows])) if any(
            not math.isnan(r["steer_flips_per_km"]) for r in rows) else math.nan,
        "return": float(np.mean([r["return"] for r in rows])),
    }
    ref = ref or {}
    out["expert_lap"] = float(ref.get("expert_lap", math.nan))
    out["limit_lap"] = float(ref.get("limit_lap", math.nan))
    out["vs_expert"] = fastest / out["expert_lap"] if out["expert_lap"] > 0 else math.nan
    out["vs_limit"] = fastest / out["limit_lap"] if out["limit_lap"] > 0 else math.nan
    return out


def fmt_value(x: Any, fmt: str = "{:.2f}", none: str = "–") -> str:
    """``x`` for a table cell: formatted with ``fmt``; ``none`` for None and NaN, ∞ / −∞ for infinities."""
    if x is None:
        return none
    try:
        if isinstance(x, float) and math.isnan(x):
            return none
        if isinstance(x, float) and math.isinf(x):
            return "∞" if x > 0 else "−∞"
    except TypeError:
        pass
    return fmt.format(x)


def summary_table(summaries: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of the time-trial table (Summers's Tables 7.1/7.2 layout, plus ours)."""
    header = ["Track", "Surface", "Laps", "Fastest lap [s]", "Mean lap [s]", "Success", "Mean speed [km/h]",
              "vs expert", "vs limit", "Off-track", "|Δsteer|", "Flips/km", "Return"]
    body = []
    for s in summaries:
        laps = f"{s['laps']:.0f}/{s['laps_target']}" if s["episodes"] == 1 else f"{s['laps']:.1f}/{s['laps_target']}"
        succ = ("yes" if s["success_rate"] == 1 else "no") if s["episodes"] == 1 else f"{100 * s['success_rate']:.0f}%"
        if s.get("terminations"):
            succ += f" ({s['terminations']})"
        body.append([s["track"], s["surface"], laps, fmt_value(s["fastest_lap"]), fmt_value(s["mean_lap"]), succ,
                     fmt_value(s["mean_speed_kmh"], "{:.1f}"), fmt_value(s["vs_expert"], "{:.3f}"),
                     fmt_value(s["vs_limit"], "{:.3f}"), str(s["off_track_events"]), fmt_value(s["steer_abs_delta"], "{:.3f}"),
                     fmt_value(s["steer_flips_per_km"], "{:.1f}"), fmt_value(s["return"], "{:.0f}")])
    return header, body


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-flavoured Markdown table."""
    esc = [[str(c).replace("|", "\\|") for c in r] for r in [header, *rows]]
    lines = ["| " + " | ".join(esc[0]) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in esc[1:]]
    return "\n".join(lines)



def jsonable(x: Any) -> Any:
    """``x`` as strict-JSON-ready Python (NaN -> None, ±inf -> "inf" / "-inf", numpy scalars and arrays -> Python)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        if math.isnan(x):
            return None
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return x
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    return x


def write_json(obj: Any, path: str | Path) -> Path:
    """Strict JSON (NaN -> null, inf -> "inf"), written atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(jsonable(obj), indent=1, allow_nan=False))
    tmp.replace(path)
    return path


def write_csv(rows: Sequence[Mapping[str, Any]], path: str | Path, columns: Sequence[str] | None = None) -> Path:
    cols = list(columns or (rows[0].keys() if rows else []))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (";".join(f"{v:.3f}" for v in r[k]) if isinstance(r.get(k), list) else jsonable(r.get(k))) for k in cols})
    return Path(path)



def read_evaluations(root: str | Path) -> list[dict[str, Any]]:
    """Every ``evaluation.json`` under ``root`` (e.g. a Hydra multirun folder: one per job), loaded."""
    out = []
    for p in sorted(Path(root).rglob("evaluation.json")):
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as err:
            print(f"[torcsrl] skipping unreadable {p} ({type(err).__name__})", file=sys.stderr)
            continue
        d["_path"] = str(p)
        out.append(d)
    return out


