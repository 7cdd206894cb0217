"""Report cells on Ray (``ray=...``, the ``[distributed]`` extra): the same robustness metrics as the local path for the same
seeds, on Ray workers; an address that cannot be reached, ``auto`` without a cluster and Ray missing each fail in
one line within seconds, before any folder or episode; Ctrl-C cancels what is left and keeps finished cells."""

from __future__ import annotations

import json
import os
import socket
import sys
import time

import pytest
import torch

from torcsrl.evaluate import EvalError
from torcsrl.policies import REFERENCE_POLICY
from torcsrl.report import ReportConfig, run_report
from torcsrl.report.app import main as report_main
from torcsrl.utils.ray_session import RayError, check_address, probe


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def tiny(**kw) -> ReportConfig:
    # a checkpoint given as a file (batched as cars; shipped to the workers as the loaded policy) and a scripted driver
    # (one car at a time; loaded by name in the worker)
    base = dict(policies=[str(REFERENCE_POLICY), "heuristic"], tracks=["oval"], degradations=["rangefinder.dropout"],
                severities=[0, 2], episodes=2, laps=1, max_steps=50, random_max_steps=30, workers=1, n_boot=50)
    base.update(kw)
    return ReportConfig(**base)


def _no_ray_cluster(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)


@pytest.mark.parametrize("address", ["local", "auto", "10.0.0.5:6379", "ray://head:10001", "head.example.org:1"])
def test_good_addresses_pass_the_check(address):
    assert check_address(f" {address} ") == address


@pytest.mark.parametrize("address", ["", "head", "head:", "head:port", "head:0", "head:70000", "http://x/y:1", 5])
def test_a_bad_address_is_one_line_before_any_work(tmp_path, address):
    with pytest.raises(EvalError, match=r"is not a Ray address; allowed: null \(no Ray\), local") as err:
        run_report(tiny(ray=address), tmp_path / "out", verbose=False)
    assert "\n" not in str(err.value) and not (tmp_path / "out").exists()


def test_an_unreachable_address_fails_fast_with_one_line(tmp_path, capsys, monkeypatch):
    pytest.importorskip("ray")
    _no_ray_cluster(monkeypatch)
    t0 = time.perf_counter()
    with pytest.raises(EvalError, match=r"cannot reach the Ray cluster at 127\.0\.0\.1:1 \(.*within 5 s\); allowed: ") as err:
        run_report(tiny(ray="127.0.0.1:1"), tmp_path / "out", verbose=False)
    assert "\n" not in str(err.value) and not (tmp_path / "out").exists()
    # the app: exit status 2, one line
    rc = report_main(["ray=ray://127.0.0.1:1", "policies=[heuristic]", "tracks=[oval]", "severities=[0,2]",
                      "degradations=[rangefinder.dropout]", "max_steps=50", f"out={tmp_path / 'app'}"])
    err_lines = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip()]
    assert rc == 2 and len(err_lines) == 1 and "cannot reach the Ray cluster at ray://127.0.0.1:1" in err_lines[0], err_lines
    # auto with no cluster on this machine: Ray's ConnectionError, as one line
    with pytest.raises(EvalError, match=r"auto found no running Ray cluster") as err:
        run_report(tiny(ray="auto"), tmp_path / "out", verbose=False)
    assert "\n" not in str(err.value)
    assert time.perf_counter() - t0 < 20
    # a host that never answers: the probe gives up after its timeout (simulated: some networks accept every connection)
    def silent(addr, timeout):
        raise socket.timeout("timed out")

    monkeypatch.setattr(socket, "create_connection", silent)
    with pytest.raises(RayError, match=r"cannot reach the Ray cluster at ray://head:10001 \(timed out within 0\.5 s\)"):
        probe("ray://head:10001", timeout_s=0.5)


def test_ray_not_installed_is_one_line_naming_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(EvalError, match=r"needs the ray package, which is not installed: pip install 'torcsrl\[distributed\]'"):
        run_report(tiny(ray="local"), tmp_path / "out", verbose=False)
    assert not (tmp_path / "out").exists()


def _metrics(folder):
    d = json.loads((folder / "robustness.json").read_text())
    return d["summary"], {c["key"]: c["rows"] for c in d["cells"] if c.get("key")}, d["cells"]


def test_ray_report_gives_the_local_metrics(tmp_path, capsys):
    """The same grid in this process and as Ray tasks on a local Ray instance of 2 CPUs: the same metrics, bit for bit
    (every episode is seeded), computed by Ray's worker processes; Ray is shut down after, as this run started it."""
    ray = pytest.importorskip("ray")
    assert not ray.is_initialized()
    run_report(tiny(), tmp_path / "local", verbose=False)
    res = run_report(tiny(workers=2, ray="local"), tmp_path / "ray", verbose=True)
    log = capsys.readouterr().err
    assert "on Ray (a local Ray instance, 2 CPU(s))" in log, log
    assert not ray.is_initialized()  # started here, so shut down here
    s_local, rows_local, _ = _metrics(tmp_path / "local")
    s_ray, rows_ray, cells = _metrics(tmp_path / "ray")
    assert s_ray == s_local
    for key in rows_local:
        for a, b in zip(rows_local[key], rows_ray[key], strict=True):
            assert {k: v for k, v in a.items() if "wall" not in k} == {k: v for k, v in b.items() if "wall" not in k}
    # run by Ray's workers (other processes of this host), and cached by this process
    computed = [c for c in cells if c.get("computed")]
    assert len(computed) == res["computed"] == len(list((tmp_path / "ray" / "cells").glob("*.json"))) > 0
    assert f"{socket.gethostname()}:{os.getpid()}" not in {c["worker"] for c in computed}
    # a re-run finds every cell in the cache and starts no Ray at all
    again = run_report(tiny(workers=2, ray="local"), tmp_path / "ray", verbose=False)
    assert again["computed"] == 0 and not ray.is_initialized()


def test_ctrl_c_cancels_the_ray_tasks_and_keeps_finished_cells(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    import torcsrl.report.runner as runner

    written = []
    real = runner.write_json

    def write_then_stop(record, path):
        real(record, path)
        written.append(path)
        raise KeyboardInterrupt  # Ctrl-C right after the first finished cell was cached

    monkeypatch.setattr(runner, "write_json", write_then_stop)
    with pytest.raises(KeyboardInterrupt):
        run_report(tiny(policies=["heuristic"], degradations=["rangefinder.dropout", "state.noise"], severities=[0, 1, 2, 3],
                        ray="local", workers=1), tmp_path, verbose=False)
    # Ray is shut down, and the pending tasks were cancelled: only the finished cell is cached (no wall-clock bound:
    # a loaded CPU took 208 s to stop the local Ray, a timing test would measure the machine)
    assert not ray.is_initialized()
    assert len(written) == 1 and [p.name for p in (tmp_path / "cells").glob("*.json")] == [os.path.basename(written[0])]


def test_a_ray_this_process_initialised_is_used_and_left_running(monkeypatch):
    import types

    from torcsrl.utils.ray_session import ray_session

    calls = []
    fake = types.SimpleNamespace(is_initialized=lambda: True, cluster_resources=lambda: {"CPU": 3.0},
                                 init=lambda **kw: calls.append("init"), shutdown=lambda: calls.append("shutdown"))
    monkeypatch.setitem(sys.modules, "ray", fake)
    with ray_session("auto") as (ray, info):
        assert ray is fake and info.cpus == 3 and not info.started
        assert info.describe() == "the Ray instance this process had initialised, 3 CPU(s)"
    assert calls == []
