"""A run rebuilt from its config and folder: the dataset as its models saw it, and the model train selected."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from hydra.utils import get_class, instantiate
from omegaconf import DictConfig

from contactbench import folders
from contactbench.models.base import ContactModel, ContactModule, require_contract
from contactbench.observation import Observation
from contactbench.recordings import Recordings, require_frames


@dataclass(frozen=True)
class Observed:
    """What the models see of a dataset (`dataset`), what they are scored against (`truth`) and how it was observed."""

    dataset: Recordings
    truth: Recordings
    observation: dict


def observed(cfg: DictConfig, recorded: Recordings) -> Observed:
    """The recordings observed as cfg.observation says (noise, frame stride); synthetic data are scored against the
    clean recording, real data against what was recorded."""
    observation = Observation.of(cfg.get("observation"))
    dataset = observation.observe(recorded)
    truth = dataset if recorded.real or observation.plain else observation.clean(recorded)
    scored_against = "observed recording" if recorded.real else "clean recording"
    context_frames = int(cfg.context_frames)
    require_frames(
        dataset,
        context_frames + 1,
        f"context_frames={context_frames} frames are given to the models, which predict the rest",
    )
    return Observed(dataset, truth, observation.describe(scored_against))


def load_module(cfg: DictConfig, dataset: Recordings, checkpoint: Path) -> ContactModule:
    """The Lightning module of cfg.model from a checkpoint (weights_only=True: never unpickles)."""
    module_class = get_class(cfg.model.module._target_)
    require_contract(module_class, ContactModule, "model.module")
    return module_class.load_from_checkpoint(str(checkpoint), dataset=dataset, weights_only=True, map_location="cpu")


def load_fitted(cfg: DictConfig, dataset: Recordings, train_dir: Path) -> ContactModel:
    """The model a train run selected, rebuilt from its run folder (checkpoints load with weights_only=True)."""
    record = Path(train_dir) / "fitted.json"
    if cfg.model.kind == "analytical":
        model = instantiate(cfg.model.contact_model)
        require_contract(model, ContactModel, "model.contact_model")
        if not record.is_file() and not model.learns:
            return model  # nothing to fit (MuJoCo's defaults): no train run needed
    if not record.is_file():
        raise FileNotFoundError(
            f"{record}: no fitted {cfg.model.name} model there; run train.py with the same model, dataset and budget "
            "first"
        )
    folders.check_signature(cfg, Path(train_dir), "score the model of")
    if cfg.model.kind == "analytical":
        model.load_fitted_state(folders.read_fitted_state(record))
        return model
    checkpoint = Path(train_dir) / "checkpoints" / json.loads(record.read_text())["checkpoint"]
    return load_module(cfg, dataset.for_models(), checkpoint).to_contact_model()
