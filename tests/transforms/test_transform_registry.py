"""Names, groups, presets, stacks from config, seeding helpers, and clear errors on bad input."""

from __future__ import annotations

import pickle

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv, check_env_specs

from _toy_sensor_env import ToySensorEnv
from torcsrl.transforms import (
    HELDOUT,
    PRESETS,
    BeamDropout,
    BeamFog,
    BeamNoise,
    DeadBeams,
    DegradedEnv,
    Fog,
    KeepClean,
    Latency,
    Rain,
    applies_to,
    degradation_names,
    make_degradation,
    make_preset,
    make_stack,
    preset_names,
    seed_degradations,
)

CATALOGUE = {
    "rangefinder": "noise quantize dropout dead_beams fov_loss bias_scale stuck outliers latency "
    "scan_drop fog rain snow spray",
    "state": "noise bias latency dropout",
    "camera": "fog rain snow droplets mud glare darkness motion_blur noise occlusion frame_drop latency",
}


def test_every_catalogue_entry_is_registered():
    for sensor, effects in CATALOGUE.items():
        expected = {f"{sensor}.{e}" for e in effects.split()}
        assert set(degradation_names(sensor)) == expected


def test_sensor_grouping():
    assert "camera.fog" in degradation_names("depth")
    assert "camera.rain" not in degradation_names("depth")
    assert applies_to("camera.fog") == ("pixels", "depth")
    assert applies_to("rangefinder.fog") == ("rangefinder",)
    assert set(degradation_names("pixels")) == set(degradation_names("camera"))


def test_heldout_group():
    assert set(HELDOUT) <= set(degradation_names())
    train = degradation_names(heldout=False)
    assert not set(train) & set(HELDOUT)
    assert set(train) | set(degradation_names(heldout=True)) == set(degradation_names())
    assert preset_names(heldout=True) == ["snow"]


def test_bare_names_resolve_by_keys():
    assert isinstance(make_degradation("fog", 3, keys=["rangefinder"]), BeamFog)
    assert isinstance(make_degradation("fog", 3, keys=["pixels"]), Fog)
    both = make_degradation("fog", 3, keys=["rangefinder", "pixels", "depth"])
    assert isinstance(both, Compose) and len(both) == 2
    assert both[1].in_keys == ["pixels", "depth"]
    with pytest.raises(ValueError, match="several sensors"):
        make_degradation("fog")


def test_overrides_by_name():
    t = Fog(severity=3, beta=0.02)
    assert torch.allclose(t._ladder["beta"], torch.full((5,), 0.02))
    t = make_degradation("rangefinder.fog", 2, alpha=[0.1, 0.2, 0.3, 0.4, 0.5])
    assert t._ladder["alpha"][1].item() == pytest.approx(0.2)
    assert Latency(steps=2).buffer_len == 3


def test_preset_composes_sensors_and_skips_missing():
    p = make_preset("rain", 4)
    labels = [t.label for t in p]
    assert labels == ["camera.rain", "camera.darkness", "rangefinder.rain"]
    assert [t.severity_range[0] for t in p] == [4, 2, 4]
    assert [t.label for t in make_preset("rain", 2)] == ["camera.rain", "rangefinder.rain"]
    # an env without a camera: camera components are skipped
    base = ToySensorEnv([2])
    env = DegradedEnv(base, Compose(KeepClean(["rangefinder"]), make_preset("fog", 5)))
    check_env_specs(env)
    for name in PRESETS:
        env = DegradedEnv(ToySensorEnv([2]), make_preset(name, 3, keep_clean=True))
        td = env.rollout(3)
        assert "pixels_clean" in td.keys()


def test_stack_from_config():
    cfg = {
        "fog": {"name": "camera.fog", "severity": 3},
        "beams": "rangefinder.dropout",
        "late": {"name": "latency", "keys": ["state"], "steps": 2},
        "off": None,  # dropped by an override
        "range": {"name": "rangefinder.noise", "severity": [1, 5]},
    }
    s = make_stack(cfg, seed=0, keep_clean=["rangefinder"])
    assert [type(t).__name__ for t in s] == ["KeepClean", "Fog", "BeamDropout", "Latency", "BeamNoise"]
    assert s[4].severity_range == (1, 5)
    env = DegradedEnv(ToySensorEnv([2]), s)
    check_env_specs(env)
    assert make_degradation("weather.rain", 2)[0].label == "camera.rain"


