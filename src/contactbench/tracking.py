"""Build the configured experiment logger (csv, tensorboard, mlflow, wandb) and log a run's config and scores."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from pytorch_lightning.loggers import CSVLogger, Logger, MLFlowLogger, WandbLogger
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
    if isinstance(logger, MLFlowLogger):
        # Without a kind, MLflow 3's experiment page opens under a "which type is this?" prompt that hides its tools.
        experiment = logger.experiment.get_experiment(logger.experiment_id)
        if EXPERIMENT_KIND not in experiment.tags:
            logger.experiment.set_experiment_tag(logger.experiment_id, EXPERIMENT_KIND, "custom_model_development")
    logger.log_hyperparams(curated_params(cfg))
    _set_tags(logger, run_tags(cfg))
    return logger


def curated_params(cfg: DictConfig) -> dict:
    """What a dashboard compares runs by: the model's own config and budget, the dataset, the observation and the
    protocol — not every other model's budget nor Hydra's bookkeeping."""
    tree = OmegaConf.to_container(cfg, resolve=True)
    model = dict(tree.get("model") or {})
    budget = tree.get("budget") or {}
    budgets = model.pop("budgets", None) or {}
    chosen = {
        "model": model,
        "dataset": {key: (tree.get("dataset") or {}).get(key) for key in ("name", "variant", "path")},
        "budget": {"name": budget.get("name"), **budgets.get(budget.get("name"), {})},
        "observation": tree.get("observation") or {},
        "seed": tree.get("seed"),
        "context_frames": tree.get("context_frames"),
    }
    flat = {key: value for key, value in flatten(chosen).items() if value is not None}
    # A model setting that only repeats its budget's value (model.module.evaluations: 16 beside budget.evaluations:
    # 16) is shown once, as the budget's.
    stated = {key.removeprefix("budget."): value for key, value in flat.items() if key.startswith("budget.")}
    return {
        key: value
        for key, value in flat.items()
        if not (key.startswith("model.") and stated.get(key.rsplit(".", 1)[-1], object()) == value)
    }


def run_tags(cfg: DictConfig) -> dict[str, str]:
    tags = {
        "task": str(cfg.get("task_name", "")),
        "model": str(cfg.model.name) if "model" in cfg else "",
        "dataset": str(cfg.dataset.name) if "dataset" in cfg else "",
        "variant": str(cfg.dataset.variant) if "dataset" in cfg else "",
        "budget": str(cfg.budget.name) if "budget" in cfg else "",
    }
    tags["run"] = "/".join(tags[key] for key in ("model", "dataset", "variant", "budget"))
    return tags


# Scores are metrics; the rest of a metrics.json summary (counts, timings, the observation) is bookkeeping: tags.
SCORES = (
    "pos_err",
    "rot_err_rad",
    "floor_penetration_m",
    "floor_penetration_true_m",
    "min_vertex_height_m",
    "interbody_penetration_m",
    "pairwise_collisions",
    "pairwise_collisions_true",
)
CURVES = ("pos_err", "rot_err_rad")  # per-frame curves logged with step = frame
EXPERIMENT_KIND = "mlflow.experimentKind"
BASE_NAME = "run_name"  # the run's name before show_scores put scores in front of it


def log_scores(logger: Logger | None, document: dict, prefix: str, step: int = 0) -> None:
    """A metrics.json's scores as metrics, its per-frame error curves with step = frame, the rest as tags."""
    if logger is None:
        return
    numbers = {
        f"{prefix}/{key}": float(document[key])
        for key in SCORES
        if isinstance(document.get(key), (int, float)) and not isinstance(document.get(key), bool)
    }
    logger.log_metrics(numbers, step=step)
    curves = document.get("per_frame") or {}
    for key in CURVES:
        for frame, value in enumerate(curves.get(key) or []):
            if value is not None:
                logger.log_metrics({f"{prefix}/{key}_by_frame": float(value)}, step=frame)
    _set_tags(
        logger,
        {
            f"{prefix}/{key}": str(value)
            for key, value in document.items()
            if key not in SCORES and key != "per_frame" and not isinstance(value, (dict, list))
        },
    )
    if isinstance(logger, MLFlowLogger):
        show_scores(logger)


