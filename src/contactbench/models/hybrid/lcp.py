"""Frictionless contact as a linear complementarity problem: Lemke and projected Gauss–Seidel solvers, and one step.

The LCP is: find z >= 0 with w = M z + q >= 0 and z . w = 0. For contact at the vertices of one body over the floor,
z are the normal impulses lambda_i (N s) and w_i = u_i - s_i, where u_i is the vertex's normal velocity after the step
and s_i the least normal velocity it may have:

- touching or above the floor (gap phi_i >= 0): s_i = -phi_i / dt, so the vertex may close its gap but not cross
  the floor within the step ("speculative" contact: a fast vertex lands exactly on the floor instead of tunnelling);
- penetrating (phi_i < 0): s_i = -beta phi_i / dt, Baumgarte-like stabilisation that pushes the vertex out by a
  fraction beta of its penetration per step (beta < 1 removes the drift without launching the body);
- restitution e: a vertex that would reach the floor this step while approaching faster than two steps of gravity
  (2 |g| dt: slower approaches are resting contact, where a bounce would jitter) must in addition leave at e times
  its approach speed, s_i += e |u_free_i| (u_free: its normal velocity after gravity and friction, before contact).

M is the Delassus matrix (`dynamics.delassus`), positive semi-definite: on a face contact several vertex impulses
give the same body wrench. The body wrench and the post-step velocities are unique (a monotone LCP), the split
between vertices is not, so the two solvers may share the load between vertices differently.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from contactbench.models.hybrid import dynamics
from contactbench.models.hybrid.dynamics import SingleBodyScene, State

Solver = Literal["pgs", "lemke"]


class LCPError(RuntimeError):
    """Lemke's algorithm ended on a secondary ray: the LCP has no solution."""


def selected_first(mask: np.ndarray) -> np.ndarray:
    """Column order [B, W] that brings each row's selected entries first; W is the largest count selected in a row."""
    width = int(mask.sum(axis=-1).max(initial=0))
    return np.argsort(~mask, axis=-1, kind="stable")[:, :width]


def solve_lemke(matrix: np.ndarray, vector: np.ndarray, max_pivots: int | None = None) -> np.ndarray:
    """Exact solution z [n] of LCP(M [n, n], q [n]) by Lemke's complementary pivoting (covering vector of ones)."""
    n = len(vector)
    if np.all(vector >= 0):
        return np.zeros(n)
    # Tableau of w - M z - 1 z0 = q; columns: w_0..w_{n-1}, z_0..z_{n-1}, the artificial z0, then the right-hand side.
    tableau = np.hstack([np.eye(n), -matrix, -np.ones((n, 1)), vector[:, None]]).astype(np.float64)
    artificial = 2 * n
    basis = np.arange(n)
    tolerance = 1e-12 * max(1.0, np.abs(matrix).max(), np.abs(vector).max())

    def pivot(row: int, column: int) -> int:
        tableau[row] /= tableau[row, column]
        others = np.arange(n) != row
        tableau[others] -= np.outer(tableau[others, column], tableau[row])
        leaving = int(basis[row])
        basis[row] = column
        return leaving

    leaving = pivot(int(np.argmin(vector)), artificial)
    for _ in range(max_pivots or 50 * (n + 1)):
        entering = leaving + n if leaving < n else leaving - n  # the complement of the variable that just left
        column = tableau[:, entering]
        positive = column > tolerance
        if not positive.any():
            raise LCPError(
                f"Lemke's algorithm found a secondary ray after entering variable {entering}; the LCP has no solution"
            )
        ratios = np.where(positive, tableau[:, -1] / np.where(positive, column, 1.0), np.inf)
        ties = ratios <= ratios.min() + tolerance
        # Letting z0 leave whenever it ties ends the algorithm at once with a complementary solution.
        row = (
            int(np.flatnonzero(ties & (basis == artificial))[0])
            if np.any(ties & (basis == artificial))
            else int(np.argmax(ties))
        )
        leaving = pivot(row, entering)
        if leaving == artificial:
            solution = np.zeros(2 * n + 1)
            solution[basis] = tableau[:, -1]
            return np.maximum(solution[n : 2 * n], 0.0)
    raise LCPError(f"Lemke's algorithm did not terminate within {max_pivots or 50 * (n + 1)} pivots")


