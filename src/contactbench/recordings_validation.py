"""What the recordings format requires of meta.json, of a split's arrays and of the meshes a dataset names, each broken
rule one RecordingsError that names the file, the field and the place."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import PurePosixPath, PureWindowsPath

import numpy as np

from contactbench import kinematics
from contactbench.errors import RecordingsError
from contactbench.meshes import Mesh, convexity_problem
from contactbench.scene import FORMAT, SCENE_VERSION, VERSIONS, Scene, Split

MAX_COORDINATE = 1000.0  # m: static geometry farther out than this is a unit or sign mistake, not a scene
QUATERNION_TOLERANCE = 1e-3
# A hinge's two anchors may sit this far apart in a recorded frame (m), and its two axes this far out of line (rad):
# tracking noise, and an engine's joint drift, stay well inside; a mislabelled anchor or body does not.
HINGE_GAP_TOLERANCE = 5e-3
HINGE_AXIS_TOLERANCE = 0.05


def fail(where: str, message: str) -> RecordingsError:
    return RecordingsError(f"{where}: {message}")


def _require(meta: Mapping, key: str, types: type | tuple[type, ...], where: str, expected: str):
    if key not in meta:
        raise fail(where, f"field '{key}' is missing (expected {expected})")
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, types):
        raise fail(where, f"field '{key}' is {value!r} (expected {expected})")
    return value


def _vector(meta: Mapping, key: str, size: int, where: str) -> list[float]:
    value = meta[key]
    if (
        not isinstance(value, list)
        or len(value) != size
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in value)
    ):
        raise fail(where, f"field '{key}' is {value!r} (expected a list of {size} finite numbers)")
    return value


def _inside_path(value: str, field: str, where: str) -> None:
    """Paths in meta.json name files inside the dataset folder: never absolute, never up and out with '..'."""
    path = PurePosixPath(value)
    if not value or path.is_absolute() or PureWindowsPath(value).is_absolute() or ".." in path.parts or "\\" in value:
        raise fail(
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
        raise fail(where, "expected a JSON object")
    if meta.get("format") != FORMAT:
        raise fail(where, f"field 'format' is {meta.get('format')!r} (expected {FORMAT!r})")
    if meta.get("version") not in VERSIONS or isinstance(meta.get("version"), bool):
        raise fail(
            where,
            f"field 'version' is {meta.get('version')!r} (expected one of {list(VERSIONS)}, the versions this "
            "reader knows)",
        )
    _require(meta, "name", str, where, "a string")
    dt = _require(meta, "dt", (int, float), where, "seconds between frames, a positive number")
    if not (np.isfinite(dt) and dt > 0):
        raise fail(where, f"field 'dt' is {dt!r} (expected a positive number of seconds)")
    _require(meta, "gravity", list, where, "[gx, gy, gz] in m/s^2")
    _vector(meta, "gravity", 3, where)
    if "floor_z" in meta:
        floor_z = _require(meta, "floor_z", (int, float), where, "a finite number of metres")
        if not np.isfinite(floor_z):
            raise fail(where, f"field 'floor_z' is {floor_z!r} (expected a finite number of metres)")
    bodies = _require(meta, "bodies", list, where, "a non-empty list of bodies")
    if not bodies:
        raise fail(where, "field 'bodies' is empty (expected at least one body)")
    for k, body in enumerate(bodies):
        body_where = f"{where}: bodies[{k}]"
        if not isinstance(body, dict):
            raise fail(body_where, "expected an object with name, mesh, mass")
        _require(body, "name", str, body_where, "a string")
        _require(body, "mesh", str, body_where, "an OBJ path relative to the dataset folder")
        _inside_path(body["mesh"], "mesh", body_where)
        mass = _require(body, "mass", (int, float), body_where, "a positive mass in kg")
        if not (np.isfinite(mass) and mass > 0):
            raise fail(body_where, f"field 'mass' is {mass!r} (expected a positive mass in kg)")
        if "inertia_diagonal" in body:
            inertia = _vector(body, "inertia_diagonal", 3, body_where)
            if min(inertia) <= 0:
                raise fail(body_where, f"field 'inertia_diagonal' is {inertia!r} (expected three positive kg m^2)")
    splits = _require(meta, "splits", dict, where, "an object mapping split names to .npz files")
    if not splits or not all(isinstance(v, str) for v in splits.values()):
        raise fail(where, f"field 'splits' is {splits!r} (expected split name -> npz file path)")
    for name, value in splits.items():
        _inside_path(value, f"splits.{name}", where)
    if meta["version"] >= SCENE_VERSION:
        _validate_scene_fields(meta, where)


def _validate_scene_fields(meta: dict, where: str) -> None:
    """Version 2's pieces, static geometry and joints (their meshes are checked when read)."""
    names = [body["name"] for body in meta["bodies"]]
    if len(set(names)) != len(names):
        raise fail(where, f"field 'bodies' repeats a name in {names} (expected unique names: joints refer to them)")
    for k, body in enumerate(meta["bodies"]):
        if "pieces" in body:
            pieces = body["pieces"]
            if not isinstance(pieces, list) or not pieces or not all(isinstance(p, str) for p in pieces):
                raise fail(
                    f"{where}: bodies[{k}]", f"field 'pieces' is {pieces!r} (expected a non-empty list of OBJ paths)"
                )
            for i, piece in enumerate(pieces):
                _inside_path(piece, f"pieces[{i}]", f"{where}: bodies[{k}]")
    static = meta.get("static", [])
    if not isinstance(static, list):
        raise fail(where, f"field 'static' is {static!r} (expected a list of static meshes and height fields)")
    for i, entry in enumerate(static):
        entry_where = f"{where}: static[{i}]"
        if not isinstance(entry, dict):
            raise fail(entry_where, "expected an object with name, pose and mesh or heightfield")
        _require(entry, "name", str, entry_where, "a string")
        _require(entry, "pose", list, entry_where, "[x, y, z, qw, qx, qy, qz]")
        pose = _vector(entry, "pose", 7, entry_where)
        if max(abs(x) for x in pose[:3]) > MAX_COORDINATE:
            raise fail(entry_where, f"field 'pose' is {pose!r} (expected a position within {MAX_COORDINATE:g} m)")
        if abs(np.linalg.norm(pose[3:]) - 1.0) > QUATERNION_TOLERANCE:
            raise fail(entry_where, f"field 'pose' has quaternion {pose[3:]!r} (expected a unit quaternion)")
        if ("mesh" in entry) == ("heightfield" in entry):
            raise fail(entry_where, "expected exactly one of 'mesh' (an OBJ path) and 'heightfield'")
        if "mesh" in entry:
            _require(entry, "mesh", str, entry_where, "an OBJ path relative to the dataset folder")
            _inside_path(entry["mesh"], "mesh", entry_where)
        else:
            _validate_heightfield(entry["heightfield"], f"{entry_where}.heightfield")
    joints = meta.get("joints", [])
    if not isinstance(joints, list):
        raise fail(where, f"field 'joints' is {joints!r} (expected a list of hinges)")
    children: set[str] = set()
    for i, joint in enumerate(joints):
        joint_where = f"{where}: joints[{i}]"
        if not isinstance(joint, dict):
            raise fail(joint_where, "expected an object with name, type, parent, child, anchors and axes")
        _require(joint, "name", str, joint_where, "a string")
        if joint.get("type") != "hinge":
            raise fail(joint_where, f"field 'type' is {joint.get('type')!r} (expected 'hinge', the one joint known)")
        for key in ("parent", "child"):
            _require(joint, key, str, joint_where, "the name of a body in 'bodies'")
            if joint[key] not in names:
                raise fail(joint_where, f"field '{key}' is {joint[key]!r} (expected one of the bodies {names})")
        if joint["parent"] == joint["child"]:
            raise fail(joint_where, f"fields 'parent' and 'child' are both {joint['parent']!r} (expected two bodies)")
        if joint["child"] in children:
            raise fail(joint_where, f"field 'child': {joint['child']!r} is the child of two joints (expected a tree)")
        children.add(joint["child"])
        for key in ("parent_anchor", "child_anchor", "axis"):
            _require(joint, key, list, joint_where, "[x, y, z] in the body's mesh frame")
            _vector(joint, key, 3, joint_where)
        if np.linalg.norm(joint["axis"]) < 1e-9:
            raise fail(joint_where, f"field 'axis' is {joint['axis']!r} (expected a non-zero direction)")
        if "range" in joint:
            _require(joint, "range", list, joint_where, "[lowest, highest] angle in rad")
            low, high = _vector(joint, "range", 2, joint_where)
            if not low < high:
                raise fail(joint_where, f"field 'range' is {joint['range']!r} (expected lowest < highest, in rad)")
        for key, unit in (("damping", "N m s/rad"), ("friction", "N m")):
            if key in joint:
                value = _require(joint, key, (int, float), joint_where, f"{unit}, >= 0")
                if not (np.isfinite(value) and value >= 0):
                    raise fail(joint_where, f"field '{key}' is {value!r} (expected {unit}, >= 0)")
    parent_of = {joint["child"]: joint["parent"] for joint in joints}
    for name in parent_of:
        seen = {name}
        while name in parent_of:
            name = parent_of[name]
            if name in seen:
                raise fail(where, f"field 'joints' closes a loop through {name!r} (expected a tree of bodies)")
            seen.add(name)


