"""Plain Python numbers in frozen dataclasses, whatever the caller passed (numpy scalars, lists, Hydra containers)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np


def freeze_numbers(instance, vectors: tuple[str, ...], skip: tuple[str, ...] = ()) -> None:
    """Set every field of a frozen dataclass to a float, or a tuple of floats for the fields in `vectors`; None stays.

    Plain values keep instances hashable (they key caches), comparable and JSON-ready.
    """
    for item in fields(instance):
        value = getattr(instance, item.name)
        if item.name in skip or value is None:
            continue
        value = tuple(float(x) for x in np.ravel(value)) if item.name in vectors else float(value)
        object.__setattr__(instance, item.name, value)


def set_floats(instance: object, *keys: str) -> None:
    """Set the named fields of a frozen dataclass to floats."""
    for key in keys:
        object.__setattr__(instance, key, float(getattr(instance, key)))


def set_vectors(instance: object, *keys: str) -> None:
    """Set the named fields of a frozen dataclass to tuples of 3 floats, refusing any other length."""
    for key in keys:
        vector = tuple(float(x) for x in getattr(instance, key))
        if len(vector) != 3:
            raise ValueError(f"{type(instance).__name__}.{key} needs 3 components, got {vector}")
        object.__setattr__(instance, key, vector)
