"""evaluate and report as Hydra apps: both configs compose, the old flags are aliases of overrides, bad input is one
line before any episode, and a multirun of evaluate feeds report --from-dir with the numbers of a direct report."""

from __future__ import annotations

import json

import pytest
import torch

from torcsrl.evaluate.app import FLAGS as EVAL_FLAGS
from torcsrl.evaluate.app import main as evaluate_main
from torcsrl.report import ReportConfig, run_report
from torcsrl.report.app import FLAGS as REPORT_FLAGS
from torcsrl.report.app import main as report_main
from torcsrl.utils.hydra_app import AppError, check_keys, compose, flags_to_overrides


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _plain(cfg) -> dict:
    from omegaconf import OmegaConf

    d = OmegaConf.to_container(cfg, resolve=False)
    d.pop("hydra", None)
    return d


def test_both_configs_compose_and_the_flags_are_aliases():
    ev = compose("evaluate", [])
    assert check_keys(ev, "evaluate")["tracks"] == "set:heldout" and ev.laps == 10 and ev.policy == "expert"
    flags = ["--policy", "reference", "--track", "set:heldout", "kidney", "--surface", "asphalt", "dirt", "--laps", "3",
             "--degradation", "rangefinder.fog", "--severity", "2", "--no-plots", "--out", "/tmp/x y"]
    keys = ["policy=reference", "tracks=[set:heldout,kidney]", "surfaces=[asphalt,dirt]", "laps=3", "corruption=rangefinder.fog",
            "severity=2", "plots=false", "out='/tmp/x y'"]
    assert _plain(compose("evaluate", flags_to_overrides(flags, EVAL_FLAGS))) == _plain(compose("evaluate", keys))
    rep = compose("report", flags_to_overrides(["--policy", "reference", "heuristic", "--severities", "0", "2", "--n-boot", "50",
                                                "episodes=3"], REPORT_FLAGS))
    d = check_keys(rep, "report")
    assert d["policies"] == ["reference", "heuristic"] and d["severities"] == [0, 2] and d["n_boot"] == 50 and d["episodes"] == 3
    assert set(d) == set(ReportConfig.__dataclass_fields__) | {"out", "cache", "from_dir"}
    race = check_keys(compose("evaluate", flags_to_overrides(["--mode", "race", "--pace", "0.85", "--opponents", "3"], EVAL_FLAGS)),
                      "evaluate")  # a decimal stays a number (it came back as the string '0.85' once)
    assert race["pace"] == 0.85 and race["opponents"] == 3 and race["mode"] == "race"
    with pytest.raises(AppError, match="unknown flag --lapz"):
        flags_to_overrides(["--lapz", "3"], EVAL_FLAGS)
    with pytest.raises(AppError, match="unknown key"):
        check_keys(compose("evaluate", ["+lapz=3"]), "evaluate")


@pytest.mark.parametrize("app,argv,msg", [
    ("evaluate", ["+foo=1"], "unknown key(s) ['foo']"),
    ("evaluate", ["foo=1"], "Could not override 'foo'"),
    ("evaluate", ["laps=abc"], "laps must be int"),
    ("evaluate", ["policy=nowhere.pt", "tracks=oval"], "neither a checkpoint file that exists"),
    ("evaluate", ["tracks=nowhere"], "unknown track 'nowhere'"),
    ("evaluate", ["tracks=oval", "corruption=rangefinder.smoke"], "unknown degradation 'rangefinder.smoke'"),
    ("evaluate", ["tracks=[]"], "empty grid"),
    ("evaluate", ["--laps", "2", "3"], "unexpected argument '3'"),
    ("report", ["+foo=1"], "unknown key(s) ['foo']"),
    ("report", ["severities=[0]"], "empty grid"),
    ("report", ["tracks=[]"], "empty grid"),
    ("report", ["degradations=[rangefinder.smoke]"], "unknown degradation"),
    ("report", ["policies=[nowhere.pt]"], "neither a checkpoint file that exists"),
    ("report", ["episodes=two"], "episodes must be int"),
    ("report", ["ray=5"], "ray must be str/null, got 5"),
    ("report", ["ray=nowhere"], "'nowhere' is not a Ray address; allowed: null (no Ray), local"),
    ("report", ["--ray", "head:port"], "'head:port' is not a Ray address"),
    ("report", ["+ray_address=auto"], "unknown key(s) ['ray_address']"),
])
def test_bad_config_is_one_line_before_any_episode(tmp_path, capsys, app, argv, msg):
    main = evaluate_main if app == "evaluate" else report_main
    out = tmp_path / "out"
    rc = main([*argv, f"out={out}"])
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and err[0].startswith(f"torcsrl.{app}: error:") and msg in err[0], (argv, err)
    assert not out.exists()


