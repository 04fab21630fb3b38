"""The real elbow of DAIRLab/dair_pll (541 tracked tosses of two bars on a pin hinge) as a recordings dataset.

    python -m contactbench.contactnets_elbow SOURCE_DIR OUT_DIR

SOURCE_DIR holds the publisher's `0.pt` ... `540.pt` (dair_pll's `assets/contactnets_elbow/`; docs/RECORDINGS.md
names the published version), and its LICENSE lies two folders up (dair_pll's root), copied beside the dataset.
Each is a torch archive of one float64 tensor [121, 15]; it is read as raw bytes, never unpickled: its pickled
header must be exactly the one every published file carries (a plain tensor), or the file is refused. The output is
the same bytes on every run.

Conventions (docs/RECORDINGS.md, "Shipped datasets"):
* A row is Drake's state of the publisher's URDF: the base link's quaternion (w, x, y, z) and position, the hinge
  angle, the base's angular velocity in its own frame, its linear velocity in the world, the hinge rate.
* Bodies: the two 10 x 5 x 5 cm bars, each with its mesh frame at the bar's centre (the base link's frame; the child
  link's frame sits on the axle, 3.5 cm from its bar's centre). Masses as published (0.37 kg); inertias are the bars'
  uniform solids, not the URDF's, which carries a 10 cm cube's value on every axis.
* The hinge: axis y, on the base's mesh frame at (-0.035, 0.06, 0), on the child's at (-0.035, 0, 0). The child's
  pose and velocity follow from the base's by `kinematics.hinge_child`, so the anchors coincide to rounding.
* dt = 1/148 s, the ContactNets tracker's rate (the cube's), not the publisher's example's 0.0068 s: the recorded
  velocities are backward differences over the tracker's step, and free flight then falls as the cube's does
  (docs/RECORDINGS.md).
* Velocities are the publisher's: backward differences (x_t - x_{t-1} = dt v_t), the project's convention, so they
  lag the motion by half a frame; the angular velocity is turned into the world frame.
* Split 50 / 30 / 20 % into train, val and test by a permutation of seed `SPLIT_SEED`; `source_index` names each
  toss's file.
"""

from __future__ import annotations

import argparse
import sys
import zipfile
from pathlib import Path

import numpy as np

from contactbench import kinematics, rotations
from contactbench.errors import ContactbenchError
from contactbench.meshes import Mesh
from contactbench.recordings import write_recordings
from contactbench.scene import Recordings, Split

