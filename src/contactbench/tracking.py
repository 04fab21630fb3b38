"""Build the configured experiment logger (csv, tensorboard, mlflow, wandb) and log a run's config and scores."""
from __future__ import annotations

import logging
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from pytorch_lightning.loggers import Logger

log = logging.getLogger(__name__)


def make_logger(cfg: DictConfig, output_dir: Path) -> Logger | None:
    if cfg.get("logger") is None:
        return None
    target = cfg.logger._target_
    # Each back-end names its output folder differently; all of them live inside the run folder.
    location = {"save_dir": str(output_dir)}
    if target.endswith("MLFlowLogger"):
        location = {}  # one store for all runs (paths.log_dir/mlflow.db), so the dashboard compares them
        Path(cfg.paths.log_dir).mkdir(parents=True, exist_ok=True)
    logger = instantiate(cfg.logger, **location)
    flat = {key: value for key, value in _flatten(OmegaConf.to_container(cfg, resolve=True)).items() if not key.startswith("hydra")}
    logger.log_hyperparams(flat)
    return logger


def log_scores(logger: Logger | None, summary: dict, prefix: str, step: int = 0) -> None:
    if logger is None:
        return
    numbers = {f"{prefix}/{key}": float(value) for key, value in summary.items() if isinstance(value, (int, float)) and not isinstance(value, bool)}
    logger.log_metrics(numbers, step=step)


def close_logger(logger: Logger | None, status: str = "success") -> None:
    if logger is not None:
        logger.finalize(status)


def _flatten(tree, prefix: str = "") -> dict:
    flat = {}
    for key, value in (tree or {}).items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat
