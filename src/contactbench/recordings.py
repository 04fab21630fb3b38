"""The one reader, validator and writer of the recordings format (docs/RECORDINGS.md, versions 1 and 2)."""

from __future__ import annotations

import copy
import json
import lzma
import math
import os
import shutil
import zipfile
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from contactbench import atomic, kinematics
from contactbench.errors import ContactbenchError
from contactbench.meshes import Mesh, MeshError, convexity_problem, obj_text, read_obj

FORMAT = "rigid-contact-recordings"
VERSION = 1  # what a dataset of free convex-collided bodies on a flat floor is written as
SCENE_VERSION = 2  # adds convex pieces of non-convex bodies, static geometry and joints (docs/RECORDINGS.md)
VERSIONS = (VERSION, SCENE_VERSION)
MAX_COORDINATE = 1000.0  # m: static geometry farther out than this is a unit or sign mistake, not a scene
QUATERNION_TOLERANCE = 1e-3
# A hinge's two anchors may sit this far apart in a recorded frame (m), and its two axes this far out of line (rad):
# tracking noise, and an engine's joint drift, stay well inside; a mislabelled anchor or body does not.
HINGE_GAP_TOLERANCE = 5e-3
HINGE_AXIS_TOLERANCE = 0.05
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a zip's first entry, or an empty zip


class RecordingsError(ContactbenchError):
    """A dataset that does not follow the recordings format; the message names file, field and place."""


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


# ---------------------------------------------------------------- validation


def _fail(where: str, message: str) -> RecordingsError:
    return RecordingsError(f"{where}: {message}")


def _require(meta: Mapping, key: str, types: type | tuple[type, ...], where: str, expected: str):
    if key not in meta:
        raise _fail(where, f"field '{key}' is missing (expected {expected})")
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, types):
        raise _fail(where, f"field '{key}' is {value!r} (expected {expected})")
    return value


def _vector(meta: Mapping, key: str, size: int, where: str) -> list[float]:
    value = meta[key]
    if (
        not isinstance(value, list)
        or len(value) != size
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in value)
    ):
        raise _fail(where, f"field '{key}' is {value!r} (expected a list of {size} finite numbers)")
    return value


def _inside_path(value: str, field: str, where: str) -> None:
    """Paths in meta.json name files inside the dataset folder: never absolute, never up and out with '..'."""
    path = PurePosixPath(value)
    if not value or path.is_absolute() or PureWindowsPath(value).is_absolute() or ".." in path.parts or "\\" in value:
        raise _fail(
            where,
            f"field '{field}' is {value!r} (expected a relative path inside the dataset folder, '/'-separated, "
            "without '..')",
        )


def mesh_paths(meta: Mapping) -> list[str]:
    """Every OBJ path a (validated) meta.json names: body meshes, their pieces (version 2), static meshes."""
    paths = [body["mesh"] for body in meta["bodies"]]
    if meta["version"] >= SCENE_VERSION:
        paths += [piece for body in meta["bodies"] for piece in body.get("pieces", [])]
        paths += [entry["mesh"] for entry in meta.get("static", []) if "mesh" in entry]
    return list(dict.fromkeys(paths))


def validate_meta(meta: object, where: str) -> None:
    if not isinstance(meta, dict):
        raise _fail(where, "expected a JSON object")
    if meta.get("format") != FORMAT:
        raise _fail(where, f"field 'format' is {meta.get('format')!r} (expected {FORMAT!r})")
    if meta.get("version") not in VERSIONS or isinstance(meta.get("version"), bool):
        raise _fail(
            where,
            f"field 'version' is {meta.get('version')!r} (expected one of {list(VERSIONS)}, the versions this "
            "reader knows)",
        )
    _require(meta, "name", str, where, "a string")
    dt = _require(meta, "dt", (int, float), where, "seconds between frames, a positive number")
    if not (np.isfinite(dt) and dt > 0):
        raise _fail(where, f"field 'dt' is {dt!r} (expected a positive number of seconds)")
    _require(meta, "gravity", list, where, "[gx, gy, gz] in m/s^2")
    _vector(meta, "gravity", 3, where)
    if "floor_z" in meta:
        floor_z = _require(meta, "floor_z", (int, float), where, "a finite number of metres")
        if not np.isfinite(floor_z):
            raise _fail(where, f"field 'floor_z' is {floor_z!r} (expected a finite number of metres)")
    bodies = _require(meta, "bodies", list, where, "a non-empty list of bodies")
    if not bodies:
        raise _fail(where, "field 'bodies' is empty (expected at least one body)")
    for k, body in enumerate(bodies):
        body_where = f"{where}: bodies[{k}]"
        if not isinstance(body, dict):
            raise _fail(body_where, "expected an object with name, mesh, mass")
        _require(body, "name", str, body_where, "a string")
        _require(body, "mesh", str, body_where, "an OBJ path relative to the dataset folder")
        _inside_path(body["mesh"], "mesh", body_where)
        mass = _require(body, "mass", (int, float), body_where, "a positive mass in kg")
        if not (np.isfinite(mass) and mass > 0):
            raise _fail(body_where, f"field 'mass' is {mass!r} (expected a positive mass in kg)")
        if "inertia_diagonal" in body:
            inertia = _vector(body, "inertia_diagonal", 3, body_where)
            if min(inertia) <= 0:
                raise _fail(body_where, f"field 'inertia_diagonal' is {inertia!r} (expected three positive kg m^2)")
    splits = _require(meta, "splits", dict, where, "an object mapping split names to .npz files")
    if not splits or not all(isinstance(v, str) for v in splits.values()):
        raise _fail(where, f"field 'splits' is {splits!r} (expected split name -> npz file path)")
    for name, value in splits.items():
        _inside_path(value, f"splits.{name}", where)
    if meta["version"] >= SCENE_VERSION:
        _validate_scene_fields(meta, where)


def _validate_scene_fields(meta: dict, where: str) -> None:
    """Version 2's pieces, static geometry and joints (their meshes are checked when read)."""
    names = [body["name"] for body in meta["bodies"]]
    if len(set(names)) != len(names):
        raise _fail(where, f"field 'bodies' repeats a name in {names} (expected unique names: joints refer to them)")
    for k, body in enumerate(meta["bodies"]):
        if "pieces" in body:
            pieces = body["pieces"]
            if not isinstance(pieces, list) or not pieces or not all(isinstance(p, str) for p in pieces):
                raise _fail(
                    f"{where}: bodies[{k}]", f"field 'pieces' is {pieces!r} (expected a non-empty list of OBJ paths)"
                )
            for i, piece in enumerate(pieces):
                _inside_path(piece, f"pieces[{i}]", f"{where}: bodies[{k}]")
    static = meta.get("static", [])
    if not isinstance(static, list):
        raise _fail(where, f"field 'static' is {static!r} (expected a list of static meshes and height fields)")
    for i, entry in enumerate(static):
        entry_where = f"{where}: static[{i}]"
        if not isinstance(entry, dict):
            raise _fail(entry_where, "expected an object with name, pose and mesh or heightfield")
        _require(entry, "name", str, entry_where, "a string")
        _require(entry, "pose", list, entry_where, "[x, y, z, qw, qx, qy, qz]")
        pose = _vector(entry, "pose", 7, entry_where)
        if max(abs(x) for x in pose[:3]) > MAX_COORDINATE:
            raise _fail(entry_where, f"field 'pose' is {pose!r} (expected a position within {MAX_COORDINATE:g} m)")
        if abs(np.linalg.norm(pose[3:]) - 1.0) > QUATERNION_TOLERANCE:
            raise _fail(entry_where, f"field 'pose' has quaternion {pose[3:]!r} (expected a unit quaternion)")
        if ("mesh" in entry) == ("heightfield" in entry):
            raise _fail(entry_where, "expected exactly one of 'mesh' (an OBJ path) and 'heightfield'")
        if "mesh" in entry:
            _require(entry, "mesh", str, entry_where, "an OBJ path relative to the dataset folder")
            _inside_path(entry["mesh"], "mesh", entry_where)
        else:
            _validate_heightfield(entry["heightfield"], f"{entry_where}.heightfield")
    joints = meta.get("joints", [])
    if not isinstance(joints, list):
        raise _fail(where, f"field 'joints' is {joints!r} (expected a list of hinges)")
    children: set[str] = set()
    for i, joint in enumerate(joints):
        joint_where = f"{where}: joints[{i}]"
        if not isinstance(joint, dict):
            raise _fail(joint_where, "expected an object with name, type, parent, child, anchors and axes")
        _require(joint, "name", str, joint_where, "a string")
        if joint.get("type") != "hinge":
            raise _fail(joint_where, f"field 'type' is {joint.get('type')!r} (expected 'hinge', the one joint known)")
        for key in ("parent", "child"):
            _require(joint, key, str, joint_where, "the name of a body in 'bodies'")
            if joint[key] not in names:
                raise _fail(joint_where, f"field '{key}' is {joint[key]!r} (expected one of the bodies {names})")
        if joint["parent"] == joint["child"]:
            raise _fail(joint_where, f"fields 'parent' and 'child' are both {joint['parent']!r} (expected two bodies)")
        if joint["child"] in children:
            raise _fail(joint_where, f"field 'child': {joint['child']!r} is the child of two joints (expected a tree)")
        children.add(joint["child"])
        for key in ("parent_anchor", "child_anchor", "axis"):
            _require(joint, key, list, joint_where, "[x, y, z] in the body's mesh frame")
            _vector(joint, key, 3, joint_where)
        if np.linalg.norm(joint["axis"]) < 1e-9:
            raise _fail(joint_where, f"field 'axis' is {joint['axis']!r} (expected a non-zero direction)")
        if "range" in joint:
            _require(joint, "range", list, joint_where, "[lowest, highest] angle in rad")
            low, high = _vector(joint, "range", 2, joint_where)
            if not low < high:
                raise _fail(joint_where, f"field 'range' is {joint['range']!r} (expected lowest < highest, in rad)")
        for key, unit in (("damping", "N m s/rad"), ("friction", "N m")):
            if key in joint:
                value = _require(joint, key, (int, float), joint_where, f"{unit}, >= 0")
                if not (np.isfinite(value) and value >= 0):
                    raise _fail(joint_where, f"field '{key}' is {value!r} (expected {unit}, >= 0)")
    parent_of = {joint["child"]: joint["parent"] for joint in joints}
    for name in parent_of:
        seen = {name}
        while name in parent_of:
            name = parent_of[name]
            if name in seen:
                raise _fail(where, f"field 'joints' closes a loop through {name!r} (expected a tree of bodies)")
            seen.add(name)


