"""Mesh graph network contact model (paper §4.3): graphs, network, learned simulator, shape matching, Lightning."""
