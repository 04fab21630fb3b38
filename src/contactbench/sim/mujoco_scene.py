"""Build a MuJoCo model of any recordings scene (convex meshes, free bodies, floor) and convert its state.

Conventions
-----------
* Body frame = the recordings' mesh frame. The mesh geom sits in the body at whatever offset MuJoCo's mesh
  compiler gives it (it recentres meshes on their own centroid and principal axes and compensates with the geom's
  pos/quat), the inertia is explicit (`<inertial pos=com fullinertia=...>`), so a free joint's
  qpos = (x, y, z, qw, qx, qy, qz) of the body is exactly a recordings pose.
* MuJoCo free-joint qvel = (linear velocity of the body-frame origin, world frame; angular velocity, BODY frame).
  Recordings velocities are both world-frame; `pack_state` / `unpack_state` convert at this boundary.
* Collision uses each mesh's convex hull (MuJoCo collides mesh geoms as convex hulls); a body with convex pieces
  (recordings version 2) has one mesh geom per piece, its inertia still the true mesh's.
* Terrain (version 2): static mesh geoms and height fields in the world body, in contact with every body through
  pairs carrying the floor's parameters. A hinge's child is nested in its parent on a hinge joint (placed as at angle
  0, damping as recorded), so its state is the joint's angle and rate (`StateLayout` converts); MuJoCo leaves a body
  and its parent out of contact, so an explicit pair puts the two links back in.
* Integrator: MuJoCo's Euler, which is semi-implicit (v += h a, then x += h v_new), the convention the recorded
  velocities follow (x_t - x_{t-1} = dt v_t); no joint damping on free joints, timestep = dt / substeps.

How contact parameters reach contacts
-------------------------------------
MuJoCo combines two geoms' parameters per contact: friction is the element-wise maximum, condim the maximum, and
solref/solimp are mixed with solmix weights (or, for the direct "-stiffness -damping" format, taken element-wise
minimum), unless geom priorities differ (then the higher-priority geom's values are copied, friction included).
Neither mixing nor priority states "the floor's solref governs floor contacts while friction stays the max of the
two" directly, so the floor takes no part in MuJoCo's dynamic collision filtering (contype = conaffinity = 0) and
every (floor, body k) contact comes from an explicit `<contact><pair>` whose values are written here:
friction = max(object_friction[k], floor_friction) (MuJoCo's own rule, applied by us), solref = the floor's,
condim and solimp as for geom contacts. The floor geom carries the same values so that model.geom_* shows them,
though only the pairs act. Body-body contacts stay dynamic: MuJoCo takes the max of the two bodies' friction and its
default solref/solimp (one contact point per convex pair: MuJoCo's `multiccd` stays off, as in its defaults).
"""

from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.kinematics import hinge_child, hinge_coordinates
from contactbench.scene import Joint, Scene, Static
from contactbench.sim.articulation import Articulation, articulated
from contactbench.sim.effects import NO_EFFECTS, SceneEffects, inertials
from contactbench.values import freeze_numbers

MUJOCO_DEFAULT_SOLREF = (0.02, 1.0)  # time constant (s), damping ratio: MuJoCo's default for every contact
MUJOCO_DEFAULT_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)


