"""The one YAML reader of configuration and model files, and the one text decoder of every file
a command reads.

Encoding policy (models, drive cycles, ``edge.yaml`` and run CSVs alike): text is UTF-8, a
byte-order mark is dropped. A file that is not UTF-8 is refused with its name, the line and
column and the byte offset of the first byte that is not (and the byte); a binary file (a NUL
byte in its first 8 KiB) and UTF-16 text are refused as such. Run CSVs alone may name a fallback
(Windows-1252: spreadsheets on test benches export "°C" that way); configuration and model files
have none, since a wrong guess there would change a name or a unit silently.

YAML strict where PyYAML is lenient:

PyYAML's safe loader follows YAML 1.1: ``1e9`` (no dot) is a string, a repeated key silently
replaces the first, and a deeply nested document raises ``RecursionError``. A configuration is
data an engineer types by hand, so here ``1e9`` is the number it looks like (YAML 1.2), a repeated
key is an error naming its line, and a document nested beyond reason is an error too.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml

from .errors import ThermalEdgeError

__all__ = ["SNIFF_BYTES", "YamlProblem", "decode_text", "parse_yaml", "read_document", "read_text"]

#: Bytes looked at to tell a binary file from a text file.
SNIFF_BYTES = 8192


class YamlProblem(ThermalEdgeError, ValueError):
    """The text is not a document this reader accepts; the message says why and where (line)."""


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2 floats (``1e9``, ``-2E-3``) and no repeated keys."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.setdefault(key, key_node.start_mark.line + 1)
            except TypeError:  # an unhashable key: the base class says so
                break
            if first != key_node.start_mark.line + 1:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} appears twice (first on line {first})", key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


# YAML 1.2's float: a mantissa without a dot and an exponent is a number too
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)$"),
    list("-+0123456789"),
)


def parse_yaml(text: str) -> Any:
    """Parse one YAML document.

    Parameters
    ----------
    text : str
        The document.

    Returns
    -------
    object
        The parsed data (None for an empty document).

    Raises
    ------
    YamlProblem
        Invalid YAML, a key repeated in one mapping, or nesting too deep to read; the message
        gives the line where known.
    """
    try:
        return yaml.load(text, Loader=_StrictLoader)  # safe: a SafeLoader subclass
    except RecursionError:
        raise YamlProblem("nested too deeply to read") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise YamlProblem(f"not valid YAML{where}: {getattr(exc, 'problem', None) or exc}") from None


def decode_text(raw: bytes, name: str, error: type[Exception], fallback: tuple[str, ...] = ()) -> str:
    """Decode the bytes of a text file by the encoding policy (module docstring).

    Parameters
    ----------
    raw : bytes
        The file's contents.
    name : str
        The file, for messages.
    error : exception class
        Raised with one line naming ``name`` and the cause (a :class:`ThermalEdgeError` subclass).
    fallback : tuple of str
        Encodings tried after UTF-8 (run CSVs: Windows-1252).
    """
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise error(f"{name}: UTF-16 text (a spreadsheet's 'Unicode text' export); save it as UTF-8")
    if b"\x00" in raw[:SNIFF_BYTES]:
        raise error(f"{name}: a binary file, not text (byte {raw.index(0)} is NUL)")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        for enc in fallback:
            try:
                return raw.decode(enc)
            except UnicodeDecodeError:
                continue
        start = exc.start
        line = raw.count(b"\n", 0, start) + 1
        column = start - (raw.rfind(b"\n", 0, start) + 1) + 1
        raise error(f"{name}: line {line}, column {column} (byte {start}): not UTF-8 (byte 0x{raw[start]:02x}); "
                    "save the file as UTF-8") from None


def read_text(path: str | os.PathLike[str], error: type[Exception], fallback: tuple[str, ...] = (),
              name: str | None = None) -> str:
    """The text of a file by the encoding policy; a missing or unreadable file raises ``error``
    naming its path, a text problem naming ``name`` (default: the path; see :func:`decode_text`)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except IsADirectoryError:
        raise error(f"{p}: is a directory, not a file") from None
    except OSError as exc:
        raise error(f"{p}: cannot read: {exc.strerror or exc}") from None
    return decode_text(raw, name or str(p), error, fallback)


def read_document(path: str | os.PathLike[str], error: type[Exception]) -> Any:
    """A YAML file parsed (:func:`read_text`, then :func:`parse_yaml`); every problem raises
    ``error`` with one line naming the file (its path when it cannot be read, else its name, as
    the loaders name it with the key at fault)."""
    name = Path(path).name
    text = read_text(path, error, name=name)
    try:
        return parse_yaml(text)
    except YamlProblem as exc:
        raise error(f"{name}: {exc}") from None
