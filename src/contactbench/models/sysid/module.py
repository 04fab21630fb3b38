"""SysID as a non-gradient Lightning run: trainer.fit ticks, the NevergradSearch callback asks, rolls out and tells;
the same search and objective for every engine (sim/engines.py)."""

from __future__ import annotations

import logging
import os
import threading
from importlib import metadata
from pathlib import Path

import nevergrad as ng
import numpy as np
import pytorch_lightning as pl
import torch
from nevergrad.optimization import recaster
from torch.utils.data import DataLoader

from contactbench.errors import ContactbenchError, require_positive_integers
from contactbench.models.analytical import EngineContactModel, MujocoContactModel
from contactbench.models.base import ContactModule
from contactbench.models.sysid import uncertainty
from contactbench.models.sysid.objective import ConfigurationObjective
from contactbench.models.sysid.search_space import search_space
from contactbench.scene import Recordings
from contactbench.sim import engines

log = logging.getLogger(__name__)

# The distributions that simulate for each engine (sim/engines.py), named in a fit's record with their versions.
ENGINE_PACKAGES = {"mujoco": ("mujoco",), "bullet": ("pybullet",), "drake": ("drake",)}


def package_versions(*distributions: str) -> dict[str, str]:
    """Installed versions of the distributions a fit ran on ('not installed' where one is missing)."""
    found = {}
    for name in distributions:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = "not installed"
    return found


class SysIDDataModule(pl.LightningDataModule):
    """Ticks the trainer once per optimiser generation. The search draws each generation's trajectories itself,
    from its own checkpointed counters, so a resumed run draws exactly what an uninterrupted one would."""

    def __init__(self, dataset: Recordings, context_frames: int, generations: int):
        super().__init__()  # dataset and context_frames: the runner's common signature; the search holds both
        self.generations = int(generations)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(range(self.generations), batch_size=None)


class IdentifiedModule(ContactModule):
    """An identified engine's parameters as a Lightning module: a callback searches, `selected` holds what won on val
    (a search-space vector), `to_contact_model()` simulates with it. No torch optimiser: a step is the callback's."""

    def __init__(self, dataset: Recordings, engine: str) -> None:
        super().__init__()
        if engine not in engines.ENGINE_CLASSES:
            known = ", ".join(engines.ENGINE_CLASSES)
            raise ContactbenchError(f"model.module.engine is {engine!r} (expected one of {known})")
        self.automatic_optimization = False
        self.dataset = dataset
        engines.engine(engine).check_scene(dataset)
        self.space = search_space(engine, dataset.n_bodies, len(dataset.joints))
        self.register_buffer("selected", torch.full((len(self.space.names),), float("nan"), dtype=torch.float64))
        self.register_buffer("selected_val_loss", torch.tensor(float("inf"), dtype=torch.float64))

    model_name: str  # what the fitted contact model is called in scores

    def configure_optimizers(self):
        return []  # no optimiser, said as Lightning reads it: None would have it warn about a fit without one

    def training_step(self, batch, batch_index):
        return None  # the callback does the work of a step

    def rollouts(self):
        """The identified engine's batched rollouts of this dataset's scene (close them when done)."""
        h = self.hparams
        return engines.engine(h.engine).rollouts(self.dataset, nthread=h.nthread, substeps=h.substeps)

    def objective(self, split: str, rollouts) -> ConfigurationObjective:
        """Eq. (1) on a split with this search's settings: what every search is told and selected by."""
        h = self.hparams
        return ConfigurationObjective(
            self.dataset,
            split,
            h.context_frames,
            rollouts,
            unstable_penalty=h.unstable_penalty,
            timeout_s=h.timeout_s,
            position_exponent=h.position_exponent,
        )

    def select(self, vector, val_loss: float) -> None:
        self.selected.copy_(torch.as_tensor(np.asarray(vector, dtype=np.float64)))
        self.selected_val_loss.fill_(float(val_loss))

    def selected_parameters(self):
        if not torch.isfinite(self.selected).all():
            raise RuntimeError("the SysID search has not selected parameters yet (no finished run in this checkpoint)")
        return self.space.from_vector(self.selected.cpu().numpy())

    def to_contact_model(self) -> EngineContactModel:
        h = self.hparams
        if h.engine == "mujoco":
            return MujocoContactModel(name=self.model_name, parameters=self.selected_parameters(), substeps=h.substeps)
        return EngineContactModel(self.model_name, h.engine, parameters=self.selected_parameters(), substeps=h.substeps)

    def fitted_summary(self) -> dict:
        return {
            "parameters": self.space.describe(self.selected_parameters()),
            "val_loss": float(self.selected_val_loss),
        }


