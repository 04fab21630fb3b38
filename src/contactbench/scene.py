"""A recordings dataset in memory: the Scene a model sees (bodies, meshes, static geometry, joints, dt, gravity, floor),
its recorded trajectories (Split), and Recordings, the two together; and the format's versions they follow
(docs/RECORDINGS.md). Reading, checking and writing them: recordings.py."""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from contactbench.errors import RecordingsError
from contactbench.meshes import Mesh

FORMAT = "rigid-contact-recordings"
VERSION = 1  # what a dataset of free convex-collided bodies on a flat floor is written as
SCENE_VERSION = 2  # adds convex pieces of non-convex bodies, static geometry and joints (docs/RECORDINGS.md)
VERSIONS = (VERSION, SCENE_VERSION)


@dataclass(frozen=True)
class Body:
    name: str
    mesh: str  # OBJ path relative to the dataset folder
    mass: float  # kg
    inertia_diagonal: tuple[float, float, float] | None  # kg m^2 about axes through the CoM parallel to the mesh frame


@dataclass(frozen=True)
class HeightField:
    """A grid of heights over the x-y plane of its static entry's pose, centred there; cells are split into two
    triangles along the diagonal from (x_i, y_j) to (x_i+1, y_j+1), the surface every engine and metric uses."""

    heights: np.ndarray  # [rows along y, columns along x] metres above the entry's frame
    size: tuple[float, float]  # extent along x and along y, m

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """The columns' x [C] and the rows' y [R] in the entry's frame."""
        rows, columns = self.heights.shape
        return (
            np.linspace(-self.size[0] / 2, self.size[0] / 2, columns),
            np.linspace(-self.size[1] / 2, self.size[1] / 2, rows),
        )

    def surface(self) -> Mesh:
        """The surface as triangles in the entry's frame (open, counter-clockwise seen from above)."""
        x, y = np.meshgrid(*self.grid())
        vertices = np.stack([x, y, self.heights], axis=-1).reshape(-1, 3)
        rows, columns = self.heights.shape
        corner = (np.arange(rows - 1)[:, None] * columns + np.arange(columns - 1)[None, :]).ravel()
        faces = np.concatenate(
            [
                np.stack([corner, corner + 1, corner + columns + 1], axis=1),
                np.stack([corner, corner + columns + 1, corner + columns], axis=1),
            ]
        )
        return Mesh(vertices, faces)


@dataclass(frozen=True)
class Static:
    """Scene geometry that never moves (version 2): a convex mesh or a height field, at a world pose."""

    name: str
    pose: np.ndarray  # [7] position, quaternion w x y z of the entry's frame in the world
    mesh: str | None = None  # OBJ path (a closed convex solid) relative to the dataset folder
    heightfield: HeightField | None = None


def static_entries(entries: list[dict]) -> list[Static]:
    """meta.json 'static' entries (validated) as Static."""
    return [
        Static(
            name=entry["name"],
            pose=np.asarray(entry["pose"], dtype=np.float64),
            mesh=entry.get("mesh"),
            heightfield=HeightField(
                np.asarray(entry["heightfield"]["heights"], dtype=np.float64),
                tuple(float(x) for x in entry["heightfield"]["size"]),
            )
            if "heightfield" in entry
            else None,
        )
        for entry in entries
    ]


@dataclass(frozen=True)
class Joint:
    """A hinge between two bodies (version 2): the anchors coincide in the world, and the child's mesh frame is the
    parent's turned by the joint angle about the axis (angle 0: the two frames are parallel)."""

    name: str
    parent: int  # body indices
    child: int
    parent_anchor: np.ndarray  # [3] in the parent's mesh frame, m
    child_anchor: np.ndarray  # [3] in the child's mesh frame, m
    axis: np.ndarray  # [3] unit, the same in both mesh frames
    damping: float  # N m s / rad: torque against the joint's angular rate
    range: tuple[float, float] | None  # rad, the angles the joint stops at; None: it turns freely
    friction: float = 0.0  # N m: Coulomb torque against the joint's turning (dry friction in the axle)


