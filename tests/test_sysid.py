"""SysID pieces: the search space, the batched objective against MuJoCo-made data, and NGOpt over a full budget."""

from __future__ import annotations

import threading
from dataclasses import replace

import nevergrad as ng
import numpy as np
import pytest
import torch
from test_pipeline import compose_config

from contactbench.config import REPO_ROOT
from contactbench.metrics import configuration_error
from contactbench.models.sysid.module import stop_recast_threads
from contactbench.models.sysid.objective import ConfigurationObjective, length_groups
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.protocol import make_context, scored_frames, trajectory_means
from contactbench.recordings import read_recordings
from contactbench.scene import Split
from contactbench.sim.mujoco_scene import ContactParameters
from contactbench.sim.rollout import MujocoRollouts

TRUE_PARAMETERS = ContactParameters(
    object_friction=(0.3,), floor_friction=0.2, floor_stiffness=2000.0, floor_damping=60.0
)


@pytest.fixture(scope="module")
def mujoco_made_cube():
    """Real cube tosses re-simulated in MuJoCo with known parameters: SysID's own model class generated them."""
    real = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["train", "val"])
    rollouts = MujocoRollouts(real)
    splits = {}
    for name in ("train", "val"):
        recorded = real.split(name).select(range(12))
        context = make_context(recorded, real.dt, 6)
        simulated = rollouts.rollout_context(context, TRUE_PARAMETERS)
        after_end = np.arange(context.horizon)[None, :, None, None] >= recorded.lengths[:, None, None, None]
        poses = np.where(after_end, np.nan, simulated.poses[0])
        velocities = np.where(after_end, np.nan, simulated.velocities[0])
        splits[name] = Split(poses, recorded.lengths, velocities)
    return replace(real, splits=splits), rollouts


def test_search_space_round_trip_and_clipping():
    space = SearchSpace(n_bodies=2)
    params = ContactParameters(
        object_friction=(0.1, 0.9), floor_friction=0.5, floor_stiffness=300.0, floor_damping=20.0
    )
    assert space.from_vector(space.to_vector(params)) == params
    clipped = space.to_parameters(
        {"object_friction": [-0.1, 1.2], "floor_friction": 0.5, "floor_stiffness": 2e4, "floor_damping": -3.0}
    )
    assert clipped.object_friction == (0.0, 1.0) and clipped.floor_stiffness == 1e4 and clipped.floor_damping == 0.0
    assert space.names == [
        "object_friction_0",
        "object_friction_1",
        "floor_friction",
        "floor_stiffness",
        "floor_damping",
    ]


def test_objective_is_zero_at_the_parameters_that_made_the_data(mujoco_made_cube):
    dataset, rollouts = mujoco_made_cube
    objective = ConfigurationObjective(dataset, "train", 6, rollouts)
    other = replace(TRUE_PARAMETERS, floor_friction=0.6)
    evaluation = objective([TRUE_PARAMETERS, other])
    assert evaluation.losses[0] == pytest.approx(0.0, abs=1e-12)  # rounding of the world/body velocity round trip
    assert evaluation.losses[1] > 1e-3
    assert not evaluation.unstable.any()
    # a mini-batch scores the same trajectories a full call would
    subset = objective([other], np.array([1, 4, 7])).losses[0]
    assert 0 < subset < 100


def test_unstable_candidate_gets_a_finite_penalty(mujoco_made_cube):
    dataset, rollouts = mujoco_made_cube
    objective = ConfigurationObjective(dataset, "train", 6, rollouts, unstable_penalty=123.0)
    exploding = replace(TRUE_PARAMETERS, floor_stiffness=100.0, floor_damping=1000.0)
    evaluation = objective([exploding, TRUE_PARAMETERS])
    assert evaluation.unstable.tolist() == [True, False]
    assert evaluation.losses[0] == 123.0


