"""rotations.py (w-first quaternions, hand-written for speed) agrees with scipy.spatial.transform.Rotation (x, y, z,
w)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from contactbench import rotations


def same_orientation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """q and -q are the same rotation."""
    return np.minimum(np.abs(a - b).max(axis=-1), np.abs(a + b).max(axis=-1))


@pytest.fixture
def quaternions() -> np.ndarray:
    rng = np.random.default_rng(16)
    q = rotations.uniform_random(rng, 500)
    # edge cases: identity, half turns about each axis, a tiny rotation, and w < 0 (not canonical)
    edges = np.array(
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 1e-9, -1e-9, 2e-9], [-0.5, 0.5, 0.5, 0.5]],
        dtype=float,
    )
    return np.concatenate([q, rotations.normalize(edges)])


def scipy_rotation(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(rotations.wxyz_to_xyzw(q))


def test_matrices_match_scipy(quaternions):
    np.testing.assert_allclose(rotations.to_matrix(quaternions), scipy_rotation(quaternions).as_matrix(), atol=1e-12)
    back = rotations.from_matrix(scipy_rotation(quaternions).as_matrix())
    assert same_orientation(back, quaternions).max() < 1e-12
    assert (back[:, 0] >= 0).all()


def test_products_and_rotations_match_scipy(quaternions):
    a, b = quaternions, np.roll(quaternions, 1, axis=0)
    product = rotations.multiply(a, b)
    expected = rotations.xyzw_to_wxyz((scipy_rotation(a) * scipy_rotation(b)).as_quat())
    assert same_orientation(product, expected).max() < 1e-12
    vectors = np.random.default_rng(1).standard_normal((len(a), 3))
    np.testing.assert_allclose(rotations.rotate(a, vectors), scipy_rotation(a).apply(vectors), atol=1e-12)
    np.testing.assert_allclose(
        rotations.rotate(rotations.conjugate(a), vectors), scipy_rotation(a).inv().apply(vectors), atol=1e-12
    )


def test_rotation_vectors_and_angles_match_scipy(quaternions):
    expected = scipy_rotation(quaternions).as_rotvec()
    np.testing.assert_allclose(rotations.to_rotation_vector(quaternions), expected, atol=1e-9)
    from_vector = rotations.from_rotation_vector(expected)
    assert same_orientation(from_vector, quaternions).max() < 1e-12
    a, b = quaternions, np.roll(quaternions, 1, axis=0)
    np.testing.assert_allclose(
        rotations.angle_between(a, b), (scipy_rotation(a).inv() * scipy_rotation(b)).magnitude(), atol=1e-9
    )


def test_axis_angle_and_tilt_match_scipy():
    axis, angle = np.array([0.3, -0.4, 1.2]), 0.9
    expected = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_quat()
    assert same_orientation(rotations.from_axis_angle(axis, angle), rotations.xyzw_to_wxyz(expected)) < 1e-12
    # about world x first, then about world y: extrinsic "xy"
    expected = Rotation.from_euler("xy", [0.2, -0.35]).as_quat()
    assert same_orientation(rotations.tilt(0.2, -0.35), rotations.xyzw_to_wxyz(expected)) < 1e-12


def test_angular_velocity_matches_scipy(quaternions):
    dt = 0.00676
    q0, q1 = (
        quaternions[:500],
        np.roll(quaternions[:500], 1, axis=0),
    )  # random pairs: none a half turn apart (sign of pi)
    expected = (scipy_rotation(q1) * scipy_rotation(q0).inv()).as_rotvec() / dt
    np.testing.assert_allclose(rotations.angular_velocity_from_quaternions(q0, q1, dt), expected, atol=1e-6)