def show_scores(logger: MLFlowLogger) -> None:
    """Scores where MLflow's runs table shows them without "Show more columns": its default columns hold no metric
    and a chosen column lives in one browser's storage, so the run's name starts with its test (else val) position /
    rotation error, and its description (mlflow.note.content) tabulates every split's scores."""
    client, run_id = logger.experiment, logger.run_id
    run = client.get_run(run_id)
    base = run.data.tags.get(BASE_NAME) or run.info.run_name
    metrics = run.data.metrics
    splits = [split for split in ("test", "val") if f"{split}/pos_err" in metrics] or sorted(
        {key.split("/", 1)[0] for key in metrics if key.endswith("/pos_err")}
    )
    if not splits:
        return
    shown = splits[0]
    name = f"{shown} {metrics[f'{shown}/pos_err']:.3f}/{metrics.get(f'{shown}/rot_err_rad', float('nan')):.3f} {base}"
    rows = [
        f"| {split} | {metrics[f'{split}/pos_err']:.4f} | {metrics.get(f'{split}/rot_err_rad', float('nan')):.4f} |"
        for split in splits
    ]
    note = "\n".join([f"**{base}**", "", "| split | position error (widths) | rotation error (rad) |", "|---|---|---|"])
    client.set_tag(run_id, BASE_NAME, base)
    client.set_tag(run_id, "mlflow.runName", name)
    client.set_tag(run_id, "mlflow.note.content", note + "\n" + "\n".join(rows))


def log_artifacts(logger: Logger | None, paths: list[Path]) -> None:
    """Files of the run folder (metrics.json, per-trajectory CSV, the fitted scene) into the tracking store, where it
    keeps artifacts (MLflow, W&B); the others have them in the run folder already."""
    if logger is None:
        return
    for path in paths:
        if not Path(path).is_file():
            continue
        if isinstance(logger, MLFlowLogger):
            logger.experiment.log_artifact(logger.run_id, str(path), artifact_path=Path(path).parent.name)
        elif isinstance(logger, WandbLogger):
            logger.experiment.save(str(path), base_path=str(Path(path).parent.parent), policy="now")


def _set_tags(logger: Logger, tags: dict[str, str]) -> None:
    if isinstance(logger, MLFlowLogger):
        for key, value in tags.items():
            logger.experiment.set_tag(logger.run_id, key, value[:5000])
    elif isinstance(logger, WandbLogger):
        logger.experiment.config.update({f"tags/{key}": value for key, value in tags.items()}, allow_val_change=True)


def prefixed(logger: Logger | None, prefix: str) -> Logger | None:
    """The run's logger as one setting of a choice on val sees it: metric names start with `prefix/`."""
    return None if logger is None else PrefixedLogger(logger, prefix)


class PrefixedLogger(Logger):
    """Metrics to another logger under `prefix/`; hyperparameters are the run's own, logged once by the run."""

    def __init__(self, logger: Logger, prefix: str):
        super().__init__()
        self.inner, self.prefix = logger, prefix

    @property
    def name(self) -> str | None:
        return self.inner.name

    @property
    def version(self) -> int | str | None:
        return self.inner.version

    @property
    def save_dir(self) -> str | None:
        return self.inner.save_dir

    def log_hyperparams(self, params, *args, **kwargs) -> None:
        pass

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        self.inner.log_metrics({f"{self.prefix}/{key}": value for key, value in metrics.items()}, step=step)

    def save(self) -> None:
        self.inner.save()


def log_choice(logger: Logger | None, setting: dict) -> None:
    """The setting a choice on val kept, as tags (MLflow, W&B) and as a line of the CSV metrics."""
    if logger is None:
        return
    _set_tags(logger, {f"chosen_on_val/{key}": str(value) for key, value in setting.items()})
    logger.log_metrics({f"chosen_on_val/{key}": float(value) for key, value in setting.items()}, step=0)


def close_logger(logger: Logger | None, status: str = "success") -> None:
    if logger is not None:
        logger.finalize(status)


def flatten(tree, prefix: str = "") -> dict:
    flat = {}
    for key, value in (tree or {}).items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, name + "."))
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


def drop_rows_from_step(output_dir: Path, step: int, prefix: str = "") -> None:
    """Remove csv/metrics.csv rows logged at or after `step` (with prefix: only rows of metrics named so, one
    setting's of a choice on val): a resumed run logs those steps again."""
    path = Path(output_dir) / "csv" / "metrics.csv"
    if not path.is_file():
        return
    with open(path, newline="") as file:
        reader = csv.DictReader(file)
        fields, rows = reader.fieldnames or [], list(reader)

    def logged_again(row: dict) -> bool:
        ours = not prefix or any(value not in ("", None) for key, value in row.items() if key.startswith(prefix))
        return ours and bool(row.get("step")) and int(float(row["step"])) >= step

    kept = [row for row in rows if not logged_again(row)]
    partial = path.with_name(f".{path.name}.partial")
    with open(partial, "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=fields)
        writer.writeheader()
        writer.writerows(kept)
    partial.replace(path)