class SysIDModule(IdentifiedModule):
    """Holds the search configuration and, once the search is over, the parameters selected on val."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int,
        evaluations: int,
        restarts: int,
        num_workers: int,
        batch_trajectories: int | None,
        val_trajectories: int | None,
        optimizer: str = "NGOpt",
        seed: int = 0,
        unstable_penalty: float = 1e3,
        timeout_s: float = 120.0,
        position_exponent: int = 1,
        nthread: int | None = None,
        substeps: int = 1,
        engine: str = "mujoco",
        interval_trajectories: int | None = None,
    ):
        super().__init__(dataset, engine)
        require_positive_integers({"evaluations": evaluations, "restarts": restarts, "num_workers": num_workers})
        self.save_hyperparameters(ignore=["dataset"], logger=False)  # the run logs curated params itself

    @property
    def model_name(self) -> str:
        return "sysid" if self.hparams.engine == "mujoco" else f"sysid_{self.hparams.engine}"

    @property
    def generations_per_restart(self) -> int:
        return -(-self.hparams.evaluations // self.hparams.num_workers)

    def fitted_summary(self) -> dict:
        h = self.hparams
        chosen = []
        for restart in range(h.restarts):
            chosen.append(optimizer_choice(new_optimizer(self, restart)))
        stop_recast_threads()
        return {
            **super().fitted_summary(),
            **self.uncertainty(),
            # NGOpt picks its algorithm from the space, budget and workers alone, never from the seed or the losses:
            # re-created here as the search created it, the choice is the one each restart ran.
            "optimizer": {"name": h.optimizer, "chosen": chosen},
            "versions": package_versions("nevergrad", *ENGINE_PACKAGES.get(h.engine, ())),
        }

    def uncertainty(self) -> dict:
        """The selected parameters' intervals and covariance (uncertainty.py), from eq. (1)'s residuals on the train
        tosses (`interval_trajectories` of them, null: all): P + 1 rollouts of them, once, when the fit is written."""
        h = self.hparams
        rollouts = self.rollouts()
        try:
            train = uncertainty.EquationOneResiduals(
                self.dataset,
                "train",
                h.context_frames,
                rollouts,
                position_exponent=h.position_exponent,
                unstable_penalty=h.unstable_penalty,
                indices=fixed_subset(self.dataset.split("train").n_trajectories, h.interval_trajectories, h.seed),
            )
            vector = self.selected.cpu().numpy()
            space = uncertainty.dimensions(h.engine, self.space.n_bodies, self.space.n_joints)
            residuals = uncertainty.residual_function(train, self.space)
            interval, covariance = uncertainty.intervals(residuals, vector, space)
        finally:
            rollouts.close()
        return uncertainty.summary(self.space.names, vector, interval, covariance, space, uncertainty.CONFIDENCE)


def new_optimizer(module: SysIDModule, restart: int) -> ng.optimizers.base.Optimizer:
    """Restart `restart`'s optimiser as the search creates it: its own seed, the whole budget, `num_workers` asks."""
    h = module.hparams
    space = module.space.parametrization(seed=h.seed * 1000 + restart, restart=restart)
    return ng.optimizers.registry[h.optimizer](parametrization=space, budget=h.evaluations, num_workers=h.num_workers)


