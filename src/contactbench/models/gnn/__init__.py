"""Mesh graph network contact model (paper §4.3): graphs, network, learned simulator, shape matching, Lightning."""

from contactbench.models.gnn import cpu_kernels

# Before any module of this package is imported: torch_geometric makes tensors when imported, and torch fixes its CPU
# kernels at the first one (cpu_kernels.py).
cpu_kernels.pin()
