"""The Hydra config tree: every group option composes, every combination validates, bad values fail fast.

Composition is expensive (Hydra reloads ~100 files per compose), so every group option is composed once with
Hydra, and the algo x sensors x degradation x surface product is assembled from those (the groups write disjoint
keys, which the first test checks) and validated with :func:`torcsrl.config.problems` -- the check
``python -m torcsrl.train`` runs before building anything.
"""

from __future__ import annotations

import copy
import itertools
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException, MissingConfigException
from omegaconf import OmegaConf
from tensordict import TensorDict

from torcsrl.config import ConfigError, problems, validate
from torcsrl.envs import surfaces, tracks
from torcsrl.envs.rewards import PRESETS as REWARD_PRESETS
from torcsrl.envs.sensors import STATE_SLOTS
from torcsrl.transforms import degradation_names, make_stack, preset_names
from torcsrl.transforms.registry import applies_to
from _compose import compose_config

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"

#: group -> the config keys its options may write (so options of different groups combine freely)
FOOTPRINT = {
    "algo": ("algo",),
    "sensors": ("env.sensors", "env.camera"),
    "surface": ("env.surface",),
    "degradation": ("degradation",),
    "track": ("env.track", "env.procedural"),
    "reward": ("env.reward",),
    "vehicle": ("env.vehicle", "env.vehicle_overrides"),
    "traffic": ("env.traffic",),
}
#: the groups of the combination test
PRODUCT = ("algo", "sensors", "degradation", "surface")


def options(group: str) -> list[str]:
    return sorted(p.name[: -len(".yaml")] for p in (CONF / group).glob("*.yaml") if p.name != "base.yaml")


def compose_cfg(*overrides: str, hydra: bool = False):
    return compose_config(*overrides, hydra=hydra)


def flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out.update(flat(v, key + "."))
        else:
            out[key] = v
    return out


def get(d, dotted):
    for part in dotted.split("."):
        d = d[part]
    return d


def put(d, dotted, value):
    *head, last = dotted.split(".")
    for part in head:
        d = d[part]
    d[last] = copy.deepcopy(value)


@pytest.fixture(scope="module")
def composed():
    """The default config and one config per option of each combined group (plain resolved dicts)."""
    out = {}
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        base = OmegaConf.to_container(compose("train"), resolve=True)
        for group in FOOTPRINT:
            for opt in options(group):
                out[group, opt] = OmegaConf.to_container(compose("train", overrides=[f"{group}={opt}"]), resolve=True)
    return base, out


# --------------------------------------------------------------------------------------------- the tree
def test_groups_cover_the_registries():
    assert set(tracks.names()) <= set(options("track"))
    assert {"default", "train_set", "heldout_set", "generated"} <= set(options("track"))
    assert set(surfaces.ROAD_SURFACES) | {"default", "mixed", "randomised"} == set(options("surface"))
    assert set(REWARD_PRESETS) | {"andersson"} == set(options("reward"))
    expected = set(degradation_names()) | {f"weather.{p}" for p in preset_names()} | {"none", "randomised"}
    assert expected == set(options("degradation"))
    assert {"rangefinder", "pixels", "both", "camera"} == set(options("sensors"))
    assert not list(CONF.rglob("__init__.py"))


def test_default_config_is_the_documented_pipeline():
    cfg = compose_cfg(hydra=True)
    choices = cfg.hydra.runtime.choices
    for group, opt in [("algo", "td3"), ("env", "race"), ("track", "default"), ("surface", "default"), ("sensors", "rangefinder"),
                       ("reward", "summers_final"), ("degradation", "none"), ("vehicle", "default"), ("logger", "csv")]:
        assert choices[group] == opt
    assert cfg.env.track == "oval" and cfg.env.surface is None and list(cfg.env.sensors) == ["rangefinder", "state"]
    assert cfg.degradation.stack == {} and problems(cfg) == []
    assert OmegaConf.to_container(cfg.hydra.sweep)["subdir"] == "${hydra.job.num}_${hydra.job.override_dirname}"


def test_group_options_write_only_their_own_keys(composed):
    base, out = composed
    fb = flat(base)
    for (group, opt), cfg in out.items():
        changed = {k for k, v in flat(cfg).items() if fb.get(k, object()) != v} | (set(fb) - set(flat(cfg)))
        stray = [k for k in changed if not any(k == p or k.startswith(p + ".") for p in FOOTPRINT[group])]
        if group == "algo":  # logger.exp_name is ${algo.name}
            stray = [k for k in stray if k != "logger.exp_name"]
        assert not stray, f"{group}={opt} writes {stray} outside {FOOTPRINT[group]}"


