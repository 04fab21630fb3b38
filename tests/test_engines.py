"""Every engine behind one interface: the same SysID search and the fixed-parameter model run the real pipeline in
MuJoCo, PyBullet and Drake, and each writes its fitted scene in its own format."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import falling_cubes
from test_pipeline import compose_config

from contactbench import runs
from contactbench.errors import ContactbenchError
from contactbench.models.sysid.search_space import search_space
from contactbench.protocol import make_context
from contactbench.sim.engines import ENGINE_CLASSES, engine
from contactbench.sim.stepped import SteppedRollouts, World

SCENE_FILES = {"mujoco": "scene.xml", "bullet": "body_0.urdf", "drake": "scene.sdf"}


@pytest.mark.parametrize("name", list(ENGINE_CLASSES))
def test_an_engines_parameters_and_its_search_space_agree(name):
    simulator = engine(name)
    space = search_space(name, 2)
    assert space.names == [d.name for d in simulator.dimensions(2)]
    for dimension in simulator.dimensions(2):
        assert dimension.low < dimension.high or dimension.choices
    candidate = space.to_parameters(space.parametrization(seed=0).value)  # where every search starts
    assert space.from_vector(space.to_vector(candidate)) == candidate


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bullet", "drake"])
def test_sysid_and_the_default_of_an_engine_run_the_pipeline(name, tmp_path):
    """model=sysid_<engine> searches with the same callback and objective as MuJoCo's sysid, evaluate.py scores what
    it fitted, and model=<engine>_default scores the engine's own defaults."""
    model = f"sysid_{name}"
    cfg = compose_config("train", ["dataset=contactnets_cube", f"model={model}", "budget=smoke"], tmp_path)
    run_dir = tmp_path / "train-run"
    val_pos_err = runs.train(cfg, run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    assert list(fitted["parameters"]) == search_space(name, 1).names
    # each identified parameter in physical units with its interval: null for a discrete choice, else around it
    uncertainty = fitted["uncertainty"]["parameters"]
    assert list(uncertainty) == search_space(name, 1).names
    for parameter, entry in uncertainty.items():
        assert entry["value"] == pytest.approx(fitted["parameters"][parameter])
        if entry["interval"] is not None:
            assert entry["unit"] is not None and entry["interval"][0] <= entry["value"] <= entry["interval"][1]
    assert any(entry["interval"] is not None for entry in uncertainty.values())
    assert (run_dir / SCENE_FILES[name]).is_file()
    document = runs.evaluate(
        compose_config(
            "evaluate",
            ["dataset=contactnets_cube", f"model={model}", "budget=smoke", f"train_dir={run_dir}", "split=val"],
            tmp_path,
        ),
        tmp_path / "eval-run",
    )
    assert document["model"] == model and document["pos_err"] == pytest.approx(val_pos_err)
    default = runs.evaluate(
        compose_config("evaluate", ["dataset=contactnets_cube", f"model={name}_default", "split=val"], tmp_path),
        tmp_path / "default-run",
    )
    assert np.isfinite(default["pos_err"]) and default["pos_err"] != pytest.approx(val_pos_err)


class Refusing(World):
    """A world that refuses a negative friction mid-search, as an engine refuses an unstable candidate."""

    def __init__(self, scene, substeps):
        self.scene = scene

    def toss(self, parameters, poses0, velocities0, n_steps):
        if parameters < 0:
            raise RuntimeError("solver failed to converge")
        return np.repeat(poses0[None], n_steps, axis=0), np.zeros((n_steps, *velocities0.shape))


def unbuildable(scene, substeps):
    raise RuntimeError("mesh has no volume\nsecond line")


def test_a_refused_candidate_is_unstable_and_a_refused_scene_is_one_clear_error():
    data = falling_cubes(2, 8)
    context = make_context(data.split("train"), data.dt, 6)
    result = SteppedRollouts(data.scene, Refusing, nthread=1).rollout_context(context, [0.5, -1.0])
    assert result.unstable.tolist() == [[False, False], [True, True]]
    assert np.isnan(result.poses[1, :, 6:]).all() and np.isfinite(result.poses[0]).all()
    with pytest.raises(
        ContactbenchError,
        match=r"falling-cubes: unbuildable cannot build this scene \(RuntimeError: "
        r"mesh has no volume\)$",
    ):
        SteppedRollouts(data.scene, unbuildable, nthread=1).simulate(
            [0.5], context.poses[:, -1], context.velocities[:, -1], 2
        )