def _validate_heightfield(field: object, where: str) -> None:
    if not isinstance(field, dict):
        raise _fail(where, "expected an object with 'heights' (rows of numbers) and 'size' [x, y]")
    heights = field.get("heights")
    rows = heights if isinstance(heights, list) else []
    if (
        len(rows) < 2
        or not all(isinstance(row, list) and len(row) == len(rows[0]) >= 2 for row in rows)
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for row in rows for x in row)
    ):
        raise _fail(where, "field 'heights' is not a grid (expected at least 2 rows of at least 2 numbers, equal rows)")
    grid = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(grid).all() or np.abs(grid).max() > MAX_COORDINATE:
        raise _fail(where, f"field 'heights' (expected finite heights within {MAX_COORDINATE:g} m)")
    _require(field, "size", list, where, "[extent along x, extent along y] in m")
    size = _vector(field, "size", 2, where)
    if min(size) <= 0 or max(size) > MAX_COORDINATE:
        raise _fail(where, f"field 'size' is {size!r} (expected two positive extents in m)")


def validate_split(split: Split, n_bodies: int, where: str) -> None:
    poses = split.poses
    if poses.ndim != 4 or poses.shape[2] != n_bodies or poses.shape[3] != 7:
        raise _fail(
            where,
            f"field 'poses' has shape {poses.shape} (expected [N, T, K={n_bodies}, 7] for the {n_bodies} bodies in "
            "meta.json)",
        )
    n, horizon = poses.shape[:2]
    if n == 0 or horizon == 0:
        raise _fail(where, f"field 'poses' has shape {poses.shape} (expected at least one trajectory and one frame)")
    lengths = split.lengths
    if not np.issubdtype(lengths.dtype, np.integer):
        raise _fail(where, f"field 'lengths' has dtype {lengths.dtype} (expected int64)")
    if lengths.shape != (n,):
        raise _fail(where, f"field 'lengths' has shape {lengths.shape} (expected [{n}], one per trajectory)")
    bad = np.flatnonzero((lengths < 1) | (lengths > horizon))
    if len(bad):
        raise _fail(where, f"field 'lengths': trajectory {bad[0]} has length {lengths[bad[0]]} (expected 1..{horizon})")
    valid = split.valid_mask()
    _check_finite(poses, valid, "poses", where)
    with np.errstate(over="ignore", invalid="ignore"):  # a huge component is an off-norm quaternion, said below
        norms = np.linalg.norm(poses[..., 3:], axis=-1)
    off = valid[..., None] & (np.abs(norms - 1.0) > QUATERNION_TOLERANCE)
    if off.any():
        t_n, t_t, t_k = np.argwhere(off)[0]
        raise _fail(
            where,
            f"field 'poses': trajectory {t_n}, frame {t_t}, body {t_k}: quaternion norm {norms[t_n, t_t, t_k]:.6f} "
            f"(expected a unit quaternion within {QUATERNION_TOLERANCE})",
        )
    if split.velocities is not None:
        velocities = split.velocities
        if velocities.shape != poses.shape[:3] + (6,):
            raise _fail(
                where,
                f"field 'velocities' has shape {velocities.shape} (expected {poses.shape[:3] + (6,)}, like poses "
                "with 6 components)",
            )
        _check_finite(velocities, valid, "velocities", where)


