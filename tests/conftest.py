"""Shared test fixtures: small in-memory recordings datasets with known motion."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from contactbench import rotations
from contactbench.meshes import Mesh
from contactbench.scene import FORMAT, VERSION, Recordings, Split


def cube_mesh(width: float = 0.1) -> Mesh:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * width / 2
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ],
        dtype=np.int64,
    )
    return Mesh(corners, faces)


def falling_cubes(
    n_trajectories: int = 3, n_frames: int = 12, n_bodies: int = 1, dt: float = 0.01, seed: int = 0
) -> Recordings:
    """Cubes in free fall (exact semi-implicit Euler kinematics), spinning at constant world angular velocity."""
    rng = np.random.default_rng(seed)
    gravity = np.array([0.0, 0.0, -9.81])
    t = np.arange(n_frames)
    poses = np.zeros((n_trajectories, n_frames, n_bodies, 7))
    velocities = np.zeros((n_trajectories, n_frames, n_bodies, 6))

    for k in range(n_bodies):
        x0 = rng.uniform(-0.3, 0.3, (n_trajectories, 3)) + np.array([0.3 * k, 0.0, 1.0])
        v0 = rng.uniform(-1.0, 1.0, (n_trajectories, 3))
        w = rng.uniform(-2.0, 2.0, (n_trajectories, 3))
        # semi-implicit Euler: v_t = v0 + t g dt, x_t = x0 + dt * sum_{s=1..t} v_s
        v = v0[:, None] + t[None, :, None] * gravity * dt
        x = x0[:, None] + dt * (np.cumsum(v, axis=1) - v[:, :1])
        q = rotations.from_rotation_vector(w[:, None] * dt * t[None, :, None])
        poses[:, :, k] = np.concatenate([x, q], axis=-1)
        velocities[:, :, k] = np.concatenate([v, np.broadcast_to(w[:, None], v.shape)], axis=-1)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "name": "falling-cubes",
        "dt": dt,
        "gravity": gravity.tolist(),
        "floor_z": 0.0,
        "bodies": [{"name": f"cube_{k}", "mesh": "meshes/cube.obj", "mass": 0.37} for k in range(n_bodies)],
        "splits": {"train": "train.npz", "val": "val.npz", "test": "test.npz"},
        "custom_key": {"kept": True},
    }
    lengths = np.full(n_trajectories, n_frames, dtype=np.int64)
    split = Split(poses, lengths, velocities, {"source_index": np.arange(n_trajectories)})
    return Recordings(
        meta=meta,
        meshes={"meshes/cube.obj": cube_mesh()},
        splits={
            "train": split,
            "val": split.select(range(n_trajectories)),
            "test": split.select(range(n_trajectories)),
        },
    )


@pytest.fixture
def small_recordings() -> Recordings:
    return falling_cubes()


@pytest.fixture
def one_torch_thread():
    """Tiny graphs: handing ops to a second thread costs more than it saves, ~50x more when the cores are busy."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
