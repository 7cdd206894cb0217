"""Golden outputs: behaviour pinned across refactors.

Recorded from the code before the package restructuring, 622f515 (``python tests/test_golden.py --record`` writes
``tests/golden/<instruction set>/``) and compared here through the public entry points only (``torcsrl.train.train``, the
``torcsrl.evaluate`` and ``torcsrl.report`` command lines), so the same test runs against any layout of the package:

- a seeded smoke run of every algorithm (ddpg, td3, d4pg, sac, ppo, bc, dagger) on the toy and the race env: the
  returned metrics and the final actor's parameters;
- each shipped driver (``reference``, ``reference_camera``, ``reference_racer`` in race mode) on one held-out track,
  2 laps: the rows of ``episodes.csv``;
- the default quick report (``python -m torcsrl.report``): ``robustness_summary.csv`` and ``robustness.csv``.

Floating-point kernels round differently on different instruction sets (``torch.backends.cpu.get_cpu_capability()``:
AVX2, AVX512, ...), so the outputs are recorded once per instruction set, from the same reference revision, under
``tests/golden/<instruction set>/``. Where this CPU's instruction set has a recording every number must be equal to
the bit. Elsewhere the smoke runs (a few hundred steps) are compared to a relative 1e-3 against any recording, and the
closed-loop drives (the drivers' rows, the quick report) are skipped with the reason: over two laps a last-bit
difference in a network's output grows into a different lap, so a tolerance would not hold and a recording is needed.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from _compose import compose_config

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = Path(__file__).resolve().parent / "golden"

ALGOS = ("ddpg", "td3", "d4pg", "sac", "ppo", "bc", "dagger")
ENVS = ("toy", "race")
#: (algo, env) pairs: imitation needs the race env (its teacher drives a track)
CASES = [(a, e) for a in ALGOS for e in ENVS if not (a in ("bc", "dagger") and e == "toy")]
_PER_ALGO = {
    "ppo": ["algo.rollout_steps=50", "algo.epochs=2", "algo.batch_size=32", "env.num_cars=2"],
    "bc": ["demos.frames=200", "algo.bc_steps=40"],
    "dagger": ["demos.frames=200", "algo.bc_steps=40", "demos.dagger_rounds=1", "demos.dagger_frames=60"],
}
_PER_ENV = {"toy": ["env=toy"], "race": ["env.track=oval", "env.max_steps=200", "eval.max_steps=30"]}
#: metrics that measure the machine, not the behaviour
_VOLATILE = ("wall_s", "run_dir", "checkpoint")

DRIVERS = {
    "reference": ["policy=reference", "tracks=kidney"],
    "reference_camera": ["policy=reference_camera", "tracks=kidney"],
    "reference_racer": ["policy=reference_racer", "tracks=kidney", "mode=race", "opponents=3"],
}
#: columns that measure the machine (wall-clock) or key a cache (config_hash: a hash of the source files, which any
#: edit changes by design) rather than the drive
_VOLATILE_COLUMNS = ("wall_s", "steps_per_s", "config_hash")


def _machine() -> str:
    return torch.backends.cpu.get_cpu_capability()


def _recorded() -> list[str]:
    """The instruction sets with a recording (``tests/golden/<set>/machine.json``)."""
    return sorted(p.parent.name for p in GOLDEN.glob("*/machine.json"))


def _exact() -> bool:
    return _machine() in _recorded()


def _golden_dir(closed_loop: bool = False) -> Path:
    """This instruction set's recording; without one, any recording for the (open-loop) smoke runs, and a skip for the
    closed-loop drives."""
    if _exact():
        return GOLDEN / _machine()
    if closed_loop:
        pytest.skip(f"no golden recording for this CPU's instruction set {_machine()} (recorded: {', '.join(_recorded())}): a "
                    "closed-loop drive turns last-bit rounding into different laps; record one from the reference revision "
                    "with `python tests/test_golden.py --record`")
    return GOLDEN / _recorded()[0]


def _same_number(got, want) -> bool:
    if isinstance(want, float) and math.isnan(want):
        return isinstance(got, float) and math.isnan(got)
    if _exact():
        return got == want
    return math.isclose(got, want, rel_tol=1e-3, abs_tol=1e-6)


# ---------------------------------------------------------------------------------------------------- smoke runs
def train_case(algo: str, env: str, run_dir: Path) -> dict:
    """One seeded smoke run: ``{"metrics": {...}, "policy": {name: tensor}}``."""
    try:
        from torcsrl.training import train
    except ImportError:  # the reference revision the recordings come from (622f515) predates the training package
        from torcsrl.train import train

    torch.set_num_threads(1)
    cfg = compose_config(*_PER_ENV[env], "debug=smoke", f"algo={algo}", "seed=3", *_PER_ALGO.get(algo, []),
                         f"run_dir={run_dir}")
    res = train(cfg)
    metrics = {k: (float(v) if isinstance(v, (int, float)) else v) for k, v in res.items()
               if k not in _VOLATILE and not k.startswith("time/")}
    ck = torch.load(res["checkpoint"], weights_only=False, map_location="cpu")
    key = "policy" if "policy" in ck else "actor"  # the off-policy loops save the policy module, PPO its actor
    policy = {k: v.detach().clone() for k, v in _tensors(ck[key], key).items()}
    return {"metrics": metrics, "policy": policy}


def _tensors(tree, prefix: str) -> dict[str, torch.Tensor]:
    """Every tensor of a nested dict / list, keyed by its path."""
    out: dict[str, torch.Tensor] = {}
    if isinstance(tree, torch.Tensor):
        out[prefix] = tree
    elif isinstance(tree, dict):
        for k, v in tree.items():
            out.update(_tensors(v, f"{prefix}.{k}"))
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            out.update(_tensors(v, f"{prefix}.{i}"))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("algo,env", CASES)
def test_smoke_run_is_unchanged(tmp_path, algo, env):
    want = torch.load(_golden_dir() / f"train_{algo}_{env}.pt", weights_only=False)
    got = train_case(algo, env, tmp_path / "run")
    assert sorted(got["metrics"]) == sorted(want["metrics"])
    for k, v in want["metrics"].items():
        assert _same_number(got["metrics"][k], v), (k, got["metrics"][k], v)
    assert sorted(got["policy"]) == sorted(want["policy"])
    for k, v in want["policy"].items():
        g = got["policy"][k]
        if _exact():
            assert torch.equal(g, v), k
        else:
            torch.testing.assert_close(g, v, rtol=1e-3, atol=1e-5, msg=k)


# ---------------------------------------------------------------------------------------------------- shipped drivers
def _run(module: str, *args: str) -> None:
    proc = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, text=True,
                          env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


def driver_rows(name: str, out: Path) -> list[dict]:
    _run("torcsrl.evaluate", *DRIVERS[name], "laps=2", "expert_laps=0", "plots=false", f"out={out}")
    rows_file = "race_episodes.csv" if "mode=race" in DRIVERS[name] else "episodes.csv"
    with open(out / rows_file, newline="") as f:
        return [{k: v for k, v in row.items() if k not in _VOLATILE_COLUMNS} for row in csv.DictReader(f)]


def _same_rows(got: list[dict], want: list[dict]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want):
        w = {k: v for k, v in w.items() if k not in _VOLATILE_COLUMNS}
        assert sorted(g) == sorted(w)
        for k, v in w.items():
            try:
                fv = float(v)
            except ValueError:
                assert g[k] == v, (k, g[k], v)
                continue
            assert _same_number(float(g[k]), fv), (k, g[k], v)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(DRIVERS))
def test_shipped_driver_rows_are_unchanged(tmp_path, name):
    want = json.loads((_golden_dir(closed_loop=True) / f"driver_{name}.json").read_text())
    _same_rows(driver_rows(name, tmp_path / "eval"), want)


# ---------------------------------------------------------------------------------------------------- quick report
def report_tables(out: Path) -> dict[str, list[dict]]:
    _run("torcsrl.report", "workers=1", f"out={out}")
    tables = {}
    for name in ("robustness_summary.csv", "robustness.csv"):
        with open(out / name, newline="") as f:
            tables[name] = [{k: v for k, v in row.items() if k not in _VOLATILE_COLUMNS} for row in csv.DictReader(f)]
    return tables


@pytest.mark.slow
def test_default_quick_report_is_unchanged(tmp_path):
    want = json.loads((_golden_dir(closed_loop=True) / "report.json").read_text())
    got = report_tables(tmp_path / "report")
    for name in want:
        _same_rows(got[name], want[name])


# ---------------------------------------------------------------------------------------------------- recording
def record(out: Path | None = None) -> None:
    """Write the golden files of this CPU's instruction set (``tests/golden/<set>/``) from the code as it is now (run
    it only from the reference revision: copy this file and ``_compose.py`` into its ``tests/``)."""
    import tempfile

    out = out or GOLDEN / _machine()
    out.mkdir(parents=True, exist_ok=True)
    (out / "machine.json").write_text(json.dumps({"cpu_capability": _machine(), "torch": torch.__version__}) + "\n")
    with tempfile.TemporaryDirectory() as tmp:
        for algo, env in CASES:
            if (out / f"train_{algo}_{env}.pt").is_file():
                continue
            torch.save(train_case(algo, env, Path(tmp) / f"{algo}_{env}"), out / f"train_{algo}_{env}.pt")
            print("recorded", algo, env, flush=True)
        for name in DRIVERS:
            rows = driver_rows(name, Path(tmp) / f"eval_{name}")
            (out / f"driver_{name}.json").write_text(json.dumps(rows, indent=1) + "\n")
            print("recorded", name, flush=True)
        (out / "report.json").write_text(json.dumps(report_tables(Path(tmp) / "report"), indent=1) + "\n")
        print("recorded report", flush=True)


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit("usage: python tests/test_golden.py --record   (writes tests/golden/ from the code as it is)")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    record()