def optimizer_choice(optimizer: ng.optimizers.base.Optimizer) -> str:
    """The algorithm an optimiser runs: for NGOpt (a wizard that delegates), the one it selected for this problem,
    with the optimiser inside it where it wraps one (NGOpt's MetaModel around CMA: 'MetaModel(ParametrizedCMA())')."""
    chosen = getattr(optimizer, "optim", optimizer)  # NGOpt's `optim` is its selected optimiser, made on first use
    inner = getattr(chosen, "_optim", None)
    return f"{chosen.name}({inner.name})" if isinstance(inner, ng.optimizers.base.Optimizer) else chosen.name


def save_last_checkpoint(trainer: pl.Trainer) -> None:
    """checkpoints/last.ckpt after every step of a search, atomically: a SIGKILL loses at most the step in flight.

    (Lightning's step counter does not move without a torch optimiser, so ModelCheckpoint cannot schedule this.)
    """
    path = Path(trainer.default_root_dir) / "checkpoints" / "last.ckpt"
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(".last.ckpt.partial")
    # Lightning's default checkpoint carries callback states: a search's are numbers only, loaded weights_only
    trainer.save_checkpoint(str(partial))
    os.replace(partial, path)


def fixed_subset(n: int, count: int | None, seed: int) -> np.ndarray:
    """The tosses of a split a search scores on (val) or states its intervals on (train): all, or the same `count`."""
    if not count or count >= n:
        return np.arange(n)
    return np.sort(np.random.default_rng([seed, 7]).choice(n, size=count, replace=False))


def stop_recast_threads() -> None:
    """nevergrad's recast optimisers run in non-daemon threads that would keep the process alive (issues #180, #325)."""
    for thread in threading.enumerate():
        if isinstance(thread, recaster._MessagingThread):
            thread.stop()


