"""The one YAML reader of configuration and model files: strict where PyYAML is lenient.

PyYAML's safe loader follows YAML 1.1: ``1e9`` (no dot) is a string, a repeated key silently
replaces the first, and a deeply nested document raises ``RecursionError``. A configuration is
data an engineer types by hand, so here ``1e9`` is the number it looks like (YAML 1.2), a repeated
key is an error naming its line, and a document nested beyond reason is an error too.
"""
from __future__ import annotations

import re
from typing import Any

import yaml

from .errors import ThermalEdgeError

__all__ = ["YamlProblem", "parse_yaml"]


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