def solve_pgs(matrix: np.ndarray, vector: np.ndarray, tolerance: float = 1e-10, max_sweeps: int = 1000) -> np.ndarray:
    """Solutions z [B, n] of a batch of LCPs (M [B, n, n] with positive diagonal, q [B, n]) by projected Gauss–Seidel.

    A problem stops once a sweep moves no w_i by more than `tolerance` times its largest |q_i|. The test is on w,
    not z: on a face contact z may wander along the null space of M for ever while w, the physics, has settled.
    """
    batch, n = vector.shape
    solution = np.zeros((batch, n))
    diagonal = np.diagonal(matrix, axis1=-2, axis2=-1)
    threshold = tolerance * np.maximum(np.abs(vector).max(axis=-1, initial=0.0), np.finfo(float).tiny)
    unsettled = np.arange(batch)  # problems still sweeping; converged ones drop out
    for _ in range(max_sweeps):
        matrix_rows, vector_rows, diagonal_rows = matrix[unsettled], vector[unsettled], diagonal[unsettled]
        current = solution[unsettled]
        before = current.copy()
        for i in range(n):
            residual = vector_rows[:, i] + np.einsum("bj,bj->b", matrix_rows[:, i], current)
            current[:, i] = np.maximum(current[:, i] - residual / diagonal_rows[:, i], 0.0)
        solution[unsettled] = current
        moved = np.abs(np.einsum("bij,bj->bi", matrix_rows, current - before)).max(axis=-1)
        unsettled = unsettled[moved > threshold[unsettled]]
        if len(unsettled) == 0:
            break
    return solution


def solve_at_candidates(
    matrix: np.ndarray, vector: np.ndarray, candidates: np.ndarray, solver: Solver = "pgs"
) -> np.ndarray:
    """Solve LCP(M [B, V, V], q [B, V]) restricted to the candidate entries [B, V]; the others stay zero.

    The candidates of each problem are packed into the first columns, so the solver works on the largest candidate
    count in the batch rather than on every vertex.
    """
    batch, n_vertices = vector.shape
    solution = np.zeros((batch, n_vertices))
    order = selected_first(candidates)
    width = order.shape[1]
    if width == 0:
        return solution
    used = np.take_along_axis(candidates, order, axis=-1)
    packed = np.take_along_axis(np.take_along_axis(matrix, order[:, :, None], axis=1), order[:, None, :], axis=2)
    packed_vector = np.take_along_axis(vector, order, axis=-1)
    pair_used = used[:, :, None] & used[:, None, :]
    # Unused slots become the decoupled problem z = 0, w = 1.
    packed = np.where(pair_used, packed, np.eye(width))
    packed_vector = np.where(used, packed_vector, 1.0)
    if solver == "pgs":
        packed_solution = solve_pgs(packed, packed_vector)
    elif solver == "lemke":
        packed_solution = np.stack([solve_lemke(m, q) for m, q in zip(packed, packed_vector)])
    else:
        raise ValueError(f"unknown LCP solver {solver!r} (expected 'pgs' or 'lemke')")
    np.put_along_axis(solution, order, np.where(used, packed_solution, 0.0), axis=-1)
    return solution


@dataclass(frozen=True)
class ContactSettings:
    """How the frictionless contact step treats the floor (see the module docstring)."""

    contact_margin: float = 0.05  # vertices predicted within this fraction of the body width of the floor take part
    stabilisation: float = 0.2  # beta: fraction of a penetration removed per step
    restitution: float = 0.0  # e: normal velocity kept (reversed) after an impact
    solver: Solver = "pgs"


def contact_candidates(
    state: State, scene: SingleBodyScene, linear: np.ndarray, angular: np.ndarray, settings: ContactSettings
) -> np.ndarray:
    """Vertices [..., V] whose gap after a step at the given velocities would be under the contact margin."""
    offsets = dynamics.vertex_offsets(state.orientation, scene.body)
    predicted_gaps = dynamics.vertex_gaps(state, scene) + scene.dt * dynamics.normal_velocities(
        offsets, linear, angular
    )
    return predicted_gaps < settings.contact_margin * scene.body.width


