"""What an identified parameter set is known to within: eq. (1) on the train tosses as least-squares residuals
(EquationOneResiduals), and at the parameters a search selected, MuJoCo's system-identification toolbox's Gauss-Newton
(Laplace) covariance and confidence intervals from a finite-difference Jacobian, in physical units, for every engine's
search (sysid, sysid_bullet, sysid_drake) and for the toolbox's own fit (mujoco_sysid).

The intervals treat every residual as independent noise. The frames of one toss are not independent, so they are
narrower than the spread over refits on other tosses would be; a parameter the data cannot move (the smaller of an
object's and the floor's friction in MuJoCo, which takes the larger), a discrete choice (PyBullet's rigid or compliant
contact) and a parameter the chosen contact does not use have none (null).
"""

from __future__ import annotations

import numpy as np
from mujoco import minimize

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.models.sysid.objective import length_groups, subset
from contactbench.protocol import make_context
from contactbench.recordings import Recordings
from contactbench.sim import articulation, engines
from contactbench.sim.engines import Dimension
from contactbench.sim.rollout import Rollouts

# The finite-difference step of the Jacobian at the selected parameters, relative where a parameter exceeds 1 (as
# mujoco.minimize.jacobian_fd takes it): model=mujoco_sysid's own default.
DIFFERENCE_STEP = 0.03
CONFIDENCE = 0.95
UNITS = {  # every engine's identified parameters and the articulation, in physical units
    "object_friction": "1",
    "floor_friction": "1",
    "floor_stiffness": "1/s^2",  # MuJoCo's direct solref: aref = -k r - b v, per unit mass
    "floor_damping": "1/s",
    "restitution": "1",
    "spinning_friction": "m",  # PyBullet: a torque per unit normal force
    "rolling_friction": "m",
    "contact_stiffness": "N/m",
    "contact_damping_ratio": "1",
    "point_stiffness": "N/m",
    "hunt_crossley_dissipation": "s/m",
    "joint_damping": "N m s/rad",
    "joint_friction": "N m",
    "inertia_scale": "1",
}


def toolbox():
    """mujoco.sysid, or one line saying how to install it (the package hides a missing extra's ImportError)."""
    from mujoco import sysid

    if not hasattr(sysid, "optimize"):
        raise ContactbenchError(
            "SysID's intervals need MuJoCo's sysid extra: pip install 'mujoco[sysid]==3.17.0' "
            "(make main and make test install it)"
        )
    return sysid


def unit(name: str) -> str | None:
    """A parameter's unit (None for a discrete choice, which has none)."""
    return UNITS.get(name.rstrip("0123456789").rstrip("_"))


class EquationOneResiduals:
    """Eq. (1) on a split's tosses as least-squares residuals: per scored frame and body, the position offset scaled by
    (2/w)^(p/2) and the rotation vector from the recorded to the predicted orientation (its norm is eq. (1)'s angle),
    each toss weighted by 1/sqrt(N x its scored frames). The sum of squares is then the ConfigurationObjective's loss:
    the mean over tosses of each toss's mean over its frames. An unstable candidate gets a flat residual whose sum of
    squares is `unstable_penalty`."""

    def __init__(
        self,
        dataset: Recordings,
        split: str,
        context_frames: int,
        rollouts: Rollouts,
        *,
        position_exponent: int = 2,
        unstable_penalty: float = 1e3,
        indices: np.ndarray | None = None,
    ):
        recorded = dataset.split(split)
        context = make_context(recorded, dataset.dt, context_frames)
        indices = np.arange(len(recorded.poses)) if indices is None else np.asarray(indices)
        self.context = subset(context, indices)
        self.truth = recorded.poses[indices]
        self.rollouts = rollouts
        self.unstable_penalty = float(unstable_penalty)
        self.steps = self.context.lengths - self.context.n_context  # scored frames per toss
        self.groups = length_groups(self.steps)
        self.position_weight = (2.0 / np.asarray(dataset.widths(), float)) ** (position_exponent / 2)  # [K]
        self.toss_weight = 1.0 / np.sqrt(len(indices) * self.steps)  # [N]
        self.size = int(self.steps.sum()) * dataset.n_bodies * 6

    @property
    def n_trajectories(self) -> int:
        return len(self.truth)

    def __call__(self, candidates: list) -> tuple[np.ndarray, np.ndarray]:
        """Residuals [B, size] and whether each candidate was unstable [B], for B parameter sets."""
        n = self.context.n_context
        parts, unstable = [], np.zeros(len(candidates), dtype=bool)
        for group in self.groups:
            horizon = int(self.steps[group].max())
            result = self.rollouts.simulate(
                candidates, self.context.poses[group, -1], self.context.velocities[group, -1], horizon
            )
            scored = np.arange(horizon)[None, :] < self.steps[group, None]  # [n, H]
            truth = self.truth[group, n : n + horizon]  # [n, H, K, 7]
            with np.errstate(invalid="ignore", over="ignore"):
                position = (truth[..., :3] - result.poses[..., :3]) * self.position_weight[:, None]
                relative = rotations.multiply(rotations.conjugate(truth[..., 3:]), result.poses[..., 3:])
                rotation = rotations.to_rotation_vector(relative)
                residual = np.concatenate([position, rotation], axis=-1) * self.toss_weight[group, None, None, None]
            parts.append(residual[:, scored].reshape(len(candidates), -1))  # [B, scored frames x K x 6]
            unstable |= (result.unstable_frames & scored).any(axis=(1, 2))
        residuals = np.concatenate(parts, axis=1)
        unstable |= ~np.isfinite(residuals).all(axis=1)
        residuals[unstable] = np.sqrt(self.unstable_penalty / self.size)
        return residuals, unstable


