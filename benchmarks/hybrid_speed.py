"""Times the hybrid model on CPU: inverse dynamics and training (transitions/s), and rollout (predicted frames/s)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pytorch_lightning as pl
import torch

from contactbench.models.hybrid import HybridDataModule, HybridModule
from contactbench.models.hybrid.inverse import transitions_from_split
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings

DEFAULT_DATASET = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--dataset",
        type=Path,
        default=DEFAULT_DATASET,
        help="a single-body recordings folder with train and val splits",
    )
    parser.add_argument("--epochs", type=int, default=2, help="training epochs to time")
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument("--context-frames", type=int, default=6)
    parser.add_argument("--rollout-split", default="val", help="split whose trajectories are rolled out")
    args = parser.parse_args()

    dataset = read_recordings(
        args.dataset,
        splits=["train", "val"] if args.rollout_split in ("train", "val") else ["train", "val", args.rollout_split],
    )
    datamodule = HybridDataModule(dataset, context_frames=args.context_frames, batch_size=args.batch_size)
    started = time.perf_counter()
    all_transitions = transitions_from_split(dataset.split("train"), datamodule.scene, datamodule.settings)
    inverse_seconds = time.perf_counter() - started
    datamodule.setup("fit")
    n_train = len(datamodule.arrays["train"][0])

    module = HybridModule(dataset, context_frames=args.context_frames)
    trainer = pl.Trainer(
        max_epochs=args.epochs,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
    )
    started = time.perf_counter()
    trainer.fit(module, datamodule=datamodule)
    train_seconds = time.perf_counter() - started

    context = make_context(dataset.split(args.rollout_split), dataset.dt, args.context_frames)
    contact_model = module.to_contact_model()
    started = time.perf_counter()
    contact_model.rollout(dataset, context)
    rollout_seconds = time.perf_counter() - started
    predicted_frames = len(context.poses) * (context.horizon - context.n_context)

    print(
        f"dataset {dataset.name}: {len(all_transitions.frame)} train transitions, {n_train} in contact; torch "
        f"threads {torch.get_num_threads()}"
    )
    print(
        f"inverse dynamics: {len(all_transitions.frame) / inverse_seconds:,.0f} transitions/s ({inverse_seconds:.2f} s)"
    )
    print(
        f"training (batch {args.batch_size}, no validation): {args.epochs * n_train / train_seconds:,.0f} "
        f"transitions/s ({train_seconds:.2f} s for {args.epochs} epochs)"
    )
    print(
        f"rollout of {len(context.poses)} trajectories x {context.horizon - context.n_context} frames: "
        f"{predicted_frames / rollout_seconds:,.0f} frames/s ({rollout_seconds:.2f} s)"
    )


if __name__ == "__main__":
    main()
