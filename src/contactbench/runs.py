"""What generate.py, train.py and evaluate.py do, as functions of a composed Hydra config (tests call these)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from contactbench import atomic, checks, fitting, folders, provenance, restore, tracking, variants
from contactbench.config import interactive
from contactbench.errors import ContactbenchError
from contactbench.evaluation.scoring import score_model, write_score
from contactbench.models.base import ContactModel
from contactbench.recordings import Recordings, RecordingsError, read_meta, read_recordings, require_frames
from contactbench.sim.engines import made_by

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- data


def generated_folder(cfg: DictConfig) -> tuple[str, Path]:
    """The variant name and folder generate.py writes: dataset.path, or a folder beside it with +effects=[...]."""
    path, variant = Path(cfg.dataset.path), str(cfg.dataset.variant)
    effects = list(cfg.get("effects") or [])
    if effects:  # a dataset of its own beside the plain variant, same tosses
        variant = f"{variant},effects={'+'.join(effects)},strength={float(cfg.get('effect_strength', 1.0)):g}"
        path = path.with_name(variant)
    return variant, path


def crossed_variant(cfg: DictConfig) -> bool:
    """Whether this Hydra job's variant config belongs to another dataset than the job's (and say so): -m
    dataset=a,b 'variant=glob(*)' crosses every dataset with every variant, and a command-line dataset wins."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return False
    variant = HydraConfig.get().runtime.choices.get("variant")
    # A recorded dataset's variant is the dataset itself (variant=contactnets_cube)
    if variant in (None, "null", cfg.dataset.name) or variant.startswith(f"{cfg.dataset.name}_"):
        return False
    log.info("variant %s is not a %s variant: skipped", variant, cfg.dataset.name)
    return True


def generate(cfg: DictConfig) -> Path:
    """Generate the configured synthetic variant into dataset.path (kept if already there and valid)."""
    from contactbench.generation.generator import generate_dataset

    path = Path(cfg.dataset.path)
    if cfg.dataset.scene is None:
        log.info("%s is a recorded dataset (%s): nothing to generate", cfg.dataset.name, path)
        return path
    effects = list(cfg.get("effects") or [])
    strength = float(cfg.get("effect_strength", 1.0))
    variant, path = generated_folder(cfg)
    if (path / "meta.json").exists() and not cfg.get("overwrite", False):
        try:
            read_meta(path)
            log.info("%s exists; keeping it (overwrite=true regenerates)", path)
            return path
        except RecordingsError as error:
            log.warning("%s is not a valid dataset (%s); generating it again", path, error)
    spec = instantiate(cfg.dataset.scene)
    written = generate_dataset(
        spec,
        path,
        variant=variant,
        seed=cfg.generation.seed,
        workers=cfg.generation.workers,
        record_contacts=cfg.generation.record_contacts,
        split_sizes=dict(cfg.generation.split_sizes),
        effects=effects,
        effect_strength=strength,
        progress=interactive(),
    )
    log.info("wrote %s", written)
    return written


def load_dataset(cfg: DictConfig, splits: list[str]) -> restore.Observed:
    """Read the configured dataset's splits (generating a synthetic variant first if it is not there yet) and observe
    them as cfg.observation says (noise, frame stride); synthetic data are scored against the clean recording."""
    path = Path(cfg.dataset.path)
    if not (path / "meta.json").exists() and cfg.dataset.scene is not None:
        sizes = cfg.generation.split_sizes
        log.warning(
            "%s not found: generating it now (%s %s tosses, as generate.py would)%s",
            path,
            "/".join(str(size) for size in sizes.values()),
            "/".join(sizes),
            "; not a paper variant" if variants.paper_variant(cfg.dataset.name, cfg.dataset.variant) is False else "",
        )
        generate(cfg)
    return restore.observed(cfg, read_recordings(path, splits))


# ---------------------------------------------------------------- entry points


def _configure_torch(cfg: DictConfig) -> None:
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg.torch_threads))


def _score_and_write(
    cfg: DictConfig, model: ContactModel, observed: restore.Observed, split: str, out_dir: Path, logger
) -> dict:
    dataset = observed.dataset
    paper = variants.paper_variant(cfg.dataset.name, cfg.dataset.variant)
    score = score_model(
        model,
        dataset,
        split,
        cfg.context_frames,
        dataset_name=cfg.dataset.name,
        variant=cfg.dataset.variant,
        truth=observed.truth.split(split),
        annotations={
            **observed.observation,
            "seed": int(cfg.seed),
            "budget": str(cfg.budget.name),
            "task": str(cfg.task_name),  # which command made this row: the report keeps one of a repeated row
            "variant_values": dict(cfg.dataset.get("values") or {}),
            **({} if paper is None else {"paper_variant": paper}),
            # a model scoring data its own engine made (bullet_default on PyBullet's tosses): the report says so
            **({"own_engine": True} if made_by(model.engine, dataset.meta) else {}),
        },
    )
    for key, value in score.metrics.summary.items():
        # A reported metric that is not a number (null in metrics.json) would rank as nothing at all: an error instead.
        # (Model selection inside training scores with NaN on purpose: there a diverging candidate just loses.)
        if isinstance(value, (float, np.floating)) and not math.isfinite(float(value)):
            where = dataset.root / "meta.json" if dataset.root is not None else cfg.dataset.path
            raise ContactbenchError(
                f"{where}: {split} metric '{key}' of model {model.name!r} is {float(value)} "
                "(expected a finite number; check the data's dt and units, or the model's rollout)"
            )
    document = write_score(score, out_dir)
    tracking.log_scores(logger, document, split)
    tracking.log_artifacts(logger, [out_dir / "metrics.json", out_dir / "per_trajectory.csv"])
    return document


