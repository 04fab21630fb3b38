"""The residual model's stage one without repeating a search: the parameters of a finished `model=sysid` run of the
same settings in the same run tree, when there is one.

A sweep (`make matrix`) fits `model=sysid` and `model=residual` on every variant with the same budget and seed, and
the residual's stage one is exactly that search. Every train run is listed in the run tree's index
(paths.log_dir/index/<signature key>.json, folders.index_run); a run listed there as `sysid` is taken when its
signature.json says it was made on the residual run's own data, context frames, seed and observation, with the
search settings the residual would pass SysIDModule (budget, restarts, eq. (1)'s exponent, threads, substeps, and
SysIDModule's defaults for the rest). Only JSON is read (the index entry, signature.json, fitted.json's `parameters`),
never a checkpoint. Anything else (no index, another setting, no fitted.json yet, a field that is not a finite
number) leaves the search to run as before, and `finished_sysid_run` says why in the one line the module logs.
"""

from __future__ import annotations

import inspect
import json
import math
from dataclasses import dataclass
from pathlib import Path

from contactbench.folders import INDEX, SIGNATURE
from contactbench.models.sysid.module import SysIDModule

SYSID_TARGET = f"{SysIDModule.__module__}.{SysIDModule.__qualname__}"
# The run's own signature fields that a reusable SysID run must share (the model's fields are compared apart).
SHARED = ("dataset", "context_frames", "seed", "observation")


@dataclass(frozen=True)
class Reused:
    """A finished SysID run's selected parameters, by SearchSpace name."""

    run: Path
    parameters: dict[str, float]


def sysid_module_fields(settings: dict, seed: int, nthread: int | None, substeps: int) -> dict:
    """model.module of a `model=sysid` run whose search is the residual's stage one: SysIDModule's defaults, then the
    settings the residual passes it (as `_identify` builds it)."""
    defaults = {
        name: parameter.default
        for name, parameter in inspect.signature(SysIDModule.__init__).parameters.items()
        if parameter.default is not inspect.Parameter.empty
    }
    fields = {"_target_": SYSID_TARGET, **defaults, **settings, "seed": seed, "nthread": nthread, "substeps": substeps}
    return json.loads(json.dumps(fields))  # as signature.json holds it (tuples as lists)


def _json(path: Path) -> object:
    """A JSON file's content; None where it is missing or not JSON."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def _same_settings(signature: object, own: dict, module_fields: dict) -> bool:
    if not isinstance(signature, dict) or not isinstance(signature.get("model"), dict):
        return False
    model = signature["model"]
    if model.get("name") != "sysid" or model.get("module") != module_fields:
        return False
    return all(signature.get(key) == own.get(key) for key in SHARED)


def _parameters(fitted: object, names: list[str]) -> dict[str, float] | None:
    """fitted.json's selected parameters, exactly the names stage one identifies, each a finite number; else None."""
    if not isinstance(fitted, dict) or fitted.get("model") != "sysid":
        return None
    parameters = fitted.get("parameters")
    if not isinstance(parameters, dict) or sorted(parameters) != sorted(names):
        return None
    values = [parameters[name] for name in names]
    if not all(isinstance(value, int | float) and not isinstance(value, bool) for value in values):
        return None
    if not all(math.isfinite(float(value)) for value in values):
        return None
    return {name: float(parameters[name]) for name in names}


def finished_sysid_run(
    runs_dir: Path | None, own_signature: object, module_fields: dict, names: list[str]
) -> Reused | str:
    """The finished `model=sysid` run of these settings in runs_dir's index, or why there is none (a sentence)."""
    if runs_dir is None:
        return "model.module.sysid_runs is null"
    if not isinstance(own_signature, dict):
        return "this run folder holds no signature.json to compare with"
    index = Path(runs_dir) / INDEX
    if not index.is_dir():
        return f"no run index in {runs_dir}"
    for entry_path in sorted(index.glob("*.json")):
        entry = _json(entry_path)
        if not isinstance(entry, dict) or entry.get("model") != "sysid" or not isinstance(entry.get("run"), str):
            continue
        run = Path(entry["run"])
        if not _same_settings(_json(run / SIGNATURE), own_signature, module_fields):
            continue
        parameters = _parameters(_json(run / "fitted.json"), names)
        if parameters is not None:
            return Reused(run, parameters)
    return f"no finished model=sysid run of the same data, seed and search settings in {index}"


def own_signature(run_dir: str | Path | None) -> object:
    """The signature.json train.py wrote in this run's folder before fitting (None outside a train run)."""
    return None if run_dir is None else _json(Path(run_dir) / SIGNATURE)
