"""The simulator and its faces: tracks, vehicle, sensors, rewards, the gymnasium and TorchRL envs.

- ``gymnasium.make("torcsrl/Race-v0", track=..., surface=..., ...)``: one car, gymnasium API (a ``Dict`` observation).
- ``gymnasium.make("torcsrl/RaceFlat-v0", ...)``: the same env, its vector keys as one ``Box``
  (:class:`torcsrl.envs.flat.FlatObservation`), for code that sizes networks from ``observation_space.shape``.
- ``torcsrl.envs.make_env(...)``: the TorchRL ``EnvBase`` (one car, or ``num_cars=N`` in one world).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
from gymnasium.envs.registration import WrapperSpec

ENV_ID = "torcsrl/Race-v0"
#: Race-v0 under FlatObservation (a gymnasium additional wrapper, so ``gym.make(env.spec)`` rebuilds it as it is).
FLAT_ENV_ID = "torcsrl/RaceFlat-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="torcsrl.envs.race:RaceEnv", disable_env_checker=False)
if FLAT_ENV_ID not in gym.registry:
    gym.register(id=FLAT_ENV_ID, entry_point="torcsrl.envs.race:RaceEnv", disable_env_checker=False,
                 additional_wrappers=(WrapperSpec("FlatObservation", "torcsrl.envs.flat:FlatObservation", {}),))


def make_env(
    track: str | list[str] = "road_flow",
    surface: str | list[str] | None = None,
    sensors: tuple[str, ...] | list[str] = ("rangefinder", "state"),
    reward: str | dict[str, float] = "summers_final",
    num_cars: int = 1,
    max_steps: int = 2500,
    lap_limit: int | None = None,
    start: str = "grid",
    seed: int | None = None,
    device: str = "cpu",
    camera: dict[str, Any] | None = None,
    batched: bool | None = None,
    policy_loader: Callable[[str], Any] | None = None,
    **kwargs: Any,
):
    """The race as a TorchRL ``EnvBase`` (see :class:`torcsrl.envs.batched.TorchRaceEnv`).

    ``batch_size`` is ``[]`` for one car, ``[num_cars]`` otherwise (or with ``batched=True``).
    Every keyword of :class:`torcsrl.envs.race.RaceCore` is accepted (reward_scale, spawn_jitter,
    offtrack_grace_s, no_progress_s, action_mode, vehicle, control_hz, …).
    ``policy_loader``: what turns the ``policy`` spec of a ``traffic`` opponent of kind ``policy`` into a policy
    (``torcsrl.policies.load_policy``, handed in by the layer above: the env loads no policies itself); a traffic
    with such opponents and no loader fails in one line. Scripted opponents need none.
    """
    # deferred: torch and torchrl, only for the TorchRL face
    from torcsrl.envs.batched import TorchRaceEnv

    if policy_loader is not None and kwargs.get("traffic") is not None:
        from torcsrl.envs.traffic import TrafficSpec  # deferred: pybullet, only once a race env is built

        spec = TrafficSpec.from_config(kwargs["traffic"])
        kwargs["traffic"] = spec.with_policy_loader(policy_loader) if spec is not None else None
    return TorchRaceEnv(track=track, surface=surface, sensors=tuple(sensors), reward=reward, num_cars=num_cars,
                        max_steps=max_steps, lap_limit=lap_limit, start=start, seed=seed, device=device,
                        camera=camera, batched=batched, **kwargs)


__all__ = ["ENV_ID", "FLAT_ENV_ID", "make_env"]
