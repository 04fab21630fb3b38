"""The contact law first (diagnosis.contact_law): every engine fitted alike, the generator's own law wins on its data,
and an engine that refuses the scene is skipped in one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from contactbench.diagnosis import contact_law
from contactbench.diagnosis.bases import engine_bases
from contactbench.diagnosis.library import Hypothesis, library
from contactbench.diagnosis.state import Budget, Diagnosis
from contactbench.errors import ContactbenchError
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.recordings import read_recordings
from contactbench.sim.bullet_scene import BulletParameters
from contactbench.sim.bullet_world import BulletSettings

TINY = Budget(
    fit_trajectories=12,
    val_trajectories=16,
    base_evaluations=24,
    batch=8,
    lsq_iterations=4,
    bootstrap=300,
    law_trajectories=15,
    law_evaluations=24,
)


def test_an_engine_base_searches_its_contact_law_only_in_the_option_it_stands_for():
    rigid, compliant = engine_bases("bullet", n_bodies=2, n_joints=0)
    assert rigid.label == "bullet (rigid contact)" and compliant.label == "bullet (compliant contact)"
    searched = {d.name for d in rigid.searched}
    # rolling and spinning friction are library effects; stiffness and damping act only in the compliant option
    assert searched == {"object_friction_0", "object_friction_1", "restitution_0", "restitution_1"}
    assert {d.name for d in compliant.searched} == searched | {"contact_stiffness", "contact_damping_ratio"}
    hypothesis = Hypothesis(2, base=compliant)
    assert hypothesis.engine == "bullet" and hypothesis.keys() == [d.name for d in compliant.searched]
    lower, upper = hypothesis.bounds()
    parameters = hypothesis.contact_parameters(upper)
    assert isinstance(parameters, BulletParameters)
    assert parameters.contact_stiffness == pytest.approx(1e8)  # a log-scaled dimension is searched as its logarithm
    assert parameters.spinning_friction == parameters.rolling_friction == pytest.approx(1e-6)
    assert Hypothesis(2, base=rigid).contact_parameters(Hypothesis(2, base=rigid).start()).contact_stiffness is None
    assert np.all(lower <= hypothesis.start()) and np.all(hypothesis.start() <= upper)
    # a library effect on an engine base becomes the engine's own: PyBullet's rolling friction, its floor's tilt
    effects = library(0.1)
    tilted = hypothesis.with_effect(effects["rolling_friction"]).with_effect(effects["floor_tilt"])
    values = tilted.start()
    values[-3:] = (0.01, 0.05, -0.02)
    parameters = tilted.contact_parameters(values)
    assert parameters.rolling_friction == pytest.approx(0.01) and parameters.effects.floor_tilt == (0.05, -0.02)
    assert parameters.object_friction == hypothesis.contact_parameters(values[:-3]).object_friction


@pytest.mark.parametrize("engines", [("bullet",), ("mujoco", "ode"), ("mujoco", "mujoco")])
def test_a_list_of_engines_the_comparison_cannot_take_is_one_line(engines):
    with pytest.raises(ContactbenchError, match=r"engines=.*mujoco among them") as error:
        contact_law.check_engines(engines)
    assert "\n" not in str(error.value)


def test_pybullet_made_tosses_are_best_fitted_by_pybullet_and_mujoco_misses_at_impacts(tmp_path):
    """The generator is PyBullet's rigid contact: its law must win on val, and MuJoCo's loss against it must sit at
    impacts (two engines' impact laws differ most) and be confirmed on the held-out full rollouts."""
    spec = SceneSpec("frictioncubes", friction=0.5, restitution=0.0)
    path = generate_dataset(
        spec, tmp_path / "null", split_sizes={"train": 15, "val": 16, "test": 20}, workers=1, progress=False
    )
    steps = Diagnosis(read_recordings(path).for_models(["train", "val", "test"]), TINY)
    base, values = steps.fit_base()
    section, (best, *_), seconds = contact_law.compare(steps, base, values, ("mujoco", "bullet"))
    assert best.engine == "bullet" and section["best_engine"] == "bullet"  # rigid or compliant, at this budget
    mujoco = next(law for law in section["laws"] if law["law"] == "mujoco")
    against = mujoco["against_best"]
    assert against["confirmed"] and against["val"]["ci95"][0] > 0.3
    phases = against["val"]["by_phase"]
    assert max(phases, key=lambda p: phases[p]["share"]) == "impact"
    assert sum(share["share"] for share in phases.values()) == pytest.approx(against["val"]["improvement"])
    assert f"{best.label} closes" in section["finding"] and "confirmed on test" in section["finding"]
    assert set(seconds) >= {"contact_law_s", contact_law.fit_seconds_key(best.label)}
    # Naming on a stepped engine fits on the train tosses its contact law was fitted on; val stays whole.
    steps.budget = dataclasses.replace(steps.budget, law_trajectories=5)
    train, val = steps.train_fit.simulator.segments, steps.val_fit.simulator.segments
    steps.use_engine("bullet", frozenset({"gravity_scale"}))
    try:
        kept = steps.train_fit.simulator.segments
        assert steps.train_split.n_trajectories == 5 and set(kept.trajectory.tolist()) == set(range(5))
        np.testing.assert_array_equal(kept.truth, train.truth[train.trajectory < 5])
        np.testing.assert_array_equal(steps.val_fit.simulator.segments.truth, val.truth)
        assert set(steps.library) == {"gravity_scale"}
    finally:
        steps.close()


def test_an_engine_that_refuses_the_scene_is_skipped_in_one_line(tmp_path):
    spec = SceneSpec(name="nonconvex", friction=0.3, restitution=0.125, shape="ring")
    generate_dataset(
        spec,
        tmp_path / "ring",
        split_sizes={"train": 3, "val": 2, "test": 2},
        settings=BulletSettings(frames=40),
        workers=1,
        progress=False,
    )
    small = Budget(fit_trajectories=3, val_trajectories=2, base_evaluations=4, batch=4, lsq_iterations=1, bootstrap=50)
    steps = Diagnosis(read_recordings(tmp_path / "ring").for_models(["train", "val", "test"]), small)
    base, values = steps.fit_base()
    section, (best, *_), _ = contact_law.compare(steps, base, values, ("mujoco", "drake"))
    assert best.engine == "mujoco" and [law["law"] for law in section["laws"]] == ["mujoco"]
    (skipped,) = section["skipped"]
    assert skipped["engine"] == "drake" and "non-convex" in skipped["reason"] and "\n" not in skipped["reason"]
    assert section["finding"] == "mujoco is the only contact law that simulates this scene"


def test_names_are_fitted_on_the_best_law_that_models_what_the_contact_signatures_measure():
    from contactbench.diagnosis.free_flight import INCONCLUSIVE, MEASURED
    from contactbench.diagnosis.pipeline import LIBRARY_SIGNATURES, naming_base

    law = dataclasses.make_dataclass("Law", ["engine", "label"])
    ranked = [law("drake", "Drake"), law("bullet", "PyBullet rigid"), law("mujoco", "MuJoCo")]
    modelled = {"drake": {"air_drag", "wind"}, "bullet": {"air_drag", "anisotropic_friction"}, "mujoco": {"air_drag"}}

    def signatures(measured: str | None) -> dict:
        return {
            "signatures": {
                name: {"speaks_to": speaks_to, "evidence": MEASURED if name == measured else INCONCLUSIVE}
                for name, speaks_to in (("anisotropy", "anisotropic_friction"), ("spin", "torsional_friction"))
                + (("rolling", "rolling_friction"),)
            }
        }

    assert set(LIBRARY_SIGNATURES) == {"anisotropy", "spin", "rolling"}
    # nothing measured: the best law on val
    assert naming_base(ranked, modelled, signatures(None)) == (ranked[0], set())
    # a measured anisotropy Drake cannot express: the runner-up that models it
    assert naming_base(ranked, modelled, signatures("anisotropy")) == (ranked[1], {"anisotropic_friction"})
    # measured physics no engine models: the best law again, and the signature left to say it is unexplained
    assert naming_base(ranked, modelled, signatures("rolling"))[0] is ranked[0]
    # a best law that models no library effect in the scene is passed over
    assert naming_base(ranked, {**modelled, "drake": set()}, signatures(None))[0] is ranked[1]