@dataclass(frozen=True)
class ContactParameters:
    """The contact parameters system identification tunes (the paper's Table 2c), plus optional spin/roll friction."""

    object_friction: tuple[float, ...]  # sliding friction coefficient per body, in the recordings' body order
    floor_friction: float
    floor_stiffness: float | None  # MuJoCo direct solref "-stiffness -damping"; None (both) = default solref
    floor_damping: float | None
    # The floor contacts' impedance (solimp dmin, dmax, width; midpoint and power stay MuJoCo's): how the constraint's
    # hardness grows with penetration, which shapes an impact beyond stiffness and damping. None: MuJoCo's default.
    floor_solimp: tuple[float, float, float] | None = None
    torsional_friction: float = 0.0  # non-zero turns on condim 4 (all contacts)
    rolling_friction: float = 0.0  # non-zero turns on condim 6 (all contacts)
    effects: SceneEffects = NO_EFFECTS
    articulation: Articulation | None = None  # hinged scenes: joint damping, friction and inertia; None: as recorded

    def __post_init__(self):
        freeze_numbers(self, vectors=("object_friction", "floor_solimp"), skip=("effects", "articulation"))
        if (self.floor_stiffness is None) != (self.floor_damping is None):
            raise ContactbenchError("floor_stiffness and floor_damping are given together or not at all")
        frictions = self.object_friction + (self.floor_friction, self.torsional_friction, self.rolling_friction)
        if not all(np.isfinite(frictions)) or min(frictions) < 0:
            raise ContactbenchError(f"friction coefficients must be finite and non-negative, got {self}")
        if self.floor_stiffness is not None and not (self.floor_stiffness > 0 and self.floor_damping >= 0):
            raise ContactbenchError(f"floor stiffness must be positive and damping non-negative, got {self}")
        if self.floor_solimp is not None and not (
            0 < self.floor_solimp[0] < 1 and 0 < self.floor_solimp[1] < 1 and self.floor_solimp[2] > 0
        ):
            raise ContactbenchError(f"floor solimp dmin and dmax must lie in (0, 1) and its width be > 0, got {self}")

    @classmethod
    def mujoco_default(cls, n_bodies: int) -> ContactParameters:
        """MuJoCo's own defaults (friction 1, solref 0.02 1, default solimp, condim 3): the untuned simulation.

        MuJoCo's default geom friction is "1 0.005 0.0001"; with condim 3 only the first entry acts.
        """
        return cls(object_friction=(1.0,) * n_bodies, floor_friction=1.0, floor_stiffness=None, floor_damping=None)

    @property
    def condim(self) -> int:
        if self.rolling_friction > 0:
            return 6
        return 4 if self.torsional_friction > 0 else 3

    @property
    def floor_impedance(self) -> tuple[float, ...]:
        if self.floor_solimp is None:
            return MUJOCO_DEFAULT_SOLIMP
        return (*self.floor_solimp, *MUJOCO_DEFAULT_SOLIMP[3:])

    @property
    def floor_solref(self) -> tuple[float, float]:
        if self.floor_stiffness is None:
            return MUJOCO_DEFAULT_SOLREF
        return (-self.floor_stiffness, -self.floor_damping)


def _numbers(values) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(values))


