"""Curricula (torcsrl/curriculum.py, conf/curriculum/): promotion logic on synthetic validations, the stages' configs
reaching the envs, a real training run through stages that resumes exactly, and bad input in one line."""

from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf, open_dict
from tensordict import TensorDict

import torcsrl.training.offpolicy as offpolicy_mod
from torcsrl.config import ConfigError, validate
from torcsrl.training import train
from torcsrl.training.curriculum import Criterion, Curriculum, CurriculumError, Stage
from torcsrl.envs.surfaces import SURFACES
from torcsrl.pipeline import make_eval_envs, make_train_env
from torcsrl.utils.checkpoint import CheckpointError, load_checkpoint
from torcsrl.utils.logging import read_csv_metric
from torcsrl.utils.replay import ReplayBuffer
from _compose import compose_config



@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def compose_cfg(*overrides: str):
    return compose_config(*overrides)


def with_stages(cfg, stages: dict):
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.curriculum = {"stages": stages}
    return cfg


def val(laps=1.0, collisions=None, **extra):
    """One validation's metrics (what torcsrl.train.validate_all returns)."""
    m = {"eval/reward": 1.0, "eval/laps": float(laps), "eval/lap_time": math.nan, **extra}
    if collisions is not None:
        m["eval/collisions"] = float(collisions)
    return m


# ------------------------------------------------------------------------------------------- promotion logic
def test_promotion_when_the_criterion_is_met_and_not_before():
    clean_rate = Criterion("clean", at_least=0.6, over=3, rule="mean")  # clean-lap rate >= 0.6 over the last 3
    in_a_row = Criterion("eval/laps_min", at_least=1, over=2, rule="every", min_frames=100)
    cur = Curriculum([Stage("a", {}, clean_rate), Stage("b", {}, in_a_row), Stage("c", {}, None)], lap_target=1)
    # stage a: clean, unclean, clean -> 2/3 only after the third validation; a collision makes a lap unclean
    assert cur.observe(val(1), 10) is None
    assert cur.observe(val(1, collisions=1), 20) is None  # a lap, but not clean
    ev = cur.observe(val(1, collisions=0), 30, episodes=7)
    assert ev is not None and cur.stage == 1 and cur.name == "b"
    assert ev["from"] == "a" and ev["to"] == "b" and ev["frames"] == 30 and ev["episodes"] == 7 and ev["validations"] == 3
    assert ev["value"] == pytest.approx(2 / 3) and "clean >= 0.6 (mean of the last 3)" in ev["criterion"]
    # stage b: its own validations only; two in a row, and not before min_frames in the stage (entered at 30)
    assert cur.observe(val(0, **{"eval/laps_min": 0}), 40) is None
    assert cur.observe(val(1), 60) is None  # laps_min falls back to eval/laps; one in a row
    assert cur.observe(val(0.5), 70) is None  # breaks the run
    assert cur.observe(val(1), 80) is None
    assert cur.observe(val(1), 120) is None  # two in a row, but only 90 frames in the stage
    assert cur.observe(val(1), 130) is not None and cur.stage == 2
    for _ in range(5):  # the final stage is never left
        assert cur.observe(val(5), 1000) is None
    assert cur.stage == 2 and [e["to"] for e in cur.history] == ["b", "c"]


def test_criterion_thresholds_lap_targets_and_nan():
    fast = Criterion("eval/lap_time", at_most=60.0)
    assert fast.met([fast.value(val(lap_time=math.nan), 1)], 0) == (False, pytest.approx(math.nan, nan_ok=True))
    assert fast.met([fast.value({"eval/lap_time": 55.0}, 1)], 0)[0]
    clean3 = Criterion("clean", at_least=1.0)  # with eval.lap_limit = 3, a clean validation drove 3 laps
    assert clean3.value(val(2), 3) == 0.0 and clean3.value(val(3, collisions=0), 3) == 1.0
    per_track = {"eval/laps": 1.5, "eval/a/laps": 3.0, "eval/b/laps": 3.0, "eval/c/laps": 0.0, "eval/a/collisions": 1.0}
    assert clean3.value(per_track, 3) == pytest.approx(1 / 3)  # the share of validation tracks driven clean (b)
    cur = Curriculum.from_config(with_stages(compose_cfg("env=toy", "eval.lap_limit=3"), {
        "x": {"overrides": {}, "promote": {"metric": "clean", "at_least": 1}}, "y": {}}))
    assert cur.lap_target == 3 and cur.observe(val(2), 1) is None and cur.observe(val(3), 2) is not None


