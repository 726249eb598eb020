"""The files that ship inside the package -- machine models (``resources/machines``), drive cycles
(``resources/cycles``) and the example service configuration (``resources/edge.yaml``) -- read
only through :mod:`importlib.resources`, so an installed wheel finds them wherever it lives.

Models and cycles are addressed by a file path or by the name of a packaged one (``pm10kw``,
``varied_drive``): a file that exists wins, else the name is looked up among the packaged files.
A leaf: every part may use it.
"""
from __future__ import annotations

import atexit
import functools
import os
from contextlib import ExitStack
from importlib import resources
from pathlib import Path

from .errors import UsageError

__all__ = ["CYCLES", "MACHINES", "config_path", "cycle_file", "example_config", "find", "model_file", "names"]

#: the kinds of packaged file addressable by name (folders of ``thermal_edge/resources``)
MACHINES = "machines"
CYCLES = "cycles"
_NOUN = {MACHINES: "model", CYCLES: "drive cycle"}
_SUFFIX = ".yaml"

# files handed out as paths stay valid until the interpreter exits (a zipped package is
# extracted to temporary files, removed at exit; an unpacked one is used in place)
_extracted = ExitStack()
atexit.register(_extracted.close)


def _root() -> resources.abc.Traversable:
    return resources.files(__package__).joinpath("resources")


@functools.cache
def config_path(*parts: str) -> Path:
    """A packaged file as a path on the file system, e.g. ``config_path("machines", "pm10kw.yaml")``.

    Raises
    ------
    FileNotFoundError
        No such packaged file (a bug of the caller: the names of packaged files are fixed).
    """
    item = _root().joinpath(*parts)
    if not item.is_file():
        raise FileNotFoundError(f"no packaged file {'/'.join(parts)}")
    return _extracted.enter_context(resources.as_file(item))


def example_config() -> str:
    """The text of the packaged example service configuration (``edge.yaml``)."""
    return _root().joinpath("edge.yaml").read_text(encoding="utf-8")


def names(kind: str) -> list[str]:
    """The names of the packaged files of one kind (:data:`MACHINES` or :data:`CYCLES`), sorted."""
    folder = _root().joinpath(kind)
    return sorted(f.name[: -len(_SUFFIX)] for f in folder.iterdir() if f.is_file() and f.name.endswith(_SUFFIX))


def find(kind: str, ref: str | os.PathLike[str], base: Path | None = None) -> Path | None:
    """The file ``ref`` names: an existing file (relative to ``base``, default the working
    directory), else the packaged file of that name (``pm10kw`` or ``pm10kw.yaml``); None if neither."""
    path = Path(ref).expanduser()
    if not path.is_absolute() and base is not None:
        path = base / path
    if path.exists():
        return path
    text = os.fspath(ref)
    if "/" in text or os.sep in text:
        return None
    name = text[: -len(_SUFFIX)] if text.endswith(_SUFFIX) else text
    return config_path(kind, name + _SUFFIX) if name in names(kind) else None


def _lookup(kind: str, ref: str, option: str) -> str:
    found = find(kind, ref)
    if found is None:
        raise UsageError(f"{option} {ref}: no such file, nor a packaged {_NOUN[kind]} of that name "
                         f"(packaged: {', '.join(names(kind))})")
    return str(found) if found != Path(ref).expanduser() else ref


def model_file(ref: str, option: str = "--model") -> str:
    """``ref`` as given when it is a file, else the path of the packaged model of that name.

    Raises
    ------
    UsageError
        Neither a file nor a packaged model; the message names ``option`` and the packaged models.
    """
    return _lookup(MACHINES, ref, option)


def cycle_file(ref: str, option: str = "--cycle") -> str:
    """``ref`` as given when it is a file, else the path of the packaged drive cycle of that name.

    Raises
    ------
    UsageError
        Neither a file nor a packaged cycle; the message names ``option`` and the packaged cycles.
    """
    return _lookup(CYCLES, ref, option)