FRAMES, COLUMNS = 121, 15
N_TOSSES = 541
DT = 1.0 / 148.0
SPLIT_SEED = 0
FRACTIONS = {"train": 0.5, "val": 0.3, "test": 0.2}
BAR = (0.1, 0.05, 0.05)  # m
MASS = 0.37  # kg per bar
HINGE = {
    "name": "hinge",
    "type": "hinge",
    "parent": "link_1",
    "child": "link_2",
    "parent_anchor": [-0.035, 0.06, 0.0],
    "child_anchor": [-0.035, 0.0, 0.0],
    "axis": [0.0, 1.0, 0.0],
}
# The pickled header of every published file: one contiguous float64 tensor of shape (121, 15) in storage "0".
TENSOR_HEADER = (
    b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\nq\x00((X\x07\x00\x00\x00storageq\x01ctorch\nDoubleStorage\nq\x02"
    b"X\x01\x00\x00\x000q\x03X\x03\x00\x00\x00cpuq\x04M\x17\x07tq\x05QK\x00KyK\x0f\x86q\x06K\x0fK\x01\x86q\x07\x89"
    b"ccollections\nOrderedDict\nq\x08)Rq\ttq\nRq\x0b."
)
SOURCE = (
    "Real tosses of a two-link articulated 'elbow' (two 10 x 5 x 5 cm bars, 0.37 kg each, on a pin hinge) tracked at "
    "148 Hz, published in DAIRLab/dair_pll assets/contactnets_elbow (the upstream commit: docs/RECORDINGS.md) "
    "with its URDF "
    "assets/contactnets_elbow.urdf. BSD 3-Clause license, copyright 2022 Dynamic Autonomy and Intelligent Robotics "
    "Lab. Converted by contactbench.contactnets_elbow: bars' inertia as uniform solids (the URDF gives a cube's), "
    "dt 1/148 s, the publisher's velocities (backward differences) with the angular one turned into the world frame."
)


def read_tensor(path: Path) -> np.ndarray:
    """The [121, 15] float64 rows of one published file, without unpickling anything."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            header = [name for name in names if name.endswith("/data.pkl")]
            storage = [name for name in names if name.endswith("/data/0")]
            if len(header) != 1 or len(storage) != 1:
                raise ContactbenchError(
                    f"{path}: holds {names} (expected a torch archive with one data.pkl and one storage data/0)"
                )
            if archive.read(header[0]) != TENSOR_HEADER:
                raise ContactbenchError(
                    f"{path}: field 'data.pkl' is not the published header (expected one float64 tensor of shape "
                    f"[{FRAMES}, {COLUMNS}]; nothing else is read, and nothing is unpickled)"
                )
            raw = archive.read(storage[0])
    except (zipfile.BadZipFile, OSError) as error:
        raise ContactbenchError(f"{path}: not a readable torch archive ({error})") from None
    if len(raw) != FRAMES * COLUMNS * 8:
        raise ContactbenchError(
            f"{path}: field 'data/0' has {len(raw)} bytes (expected {FRAMES * COLUMNS * 8}: {FRAMES} x {COLUMNS} "
            "float64)"
        )
    rows = np.frombuffer(raw, dtype="<f8").reshape(FRAMES, COLUMNS).astype(np.float64)
    if not np.isfinite(rows).all():
        raise ContactbenchError(f"{path}: field 'data/0' holds NaN or infinite values (expected tracked states)")
    return rows


def bar_mesh() -> Mesh:
    """A BAR-sized box centred on its frame, faces counter-clockwise from outside."""
    half = np.array(BAR) / 2
    vertices = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * half
    faces = np.array(
        [[2, 0, 1], [2, 1, 3], [5, 4, 6], [5, 6, 7], [1, 0, 4], [1, 4, 5], [6, 2, 3], [6, 3, 7], [4, 0, 2], [4, 2, 6],
         [3, 1, 5], [3, 5, 7]],
        dtype=np.int64,
    )  # fmt: skip
    return Mesh(vertices, faces)


def meta() -> dict:
    bodies = [{"name": name, "mesh": "meshes/bar.obj", "mass": MASS} for name in ("link_1", "link_2")]
    return {
        "format": "rigid-contact-recordings",
        "version": 2,
        "name": "contactnets-elbow",
        "dt": DT,
        "gravity": [0.0, 0.0, -9.81],
        "bodies": bodies,
        "joints": [dict(HINGE)],
        "splits": {name: f"{name}.npz" for name in FRACTIONS},
        "source": SOURCE,
        "real": True,
    }


def states_to_recordings(rows: np.ndarray, joint) -> tuple[np.ndarray, np.ndarray]:
    """Drake state rows [..., 15] -> recordings poses [..., 2, 7] and world velocities [..., 2, 6]."""
    quaternion = rotations.normalize(rows[..., 0:4])
    base = np.concatenate([rows[..., 4:7], quaternion], axis=-1)
    spin = rotations.rotate(quaternion, rows[..., 8:11])  # the body frame's angular velocity, in the world
    base_velocity = np.concatenate([rows[..., 11:14], spin], axis=-1)
    child, child_velocity = kinematics.hinge_child(base, base_velocity, joint, rows[..., 7], rows[..., 14])
    return np.stack([base, child], axis=-2), np.stack([base_velocity, child_velocity], axis=-2)


def split_indices(n: int, seed: int = SPLIT_SEED) -> dict[str, np.ndarray]:
    """Train / val / test tosses: a seeded permutation cut at 50 and 80 % (each part sorted)."""
    order = np.random.default_rng(seed).permutation(n)
    train_end = int(round(FRACTIONS["train"] * n))
    val_end = train_end + int(round(FRACTIONS["val"] * n))
    parts = {"train": order[:train_end], "val": order[train_end:val_end], "test": order[val_end:]}
    return {name: np.sort(part) for name, part in parts.items()}


def convert(source: Path, out: Path, seed: int = SPLIT_SEED) -> Path:
    """Read SOURCE/0.pt ... SOURCE/540.pt and write the recordings dataset at OUT (atomically, same bytes each run)."""
    source = Path(source)
    if not source.is_dir():
        raise ContactbenchError(f"{source}: not a folder (expected dair_pll's assets/contactnets_elbow)")
    missing = [i for i in range(N_TOSSES) if not (source / f"{i}.pt").is_file()]
    if missing:
        raise ContactbenchError(
            f"{source}: {len(missing)} of the {N_TOSSES} files are missing, first {missing[0]}.pt (expected 0.pt to "
            f"{N_TOSSES - 1}.pt)"
        )
    rows = np.stack([read_tensor(source / f"{i}.pt") for i in range(N_TOSSES)])
    description = meta()
    scene = Recordings(meta=description, meshes={"meshes/bar.obj": bar_mesh()})
    poses, velocities = states_to_recordings(rows, scene.joints[0])
    splits = {
        name: Split(
            poses=poses[index],
            lengths=np.full(len(index), FRAMES, dtype=np.int64),
            velocities=velocities[index],
            extras={"source_index": index.astype(np.int64)},
        )
        for name, index in split_indices(N_TOSSES, seed).items()
    }
    licence = source.parent.parent / "LICENSE"
    if not licence.is_file():
        raise ContactbenchError(f"{licence}: missing (expected dair_pll's LICENSE two folders above the tosses)")
    recordings = Recordings(meta=description, meshes=scene.meshes, splits=splits)
    return write_recordings(out, recordings, extra_files={"LICENSE": licence.read_text()})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m contactbench.contactnets_elbow",
        description="Convert dair_pll's real elbow tosses (0.pt ... 540.pt) into a recordings dataset.",
    )
    parser.add_argument("source", type=Path, help="the folder of the published .pt files")
    parser.add_argument("out", type=Path, help="the dataset folder to write (replaced atomically)")
    parser.add_argument("--seed", type=int, default=SPLIT_SEED, help="the split's permutation seed")
    arguments = parser.parse_args(argv)
    try:
        print(convert(arguments.source, arguments.out, arguments.seed))
    except ContactbenchError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
