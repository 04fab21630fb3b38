"""The fitted residual model as the benchmark scores it: the identified MuJoCo steps every trajectory one frame in one
native call, the learned correction (correction.py) is applied to every body, MuJoCo steps on."""

from __future__ import annotations

import numpy as np

from contactbench.models.base import ContactModel
from contactbench.models.residual import correction
from contactbench.models.residual.correction import Bodies, Predictor
from contactbench.protocol import Context
from contactbench.scene import Recordings, Scene
from contactbench.sim.mujoco_scene import ContactParameters, pack_state, scene_xml
from contactbench.sim.rollout import MujocoRollouts


class ResidualContactModel(ContactModel):
    """Rollout: MuJoCo with the identified parameters steps all trajectories one frame in one native call, the
    learned correction is applied to every body (projected: see `correction`), MuJoCo steps on."""

    name = "residual"
    engine = "mujoco"

    def __init__(
        self,
        parameters: ContactParameters,
        predict: Predictor | None,
        contact_margin: float,
        substeps: int = 1,
        nthread: int | None = None,
    ):
        self.parameters = parameters
        self.predict = predict
        self.contact_margin = float(contact_margin)
        self.substeps = substeps
        self.nthread = nthread

    def scene_files(self, dataset: Recordings) -> dict[str, str]:
        return {"scene.xml": scene_xml(dataset, self.parameters, self.substeps)}

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        simulator = MujocoRollouts(scene, self.nthread, self.substeps)
        bodies = Bodies.of(scene)
        n, n_bodies = len(context.poses), scene.n_bodies
        qpos, qvel = pack_state(context.poses[:, -1], context.velocities[:, -1])
        qpos, qvel = qpos.reshape(n, n_bodies, 7), qvel.reshape(n, n_bodies, 6)
        poses = np.empty((n, context.horizon, n_bodies, 7))
        poses[:, : context.n_context] = context.poses
        for frame in range(context.n_context, context.horizon):
            qpos, qvel = self.step(simulator, bodies, qpos, qvel)
            poses[:, frame] = qpos
        return poses

    def step(
        self, simulator: MujocoRollouts, bodies: Bodies, qpos: np.ndarray, qvel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """States [N, K, 7] / [N, K, 6] one frame later."""
        n, n_bodies = qpos.shape[:2]
        qpos1, qvel1, _ = simulator.step(self.parameters, qpos.reshape(n, -1), qvel.reshape(n, -1))
        qpos1, qvel1 = qpos1.reshape(n, n_bodies, 7), qvel1.reshape(n, n_bodies, 6)
        if self.predict is None:
            return qpos1, qvel1
        inputs = correction.features(bodies, qpos, qvel, qpos1, qvel1)
        change = self.predict(inputs.reshape(n * n_bodies, -1)).reshape(n, n_bodies, 6)
        return correction.corrected(bodies, qpos, qvel, qpos1, qvel1, change, self.contact_margin)
