"""torcsrl: deep-RL racing drivers on pybullet tracks, seen through TORCS-style sensors, trained with TorchRL.

Importing the package registers the gymnasium ids ``torcsrl/Race-v0`` and ``torcsrl/RaceFlat-v0`` (as gymnasium
packages do); the registrations are entry-point strings, so ``import torcsrl`` loads neither pybullet nor torch.
"""

__version__ = "0.1.0"

from torcsrl.envs import ENV_ID  # noqa: E402,F401  (registers torcsrl/Race-v0, torcsrl/RaceFlat-v0)
