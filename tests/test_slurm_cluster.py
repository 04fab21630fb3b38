"""cluster/slurm_check.py's own single-node Slurm: up, one job through sbatch and srun, down (make slurm-check sends
the matrix through it)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys

import pytest

from contactbench.config import REPO_ROOT

INSTALLED = all(shutil.which(name) for name in ("munged", "slurmctld", "slurmd", "sbatch", "srun"))


def load_slurm_check():
    spec = importlib.util.spec_from_file_location("slurm_check", REPO_ROOT / "cluster" / "slurm_check.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(not INSTALLED, reason="Slurm not installed (apt-get install slurm-wlm munge)")
@pytest.mark.skipif(INSTALLED and os.geteuid() != 0, reason="a Slurm of its own needs root")
def test_single_node_slurm_runs_a_job_and_stops(tmp_path):
    slurm_check = load_slurm_check()
    cluster = slurm_check.Cluster()
    try:
        cluster.start()
        output = tmp_path / "job.out"
        cluster.slurm("sbatch", "--wait", f"--output={output}", "--wrap", "srun echo ran on $SLURMD_NODENAME")
        assert output.read_text().strip() == f"ran on {cluster.host}"
    finally:
        stopped = cluster.stop()
        shutil.rmtree(cluster.state, ignore_errors=True)
    assert stopped == ["slurmd", "slurmctld", "munged"]
    assert not any(slurm_check.alive(pid) for pid in cluster.pids.values())
