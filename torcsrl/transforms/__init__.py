"""Sensor degradations as TorchRL transforms, at graded severities 1..5.

The catalogue (what each effect does, its parameters per severity) is
``docs/guides/degradation-catalogue.md``; every class docstring repeats its line of it.

In code::

    from torchrl.envs import Compose
    from torcsrl.transforms import DegradedEnv, Fog, BeamDropout, Latency, make_preset

    env = DegradedEnv(base_env, Compose(Fog(severity=3), BeamDropout(severity=2), Latency(steps=2)))
    env.set_seed(0)              # seeds the base env and every degradation in the stack
    env = DegradedEnv(base_env, make_preset("rain", 4))            # camera + rangefinder rain
    t = make_degradation("fog", severity=3, keys=["rangefinder"])   # by name (config, reports)
    rb = ReplayBuffer(storage=..., transform=BeamNoise(severity=(1, 5)))  # augmentation

A plain ``TransformedEnv`` works too; its ``set_seed`` then seeds only the base env, so seed
the transforms with ``seed=`` or :func:`seed_degradations`.

Modules: ``_base`` (contract, seeding, :class:`KeepClean`, :class:`DegradedEnv`),
``rangefinder``, ``state``, ``camera``, ``temporal`` (latency, dropped frames/scans), ``frame_stack`` (the actor's K frames; not a degradation),
``normalize`` (the sensors' scaling into about [-1, 1]; not a degradation),
``registry`` (names, held-out group, presets, stacks from config), ``synthetic`` (stand-in
camera frame, depth and scans), ``gallery`` (``python -m torcsrl.transforms.gallery``).
"""

from ._base import (
    SENSOR_KEYS,
    Degradation,
    DegradedEnv,
    KeepClean,
    LeanTransformedEnv,
    check_severity,
    derive_seed,
    seed_degradations,
    seed_degradation_rows,
)
from .camera import (
    Darkness,
    Droplets,
    Fog,
    Glare,
    ImageDegradation,
    ImageNoise,
    MotionBlur,
    Mud,
    Occlusion,
    Rain,
    Snow,
)
from .rangefinder import (
    BeamBiasScale,
    BeamDegradation,
    BeamDropout,
    BeamFog,
    BeamNoise,
    BeamOutliers,
    BeamQuantize,
    BeamRain,
    BeamSnow,
    BeamSpray,
    OpponentDropout,
    OpponentNoise,
    DeadBeams,
    FovLoss,
    StuckBeams,
)
from .registry import (
    HELDOUT,
    PRESETS,
    applies_to,
    degradation_class,
    degradation_names,
    make_degradation,
    make_preset,
    make_stack,
    preset_names,
    sensor_of_key,
)
from .frame_stack import HISTORY_KEYS, IMAGE_KEYS, FrameStack, stack_frames
from .normalize import NORMALIZED_KEYS, normalize_transform, obs_scale
from .state import StateBias, StateDegradation, StateDropout, StateNoise
from .temporal import FrameDrop, Hold, Latency, ScanDrop

__all__ = [
    # base
    "Degradation",
    "DegradedEnv",
    "KeepClean",
    "LeanTransformedEnv",
    "SENSOR_KEYS",
    "check_severity",
    "derive_seed",
    "seed_degradations",
    "seed_degradation_rows",
    # rangefinder
    "BeamDegradation",
    "BeamNoise",
    "BeamQuantize",
    "BeamDropout",
    "DeadBeams",
    "FovLoss",
    "BeamBiasScale",
    "StuckBeams",
    "BeamOutliers",
    "BeamFog",
    "BeamRain",
    "BeamSnow",
    "BeamSpray",
    "OpponentDropout",
    "OpponentNoise",
    "ScanDrop",
    # state
    "StateDegradation",
    "StateNoise",
    "StateBias",
    "StateDropout",
    # camera
    "ImageDegradation",
    "Fog",
    "Rain",
    "Snow",
    "Droplets",
    "Mud",
    "Glare",
    "Darkness",
    "MotionBlur",
    "ImageNoise",
    "Occlusion",
    "FrameDrop",
    # any sensor
    "Latency",
    "Hold",
    # registry
    "HELDOUT",
    "PRESETS",
    "applies_to",
    "degradation_class",
    "degradation_names",
    "make_degradation",
    "make_preset",
    "make_stack",
    "FrameStack",
    "HISTORY_KEYS",
    "IMAGE_KEYS",
    "stack_frames",
    # normalisation
    "NORMALIZED_KEYS",
    "normalize_transform",
    "obs_scale",
    "preset_names",
    "sensor_of_key",
]
