"""Report results: reading episode rows back from disk, the metrics, and every output file (JSON, CSV, Markdown, HTML)."""

from __future__ import annotations

import base64
import html
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torcsrl import metrics
from torcsrl.evaluate.results import fmt_value, markdown_table, read_evaluations, write_csv, write_json
from torcsrl.evaluate.spec import EvalError
from torcsrl.report.grid import EFFECT_FAMILIES, RANDOM, check_counts, sensor_and_family, stable_hash
from torcsrl.report.plots import plot_heatmap, plot_severity_curves

# --------------------------------------------------------------------------------------------
# Reading results from disk
# --------------------------------------------------------------------------------------------
def read_rows(root: str | Path) -> list[dict[str, Any]]:
    """Episode rows from every ``evaluation.json`` (torcsrl.evaluate outputs, e.g. a Hydra
    multirun's jobs) and every cached cell JSON under ``root``. Duplicate episodes (same policy,
    fingerprint, track, surface, degradation, severity, episode, seeds) are kept once."""
    root = Path(root)
    if not root.exists():
        raise EvalError(f"{root} does not exist")
    rows: list[dict[str, Any]] = []
    for d in read_evaluations(root):
        rows += d.get("episodes", [])
    for p in sorted(root.rglob("*.json")):
        if p.name in ("evaluation.json", "robustness.json"):
            continue
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(d, dict) and isinstance(d.get("rows"), list) and "cell" in d:
            rows += d["rows"]
    seen, out = set(), []
    for r in rows:
        k = (r.get("policy"), r.get("policy_fingerprint"), r.get("track"), r.get("surface"), r.get("corruption"),
             int(r.get("severity", 0)), int(r.get("episode", 0)), r.get("env_seed"), r.get("degradation_seed"))
        if k not in seen:
            seen.add(k)
            out.append(r)
    if not out:
        raise EvalError(f"no evaluation results (evaluation.json or cell JSON files) under {root}")
    return out


# --------------------------------------------------------------------------------------------
# The report: JSON, CSV, Markdown, HTML, plots
# --------------------------------------------------------------------------------------------
class _Doc:
    """Blocks rendered both to Markdown and to self-contained HTML."""

    def __init__(self) -> None:
        self.blocks: list[tuple[str, Any]] = []

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", (level, text)))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def table(self, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        self.blocks.append(("table", (list(header), [list(r) for r in rows])))

    def img(self, path: Path, alt: str) -> None:
        self.blocks.append(("img", (Path(path), alt)))

    def markdown(self) -> str:
        out = []
        for kind, b in self.blocks:
            if kind == "h":
                out.append("#" * b[0] + " " + b[1])
            elif kind == "p":
                out.append(b)
            elif kind == "table":
                out.append(markdown_table(*b))
            elif kind == "img":
                out.append(f"![{b[1]}]({b[0].name})")
            out.append("")
        return "\n".join(out)

    def html(self, title: str) -> str:
        def inline(t: str) -> str:
            t = html.escape(t)
            return re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", t)

        parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>"
                 "body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}"
                 "table{border-collapse:collapse;margin:.5em 0 1.5em;font-size:13px}"
                 "th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f0f0f0}"
                 "td:first-child,th:first-child{text-align:left}img{max-width:100%}code{background:#f4f4f4}"
                 "</style></head><body>"]
        for kind, b in self.blocks:
            if kind == "h":
                parts.append(f"<h{b[0]}>{inline(b[1])}</h{b[0]}>")
            elif kind == "p":
                if b.startswith("- "):
                    items = "".join(f"<li>{inline(x[2:])}</li>" for x in b.split("\n") if x.startswith("- "))
                    parts.append(f"<ul>{items}</ul>")
                else:
                    parts.append(f"<p>{inline(b)}</p>")
            elif kind == "table":
                head = "".join(f"<th>{inline(c)}</th>" for c in b[0])
                body = "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in b[1])
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            elif kind == "img":
                data = base64.b64encode(b[0].read_bytes()).decode()
                parts.append(f"<p><img alt='{html.escape(b[1])}' src='data:image/png;base64,{data}'></p>")
        parts.append("</body></html>")
        return "\n".join(parts)


def _ci(v, ci, fmt="{:.2f}") -> str:
    s = fmt_value(v, fmt)
    if ci and ci[0] is not None and ci[1] is not None and v is not None and not (ci[0] == ci[1] == v):
        s += f" ({fmt_value(ci[0], fmt)}–{fmt_value(ci[1], fmt)})"
    return s


def _pct(v) -> str:
    return fmt_value(None if v is None else 100.0 * v, "{:.0f}%")



def _fails_clean(first_break: Mapping[str, Any] | None) -> bool:
    """A policy whose "first break" is severity 0 never completed laps clean: no degradation broke it."""
    return bool(first_break) and first_break["severity"] == 0


