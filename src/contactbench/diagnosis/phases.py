"""Contact phase of every frame, from the recordings alone: free flight, impact, sliding, rolling/tumbling, rest."""

from __future__ import annotations

import numpy as np

from contactbench.kinematics import estimate_velocities, world_vertices
from contactbench.scene import Recordings, Split

PHASES = ("free", "impact", "sliding", "rolling", "rest")
FREE, IMPACT, SLIDING, ROLLING, REST = range(len(PHASES))
# A vertex closer to the floor than this fraction of the body width touches it (engines let bodies sink a few mm).
CONTACT_HEIGHT = 0.03
# m/s: a touching vertex faster than this along the floor slides; a body slower than this everywhere rests.
SLIP_SPEED = 0.05
REST_SPEED = 0.02
# m/s: the lowest vertex approached the floor faster than this in the frame before: an impact.
IMPACT_SPEED = 0.1


def recorded_velocities(split: Split, dt: float) -> np.ndarray:
    """The split's world velocities [N, T, K, 6], estimated from the poses when the recordings have none."""
    return split.velocities if split.velocities is not None else estimate_velocities(split.poses, dt)


def vertex_heights(dataset: Recordings, split: Split, body: int) -> np.ndarray:
    """Height above the recorded floor [N, T, V] of every vertex of one body, in every frame."""
    poses = np.nan_to_num(split.poses[:, :, body])
    return world_vertices(poses, dataset.body_mesh(body).vertices)[..., 2] - dataset.floor_z


def clearances(dataset: Recordings, split: Split) -> np.ndarray:
    """Height of each body's lowest vertex above the recorded floor, in body widths [N, T, K]."""
    widths = dataset.widths()
    return np.stack(
        [vertex_heights(dataset, split, k).min(axis=-1) / widths[k] for k in range(dataset.n_bodies)], axis=-1
    )


def label_phases(dataset: Recordings, split: Split) -> np.ndarray:
    """Phase codes [N, T, K] (indices into PHASES) of every body at every frame; -1 past a trajectory's end."""
    velocities = recorded_velocities(split, dataset.dt)
    labels = np.full(split.poses.shape[:3], -1, dtype=np.int8)
    for k in range(dataset.n_bodies):
        vertices = dataset.body_mesh(k).vertices
        width = dataset.widths()[k]
        poses = np.nan_to_num(split.poses[:, :, k])
        heights = vertex_heights(dataset, split, k)
        lowest = heights.min(axis=-1)
        touching = heights < lowest[..., None] + CONTACT_HEIGHT * width  # the vertices that carry the contact
        in_contact = lowest < CONTACT_HEIGHT * width
        # Vertex velocities v + w x (R r), world frame.
        arms = world_vertices(poses, vertices) - poses[..., None, :3]
        vertex_velocity = velocities[:, :, k, None, :3] + np.cross(velocities[:, :, k, None, 3:], arms)
        weights = touching / touching.sum(axis=-1, keepdims=True)
        slip = np.einsum("ntv,ntv->nt", np.linalg.norm(vertex_velocity[..., :2], axis=-1), weights)
        lowest_vertical = np.take_along_axis(vertex_velocity[..., 2], heights.argmin(axis=-1)[..., None], axis=-1)[
            ..., 0
        ]
        approaching = np.concatenate(
            [np.zeros_like(lowest_vertical[:, :1], dtype=bool), lowest_vertical[:, :-1] < -IMPACT_SPEED], axis=1
        )
        speed = np.maximum(
            np.linalg.norm(velocities[:, :, k, :3], axis=-1),
            np.linalg.norm(velocities[:, :, k, 3:], axis=-1) * width / 2,
        )
        phase = np.full(lowest.shape, FREE, dtype=np.int8)
        phase[in_contact] = ROLLING
        phase[in_contact & (slip > SLIP_SPEED)] = SLIDING
        phase[in_contact & (speed < REST_SPEED)] = REST
        phase[in_contact & approaching] = IMPACT
        labels[:, :, k] = phase
    labels[~split.valid_mask()] = -1
    return labels