def scene_xml(dataset: Scene, params: ContactParameters, substeps: int = 1) -> str:
    """The MJCF text of the dataset's scene with the given contact parameters (see the module docstring)."""
    if len(params.object_friction) != dataset.n_bodies:
        raise ContactbenchError(
            f"{len(params.object_friction)} object frictions for a scene of {dataset.n_bodies} bodies"
        )
    if substeps < 1:
        raise ContactbenchError(f"substeps must be a positive integer, got {substeps}")
    dataset = articulated(dataset, params.articulation)
    pieces = [dataset.piece_paths(k) for k in range(dataset.n_bodies)]
    static = dataset.static
    used = [path for paths in pieces for path in paths] + [entry.mesh for entry in static if entry.mesh is not None]
    mesh_names = {path: f"mesh{i}" for i, path in enumerate(dict.fromkeys(used))}
    spin_roll = (params.torsional_friction, params.rolling_friction)
    assets = [
        f'<mesh name="{name}" vertex="{_numbers(dataset.meshes[path].vertices)}" '
        f'face="{" ".join(str(int(i)) for i in dataset.meshes[path].faces.ravel())}"/>'
        for path, name in mesh_names.items()
    ] + [_hfield_asset(i, entry) for i, entry in enumerate(static) if entry.heightfield is not None]
    effects = params.effects
    ground_contact = (
        f'condim="{params.condim}" contype="0" conaffinity="0" solref="{_numbers(params.floor_solref)}" '
        f'solimp="{_numbers(params.floor_impedance)}" friction="{_numbers((params.floor_friction,) + spin_roll)}"'
    )
    ground_geoms = ["floor"] + [f"static{i}" for i in range(len(static))]
    coms, inertias = inertials(dataset, effects)
    bodies, pairs, geom_names = {}, [], []
    for k, body in enumerate(dataset.bodies):
        com, inertia = coms[k], inertias[k]
        full_inertia = (inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2])
        names = [f"geom{k}"] if len(pieces[k]) == 1 else [f"geom{k}_{i}" for i in range(len(pieces[k]))]
        geom_names.append(names)
        geoms = "".join(
            f'<geom name="{name}" type="mesh" mesh="{mesh_names[path]}" condim="{params.condim}" '
            f'friction="{_numbers((params.object_friction[k],) + spin_roll)}"/>'
            for name, path in zip(names, pieces[k])
        )
        bodies[k] = (
            f'<inertial pos="{_numbers(com)}" mass="{body.mass!r}" fullinertia="{_numbers(full_inertia)}"/>{geoms}'
        )
        sliding = max(params.object_friction[k], params.floor_friction)
        # A floor contact's first tangent is the floor's y axis, its second the x axis (MuJoCo's plane frame).
        along_y, along_x = (
            sliding / np.sqrt(effects.friction_anisotropy),
            sliding * np.sqrt(effects.friction_anisotropy),
        )
        pairs += [
            f'<pair geom1="{ground}" geom2="{name}" condim="{params.condim}" solref="{_numbers(params.floor_solref)}" '
            f'solimp="{_numbers(params.floor_impedance)}" '
            f'friction="{_numbers((along_y, along_x, params.torsional_friction) + (params.rolling_friction,) * 2)}"/>'
            for name in names
            for ground in ground_geoms
        ]
    for joint in dataset.joints:  # MuJoCo leaves a body and its parent out of contact: the pair puts them back
        linked = max(params.object_friction[joint.parent], params.object_friction[joint.child])
        pairs += [
            f'<pair geom1="{first}" geom2="{second}" condim="{params.condim}" '
            f'friction="{_numbers((linked, linked, params.torsional_friction) + (params.rolling_friction,) * 2)}"/>'
            for first in geom_names[joint.parent]
            for second in geom_names[joint.child]
        ]
    statics = [_static_geom(i, entry, mesh_names, ground_contact) for i, entry in enumerate(static)]
    fluid = f' density="{effects.fluid_density!r}" wind="{_numbers(effects.wind)}"' if effects.fluid_density > 0 else ""
    gravity = _numbers(np.asarray(dataset.gravity) * effects.gravity_scale)
    return "\n".join(
        [
            f"<mujoco model={quoteattr(dataset.name)}>",
            '<compiler angle="radian" inertiafromgeom="false"/>',
            f'<option timestep="{dataset.dt / substeps!r}" gravity="{gravity}" integrator="Euler"{fluid}/>',
            "<asset>",
            *assets,
            "</asset>",
            "<worldbody>",
            f'<geom name="floor" type="plane" size="0 0 1" pos="0 0 {dataset.floor_z + effects.floor_offset!r}" '
            f'quat="{_numbers(rotations.tilt(*effects.floor_tilt))}" {ground_contact}/>',
            *statics,
            *_body_tree(dataset, bodies),
            "</worldbody>",
            "<contact>",
            *pairs,
            "</contact>",
            "</mujoco>",
        ]
    )


