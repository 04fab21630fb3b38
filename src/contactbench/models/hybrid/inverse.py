"""Inverse contact dynamics: the contact impulse of each recorded transition, split into normal impulses and friction.

A transition runs from frame t to frame t+1 of one trajectory (1 <= t <= length - 2). Its velocities are backward
differences of the recorded poses, never the recorded velocities: the differences are what the transition really
did (the real cube's recorded velocities are filtered estimates), and they are exactly the integrator's state in the
hybrid rollout, so the regressor sees the same kind of velocity in training and in use. The body-level contact
impulse is then W = M (v_{t+1} - v_unconstrained) (`dynamics.impulse_between`): momentum and angular-momentum change
minus one step of gravity (and the gyroscopic term).

Friction acts along the floor, so the normal impulses carry the whole vertical impulse J_z, and (if J_z > 0) their
weights mu_i = lambda_i / J_z, non-negative and summing to one, place the centre of pressure p = sum mu_i r_i in the
convex hull of the contact candidates. The friction force is the tangential rest J_t. How the torque splits between
normal and friction cannot be observed from the motion of one body (on a face contact, friction's tipping torque and
a shifted normal distribution look the same), so we take the split that a rigid contact would give: the whole
impulse J acts at the centre of pressure, plus a torsional torque about the normal, i.e. L = p x J + tau n. We choose
p (that is, mu) to best explain L in the kinetic-energy metric of the angular impulse, with tau free:
    minimise (L - p x J - tau n)^T I^-1 (L - p x J - tau n) over mu on the simplex and tau,
a projection of a point onto a convex polygon in 2-D once tau is eliminated. Then the normal wrench is
(J_z n, J_z p x n) and the friction wrench the remainder (J_t, p x J_t + tau n + what no contact explains). For a
sliding, resting or single-vertex contact this is exactly what a simulator with point contacts at the vertices does
(PyBullet's recorded forces agree to 1e-3, see `compare_with_bullet_contacts`), and the forward step (friction first,
then the frictionless LCP) gives the transition back wherever the data's contacts end the step as the LCP's do
(e.g. a cube sliding on a face: its centre of pressure moves forwards by mu_friction * h, as in the hand result).
Candidates are the vertices that `lcp.contact_candidates` names under gravity alone, as the forward step does; a
transition with no candidate or no upward impulse gets no normal impulse and all its impulse counts as friction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench.models.hybrid import dynamics, lcp
from contactbench.models.hybrid.dynamics import SingleBodyScene, State
from contactbench.models.hybrid.lcp import ContactSettings
from contactbench.scene import Recordings, Split

BULLET_CONTACT_EXTRAS = (
    "contact_normal_force",
    "contact_friction_force",
    "contact_normal_torque",
    "contact_friction_torque",
)


def _torque_plane(orientation: np.ndarray, body: dynamics.RigidBody) -> np.ndarray:
    """P [..., 2, 3] with |P e|^2 = min over tau of (e - tau n)^T I^-1 (e - tau n): the metric without the torsion
    axis."""
    inverse_inertia = dynamics.world_inverse_inertia(orientation, body)
    along_normal = inverse_inertia[..., :, 2]
    reduced = (
        inverse_inertia - along_normal[..., :, None] * along_normal[..., None, :] / along_normal[..., 2, None, None]
    )
    eigenvalues, eigenvectors = np.linalg.eigh(reduced)  # ascending; the first is the eliminated torsion direction (0)
    return np.sqrt(np.maximum(eigenvalues[..., 1:], 0.0))[..., :, None] * np.swapaxes(eigenvectors[..., :, 1:], -1, -2)


def _closest_convex_combination(
    points: np.ndarray, target: np.ndarray, allowed: np.ndarray, chunk: int = 4096
) -> np.ndarray:
    """Weights [B, V] on the simplex of the allowed points [B, V, 2] whose combination is nearest to target [B, 2].

    Exact: the nearest point of a convex polygon is inside a triangle of its points, or on a segment between two,
    or one of them, so we try all of those and keep the nearest feasible one. Rows with no allowed point get zeros.
    """
    batch, n_points = allowed.shape
    weights = np.zeros((batch, n_points))
    order = lcp.selected_first(allowed)
    width = order.shape[1]
    if width == 0:
        return weights
    singles = [(i, i, i) for i in range(width)]
    pairs = [(i, j, j) for i in range(width) for j in range(i + 1, width)]
    triples = [(i, j, k) for i in range(width) for j in range(i + 1, width) for k in range(j + 1, width)]
    options = np.array(singles + pairs + triples, dtype=np.int64).reshape(-1, 3)  # [O, 3] vertex slots of each option
    for rows in range(0, batch, chunk):
        block = slice(rows, rows + chunk)
        slots = order[block]
        packed = np.take_along_axis(points[block], slots[:, :, None], axis=1)  # [b, width, 2]
        usable = np.take_along_axis(allowed[block], slots, axis=1)
        corner = packed[:, options]  # [b, O, 3, 2]
        offset = target[block, None, :] - corner[:, :, 0]
        edge_a = corner[:, :, 1] - corner[:, :, 0]
        edge_b = corner[:, :, 2] - corner[:, :, 0]
        # Segment a (singles have edge_a = 0): the clamped projection.
        length = np.einsum("boi,boi->bo", edge_a, edge_a)
        along = np.clip(np.einsum("boi,boi->bo", offset, edge_a) / np.where(length > 0, length, 1.0), 0.0, 1.0)
        along = np.where(length > 0, along, 0.0)
        # Triangles: barycentric coordinates where the triangle is not degenerate.
        determinant = edge_a[..., 0] * edge_b[..., 1] - edge_a[..., 1] * edge_b[..., 0]
        scale = np.maximum(length, np.einsum("boi,boi->bo", edge_b, edge_b))
        proper = np.abs(determinant) > 1e-12 * np.maximum(scale, np.finfo(float).tiny)
        safe = np.where(proper, determinant, 1.0)
        first = (offset[..., 0] * edge_b[..., 1] - offset[..., 1] * edge_b[..., 0]) / safe
        second = (edge_a[..., 0] * offset[..., 1] - edge_a[..., 1] * offset[..., 0]) / safe
        is_triangle = np.arange(len(options)) >= width + len(pairs)
        coefficients = np.where(
            is_triangle[None, :, None],
            np.stack([1.0 - first - second, first, second], axis=-1),
            np.stack([1.0 - along, along, np.zeros_like(along)], axis=-1),
        )
        reached = np.einsum("boc,boci->boi", coefficients, corner)
        residual = np.sum((target[block, None, :] - reached) ** 2, axis=-1)
        feasible = np.all(usable[:, options], axis=-1) & np.where(
            is_triangle, proper & np.all(coefficients >= 0.0, axis=-1), True
        )
        best = np.argmin(np.where(feasible, residual, np.inf), axis=-1)
        chosen = np.take_along_axis(coefficients, best[:, None, None], axis=1)[:, 0]  # [b, 3]
        packed_weights = np.zeros((len(slots), width))
        np.add.at(packed_weights, (np.arange(len(slots))[:, None], options[best]), chosen)
        block_weights = np.zeros((len(slots), n_points))
        np.put_along_axis(block_weights, slots, np.where(usable, packed_weights, 0.0), axis=-1)
        weights[block] = block_weights
    return weights


def decompose_impulse(
    state: State, impulse: np.ndarray, scene: SingleBodyScene, settings: ContactSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Normal impulses [B, V] at the vertices and the friction impulse [B, 6] (world frame) of body impulses [B, 6]."""
    offsets = dynamics.vertex_offsets(state.orientation, scene.body)
    candidates = lcp.contact_candidates(state, scene, *dynamics.unconstrained_velocities(state, scene), settings)
    push = impulse[:, 2]
    plane = _torque_plane(state.orientation, scene.body)
    # The whole impulse applied at each vertex, and the observed angular impulse, both seen in the metric's plane.
    arms = np.einsum("bij,bvj->bvi", plane, np.cross(offsets, impulse[:, None, :3]))
    observed = np.einsum("bij,bj->bi", plane, impulse[:, 3:])
    weights = _closest_convex_combination(arms, observed, candidates & (push > 0)[:, None])
    normal = weights * np.maximum(push, 0.0)[:, None]
    return normal, impulse - dynamics.normal_wrench(offsets, normal)


