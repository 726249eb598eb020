"""One BLAS thread for the estimation's linear algebra, however the process was started.

The matrices of a thermal network are small (tens of nodes): a BLAS call on them is over before
a second thread has done its share, so extra threads only synchronise, and on a host whose cores
are busy they wait for a core at every call. ``bench paper`` with ``OPENBLAS_NUM_THREADS=2``, two
side by side on a busy 2-core host, ran every fit about ten times slower than with one thread each
(the analytic SQP 40 s instead of 4 s, the numerical 240 s instead of 19 s). The command line sets
``OPENBLAS_NUM_THREADS=1`` before numpy loads; a program that imports the package itself gets the
same through :func:`one_blas_thread` around each fit.
"""
from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from typing import Any

__all__ = ["blas_threads", "one_blas_thread"]

_blas: Any = None  # threadpoolctl's controller of the BLAS libraries loaded, made at first use


def _controller() -> Any:
    global _blas
    if _blas is None:
        from threadpoolctl import ThreadpoolController

        _blas = ThreadpoolController().select(user_api="blas")
    return _blas


def blas_threads() -> int:
    """The largest thread count among the BLAS libraries loaded (numpy's, scipy's), 1 if none."""
    return max((int(lib.num_threads) for lib in _controller().lib_controllers), default=1)


def one_blas_thread() -> AbstractContextManager[Any]:
    """A context in which the loaded BLAS libraries use one thread; the previous counts come back
    on exit. Changes nothing where every library already uses one (the command line): the count is
    process-wide, and the service's tick calls BLAS from another thread meanwhile."""
    if blas_threads() <= 1:
        return nullcontext()
    limiter: AbstractContextManager[Any] = _controller().limit(limits=1)
    return limiter
