"""Sim-to-real diagnosis: locate where a fitted simulator misses the recordings, name the missing physics, prove it."""
