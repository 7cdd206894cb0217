"""What the cars stand on: the collision groups, the ground models and the ground plane.

The suspension rays only hit bodies in :data:`GROUND_GROUP`; car chassis are in :data:`CAR_GROUP`. With the
``"plane"`` ground model (:data:`GROUND_MODELS`) the rays are intersected with the z = 0 plane of
:func:`make_ground` in closed form; with ``"raycast"`` pybullet casts them against every ground body.
"""

from __future__ import annotations

from torcsrl.utils.bullet import pybullet as p

__all__ = ["GROUND_GROUP", "CAR_GROUP", "GROUND_MODELS", "make_ground"]

#: Collision group of the ground (and anything the suspension rays should hit).
GROUND_GROUP: int = 1
#: Collision group of car chassis. Cars collide with the ground; with each other only if ``collide``.
CAR_GROUP: int = 2
#: Ground models of :class:`~torcsrl.envs.vehicle.fleet.CarFleet` (see its ``ground`` argument).
GROUND_MODELS = ("plane", "raycast")


def make_ground(client_id: int, lateral_friction: float = 0.8) -> int:
    """A static infinite plane at z = 0 in collision group :data:`GROUND_GROUP`; returns its body id.

    ``lateral_friction`` [-] only matters for chassis-ground contact (tyre grip comes from the
    surface ids given to the fleet).
    """
    shape = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client_id)
    body = p.createMultiBody(0.0, shape, basePosition=[0.0, 0.0, 0.0], physicsClientId=client_id)
    p.setCollisionFilterGroupMask(body, -1, GROUND_GROUP, 0xFFFF, physicsClientId=client_id)
    p.changeDynamics(body, -1, lateralFriction=lateral_friction, physicsClientId=client_id)
    return body