@dataclass(frozen=True)
class Transitions:
    """Every transition t -> t+1 of a split, with its contact impulse and their split (world frame)."""

    trajectory: np.ndarray  # [M] trajectory index
    frame: np.ndarray  # [M] start frame t
    state: State  # [M] state at frame t
    impulse: np.ndarray  # [M, 6] contact impulse over the step (N s, N m s about the CoM)
    normal: np.ndarray  # [M, V] normal impulses at the vertices (N s)
    friction: np.ndarray  # [M, 6] friction impulse, the remainder
    in_contact: np.ndarray  # [M] bool, some vertex may touch the floor (the forward step applies friction only then)

    @property
    def normal_wrench(self) -> np.ndarray:
        """[M, 6] body impulse of the normal impulses."""
        return self.impulse - self.friction


def transitions_from_split(split: Split, scene: SingleBodyScene, settings: ContactSettings) -> Transitions:
    """Inverse contact dynamics on every transition of `split` (body 0)."""
    frames = np.arange(split.n_frames)
    trajectory, frame = np.nonzero((frames[None, :] >= 1) & (frames[None, :] + 1 < split.lengths[:, None]))
    windows = split.poses[trajectory[:, None], frame[:, None] + np.arange(-1, 2), 0]  # [M, 3, 7]: t-1, t, t+1
    states = dynamics.states_from_poses(windows, scene.body, scene.dt)
    start, after = states[:, 1], states[:, 2]
    impulse = dynamics.impulse_between(start, after.linear, after.angular, scene)
    normal, friction = decompose_impulse(start, impulse, scene, settings)
    return Transitions(trajectory, frame, start, impulse, normal, friction, lcp.in_contact(start, scene, settings))


