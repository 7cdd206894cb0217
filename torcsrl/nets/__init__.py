"""Networks of every agent: observation encoders, actors and critics.

Below both :mod:`torcsrl.agents` (which builds them from the env's specs) and :mod:`torcsrl.objectives` (whose
losses call them), so neither package imports the other.

* :mod:`~torcsrl.nets.encoders` — :class:`ObsEncoder` (vectors scaled by their spec bounds, optionally standardised
  by :class:`RunningNorm`; images through a small CNN), :func:`random_shift` (DrQ), :func:`split_obs_keys`, :func:`mlp`;
* :mod:`~torcsrl.nets.actors` — :class:`DeterministicActor` (DDPG, TD3, D4PG, BC) and :class:`TanhGaussianActor`
  (SAC, PPO);
* :mod:`~torcsrl.nets.critics` — the fused Q ensemble :class:`Critic` (DDPG, TD3, D4PG, SAC) and :class:`ValueNet` (PPO).
"""

from torcsrl.nets.actors import DeterministicActor, TanhGaussianActor
from torcsrl.nets.critics import Critic, EnsembleLinear, ValueNet, ensemble_linear
from torcsrl.nets.encoders import ObsEncoder, RunningNorm, mlp, mlp_forward, random_shift, shift_pad, split_obs_keys

__all__ = ["Critic", "DeterministicActor", "EnsembleLinear", "ObsEncoder", "RunningNorm", "TanhGaussianActor", "ValueNet",
           "ensemble_linear", "mlp", "mlp_forward", "random_shift", "shift_pad", "split_obs_keys"]
