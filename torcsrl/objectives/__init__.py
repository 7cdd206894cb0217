"""Losses as TorchRL LossModules: the actor-critic base (``base.py``) with TD3/DDPG (``td3.py``), the D4PG categorical
loss (``d4pg.py``) and SAC (``sac.py``); TorchRL's ``ClipPPOLoss`` computed on tensors (``ppo.py``)."""
