"""torcsrl.policies.registry: the specs load_policy reads — the shipped drivers by name, and the parametrised
drivers' named values against their colon forms."""

from __future__ import annotations

import re

import pytest

from torcsrl.policies import EnsemblePolicy, PolicyError, SideGuard, load_policy


def test_the_shipped_racer_reads_the_race_sensors_and_laps_alone():
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import REFERENCE_RACER_POLICY

    racer = load_policy("reference_racer")
    assert REFERENCE_RACER_POLICY.is_file() and racer.obs_keys == ("rangefinder", "state", "opponents")
    assert racer.env_overrides["control_hz"] == 10
    assert isinstance(racer, SideGuard) and racer.settings == SideGuard.DEFAULTS  # a medoid behind the default guard
    assert isinstance(racer.inner, EnsemblePolicy) and racer.inner.reduce == "medoid" and len(racer.inner.members) == 4
    rows, _ = run_cell(racer, "oval", "asphalt", laps=1)  # no opponents: its sectors read free (200 m)
    assert rows[0]["success"] and rows[0]["off_track_events"] == 0
    pol = racer.inner.members[0]  # one student: its rows batched as one car each


def _race_rows():
    """A batch of race observations: a straight road at three speeds, cars ahead, beside and behind, on asphalt and
    dirt (each row a different scene), with the friction under the car."""
    import numpy as np
    import torch
    from tensordict import TensorDict

    from ._scenes import sectors, straight_road

    rows = []
    for speed in (40.0, 120.0, 205.0):
        for cars in ({}, {"s17": 25.0}, {"s18": 12.0}, {"s9": 4.0}, {"s26": 2.0}, {"s33": 5.6}, {"s8": 40.0}, {"s17": 100.0}):
            for mu in (1.0, 0.6):
                r, st = straight_road(speed_kmh=speed)
                rows.append((r, st, sectors(**cars), mu))
    r, st, opp, mu = (np.stack([x[i] for x in rows]) for i in range(4))
    return TensorDict({"rangefinder": torch.tensor(r, dtype=torch.float32), "state": torch.tensor(st, dtype=torch.float32),
                       "opponents": torch.tensor(opp, dtype=torch.float32),
                       ("info", "surfaceMu"): torch.tensor(mu, dtype=torch.float32)[:, None]}, [len(rows)])


NAMED_AND_COLON = {
    "racer_safe(gamma=1.27,decel=8,fight_decel=9)": "racer_safe:1.27:8:9",
    "racer_safe(fight_decel=9, decel=8, gamma=1.27)": "racer_safe:1.27:8:9",  # any order, spaces allowed
    "racer_safe()": "racer_safe",
    "racer_clean(gamma=1.5)": "racer_clean:1.5",
    "racer_keep(gamma=1.27,decel=8,fight_decel=9)": "racer_keep:1.27:8:9",
    "racer_yield(gamma=1.27,decel=8,fight_decel=9,fight_m=60,clear_m=0,abandon_m=20)": "racer_yield:1.27:8:9:60:0:20",
    "racer_safe(gamma=1.27,decel=8,fight_decel=9,fight_m=150,clear_m=6)": "racer_safe:1.27:8:9:150:6",
    "side_guard(clear_m=3,gain_per_m=0.05,edge_tp=0.6):racer_safe(gamma=1.27,decel=8,fight_decel=9)":
        "side_guard:3:0.05:0.6:racer_safe:1.27:8:9",
    "side_guard():racer_yield": "side_guard:racer_yield",
}


@pytest.mark.parametrize("named", list(NAMED_AND_COLON))
def test_a_named_spec_builds_the_driver_of_its_colon_form(named):
    """``name(key=value,...)`` and the colon form it names: the same driver (gains, fingerprint, every action on the
    same observations); only the spec it records differs."""
    import torch

    a, b = load_policy(named), load_policy(NAMED_AND_COLON[named])
    assert type(a) is type(b) and a.spec == named and b.spec == NAMED_AND_COLON[named]
    inner_a, inner_b = (a.inner, b.inner) if isinstance(a, SideGuard) else (a, b)
    assert vars(inner_a.k) == vars(inner_b.k) and vars(inner_a.race) == vars(inner_b.race)
    assert inner_a.fingerprint == inner_b.fingerprint
    if isinstance(a, SideGuard):
        assert a.settings == b.settings
    td = _race_rows()
    assert torch.equal(a(td.clone())["action"], b(td.clone())["action"])


def test_named_sight_and_racer_values():
    """The camera teachers' sight by name; ``racer(...)`` / ``racer_bold(...)`` take the racer keys on their own gains
    (the cautious racer's wide corridor, the bold one's; gamma 1 unless given)."""
    import torch

    from torcsrl.policies import SensorRacer

    for named, colon in (("sensor_sight(sight_m=90)", "sensor_sight:90"), ("sensor_fast_sight(sight_m=70)", "sensor_fast_sight:70"),
                         ("sensor_fast_sight()", "sensor_fast_sight")):
        a, b = load_policy(named), load_policy(colon)
        assert vars(a.k) == vars(b.k) and a.fingerprint == b.fingerprint
        td = _race_rows()
        assert torch.equal(a(td.clone())["action"], b(td.clone())["action"])
    racer = load_policy("racer(gamma=1.27,decel=8,fight_decel=9)")
    plain = SensorRacer(grip_exponent=1.27, decel_per_mu=8.0, fight_decel_per_mu=9.0)
    assert vars(racer.k) == vars(plain.k) and vars(racer.race) == vars(plain.race) and racer.race.bend_lanes == 2.5
    bold = load_policy("racer_bold(decel=8)")
    assert bold.k.grip_exponent == 1.0 and bold.k.decel_per_mu == 8.0 and bold.race.bend_lanes == 1.0
    assert load_policy("racer_bold()").fingerprint == load_policy("racer_bold").fingerprint


