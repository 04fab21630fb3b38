"""pybullet, imported without the line its C extension writes at import (`pybullet build time: ...`): once in every
process that imports it, every generation or engine worker included, so into every log and piped output. Import it
from here: `from contactbench.sim.quiet_pybullet import pybullet`."""

from __future__ import annotations

import ctypes
import os
import sys


def _import_quietly():
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}  # it writes to stderr; stdout too, in case another build does
    try:
        with open(os.devnull, "wb") as devnull:
            for fd in saved:
                os.dup2(devnull.fileno(), fd)
            import pybullet

            _flush_c_stdio()  # C buffers stdout when fd 1 is not a terminal: flushed while it is devnull
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
    return pybullet


def _flush_c_stdio() -> None:
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library to reach this way (Windows): nothing buffered to drop
        pass


pybullet = _import_quietly()
