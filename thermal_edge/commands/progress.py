"""Progress bars with an ETA for the commands that can run longer than ~10 s (tqdm, on stderr).

The bar is drawn only when stderr is a terminal, so logs, pipes and tests see nothing of it.
"""
from __future__ import annotations

import sys
from typing import Any


class _Silent:
    """Stands in for a tqdm bar when none is drawn (it counts as tqdm does: ``n``)."""

    def __init__(self) -> None:
        self.n: float = 0

    def update(self, n: float = 1) -> None:
        self.n += n

    def set_postfix_str(self, s: str, refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> _Silent:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def bar(total: float | None, desc: str, unit: str = "it") -> Any:
    """A tqdm progress bar on stderr when it is a terminal, else a silent stand-in.

    Parameters
    ----------
    total : float or None
        Units of work expected (the ETA is computed against it); None when unknown.
    desc : str
        What is being done, shown left of the bar.
    unit : str
        Name of one unit of work ("generation", "s" of a simulated run …).
    """
    if not sys.stderr.isatty():
        return _Silent()
    from tqdm import tqdm  # a core dependency; imported only when a bar is drawn

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=True)


class StageBars:
    """Draws a benchmark's :class:`~thermal_edge.bench.common.Progress`: one bar per stage, the
    last one closed when the next stage starts (or on leaving the ``with`` block)."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self._stage: str | None = None
        self._bar: Any = None

    def __call__(self, stage: str, done: float, total: float, unit: str) -> None:
        if stage != self._stage:
            self.close()
            self._stage, self._bar = stage, bar(total, f"{self.prefix}: {stage}", unit)
        self._bar.update(done - self._bar.n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        self._stage, self._bar = None, None

    def __enter__(self) -> StageBars:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