@dataclass
class Split:
    poses: np.ndarray  # [N, T, K, 7] position (m) then quaternion w, x, y, z; world frame
    lengths: np.ndarray  # [N] valid frames per trajectory
    velocities: np.ndarray | None = None  # [N, T, K, 6] linear (m/s) then angular (rad/s), world frame
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_trajectories(self) -> int:
        return self.poses.shape[0]

    @property
    def n_frames(self) -> int:
        return self.poses.shape[1]

    @property
    def n_bodies(self) -> int:
        return self.poses.shape[2]

    def valid_mask(self) -> np.ndarray:
        """[N, T] True where a frame is inside its trajectory."""
        return np.arange(self.n_frames)[None, :] < self.lengths[:, None]

    def select(self, indices: Iterable[int] | np.ndarray) -> Split:
        """The trajectories at `indices`, trimmed to the longest of them."""
        indices = np.asarray(list(indices) if not isinstance(indices, np.ndarray) else indices, dtype=np.int64)
        lengths = self.lengths[indices]
        horizon = int(lengths.max()) if len(lengths) else 0
        extras = {name: self._select_extra(value, indices, horizon) for name, value in self.extras.items()}
        velocities = None if self.velocities is None else self.velocities[indices, :horizon]
        return Split(self.poses[indices, :horizon], lengths, velocities, extras)

    def every(self, stride: int) -> Split:
        """Frames 0, stride, 2 stride, ... of every trajectory (a lower frame rate); per-frame extras alike."""
        lengths = (self.lengths - 1) // stride + 1
        horizon = int(lengths.max()) if len(lengths) else 0

        def thin(value: np.ndarray) -> np.ndarray:
            return value[:, ::stride][:, :horizon]

        velocities = None if self.velocities is None else thin(self.velocities)
        extras = {
            name: thin(value) if value.shape[:2] == self.poses.shape[:2] else value
            for name, value in self.extras.items()
        }
        return Split(thin(self.poses), lengths, velocities, extras)

    def _select_extra(self, value: np.ndarray, indices: np.ndarray, horizon: int) -> np.ndarray:
        """Per-frame extras ([N, T, ...]) follow poses; per-trajectory ones ([N, ...]) follow lengths; others stay."""
        if value.shape[:2] == self.poses.shape[:2]:
            return value[indices, :horizon]
        if value.shape[:1] == (self.n_trajectories,):
            return value[indices]
        return value

    def arrays(self) -> dict[str, np.ndarray]:
        arrays = dict(self.extras)
        arrays["poses"] = self.poses
        arrays["lengths"] = self.lengths
        if self.velocities is not None:
            arrays["velocities"] = self.velocities
        return arrays


