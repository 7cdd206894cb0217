"""Defect 8: nonsense settings are refused before any work, in one line naming the key and what is allowed."""

from __future__ import annotations

import math

import pytest
from _faults import cfg_for, one_line, one_line_error, run_cli, run_main

from torcsrl.config import ConfigError, problems, validate
from torcsrl.envs.rewards import Reward


def test_warmup_not_below_total_frames_is_refused():
    with pytest.raises(ConfigError, match=r"learner.warmup_frames: 600 >= total_frames 600.*no gradient step.*allowed") as e:
        validate(cfg_for("learner.warmup_frames=600", "total_frames=600"))
    assert "\n" not in str(e.value)
    validate(cfg_for("learner.warmup_frames=599", "total_frames=600"))  # one update's worth is fine


@pytest.mark.parametrize("override,key", [
    ("env.reward_scale=nan", "env.reward_scale"),
    ("env.reward_scale=inf", "env.reward_scale"),
    ("env.reward={speed_cos: nan}", "env.reward"),
    ("+env.no_progress_s=-1", "env.no_progress_s"),
    ("+env.offtrack_grace_s=-0.5", "env.offtrack_grace_s"),
])
def test_non_finite_or_negative_env_numbers_are_refused(override, key):
    found = problems(cfg_for(override, toy=False))
    assert any(p.startswith(f"{key}:") and "allowed" in p for p in found), found


def test_the_env_itself_refuses_them():
    from torcsrl.envs import make_env

    for kw in ({"reward_scale": math.nan}, {"no_progress_s": -1.0}, {"offtrack_grace_s": -1.0}):
        with pytest.raises(ValueError, match="allowed") as e:
            make_env(track="oval", **kw)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="speed_cos"):
        Reward({"speed_cos": math.nan})


def test_algo_base_names_algo_name_once():
    found = problems(cfg_for("algo=base"))
    assert any(p.startswith("algo.name: must be given") for p in found), found
    assert not any("algo.algo" in p for p in found), found


def test_algo_base_on_the_command_line_is_one_line(tmp_path):
    proc = run_cli("torcsrl.train", "algo=base", "env=toy", "debug=smoke", f"run_dir={tmp_path / 'run'}")
    line = one_line_error(proc, "torcsrl.train")
    assert "algo.name: must be given" in line and "algo.algo" not in line


def test_report_n_boot_zero_is_refused(tmp_path, capsys):
    from torcsrl.report import main

    line = one_line(*run_main(main, ["--n-boot", "0", "--out", str(tmp_path / "r"), "--policy", "expert"], capsys), "torcsrl.report")
    assert "--n-boot" in line and ">= 1" in line
    assert not (tmp_path / "r").exists()
