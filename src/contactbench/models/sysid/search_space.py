"""The SysID search spaces: MuJoCo's (paper Table 2c) and any other engine's, mapped to its contact parameters."""

from __future__ import annotations

from dataclasses import dataclass, replace

import nevergrad as ng
import numpy as np

from contactbench.sim import articulation, mujoco_engine
from contactbench.sim.engines import Engine, engine
from contactbench.sim.mujoco_scene import ContactParameters


@dataclass(frozen=True)
class SearchSpace:
    """Per-object friction, floor friction, floor stiffness (log scale) and floor damping, as in Table 2c: MuJoCo's
    dimensions (sim/mujoco_engine.py) as one array of frictions and three scalars, the parametrization every
    published MuJoCo SysID number here was searched in. A hinged scene adds its articulation (sim/articulation.py)."""

    n_bodies: int
    n_joints: int = 0
    friction: tuple[float, float] = mujoco_engine.FRICTION
    stiffness: tuple[float, float] = mujoco_engine.STIFFNESS  # MuJoCo direct solref: -stiffness
    damping: tuple[float, float] = mujoco_engine.DAMPING  # MuJoCo direct solref: -damping
    initial_damping: float = mujoco_engine.INITIAL_DAMPING  # where every search starts (see mujoco_engine)

    @property
    def names(self) -> list[str]:
        return (
            [f"object_friction_{k}" for k in range(self.n_bodies)]
            + [
                "floor_friction",
                "floor_stiffness",
                "floor_damping",
            ]
            + [d.name for d in articulation.dimensions(self.n_joints)]
        )

    def parametrization(self, seed: int, restart: int = 0) -> ng.p.Dict:
        space = ng.p.Dict(
            object_friction=ng.p.Array(shape=(self.n_bodies,), lower=self.friction[0], upper=self.friction[1]),
            floor_friction=ng.p.Scalar(lower=self.friction[0], upper=self.friction[1]),
            floor_stiffness=ng.p.Log(lower=self.stiffness[0], upper=self.stiffness[1]),
            floor_damping=ng.p.Scalar(init=self.initial_damping, lower=self.damping[0], upper=self.damping[1]),
            **_articulation_entries(self.n_joints),
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
            articulation=_articulation(value, self.n_joints),
        )

    def to_vector(self, params: ContactParameters) -> np.ndarray:
        hinges = articulation.to_values(params.articulation).values()
        return np.array(
            [*params.object_friction, params.floor_friction, params.floor_stiffness, params.floor_damping, *hinges]
        )

    def from_vector(self, vector) -> ContactParameters:
        vector = np.asarray(vector, dtype=float)
        k = self.n_bodies
        return self.to_parameters(
            {
                "object_friction": vector[:k],
                "floor_friction": vector[k],
                "floor_stiffness": vector[k + 1],
                "floor_damping": vector[k + 2],
                **dict(zip(self.names[k + 3 :], vector[k + 3 :])),
            }
        )

    def describe(self, params: ContactParameters) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.to_vector(params))))


class EngineSearchSpace:
    """Any engine's identified parameters (sim/engines.py: its `dimensions`) as a nevergrad space, with the same
    methods as SearchSpace: continuous ones as scalars (log-scaled where the engine says). Discrete ones are not
    searched but enumerated over the restarts (restart r takes choice r mod n; selection on val compares them), and
    dimensions that act only with another choice are constants in that restart: with a choice among its dimensions
    NGOpt runs a portfolio of DiagonalCMA, PSO and DE, without one the CMA metamodel of MuJoCo's Table 2c search."""

    def __init__(self, engine: Engine, n_bodies: int, n_joints: int = 0):
        self.engine = engine
        self.n_bodies = n_bodies
        self.n_joints = n_joints
        self.dimensions = engine.dimensions(n_bodies) + articulation.dimensions(n_joints)

    @property
    def names(self) -> list[str]:
        return [d.name for d in self.dimensions]

    def parametrization(self, seed: int, restart: int = 0) -> ng.p.Dict:
        chosen = {d.name: d.choices[restart % len(d.choices)] for d in self.dimensions if d.choices}
        entries = {}
        for d in self.dimensions:
            if d.choices:
                entries[d.name] = chosen[d.name]  # a constant of this restart's search
            elif d.when is not None and chosen[d.when[0]] != d.when[1]:
                entries[d.name] = d.init  # a constant: it does not act in this restart's choice
            else:
                kind = ng.p.Log if d.log else ng.p.Scalar
                entries[d.name] = kind(init=d.init, lower=d.low, upper=d.high)
        space = ng.p.Dict(**entries)
        space.random_state = np.random.RandomState(seed)
        return space

    def to_parameters(self, value: dict):
        """A candidate's value (clipped into the domain: nevergrad may step a hair outside) as engine parameters."""
        numbers = {
            d.name: float(d.choices.index(value[d.name])) if d.choices else float(np.clip(value[d.name], d.low, d.high))
            for d in self.dimensions
        }
        return self._parameters(numbers)

    def _parameters(self, numbers: dict[str, float]):
        parameters = self.engine.from_values(numbers, self.n_bodies)
        if self.n_joints:
            parameters = replace(parameters, articulation=articulation.from_values(numbers, self.n_joints))
        return parameters

    def to_vector(self, params) -> np.ndarray:
        values = self.engine.to_values(params) | articulation.to_values(params.articulation)
        return np.array([values[name] for name in self.names], dtype=float)

    def from_vector(self, vector):
        return self._parameters(dict(zip(self.names, map(float, vector))))

    def describe(self, params) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.to_vector(params))))


def _articulation_entries(n_joints: int) -> dict:
    """The articulation's dimensions as nevergrad parameters (none without hinges)."""
    return {
        d.name: (ng.p.Log if d.log else ng.p.Scalar)(init=d.init, lower=d.low, upper=d.high)
        for d in articulation.dimensions(n_joints)
    }


def _articulation(value: dict, n_joints: int) -> articulation.Articulation | None:
    """A candidate's articulation, clipped into its domain like the contact parameters."""
    bounds = {d.name: (d.low, d.high) for d in articulation.dimensions(n_joints)}
    return articulation.from_values({name: float(np.clip(value[name], *bounds[name])) for name in bounds}, n_joints)


def search_space(engine_name: str, n_bodies: int, n_joints: int = 0) -> SearchSpace | EngineSearchSpace:
    """MuJoCo's Table 2c space, or another engine's own; with hinges, each joint's damping and friction and the
    links' inertia beside them (sim/articulation.py)."""
    if engine_name == "mujoco":
        return SearchSpace(n_bodies, n_joints)
    return EngineSearchSpace(engine(engine_name), n_bodies, n_joints)
