"""The simulator and its faces: tracks, vehicle, sensors, rewards, the gymnasium and TorchRL envs."""
