"""DAgger (``algo=dagger``): behaviour cloning plus rounds of learner-driven, expert-labelled data.

The actor and optimiser are :mod:`torcsrl.agents.bc`'s; the rounds are run by :func:`torcsrl.imitation.train`.
"""

from torcsrl.agents.bc import make_actor, make_optimizers  # noqa: F401

NAME = "dagger"
