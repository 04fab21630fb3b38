"""An engine other than the diagnosis' own MuJoCo base as the base a hypothesis is fitted on: its identified contact
parameters (sim/engines.py, with a hinged scene's articulation) in one contact option, as fit parameters."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product
from typing import Any

import numpy as np

from contactbench.diagnosis.library import Parameter
from contactbench.models.sysid.search_space import EngineSearchSpace
from contactbench.sim.engines import Dimension, engine

# Engine dimensions that are effects of the library (diagnosis.library), kept out of every engine's base
LIBRARY_DIMENSIONS = frozenset(("spinning_friction", "rolling_friction"))


@dataclass(frozen=True)
class EngineBase:
    """An engine in one contact option: its continuous dimensions are fitted (a log-scaled one as its logarithm), the
    discrete ones fixed to the option, those that act only in another option at their start value, and those that are
    library effects (LIBRARY_DIMENSIONS) at the least the engine allows: no engine's base has them, so a dataset's
    rolling friction cannot make PyBullet's law look better, and the library can still name it."""

    engine: str
    space: EngineSearchSpace
    option: tuple[tuple[str, str], ...] = ()  # (discrete dimension, choice)

    @property
    def label(self) -> str:
        return self.engine + "".join(f" ({choice} contact)" for _, choice in self.option)

    @property
    def searched(self) -> tuple[Dimension, ...]:
        chosen = dict(self.option)
        return tuple(
            d
            for d in self.space.dimensions
            if not d.choices and d.name not in LIBRARY_DIMENSIONS and (d.when is None or chosen[d.when[0]] == d.when[1])
        )

    def parameters(self) -> tuple[Parameter, ...]:
        """The searched dimensions as fit parameters, starting where the engine's search starts (Dimension.init), else
        in the middle of the range (on a log scale, the geometric middle)."""
        out = []
        for d in self.searched:
            low, high = (np.log(d.low), np.log(d.high)) if d.log else (d.low, d.high)
            start = 0.5 * (low + high) if d.init is None else (np.log(d.init) if d.log else d.init)
            out.append(Parameter(d.name, float(low), float(high), float(start), log=d.log))
        return tuple(out)

    def engine_parameters(self, reported: dict[str, float]) -> Any:
        """The engine's parameters for the searched dimensions' values (reported units), clipped into their ranges."""
        chosen = dict(self.option)
        numbers = {d.name: float(d.choices.index(chosen[d.name])) for d in self.space.dimensions if d.choices}
        numbers |= {d.name: float(d.init) for d in self.space.dimensions if not d.choices and d.when is not None}
        numbers |= {d.name: d.low for d in self.space.dimensions if d.name in LIBRARY_DIMENSIONS}
        numbers |= {d.name: float(np.clip(reported[d.name], d.low, d.high)) for d in self.searched}
        return self.space.from_vector([numbers[name] for name in self.space.names])


def engine_bases(name: str, n_bodies: int, n_joints: int) -> list[EngineBase]:
    """One EngineBase per contact option of the engine (every combination of its discrete dimensions)."""
    space = EngineSearchSpace(engine(name), n_bodies, n_joints)
    discrete = [d for d in space.dimensions if d.choices]
    return [
        EngineBase(name, space, tuple(zip((d.name for d in discrete), choice)))
        for choice in product(*(d.choices for d in discrete))
    ]