def validate_hinges(scene: Scene, split: Split, where: str) -> None:
    """Every valid frame keeps each hinge: its anchors coincide and its axes line up, within the tolerances above."""
    valid = split.valid_mask()
    with np.errstate(invalid="ignore"):  # NaN frames past a toss's end are not judged
        gaps, tilts = kinematics.hinge_errors(split.poses, scene.joints)
    for j, joint in enumerate(scene.joints):
        gap, tilt = gaps[..., j], tilts[..., j]
        for values, tolerance, what in (
            (gap, HINGE_GAP_TOLERANCE, "m between its anchors"),
            (tilt, HINGE_AXIS_TOLERANCE, "rad between its axes"),
        ):
            bad = valid & ~(values <= tolerance)
            if bad.any():
                n, t = np.argwhere(bad)[0]
                raise _fail(
                    where,
                    f"field 'poses': trajectory {n}, frame {t}: hinge joints[{j}] ({joint.name!r}) has "
                    f"{values[n, t]:.4g} {what} (expected at most {tolerance}; meta.json's parent_anchor, "
                    "child_anchor and axis say where the two bodies meet)",
                )


def _check_finite(array: np.ndarray, valid: np.ndarray, name: str, where: str) -> None:
    bad = valid[..., None, None] & ~np.isfinite(array)
    if bad.any():
        t_n, t_t, t_k = np.argwhere(bad)[0][:3]
        raise _fail(
            where,
            f"field '{name}': trajectory {t_n}, frame {t_t}, body {t_k}: NaN or infinite value inside the valid frames",
        )


# ---------------------------------------------------------------- reading


def read_meta(root: str | os.PathLike) -> dict:
    path = Path(root) / "meta.json"
    if not Path(root).is_dir():
        raise RecordingsError(f"{root}: not a dataset folder (expected a folder with meta.json)")
    if not path.is_file():
        raise RecordingsError(f"{path}: missing (every recordings dataset needs meta.json)")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise RecordingsError(f"{path}: not valid JSON ({error})") from None
    validate_meta(meta, str(path))
    return meta


def read_split(path: Path, n_bodies: int) -> Split:
    where = str(path)
    if not path.is_file():
        raise RecordingsError(f"{path}: split file missing (named in meta.json 'splits')")
    with open(path, "rb") as handle:
        magic = handle.read(4)
    if magic not in ZIP_MAGIC:  # np.load would call any other bytes "pickled data"
        raise _fail(where, f"not an .npz archive (starts with {magic!r}; expected a zip archive of .npy arrays)")
    try:
        with zipfile.ZipFile(path) as archive:
            members = _npz_members(archive, path, where)
            if "poses" not in members:
                raise _fail(where, "field 'poses' is missing (expected float64 [N, T, K, 7])")
            poses = _float_array(archive, members, "poses", where)
            if "lengths" in members:
                lengths = _member(archive, members, "lengths", where)
                if not np.issubdtype(lengths.dtype, np.integer):
                    raise _fail(where, f"field 'lengths' has dtype {lengths.dtype} (expected int64)")
                lengths = lengths.astype(np.int64)
            else:
                lengths = np.full(
                    poses.shape[0] if poses.ndim else 0, poses.shape[1] if poses.ndim > 1 else 0, dtype=np.int64
                )
            velocities = _float_array(archive, members, "velocities", where) if "velocities" in members else None
            extras = {
                name: _member(archive, members, name, where)
                for name in members
                if name not in ("poses", "lengths", "velocities")
            }
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        NotImplementedError,
        OSError,
        EOFError,
        RuntimeError,
        zlib.error,
        lzma.LZMAError,
    ) as error:
        raise _fail(where, f"not a readable .npz archive ({_first_line(error)})") from None
    except ValueError as error:
        if isinstance(error, RecordingsError):
            raise
        raise _fail(where, f"not a readable .npz archive ({_first_line(error)})") from None
    split = Split(poses, lengths, velocities, extras)
    validate_split(split, n_bodies, where)
    return split