def test_composition_example_from_the_issue():
    env = TransformedEnv(
        ToySensorEnv([2]), Compose(Fog(severity=3), BeamDropout(severity=2), Latency(steps=2))
    )
    assert env.transform[2].in_keys == []  # auto: resolved against the env's keys
    check_env_specs(env)
    assert env.transform[2].in_keys == ["rangefinder", "state", "pixels", "depth"]
    assert seed_degradations(env, 3) == 3


def test_seeding_through_env_and_clone_and_pickle():
    def run(env):
        env.set_seed(5)
        return env.rollout(5)["next", "rangefinder"]

    a = run(DegradedEnv(ToySensorEnv([2]), Compose(BeamNoise(3), BeamDropout(3))))
    b = run(DegradedEnv(ToySensorEnv([2]), Compose(BeamNoise(3), BeamDropout(3))))
    assert torch.equal(a, b)
    t = BeamNoise(3, seed=1)
    c = t.clone()
    td = TensorDict({"rangefinder": torch.full((4, 19), 50.0)}, [4])
    assert torch.equal(t(td.clone())["rangefinder"], c(td.clone())["rangefinder"])
    u = pickle.loads(pickle.dumps(BeamNoise(3, seed=1)))
    assert torch.equal(u(td.clone())["rangefinder"], BeamNoise(3, seed=1)(td.clone())["rangefinder"])


def test_time_dim_runs_as_an_episode():
    env = ToySensorEnv([2], offtrack=False)
    data = env.rollout(10)
    td = data.select("rangefinder").clone()
    td.refine_names(None, "time")
    out = Latency(steps=2, in_keys=["rangefinder"])(td)
    assert torch.equal(out["rangefinder"][:, 2:], data["rangefinder"][:, :-2])
    # a done inside the stored trajectory starts a new episode: new dead beams, fresh history
    td = data.select("rangefinder", ("next", "done")).clone()
    td["next", "done"][:, 4] = True
    td.refine_names(None, "time")
    out = DeadBeams(5, seed=0)(td)["rangefinder"] == 200.0
    assert (out[:, :5] == out[:, :1]).all() and (out[:, 5:] == out[:, 5:6]).all()
    assert not torch.equal(out[:, 0], out[:, 5])


# ------------------------------------------------------------------------ bad input
def test_unknown_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="known:.*camera.fog.*rangefinder.spray"):
        make_degradation("hail")
    with pytest.raises(ValueError, match="known"):
        make_degradation("camera.hail")
    with pytest.raises(ValueError, match="unknown preset"):
        make_preset("hail")


@pytest.mark.parametrize("bad", [0, 6, -1, (0, 3), (4, 2), (1, 2, 3)])
def test_severity_out_of_range(bad):
    with pytest.raises(ValueError, match="severity"):
        BeamNoise(bad)


@pytest.mark.parametrize("bad", ["3", 2.5, True, None])
def test_severity_wrong_type(bad):
    with pytest.raises(TypeError, match="severity"):
        BeamNoise(bad)


def test_bad_parameters():
    with pytest.raises(ValueError, match="probability"):
        BeamDropout(3, p=-0.1)
    with pytest.raises(ValueError, match="probability"):
        BeamDropout(3, p=1.5)
    with pytest.raises(ValueError, match="> 0"):
        BeamFog(3, alpha=0.0)
    with pytest.raises(TypeError, match="unknown parameter.*ladder parameters"):
        BeamNoise(3, sigma=1.0)
    with pytest.raises(ValueError, match="5"):
        BeamNoise(3, a=[0.1, 0.2])
    with pytest.raises(ValueError, match="does not degrade depth"):
        Rain(3, in_keys=["pixels", "depth"])
    with pytest.raises(ValueError, match="pair"):
        BeamNoise(3, in_keys=["rangefinder"], out_keys=["a", "b"])
    with pytest.raises(ValueError, match="cannot degrade"):
        make_degradation("rain", 3, keys=["depth"])


def test_missing_key_fails_when_attached_not_at_step_1000():
    with pytest.raises(KeyError, match="reads 'lidar', which this env does not produce"):
        TransformedEnv(ToySensorEnv([2]), BeamNoise(3, in_keys=["lidar"]))
    with pytest.raises(KeyError, match="lidar.*not found"):
        BeamNoise(3, in_keys=["lidar"])(TensorDict({"rangefinder": torch.zeros(2, 19)}, [2]))
