"""pybullet without its build banner: the C extension prints ``pybullet build time: ...`` when it loads.

``from torcsrl.utils.bullet import pybullet as p`` is how torcsrl imports pybullet: the first import runs with the
process's stdout and stderr file descriptors pointed at the null device (:func:`silenced_fds`), so no command of
torcsrl prints the banner; later imports find the loaded module.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator

__all__ = ["pybullet", "silenced_fds"]


@contextlib.contextmanager
def silenced_fds(fds: tuple[int, ...] = (1, 2)) -> Iterator[None]:
    """While inside, what C code writes to the file descriptors ``fds`` (stdout, stderr) goes to the null device;
    Python's own streams are flushed before and the C streams after, so nothing crosses the boundary either way.
    A descriptor that is not open is left alone."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved: list[tuple[int, int]] = []
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in fds:
            try:
                saved.append((fd, os.dup(fd)))
            except OSError:  # not open: nothing to silence
                continue
            os.dup2(null, fd)
        yield
    finally:
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)  # the C library's buffered stdout, into the null device
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)


with silenced_fds():
    import pybullet