def test_state_round_trip_and_mismatch_is_one_line():
    stages = [Stage("a", {}, Criterion("clean", at_least=1.0, over=2)), Stage("b")]
    cur = Curriculum(stages)
    cur.observe(val(1), 5)
    state = cur.state_dict()
    other = Curriculum(stages)
    other.load_state_dict(state)
    assert other.state_dict() == state and other.observe(val(1), 9) is not None  # the window came along
    with pytest.raises(CurriculumError, match=r"written with curriculum stages \[a, b\], this config has \[a, c\]") as e:
        Curriculum([stages[0], Stage("c")]).load_state_dict(state)
    assert "\n" not in str(e.value)
    with pytest.raises(CurriculumError, match=r"stages \[none\], this config has \[a, b\]"):
        Curriculum(stages).load_state_dict(None)


# ------------------------------------------------------------------------------------------- configs and envs
def test_presets_compose_and_stages_are_cumulative():
    cfg = compose_cfg("curriculum=guppy")
    validate(cfg)
    cur = Curriculum.from_config(cfg)
    assert cur.names == ["solo", "tighter", "lower_grip", "slow_traffic", "faster_traffic"]
    assert cur.stages[-1].promote is None and all(s.promote.metric == "clean" for s in cur.stages[:-1])
    last = cur.config(cfg, 4)
    assert list(last.env.procedural.difficulty) == [0.0, 1.0] and list(last.env.surface) == ["asphalt", "wet", "dirt", "gravel"]
    assert last.env.traffic.driver.kind == "expert" and list(last.env.sensors) == ["rangefinder", "state", "opponents"]
    assert cfg.env.traffic is None and cfg.env.get("procedural").get("difficulty") is None  # the base config is untouched
    robust = compose_cfg("curriculum=robust")
    severities = [OmegaConf.to_container(Curriculum.from_config(robust).config(robust, k).degradation, resolve=True)
                  for k in range(3)]
    assert [d["stack"]["rangefinder_noise"]["severity"] for d in severities] == [1, [1, 3], [1, 5]]
    assert compose_cfg("curriculum=none").curriculum.stages == {} and not Curriculum.from_config(compose_cfg()).active


def test_stage_overrides_reach_the_rebuilt_race_env():
    """Each stage's env is built from its config: the pool circuits' difficulty, the surfaces and the traffic."""
    cfg = compose_cfg("curriculum=guppy", "debug=smoke", "env.track=oval", "env.procedural.pool=2")
    cur = Curriculum.from_config(cfg)
    solo, slow = cur.config(cfg, 0), cur.config(cfg, 3)
    env = make_train_env(solo)
    try:
        core = env.base_env.core
        assert core.traffic is None and core.surfaces == [None]
        diffs = [float(n.split("@")[1]) for n in core.track_names if "@" in n]
        assert len(diffs) == 2 and all(d <= 0.3 for d in diffs)
    finally:
        env.close()
    env, evals = make_train_env(slow), make_eval_envs(slow)
    try:
        core = env.base_env.core
        assert core.traffic_spec.opponents == 3 and core.traffic_spec.driver.kind == "slow"
        assert core.surfaces == ["asphalt", "wet", "dirt", "gravel"]
        seeds = [n.split("@")[0] for n in core.track_names if "@" in n]
        assert seeds == [n.split("@")[0] for n in make_track_names(solo)]  # the same seeds, tighter
        assert evals[""].base_env.core.traffic_spec.driver.kind == "slow"  # validation races the stage's traffic too
        td = env.rollout(3)
        assert float(td["next", "opponents"].min()) < 1.0  # normalised sectors: a car is in sight (free = 200 m = 1)
    finally:
        env.close()
        for e in evals.values():
            e.close()


def make_track_names(cfg):
    from torcsrl.envs.tracks.procedural import ProceduralSpec

    return ProceduralSpec.from_config(OmegaConf.to_container(cfg.env.procedural, resolve=True)).names(int(cfg.seed))


