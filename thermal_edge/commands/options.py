"""Checked command-line values: numbers within their range, name lists, output paths.

Each function here is an argparse ``type=``: it turns the text of an option into its value or
raises :class:`argparse.ArgumentTypeError`, which the parser prints as one line naming the option
(``thermal-edge replay: error: argument --threshold: must be a finite number >= 0, got 'nan'``)
before any work starts. Ranges are stated at the option, once, with its unit.
"""
from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

__all__ = ["MAX_EPOCH_S", "frame_period_s", "http_url", "integer", "ip_address", "kelvin", "names", "number", "output_dir",
           "output_file", "output_path", "positive_s"]

#: Latest time stamp taken as seconds since the epoch (the year 2286); a larger one is in ms or µs.
MAX_EPOCH_S = 1e10


def _range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool, unit: str) -> str:
    u = f" {unit}" if unit else ""
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}{u}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}{u}")
    return " and ".join(parts)


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
           unit: str = "") -> Callable[[str], float]:
    """A finite float within ``[lo, hi]`` (``lo_open``/``hi_open``: the bound itself excluded).

    Parameters
    ----------
    lo, hi : float, optional
        The bounds (None: unbounded on that side).
    lo_open, hi_open : bool
        Exclude the bound itself (``number(0, lo_open=True)``: positive).
    unit : str
        The option's unit, named in the message (``s``, ``K``).
    """
    want = _range_text(lo, hi, lo_open, hi_open, unit)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number{f' {want}' if want else ''}, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"must be a finite number{f' {want}' if want else ''}, got {text!r}")
        ok = True
        if lo is not None:
            ok = v > lo if lo_open else v >= lo
        if ok and hi is not None:
            ok = v < hi if hi_open else v <= hi
        if not ok:
            raise argparse.ArgumentTypeError(f"must be {want}, got {text!r}")
        return v

    parse.__name__ = "number"
    return parse


def integer(lo: int | None = None, hi: int | None = None, *, unit: str = "") -> Callable[[str], int]:
    """An integer within ``[lo, hi]`` (inclusive; None: unbounded on that side)."""
    want = _range_text(lo, hi, False, False, unit)

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer{f' {want}' if want else ''}, got {text!r}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be an integer {want}, got {text!r}")
        return v

    parse.__name__ = "integer"
    return parse


def ip_address(text: str) -> str:
    """An IP address to bind (not a host name: what it binds to must be plain)."""
    import ipaddress

    try:
        ipaddress.ip_address(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an IP address: {text!r} (127.0.0.1 for this host only)") from None
    return text


#: A positive duration or period, s.
positive_s = number(0, lo_open=True, unit="s")
#: A frame period of a simulated inverter, s (1 ms to 10 s: a CAN frame's cycle time).
frame_period_s = number(0.001, 10, unit="s")
#: A non-negative temperature difference, K.
kelvin = number(0, unit="K")


def http_url(text: str) -> str:
    """An ``http://`` or ``https://`` URL with a host."""
    from urllib.parse import urlsplit

    parts = urlsplit(text)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise argparse.ArgumentTypeError(f"expected an http:// URL such as http://127.0.0.1:9108/metrics, got {text!r}")
    return text


def names(text: str) -> str:
    """A comma-separated list of names with at least one name and no empty one (``a,b``); the
    text itself is returned (the commands split it)."""
    items = [x.strip() for x in text.split(",")]
    if not any(items):
        raise argparse.ArgumentTypeError(f"expected comma-separated names, got {text!r}")
    if not all(items):
        raise argparse.ArgumentTypeError(f"an empty name in {text!r} (comma-separated names, no empty one)")
    return text


def _parent_ok(p: Path) -> None:
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.exists():
        raise argparse.ArgumentTypeError(f"{p}: the directory {parent} does not exist")
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{p}: {parent} is not a directory")
    if not os.access(parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"{p}: the directory {parent} is not writable")


def output_file(text: str) -> str:
    """A file to write: its directory exists and is writable, and it is not itself a directory
    (an existing file is replaced)."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path")
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{p} is a directory; give a file name")
    _parent_ok(p)
    return text


def output_model_file(text: str) -> str:
    """A model file to write (:func:`output_file`), named ``.yaml`` or ``.yml``: what reads it back
    (``--model``, ``model.path``) takes YAML files."""
    out = output_file(text)
    if Path(out).suffix.lower() not in (".yaml", ".yml"):
        raise argparse.ArgumentTypeError(f"{out}: a model file ends in .yaml (or .yml)")
    return out


def output_path(text: str) -> str:
    """A file or a directory to write (the command says which it makes): its parent exists and
    is writable."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path")
    _parent_ok(Path(text))
    return text


def output_dir(text: str) -> str:
    """A directory to write into (made if missing, with its parents): not an existing file, and
    under nothing that is a file."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path")
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{p} is an existing file, not a directory")
    probe = p
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise argparse.ArgumentTypeError(f"{p}: {probe} is a file, not a directory")
    if probe.exists() and not os.access(probe, os.W_OK):
        raise argparse.ArgumentTypeError(f"{p}: {probe} is not writable")
    return text
