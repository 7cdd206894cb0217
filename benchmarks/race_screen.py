"""The racer selection screen as one command: races on TRAINING tracks, a table with the eligibility.

    python benchmarks/race_screen.py --policy A.pt B.pt reference_racer [--episodes 3] [--workers 2] [--out DIR]
    python benchmarks/race_screen.py --policy A.pt --surfaces asphalt dirt     # every track on both (48 races)
    python benchmarks/race_screen.py --policy A.pt --surfaces asphalt dirt --surface-weights asphalt=5 dirt=1

Each policy races 3 scripted experts, 5 laps from the grid, on ``set:train`` and ``gen-10001..10003`` (the training
seed range), ``--episodes`` races a track, each opponent's pace drawn per race from ``--pace`` ([0.83, 0.87]: around
85 %, so that every race is its own scenario — at one pace the races of a track come from at most K + 1
grid slots; the ``scenarios`` column counts the distinct ones), each track on its own surface (the training set's:
asphalt) or on each of ``--surfaces``. It prints, per policy, races finished, wins,
collisions a race, how they spread (the races without a contact, the most in one race: a mean of 1.04 can be one
pile-up), scenarios and whether it is eligible: ``--min-finished`` / ``--min-wins`` of the races (0.75 / 0.5)
and at most ``--max-collisions`` a race (1.0) — the issue's two race goals on training tracks, and finishing. This is
the race screen the shipped racers were chosen on (2026-11-27, ``torcsrl/assets/reference_racer.md``); pair it with
``python benchmarks/generalisation.py --screen --laps 10 --surfaces asphalt dirt`` (solo, no forgetting).

``--surface-weights asphalt=5 dirt=1`` judges the eligibility on surface-weighted rates instead of the pooled counts:
each surface's finished share, win share and collisions a race, weighted (``5/6 * asphalt + 1/6 * dirt``). Racing every
track on both surfaces weighs dirt half; the held-out race protocol (``set:heldout``) has one dirt track of six, so
weights 5 and 1 make the training screen's mix the held-out one without racing fewer dirt races.

``--baseline B`` compares every policy with B race by race: the same seed gives every policy the same races (grid slot,
opponents' paces, env seed per track, surface and episode), so the difference in finished share, win share and
collisions a race is paired, and its 95 % bootstrap interval (races resampled within each surface, 2,000 draws, seeded)
says whether a few races' difference is more than the draw of races. B is one of ``--policy`` or the
``race_episodes.csv`` a screen wrote with ``--out`` (a screen of the same races; anything else is refused in one line),
so the incumbent need not be raced again.

Selection happens on training tracks only: a held-out track (``set:heldout``, a bundled held-out track or a generated
track of the held-out seed range) is refused in one line; measure those once, after the choice, with
``python -m torcsrl.evaluate mode=race tracks=set:heldout``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TRAIN_RACE_TRACKS = ("set:train", "gen-10001", "gen-10002", "gen-10003")


def heldout_tracks(names: list[str]) -> list[str]:
    """The names in ``names`` that are held-out: bundled ``set:heldout`` tracks or generated tracks of the held-out
    seed range (:data:`torcsrl.envs.tracks.procedural.HELDOUT_SEEDS`)."""
    import re

    from torcsrl.envs import tracks
    from torcsrl.envs.tracks.procedural import HELDOUT_SEEDS

    held = set(tracks.track_sets().get("heldout", []))
    out = []
    for n in names:
        m = re.fullmatch(r"(?:gen|proc)-(\d+)(?:@.*)?", n)
        if n in held or (m and HELDOUT_SEEDS[0] <= int(m.group(1)) < HELDOUT_SEEDS[1]):
            out.append(n)
    return out


def screen(policies: list[str], tracks: list[str], *, episodes: int = 3, pace: tuple[float, float] = (0.83, 0.87),
           laps: int = 5, opponents: int = 3, seed: int = 0, workers: int = 1, out: str | None = None,
           surfaces: list[str] | None = None) -> list[dict]:
    """One summary per policy: ``{"policy", "races", "finished", "wins", "collisions_per_race", "contact_free",
    "most_collisions", "contacts_ahead", "contacts_alongside", "contacts_behind", "scenarios", "wall_s", "by_surface"}``
    (how the collisions spread, and where the other car was: :func:`race_summary`);
    ``by_surface``: the same counts for each surface raced (``{surface: {"races", "finished", "wins",
    "collisions_per_race"}}``). ``surfaces``: race every track on each of them (None: each track on its own surface)."""
    from torcsrl.evaluate.spec import EvalError, validate_grid
    from torcsrl.evaluate.race import evaluate_race, race_summary

    try:
        names, _ = validate_grid(list(tracks), surfaces)  # the race mode's own checks of names and road surfaces
    except EvalError as err:
        raise SystemExit(f"race_screen: {err}") from None
    bad = heldout_tracks(names)
    if bad:
        raise SystemExit(f"race_screen: {', '.join(bad)} {'is a held-out track' if len(bad) == 1 else 'are held-out tracks'}; "
                         f"a selection screen drives training tracks only (default {' '.join(TRAIN_RACE_TRACKS)})")
    rows = []
    for spec in policies:
        t0 = time.perf_counter()
        res = evaluate_race(spec, names, surfaces=surfaces, laps=laps, seed=seed, episodes=episodes, opponents=opponents, pace=list(pace),
                            workers=workers, plots=out is not None, verbose=False,
                            out_dir=None if out is None else Path(out) / Path(str(spec)).stem)
        tot = res["summary"][-1]  # the race table's "all" row (its only row for one track): torcsrl.evaluate.race.race_summary
        raced = dict.fromkeys(r["surface"] for r in res["episodes"])  # in the order raced
        by_surface = {s: race_summary([r for r in res["episodes"] if r["surface"] == s]) for s in raced}
        rows.append({"policy": str(spec), **{k: tot[k] for k in ("races", "finished", "wins", "collisions_per_race", "contact_free",
                                                                  "most_collisions", "contacts_ahead", "contacts_alongside",
                                                                  "contacts_behind", "scenarios")},
                     "wall_s": time.perf_counter() - t0, "race_rows": [_race_key(r) for r in res["episodes"]],
                     "by_surface": {s: {k: v[k] for k in ("races", "finished", "wins", "collisions_per_race")} for s, v in by_surface.items()}})
    return rows


def _race_key(r: dict) -> dict:
    """What a paired comparison needs of one race (an episode row of :func:`torcsrl.evaluate.race.evaluate_race`)."""
    return {"track": str(r["track"]), "surface": str(r["surface"]), "episode": int(r["episode"]), "env_seed": int(r["env_seed"]),
            "finished": r["position"] is not None, "win": bool(r["win"]), "collisions": float(r["collisions"])}


def read_races(path: str | Path) -> list[dict]:
    """The races of a screen's ``race_episodes.csv`` (``--out``) in :func:`_race_key`'s form; SystemExit (one line) if
    it is not such a file."""
    import csv

    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        return [{"track": r["track"], "surface": r["surface"], "episode": int(r["episode"]), "env_seed": int(r["env_seed"]),
                 "finished": r["position"] not in ("", "None"), "win": r["win"] == "True", "collisions": float(r["collisions"])}
                for r in rows]
    except (OSError, KeyError, ValueError) as err:
        raise SystemExit(f"race_screen: baseline {str(path)!r} is not a race_episodes.csv written by race_screen --out "
                         f"({type(err).__name__}: {err})") from None


def paired_delta(races: list[dict], base: list[dict], weights: dict[str, float] | None = None, n_boot: int = 2000,
                 seed: int = 0, ci: float = 0.95) -> dict[str, tuple[float, float, float]]:
    """``races`` minus ``base``, race by race: ``{"finished" | "wins" | "collisions_per_race": (delta, lo, hi)}`` with a
    percentile bootstrap interval (races resampled within each surface; the surfaces combined with ``weights``, or by
    their race counts). SystemExit (one line) unless both are the same races (track, surface, episode, env seed)."""
    import numpy as np

    def key(r: dict) -> tuple:
        return r["track"], r["surface"], r["episode"]

    b = {key(r): r for r in base}
    a = {key(r): r for r in races}
    if set(a) != set(b) or any(a[k]["env_seed"] != b[k]["env_seed"] for k in a) or len(a) != len(races):
        raise SystemExit(f"race_screen: the baseline raced other races ({len(b)} races) than this screen ({len(a)}); "
                         "compare screens of the same tracks, surfaces, episodes and seed")
    surfaces = list(dict.fromkeys(k[1] for k in a))
    n = {s: sum(k[1] == s for k in a) for s in surfaces}
    w = {s: (weights[s] if weights else n[s]) for s in surfaces}
    tot = sum(w.values())
    rng = np.random.default_rng(seed)
    out = {}
    for m, field in (("finished", "finished"), ("wins", "win"), ("collisions_per_race", "collisions")):
        est, boot = 0.0, np.zeros(n_boot)
        for s in surfaces:
            d = np.array([float(a[k][field]) - float(b[k][field]) for k in sorted(a) if k[1] == s])
            est += w[s] / tot * d.mean()
            boot += w[s] / tot * d[rng.integers(0, len(d), size=(n_boot, len(d)))].mean(axis=1)
        lo, hi = np.quantile(boot, [(1 - ci) / 2, 1 - (1 - ci) / 2])
        out[m] = (float(est), float(lo), float(hi))
    return out


def parse_surface_weights(items: list[str], surfaces: list[str] | None) -> dict[str, float]:
    """``["asphalt=5", "dirt=1"]`` -> ``{"asphalt": 5.0, "dirt": 1.0}``; SystemExit (one line) unless every surface
    raced (``--surfaces``) has one weight >= 0 and they sum to more than 0."""
    if not surfaces:
        raise SystemExit("race_screen: --surface-weights needs --surfaces (the surfaces every track is raced on)")
    out: dict[str, float] = {}
    for item in items:
        name, eq, val = item.partition("=")
        try:
            w = float(val) if eq else float("nan")
        except ValueError:
            w = float("nan")
        if not w >= 0:  # also NaN
            raise SystemExit(f"race_screen: surface weight {item!r} is not SURFACE=W with W >= 0 (e.g. asphalt=5 dirt=1)")
        if name not in surfaces:
            raise SystemExit(f"race_screen: surface weight {name!r} names a surface not raced; raced: {', '.join(surfaces)}")
        out[name] = w
    missing = [s for s in surfaces if s not in out]
    if missing or sum(out.values()) <= 0:
        raise SystemExit(f"race_screen: --surface-weights must weigh every surface raced ({', '.join(surfaces)}) and "
                         f"sum to more than 0; {'missing: ' + ', '.join(missing) if missing else 'all weights are 0'}")
    return out


def weighted_rates(row: dict, weights: dict[str, float]) -> dict[str, float]:
    """The surface-weighted finished share, win share and collisions a race of one screen row (``by_surface``)."""
    tot = sum(weights[s] for s in row["by_surface"])
    rate = {"finished": 0.0, "wins": 0.0, "collisions_per_race": 0.0}
    for s, v in row["by_surface"].items():
        w = weights[s] / tot
        rate["finished"] += w * v["finished"] / v["races"]
        rate["wins"] += w * v["wins"] / v["races"]
        rate["collisions_per_race"] += w * v["collisions_per_race"]
    return rate


def eligible(row: dict, min_finished: float, min_wins: float, max_collisions: float,
             weights: dict[str, float] | None = None) -> bool:
    """The pooled counts pass the thresholds (``weights``: the surface-weighted rates do)."""
    if weights:
        r = weighted_rates(row, weights)
        return r["finished"] >= min_finished and r["wins"] >= min_wins and r["collisions_per_race"] <= max_collisions
    n = row["races"]
    return row["finished"] >= min_finished * n and row["wins"] >= min_wins * n and row["collisions_per_race"] <= max_collisions


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", nargs="+", required=True, help="checkpoints, run folders, built-in drivers (racer_bold, ...)")
    ap.add_argument("--tracks", nargs="+", default=list(TRAIN_RACE_TRACKS))
    ap.add_argument("--surfaces", nargs="+", default=None,
                    help="race every track on each of these surfaces (default: each track on its own, asphalt for the training set)")
    ap.add_argument("--episodes", type=int, default=3, help="races a track (and surface)")
    ap.add_argument("--pace", type=float, nargs=2, default=(0.83, 0.87), help="each opponent's pace drawn per race from [lo, hi]")
    ap.add_argument("--laps", type=int, default=5)
    ap.add_argument("--opponents", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--min-finished", type=float, default=0.75, help="share of the races finished to be eligible")
    ap.add_argument("--min-wins", type=float, default=0.5, help="share of the races won to be eligible")
    ap.add_argument("--max-collisions", type=float, default=1.0, help="collisions a race to be eligible")
    ap.add_argument("--surface-weights", nargs="+", default=None, metavar="SURFACE=W",
                    help="judge eligibility on surface-weighted rates, e.g. asphalt=5 dirt=1 (the held-out race mix); needs --surfaces")
    ap.add_argument("--baseline", default=None,
                    help="compare each policy race by race with this one: one of --policy, or a race_episodes.csv of an earlier --out")
    ap.add_argument("--out", default=None, help="write each policy's race tables and plots under OUT/<policy>, the screen as OUT/screen.json")
    a = ap.parse_args(argv)
    weights = parse_surface_weights(a.surface_weights, a.surfaces) if a.surface_weights else None
    base_csv = a.baseline is not None and a.baseline.endswith(".csv")
    if a.baseline is not None and not base_csv and a.baseline not in a.policy:
        raise SystemExit(f"race_screen: --baseline {a.baseline!r} is neither one of --policy ({' '.join(a.policy)}) "
                         "nor a race_episodes.csv written by an earlier --out")
    base_races = read_races(a.baseline) if base_csv else None
    torch.set_num_threads(1)
    rows = screen(a.policy, a.tracks, episodes=a.episodes, pace=tuple(a.pace), laps=a.laps, opponents=a.opponents,
                  seed=a.seed, workers=a.workers, out=a.out, surfaces=a.surfaces)
    on = f" on {' '.join(a.surfaces)}" if a.surfaces else ""
    print(f"race screen: {' '.join(a.tracks)}{on}, {a.laps} laps against {a.opponents} experts at pace "
          f"[{a.pace[0]:g}, {a.pace[1]:g}], {a.episodes} races a track, seed {a.seed}")
    print("| policy | races | finished | wins | collisions / race | contact-free races | most in a race | "
          "other car ahead · alongside · behind | scenarios | eligible | wall [s] |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|")
    for r in rows:
        ok = eligible(r, a.min_finished, a.min_wins, a.max_collisions, weights)
        print(f"| {r['policy']} | {r['races']} | {r['finished']} | {r['wins']} | {r['collisions_per_race']:.2f} | "
              f"{r['contact_free']} | {r['most_collisions']} | {r['contacts_ahead']} · {r['contacts_alongside']} · "
              f"{r['contacts_behind']} | {r['scenarios']} | {'yes' if ok else 'no'} | {r['wall_s']:.0f} |")
    mix = f" (surface-weighted: {', '.join(f'{k} {v:g}' for k, v in weights.items())})" if weights else ""
    print(f"eligible{mix}: finished >= {a.min_finished:g}, wins >= {a.min_wins:g} of the races, <= {a.max_collisions:g} "
          "collisions a race")
    if any(len(r["by_surface"]) > 1 for r in rows):  # a driver can win its asphalt races and few on dirt: show each
        print("\nper surface:")
        print("| policy | surface | races | finished | wins | collisions / race |")
        print("|---|---|---:|---:|---:|---:|")
        for r in rows:
            for surf, v in r["by_surface"].items():
                print(f"| {r['policy']} | {surf} | {v['races']} | {v['finished']} | {v['wins']} | {v['collisions_per_race']:.2f} |")
    if weights:
        print(f"\nsurface-weighted ({', '.join(f'{k} {v:g}' for k, v in weights.items())}):")
        print("| policy | finished | wins | collisions / race | eligible |")
        print("|---|---:|---:|---:|---|")
        for r in rows:
            w = weighted_rates(r, weights)
            ok = eligible(r, a.min_finished, a.min_wins, a.max_collisions, weights)
            print(f"| {r['policy']} | {w['finished']:.3f} | {w['wins']:.3f} | {w['collisions_per_race']:.2f} | {'yes' if ok else 'no'} |")
    if a.baseline is not None:
        base = base_races if base_csv else next(r["race_rows"] for r in rows if r["policy"] == a.baseline)
        mix = "surface-weighted" if weights else "pooled"
        print(f"\npaired with {a.baseline} (the same {len(base)} races; {mix}; 95 % bootstrap over races within each surface, "
              "2000 draws, seed 0):")
        print("| policy | Δ finished share | Δ win share | Δ collisions / race |")
        print("|---|---:|---:|---:|")
        for r in rows:
            if r["policy"] == a.baseline:
                continue
            d = r["paired"] = paired_delta(r["race_rows"], base, weights)
            print(f"| {r['policy']} | " + " | ".join(f"{d[m][0]:+.3f} [{d[m][1]:+.3f}, {d[m][2]:+.3f}]"
                                                    for m in ("finished", "wins", "collisions_per_race")) + " |")
    if a.out:
        write_summary(Path(a.out) / "screen.json", a, rows, weights)
    return 0


def write_summary(path: Path, a: argparse.Namespace, rows: list[dict], weights: dict[str, float] | None) -> None:
    """The screen as one JSON file (written atomically): the protocol, the thresholds and, per policy, the counts, the
    per-surface counts, the surface-weighted rates, the eligibility and the paired difference from the baseline."""
    import json
    import os

    protocol = {k: getattr(a, k) for k in ("tracks", "surfaces", "episodes", "pace", "laps", "opponents", "seed",
                                           "min_finished", "min_wins", "max_collisions", "baseline")}
    out = {"protocol": {**protocol, "pace": list(a.pace), "surface_weights": weights}, "policies": []}
    for r in rows:
        item = {k: v for k, v in r.items() if k not in ("race_rows", "paired")}
        item["eligible"] = eligible(r, a.min_finished, a.min_wins, a.max_collisions, weights)
        if weights:
            item["weighted"] = weighted_rates(r, weights)
        if "paired" in r:
            item["paired"] = {m: {"delta": d, "ci95": [lo, hi]} for m, (d, lo, hi) in r["paired"].items()}
        out["policies"].append(item)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(out, indent=1))
    os.replace(tmp, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
