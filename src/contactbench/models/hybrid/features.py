"""Body-frame inputs of the friction regressor, and the friction wrench between body and world frames.

The features of a state, all unchanged by a rotation of the whole scene about the vertical or a horizontal shift
(so the regressor need not learn those symmetries from data):

- the CoM's linear velocity in the body frame (3, m/s);
- the angular velocity in the body frame (3, rad/s);
- the unit gravity direction in the body frame (3): how the body is tilted relative to the floor;
- the height above the floor of every contact vertex (V, m), in the mesh's vertex order. Each input always refers to
  the same corner, so the network can tell which vertices touch (height ~ 0), which penetrate, and which are near;
  for the meshes of this benchmark (at most a few dozen vertices) the full list costs little and drops nothing,
  where "the k lowest heights" would lose which corner is which.

The regressor predicts the friction wrench in the body frame: force (N) then torque about the CoM (N m).
"""

from __future__ import annotations

import numpy as np

from contactbench import rotations
from contactbench.models.hybrid import dynamics
from contactbench.models.hybrid.dynamics import RigidBody, SingleBodyScene, State


def feature_count(body: RigidBody) -> int:
    return 9 + body.n_vertices


def body_features(state: State, scene: SingleBodyScene) -> np.ndarray:
    """Features [..., 9 + V] of states [...]."""
    to_body = rotations.conjugate(state.orientation)
    gravity_direction = np.broadcast_to(scene.gravity / np.linalg.norm(scene.gravity), state.linear.shape)
    return np.concatenate(
        [
            rotations.rotate(to_body, state.linear),
            rotations.rotate(to_body, state.angular),
            rotations.rotate(to_body, gravity_direction),
            dynamics.vertex_gaps(state, scene),
        ],
        axis=-1,
    )


def wrench_to_body(orientation: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """World-frame wrenches [..., 6] expressed in the body frame."""
    to_body = rotations.conjugate(orientation)
    return np.concatenate(
        [rotations.rotate(to_body, wrench[..., :3]), rotations.rotate(to_body, wrench[..., 3:])], axis=-1
    )


def wrench_to_world(orientation: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """Body-frame wrenches [..., 6] expressed in the world frame."""
    return np.concatenate(
        [rotations.rotate(orientation, wrench[..., :3]), rotations.rotate(orientation, wrench[..., 3:])], axis=-1
    )