# Bounds checked before a member is decompressed or allocated: a few kB of crafted zip must not claim gigabytes.
MAX_INFLATION = 100  # uncompressed / compressed size of a deflated member; trajectories compress ~1.2x, a bomb ~1000x
INFLATION_FREE_BYTES = 1 << 20  # members this small may compress as well as they like
NPY_MAGIC = b"\x93NUMPY"
NUMERIC_KINDS = "biufc"  # bool, integers, floats, complex: plain numbers, nothing to unpickle or interpret
_CHUNK = 1 << 24


def memory_limit() -> int:
    """The most bytes one split may declare: this machine's physical memory (a larger split cannot be read here)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 36


def _first_line(error: BaseException) -> str:
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


def _npz_members(archive: zipfile.ZipFile, path: Path, where: str) -> dict[str, zipfile.ZipInfo]:
    """The archive's members by field name (np.load's naming: '.npy' dropped), their sizes checked against the file."""
    file_size = path.stat().st_size
    members: dict[str, zipfile.ZipInfo] = {}
    declared = 0
    for info in archive.infolist():
        name = info.filename[: -len(".npy")] if info.filename.endswith(".npy") else info.filename
        if info.is_dir():
            continue
        if info.compress_size > file_size:
            raise _fail(
                where,
                f"field '{name}': its zip entry claims {info.compress_size} compressed bytes, more than the file's "
                f"{file_size} (expected an intact archive)",
            )
        if info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
            raise _fail(
                where,
                f"field '{name}': its stored zip entry claims {info.file_size} bytes but holds {info.compress_size} "
                "(expected an intact archive)",
            )
        if info.file_size > INFLATION_FREE_BYTES and info.file_size > MAX_INFLATION * max(info.compress_size, 1):
            raise _fail(
                where,
                f"field '{name}' inflates from {info.compress_size} to {info.file_size} bytes "
                f"(more than {MAX_INFLATION}x; expected recorded trajectories, not a decompression bomb)",
            )
        members[name] = info
        declared += info.file_size
    limit = memory_limit()
    if declared > limit:
        raise _fail(
            where,
            f"its arrays declare {declared} bytes, more than this machine's {limit} bytes of memory (expected a "
            "split that fits in memory)",
        )
    return members


def _float_array(archive: zipfile.ZipFile, members: Mapping[str, zipfile.ZipInfo], name: str, where: str) -> np.ndarray:
    array = _member(archive, members, name, where)
    if not np.issubdtype(array.dtype, np.floating):
        raise _fail(where, f"field '{name}' has dtype {array.dtype} (expected float64)")
    return array.astype(np.float64, copy=False)


def _member(archive: zipfile.ZipFile, members: Mapping[str, zipfile.ZipInfo], name: str, where: str) -> np.ndarray:
    """One .npy member as a plain numeric array, or a RecordingsError that says what it is instead.

    The .npy header is read first and its shape and dtype checked against the member's size in the zip directory
    (header plus data, exactly), so nothing is allocated or decompressed beyond what the header and directory agree on.
    """
    info = members[name]
    with archive.open(info) as handle:
        if not info.filename.endswith(".npy") or handle.read(len(NPY_MAGIC)) != NPY_MAGIC:
            raise _fail(where, f"field '{name}' is not an .npy array (no .npy header; expected a plain numeric array)")
        try:
            version = (ord(handle.read(1) or b"\xff"), ord(handle.read(1) or b"\xff"))
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(handle)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(handle)
            else:
                raise ValueError(f"unsupported .npy format version {version}")
        except Exception as error:  # numpy parses the header text as a Python literal: any failure there is this one
            raise _fail(where, f"field '{name}' is not a readable .npy array ({_first_line(error)})") from None
        if dtype.hasobject:
            raise _fail(
                where, f"field '{name}' cannot be read without unpickling (object data); arrays must be plain numeric"
            )
        if dtype.kind not in NUMERIC_KINDS or dtype.fields is not None or dtype.subdtype is not None:
            raise _fail(where, f"field '{name}' has dtype {dtype} (expected a plain numeric array)")
        if any(n < 0 for n in shape):
            raise _fail(where, f"field '{name}': its .npy header declares shape {shape} (expected non-negative sizes)")
        count = math.prod(shape)
        expected = handle.tell() + count * dtype.itemsize
        if expected != info.file_size:
            raise _fail(
                where,
                f"field '{name}': its .npy header declares shape {shape} {dtype} ({count * dtype.itemsize} bytes of "
                f"data) but the member holds {info.file_size} bytes in all (expected header and data to agree)",
            )
        array = np.empty(count, dtype=dtype)
        raw = array.view(np.uint8)
        for start in range(0, raw.size, _CHUNK):
            chunk = handle.read(min(_CHUNK, raw.size - start))
            if len(chunk) != min(_CHUNK, raw.size - start):
                raise _fail(where, f"field '{name}' ends early (expected {raw.size} bytes of data)")
            raw[start : start + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
    if not dtype.isnative:
        array = array.astype(dtype.newbyteorder("="))
    return array.reshape(shape, order="F" if fortran else "C")


def read_recordings(root: str | os.PathLike, splits: Iterable[str] | None = None) -> Recordings:
    """Read and validate a dataset folder; `splits` limits which split files are loaded (default: all)."""
    root = Path(root)
    meta = read_meta(root)
    meshes: dict[str, Mesh] = {}
    for relative, named_by in _mesh_fields(meta):
        if relative in meshes:
            continue
        mesh_path = _inside(root, relative, named_by)
        if not mesh_path.is_file():
            raise RecordingsError(f"{mesh_path}: mesh file missing (meta.json {named_by})")
        try:
            meshes[relative] = read_obj(mesh_path)
        except MeshError as error:
            raise RecordingsError(f"{error} (meta.json {named_by})") from None
    check_convex_parts(meta, meshes, str(root / "meta.json"))
    wanted = list(meta["splits"]) if splits is None else list(splits)
    unknown = [name for name in wanted if name not in meta["splits"]]
    if unknown:
        raise RecordingsError(
            f"{root / 'meta.json'}: field 'splits' has no split {unknown[0]!r} (it has {sorted(meta['splits'])})"
        )
    loaded = {
        name: read_split(_inside(root, meta["splits"][name], f"splits.{name}"), len(meta["bodies"])) for name in wanted
    }
    recordings = Recordings(meta=meta, meshes=meshes, splits=loaded, root=root)
    for name, split in loaded.items():
        validate_hinges(recordings, split, str(root / meta["splits"][name]))
    return recordings


def _mesh_fields(meta: Mapping) -> list[tuple[str, str]]:
    """(OBJ path, the meta.json field naming it) for every mesh of a validated meta."""
    fields = [(body["mesh"], f"bodies[{k}].mesh") for k, body in enumerate(meta["bodies"])]
    if meta["version"] >= SCENE_VERSION:
        fields += [
            (piece, f"bodies[{k}].pieces[{i}]")
            for k, body in enumerate(meta["bodies"])
            for i, piece in enumerate(body.get("pieces", []))
        ]
        fields += [
            (entry["mesh"], f"static[{i}].mesh") for i, entry in enumerate(meta.get("static", [])) if "mesh" in entry
        ]
    return fields


def check_convex_parts(meta: Mapping, meshes: Mapping[str, Mesh], where: str) -> None:
    """Pieces and static meshes are convex (engines collide convex hulls), and a body's pieces stay within its mesh's
    bounding box (they are parts of it)."""
    if meta["version"] < SCENE_VERSION:
        return
    for relative, named_by in _mesh_fields(meta):
        if ".pieces[" in named_by or named_by.startswith("static["):
            problem = convexity_problem(meshes[relative])
            if problem:
                raise RecordingsError(
                    f"{where}: field '{named_by}' ({relative}) is {problem}; expected a convex solid (split a"
                    " non-convex shape into several convex pieces or static entries)"
                )
    for k, body in enumerate(meta["bodies"]):
        mesh = meshes[body["mesh"]]
        slack = 1e-6 * mesh.width
        for i, piece in enumerate(body.get("pieces", []) if meta["version"] >= SCENE_VERSION else []):
            vertices = meshes[piece].vertices
            if (vertices < mesh.vertices.min(axis=0) - slack).any() or (
                vertices > mesh.vertices.max(axis=0) + slack
            ).any():
                raise RecordingsError(
                    f"{where}: field 'bodies[{k}].pieces[{i}]' ({piece}) reaches outside its body's mesh "
                    f"{body['mesh']} (expected convex parts of that body, in its mesh frame)"
                )


def require_frames(recordings: Recordings, minimum: int, reason: str) -> None:
    """Every loaded trajectory has at least `minimum` frames, or one RecordingsError naming the split file."""
    for name, split in recordings.splits.items():
        short = np.flatnonzero(split.lengths < minimum)
        if len(short):
            where = (
                recordings.root / recordings.meta["splits"][name]
                if recordings.root is not None
                else f"{recordings.name} split {name!r}"
            )
            raise RecordingsError(
                f"{where}: field 'lengths': trajectory {short[0]} has {split.lengths[short[0]]} frames "
                f"({len(short)} of {split.n_trajectories} have fewer than {minimum}; expected at least {minimum}: "
                f"{reason})"
            )


def _inside(root: Path, relative: str, field: str) -> Path:
    """A meta.json path, refused if a link leads it out of the dataset folder (validate_meta caught '..' already)."""
    path = root / relative
    if not path.resolve().is_relative_to(root.resolve()):
        raise RecordingsError(
            f"{root / 'meta.json'}: field '{field}' is {relative!r}, which leads to {path.resolve()} "
            "(expected a file inside the dataset folder, not a link out of it)"
        )
    return path


# ---------------------------------------------------------------- writing


def _inside_path_checked(name: str) -> str:
    """An extra file's name, refused if it would leave the dataset folder."""
    if Path(name).is_absolute() or ".." in Path(name).parts:
        raise RecordingsError(f"extra file {name!r}: expected a path inside the dataset folder")
    return name