def _agreement(recovered: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    reference_norm = np.linalg.norm(reference)
    both = np.stack([recovered.ravel(), reference.ravel()])
    spread = both.std(axis=1)
    return {
        "relative_error": float(np.linalg.norm(recovered - reference) / reference_norm)
        if reference_norm > 0
        else float("nan"),
        "correlation": float(np.corrcoef(both)[0, 1]) if np.all(spread > 0) else float("nan"),
        "reference_rms": float(np.sqrt(np.mean(reference**2))),
    }


def compare_with_bullet_contacts(
    dataset: Recordings, split: str = "train", settings: ContactSettings = ContactSettings()
) -> dict[str, dict[str, float]]:
    """How well inverse dynamics recovers a simulator's recorded contact forces on a split of `dataset`.

    The split must carry the extras contact_normal_force, contact_friction_force, contact_normal_torque and
    contact_friction_torque ([N, T, K, 3], world frame, N and N m about the CoM, applied during the step that
    produced frame t). Recovered impulses of transition t -> t+1 are divided by dt and set against frame t+1.
    Returns, for the normal and friction forces and torques and for their sums ("contact_force", "contact_torque",
    which do not depend on how normal and friction are told apart), the relative error ||recovered - recorded|| /
    ||recorded|| over all transitions, the Pearson correlation of all components, and the recorded RMS.
    """
    scene = dynamics.single_body_scene(dataset)
    data = dataset.split(split)
    missing = [name for name in BULLET_CONTACT_EXTRAS if name not in data.extras]
    if missing:
        raise KeyError(
            f"{dataset.name}/{split}: no recorded contact forces {missing} (generate with record_contacts=true)"
        )
    transitions = transitions_from_split(data, scene, settings)
    recorded = {
        name: data.extras[name][transitions.trajectory, transitions.frame + 1, 0] for name in BULLET_CONTACT_EXTRAS
    }
    normal = transitions.normal_wrench / scene.dt
    friction = transitions.friction / scene.dt
    recovered = {
        "contact_normal_force": normal[:, :3],
        "contact_friction_force": friction[:, :3],
        "contact_normal_torque": normal[:, 3:],
        "contact_friction_torque": friction[:, 3:],
    }
    report = {
        name.removeprefix("contact_"): _agreement(recovered[name], recorded[name]) for name in BULLET_CONTACT_EXTRAS
    }
    report["contact_force"] = _agreement(
        transitions.impulse[:, :3] / scene.dt, recorded["contact_normal_force"] + recorded["contact_friction_force"]
    )
    report["contact_torque"] = _agreement(
        transitions.impulse[:, 3:] / scene.dt, recorded["contact_normal_torque"] + recorded["contact_friction_torque"]
    )
    return report