def test_objective_scores_what_one_rollout_to_the_longest_toss_scores(mujoco_made_cube):
    """Each group of alike lengths is simulated only to its last scored frame; the losses are still those of one
    rollout of the whole batch to its longest toss, to the last bit."""
    dataset, rollouts = mujoco_made_cube
    objective = ConfigurationObjective(dataset, "train", 6, rollouts, position_exponent=2)
    context = objective.context
    assert len(length_groups(context.lengths - context.n_context)) > 1
    candidates = [
        TRUE_PARAMETERS,
        replace(TRUE_PARAMETERS, floor_friction=0.6),
        replace(TRUE_PARAMETERS, floor_damping=5.0),
    ]
    whole = rollouts.rollout_context(context, candidates)
    with np.errstate(invalid="ignore"):
        errors = configuration_error(objective.truth[:, : context.horizon], whole.poses, objective.widths, 2)
        expected = trajectory_means(errors, scored_frames(context.lengths, context.horizon, 6)).mean(axis=-1)
    np.testing.assert_array_equal(objective(candidates).losses, expected)


def test_a_rollout_that_does_not_come_back_in_time_fails_every_candidate(mujoco_made_cube):
    dataset, _ = mujoco_made_cube
    rollouts = MujocoRollouts(dataset, nthread=1)
    candidates = [TRUE_PARAMETERS, replace(TRUE_PARAMETERS, floor_friction=0.6)]
    expected = ConfigurationObjective(dataset, "train", 6, rollouts)(candidates).losses
    simulate, release, calls = rollouts.simulate, threading.Event(), []

    def first_call_hangs(*args):  # as a native call that does not return would
        calls.append(args)
        if len(calls) == 1:
            release.wait(timeout=60)
        return simulate(*args)

    rollouts.simulate = first_call_hangs
    objective = ConfigurationObjective(dataset, "train", 6, rollouts, unstable_penalty=123.0, timeout_s=0.5)
    failed = objective(candidates)
    assert failed.unstable.all() and (failed.losses == 123.0).all()
    assert len(calls) == 1  # no later group was started behind the hung one
    again = objective(candidates)  # a fresh executor and fresh data
    release.set()
    np.testing.assert_array_equal(again.losses, expected)