def dimensions(engine: str, n_bodies: int, n_joints: int) -> tuple[Dimension, ...]:
    """An engine's identified parameters and the articulation's, in the order of its search space's vectors."""
    return engines.engine(engine).dimensions(n_bodies) + articulation.dimensions(n_joints)


def residual_function(train: EquationOneResiduals, space):
    """Residuals of search-space vectors: [P] -> [size], or [P, k] -> [size, k] in one batched call (the
    finite-difference columns of a Jacobian)."""

    def residuals(x: np.ndarray) -> np.ndarray:
        columns = np.asarray(x, float).reshape(len(space.names), -1).T
        values, _ = train([space.from_vector(column) for column in columns])
        return values[0] if np.ndim(x) == 1 else values.T

    return residuals


def active(dimensions: tuple[Dimension, ...], vector: np.ndarray) -> np.ndarray:
    """Which parameters a Jacobian can move: continuous ones that act with the vector's discrete choices."""
    chosen = {d.name: d.choices[int(round(vector[k]))] for k, d in enumerate(dimensions) if d.choices}
    return np.array([not d.choices and (d.when is None or chosen.get(d.when[0]) == d.when[1]) for d in dimensions])


def intervals(
    residuals,
    vector: np.ndarray,
    dimensions: tuple[Dimension, ...],
    confidence: float = CONFIDENCE,
    step: float = DIFFERENCE_STEP,
    at: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Half-width intervals [P] (inf: not identifiable) and covariance [P, P] at `vector`, from `residuals`, a
    function of [P, k] points giving [size, k] (one batched call for the Jacobian's columns) or of [P] giving [size];
    `at`: the residuals at `vector`, where already known."""
    moving = active(dimensions, vector)
    low = np.array([d.low for d in dimensions])[moving]
    high = np.array([d.high for d in dimensions])[moving]

    def of_moving(x: np.ndarray) -> np.ndarray:
        full = np.repeat(vector[:, None], x.shape[1] if x.ndim == 2 else 1, axis=1)
        full[moving] = x.reshape(int(moving.sum()), -1)
        return residuals(full) if x.ndim == 2 else residuals(full[:, 0])

    interval = np.full(len(dimensions), np.inf)
    covariance = np.full((len(dimensions), len(dimensions)), np.nan)
    if not moving.any():
        return interval, covariance
    x = vector[moving]
    at = of_moving(x) if at is None else at
    jacobian, _ = minimize.jacobian_fd(
        residual=of_moving,
        x=x.reshape(-1, 1),
        r=at.reshape(-1, 1),
        eps=step,
        n_res=0,
        bounds=[low.reshape(-1, 1), high.reshape(-1, 1)],
    )
    moving_covariance, moving_interval = toolbox().calculate_intervals([at], jacobian, alpha=1.0 - confidence)
    interval[moving] = np.asarray(moving_interval, float)
    covariance[np.ix_(moving, moving)] = np.asarray(moving_covariance, float)
    return interval, covariance


def summary(
    names: list[str],
    values: np.ndarray,
    interval: np.ndarray,
    covariance: np.ndarray,
    dimensions: tuple[Dimension, ...],
    confidence: float,
) -> dict:
    """fitted.json's `uncertainty` (each parameter's value, unit, std and interval clipped to its searched range;
    null where the data cannot say) and `covariance` (null where either parameter is not identifiable)."""
    identifiable = np.isfinite(interval)
    parameters = {}
    for k, (name, d) in enumerate(zip(names, dimensions)):
        finite = bool(identifiable[k])
        parameters[name] = {
            "value": float(values[k]),
            "unit": unit(name),
            "std": float(np.sqrt(max(covariance[k, k], 0.0))) if finite else None,
            # the interval clipped to the searched range: the optimum may sit on a bound
            "interval": [float(max(values[k] - interval[k], d.low)), float(min(values[k] + interval[k], d.high))]
            if finite
            else None,
            "at_bound": bool(not d.choices and (np.isclose(values[k], d.low) or np.isclose(values[k], d.high))),
        }
    # the toolbox's covariance keeps numbers where the data leave a direction free (a clamped zero eigenvalue): null
    # there, as the interval is
    matrix = [
        [float(covariance[i, j]) if identifiable[i] and identifiable[j] else None for j in range(len(names))]
        for i in range(len(names))
    ]
    return {
        "uncertainty": {"confidence": confidence, "parameters": parameters},
        "covariance": {"names": list(names), "matrix": matrix},
    }