def test_buffer_end_episodes_cuts_streams_as_truncations():
    rb = ReplayBuffer(16, 4, ["obs"], streams=2)

    def step(o, done):
        d = torch.tensor([[done[0]], [done[1]]])
        return TensorDict({"obs": torch.full((2, 1), float(o)), "action": torch.zeros(2, 1),
                           "next": {"obs": torch.full((2, 1), o + 0.5), "reward": torch.ones(2, 1), "done": d, "terminated": d,
                                    "truncated": torch.zeros(2, 1, dtype=torch.bool)}}, batch_size=[2])

    rb.extend(step(1, (False, False)))
    rb.extend(step(2, (False, True)))  # stream 1 ended on its own (terminated)
    rb.end_episodes()  # the env is swapped here
    rb.extend(step(10, (False, False)))  # the new env's first step
    t = rb[:]
    assert t["obs"].squeeze(-1).tolist() == [1, 1, 2, 2, 10, 10]
    assert t["next", "obs"].squeeze(-1).tolist()[2:4] == [2.5, 2.5]  # the old env's last observations, not 10
    assert t["next", "done"].squeeze(-1).tolist()[2:4] == [True, True]
    assert t["next", "truncated"].squeeze(-1).tolist()[2:4] == [True, False]
    assert t["next", "terminated"].squeeze(-1).tolist()[2:4] == [False, True]  # bootstrapped / left as it was


# ------------------------------------------------------------------------------------------- training
TOY_STAGES = {
    "dry": {"overrides": {"env.surface": "asphalt"}, "promote": {"metric": "eval/laps", "at_least": 0, "over": 2, "rule": "every"}},
    "wet": {"overrides": {"env.surface": "wet"}, "promote": {"metric": "eval/laps", "at_least": 0, "over": 2}},
    "icy": {"overrides": {"env.surface": "ice", "env.track": "hairpin"}},
}


def toy(*overrides: str):
    return with_stages(compose_cfg("env=toy", "debug=smoke", "checkpoint.every_frames=400", *overrides), TOY_STAGES)


def test_training_goes_through_stages_and_resumes_the_stage_exactly(tmp_path, monkeypatch):
    built = []
    real = offpolicy_mod.make_train_env

    def spy(cfg, worker=-1, policy_loader=None):
        env = real(cfg, worker, policy_loader)
        built.append(getattr(env, "base_env", env).mu)
        return env

    monkeypatch.setattr(offpolicy_mod, "make_train_env", spy)
    ref = train(toy("total_frames=600", f"run_dir={tmp_path / 'ref'}"))
    assert ref["train/stage"] == 2 and ref["train/stage_name"] == "icy"
    assert built == [SURFACES[s].mu for s in ("asphalt", "wet", "ice")]  # each stage's env built with its overrides
    log = json.loads((tmp_path / "ref" / "curriculum.json").read_text())
    promoted = [(e["to"], e["frames"]) for e in log["promotions"]]
    assert [to for to, _ in promoted] == ["wet", "icy"] and promoted[0][1] < 400 < promoted[1][1]  # one on each side of the cut
    stages = read_csv_metric(tmp_path / "ref", "train/stage")
    assert stages[0] == (100, 0.0) and stages[-1] == (600, 2.0)
    assert [s for s, _ in read_csv_metric(tmp_path / "ref", "curriculum/promotion")] == [f for _, f in promoted]

    train(toy("total_frames=400", f"run_dir={tmp_path / 'cut'}"))
    ck = load_checkpoint(tmp_path / "cut" / "checkpoints" / "ckpt_000000000400.pt")
    assert ck["curriculum"]["stage"] == 1 and len(ck["curriculum"]["values"]) == 1  # mid-stage: one validation booked
    res = train(toy("total_frames=600", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"))
    for k in ("frames", "updates", "episodes", "loss/qvalue", "eval/reward", "train/stage"):
        assert res[k] == ref[k], k
    for m in ("loss/qvalue", "train/episode_reward", "train/stage", "curriculum/promotion", "eval/reward"):
        assert read_csv_metric(tmp_path / "cut", m) == read_csv_metric(tmp_path / "ref", m), m
    assert json.loads((tmp_path / "cut" / "curriculum.json").read_text())["promotions"] == log["promotions"]

    other = dict(TOY_STAGES)
    other["snowy"] = other.pop("icy")
    with pytest.raises(CheckpointError, match=r"stages \[dry, wet, icy\], this config has \[dry, wet, snowy\]; allowed") as e:
        train(with_stages(toy("total_frames=900", f"run_dir={tmp_path / 'cut'}", "checkpoint.resume=latest"), other))
    assert "\n" not in str(e.value)


# ------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("stages,match", [
    ({"a": {"overrides": {"env.surfce": "ice"}, "promote": {"metric": "clean", "at_least": 1}}, "b": {}},
     r"curriculum.stages.a.overrides: unknown key 'env.surfce' \(env=toy has no 'surfce'\); allowed: env.<.*surface"),
    ({"a": {"overrides": {"algo.gamma": 0.9}, "promote": {"metric": "clean", "at_least": 1}}, "b": {}},
     r"curriculum.stages.a.overrides: unknown key 'algo.gamma'; allowed: env.<.*>.*, eval.env.<the same>, degradation.severity"),
    ({"a": {"overrides": {"env.sensors": ["state"]}, "promote": {"metric": "clean", "at_least": 1}}, "b": {}},
     r"env.sensors cannot change between stages .*; allowed: env.<"),
    ({"a": {"overrides": {"env.surface": "ice"}}, "b": {}},
     r"curriculum.stages.a: a stage before the last needs a promotion criterion, promote: .*only the final stage \(b\) may"),
    ({"a": {"promote": {"metric": "eval/lapz", "at_least": 1}}, "b": {}},
     r"curriculum.stages.a.promote.metric: unknown metric 'eval/lapz'; allowed: clean, eval/laps, eval/laps_min"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1, "over": 0}}, "b": {}}, r"promote.over: expected a positive integer"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1, "rule": "median"}}, "b": {}}, r"promote.rule: unknown rule 'median'; allowed: mean, every"),
    ({"a": {"promote": {"metric": "clean"}}, "b": {}}, r"give exactly one threshold, at_least or at_most"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {"overrides": {"env.surface": "lava"}}},
     r"curriculum.stages.b: env.surface: the toy env takes one surface of asphalt, .* got 'lava'"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {}, "rehearse": {"stage": "b", "frames": 10}},
     r"curriculum.rehearse.stage: 'b' is not a stage before the last; allowed: a"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {}, "rehearse": {"stage": "a", "frames": 0}},
     r"curriculum.rehearse.frames: expected a positive integer"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {}, "rehearse": {"stage": "a", "frame": 10}},
     r"curriculum.rehearse.frame: unknown key; allowed: stage, frames, overrides"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {}, "rehearse": {"stage": "a", "frames": 10, "overrides": {"algo.gamma": 0.9}}},
     r"curriculum.rehearse.overrides: unknown key 'algo.gamma'; allowed: env.<"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {}, "rehearse": {"stage": "a", "frames": 10, "overrides": {"env.sensors": ["state"]}}},
     r"env.sensors cannot change between stages"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {}, "rehearse": {"stage": "a", "frames": 10, "overrides": [1]}},
     r"curriculum.rehearse.overrides: expected a mapping"),
    ({"a": {"promote": {"metric": "clean", "at_least": 1}}, "b": {"overrides": {"degradation.severity": 4}}},
     r"curriculum.stages.b: overrides degradation.severity but degradation.stack is empty"),
])
def test_bad_curricula_fail_in_one_line(stages, match):
    cfg = with_stages(compose_cfg("env=toy"), {k: v for k, v in stages.items() if k != "rehearse"})
    if "rehearse" in stages:
        with open_dict(cfg):
            cfg.curriculum.rehearse = stages["rehearse"]
    with pytest.raises(ConfigError, match=match) as e:
        validate(cfg)
    assert "\n" not in str(e.value)