def test_named_values_fail_in_one_line_naming_the_key_and_the_allowed_keys():
    racer_keys = "allowed keys: gamma, decel, fight_decel, fight_m, clear_m, abandon_m"
    cases = {
        "racer_safe(gama=1.2)": f"unknown key 'gama'; {racer_keys}",
        "racer_yield(decel=13)": f"decel (the braking rate) must be in (0, 12] m/s^2 at mu 1 (the default: 9), got 13; {racer_keys}",
        "racer_keep(fight_m=fast)": f"fight_m (the fight distance) must be a number in (0, 200] m (the opponents sensor's range), got 'fast'; {racer_keys}",
        "racer_safe(gamma=0.5)": "gamma (the grip exponent) must be >= 1",
        "racer_safe(gamma)": f"'gamma' is not key=value; {racer_keys}",
        "racer_safe(gamma=1,gamma=2)": f"gamma is given twice; {racer_keys}",
        "racer_safe(gamma=2):racer": "racer_safe(...) ends the spec",
        "sensor_sight(sight=90)": "unknown key 'sight'; allowed keys: sight_m",
        "sensor_fast_sight(sight_m=5)": "sight_m (the sight distance) must be > 8 m",
        "side_guard(clear_m=-1):racer_safe": "clear_m (the lateral room kept) must be >= 0 m",
        "side_guard(wide=3):racer_safe": "unknown key 'wide'; allowed keys: clear_m, gain_per_m, reach_m, toward, edge_tp",
        "side_guard(toward=2):racer_safe": "toward (the factor on steering toward it) must be in [0, 1]",
        "side_guard(clear_m=3)": "names no policy",
        "side_guard(clear_m=3):racer_safe(decel=20)": "decel (the braking rate) must be in (0, 12]",
        "expert(line=centre)": "expert takes no named values; named values are taken by racer, racer_bold, racer_safe",
    }
    for spec, msg in cases.items():
        with pytest.raises(PolicyError, match=re.escape(msg)) as err:
            load_policy(spec)
        assert "\n" not in str(err.value) and spec.split(":")[-1] in str(err.value), spec  # the spec (or the guarded one) named


def test_colon_specs_load_as_before_and_named_ones_are_not_builtin_names():
    """The colon forms checkpoints and result files recorded keep their spec, name and gains; ``BUILTIN_POLICIES`` (what
    tools test a spec against) is unchanged."""
    from torcsrl.policies import BUILTIN_POLICIES, RACER_SPECS

    for spec in ("racer_safe:1.27:8:9", "racer_yield:1.27:8:9:60:0:30", "racer_clean", "sensor_fast_sight:70"):
        pol = load_policy(spec)
        assert pol.spec == pol.name == spec
    assert load_policy("sensor_sight:90").spec == "sensor-grip7.5-sight90"
    assert load_policy("side_guard:3:racer_safe").spec == "side_guard:3:racer_safe"
    assert RACER_SPECS[0] == "racer_safe[:<gamma>[:<decel>[:<fight decel>[:<fight m>[:<clear m>[:<abandon m>]]]]]]"
    assert BUILTIN_POLICIES[-1] == "side_guard[:<clear m>[:<gain per m>[:<edge tp>]]]:<policy>" and len(BUILTIN_POLICIES) == 21


def test_the_command_line_reads_named_specs(capsys):
    from torcsrl.policies.cli import main

    assert main(["info", "racer_safe(gamma=1.27,decel=8)"]) == 0
    assert "'spec': 'racer_safe(gamma=1.27,decel=8)'" in capsys.readouterr().out
    assert main(["info", "racer_safe(gama=1)"]) == 2
    assert "torcsrl.policies: error: policy 'racer_safe(gama=1)': unknown key 'gama'" in capsys.readouterr().err


def test_the_shipped_ppo_driver_loads_as_reference_rl():
    """``reference_rl`` (and ``reference-rl``): the shipped PPO driver, one network on rangefinder + a state history (its
    grip head estimates the road's friction from 3 s of it), no rule."""
    from torcsrl.policies import REFERENCE_PPO_POLICY, load_policy

    assert REFERENCE_PPO_POLICY.is_file()
    for spec in ("reference_rl", "reference-rl"):
        pol = load_policy(spec)
        assert tuple(pol.obs_keys) == ("rangefinder", "state") and pol.state_history == 30
        assert pol.actor.grip_head is not None and hasattr(pol.actor, "log_std")  # PPO's tanh-Gaussian, started from a grip student
        assert pol.fingerprint == load_policy(str(REFERENCE_PPO_POLICY)).fingerprint