def _body_tree(dataset: Scene, contents: dict[int, str]) -> list[str]:
    """Every body's XML: free bodies at the top, each hinge's child nested in its parent, placed as at angle 0."""
    child_joint = {joint.child: (j, joint) for j, joint in enumerate(dataset.joints)}

    def body(k: int) -> str:
        if k in child_joint:
            j, joint = child_joint[k]
            limits = f' limited="true" range="{_numbers(joint.range)}"' if joint.range is not None else ""
            head = (
                f'<body name="body{k}" pos="{_numbers(joint.parent_anchor - joint.child_anchor)}">'
                f'<joint name="hinge{j}" type="hinge" pos="{_numbers(joint.child_anchor)}" '
                f'axis="{_numbers(joint.axis)}" damping="{joint.damping!r}" frictionloss="{joint.friction!r}"{limits}/>'
            )
        else:
            head = f'<body name="body{k}"><freejoint name="joint{k}"/>'
        children = "".join(body(joint.child) for joint in dataset.joints if joint.parent == k)
        return f"{head}{contents[k]}{children}</body>"

    return [body(k) for k in range(dataset.n_bodies) if k not in child_joint]


def _hfield_asset(i: int, entry: Static) -> str:
    """MuJoCo scales a height field's elevation data to [0, 1] and reads its first row at +y: the heights go in
    shifted to 0 and row-reversed, their range as the size's elevation (the geom's height adds the minimum back)."""
    heights = entry.heightfield.heights
    span = max(float(heights.max() - heights.min()), 1e-9)
    rows, columns = heights.shape
    half_x, half_y = (size / 2 for size in entry.heightfield.size)
    return (
        f'<hfield name="field{i}" nrow="{rows}" ncol="{columns}" size="{half_x!r} {half_y!r} {span!r} {span!r}" '
        f'elevation="{_numbers((heights - heights.min())[::-1])}"/>'
    )


def _static_geom(i: int, entry: Static, mesh_names: dict[str, str], contact: str) -> str:
    position = entry.pose[:3].copy()
    if entry.mesh is not None:
        shape = f'type="mesh" mesh="{mesh_names[entry.mesh]}"'
    else:
        position += rotations.rotate(entry.pose[3:], np.array([0.0, 0.0, entry.heightfield.heights.min()]))
        shape = f'type="hfield" hfield="field{i}"'
    return f'<geom name="static{i}" {shape} pos="{_numbers(position)}" quat="{_numbers(entry.pose[3:])}" {contact}/>'


def build_model(dataset: Scene, params: ContactParameters, substeps: int = 1) -> mujoco.MjModel:
    """A compiled MuJoCo model of the scene: one free body per recordings body, timestep dt / substeps."""
    return mujoco.MjModel.from_xml_string(scene_xml(dataset, params, substeps))