def test_every_group_option_validates_on_its_own(composed):
    base, out = composed
    for (group, opt), cfg in out.items():
        found = problems(cfg)
        assert found == [] or group == "degradation" and opt.startswith(("camera.", "weather.night", "opponents.")), (group, opt, found)
    # and the values reach make_env's keywords
    assert out["track", "heldout_set"]["env"]["track"] == "set:heldout"
    assert out["track", "generated"]["env"]["track"] == "gen-7"
    assert out["surface", "randomised"]["env"]["surface"] == list(surfaces.ROAD_SURFACES)
    assert out["reward", "andersson"]["env"]["reward"] == {"preset": "lau", "termination": -500.0}
    assert out["sensors", "both"]["env"]["camera"]["mount"] == "hood"


def _touches(stack: dict, sensors: list[str]) -> bool:
    """Whether some entry of a resolved stack degrades one of ``sensors`` (what the env observes)."""
    from torcsrl.transforms.registry import PRESETS

    for e in stack.values():
        name = e["name"]
        if name.startswith("weather."):
            keys = {k for c, _, kw in PRESETS[name[8:]] for k in kw.get("in_keys", applies_to(c)[:1])}
        else:
            keys = set(applies_to(name))
        if keys & set(sensors) or e.get("optional"):
            return True
    return not stack


def test_every_algo_sensors_degradation_surface_combination(composed):
    """Compose (from the per-option configs) and validate all of them; instantiate every stack once."""
    base, out = composed
    n = bad = 0
    stack_ok: dict[str, bool] = {}
    for algo, sens, deg, surf in itertools.product(*(options(g) for g in PRODUCT)):
        cfg = copy.deepcopy(base)
        for group, opt in (("algo", algo), ("sensors", sens), ("degradation", deg), ("surface", surf)):
            for key in FOOTPRINT[group]:
                put(cfg, key, get(out[group, opt], key))
        found = problems(cfg)
        n += 1
        sensors = cfg["env"]["sensors"]
        if deg not in stack_ok:
            stack_ok[deg] = True
            make_stack(cfg["degradation"]["stack"], seed=0)  # builds
        if _touches(cfg["degradation"]["stack"], sensors):
            assert found == [], (algo, sens, deg, surf, found)
        else:  # e.g. camera.fog on rangefinder + state: refused before training, by name
            bad += 1
            assert len(found) == 1 and "does not include" in found[0] and deg.replace(".", "_") in found[0], found
    assert n == len(options("algo")) * len(options("sensors")) * len(options("degradation")) * 8
    assert 0 < bad < n


def test_every_degradation_option_degrades_sensor_readings(composed):
    """Each stack from config runs on a batch of clean readings (2 envs), at its lowest and highest severity."""
    _, out = composed
    gen = torch.Generator().manual_seed(0)
    clean = TensorDict({
        "rangefinder": torch.rand(2, 19, generator=gen) * 150 + 5,
        "state": torch.rand(2, len(STATE_SLOTS), generator=gen),
        "pixels": (torch.rand(2, 3, 32, 32, generator=gen) * 255).to(torch.uint8),
        "depth": torch.rand(2, 1, 32, 32, generator=gen) * 80 + 1,
        "opponents": torch.where(torch.rand(2, 36, generator=gen) < 0.2, torch.rand(2, 36, generator=gen) * 150, torch.full((2, 36), 200.0)),
    }, batch_size=[2])
    for opt in options("degradation"):
        stack = out["degradation", opt]["degradation"]["stack"]
        for sev in ([1, 5] if opt not in ("none",) and not opt.startswith("weather.") else [None]):
            s = copy.deepcopy(stack)
            for e in s.values():
                e["severity"] = e["severity"] if sev is None else sev
            t = make_stack(s, seed=1)
            td = t(clean.clone())
            assert set(td.keys()) >= set(clean.keys()), opt


#: Presets that start from a checkpoint the user trains first (what to pass, here any file: validation does not read it).
NEEDS = {"generalise_rl_grip": ("init.actor=runs/grip/checkpoints/ckpt_000000075000.pt",)}


