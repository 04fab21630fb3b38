"""One set of CPU kernels on every machine, so that the same command trains the same network bit for bit.

torch picks its CPU kernels by the instruction set of the machine it runs on: ATen's own vectorised kernels
(ATEN_CPU_CAPABILITY: default, avx2, avx512) and MKL's matrix products (its code branch; MKL_CBWR pins one). A
product or an activation computed with 16-wide AVX-512 instead of 8-wide AVX2 rounds differently in its last bits,
and thousands of training steps amplify that into a different network: the same seed gave the GNN different scores
on two machines. Threads are pinned apart from this (conf/protocol: torch_threads).

Both libraries read their variable once, at their first operation in the process, not at `import torch`: `pin` sets
them and makes torch choose at once. Importing contactbench.models.gnn calls it (before torch_geometric, which makes
tensors when imported), and so does contactbench.fitting, which train.py and evaluate.py import before any tensor is
made. The mode comes from CONTACTBENCH_CPU_KERNELS:
- avx2 (the default): ATen's AVX2 kernels and MKL's AVX2 branch. The same bytes on every Intel CPU with AVX2 or
  AVX-512; MKL documents its branches for Intel CPUs only (elsewhere it falls back to its own choice), and a CPU
  without AVX2 gets other kernels.
- compatible: ATen's scalar kernels and MKL's SSE2 branch: the same bytes on every x86-64 CPU, AMD's included,
  at about twice the training time (benchmarks/gnn_speed.py --compare-kernels measures it).
- native: torch's own choice for this machine (the fastest; machine-dependent results).
ATEN_CPU_CAPABILITY or MKL_CBWR set in the environment win over the mode. CPUs other than x86-64 (ARM) have neither
set of kernels: their results differ from x86's in any mode.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

MODE_VARIABLE = "CONTACTBENCH_CPU_KERNELS"
MODES = {  # mode: (ATEN_CPU_CAPABILITY, MKL_CBWR)
    "avx2": ("avx2", "AVX2"),
    "compatible": ("default", "COMPATIBLE"),
    "native": (None, None),
}
DEFAULT_MODE = "avx2"


def mode() -> str:
    """The mode CONTACTBENCH_CPU_KERNELS names (avx2 when unset)."""
    name = os.environ.get(MODE_VARIABLE, DEFAULT_MODE).strip().lower() or DEFAULT_MODE
    if name not in MODES:
        raise ValueError(f"{MODE_VARIABLE}={name!r}: expected one of {', '.join(MODES)}")
    return name


def pin() -> dict:
    """Set the mode's kernel variables where the environment has not, and make torch choose its kernels now.
    Returns what is in effect (`in_effect`)."""
    capability, branch = MODES[mode()]
    if capability == "avx2" and not cpu_has("avx2"):
        # ATen takes its variable on trust: AVX2 kernels on a CPU without AVX2 would stop the process
        log.warning("this CPU has no AVX2: torch keeps its own kernels (%s=avx2 pins AVX2 CPUs only)", MODE_VARIABLE)
        capability = None
    if capability is not None:
        os.environ.setdefault("ATEN_CPU_CAPABILITY", capability)
    if branch is not None:
        os.environ.setdefault("MKL_CBWR", branch)
    import torch  # after the variables: nothing above may make a tensor

    chosen = torch.backends.cpu.get_cpu_capability()  # ATen reads its variable here, once per process
    if torch.backends.mkl.is_available():
        torch.ones(2, 2) @ torch.ones(2, 2)  # MKL reads MKL_CBWR at its first product
    wanted = os.environ.get("ATEN_CPU_CAPABILITY")
    if wanted and chosen.lower() != wanted.lower() and chosen != "DEFAULT":
        log.warning(
            "torch's CPU kernels are %s, not ATEN_CPU_CAPABILITY=%s: chosen before this process pinned them, or "
            "this CPU lacks them",
            chosen,
            wanted,
        )
    return in_effect()


def cpu_has(flag: str) -> bool:
    """Whether the CPU reports an instruction-set flag (Linux's /proc/cpuinfo); True where it cannot be read."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            for line in info:
                if line.startswith("flags"):
                    return flag in line.split(":", 1)[1].split()
    except OSError:
        return True
    return True


def in_effect() -> dict:
    """The kernels this process uses, for a run's record: the mode, ATen's capability, MKL's requested branch."""
    import torch

    return {
        "mode": mode(),
        "aten": torch.backends.cpu.get_cpu_capability(),
        "mkl_cbwr": os.environ.get("MKL_CBWR") if torch.backends.mkl.is_available() else None,
    }