@dataclass(frozen=True)
class StateLayout:
    """Where each recordings body lives in a compiled scene's qpos / qvel: a free body as its free joint, a hinge's
    child as the joint's angle and rate (its pose and velocity follow from its parent's, kinematics.hinge_child)."""

    n_bodies: int
    joints: tuple[Joint, ...]
    free_qpos: dict[int, int]  # body -> qpos address of its free joint (7 entries)
    free_qvel: dict[int, int]  # body -> qvel address (6 entries)
    hinge_qpos: tuple[int, ...]  # per joint
    hinge_qvel: tuple[int, ...]

    @classmethod
    def of(cls, dataset: Scene, model: mujoco.MjModel) -> StateLayout:
        joints = tuple(dataset.joints)
        children = {joint.child for joint in joints}
        roots = [k for k in range(dataset.n_bodies) if k not in children]
        return cls(
            dataset.n_bodies,
            joints,
            {k: int(model.joint(f"joint{k}").qposadr[0]) for k in roots},
            {k: int(model.joint(f"joint{k}").dofadr[0]) for k in roots},
            tuple(int(model.joint(f"hinge{j}").qposadr[0]) for j in range(len(joints))),
            tuple(int(model.joint(f"hinge{j}").dofadr[0]) for j in range(len(joints))),
        )

    @property
    def free(self) -> bool:
        """Every body free, in order: qpos and qvel are the recordings' states side by side (pack_state)."""
        return not self.joints

    def pack(self, poses: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Recordings poses [..., K, 7] and world velocities [..., K, 6] -> qpos [..., nq], qvel [..., nv]."""
        if self.free:
            return pack_state(poses, velocities)
        lead = poses.shape[:-2]
        qpos = np.zeros(lead + (7 * len(self.free_qpos) + len(self.joints),))
        qvel = np.zeros(lead + (6 * len(self.free_qvel) + len(self.joints),))
        free_qvel = body_frame_velocities(poses, velocities)
        for k, address in self.free_qpos.items():
            qpos[..., address : address + 3] = poses[..., k, :3]
            qpos[..., address + 3 : address + 7] = rotations.normalize(poses[..., k, 3:])
            qvel[..., self.free_qvel[k] : self.free_qvel[k] + 6] = free_qvel[..., k, :]
        for joint, position_at, velocity_at in zip(self.joints, self.hinge_qpos, self.hinge_qvel):
            qpos[..., position_at], qvel[..., velocity_at] = hinge_coordinates(
                poses[..., joint.parent, :],
                velocities[..., joint.parent, :],
                poses[..., joint.child, :],
                velocities[..., joint.child, :],
                joint,
            )
        return qpos, qvel

    def unpack(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qpos [..., nq], qvel [..., nv] -> recordings poses [..., K, 7] and free-joint velocities [..., K, 6] (world
        linear, body angular: what a free body's qvel would be)."""
        if self.free:
            return (
                qpos.reshape(*qpos.shape[:-1], self.n_bodies, 7),
                qvel.reshape(*qvel.shape[:-1], self.n_bodies, 6),
            )
        lead = qpos.shape[:-1]
        poses = np.empty(lead + (self.n_bodies, 7))
        velocities = np.empty(lead + (self.n_bodies, 6))
        for k, address in self.free_qpos.items():
            poses[..., k, :] = qpos[..., address : address + 7]
            velocities[..., k, :] = world_velocities(
                poses[..., k, :], qvel[..., self.free_qvel[k] : self.free_qvel[k] + 6]
            )
        for joint, position_at, velocity_at in zip(self.joints, self.hinge_qpos, self.hinge_qvel):  # parents first
            poses[..., joint.child, :], velocities[..., joint.child, :] = hinge_child(
                poses[..., joint.parent, :],
                velocities[..., joint.parent, :],
                joint,
                qpos[..., position_at],
                qvel[..., velocity_at],
            )
        return poses, body_frame_velocities(poses, velocities)


def pack_state(poses: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Recordings poses [..., K, 7] and world velocities [..., K, 6] -> MuJoCo qpos [..., 7K], qvel [..., 6K]."""
    qpos = np.concatenate([poses[..., :3], rotations.normalize(poses[..., 3:])], axis=-1)
    qvel = body_frame_velocities(qpos, velocities)
    return qpos.reshape(*poses.shape[:-2], -1), qvel.reshape(*velocities.shape[:-2], -1)


def unpack_state(qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo qpos [..., 7K], qvel [..., 6K] -> recordings poses [..., K, 7] and world velocities [..., K, 6]."""
    poses = qpos.reshape(*qpos.shape[:-1], -1, 7)
    return poses, world_velocities(poses, qvel.reshape(*qvel.shape[:-1], -1, 6))


def body_frame_velocities(poses: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """World [v, w] [..., K, 6] -> free-joint velocities [..., K, 6]: v stays world-frame, w turns into the body
    frame."""
    qvel = np.empty(np.broadcast_shapes(poses.shape[:-1], velocities.shape[:-1]) + (6,))
    qvel[..., :3] = velocities[..., :3]
    qvel[..., 3:] = rotations.rotate(rotations.conjugate(poses[..., 3:]), velocities[..., 3:])
    return qvel


def world_velocities(poses: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """Free-joint velocities [..., K, 6] (body-frame angular part) -> world [v, w] [..., K, 6]."""
    velocities = np.empty(np.broadcast_shapes(poses.shape[:-1], qvel.shape[:-1]) + (6,))
    velocities[..., :3] = qvel[..., :3]
    velocities[..., 3:] = rotations.rotate(poses[..., 3:], qvel[..., 3:])
    return velocities
