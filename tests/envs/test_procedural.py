"""Procedural training distributions: pools of generated tracks in the race env, seed ranges kept apart."""

from __future__ import annotations

import pytest

from torcsrl.envs import make_env
from torcsrl.envs.tracks.procedural import HELDOUT_SEEDS, TRAIN_SEEDS, ProceduralSpec, heldout_names


def test_pool_is_seeded_distinct_and_inside_the_training_range():
    spec = ProceduralSpec.from_config({"seeds": [20_000, 20_050], "pool": 50, "generator": "gen"})
    a, b = spec.track_seeds(0), spec.track_seeds(0)
    assert a == b and len(set(a)) == 50 and all(20_000 <= s < 20_050 for s in a)
    assert spec.track_seeds(1) != a  # another env seed, another order
    assert spec.names(0)[0] == f"gen-{a[0]}"


def test_a_mixed_pool_takes_its_generators_in_turn_over_the_same_seeds_and_the_env_builds_both():
    cfg = {"seeds": [20_000, 20_050], "pool": 6}
    mixed = ProceduralSpec.from_config({**cfg, "generator": ["gen", "proc"]})
    seeds = ProceduralSpec.from_config({**cfg, "generator": "gen"}).track_seeds(0)
    assert mixed.track_seeds(0) == seeds
    assert mixed.names(0) == [f"{'gen' if k % 2 == 0 else 'proc'}-{s}" for k, s in enumerate(seeds)]
    assert ProceduralSpec.from_config({**cfg, "generator": ["proc"]}).generator == "proc"  # one generator in a list
    env = make_env(seed=0, track="oval", procedural={"seeds": [30_000, 40_000], "pool": 2, "share": 1.0, "generator": ["gen", "proc"]})
    try:
        assert [n.split("-")[0] for n in env.core.track_names[1:]] == ["gen", "proc"]
    finally:
        env.close()


@pytest.mark.parametrize("cfg,match", [
    ({"seeds": [0, 5000]}, "overlaps the held-out seed range"),
    ({"seeds": [500, 600]}, "overlaps the held-out seed range"),
    ({"seeds": [20_000, 20_000]}, "empty"),
    ({"seeds": [20_000, 20_010], "pool": 11}, "exceeds the 10 seeds"),
    ({"pool": 0}, "positive integer"),
    ({"share": 1.5}, r"outside \[0, 1\]"),
    ({"generator": "blob"}, "allowed: proc, gen"),
    ({"generator": ["gen", "gen"]}, "repeats a generator"),
    ({"generator": []}, "needs at least one generator"),
    ({"generator": ["gen", "proc"], "difficulty": 0.5}, "needs generator: proc"),
    ({"seed": [1, 2]}, "unknown keys"),
])
def test_bad_specs_fail_with_one_line(cfg, match):
    with pytest.raises(ValueError, match=match) as err:
        ProceduralSpec.from_config(cfg)
    assert "\n" not in str(err.value)


def test_default_ranges_are_disjoint_and_heldout_names_stay_inside():
    assert TRAIN_SEEDS[0] >= HELDOUT_SEEDS[1]
    assert heldout_names(3, "gen") == ["gen-0", "gen-1", "gen-2"]
    with pytest.raises(ValueError, match="held-out procedural seeds"):
        heldout_names(10, start=HELDOUT_SEEDS[1] - 5)


def test_env_draws_named_and_pool_tracks_per_episode_from_its_seed():
    kw = dict(track="oval", procedural={"seeds": [30_000, 40_000], "pool": 4, "share": 0.5, "generator": "gen"}, start="random")
    env = make_env(seed=3, **kw)
    try:
        names = env.core.track_names
        assert names[0] == "oval" and len(names) == 5 and all(n.startswith("gen-") for n in names[1:])
        drawn = []
        for _ in range(16):
            env.reset()
            drawn.append(env.core.car_tracks[0].name)
        assert "oval" in drawn and any(d.startswith("gen-") for d in drawn)
        assert set(drawn) <= set(names)
    finally:
        env.close()
    again = make_env(seed=3, **kw)
    try:
        assert again.core.track_names == names
        redrawn = []
        for _ in range(16):
            again.reset()
            redrawn.append(again.core.car_tracks[0].name)
        assert redrawn == drawn
    finally:
        again.close()


def test_the_walls_of_a_pool_track_are_built_when_it_is_first_drawn_and_read_as_if_built_up_front():
    """The rangefinder's edge walls of a procedural pool are built lazily (a pool of 100 built up front cost 4-7 s an
    env): only the slots drawn so far have walls, and the beams read exactly what walls built at construction read."""
    import numpy as np

    kw = dict(track="oval", procedural={"seeds": [30_000, 40_000], "pool": 6, "share": 1.0, "generator": "gen"}, start="random")
    lazy, eager = make_env(seed=5, **kw), make_env(seed=5, **kw)
    try:
        for slot, t in enumerate(eager.core._geometry):  # the old way: every slot's walls at construction
            eager.core.rangefinder.add_track(slot, t)
        drawn = {0}  # the initial track (slot 0: oval)
        assert set(lazy.core.rangefinder._bodies) == drawn
        for _ in range(4):
            a, b = lazy.reset(), eager.reset()
            drawn.add(int(lazy.core.slot[0]))
            assert set(lazy.core.rangefinder._bodies) == drawn
            act = lazy.action_spec.zero()
            act[..., 1] = 0.6  # throttle: the beams sweep the walls as the car moves
            for _ in range(15):
                np.testing.assert_array_equal(a["rangefinder"].numpy(), b["rangefinder"].numpy())
                a = lazy.step(a.set("action", act.clone()))["next"]
                b = eager.step(b.set("action", act.clone()))["next"]
        assert len(lazy.core.rangefinder._bodies) < len(eager.core.rangefinder._bodies) == 7
    finally:
        lazy.close()
        eager.close()
