"""Build the configured experiment logger (csv, tensorboard, mlflow, wandb) and log a run's config and scores."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from pytorch_lightning.loggers import CSVLogger, Logger
from pytorch_lightning.loggers.csv_logs import ExperimentWriter

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
    flat = {
        key: value
        for key, value in _flatten(OmegaConf.to_container(cfg, resolve=True)).items()
        if not key.startswith("hydra")
    }
    logger.log_hyperparams(flat)
    return logger


def log_scores(logger: Logger | None, summary: dict, prefix: str, step: int = 0) -> None:
    if logger is None:
        return
    numbers = {
        f"{prefix}/{key}": float(value)
        for key, value in summary.items()
        if isinstance(value, (int, float)) and not isinstance(value, bool)
    }
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


class KeepingExperimentWriter(ExperimentWriter):
    """Lightning's CSV writer, except that a run resumed in its folder appends to metrics.csv instead of deleting it."""

    def _check_log_dir_exists(self) -> None:
        if self._fs.isfile(self.metrics_file_path):
            with self._fs.open(self.metrics_file_path, "r", newline="") as file:
                self.metrics_keys = sorted(csv.DictReader(file).fieldnames or [])


class ResumableCSVLogger(CSVLogger):
    """CSV files in the run folder that survive a resume (csv/metrics.csv keeps the rows logged before a kill)."""

    @property
    def experiment(self) -> ExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = KeepingExperimentWriter(log_dir=self.log_dir)
        return self._experiment


def drop_rows_from_step(output_dir: Path, step: int) -> None:
    """Remove csv/metrics.csv rows logged at or after `step`: a resumed run logs those steps again."""
    path = Path(output_dir) / "csv" / "metrics.csv"
    if not path.is_file():
        return
    with open(path, newline="") as file:
        reader = csv.DictReader(file)
        fields, rows = reader.fieldnames or [], list(reader)
    kept = [row for row in rows if not row.get("step") or int(float(row["step"])) < step]
    partial = path.with_name(f".{path.name}.partial")
    with open(partial, "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=fields)
        writer.writeheader()
        writer.writerows(kept)
    partial.replace(path)
