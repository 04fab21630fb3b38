"""A real dataset's tosses (the cube's 550 or the elbow's 541) dealt into train / val / test again with another seed,
written as a user's own folder.

A model's settings tuned where its data come from do not reach a user's recordings; this folder is how that is
checked: the same tosses, another split, loaded as `dataset=recordings` (no named dataset's config applies).
    python benchmarks/real_cube_resplit.py --seed 1          # -> data/contactnets_cube_resplit_seed1
    python train.py model=gnn dataset=recordings recordings=data/contactnets_cube_resplit_seed1 test=true
    python benchmarks/real_cube_resplit.py --seed 1 --source assets/contactnets_elbow    # the elbow, likewise
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from contactbench.config import REPO_ROOT
from contactbench.recordings import read_recordings, write_recordings
from contactbench.scene import Split

SPLITS = ("train", "val", "test")


def pooled(splits: list[Split]) -> Split:
    """The splits' tosses in one Split, padded with NaN frames to the longest."""
    frames = max(split.n_frames for split in splits)

    def padded(array: np.ndarray) -> np.ndarray:
        shape = (array.shape[0], frames - array.shape[1], *array.shape[2:])
        return np.concatenate([array, np.full(shape, np.nan)], axis=1)

    velocities = None
    if all(split.velocities is not None for split in splits):
        velocities = np.concatenate([padded(split.velocities) for split in splits])
    return Split(
        np.concatenate([padded(split.poses) for split in splits]),
        np.concatenate([split.lengths for split in splits]),
        velocities,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--source", default=str(REPO_ROOT / "assets" / "contactnets_cube"))
    parser.add_argument("--out", default=None, help="default: data/<source folder>_resplit_seed<seed>")
    args = parser.parse_args()
    source = read_recordings(args.source, SPLITS)
    sizes = [source.split(name).n_trajectories for name in SPLITS]
    everything = pooled([source.split(name) for name in SPLITS])
    order = np.random.default_rng(args.seed).permutation(everything.n_trajectories)
    bounds = np.cumsum([0, *sizes])
    splits = {name: everything.select(order[bounds[i] : bounds[i + 1]]) for i, name in enumerate(SPLITS)}
    meta = dict(source.meta, name=f"{source.meta['name']}-resplit-seed{args.seed}")
    out = args.out or str(REPO_ROOT / "data" / f"{Path(args.source).name}_resplit_seed{args.seed}")
    written = write_recordings(out, dataclasses.replace(source, meta=meta, splits=splits))
    counts = ", ".join(f"{name} {size}" for name, size in zip(SPLITS, sizes))
    print(f"wrote {written}: {counts} tosses, seed {args.seed}")


if __name__ == "__main__":
    main()