class NevergradSearch(pl.Callback):
    """Runs `restarts` independent NGOpt searches of `evaluations` each, one generation per training step.

    Per generation: ask `num_workers` candidates, roll all of them out on one mini-batch of train trajectories in a
    single batched MuJoCo call, tell the losses. After each restart its recommendation is scored on val; the restart
    with the best val score is selected (paper §4.2). The checkpoint holds numbers only: the counters, the restart
    results and the current restart's ask/tell history. A resumed run re-creates the optimiser from its seed and
    replays that history, so it continues bit-identically without ever unpickling anything from a run folder.
    """

    def __init__(self):
        self.optimizer: ng.optimizers.base.Optimizer | None = None
        self.restart = 0
        self.generation = 0  # within the current restart
        self.evaluations = 0
        self.unstable = 0
        self.results: list[dict] = []  # per finished restart: its recommended parameter vector and val loss
        # The current restart's history, in ask order: standardized candidate data and the loss told for it.
        self.asked: list[np.ndarray] = []
        self.losses: list[float] = []

    # ------------------------------------------------------------ lifecycle

    def on_fit_start(self, trainer, module: SysIDModule) -> None:
        h = module.hparams
        self.rollouts = module.rollouts()
        self.train_objective = module.objective("train", self.rollouts)
        self.val_objective = module.objective("val", self.rollouts)
        log.info(
            "SysID search: restart %d/%d, generation %d, %d evaluations done so far (%d per restart)",
            min(self.restart + 1, h.restarts),
            h.restarts,
            self.generation,
            self.evaluations,
            h.evaluations,
        )

    def on_fit_end(self, trainer, module) -> None:
        stop_recast_threads()
        self.train_objective.close()
        self.val_objective.close()
        self.rollouts.close()

    # ------------------------------------------------------------ one generation per step

    def on_train_batch_start(self, trainer, module: SysIDModule, batch, batch_index) -> None:
        h = module.hparams
        if self.restart >= h.restarts:  # a resumed run that had already finished
            trainer.should_stop = True
            return
        if self.optimizer is None:
            self.optimizer = new_optimizer(module, self.restart)
            log.info(
                "SysID restart %d/%d: %s runs %s",
                self.restart + 1,
                h.restarts,
                h.optimizer,
                optimizer_choice(self.optimizer),
            )
            self._replay(module)
        candidates = [self.optimizer.ask() for _ in range(self._generation_size(module, self.generation))]
        indices = self._batch(module)
        result = self.train_objective([module.space.to_parameters(c.value) for c in candidates], indices)
        for candidate, loss in zip(candidates, result.losses):
            self.asked.append(candidate.get_standardized_data(reference=self.optimizer.parametrization))
            self.losses.append(float(loss))
            self.optimizer.tell(candidate, float(loss))
        self.generation += 1
        self.evaluations += len(candidates)
        self.unstable += int(result.unstable.sum())
        module.log_dict(
            {
                "train/loss": float(result.losses.min()),
                "train/evaluations": float(self.evaluations),
                "train/unstable_candidates": float(self.unstable),
                "train/restart": float(self.restart),
            },
            on_step=True,
        )
        if self.generation >= module.generations_per_restart:
            self._finish_restart(module)
            trainer.should_stop = self.restart >= h.restarts
        save_last_checkpoint(trainer)

    @staticmethod
    def _generation_size(module: SysIDModule, generation: int) -> int:
        h = module.hparams
        return min(h.num_workers, h.evaluations - generation * h.num_workers)

    def _replay(self, module: SysIDModule) -> None:
        """Bring a fresh optimiser to where the checkpointed one was: the same asks, told the recorded losses."""
        expected = sum(self._generation_size(module, g) for g in range(self.generation))
        if len(self.losses) != expected:
            raise ContactbenchError(
                f"checkpoint search state: {len(self.losses)} recorded evaluations in restart {self.restart} "
                f"(expected {expected} for generation {self.generation} with these settings); resume=false starts over"
            )
        recorded = iter(zip(self.asked, self.losses))
        for generation in range(self.generation):
            candidates = [self.optimizer.ask() for _ in range(self._generation_size(module, generation))]
            for candidate in candidates:
                asked, loss = next(recorded)
                data = candidate.get_standardized_data(reference=self.optimizer.parametrization)
                # Bitwise: anything less and the continuation would silently differ from the uninterrupted run.
                if data.shape != asked.shape or not np.array_equal(data, asked):
                    raise ContactbenchError(
                        "checkpoint search state: the re-created optimiser asks other candidates than the recorded "
                        f"ones (restart {self.restart}, generation {generation}; another nevergrad version?); "
                        "resume=false starts over"
                    )
                self.optimizer.tell(candidate, loss)

    def _batch(self, module: SysIDModule) -> np.ndarray:
        h = module.hparams
        n = self.train_objective.n_trajectories
        if not h.batch_trajectories or h.batch_trajectories >= n:
            return np.arange(n)
        rng = np.random.default_rng([h.seed, self.restart, self.generation])
        return np.sort(rng.choice(n, size=h.batch_trajectories, replace=False))

    def _finish_restart(self, module: SysIDModule) -> None:
        h = module.hparams
        recommendation = module.space.to_parameters(self.optimizer.provide_recommendation().value)
        val_indices = fixed_subset(self.val_objective.n_trajectories, h.val_trajectories, h.seed)
        val_loss = float(self.val_objective([recommendation], val_indices).losses[0])
        vector = module.space.to_vector(recommendation)
        self.results.append({"vector": vector.tolist(), "val_loss": val_loss})
        module.log_dict(
            {"val/loss": val_loss, **{f"params/{k}": v for k, v in module.space.describe(recommendation).items()}},
            on_step=True,
        )
        log.info(
            "SysID restart %d/%d: val loss %.5f with %s",
            self.restart + 1,
            h.restarts,
            val_loss,
            module.space.describe(recommendation),
        )
        stop_recast_threads()
        self.optimizer = None
        self.asked, self.losses = [], []
        self.restart += 1
        self.generation = 0
        best = min(self.results, key=lambda r: r["val_loss"])
        module.select(best["vector"], best["val_loss"])

    # ------------------------------------------------------------ checkpointing

    @staticmethod
    def check_state(state: object, where: str) -> None:
        """Checked before a resume loads anything (contactbench.folders.check_checkpoint)."""
        check_search_state(state, where)

    def state_dict(self) -> dict:
        return {
            "restart": self.restart,
            "generation": self.generation,
            "evaluations": self.evaluations,
            "unstable": self.unstable,
            "results": self.results,
            "asked": torch.from_numpy(np.stack(self.asked).astype(np.float64) if self.asked else np.zeros((0, 0))),
            "losses": torch.tensor(self.losses, dtype=torch.float64),
        }

    def load_state_dict(self, state: dict) -> None:
        check_search_state(state, "checkpoint search state")
        self.optimizer = None  # re-created and replayed at the next step, when the module's settings are at hand
        self.restart = int(state["restart"])
        self.generation = int(state["generation"])
        self.evaluations = int(state["evaluations"])
        self.unstable = int(state["unstable"])
        self.results = [
            {"vector": [float(x) for x in r["vector"]], "val_loss": float(r["val_loss"])} for r in state["results"]
        ]
        self.asked = list(state["asked"].numpy().copy())
        self.losses = [float(x) for x in state["losses"].tolist()]


