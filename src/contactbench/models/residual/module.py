"""The residual model in Lightning: SysID fits MuJoCo first, then an MLP learns the impulse that corrects its steps.

Fitting runs in two stages inside one `trainer.fit`. Stage one (`on_fit_start`, once: a resumed run finds its result
in the checkpoint) is `model=sysid`'s search with the same budget and seed: NGOpt on train, restart chosen on val. A
finished `model=sysid` run of the same settings in the same run tree (`sysid_runs`: paths.log_dir's run index, as a
sweep leaves it) gives its selected parameters instead, read from its fitted.json (stage_one.py); one log line says
which, and fitted.json's `sysid_run` names the run taken (null: searched here).
Stage two trains the correction on rollouts: windows of `unroll` frames from recorded train states are rolled out
by the corrected MuJoCo and scored frame by frame with equation (1)'s terms; the gradient is the adjoint of MuJoCo's
finite-difference linearisation (`rollout_loss`). Inputs are standardised with train statistics kept as buffers, and
outputs scaled by the standard deviation of the one-step corrections (`transitions`) and clipped to `max_correction`
of them; the last layer starts at zero, so training starts from the identified MuJoCo itself.

Why not regress the one-step correction (what MuJoCo gets wrong from each recorded state to the next)? It lowers
the one-step error and makes rollouts worse, on the real cube and on synthetic cubes alike, and so does training it
from the model's own states (DAgger-style): the regression loss falls while the rollout error rises. Neither did
the GNN's training noise in state form, a larger learning rate for the window loss (the linearised gradient agrees
with central differences of the loss on the linear outputs only, and those differences change sign with the step:
contact makes the rollout loss non-smooth), evolution strategies on whole train rollouts, a per-step angular
damping in contact, or a learned impact map in place of MuJoCo's impulse at impact frames come clearly below MuJoCo
alone on val. The measurements: docs/results/matrix.md (what the residual model tried).

`gradient: mjx` replaces the linearised adjoint by reverse mode through MJX (through_mjx.py): exact, the features'
own dependence on the state included, over windows up to whole tosses (`unroll`), optionally cut every `truncation`
frames. Measured on the real cube (docs/DIFFERENTIABLE.md): no window length or truncation beat SysID on val; beyond
4 frames the gradients of different batches agree no better than noise.

Selection is on the val split's rollout position error after every epoch (`models.selection.ValRollouts`, as for
every Lightning-trained model; checkpoint and early stopping on `val/pos_err`). The identified MuJoCo alone is
scored on val too: if no epoch beats it, the fitted model is MuJoCo without the correction (fitted.json says
`correction_used: false`), so the residual model is never selected worse than SysID on val.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Sequence

import mujoco
import numpy as np
import pytorch_lightning as pl
import torch
from torch import nn
from torch.utils.data import DataLoader

from contactbench import rotations
from contactbench.config import generations
from contactbench.errors import ContactbenchError, require_positive_integers
from contactbench.models.base import ContactModule
from contactbench.models.residual import correction, stage_one
from contactbench.models.residual.contact_model import ResidualContactModel
from contactbench.models.residual.correction import Bodies, Predictor
from contactbench.models.residual.through_mjx import MjxResidualWindows
from contactbench.models.residual.windows import recorded_windows, segment_starts, transitions
from contactbench.models.selection import rollout_errors
from contactbench.models.sysid.module import NevergradSearch, SysIDDataModule, SysIDModule
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.scene import Recordings
from contactbench.sim.mujoco_scene import ContactParameters
from contactbench.sim.rollout import MujocoRollouts

log = logging.getLogger(__name__)
GRADIENTS = ("linearised", "mjx")  # how stage two differentiates the rollout: MuJoCo's finite differences, or MJX
STD_FLOOR = 1e-6  # a constant feature (a single body's neighbour) or target stays finite once standardised


class ResidualDataModule(pl.LightningDataModule):
    """Windows of the train split (a fresh random draw of `segments_per_epoch` per epoch) and a fixed draw of the
    val split's, as (trajectory, first frame) pairs: the module rolls each window out itself."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int,
        batch_size: int = 256,
        segments_per_epoch: int = 8192,
        val_segments: int = 1024,
        seed: int = 0,
    ):
        super().__init__()
        self.dataset = dataset
        self.batch_size = int(batch_size)
        self.segments_per_epoch = int(segments_per_epoch)
        self.val_segments = int(val_segments)
        self.seed = int(seed)

    def _draw(self, split: str, count: int, rng: np.random.Generator) -> torch.Tensor:
        starts = segment_starts(self.dataset.split(split))
        chosen = starts[np.sort(rng.choice(len(starts), size=min(count, len(starts)), replace=False))]
        return torch.as_tensor(chosen[rng.permutation(len(chosen))])

    def train_dataloader(self) -> DataLoader:
        rng = np.random.default_rng([self.seed, self.trainer.current_epoch])
        return DataLoader(self._draw("train", self.segments_per_epoch, rng), batch_size=self.batch_size)

    def val_dataloader(self) -> DataLoader:
        rng = np.random.default_rng([self.seed, 1 << 20])
        return DataLoader(self._draw("val", self.val_segments, rng), batch_size=self.batch_size)