def _validate_heightfield(field: object, where: str) -> None:
    if not isinstance(field, dict):
        raise fail(where, "expected an object with 'heights' (rows of numbers) and 'size' [x, y]")
    heights = field.get("heights")
    rows = heights if isinstance(heights, list) else []
    if (
        len(rows) < 2
        or not all(isinstance(row, list) and len(row) == len(rows[0]) >= 2 for row in rows)
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for row in rows for x in row)
    ):
        raise fail(where, "field 'heights' is not a grid (expected at least 2 rows of at least 2 numbers, equal rows)")
    grid = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(grid).all() or np.abs(grid).max() > MAX_COORDINATE:
        raise fail(where, f"field 'heights' (expected finite heights within {MAX_COORDINATE:g} m)")
    _require(field, "size", list, where, "[extent along x, extent along y] in m")
    size = _vector(field, "size", 2, where)
    if min(size) <= 0 or max(size) > MAX_COORDINATE:
        raise fail(where, f"field 'size' is {size!r} (expected two positive extents in m)")


def validate_split(split: Split, n_bodies: int, where: str) -> None:
    poses = split.poses
    if poses.ndim != 4 or poses.shape[2] != n_bodies or poses.shape[3] != 7:
        raise fail(
            where,
            f"field 'poses' has shape {poses.shape} (expected [N, T, K={n_bodies}, 7] for the {n_bodies} bodies in "
            "meta.json)",
        )
    n, horizon = poses.shape[:2]
    if n == 0 or horizon == 0:
        raise fail(where, f"field 'poses' has shape {poses.shape} (expected at least one trajectory and one frame)")
    lengths = split.lengths
    if not np.issubdtype(lengths.dtype, np.integer):
        raise fail(where, f"field 'lengths' has dtype {lengths.dtype} (expected int64)")
    if lengths.shape != (n,):
        raise fail(where, f"field 'lengths' has shape {lengths.shape} (expected [{n}], one per trajectory)")
    bad = np.flatnonzero((lengths < 1) | (lengths > horizon))
    if len(bad):
        raise fail(where, f"field 'lengths': trajectory {bad[0]} has length {lengths[bad[0]]} (expected 1..{horizon})")
    valid = split.valid_mask()
    _check_finite(poses, valid, "poses", where)
    with np.errstate(over="ignore", invalid="ignore"):  # a huge component is an off-norm quaternion, said below
        norms = np.linalg.norm(poses[..., 3:], axis=-1)
    off = valid[..., None] & (np.abs(norms - 1.0) > QUATERNION_TOLERANCE)
    if off.any():
        t_n, t_t, t_k = np.argwhere(off)[0]
        raise fail(
            where,
            f"field 'poses': trajectory {t_n}, frame {t_t}, body {t_k}: quaternion norm {norms[t_n, t_t, t_k]:.6f} "
            f"(expected a unit quaternion within {QUATERNION_TOLERANCE})",
        )
    if split.velocities is not None:
        velocities = split.velocities
        if velocities.shape != poses.shape[:3] + (6,):
            raise fail(
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
                raise fail(
                    where,
                    f"field 'poses': trajectory {n}, frame {t}: hinge joints[{j}] ({joint.name!r}) has "
                    f"{values[n, t]:.4g} {what} (expected at most {tolerance}; meta.json's parent_anchor, "
                    "child_anchor and axis say where the two bodies meet)",
                )


def _check_finite(array: np.ndarray, valid: np.ndarray, name: str, where: str) -> None:
    bad = valid[..., None, None] & ~np.isfinite(array)
    if bad.any():
        t_n, t_t, t_k = np.argwhere(bad)[0][:3]
        raise fail(
            where,
            f"field '{name}': trajectory {t_n}, frame {t_t}, body {t_k}: NaN or infinite value inside the valid frames",
        )


def mesh_fields(meta: Mapping) -> list[tuple[str, str]]:
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
    for relative, named_by in mesh_fields(meta):
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