def test_bad_race_stage_and_algos_without_stages():
    cfg = with_stages(compose_cfg(), {"a": {"overrides": {"env.traffic.opponents": 2}, "promote": {"metric": "clean", "at_least": 1}},
                                      "b": {}})
    with pytest.raises(ConfigError, match=r"env.traffic.opponents sets 'opponents' inside env.traffic, which is null at this stage"):
        validate(cfg)
    cfg = with_stages(compose_cfg(), {"a": {"overrides": {"env.traffic": {"opponents": 20}}, "promote": {"metric": "clean", "at_least": 1}},
                                      "b": {}})
    with pytest.raises(ConfigError, match=r"curriculum.stages.a: env.traffic: .*grid"):
        validate(cfg)
    with pytest.raises(ConfigError, match=r"curriculum: algo=ppo does not follow a curriculum .*; allowed: curriculum=none"):
        validate(compose_cfg("algo=ppo", "curriculum=robust"))
    with pytest.raises(ConfigError, match=r"curriculum.rehearse: algo=td3 cannot rehearse an earlier stage .*; allowed: algo=dagger"):
        validate(compose_cfg("algo=td3", "curriculum=guppy", "curriculum.rehearse={stage:solo,frames:100}"))
    # the rehearsal's own overrides are checked like a stage's config, and named as the rehearsal's
    with pytest.raises(ConfigError, match=r"^invalid config: curriculum.rehearse: env.surface: unknown surface 'lava'; allowed: asphalt"):
        validate(compose_cfg("experiment=racer", "curriculum.rehearse={stage:solo,frames:100,overrides:{env.surface:lava}}"))
    cfg = compose_cfg("experiment=racer", "curriculum.rehearse={stage:solo,frames:100,overrides:{env.procedural.generator:proc}}")
    validate(cfg)
    cur = Curriculum.from_config(cfg)
    assert cur.rehearsal_config(cfg).env.procedural.generator == "proc"  # on top of the solo stage's config
    assert cur.config(cfg, 0).env.procedural.generator == cur.config(cfg, 2).env.procedural.generator == "gen"  # the stages keep theirs


