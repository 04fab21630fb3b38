"""What every pool of worker processes in contactbench shares (the generator's, the Python-stepped engines' lanes)."""

from __future__ import annotations

import multiprocessing


def standard_start_method() -> None:
    """Put the caller's default start method back to the standard library's when a launcher set one of its own.

    A worker started by spawn or a fork server re-applies its parent's default start method before anything else;
    inside a joblib worker (Hydra's local launcher, `make matrix`) that default is loky's, which a fresh worker has
    never imported, so every worker died before its first task and each of its tosses was NaN."""
    if multiprocessing.get_start_method(allow_none=True) not in (None, *multiprocessing.get_all_start_methods()):
        multiprocessing.set_start_method(None, force=True)
