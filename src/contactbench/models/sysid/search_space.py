"""The SysID search space (paper Table 2c) and its mapping to MuJoCo contact parameters."""

from __future__ import annotations

from dataclasses import dataclass

import nevergrad as ng
import numpy as np

from contactbench.sim.mujoco_scene import ContactParameters


@dataclass(frozen=True)
class SearchSpace:
    """Per-object friction, floor friction, floor stiffness (log scale) and floor damping, as in Table 2c."""

    n_bodies: int
    friction: tuple[float, float] = (0.0, 1.0)
    stiffness: tuple[float, float] = (1e2, 1e4)  # MuJoCo direct solref: -stiffness
    damping: tuple[float, float] = (0.0, 1e3)  # MuJoCo direct solref: -damping
    # Where every search starts. The domain's centre (damping 500) is unstable at the datasets' dt (~6.8 ms):
    # MuJoCo diverges once damping * dt is of order 1, and a search started there sees only penalties.
    initial_damping: float = 50.0

    @property
    def names(self) -> list[str]:
        return [f"object_friction_{k}" for k in range(self.n_bodies)] + [
            "floor_friction",
            "floor_stiffness",
            "floor_damping",
        ]

    def parametrization(self, seed: int) -> ng.p.Dict:
        space = ng.p.Dict(
            object_friction=ng.p.Array(shape=(self.n_bodies,), lower=self.friction[0], upper=self.friction[1]),
            floor_friction=ng.p.Scalar(lower=self.friction[0], upper=self.friction[1]),
            floor_stiffness=ng.p.Log(lower=self.stiffness[0], upper=self.stiffness[1]),
            floor_damping=ng.p.Scalar(init=self.initial_damping, lower=self.damping[0], upper=self.damping[1]),
        )
        space.random_state = np.random.RandomState(seed)
        return space

    def to_parameters(self, value: dict) -> ContactParameters:
        """A candidate's value (clipped into the domain: nevergrad may step a hair outside) as MuJoCo parameters."""
        return ContactParameters(
            object_friction=tuple(np.clip(np.ravel(value["object_friction"]), *self.friction)),
            floor_friction=float(np.clip(value["floor_friction"], *self.friction)),
            floor_stiffness=float(np.clip(value["floor_stiffness"], *self.stiffness)),
            floor_damping=float(np.clip(value["floor_damping"], *self.damping)),
        )

    def to_vector(self, params: ContactParameters) -> np.ndarray:
        return np.array([*params.object_friction, params.floor_friction, params.floor_stiffness, params.floor_damping])

    def from_vector(self, vector) -> ContactParameters:
        vector = np.asarray(vector, dtype=float)
        k = self.n_bodies
        return self.to_parameters(
            {
                "object_friction": vector[:k],
                "floor_friction": vector[k],
                "floor_stiffness": vector[k + 1],
                "floor_damping": vector[k + 2],
            }
        )

    def describe(self, params: ContactParameters) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.to_vector(params))))
