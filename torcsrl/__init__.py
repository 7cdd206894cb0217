"""torcsrl: deep-RL racing drivers on pybullet tracks, seen through TORCS-style sensors, trained with TorchRL."""

__version__ = "0.1.0"