@dataclass
class Scene:
    """What a model sees of a dataset when it rolls out: bodies, meshes, dt, gravity, floor; no trajectories."""

    meta: dict  # meta.json as read; unknown keys are kept and written back
    meshes: dict[str, Mesh]  # by the mesh path used in meta.bodies
    root: Path | None = None
    # Multiplies every body's inertia tensor: a candidate of identification (sim/articulation.py), never read from or
    # written to a file.
    inertia_scale: float = 1.0

    @property
    def name(self) -> str:
        return self.meta["name"]

    @property
    def dt(self) -> float:
        return float(self.meta["dt"])

    @property
    def gravity(self) -> np.ndarray:
        return np.asarray(self.meta["gravity"], dtype=np.float64)

    @property
    def floor_z(self) -> float:
        return float(self.meta.get("floor_z", 0.0))

    @property
    def real(self) -> bool:
        return bool(self.meta.get("real", False))

    @property
    def bodies(self) -> list[Body]:
        return [
            Body(
                name=entry["name"],
                mesh=entry["mesh"],
                mass=float(entry["mass"]),
                inertia_diagonal=tuple(float(x) for x in entry["inertia_diagonal"])
                if "inertia_diagonal" in entry
                else None,
            )
            for entry in self.meta["bodies"]
        ]

    @property
    def n_bodies(self) -> int:
        return len(self.meta["bodies"])

    def body_mesh(self, k: int) -> Mesh:
        """Body k's true surface (closed; convex or not)."""
        return self.meshes[self.meta["bodies"][k]["mesh"]]

    @property
    def version(self) -> int:
        return int(self.meta["version"])

    def piece_paths(self, k: int) -> list[str]:
        """The OBJ paths of the convex solids engines collide for body k: its pieces (version 2) or its mesh."""
        entry = self.meta["bodies"][k]
        return list(entry["pieces"]) if not self.is_convex(k) else [entry["mesh"]]

    def body_pieces(self, k: int) -> list[Mesh]:
        """The convex solids engines collide for body k (piece_paths)."""
        return [self.meshes[path] for path in self.piece_paths(k)]

    def is_convex(self, k: int) -> bool:
        """Whether body k is collided as its own mesh (no pieces)."""
        return self.version < SCENE_VERSION or "pieces" not in self.meta["bodies"][k]

    @property
    def static(self) -> list[Static]:
        """Static scene geometry besides the floor (version 2; none in version 1)."""
        return static_entries(self.meta.get("static", [])) if self.version >= SCENE_VERSION else []

    @property
    def joints(self) -> list[Joint]:
        """Hinges between bodies (version 2; none in version 1), each after the one that places its parent."""
        if self.version < SCENE_VERSION:
            return []
        index = {body["name"]: k for k, body in enumerate(self.meta["bodies"])}

        def unit(vector) -> np.ndarray:
            vector = np.asarray(vector, dtype=np.float64)
            return vector / np.linalg.norm(vector)

        joints = [
            Joint(
                name=entry["name"],
                parent=index[entry["parent"]],
                child=index[entry["child"]],
                parent_anchor=np.asarray(entry["parent_anchor"], dtype=np.float64),
                child_anchor=np.asarray(entry["child_anchor"], dtype=np.float64),
                axis=unit(entry["axis"]),
                damping=float(entry.get("damping", 0.0)),
                range=tuple(float(x) for x in entry["range"]) if "range" in entry else None,
                friction=float(entry.get("friction", 0.0)),
            )
            for entry in self.meta.get("joints", [])
        ]
        # parents first (a validated tree), so a joint's parent is placed before its child is
        placed = set(range(self.n_bodies)) - {joint.child for joint in joints}
        ordered: list[Joint] = []
        while len(ordered) < len(joints):
            ready = [joint for joint in joints if joint.parent in placed and joint.child not in placed]
            ordered += ready
            placed |= {joint.child for joint in ready}
        return ordered

    @property
    def flat(self) -> bool:
        """Free convex-collided bodies on the flat floor alone: the scenes every model of the paper handles."""
        return not self.static and not self.joints and all(self.is_convex(k) for k in range(self.n_bodies))

    def widths(self) -> np.ndarray:
        """Per-body width w_k: the largest extent of the mesh's axis-aligned bounding box (m)."""
        return np.array([self.body_mesh(k).width for k in range(self.n_bodies)])

    def inertial(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Body k's centre of mass in the mesh frame and its inertia tensor about the CoM (mesh-frame axes): its mesh's
        uniform solid (Mesh.mass_properties), with the recorded inertia diagonal where the recordings give one."""
        body = self.bodies[k]
        com, inertia = self.body_mesh(k).mass_properties(body.mass)
        if body.inertia_diagonal is not None:
            inertia = np.diag(body.inertia_diagonal)
        return com, self.inertia_scale * inertia


@dataclass
class Recordings(Scene):
    """A scene and its recorded trajectories, split by name (train, val, test)."""

    splits: dict[str, Split] = field(default_factory=dict)

    @property
    def scene(self) -> Scene:
        """The scene alone, without meta.generator (the hidden simulation parameters): what a rollout may see."""
        return Scene(meta=self._meta_for_models(), meshes=self.meshes, root=self.root, inertia_scale=self.inertia_scale)

    def split(self, name: str) -> Split:
        if name not in self.splits:
            where = self.root or self.name
            raise RecordingsError(f"{where}: split {name!r} not loaded (available: {sorted(self.splits)})")
        return self.splits[name]

    def for_models(self, splits: Iterable[str] = ()) -> Recordings:
        """What a model may see: only the named splits, and no meta.generator (the hidden simulation parameters)."""
        return replace(self, meta=self._meta_for_models(), splits={name: self.split(name) for name in splits})

    def _meta_for_models(self) -> dict:
        meta = copy.deepcopy(self.meta)
        meta.pop("generator", None)
        return meta
