"""The three RL agent modules expose the same factories in the same order; the imitation ones share the actor."""

import inspect

from torcsrl import agents

FACTORIES = ["make_actor", "make_critic", "make_loss", "make_target_updater", "make_exploration", "make_optimizers", "update"]


def test_identical_factory_shapes():
    for name in (a for a in agents.ALGOS if a not in agents.IMITATION):
        mod = agents.get(name)
        funcs = [n for n, f in inspect.getmembers(mod, inspect.isfunction) if f.__module__ == mod.__name__]
        order = sorted(funcs, key=lambda n: inspect.getsourcelines(getattr(mod, n))[1])
        assert order == FACTORIES, name
        for f in FACTORIES:
            assert inspect.signature(getattr(mod, f)) == inspect.signature(getattr(agents.get("td3"), f)), (name, f)


def test_imitation_agents_build_the_rl_actor():
    for name in agents.IMITATION:
        mod = agents.get(name)
        assert mod.make_actor.__code__ is agents.get("bc").make_actor.__code__
        assert inspect.signature(mod.make_actor) == inspect.signature(agents.get("td3").make_actor)


def test_unknown_algo_is_one_clear_line():
    import pytest

    with pytest.raises(ValueError, match="unknown algorithm 'sac'; known: ddpg, td3, d4pg, bc, dagger"):
        agents.get("sac")
