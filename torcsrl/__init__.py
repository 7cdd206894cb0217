"""torcsrl: deep-RL racing drivers on pybullet tracks, seen through TORCS-style sensors, trained with TorchRL.

Importing the package registers the gymnasium id ``torcsrl/Race-v0`` (as gymnasium packages do); the
registration is an entry-point string, so ``import torcsrl`` loads neither pybullet nor torch.
"""

__version__ = "0.1.0"

from torcsrl.envs import ENV_ID  # noqa: E402,F401  (registers torcsrl/Race-v0)