def write_recordings(
    root: str | os.PathLike, recordings: Recordings, extra_files: Mapping[str, str] | None = None
) -> Path:
    """Validate, then write the whole dataset into a staging folder and swap it into place; `extra_files` ({name:
    text}, e.g. a LICENSE) go into the same folder in the same swap."""
    root = Path(root)
    meta = copy.deepcopy(recordings.meta)
    validate_meta(meta, f"{root / 'meta.json'} (being written)")
    missing = [path for path in mesh_paths(meta) if path not in recordings.meshes]
    if missing:
        raise RecordingsError(f"{root / 'meta.json'} (being written): no mesh given for {missing[0]!r}")
    check_convex_parts(meta, recordings.meshes, f"{root / 'meta.json'} (being written)")
    for name, split in recordings.splits.items():
        if name not in meta["splits"]:
            raise RecordingsError(f"{root / 'meta.json'} (being written): split {name!r} not listed in 'splits'")
        validate_split(split, len(meta["bodies"]), f"{root / meta['splits'][name]} (being written)")
        validate_hinges(recordings, split, f"{root / meta['splits'][name]} (being written)")
    atomic.remove_stale_staging(root)  # left by a writer killed during its final write
    staging = atomic.staging_directory(root)
    try:
        for mesh_path in mesh_paths(meta):
            atomic.write_text(staging / mesh_path, obj_text(recordings.meshes[mesh_path]))
        for name, split in recordings.splits.items():
            atomic.write_npz(staging / meta["splits"][name], split.arrays())
        for name, text in (extra_files or {}).items():
            atomic.write_text(staging / _inside_path_checked(name), text)
        atomic.write_json(staging / "meta.json", meta)
        atomic.replace_directory(staging, root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return root
