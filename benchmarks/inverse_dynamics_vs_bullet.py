"""Inverse contact dynamics (hybrid model) against PyBullet's own recorded contact forces, on freshly generated
tosses."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.models.hybrid.inverse import compare_with_bullet_contacts
from contactbench.recordings import read_recordings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tosses", type=int, default=40)
    parser.add_argument("--frictions", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    args = parser.parse_args()
    print(f"{'variant':<28} {'quantity':<16} {'relative error':>15} {'correlation':>12} {'recorded RMS':>13}")
    with tempfile.TemporaryDirectory() as folder:
        for friction in args.frictions:
            spec = SceneSpec(
                name="frictioncubes", friction=friction, restitution=0.0, faces=6, bodies=1, center_bias_speed=0.0
            )
            path = generate_dataset(
                spec,
                Path(folder) / f"mu{friction:g}",
                split_sizes={"train": args.tosses},
                record_contacts=True,
                progress=False,
            )
            report = compare_with_bullet_contacts(read_recordings(path))
            for quantity, numbers in report.items():
                print(
                    f"{'frictioncubes mu=' + format(friction, 'g'):<28} {quantity:<16} "
                    f"{numbers['relative_error']:>15.2e} {numbers['correlation']:>12.6f} "
                    f"{numbers['reference_rms']:>13.4f}"
                )


if __name__ == "__main__":
    main()
