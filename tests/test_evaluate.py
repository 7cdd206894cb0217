"""torcsrl.evaluate and torcsrl.policies: time-trial bookkeeping, outputs, policy loading and errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from torcsrl.evaluate import EvalError, evaluate, main, parse_degradation, run_cell, seed_for
from torcsrl.policies import CheckpointPolicy, load_policy



@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _strict_json(path: Path):
    def bad(x):
        raise ValueError(f"non-standard JSON constant {x}")

    return json.loads(Path(path).read_text(), parse_constant=bad)


def make_checkpoint(path: Path, obs_layout: dict[str, int], training_format: bool = False,
                    overrides: tuple[str, ...] = ()) -> Path:
    """A torcsrl checkpoint holding a freshly initialised TD3 actor for ``obs_layout`` ({key: size})."""
    from _compose import compose_config
    from omegaconf import OmegaConf
    from torchrl.data import Bounded, Composite, Unbounded

    from torcsrl import agents
    from torcsrl.utils.checkpoint import save_checkpoint

    cfg = compose_config("debug=smoke", "env.camera=null", *overrides)
    spec = Composite({k: Unbounded((n,)) for k, n in obs_layout.items()}, shape=())
    env = type("FakeEnv", (), {"observation_spec": spec, "action_spec": Bounded(-1.0, 1.0, (2,))})()
    torch.manual_seed(0)
    actor = agents.get("td3").make_actor(cfg.algo, env, list(obs_layout))
    meta = {"algo": "td3", "obs_layout": ",".join(f"{k}:{n}" for k, n in obs_layout.items()), "action_dim": 2}
    sd = actor.state_dict()
    payload = {"meta": meta, "config": OmegaConf.to_yaml(cfg)}
    if training_format:
        payload["loss"] = {f"actor_network_params.{k}": v for k, v in sd.items()}
    else:
        payload["actor"] = sd
    return save_checkpoint(path, payload)


# ------------------------------------------------------------------------------- time trials
@pytest.mark.slow
def test_expert_time_trial_on_the_oval_books_laps_and_lap_times(tmp_path):
    res = evaluate("expert", "oval", laps=1, seed=0, out_dir=tmp_path, expert_laps=1, verbose=False)
    (ep,) = res["episodes"]
    (summ,) = res["summary"]
    assert ep["laps"] == 1 and ep["success"] and not ep["terminated"] and ep["finished"]
    assert len(ep["lap_times"]) == 1
    # grid start, lap_limit=1: the episode ends on the step that crosses the line
    assert ep["lap_times"][0] == pytest.approx(ep["steps"] * 0.02, abs=0.021)
    assert ep["fastest_lap"] == ep["mean_lap"] == ep["lap_times"][0] == summ["fastest_lap"]
    assert 30.0 < ep["fastest_lap"] < 120.0
    assert ep["distance_m"] == pytest.approx(1754.0, abs=15.0)
    assert ep["mean_speed_kmh"] == pytest.approx(ep["distance_m"] / (ep["steps"] * 0.02) * 3.6)
    assert ep["off_track_events"] == 0 and ep["steer_abs_delta"] >= 0 and ep["steer_flips_per_km"] >= 0
    assert summ["limit_lap"] > 0 and summ["vs_limit"] > 1.0  # nobody beats the physical limit
    assert summ["expert_lap"] > 0 and summ["vs_expert"] == pytest.approx(summ["fastest_lap"] / summ["expert_lap"])
    for f in ("evaluation.json", "evaluation.csv", "episodes.csv", "evaluation.md", "trajectory_oval_asphalt.png"):
        assert (tmp_path / f).is_file(), f
    d = _strict_json(tmp_path / "evaluation.json")
    assert d["summary"][0]["track"] == "oval" and d["config"]["laps"] == 1
    md = (tmp_path / "evaluation.md").read_text()
    assert "| Track | Surface | Laps | Fastest lap [s] | Mean lap [s] | Success |" in md and "| oval | asphalt | 1/1 |" in md


def test_truncated_episode_counts_no_lap_and_no_success():
    rows, _ = run_cell(load_policy("heuristic"), "oval", None, None, episodes=2, laps=1, seed=3, max_steps=40)
    assert [r["episode"] for r in rows] == [0, 1]
    for r in rows:
        assert r["steps"] == 40 and r["truncated"] and not r["terminated"]
        assert r["laps"] == 0 and not r["success"] and r["lap_times"] == [] and math.isnan(r["fastest_lap"])
        assert r["env_seed"] == seed_for(3, "env", "oval", "asphalt", r["episode"])
    assert rows[0]["return"] == pytest.approx(rows[1]["return"])  # grid start, deterministic policy


def test_random_policy_is_seeded_per_episode():
    pol = load_policy("random")
    a, _ = run_cell(pol, "oval", None, None, episodes=2, seed=0, max_steps=30)
    b, _ = run_cell(pol, "oval", None, None, episodes=2, seed=0, max_steps=30)
    assert [r["return"] for r in a] == [r["return"] for r in b]
    assert a[0]["return"] != a[1]["return"]


# ------------------------------------------------------------------------------- checkpoints
def test_checkpoint_policy_loads_both_formats_and_drives(tmp_path):
    layout = {"rangefinder": 19, "state": 11}
    slim = load_policy(str(make_checkpoint(tmp_path / "slim.pt", layout)))
    full = load_policy(str(make_checkpoint(tmp_path / "full.pt", layout, training_format=True)))
    assert isinstance(slim, CheckpointPolicy) and slim.obs_keys == ("rangefinder", "state")
    from tensordict import TensorDict

    td = TensorDict({"rangefinder": torch.rand(19) * 50, "state": torch.randn(11)}, [])
    a1 = slim(td.clone())["action"]
    a2 = full(td.clone())["action"]
    assert a1.shape == (2,) and torch.equal(a1, a2) and a1.abs().max() <= 1
    assert torch.equal(slim.as_module()(td.clone())["action"], a1)  # a TensorDictModule too
    res = evaluate(slim, "oval", laps=1, out_dir=None, max_steps=20, expert_laps=None, degradation="rangefinder.noise@2",
                   verbose=False)
    assert res["episodes"][0]["steps"] <= 20 and res["episodes"][0]["corruption"] == "rangefinder.noise"


def test_checkpoint_policy_drives_at_the_control_rate_it_was_trained_at(tmp_path):
    """A policy trained at 10 Hz is evaluated at 10 Hz (its control problem travels with it)."""
    path = make_checkpoint(tmp_path / "p10.pt", {"rangefinder": 19, "state": 11},
                           overrides=("env.control_hz=10", "env.substeps=20"))
    pol = load_policy(str(path))
    assert pol.env_overrides["control_hz"] == 10 and pol.env_overrides["substeps"] == 20
    res = evaluate(pol, "oval", laps=1, out_dir=None, max_steps=10, expert_laps=None, verbose=False)
    ep = res["episodes"][0]
    assert ep["steps"] == 10 or ep["time_s"] < 1.0 + 1e-9
    assert ep["time_s"] == pytest.approx(ep["steps"] * 0.1)


def test_checkpoint_policy_scales_observations_as_training_did(tmp_path):
    """env.normalize: the actor saw sensor readings divided by sensors.obs_scale; so must evaluation."""
    from tensordict import TensorDict

    from torcsrl.transforms import obs_scale

    layout = {"rangefinder": 19, "state": 11}
    on = load_policy(str(make_checkpoint(tmp_path / "on.pt", layout)))
    off = load_policy(str(make_checkpoint(tmp_path / "off.pt", layout, overrides=("env.normalize=false",))))
    rf, st = torch.rand(19) * 150, torch.randn(11) * 50
    td = TensorDict({"rangefinder": rf, "state": st}, [])
    scaled = on.actor(rf / torch.as_tensor(obs_scale("rangefinder")), st / torch.as_tensor(obs_scale("state")))
    assert torch.allclose(on(td.clone())["action"], scaled)
    assert torch.allclose(on.as_module()(td.clone())["action"], scaled)
    assert torch.allclose(off(td.clone())["action"], off.actor(rf, st))
    assert not torch.allclose(on.actor(rf, st), scaled)  # the scaling matters


def test_bad_inputs_fail_with_one_line_before_any_work(tmp_path, capsys):
    bad_layout = make_checkpoint(tmp_path / "toy.pt", {"rangefinder": 19, "state": 6})
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint at all")
    cases = [
        (["--policy", str(tmp_path / "missing.pt")], "neither a checkpoint file that exists"),
        (["--policy", str(corrupt)], "corrupt or truncated"),
        (["--policy", str(bad_layout)], "state of shape (6,), the env gives (11,)"),
        (["--track", "nowhere"], "unknown track 'nowhere'"),
        (["--track", "set:nothing"], "unknown track set"),
        (["--surface", "lava"], "unknown surface 'lava'"),
        (["--degradation", "rangefinder.smoke"], "unknown degradation 'rangefinder.smoke'"),
        (["--degradation", "rangefinder.fog", "--severity", "7"], "severity must be in 0..5"),
        (["--laps", "0"], "laps and episodes must be >= 1"),
    ]
    out = tmp_path / "out"
    for argv, msg in cases:
        argv = list(argv)
        argv += [] if "--track" in argv else ["--track", "oval"]
        argv += [] if "--laps" in argv else ["--laps", "1"]
        rc = main([*argv, "--out", str(out), "--no-plots", "--expert-laps", "0"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2, argv
        assert len(err) == 1 and err[0].startswith("torcsrl.evaluate: error:") and msg in err[0], (argv, err)
        assert not out.exists(), argv  # nothing was started
    with pytest.raises(EvalError, match="unknown weather preset"):
        parse_degradation("weather.hail@2")


def test_the_shipped_reference_driver_loads_with_its_config():
    """The package ships its reference driver and its RL driver (rangefinder + state), each with its summary beside it."""
    from torcsrl.policies import REFERENCE_POLICY, REFERENCE_RL_POLICY

    assert REFERENCE_RL_POLICY.is_file() and REFERENCE_RL_POLICY.with_suffix(".md").is_file()
    assert load_policy("reference-td3").algo == "td3"

    assert REFERENCE_POLICY.is_file(), "torcsrl/assets/reference_dagger.pt is the shipped reference driver"
    assert REFERENCE_POLICY.with_suffix(".md").is_file(), "its training summary ships beside it"
    ref = load_policy("reference")
    assert isinstance(ref, CheckpointPolicy) and ref.name == "reference"
    assert set(ref.obs_keys) == {"rangefinder", "state"}
    # it drives off the grid of a training track and stays on the road
    res = evaluate("reference", "oval", laps=1, seed=0, max_steps=50, plots=False, expert_laps=0, verbose=False)
    (ep,) = res["episodes"]
    assert ep["steps"] == 50 and ep["distance_m"] > 20.0 and ep["off_track_events"] == 0  # 5 s from a standstill at 10 Hz
