"""Scoring models on a split and reporting the results."""
