"""The same command trains the same GNN, bit for bit, on CPUs with different vector instructions
(contactbench/models/gnn/cpu_kernels.py). Another CPU is emulated on this one: MKL_ENABLE_INSTRUCTIONS=AVX2 makes MKL
use the code it would use on an Intel CPU without AVX-512."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from contactbench.config import REPO_ROOT

KERNEL_VARIABLES = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "MKL_ENABLE_INSTRUCTIONS", "CONTACTBENCH_CPU_KERNELS")


def environment(**variables: str) -> dict:
    """This process's environment without any kernel setting, plus the given ones."""
    clean = {key: value for key, value in os.environ.items() if key not in KERNEL_VARIABLES}
    return {**clean, "WANDB_MODE": "disabled", **variables}


def python(code: str, **variables: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environment(**variables), timeout=120
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip()


def native_capability() -> str:
    """The ATen kernels torch picks on this CPU by itself."""
    code = "import torch; print(torch.backends.cpu.get_cpu_capability())"
    return python(code, CONTACTBENCH_CPU_KERNELS="native")


@pytest.mark.parametrize("first", ["contactbench.runs", "contactbench.models.gnn.module"])
def test_train_and_evaluate_processes_run_on_the_pinned_kernels(first):
    if native_capability() not in ("AVX2", "AVX512"):
        pytest.skip("this CPU has no AVX2: its kernels are ATen's scalar ones in any mode")
    code = f"import {first}, os, torch; print(torch.backends.cpu.get_cpu_capability(), os.environ.get('MKL_CBWR'))"
    assert python(code).split() == ["AVX2", "AVX2" if torch.backends.mkl.is_available() else "None"]
    assert python(code, CONTACTBENCH_CPU_KERNELS="compatible").split()[0] == "DEFAULT"
    assert python(code, CONTACTBENCH_CPU_KERNELS="native").split()[0] == native_capability()


def smoke_fit(run: Path, **variables: str) -> dict:
    """A budget=smoke GNN fit on the real cube: a digest of each setting's last weights and of the val scores."""
    command = [
        sys.executable,
        str(REPO_ROOT / "train.py"),
        "model=gnn",
        "dataset=contactnets_cube",
        "budget=smoke",
        f"hydra.run.dir={run}",
        f"paths.log_dir={run.parent}/outputs",
        f"paths.data_dir={run.parent}/data",
    ]
    done = subprocess.run(
        command, capture_output=True, text=True, timeout=300, env=environment(**variables), cwd=run.parent
    )
    assert done.returncode == 0, done.stderr[-3000:]
    digests = {}
    for checkpoint in sorted((run / "checkpoints").rglob("last.ckpt")):
        weights = torch.load(checkpoint, map_location="cpu", weights_only=True)["state_dict"]
        digest = hashlib.sha256()
        for key in sorted(weights):
            digest.update(key.encode() + weights[key].contiguous().numpy().tobytes())
        digests[checkpoint.parent.name] = digest.hexdigest()
    scores = json.loads((run / "val" / "metrics.json").read_text())
    digests["val"] = json.dumps({key: value for key, value in scores.items() if "seconds" not in key}, sort_keys=True)
    digests["cpu_kernels"] = json.loads((run / "fitted.json").read_text())["cpu_kernels"]
    return digests


@pytest.mark.slow
def test_a_gnn_fit_gives_the_same_bytes_on_a_cpu_without_avx512(tmp_path):
    if native_capability() != "AVX512" or not torch.backends.mkl.is_available():
        pytest.skip("emulating a CPU without AVX-512 needs one with it, and torch built with MKL")
    here = smoke_fit(tmp_path / "here")
    assert here["cpu_kernels"] == {"mode": "avx2", "aten": "AVX2", "mkl_cbwr": "AVX2"}
    unpinned = smoke_fit(tmp_path / "unpinned", CONTACTBENCH_CPU_KERNELS="native")
    if unpinned["noise_std=0.0002"] == here["noise_std=0.0002"]:
        pytest.skip("this CPU's own kernels give the pinned ones' bytes: nothing here tells CPUs apart")
    there = smoke_fit(tmp_path / "there", MKL_ENABLE_INSTRUCTIONS="AVX2")
    assert len(here) == 5  # three noise settings, the val scores, the kernels
    assert there == here


def test_a_cpu_without_avx2_keeps_torchs_own_kernels(monkeypatch):
    """ATen takes ATEN_CPU_CAPABILITY on trust: pinning AVX2 on a CPU without it would stop the process."""
    from contactbench.models.gnn import cpu_kernels

    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
    monkeypatch.delenv(cpu_kernels.MODE_VARIABLE, raising=False)
    monkeypatch.setattr(cpu_kernels, "cpu_has", lambda flag: False)
    cpu_kernels.pin()
    assert "ATEN_CPU_CAPABILITY" not in os.environ
    monkeypatch.setattr(cpu_kernels, "cpu_has", lambda flag: True)
    cpu_kernels.pin()
    assert os.environ["ATEN_CPU_CAPABILITY"] == "avx2"