def build_report(rows: Sequence[Mapping[str, Any]], out_dir: str | Path, *, policies: Sequence[str] | None = None,
                 reference: str | None = None, corruptions: Sequence[str] | None = None, severities: Sequence[int] | None = None,
                 n_boot: int = 1000, seed: int = 0, meta: Mapping[str, Any] | None = None,
                 cells: Sequence[Mapping[str, Any]] | None = None, verbose: bool = True) -> dict[str, Any]:
    """Metrics from episode ``rows`` and every output file in ``out_dir``; returns
    ``{"summary", "files", "summary_line"}``."""
    check_counts(n_boot=n_boot)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [dict(r) for r in rows]
    summary = metrics.robustness_summary(rows, policies=policies, reference=reference, random_policy=RANDOM,
                                         corruptions=corruptions, severities=severities, n_boot=n_boot, seed=seed)
    meta = dict(meta or {})
    pols = list(summary["policies"])
    ref = summary["reference"]
    sev = summary["severities"]
    cors = summary["corruptions"]

    # files: JSON, CSVs
    config_hash = meta.get("config_hash") or stable_hash(sorted({str(r.get("policy_fingerprint")) for r in rows}))[:16]
    if cells is None:
        groups: dict[tuple, list] = {}
        for r in rows:
            groups.setdefault((r["policy"], r["track"], r["surface"], r["corruption"], int(r["severity"])), []).append(r)
        cells = [{"cell": dict(zip(("policy", "track", "surface", "corruption", "severity"), k)), "rows": v} for k, v in groups.items()]
    write_json({**meta, "config_hash": config_hash, "summary": summary, "cells": list(cells)}, out / "robustness.json")
    ep_cols = ["policy", "track", "surface", "corruption", "severity", "episode", "env_seed", "degradation_seed", "return",
               "success", "laps", "laps_target", "terminated", "termination", "steps", "distance_m", "fastest_lap", "mean_lap",
               "mean_speed_kmh", "off_track_events", "steer_abs_delta", "steer_flips_per_km", "reused_clean",
               "policy_fingerprint"]
    write_csv([dict(r, config_hash=config_hash) for r in rows], out / "robustness.csv", ep_cols + ["config_hash"])
    srows = []
    for p in pols:
        for c in cors:
            pc = summary["policies"][p]["corruptions"][c]
            for s in sev:
                d = pc["severities"][str(s)]
                srows.append({"policy": p, "corruption": c, "sensor": sensor_and_family(c)[0], "effect": sensor_and_family(c)[1],
                              "severity": s, "nr": d["nr"], "nr_lo": d["nr_ci"][0], "nr_hi": d["nr_ci"][1], "lcr": d["lcr"],
                              "lcr_lo": d["lcr_ci"][0], "lcr_hi": d["lcr_ci"][1], "return": d["return"], "episodes": d["n"],
                              "ce": pc["ce"], "relative_ce": pc["relative_ce"], "ausc": pc["ausc"],
                              "breaking_severity": pc["breaking_severity"]})
    write_csv(srows, out / "robustness_summary.csv")

    # plots
    reused = {(r["policy"], r["corruption"]) for r in rows if r.get("reused_clean")}
    heat = plot_heatmap(summary, out / "nr_heatmap.png", reused)
    curves = plot_severity_curves(summary, out / "severity_curves.png", reused)

    # the document
    def rank_key(p):
        v = summary["policies"][p]["mrr"]
        return -(v if v is not None else -1e9)

    board = sorted(pols, key=rank_key)
    best = board[0]
    bp = summary["policies"][best]
    wc = bp["worst_case"]
    fb = bp["first_break"]
    n_p = f"{len(pols)} polic{'y' if len(pols) == 1 else 'ies'}"
    lead = f"**{best}** has the highest mRR of {n_p}:" if len(pols) > 1 else f"**{best}**: mRR"
    line = (f"{lead} {_ci(bp['mrr'], bp['mrr_ci'])}, mCE {_pct(bp['mce'])} of {ref}'s; "
            f"clean LCR {_pct(bp['clean']['lcr'])}; worst degradation {wc['corruption']} (mean NR {fmt_value(wc['nr'])}); "
            + ("already fails clean (LCR < 50% at severity 0): read normalised return, not breaking severity."
               if _fails_clean(fb) else
               f"first breaks (LCR < 50%) under {fb['corruption']} at severity {fb['severity']}." if fb
               else "never breaks (LCR >= 50% everywhere)."))
    finite = [p for p in pols if summary["policies"][p]["mce"] is not None]
    if len(pols) > 1 and finite:
        low = min(finite, key=lambda p: summary["policies"][p]["mce"])
        if low != best:
            line += f" Lowest mCE: **{low}** ({_pct(summary['policies'][low]['mce'])})."
    doc = _Doc()
    doc.h(1, "Degradation robustness report")
    doc.p(line)
    tracks = sorted({f"{r['track']}/{r['surface']}" for r in rows if r["policy"] != RANDOM})
    n_ep = sorted({int(r.get("laps_target", 1)) for r in rows})
    doc.p(f"{len(pols)} polic{'y' if len(pols) == 1 else 'ies'} × {len(tracks)} track(s) ({', '.join(tracks)}) × {len(cors)} "
          f"degradation(s) × severities {', '.join(map(str, sev))}; {summary['units']} episode unit(s) (tracks × episodes) per cell, "
          f"{'/'.join(map(str, n_ep))} lap(s) each. Reference policy for CE: **{ref}**. Config hash `{config_hash}`. "
          f"Intervals: 95% percentile bootstrap over episode units ({n_boot} resamples, seed {seed}).")
    doc.h(2, "Leaderboard")
    header = ["Rank", "Policy", "Clean LCR", "Clean return", "mRR (95% CI)", "mCE (95% CI)", "Relative mCE", "Mean AUSC",
              "Worst case (mean NR)", "First break"]
    body = []
    for i, p in enumerate(board, 1):
        d = summary["policies"][p]
        w = d["worst_case"]
        b = d["first_break"]
        body.append([str(i), p + (" (ref)" if p == ref else ""), _pct(d["clean"]["lcr"]), fmt_value(d["clean"]["return"], "{:.0f}"),
                     _ci(d["mrr"], d["mrr_ci"]), _ci(None if d["mce"] is None else 100 * d["mce"],
                                                     [None if v is None else 100 * v for v in d["mce_ci"]], "{:.0f}%"),
                     _pct(d["relative_mce"]), fmt_value(d["mean_ausc"]),
                     f"{w['corruption']} ({fmt_value(w['nr'])})" if w["corruption"] else "–",
                     "fails clean" if _fails_clean(b) else f"{b['corruption']} @ {b['severity']}" if b else "none"])
    doc.table(header, body)
    doc.h(2, "Plots")
    doc.img(heat, "NR heatmap")
    doc.img(curves, "severity curves")
    doc.h(2, "Per degradation")
    doc.p("NR per severity (95% CI), lap completion rate (LCR) per severity, AUSC (area under NR(s), 1 = no loss), the "
          "breaking severity (first s with LCR < 50%), and CE / relative CE against the reference (100% = as robust as the "
          "reference; ∞: the reference never failed there but this policy did).")
    s_hi = [s for s in sev if s >= 1]
    for p in board:
        doc.h(3, f"{p}" + (" (reference)" if p == ref else ""))
        by_sensor: dict[str, list[str]] = {}
        for c in cors:
            by_sensor.setdefault(sensor_and_family(c)[0], []).append(c)
        for sensor, cs in by_sensor.items():
            cs = sorted(cs, key=lambda c: (list(EFFECT_FAMILIES).index(sensor_and_family(c)[1]) if sensor_and_family(c)[1] in EFFECT_FAMILIES else 99, c))
            header = ["Effect", "Degradation", *[f"NR s{s}" for s in s_hi], *[f"LCR s{s}" for s in s_hi], "AUSC", "Breaks at",
                      "CE", "Rel. CE"]
            body = []
            for c in cs:
                d = summary["policies"][p]["corruptions"][c]
                body.append([sensor_and_family(c)[1], c + (" †" if (p, c) in reused else ""),
                             *[_ci(d["severities"][str(s)]["nr"], d["severities"][str(s)]["nr_ci"]) for s in s_hi],
                             *[_pct(d["severities"][str(s)]["lcr"]) for s in s_hi], fmt_value(d["ausc"]),
                             "–" if d["breaking_severity"] is None else str(d["breaking_severity"]),
                             _pct(d["ce"]), _pct(d["relative_ce"])])
            doc.p(f"**{sensor}**")
            doc.table(header, body)
    if reused:
        doc.p("† the degradation touches none of the policy's observation keys, so its clean episodes stand in.")
    doc.h(2, "Definitions")
    doc.p("- NR = (R − R_random) / (R_clean − R_random) per (track, episode), R_random from uniform random actions on the clean track; "
          "mRR = mean NR over degradations and severities ≥ 1.\n"
          "- LCR = share of episodes that drove all their laps without leaving the track, driving backwards, stalling or flipping; "
          "DE = 1 − LCR; CE_c = Σ_s DE / Σ_s DE_ref over s ≥ 1; mCE = mean CE_c; relative CE subtracts each policy's clean DE first.\n"
          "- AUSC = trapezoid area under NR(s) (NR clipped to [0, 1]) over the tested severities, divided by their span.\n"
          "- Common random numbers: every policy saw the same starts and the same degradation draws (seeded per "
          "(seed, degradation, severity, episode)).")
    notes = list(summary["notes"]) + list(meta.get("notes", []))
    if notes:
        doc.h(2, "Notes")
        doc.p("\n".join(f"- {n}" for n in notes))
    (out / "REPORT.md").write_text(doc.markdown())
    (out / "report.html").write_text(doc.html("torcsrl robustness report"))
    files = [str(out / f) for f in ("robustness.json", "robustness.csv", "robustness_summary.csv", "REPORT.md", "report.html",
                                    "nr_heatmap.png", "severity_curves.png")]
    return {"summary": summary, "files": files, "summary_line": line.replace("**", "")}