def test_experiment_presets_compose_validate_and_only_override():
    for exp in options("experiment"):
        text = (CONF / "experiment" / f"{exp}.yaml").read_text()
        assert text.startswith("# @package _global_\n# Reproduces:"), exp
        assert "differ" in text, f"{exp}: the header says how our setup differs from the original"
        need = NEEDS.get(exp, ())
        cfg = compose_cfg(f"experiment={exp}", *need, hydra=True)
        assert problems(cfg) == [], (exp, problems(cfg))
        if need:  # a preset that starts from a run's checkpoint says so in one line without it
            bare = problems(compose_cfg(f"experiment={exp}", hydra=True))
            assert len(bare) == 1 and "init.actor=" in bare[0], (exp, bare)
        smoke = compose_cfg(f"experiment={exp}", "env=toy", "env.track=oval", "debug=smoke", "++eval.env.track=oval")
        assert smoke.total_frames == 600, exp
    s = compose_cfg("experiment=summers2022")
    assert s.algo.name == "td3" and s.env.reward == "summers_final" and list(s.env.track) == ["fast_straights", "hairpins"]
    assert list(s.env.surface) == ["asphalt", "dirt"]
    heldout = set(tracks.track_sets()["heldout"])
    for exp in ("summers2022", "summers_road", "summers_dirt"):  # neither trained nor validated on a held-out track
        c = compose_cfg(f"experiment={exp}")
        trained = [c.env.track] if isinstance(c.env.track, str) else list(c.env.track)
        validated = [c.eval.env.track] if isinstance(c.eval.env.track, str) else list(c.eval.env.track)
        assert not heldout & set(trained + validated), exp
    a = compose_cfg("experiment=andersson")
    assert a.algo.name == "ddpg" and list(a.algo.actor_hidden) == [300, 600] and a.env.track == "oval"
    assert list(a.algo.exploration.theta) == [0.6, 1.0] and list(a.algo.exploration.mu) == [0.0, 0.5]
    assert a.env.reward.termination == -500.0
    assert compose_cfg("experiment=degradation_study").degradation.stack == {}
    r = compose_cfg("experiment=robust_training")
    assert list(r.degradation.severity) == [1, 5] and len(r.degradation.stack) == len(degradation_names(heldout=False))
    assert compose_cfg("experiment=multitrack").env.track == "set:train"


def test_debug_smoke_shrinks_every_group_combination():
    cfg = compose_cfg("env=toy", "debug=smoke", "sensors=pixels", "degradation=camera.fog", "experiment=andersson", "env.track=oval",
                      "env.reward=summers_final")
    assert cfg.total_frames == 600 and cfg.env.camera.height == 32 and cfg.algo.actor_hidden == [32, 32]
    assert problems(cfg) == []


def test_launcher_presets_compose():
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    cfg = compose_cfg("hydra/launcher=parallel", hydra=True)
    assert cfg.hydra.launcher._target_.endswith("JoblibLauncher") and cfg.hydra.launcher.n_jobs == 2


def test_slurm_preset_composes():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="hydra-submitit-launcher is not installed ([sweeps] extra)")
    cfg = compose_cfg("hydra/launcher=slurm", hydra=True)
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher") and cfg.hydra.launcher.partition is None
    cfg = compose_cfg("hydra/launcher=slurm", "hydra.launcher.partition=gpu", hydra=True)
    assert cfg.hydra.launcher.partition == "gpu" and cfg.hydra.launcher.timeout_min == 1440


# ------------------------------------------------------------------------------------------- fail fast
def one_problem(*overrides: str, hydra: bool = False) -> str:
    with pytest.raises(ConfigError) as e:
        validate(compose_cfg(*overrides, hydra=hydra))
    return str(e.value)


def test_misspelt_keys_fail_at_composition_or_validation():
    with pytest.raises(ConfigCompositionException, match="algo.batchsize"):
        compose_cfg("algo.batchsize=3")
    msg = one_problem("+algo.batchsize=3")
    assert "algo.batchsize: unknown key (did you mean algo.batch_size?)" in msg and "conf/algo/base.yaml" in msg
    msg = one_problem("+env.trak=kidney")
    assert "env.trak: unknown key (did you mean env.track?)" in msg and "surface" in msg
    assert "eval.env.surfce" in one_problem("+eval.env.surfce=ice")
    assert "degradation.stack.fog" in one_problem("+degradation.stack.fog.name=rangefinder.fog", "+degradation.stack.fog.sevrity=2")


def test_wrong_types_name_the_key():
    assert "total_frames: expected an integer like 100000, got 'lots'" in one_problem("total_frames=lots")
    assert "env.num_cars: expected an integer, got 'two'" in one_problem("env.num_cars=two")
    assert "algo.actor_lr: expected a number" in one_problem("algo.actor_lr=fast")
    assert "env.normalize: expected a boolean" in one_problem("env.normalize=3")
    assert "algo.gamma: 1.5 is out of range; allowed: [0, 1]" in one_problem("algo.gamma=1.5")