def test_evaluate_multirun_feeds_report_from_dir(tmp_path, capsys):
    """A Hydra multirun of evaluate over policies x severities (one job folder each), then report --from-dir: the same
    robustness numbers as the report that drives the cells itself."""
    sweep = tmp_path / "sweep"
    rc = evaluate_main(["-m", "policy=heuristic,random", "tracks=oval", "corruption=rangefinder.dropout", "severity=0,2", "laps=1",
                        "max_steps=40", "expert_laps=0", "plots=false", f"hydra.sweep.dir={sweep}"])
    assert rc == 0
    jobs = sorted(sweep.rglob("evaluation.json"))
    assert len(jobs) == 4  # 2 policies x 2 severities, each in its own job folder
    assert {json.loads(p.read_text())["config"]["degradation"]["severity"] for p in jobs} == {0, 2}
    rc = report_main(["--from-dir", str(sweep), "--out", str(tmp_path / "rep"), "--n-boot", "50", "--degradations",
                      "rangefinder.dropout"])
    assert rc == 0
    from_dir = json.loads((tmp_path / "rep" / "robustness.json").read_text())["summary"]
    direct = run_report(ReportConfig(policies=["heuristic"], tracks=["oval"], degradations=["rangefinder.dropout"],
                                     severities=[0, 2], episodes=1, laps=1, max_steps=40, random_max_steps=40, workers=1,
                                     n_boot=50), tmp_path / "direct", verbose=False)["summary"]
    a, b = from_dir["policies"]["heuristic"], direct["policies"]["heuristic"]
    assert a["corruptions"]["rangefinder.dropout"]["severities"]["2"]["return"] == pytest.approx(
        b["corruptions"]["rangefinder.dropout"]["severities"]["2"]["return"])
    assert a["mrr"] == pytest.approx(b["mrr"]) and from_dir["r_random"] == pytest.approx(direct["r_random"])


LIGHT_CHECK = """
import sys
from torcsrl.{app}.app import main
assert main({argv!r}) == {rc}
heavy = sorted(m for m in ("torch", "torchrl", "tensordict", "pybullet", "matplotlib", "numba") if m in sys.modules)
assert not heavy, heavy
"""


@pytest.mark.parametrize("app,argv,rc", [
    ("evaluate", ["--help"], 0),
    ("evaluate", ["--laps", "many"], 2),
    ("evaluate", ["--lapz", "3"], 2),
    ("evaluate", ["mode=rally"], 2),
    ("report", ["--help"], 0),
    ("report", ["--episodes", "0"], 2),
    ("report", ["--severities", "x"], 2),
])
def test_help_and_bad_arguments_load_no_heavy_module(app, argv, rc):
    """--help and a bad argument answer before torch, TorchRL, pybullet or matplotlib load (fast, and quiet)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", LIGHT_CHECK.format(app=app, argv=argv, rc=rc)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "pybullet build time" not in out.stdout + out.stderr


def test_import_torcsrl_registers_the_env_without_pybullet_or_torch():
    import subprocess
    import sys

    code = ("import sys, torcsrl, gymnasium as gym\n"
            "assert not {'torch', 'pybullet'} & set(sys.modules), 'heavy import'\n"
            "assert 'torcsrl/Race-v0' in gym.registry\n"
            "e = gym.make('torcsrl/Race-v0', track='oval'); e.reset(seed=0); e.close()\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout == ""


def test_evaluate_and_report_import_no_circle_and_no_private_name():
    """Within the apps' packages each module imports the others one way only, and no module reads another's _private
    names (grimp's graph counts function-level imports too)."""
    import ast
    from pathlib import Path

    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("torcsrl")
    for pkg in ("torcsrl.evaluate", "torcsrl.report"):
        mods = sorted(m for m in graph.modules if m.startswith(pkg + "."))
        for i, a in enumerate(mods):
            for b in mods[i + 1:]:
                both = graph.find_shortest_chain(importer=a, imported=b) and graph.find_shortest_chain(importer=b, imported=a)
                assert not both, f"{a} and {b} import each other"
    root = Path(__file__).resolve().parents[1] / "torcsrl"
    files = [*root.glob("evaluate/*.py"), *root.glob("report/*.py"), *root.glob("utils/*.py"), root / "sweep.py",
             root / "metrics.py"]
    bad = [f"{f.name}: from {n.module} import {a.name}" for f in files for n in ast.walk(ast.parse(f.read_text()))
           if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("torcsrl") for a in n.names
           if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, bad