COUNTERS = ("restart", "generation", "evaluations", "unstable")
SEARCH_STATE_FIELDS = (*COUNTERS, "results", "asked", "losses")


def check_search_state(state: object, where: str) -> None:
    """Refuse anything but the numbers-only search state that NevergradSearch.state_dict writes."""

    def fail(field: str, problem: str, expected: str) -> ContactbenchError:
        return ContactbenchError(f"{where}: field '{field}' {problem} (expected {expected})")

    if not isinstance(state, dict):
        raise ContactbenchError(
            f"{where}: is a {type(state).__name__} (expected a dict of counters, results and history)"
        )
    if "optimizer" in state:
        raise fail(
            "optimizer",
            "holds serialized optimiser bytes (an older contactbench or a crafted file); loading them would "
            "mean unpickling",
            "the numbers-only search state; resume=false starts over",
        )
    unknown = sorted(set(state) - set(SEARCH_STATE_FIELDS), key=str)
    if unknown:
        raise fail(str(unknown[0]), "is not part of the search state", f"only {', '.join(SEARCH_STATE_FIELDS)}")
    for name in SEARCH_STATE_FIELDS:
        if name not in state:
            raise fail(name, "is missing", "the numbers-only search state; resume=false starts over")
    for name in COUNTERS:
        value = state[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise fail(name, f"is {value!r}", "a non-negative integer")
    results = state["results"]
    if not isinstance(results, list) or len(results) != state["restart"]:
        size = f" of {len(results)} entries" if isinstance(results, list) else ""
        raise fail(
            "results",
            f"is a {type(results).__name__}{size}",
            f"a list with one entry per finished restart ({state['restart']})",
        )
    for k, entry in enumerate(results):
        if (
            not isinstance(entry, dict)
            or set(entry) != {"vector", "val_loss"}
            or not isinstance(entry["vector"], list)
            or not all(_is_number(x) for x in entry["vector"])
            or not _is_number(entry["val_loss"])
        ):
            raise fail(f"results[{k}]", "is malformed", "{'vector': [numbers], 'val_loss': number}")
    asked, losses = state["asked"], state["losses"]
    if not isinstance(asked, torch.Tensor) or asked.dtype != torch.float64 or asked.ndim != 2:
        raise fail("asked", f"is {_describe(asked)}", "a float64 tensor [evaluations, dimensions]")
    if not isinstance(losses, torch.Tensor) or losses.dtype != torch.float64 or losses.shape != (asked.shape[0],):
        raise fail(
            "losses", f"is {_describe(losses)}", f"a float64 tensor [{asked.shape[0]}], one loss per asked candidate"
        )
    if not (torch.isfinite(asked).all() and torch.isfinite(losses).all()):
        raise fail(
            "asked" if not torch.isfinite(asked).all() else "losses", "holds NaN or infinite values", "finite numbers"
        )


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _describe(value: object) -> str:
    if isinstance(value, torch.Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return f"a {type(value).__name__}"
