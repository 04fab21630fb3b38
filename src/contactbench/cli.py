"""Entry-point guard: user errors become one clear line and exit status 2; a failed multirun job lets the sweep go on."""
from __future__ import annotations

import functools
import logging
import os
import sys

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode

from contactbench.errors import ContactbenchError
from contactbench.folders import FolderRefused

log = logging.getLogger("contactbench")


def _in_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def guarded(main):
    @functools.wraps(main)
    def wrapper(cfg):
        try:
            return main(cfg)
        except (ContactbenchError, FileNotFoundError) as error:
            if os.environ.get("CONTACTBENCH_TRACEBACK"):
                raise
            message = f"error: {error}"
            if _in_multirun():
                # One bad job (e.g. the hybrid model on a multi-body variant) must not stop the sweep. A refused
                # folder is another run's: its log file is not written either.
                if isinstance(error, FolderRefused):
                    print(f"{message} (job skipped)", file=sys.stderr)
                else:
                    log.error("%s (job skipped)", message)
                return None
            print(message, file=sys.stderr)
            sys.exit(2)

    return wrapper