def write_scene(model: ContactModel, dataset: Recordings, output_dir: Path, logger) -> None:
    """An engine-based model's fitted scene in its engine's own format (scene.xml for MuJoCo's viewer, URDF for
    PyBullet, SDFormat for Drake, with their meshes), kept as artifacts."""
    files = model.scene_files(dataset)
    for relative, text in files.items():
        atomic.write_text(output_dir / relative, text)
    tracking.log_artifacts(logger, [output_dir / relative for relative in files])


def train(cfg: DictConfig, output_dir: Path) -> float:
    """Fit the model on train (selecting on val), score it on val, and on test when cfg.test. Returns val pos_err."""
    output_dir = Path(output_dir)
    stopwatch = provenance.Stopwatch()
    checks.check(cfg)
    folders.check(cfg, output_dir, "train")  # before anything is written: a refused run leaves the folder as it was
    pl.seed_everything(cfg.seed, workers=True)
    _configure_torch(cfg)
    splits = ["train", "val"] + (["test"] if cfg.test else [])
    observed = load_dataset(cfg, splits)
    dataset = observed.dataset
    folders.record(cfg, output_dir, "train")  # the dataset is readable and long enough: the run starts here
    logger, status = None, "failed"
    try:
        logger = tracking.make_logger(cfg, output_dir)
        model = fitting.fit(cfg, dataset.for_models(["train", "val"]), output_dir, logger)
        write_scene(model, dataset, output_dir, logger)
        results = {"val": _score_and_write(cfg, model, observed, "val", output_dir / "val", logger)}
        if cfg.test:
            results["test"] = _score_and_write(cfg, model, observed, "test", output_dir / "test", logger)
        stopwatch.write(output_dir)
        status = "success"
    except BaseException:
        folders.release(output_dir)  # a failure before anything resumable was written leaves the folder unclaimed
        raise
    finally:
        tracking.close_logger(logger, status)
    folders.index_run(cfg, output_dir)
    log.info("results: %s", ", ".join(str(output_dir / split / "metrics.json") for split in results))
    return results["val"]["pos_err"]


def _train_dir(cfg: DictConfig) -> Path:
    """cfg.train_dir if a model was fitted there; else the run the index holds for this signature (a sweep's, or one
    moved with hydra.run.dir), also when the default train_dir holds a run of other settings (a train_dir named on
    the command line is scored as named, or refused)."""
    train_dir = Path(cfg.train_dir)
    elsewhere = OmegaConf.is_interpolation(cfg, "train_dir") and not folders.same_signature(cfg, train_dir)
    if not (train_dir / "fitted.json").is_file() or elsewhere:
        found = folders.indexed_run(cfg)
        if found is not None:
            log.info("the model of these settings was fitted in %s (run index)", found)
            return found
    return train_dir


def evaluate(cfg: DictConfig, output_dir: Path) -> dict:
    """Score an analytical model, or the model a train run fitted, on cfg.split; writes metrics.json."""
    output_dir = Path(output_dir)
    stopwatch = provenance.Stopwatch()
    checks.check(cfg)
    train_dir = _train_dir(cfg)
    scored = folders.scored_signature(cfg, train_dir if (train_dir / "fitted.json").is_file() else None)
    folders.check(cfg, output_dir, "evaluate", scored)
    _configure_torch(cfg)
    observed = load_dataset(cfg, [cfg.split])
    folders.record(cfg, output_dir, "evaluate")
    logger = tracking.make_logger(cfg, output_dir)
    status = "failed"
    try:
        model = restore.load_fitted(cfg, observed.dataset, train_dir)
        document = _score_and_write(cfg, model, observed, cfg.split, output_dir, logger)
        folders.record_scores(output_dir, scored)
        stopwatch.write(output_dir)
        status = "success"
    finally:
        tracking.close_logger(logger, status)
    log.info("results: %s", output_dir / "metrics.json")
    return document


def diagnose(cfg: DictConfig, output_dir: Path) -> str:
    """Diagnose a recordings dataset (never reading meta.generator); writes diagnosis.json and report.md. Returns the
    verdict."""
    from contactbench.diagnosis.pipeline import Budget, Decision, run_diagnosis
    from contactbench.diagnosis.report import budget_sentence, console_paragraph, write_diagnosis

    checks.check(cfg)
    folders.check(cfg, Path(output_dir), "diagnose")
    path = Path(cfg.recordings)
    dataset = read_recordings(path, ["train", "val", "test"])
    require_frames(
        dataset,
        int(cfg.context_frames) + 1,
        f"context_frames={int(cfg.context_frames)} frames are given to the models, which predict the rest",
    )
    dataset = dataset.for_models(["train", "val", "test"])
    folders.record(cfg, Path(output_dir), "diagnose")
    document, arrays = run_diagnosis(
        dataset,
        Budget(**cfg.budget.diagnose),
        Decision(margin=float(cfg.margin)),
        seed=int(cfg.seed),
        context_frames=int(cfg.context_frames),
        engines=tuple(cfg.engines),
    )
    document["recordings"] = str(path)
    document["budget_name"] = str(cfg.budget.name)
    document["conclusive"] = document["budget_name"] != "smoke"  # smoke checks the pipeline runs, nothing more
    document["budget_note"] = budget_sentence(document)
    report = write_diagnosis(document, arrays, Path(output_dir))
    log.info("%s", console_paragraph(document, report))
    return document["verdict"]