class ResidualModule(ContactModule):
    """SysID'd MuJoCo parameters and an MLP (SiLU) from step features to a body-frame velocity correction."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int,
        sysid: dict,
        hidden: Sequence[int] = (256, 256),
        lr: float = 1e-3,
        contact_margin: float = 0.01,
        max_correction: float = 4.0,
        unroll: int = 16,
        seed: int = 0,
        nthread: int | None = None,
        substeps: int = 1,
        gradient: str = "linearised",
        solver_iterations: int = 10,
        truncation: int | None = None,
        sysid_runs: str | None = None,
    ):
        super().__init__()
        if gradient not in GRADIENTS:
            raise ContactbenchError(f"model.module.gradient is {gradient!r} (expected one of {', '.join(GRADIENTS)})")
        counts = {"unroll": unroll, "solver_iterations": solver_iterations, "truncation": truncation}
        require_positive_integers(counts, optional=("truncation",))
        # Plain values only: a checkpoint's hyperparameters must open with weights_only=True.
        sysid = {str(key): value for key, value in dict(sysid).items()}
        hidden = tuple(int(width) for width in hidden)
        self.save_hyperparameters(ignore=["dataset"], logger=False)  # the run logs curated params itself
        self.dataset = dataset
        self.bodies = Bodies.of(dataset)
        self.space = SearchSpace(dataset.n_bodies)
        widths = (self.bodies.n_features, *hidden)
        layers: list[nn.Module] = []
        for width_in, width_out in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(width_in, width_out), nn.SiLU()]
        self.network = nn.Sequential(*layers, nn.Linear(widths[-1], 6))
        # Zero output at first: training starts from the identified MuJoCo itself, not from a random correction.
        nn.init.zeros_(self.network[-1].weight)
        nn.init.zeros_(self.network[-1].bias)
        self.register_buffer(
            "parameters_vector", torch.full((len(self.space.names),), float("nan"), dtype=torch.float64)
        )
        self.register_buffer("feature_mean", torch.zeros(widths[0]))
        self.register_buffer("feature_std", torch.zeros(widths[0]))  # zero until fitted
        self.register_buffer("target_std", torch.ones(6))
        self.register_buffer("sysid_val_pos_err", torch.tensor(float("inf"), dtype=torch.float64))
        self.register_buffer("val_pos_err", torch.tensor(float("inf"), dtype=torch.float64))
        self._simulator: MujocoRollouts | None = None
        self._jacobian_data: mujoco.MjData | None = None
        self._mjx_windows: MjxResidualWindows | None = None
        self.skipped_batches = 0
        self.sysid_run: str | None = None  # the finished model=sysid run stage one took (None: searched here)

    # ------------------------------------------------------------ stage one: SysID, then statistics

    @property
    def identified(self) -> ContactParameters:
        if not torch.isfinite(self.parameters_vector).all():
            raise RuntimeError("the residual model's MuJoCo parameters are not identified yet (no SysID stage run)")
        return self.space.from_vector(self.parameters_vector.cpu().numpy())

    @property
    def simulator(self) -> MujocoRollouts:
        if self._simulator is None:
            self._simulator = MujocoRollouts(self.dataset, self.hparams.nthread, self.hparams.substeps)
        return self._simulator

    def on_fit_start(self) -> None:
        if not torch.isfinite(self.parameters_vector).all():
            self.parameters_vector.copy_(torch.as_tensor(self._identify(), dtype=torch.float64))
            alone = rollout_errors(self._contact_model(None), self.dataset, "val", self.context_frames)
            self.sysid_val_pos_err.fill_(alone["pos_err"])
            log.info(
                "residual: SysID identified %s (val pos_err %.4f without the correction)",
                self.space.describe(self.identified),
                float(self.sysid_val_pos_err),
            )
        if not bool((self.feature_std > 0).all()):
            inputs, wanted = self.transitions("train")
            self.feature_mean.copy_(torch.as_tensor(inputs.mean(axis=0)))
            self.feature_std.copy_(torch.as_tensor(inputs.std(axis=0)).clamp_min(STD_FLOOR))
            self.target_std.copy_(torch.as_tensor(wanted.std(axis=0)).clamp_min(STD_FLOOR))

    def _identify(self) -> np.ndarray:
        """The SysID stage: a finished model=sysid run's selection where one of the same settings is in the run tree,
        else model=sysid's search with the same settings."""
        h = self.hparams
        fields = stage_one.sysid_module_fields(h.sysid, h.seed, h.nthread, h.substeps)
        run_dir = self.trainer.default_root_dir if self._trainer is not None else None
        found = stage_one.finished_sysid_run(h.sysid_runs, stage_one.own_signature(run_dir), fields, self.space.names)
        if isinstance(found, stage_one.Reused):
            log.info("residual: stage one took the SysID fit of %s (same settings; its search not repeated)", found.run)
            self.sysid_run = str(found.run)
            return np.array([found.parameters[name] for name in self.space.names], dtype=np.float64)
        log.info("residual: stage one runs SysID's search (%s)", found)
        return self._search()

    def _search(self) -> np.ndarray:
        """model=sysid's search with the same settings, in a trainer of its own."""
        settings = self.hparams.sysid
        search = SysIDModule(
            self.dataset,
            self.context_frames,
            seed=self.hparams.seed,
            nthread=self.hparams.nthread,
            substeps=self.hparams.substeps,
            **settings,
        )
        ticks = SysIDDataModule(
            self.dataset,
            self.context_frames,
            generations(settings["evaluations"], settings["num_workers"], settings["restarts"]),
        )
        with tempfile.TemporaryDirectory(prefix="contactbench-sysid-") as scratch:
            trainer = pl.Trainer(
                max_epochs=-1,
                limit_val_batches=0,
                logger=False,
                enable_checkpointing=False,
                enable_progress_bar=False,
                enable_model_summary=False,
                callbacks=[NevergradSearch()],
                default_root_dir=scratch,
                accelerator="cpu",
                devices=1,
            )
            trainer.fit(search, datamodule=ticks, weights_only=True)
        return search.selected.cpu().numpy()

    def transitions(self, split: str) -> tuple[np.ndarray, np.ndarray]:
        return transitions(self.dataset.split(split), self.bodies, self.simulator, self.identified)

    # ------------------------------------------------------------ stage two: the correction

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """Body-frame velocity correction [B, 6] from step features [B, F]."""
        standardised = self.network((inputs - self.feature_mean) / self.feature_std)
        bound = self.hparams.max_correction
        return self.target_std * standardised.clamp(-bound, bound)

    def rollout_loss(self, split: str, segments: torch.Tensor) -> torch.Tensor:
        """Roll the corrected MuJoCo `unroll` frames from each window's recorded first state and score every frame
        against the recording: (position error in half-widths)^2 + (rotation error in rad)^2, equation (1)'s terms.

        MuJoCo is not differentiable, so the gradient is the adjoint of its linearisation: mjd_transitionFD gives
        each step's Jacobian A_t (finite differences, MuJoCo's soft contacts included), the costate runs backward
        (lambda_t = dl_t/dx_t + A_t^T lambda_{t+1}) and each correction u_t receives B_t^T lambda_{t+1}, B_t being how
        a velocity change moves the state (x += dt u, v += u). The network's inputs are taken as given (their own
        dependence on the state is left out of the gradient). Returns a surrogate whose value is the loss and whose
        gradient is that estimate."""
        qpos, qvel, truth, present = recorded_windows(
            self.dataset.split(split), segments.cpu().numpy(), self.hparams.unroll, self.bodies.dt
        )
        n, n_bodies = qpos.shape[:2]
        nv = 6 * n_bodies
        dt = self.bodies.dt
        half_widths = self.dataset.widths() / 2
        corrections, inputs_to, losses, gradients, jacobians = [], [], [], [], []
        for step in range(self.hparams.unroll):
            if step > 0:
                jacobians.append(self._step_jacobians(qpos, qvel))
            qpos1, qvel1, diverged = self.simulator.step(self.identified, qpos.reshape(n, -1), qvel.reshape(n, -1))
            qpos1, qvel1 = qpos1.reshape(n, n_bodies, 7), qvel1.reshape(n, n_bodies, 6)
            inputs = np.nan_to_num(correction.features(self.bodies, qpos, qvel, qpos1, qvel1))
            predicted = self(torch.as_tensor(inputs, dtype=torch.float32))
            plain = np.nan_to_num(predicted.detach().numpy().astype(np.float64))
            change, fraction = correction.projected_change(
                self.bodies, qpos, qvel, qpos1, qvel1, plain, self.hparams.contact_margin
            )
            qpos, qvel = correction.integrate(self.bodies, qpos1, qvel1, change * fraction[..., None])
            # How the (unprojected, body-frame) correction moves the state: [n, 2 nv, 6 K].
            orientation = np.nan_to_num(rotations.to_matrix(qpos1[..., 3:]))
            effect = np.zeros((n, 2 * nv, nv))
            for k in range(n_bodies):
                scale = fraction[:, k, None, None]
                effect[:, 6 * k : 6 * k + 3, 6 * k : 6 * k + 3] = dt * orientation[:, k] * scale
                effect[:, 6 * k + 3 : 6 * k + 6, 6 * k + 3 : 6 * k + 6] = dt * np.eye(3) * scale
                effect[:, nv + 6 * k : nv + 6 * k + 3, 6 * k : 6 * k + 3] = orientation[:, k] * scale
                effect[:, nv + 6 * k + 3 : nv + 6 * k + 6, 6 * k + 3 : 6 * k + 6] = np.eye(3) * scale
            counted = (~diverged & present[:, step]).astype(float)
            target = truth[:, step]
            position_error = (qpos[..., :3] - target[..., :3]) / half_widths[:, None]
            rotation_error = rotations.to_rotation_vector(
                rotations.multiply(qpos[..., 3:], rotations.conjugate(rotations.normalize(target[..., 3:])))
            )
            loss = (position_error**2).sum(-1) + (rotation_error**2).sum(-1)  # [n, K]
            gradient = np.zeros((n, 2 * nv))
            local_rotation = np.einsum("nkji,nkj->nki", rotations.to_matrix(qpos[..., 3:]), rotation_error)
            for k in range(n_bodies):
                gradient[:, 6 * k : 6 * k + 3] = 2 * position_error[:, k] / half_widths[k]
                gradient[:, 6 * k + 3 : 6 * k + 6] = 2 * local_rotation[:, k]
            gradients.append(np.nan_to_num(gradient) * counted[:, None])
            losses.append(np.nan_to_num(loss).sum(-1) * counted)
            corrections.append(predicted)
            inputs_to.append(effect)
        costate = np.zeros((n, 2 * nv))
        surrogate = torch.zeros(())
        for step in reversed(range(self.hparams.unroll)):
            costate = gradients[step] + costate
            pull = np.einsum("nij,ni->nj", inputs_to[step], costate).reshape(n, n_bodies, 6)
            surrogate = surrogate + (corrections[step] * torch.as_tensor(pull, dtype=torch.float32)).sum()
            if step > 0:
                costate = np.einsum("nij,ni->nj", jacobians[step - 1], costate)
        scale = 1.0 / max(float(n * self.hparams.unroll), 1.0)
        value = float(np.sum(losses)) * scale
        return surrogate * scale - (surrogate * scale).detach() + value

    def _step_jacobians(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """[n, 2 nv, 2 nv] d(state after one MuJoCo step)/d(state) in MuJoCo's tangent space, per item.

        One mjd_transitionFD call per state (MuJoCo has no batched form; ~60 us each for a cube, a few ms per batch)."""
        model = self.simulator.model(self.identified)
        if self._jacobian_data is None or self._jacobian_data.model is not model:
            self._jacobian_data = mujoco.MjData(model)
        data = self._jacobian_data
        n = len(qpos)
        out = np.zeros((n, 2 * model.nv, 2 * model.nv))
        flat_qpos, flat_qvel = qpos.reshape(n, -1), qvel.reshape(n, -1)
        for i in range(n):
            if not (np.isfinite(flat_qpos[i]).all() and np.isfinite(flat_qvel[i]).all()):
                continue
            data.qpos[:] = flat_qpos[i]
            data.qvel[:] = flat_qvel[i]
            mujoco.mjd_transitionFD(model, data, 1e-6, False, out[i], None, None, None)
        return out

    def rollout_loss_through_mjx(self, split: str, segments: torch.Tensor) -> torch.Tensor:
        """`rollout_loss`'s windows and eq. (1) terms, rolled out in MJX and differentiated exactly by reverse mode
        (through_mjx.py): a surrogate whose value is the loss and whose gradient is MJX's. A window batch whose
        loss or gradient is not finite contributes nothing (logged as `train/skipped_batches`)."""
        recorded = self.dataset.split(split)
        windows = recorded_windows(recorded, segments.cpu().numpy(), self.hparams.unroll, self.bodies.dt)
        if self._mjx_windows is None:
            h = self.hparams
            self._mjx_windows = MjxResidualWindows(
                self.dataset,
                self.identified,
                h.contact_margin,
                h.max_correction,
                h.solver_iterations,
                h.substeps,
                h.truncation,
            )
        value, gradient = self._mjx_windows.value_and_gradient(MjxResidualWindows.weights(self), *windows)
        layers = [layer for layer in self.network if isinstance(layer, nn.Linear)]
        finite = np.isfinite(value) and all(np.isfinite(part).all() for pair in gradient for part in pair)
        self.skipped_batches += 0 if finite else 1
        surrogate = torch.zeros(())
        for layer, (weight, bias) in zip(layers, gradient if finite else []):
            surrogate = surrogate + (layer.weight * torch.as_tensor(weight, dtype=layer.weight.dtype)).sum()
            surrogate = surrogate + (layer.bias * torch.as_tensor(bias, dtype=layer.bias.dtype)).sum()
        return surrogate - surrogate.detach() + (value if finite else 0.0)

    def window_loss(self, split: str, segments: torch.Tensor) -> torch.Tensor:
        # Through MJX, val windows take the gradient too (discarded): one jit-compiled function, not two compiles.
        if self.hparams.gradient == "mjx":
            return self.rollout_loss_through_mjx(split, segments)
        return self.rollout_loss(split, segments)

    def training_step(self, batch: torch.Tensor, batch_index: int) -> torch.Tensor:
        loss = self.window_loss("train", batch)
        self.log("train/loss", loss, on_step=False, on_epoch=True, batch_size=len(batch))
        if self.hparams.gradient == "mjx":
            self.log("train/skipped_batches", float(self.skipped_batches), on_step=False, on_epoch=True)
        return loss

    def validation_step(self, batch: torch.Tensor, batch_index: int) -> None:
        self.log("val/loss", self.window_loss("val", batch), on_step=False, on_epoch=True, batch_size=len(batch))

    def record_selection(self, errors: dict[str, float]) -> None:
        """ValRollouts' scores of the corrected model: kept with the checkpoint, beside MuJoCo alone's."""
        self.val_pos_err.fill_(errors["pos_err"])
        self.log("val/sysid_pos_err", float(self.sysid_val_pos_err))

    def selection_candidate(self) -> ResidualContactModel:
        """What val rollouts score: the correction, even while MuJoCo alone is ahead."""
        return self._contact_model(self.predict)

    def _contact_model(self, predict: Predictor | None) -> ResidualContactModel:
        return ResidualContactModel(
            self.identified, predict, self.hparams.contact_margin, self.hparams.substeps, self.hparams.nthread
        )

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.network.parameters(), lr=self.hparams.lr)

    def predict(self, inputs: np.ndarray) -> np.ndarray:
        """NumPy face of `forward` for the rollout, called once a frame. The module's mode is left as it is: Linear and
        SiLU layers compute the same in training and evaluation, so switching every submodule there and back each
        frame would only cost time."""
        with torch.inference_mode():
            out = self(torch.as_tensor(inputs, dtype=torch.float32, device=self.device)).cpu().numpy()
        return out.astype(np.float64)

    @property
    def corrects(self) -> bool:
        """Whether the selected epoch beat the identified MuJoCo alone on val (else the correction is left out)."""
        return bool(self.val_pos_err < self.sysid_val_pos_err)

    def to_contact_model(self) -> ResidualContactModel:
        return self._contact_model(self.predict if self.corrects else None)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["residual_sysid_run"] = self.sysid_run  # a string or None: loads with weights_only=True

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        run = checkpoint.get("residual_sysid_run")
        self.sysid_run = run if isinstance(run, str) else None

    def fitted_summary(self) -> dict:
        return {
            "parameters": self.space.describe(self.identified),
            "sysid_run": self.sysid_run,
            "val_pos_err_sysid": float(self.sysid_val_pos_err),
            "val_pos_err_corrected": float(self.val_pos_err),
            "correction_used": self.corrects,
        }