def test_severity_out_of_range():
    msg = one_problem("degradation=rangefinder.fog", "degradation.severity=7")
    assert "degradation.severity: severity must be an integer in 1..5" in msg and "got 7" in msg
    msg = one_problem("degradation=rangefinder.fog", "degradation.stack.rangefinder_fog.severity=[4,9]")
    assert "degradation.stack.rangefinder_fog.severity" in msg and "1..5" in msg
    assert "preset severity must be an int" in one_problem("degradation=weather.rain", "degradation.severity=[1,3]")
    msg = one_problem("degradation=randomised", "degradation.p=2")  # one line, not one per stack entry
    assert msg.count("\n") == 0 and "degradation.p=2: the probability" in msg and "allowed: 0 < p <= 1" in msg


def test_unknown_names_list_the_allowed_ones():
    msg = one_problem("env.track=monza")
    assert "env.track: unknown track 'monza'" in msg and "oval" in msg and "set:heldout" in msg
    msg = one_problem("env.surface=sand")
    assert "env.surface: unknown surface 'sand'" in msg and "gravel" in msg
    msg = one_problem("env.reward=fast")
    assert "env.reward" in msg and "summers_final" in msg
    msg = one_problem("env.sensors=[rangefinder,lidar]")
    assert "env.sensors" in msg and "pixels" in msg
    msg = one_problem("+degradation.stack.x.name=rangefinder.fgo")
    assert "degradation.stack.x: unknown degradation 'rangefinder.fgo'" in msg and "rangefinder.fog" in msg
    msg = one_problem("collector.worker_tracks=[oval,monza]")
    assert "collector.worker_tracks[1]: unknown track 'monza'" in msg
    msg = one_problem("env=toy", "track=train_set")
    assert "env.track: unknown toy track 'set:train'" in msg and "stadium" in msg
    msg = one_problem("env=toy", "+env.vehicle=default")
    assert "env.vehicle: the toy env has no 'vehicle'" in msg
    with pytest.raises(MissingConfigException, match="kidney"):  # a group option that does not exist lists the others
        compose_cfg("track=monza")
    assert "algo.name: unknown algorithm 'a2c'" in one_problem("algo.name=a2c")


def test_frame_stacks_need_images_and_a_sensible_size():
    assert "frame_stack: expected an integer from 1 to 16" in one_problem("frame_stack=0")
    assert "frame_stack: expected an integer from 1 to 16" in one_problem("frame_stack=three")
    msg = one_problem("frame_stack=3")  # the default sensors: rangefinder + state, no image to stack
    assert "frame_stack=3 stacks image observations" in msg and "sensors=camera" in msg
    assert "algo=ppo is not built for frame stacks" in one_problem("algo=ppo", "sensors=camera", "frame_stack=2")
    assert not problems(compose_cfg("sensors=camera", "frame_stack=4"))


def test_missing_mandatory_values_are_named():
    assert "algo.name: must be given" in one_problem("algo.name=???")


def test_the_command_line_fails_fast_with_the_message(tmp_path):
    """python -m torcsrl.train ... exits 2 with the message before building anything."""
    proc = subprocess.run([sys.executable, "-m", "torcsrl.train", "env=toy", "debug=smoke", "degradation=rangefinder.fog",
                           "degradation.severity=7", f"hydra.run.dir={tmp_path}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "torcsrl.train: error: invalid config" in proc.stderr and "degradation.severity" in proc.stderr
    assert "training" not in proc.stderr and not (tmp_path / "checkpoints").exists() and not (tmp_path / "config.yaml").exists()


# --------------------------------------------------------------------------------------- reproducibility
def test_same_config_and_seed_give_the_same_metrics(tmp_path):
    from torcsrl.training import train

    torch.set_num_threads(1)
    ov = ["env=toy", "debug=smoke", "total_frames=250", "eval.every_episodes=1", "checkpoint.buffer=false",
          "degradation=[rangefinder.noise,state.noise]", "degradation.severity=[1,5]"]
    a = train(compose_cfg(*ov, f"run_dir={tmp_path / 'a'}"))
    b = train(compose_cfg(*ov, f"run_dir={tmp_path / 'b'}"))
    c = train(compose_cfg(*ov, f"run_dir={tmp_path / 'c'}", "seed=1"))
    keys = [k for k in a if k.startswith(("loss/", "eval/")) or k in ("frames", "updates", "episodes")]
    assert keys and any(k.startswith("eval/") for k in keys)
    same = lambda x, y: x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))  # noqa: E731
    assert all(same(a[k], b[k]) for k in keys), {k: (a[k], b[k]) for k in keys}
    assert any(not same(a[k], c[k]) for k in keys)