def test_bc_refuses_a_curriculum_and_dagger_rounds_follow_its_stages(tmp_path, monkeypatch):
    """algo=bc has no rounds to follow stages (one line); algo=dagger's rounds drive the stage's env (here: the second
    stage puts 2 scripted cars in the learner's race), a round's validation promotes, the checkpoint keeps the stage."""
    with pytest.raises(ConfigError, match=r"curriculum: algo=bc does not follow a curriculum .*algo=dagger"):
        validate(compose_cfg("algo=bc", "curriculum=racer", "demos.frames=100"))
    cfg = compose_cfg("experiment=racer", "demos.frames=300", "demos.episode_steps=150", "algo.bc_steps=20", "algo.batch_size=32",
                      "demos.dagger_rounds=2", "demos.dagger_frames=150", "eval.max_steps=40", "eval.per_track=false",
                      "eval.env.track=oval", "env.track=oval", "env.procedural.share=0.0", f"run_dir={tmp_path}",
                      "progress=false", "curriculum.stages.solo.promote.at_least=0.0")
    with open_dict(cfg):
        cfg.curriculum.stages.pop("slow_traffic")
        cfg.curriculum.stages.experts.overrides["env.traffic"] = {"opponents": 2, "driver": {"kind": "expert", "pace": 0.5},
                                                                   "start": "grid", "order": "fixed", "learner_slot": "last"}
        cfg.curriculum.stages.experts.overrides["eval.env.traffic"] = None
        # every round in experts also drives 160 frames alone, on another track (the rehearsal's own override)
        cfg.curriculum.rehearse = {"stage": "solo", "frames": 160, "overrides": {"env.track": "hairpins"}}
    validate(cfg)
    seen: list = []
    tracks: list = []
    import torcsrl.training.demos as demos_mod
    import torcsrl.training.imitation as imitation_mod

    real_demo_env = demos_mod.make_demo_env

    def spy_demo_env(c, seed):  # the real env; only notes how many cars each demonstration / DAgger env races
        env = real_demo_env(c, seed)
        seen.append(int(c.env.traffic.opponents) if c.env.traffic else 0)
        tracks.append(str(c.env.track))
        assert "opponents_clean" in env.observation_spec.keys()  # the racer teacher reads the clean sectors
        return env

    monkeypatch.setattr(demos_mod, "make_demo_env", spy_demo_env)  # the demonstrations
    monkeypatch.setattr(imitation_mod, "make_demo_env", spy_demo_env)  # the DAgger rounds
    out = train(cfg)
    assert out["train/stage_name"] == "experts" and out["train/stage"] == 1
    # the demonstrations alone; then each DAgger round among 2 cars, and its rehearsal alone (curriculum.rehearse)
    assert seen == [0, 2, 0, 2, 0]
    assert tracks == ["oval", "oval", "hairpins", "oval", "hairpins"]  # the rehearsal's overrides apply to it alone
    ck = load_checkpoint(out["checkpoint"])
    assert ck["counters"]["frames"] == 2 * (150 + 160) and ck["curriculum"]["stage"] == 1
    rehearsed = [v for _, v in read_csv_metric(tmp_path, "train/rehearsal_episodes")]
    assert len(rehearsed) == 2 and min(rehearsed) >= 1  # 160 frames of 150-step episodes: at least one ends per round
    summary = json.loads((tmp_path / "curriculum.json").read_text())
    assert summary["stage"] == 1 and [h["to"] for h in summary["promotions"]] == ["experts"]
    assert summary["rehearse"] == {"stage": 0, "name": "solo", "frames": 160, "overrides": {"env.track": "hairpins"}}
    # logged against the loop's x axis (updates: one fit of algo.bc_steps per round), like every imitation metric
    assert [s for s, _ in read_csv_metric(tmp_path, "curriculum/promotion")] == [20]
    assert [v for _, v in read_csv_metric(tmp_path, "train/stage")][-1] == 1.0
