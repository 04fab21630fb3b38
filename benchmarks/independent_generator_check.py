"""Generate one case of the independent generator and its null twin; print size, timing and physics checks.

    python benchmarks/independent_generator_check.py [--shape cube] [--effect quadratic_drag] [--strength 0.5]

Checks on the null twin (the nominal world, which the recordings describe): in free flight the centre of mass
accelerates at exactly the recorded gravity (no hidden damping), and the mechanical energy never rises from one frame
to the next (restitution below 1, no external force). Also: the same case written twice gives the same bytes.
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import independent_generator as generator  # noqa: E402  (a sibling script, not a package)

from contactbench import rotations  # noqa: E402
from contactbench.recordings import read_recordings  # noqa: E402

FREE_FLIGHT_CLEARANCE = 0.005  # m: a frame whose lowest vertex is this far above the floor is in free flight
ENERGY_TOLERANCE = 1e-3  # J: Bullet's penetration recovery may push a resting body out by a few microjoules


def free_flight_acceleration_error(recordings, split: str) -> float:
    """Largest deviation (m/s^2) of a free-flight frame's central-difference acceleration from the recorded gravity."""
    poses = recordings.split(split).poses[:, :, 0]
    vertices = recordings.body_mesh(0).vertices
    lowest = poses[..., 2] + rotations.rotate(poses[..., None, 3:], vertices)[..., 2].min(axis=-1)
    airborne = lowest > recordings.floor_z + FREE_FLIGHT_CLEARANCE
    flying = airborne[:, :-2] & airborne[:, 1:-1] & airborne[:, 2:]
    acceleration = (poses[:, 2:, :3] - 2 * poses[:, 1:-1, :3] + poses[:, :-2, :3]) / recordings.dt**2
    return float(np.abs(acceleration[flying] - recordings.gravity).max())


def largest_energy_rise(recordings, split: str) -> float:
    """Largest frame-to-frame rise of kinetic plus potential energy (J) over all tosses of a split."""
    data = recordings.split(split)
    poses, velocities = data.poses[:, :, 0], data.velocities[:, :, 0]
    body = recordings.bodies[0]
    mass, inertia = body.mass, np.diag(body.inertia_diagonal)  # the generator always records the diagonal
    # Rotational energy in the body frame: rotate the world angular velocity back by the orientation.
    body_angular = rotations.rotate(rotations.conjugate(poses[..., 3:]), velocities[..., 3:])
    energy = (
        0.5 * mass * (velocities[..., :3] ** 2).sum(-1)
        + 0.5 * np.einsum("...i,ij,...j->...", body_angular, inertia, body_angular)
        - mass * recordings.gravity[2] * (poses[..., 2] - recordings.floor_z)
    )
    return float(np.diff(energy, axis=1).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", default="cube")
    parser.add_argument("--effect", default="quadratic_drag", choices=sorted(generator.EFFECTS))
    parser.add_argument("--strength", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    case = {"shape": args.shape, "effect": args.effect, "strength": args.strength, "seed": args.seed}
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(scratch)
        for with_effect in (True, False):
            start = time.perf_counter()
            generator.generate_case(case, out, with_effect=with_effect)
            label = "case" if with_effect else "null twin"
            print(f"{label}: generated 550 tosses in {time.perf_counter() - start:.1f} s")
        print(f"size: {generator.size(case, out):.3f} widths")
        null = read_recordings(generator.generate_case(case, out, with_effect=False))
        error = free_flight_acceleration_error(null, "train")
        print(f"null twin: free-flight acceleration within {error:.2e} m/s^2 of the recorded gravity")
        rise = largest_energy_rise(null, "train")
        print(f"null twin: largest frame-to-frame energy rise {rise:.2e} J (tolerance {ENERGY_TOLERANCE:g})")
        again = out / "again"
        first = generator.generate_case(case, out)
        second = generator.generate_case(case, again)
        same = all(filecmp.cmp(first / name, second / name, shallow=False) for name in ("train.npz", "meta.json"))
        print(f"deterministic (same bytes when written twice): {same}")
        if error > 1e-6 or rise > ENERGY_TOLERANCE or not same:
            raise SystemExit("a check failed")


if __name__ == "__main__":
    main()