def test_ngopt_runs_the_whole_quick_budget(tmp_path):
    """nevergrad 1.0.12's metamodel breaks on numpy >= 2.4 after a few hundred evaluations: run a full quick search."""
    cfg = compose_config("train", ["model=sysid", "budget=quick"], tmp_path)
    h = cfg.model.module
    space = SearchSpace(1)
    optimizer = ng.optimizers.registry[h.optimizer](
        parametrization=space.parametrization(0), budget=h.evaluations, num_workers=h.num_workers
    )
    target = space.to_vector(TRUE_PARAMETERS)
    scale = np.array([1.0, 1.0, 1e3, 1e2])
    for _ in range(-(-h.evaluations // h.num_workers)):
        candidates = [optimizer.ask() for _ in range(h.num_workers)]
        for candidate in candidates:
            vector = space.to_vector(space.to_parameters(candidate.value))
            optimizer.tell(candidate, float(np.sum(((vector - target) / scale) ** 2)))
    best = space.to_vector(space.to_parameters(optimizer.provide_recommendation().value))
    stop_recast_threads()
    assert optimizer.num_tell == -(-h.evaluations // h.num_workers) * h.num_workers
    assert np.all(np.abs(best - target) / scale < 0.1)


class _Killed(RuntimeError):
    pass


def _search_run(dataset, root, kill_at=None, resume=False):
    """A tiny two-restart SysID search; kill_at=(restart, generation) stops it right after that checkpoint."""
    import pytorch_lightning as pl

    from contactbench.models.sysid.module import NevergradSearch, SysIDDataModule, SysIDModule

    class Search(NevergradSearch):
        def on_train_batch_start(self, trainer, module, batch, batch_index):
            super().on_train_batch_start(trainer, module, batch, batch_index)
            if kill_at == (self.restart, self.generation):
                raise _Killed  # like SIGKILL: the checkpoint of this generation is all that survives

    options = {
        "evaluations": 24,
        "restarts": 2,
        "num_workers": 4,
        "batch_trajectories": 4,
        "val_trajectories": 4,
        "nthread": 1,
    }
    module = SysIDModule(dataset, context_frames=6, **options)
    search = Search()
    trainer = pl.Trainer(
        max_epochs=-1,
        limit_val_batches=0,
        enable_checkpointing=False,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[search],
        default_root_dir=str(root),
    )
    checkpoint = root / "checkpoints" / "last.ckpt"
    trainer.fit(
        module,
        datamodule=SysIDDataModule(dataset, 6, generations=12),
        ckpt_path=str(checkpoint) if resume else None,
        weights_only=True,
    )
    return module, search


def test_a_killed_search_resumes_bit_identically_from_numbers_only(mujoco_made_cube, tmp_path):
    """The checkpoint holds no pickled optimiser: the resumed run replays its history and ends exactly as an
    uninterrupted one."""
    dataset, _ = mujoco_made_cube
    whole, whole_search = _search_run(dataset, tmp_path / "whole")
    with pytest.raises(_Killed):
        _search_run(dataset, tmp_path / "killed", kill_at=(0, 3))
    (state,) = torch.load(tmp_path / "killed" / "checkpoints" / "last.ckpt", weights_only=True)["callbacks"].values()
    assert state["generation"] == 3 and state["asked"].shape == (12, 4) and state["losses"].dtype == torch.float64
    resumed, resumed_search = _search_run(dataset, tmp_path / "killed", resume=True)
    assert resumed_search.evaluations == whole_search.evaluations == 48
    assert (
        resumed_search.results == whole_search.results
    )  # exact floats: recommendations and val losses of both restarts
    assert torch.equal(resumed.selected, whole.selected)


def test_the_intervals_of_identified_parameters_follow_the_data_and_skip_what_it_cannot_move():
    """uncertainty.intervals on residuals linear in the parameters: a parameter the residuals do not depend on, a
    discrete choice and one its choice leaves unused get none; the others an interval that shrinks with more data."""
    from contactbench.models.sysid import uncertainty
    from contactbench.sim.engines import Dimension

    dimensions = (
        Dimension("object_friction_0", 0.0, 1.0),
        Dimension("floor_friction", 0.0, 1.0),  # the residuals ignore it
        Dimension("contact", 0.0, 1.0, choices=("rigid", "compliant")),
        Dimension("contact_stiffness", 1e3, 1e8, log=True, init=1e5, when=("contact", "compliant")),
    )
    vector = np.array([0.4, 0.3, 0.0, 1e5])  # rigid contact: the stiffness does not act
    rng = np.random.default_rng(0)

    def linear(n: int):
        noise = rng.normal(0.0, 0.01, n)

        def residuals(x):
            x = np.asarray(x, float)
            columns = x.reshape(len(dimensions), -1)
            out = (columns[0][None, :] - 0.4) * np.linspace(1.0, 2.0, n)[:, None] + noise[:, None]
            return out[:, 0] if x.ndim == 1 else out

        return residuals

    few, few_covariance = uncertainty.intervals(linear(50), vector, dimensions)
    many, _ = uncertainty.intervals(linear(5000), vector, dimensions)
    assert np.isfinite(few[0]) and np.isinf(few[1:]).all()
    assert 0 < many[0] < few[0] / 4  # 100x the data: about a tenth of the interval
    assert few_covariance[0, 0] > 0 and np.isnan(few_covariance[2]).all()
    fitted = uncertainty.summary([d.name for d in dimensions], vector, few, few_covariance, dimensions, 0.95)
    entries = fitted["uncertainty"]["parameters"]
    assert entries["object_friction_0"]["unit"] == "1" and entries["contact_stiffness"]["unit"] == "N/m"
    assert entries["contact"]["unit"] is None and entries["contact"]["interval"] is None
    assert not entries["contact"]["at_bound"]  # a choice sits on no bound of a range
    assert entries["floor_friction"]["std"] is None and fitted["covariance"]["matrix"][0][1] is None
