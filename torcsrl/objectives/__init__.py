"""Losses as TorchRL LossModules: fused TD3/DDPG (``td3.py``) and the D4PG categorical loss (``d4pg.py``)."""