def in_contact(state: State, scene: SingleBodyScene, settings: ContactSettings) -> np.ndarray:
    """Bodies [...] that may touch the floor this step: some vertex is a candidate under gravity alone."""
    linear, angular = dynamics.unconstrained_velocities(state, scene)
    return contact_candidates(state, scene, linear, angular, settings).any(axis=-1)


def normal_impulses(
    state: State, scene: SingleBodyScene, linear: np.ndarray, angular: np.ndarray, settings: ContactSettings
) -> np.ndarray:
    """Frictionless normal impulses [B, V] for bodies [B] whose velocities before contact are `linear`, `angular`."""
    offsets = dynamics.vertex_offsets(state.orientation, scene.body)
    gaps = dynamics.vertex_gaps(state, scene)
    free_velocity = dynamics.normal_velocities(offsets, linear, angular)
    least_velocity = np.where(gaps >= 0, -gaps, -settings.stabilisation * gaps) / scene.dt
    impact = (free_velocity < -2.0 * np.linalg.norm(scene.gravity) * scene.dt) & (gaps + scene.dt * free_velocity < 0)
    least_velocity = least_velocity - np.where(impact, settings.restitution * free_velocity, 0.0)
    candidates = contact_candidates(state, scene, linear, angular, settings)
    matrix = dynamics.delassus(state.orientation, offsets, scene.body)
    return solve_at_candidates(matrix, free_velocity - least_velocity, candidates, settings.solver)


def dissipative_friction(state: State, scene: SingleBodyScene, friction_impulse: np.ndarray) -> np.ndarray:
    """Friction impulses [B, 6] scaled down (by s in [0, 1]) so that they cannot add kinetic energy or overshoot.

    Coulomb friction opposes motion: within one step it can at most bring the motion it acts on to rest, never
    reverse it or speed the body up. Along the line s J of a friction impulse J, the kinetic energy after the step
    (from the velocities after gravity, v) is a parabola in s with its minimum at s* = -J.v / (J^T M^-1 J); friction
    may go as far as that minimum and no further, so s = clip(s*, 0, 1). A learned wrench that would push the body
    along (J.v > 0) is dropped; one that would overshoot (s* < 1), e.g. a nearly resting body that it would set
    sliding the other way, is cut back to the impulse that stops it.
    """
    linear, angular = dynamics.unconstrained_velocities(state, scene)
    linear_change, angular_change = dynamics.velocity_change(state.orientation, friction_impulse, scene.body)
    braking = -(
        np.sum(friction_impulse[..., :3] * linear, axis=-1) + np.sum(friction_impulse[..., 3:] * angular, axis=-1)
    )
    curvature = np.sum(friction_impulse[..., :3] * linear_change, axis=-1) + np.sum(
        friction_impulse[..., 3:] * angular_change, axis=-1
    )
    scale = np.clip(braking / np.where(curvature > 0, curvature, np.inf), 0.0, 1.0)
    return friction_impulse * scale[..., None]


def frictionless_step(
    state: State, scene: SingleBodyScene, friction_impulse: np.ndarray, settings: ContactSettings
) -> tuple[State, np.ndarray]:
    """One step of bodies [B]: gravity and the given friction impulses [B, 6], then the LCP's normal impulses, then
    integration.

    Returns the next states and the normal impulses [B, V].
    """
    linear, angular = dynamics.unconstrained_velocities(state, scene)
    friction_linear, friction_angular = dynamics.velocity_change(state.orientation, friction_impulse, scene.body)
    linear, angular = linear + friction_linear, angular + friction_angular
    impulses = normal_impulses(state, scene, linear, angular, settings)
    offsets = dynamics.vertex_offsets(state.orientation, scene.body)
    contact_linear, contact_angular = dynamics.velocity_change(
        state.orientation, dynamics.normal_wrench(offsets, impulses), scene.body
    )
    return dynamics.integrate(state, linear + contact_linear, angular + contact_angular, scene.dt), impulses
