"""The simulator's drag in the units free flight measures the recordings' in: k of a = c - k|v|v, from MuJoCo itself.

A named air_drag or wind is MuJoCo's inertia-box fluid model at a fitted density: a knob that also slows spin and
acts through the equivalent box of a fitted inertia. Whether it is the drag the recordings show is checked against
the model-free measurement (diagnosis.free_flight): the fluid force MuJoCo applies to each body moving at 1 m/s through
still air, along its motion, per unit mass, over random orientations and directions.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from contactbench import rotations
from contactbench.scene import Recordings
from contactbench.sim.mujoco_scene import ContactParameters, build_model

PROBES = 64  # orientations (each with its own direction of motion) per body


def drag_per_metre(dataset: Recordings, parameters: ContactParameters, rng: np.random.Generator) -> dict:
    """k (1/m) of the simulated drag: mean and range over orientations, all bodies pooled. The wind is left out (it
    moves the air, not the drag's size) and bodies are probed apart, one moving at a time, far above the floor."""
    still = dataclasses.replace(parameters, effects=dataclasses.replace(parameters.effects, wind=(0.0, 0.0, 0.0)))
    model = build_model(dataset, still)
    data = mujoco.MjData(model)
    masses = model.body_mass[1 : 1 + dataset.n_bodies]
    rest = np.zeros(7 * dataset.n_bodies)
    rest[0::7] = 10.0 * np.arange(dataset.n_bodies)  # apart from each other
    rest[2::7] = 10.0  # clear of the floor
    rest[3::7] = 1.0
    samples = []
    for body in range(dataset.n_bodies):
        for _ in range(PROBES):
            data.qpos[:], data.qvel[:] = rest, 0.0
            data.qpos[7 * body + 3 : 7 * body + 7] = rotations.normalize(rng.normal(size=4))
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            data.qvel[6 * body : 6 * body + 3] = direction
            mujoco.mj_forward(model, data)
            samples.append(-float(data.qfrc_fluid[6 * body : 6 * body + 3] @ direction) / masses[body])
    samples = np.array(samples)
    return {"k_per_m": float(samples.mean()), "range": [float(samples.min()), float(samples.max())]}


def against_free_flight(simulated: dict, measured: dict) -> dict:
    """The simulated drag beside the one measured model-free on a split (free_flight.measure): consistent where its
    range over orientations meets the measurement's 95% interval."""
    low, high = measured["drag_ci95"]
    return {
        "simulated_k_per_m": simulated["k_per_m"],
        "simulated_range": simulated["range"],
        "measured_k_per_m": measured["drag_per_m"],
        "measured_ci95": [low, high],
        "ratio": simulated["k_per_m"] / measured["drag_per_m"] if measured["drag_per_m"] > 0 else float("inf"),
        "consistent": bool(simulated["range"][0] <= high and simulated["range"][1] >= low),
    }
