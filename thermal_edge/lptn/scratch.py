"""Scratch arrays reused across the stretches of one run.

A fresh array of a few megabytes costs the kernel's zeroing of its pages at first touch, and on a
busy host that can cost as much as the matrix product that fills it (a product of 460 Mflop into
a fresh 47 MB array measured about twice as long as into one already touched). The stretches of
a run need the same large temporaries one after the other (the sensitivities' forcing, the
modal filter's blocks): :class:`Scratch` hands out views of buffers that grow to the largest
request and are reused, instead of a new array per stretch.
"""
from __future__ import annotations

import math

import numpy as np


class Scratch:
    """Named float64 buffers, each grown to the largest request and reused.

    A view handed out stays valid until the next request of the same name.
    """

    def __init__(self) -> None:
        self._buf: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], zero: bool = False) -> np.ndarray:
        """A C-contiguous array of ``shape`` backed by buffer ``name`` (uninitialised unless ``zero``).

        >>> s = Scratch()
        >>> a = s.get("x", (2, 3), zero=True)
        >>> b = s.get("x", (3, 2))
        >>> a.shape, b.shape, np.shares_memory(a, b), float(a.sum())
        ((2, 3), (3, 2), True, 0.0)
        """
        size = math.prod(shape)
        buf = self._buf.get(name)
        if buf is None or buf.size < size:
            buf = self._buf[name] = np.empty(size)
        out = buf[:size].reshape(shape)
        if zero:
            out.fill(0.0)
        return out
