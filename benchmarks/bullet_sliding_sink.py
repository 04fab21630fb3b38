"""How deep the generator's PyBullet cubes sink into the floor while they slide: the recordings, and a flat cube slid.

PyBullet at Table 2a's settings (one engine step of 6.76 ms per frame, its default contact ERP) leaves a sliding body
below the floor by an amount that grows with its speed and vanishes at rest. This prints it twice:

- in the recordings (`--data`, default data/frictioncubes): over the frames where the cube lies flat (tilt under 2°)
  and nearly still vertically, its lowest vertex's depth below the floor, binned by horizontal speed;
- in the generator's own world (`generation.bullet.BulletScene`, the same code that made the data): a cube set flat
  on the floor and pushed at each speed, the steady depth after 100 frames, with PyBullet's contact ERP as shipped
  and raised to 0.8, which shows where the depth comes from.

    python benchmarks/bullet_sliding_sink.py [--data data/frictioncubes] [--speeds 0 0.1 0.3 0.6 1.0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pybullet

from contactbench import metrics, rotations
from contactbench.generation.bullet import BulletScene
from contactbench.generation.scenes import SceneSpec
from contactbench.generation.solids import solid
from contactbench.ground import Ground
from contactbench.recordings import read_recordings
from contactbench.sim.bullet_world import BulletSettings

SPEED_BINS = (0.0, 0.02, 0.1, 0.3, 0.6, 1.0, 2.0)  # m/s, horizontal
FLAT_TILT = np.radians(2.0)
STILL_VERTICALLY = 0.05  # m/s


def recorded_sink(root: Path) -> list[tuple[str, float, float, int]]:
    """(bin, mean depth mm, 95th percentile mm, frames) per horizontal-speed bin of the train split's flat frames."""
    recordings = read_recordings(root, splits=["train"])
    split = recordings.split("train")
    lowest = metrics.ground_clearance(split.poses, [recordings.body_mesh(0)], Ground.of(recordings))[..., 0]
    matrices = rotations.to_matrix(split.poses[:, :, 0, 3:])
    speed = np.linalg.norm(split.velocities[:, :, 0, :2], axis=-1)
    vertical = np.abs(split.velocities[:, :, 0, 2])
    up = matrices[..., :, 2]  # every body axis's z component: a flat cube has one at ±1
    flat = np.arccos(np.clip(np.abs(up).max(-1), 0.0, 1.0)) < FLAT_TILT
    frames = np.arange(split.n_frames)[None, :] < split.lengths[:, None]
    rows = []
    for low, high in zip(SPEED_BINS[:-1], SPEED_BINS[1:]):
        chosen = frames & flat & (vertical < STILL_VERTICALLY) & (speed >= low) & (speed < high)
        depth = np.maximum(0.0, -lowest[chosen]) * 1e3
        if depth.size:
            rows.append((f"{low:g}–{high:g}", float(depth.mean()), float(np.percentile(depth, 95)), int(depth.size)))
    return rows


def slid_sink(speed: float, friction: float, contact_erp: float | None) -> float:
    """Mean depth (mm) below the floor of a flat cube pushed at `speed` (m/s) over frames 100–139 of a toss."""
    settings = BulletSettings()
    mesh = solid(6, settings.width)
    spec = SceneSpec(name="frictioncubes", friction=friction, restitution=0.0)
    with BulletScene(mesh, spec, settings) as scene:
        if contact_erp is not None:
            pybullet.setPhysicsEngineParameter(contactERP=contact_erp, erp=contact_erp, physicsClientId=scene.client)
        rest_height = -mesh.vertices[:, 2].min()
        pose = np.array([[0.0, 0.0, rest_height, 1.0, 0.0, 0.0, 0.0]])
        velocity = np.array([[speed, 0.0, 0.0, 0.0, 0.0, 0.0]])
        poses, _ = scene.simulate(pose, velocity, settings.frames)
    return float(np.maximum(0.0, rest_height - poses[100:, 0, 2]).mean() * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/frictioncubes"))
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.0, 0.1, 0.3, 0.6, 1.0])
    arguments = parser.parse_args()

    variants = sorted(path for path in arguments.data.glob("*") if (path / "meta.json").is_file())
    for variant in variants:
        print(f"{variant}: flat frames' depth below the floor by horizontal speed (train split)")
        for speeds, mean, high, count in recorded_sink(variant):
            print(f"  {speeds:>9} m/s: mean {mean:5.2f} mm, 95th percentile {high:5.2f} mm ({count} frames)")
    if not variants:
        print(f"{arguments.data}: no recordings there (python generate.py dataset=frictioncubes 'variant=glob(*)')")

    print("a flat cube pushed along the generator's frictionless floor (it keeps its speed), depth in frames 100–139:")
    for speed in arguments.speeds:
        shipped = slid_sink(speed, 0.0, None)
        stiffer = slid_sink(speed, 0.0, 0.8)
        print(f"  {speed:4.2f} m/s: {shipped:5.2f} mm at PyBullet's default contact ERP, {stiffer:5.2f} mm at ERP 0.8")


if __name__ == "__main__":
    main()
