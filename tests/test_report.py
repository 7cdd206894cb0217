"""torcsrl.report: a tiny end-to-end report, resuming from the cell cache, common random numbers, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from torcsrl.evaluate import evaluate, run_cell
from torcsrl.policies import Policy, load_policy
from torcsrl.report import ReportConfig, build_report, main, read_rows, run_report

OUTPUTS = ("robustness.json", "robustness.csv", "robustness_summary.csv", "REPORT.md", "report.html", "nr_heatmap.png",
           "severity_curves.png")


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _strict_json(path: Path):
    def bad(x):
        raise ValueError(f"non-standard JSON constant {x}")

    return json.loads(Path(path).read_text(), parse_constant=bad)


def tiny(**kw) -> ReportConfig:
    base = dict(policies=["heuristic"], tracks=["oval"], degradations=["rangefinder.dropout"], severities=[0, 2], episodes=1,
                laps=1, max_steps=60, random_max_steps=30, workers=1, n_boot=50)
    base.update(kw)
    return ReportConfig(**base)


def test_tiny_report_writes_every_output(tmp_path):
    cfg = tiny(policies=["heuristic", "expert"], reference="heuristic", degradations=["rangefinder.dropout", "state.noise"],
               severities=[0, 1, 3], episodes=2, max_steps=80)
    res = run_report(cfg, tmp_path, verbose=False)
    for f in OUTPUTS:
        assert (tmp_path / f).is_file() and (tmp_path / f).stat().st_size > 0, f
    d = _strict_json(tmp_path / "robustness.json")
    assert d["config_hash"] and d["config"]["cell_config"]["max_steps"] == 80
    # cells: 2 policies x (clean + 2 degradations x 2 severities) + random; expert does not read the rangefinder
    cells = {(c["cell"]["policy"], c["cell"]["corruption"], c["cell"]["severity"]): c for c in d["cells"]}
    assert len(cells) == 2 * 5 + 1
    assert cells[("expert", "rangefinder.dropout", 3)].get("reused_clean") is True
    assert not cells[("heuristic", "rangefinder.dropout", 3)].get("reused_clean")
    assert res["computed"] == 2 * 5 + 1 - 2 and res["cached"] == 0 and res["reused"] == 2
    for c in d["cells"]:
        assert len(c["rows"]) == 2 and all("env_seed" in r and "degradation_seed" in r for r in c["rows"])
    s = d["summary"]
    assert s["reference"] == "heuristic" and set(s["policies"]) == {"heuristic", "expert"}
    h = s["policies"]["heuristic"]
    assert h["mce"] == pytest.approx(1.0) and h["corruptions"]["state.noise"]["severities"]["0"]["nr"] == pytest.approx(1.0)
    # the random baseline drove too, so NR is defined
    assert h["mrr"] is not None and s["r_random"]["oval/asphalt"] is not None
    lines = (tmp_path / "robustness.csv").read_text().strip().splitlines()
    assert len(lines) == 1 + 2 * len(cells)  # one row per episode
    md = (tmp_path / "REPORT.md").read_text()
    assert "## Leaderboard" in md and "**rangefinder**" in md and "**state**" in md and "![NR heatmap](nr_heatmap.png)" in md
    html = (tmp_path / "report.html").read_text()
    assert html.count("data:image/png;base64,") == 2 and "<table>" in html and "src='nr_heatmap.png'" not in html
    # a report fed from files on disk (the cell cache, like a folder of evaluation JSONs) gives the same numbers
    again = build_report(read_rows(tmp_path / "cells"), tmp_path / "from_dir", reference="heuristic", n_boot=50, verbose=False)
    assert again["summary"]["policies"]["heuristic"]["mrr"] == pytest.approx(h["mrr"])


def test_resume_skips_done_cells_and_config_or_policy_changes_invalidate(tmp_path):
    cfg = tiny(workers=2)  # the process pool
    first = run_report(cfg, tmp_path, verbose=False)
    assert (first["computed"], first["cached"]) == (3, 0)  # heuristic clean + dropout@2 + random
    again = run_report(tiny(), tmp_path, verbose=False)
    assert (again["computed"], again["cached"]) == (0, 3)
    cells = sorted((tmp_path / "cells").glob("*.json"))
    assert len(cells) == 3
    victim = next(p for p in cells if json.loads(p.read_text())["cell"]["corruption"] == "rangefinder.dropout")
    victim.unlink()
    resumed = run_report(tiny(), tmp_path, verbose=False)
    assert (resumed["computed"], resumed["cached"]) == (1, 2)
    assert victim.is_file()
    changed = run_report(tiny(max_steps=61), tmp_path, verbose=False)  # a config change recomputes everything
    assert (changed["computed"], changed["cached"]) == (3, 0)
    # results are the same whether computed or cached
    assert first["summary"]["policies"]["heuristic"]["mrr"] == pytest.approx(resumed["summary"]["policies"]["heuristic"]["mrr"])


def test_changed_policy_file_invalidates_its_cells(tmp_path):
    from test_evaluate import make_checkpoint

    ck = make_checkpoint(tmp_path / "p.pt", {"rangefinder": 19, "state": 11})
    cfg = tiny(policies=[str(ck)], max_steps=20, random_max_steps=10)
    assert run_report(cfg, tmp_path / "r", verbose=False)["computed"] == 3
    assert run_report(cfg, tmp_path / "r", verbose=False)["computed"] == 0
    from torcsrl.utils.checkpoint import save_checkpoint

    payload = torch.load(ck, weights_only=True)
    payload["actor"]["net.0.bias"] += 0.1
    save_checkpoint(ck, payload)  # a retrained policy file (edited bytes without a new checksum are refused as corrupt)
    res = run_report(cfg, tmp_path / "r", verbose=False)
    assert (res["computed"], res["cached"]) == (2, 1)  # the random baseline stays cached


class FixedActions(Policy):
    """Always the same action, under any name: identical actions for two 'policies'."""

    def __init__(self, name: str) -> None:
        self.name, self.spec, self.obs_keys, self.env_overrides = name, name, ("rangefinder", "state"), {"sensors": ("rangefinder", "state")}
        self.fingerprint = name

    def __call__(self, td):
        td.set("action", torch.tensor([0.05, 0.6]))
        return td


def _record(policy, degradation, seed=0, episodes=1, steps=15):
    seen = {}

    def obs(e, t, td):
        seen[(e, t)] = (td.get("rangefinder").clone(), td.get("state").clone())

    run_cell(policy, "oval", None, degradation, episodes=episodes, seed=seed, max_steps=steps, observer=obs)
    return seen


def test_common_random_numbers_every_policy_sees_the_same_weather():
    # two different policies: identical degraded observations at the (identical) start
    a = _record(load_policy("heuristic"), "rangefinder.noise@4", steps=1)
    b = _record(FixedActions("p0"), "rangefinder.noise@4", steps=1)
    assert torch.equal(a[(0, 0)][0], b[(0, 0)][0])
    clean = _record(load_policy("heuristic"), None, steps=1)
    assert not torch.equal(a[(0, 0)][0], clean[(0, 0)][0])  # the degradation is really there
    seen = []
    for name in ("heuristic", "expert"):  # both read "state"
        pol = load_policy(name)
        run_cell(pol, "oval", None, "state.noise@4", max_steps=1,
                 observer=lambda e, t, td: seen.append(td.get("state").clone()))
    assert torch.equal(seen[0], seen[1]) and not torch.equal(seen[0], clean[(0, 0)][1])
    # identical actions under two policy names: the same degraded stream at every step
    x = _record(FixedActions("p1"), "state.noise@3")
    y = _record(FixedActions("p2"), "state.noise@3")
    assert x.keys() == y.keys() and len(x) == 15
    assert all(torch.equal(x[k][1], y[k][1]) for k in x)
    # the draws depend on the eval seed and the episode, not on the policy
    z = _record(FixedActions("p1"), "state.noise@3", seed=1)
    assert not torch.equal(x[(0, 3)][1], z[(0, 3)][1])
    two = _record(FixedActions("p1"), "state.noise@3", episodes=2, steps=4)
    assert torch.equal(two[(0, 3)][1], x[(0, 3)][1]) and not torch.equal(two[(1, 3)][1], two[(0, 3)][1])


def test_report_reads_a_folder_of_evaluation_jsons(tmp_path):
    for i, (deg, pol) in enumerate([(None, "heuristic"), ("rangefinder.dropout@3", "heuristic"), (None, "random")]):
        evaluate(pol, "oval", laps=1, out_dir=tmp_path / "multirun" / str(i), degradation=deg, max_steps=40,
                 expert_laps=None, plots=False, verbose=False)
    rows = read_rows(tmp_path / "multirun")
    assert len(rows) == 3
    rc = main(["--from-dir", str(tmp_path / "multirun"), "--out", str(tmp_path / "rep"), "--n-boot", "20"])
    assert rc == 0
    s = _strict_json(tmp_path / "rep" / "robustness.json")["summary"]
    assert s["corruptions"] == ["rangefinder.dropout"] and s["policies"]["heuristic"]["mrr"] is not None


def test_bad_input_fails_with_one_line_before_any_work(tmp_path, capsys):
    cases = [
        (["--tracks", "nowhere"], "unknown track 'nowhere'"),
        (["--degradations", "rangefinder.smoke"], "unknown degradation 'rangefinder.smoke'"),
        (["--severities", "0"], "empty grid"),
        (["--severities", "0", "6"], "severities must be in 0..5"),
        (["--policy", str(tmp_path / "missing.pt")], "neither a checkpoint file that exists"),
        (["--policy", "random"], "random policy is the NR baseline"),
        (["--from-dir", str(tmp_path / "empty")], "does not exist"),
    ]
    out = tmp_path / "out"
    for argv, msg in cases:
        rc = main([*argv, "--out", str(out), "--workers", "1"])
        err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("[torcsrl.report] note")]
        assert rc == 2, argv
        assert len(err) == 1 and err[0].startswith("torcsrl.report: error:") and msg in err[0], (argv, err)
        assert not out.exists(), argv


def test_tiny_report_on_the_shipped_reference_driver(tmp_path):
    """The README's quick demo in miniature: the shipped policy, a few cells, every output file."""
    from torcsrl.policies import REFERENCE_POLICY, file_fingerprint

    cfg = tiny(policies=["reference"], degradations=["rangefinder.dropout"], severities=[0, 3], max_steps=60)
    run_report(cfg, tmp_path, verbose=False)
    for f in OUTPUTS:
        assert (tmp_path / f).is_file() and (tmp_path / f).stat().st_size > 0, f
    d = _strict_json(tmp_path / "robustness.json")
    assert d["summary"]["reference"] == "reference"
    cells = [c for c in d["cells"] if c["cell"]["policy"] == "reference"]
    assert {c["cell"]["severity"] for c in cells} == {0, 3}
    # cached cells are keyed by the shipped file's bytes
    assert {r["policy_fingerprint"] for c in cells for r in c["rows"]} == {file_fingerprint(REFERENCE_POLICY)}
    # 60 steps cannot finish a lap: the clean cell fails, and the summary says so instead of "breaks at 0"
    md = (tmp_path / "REPORT.md").read_text()
    assert "already fails clean" in md and "at severity 0." not in md
    assert "| fails clean |" in md and "@ 0 |" not in md  # the leaderboard says the same
