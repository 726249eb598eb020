"""The examples in the package's docstrings are run, so that they cannot drift from the code."""
from __future__ import annotations

import doctest
import importlib
import importlib.util
import pkgutil

import pytest

import thermal_edge


def _modules_with_examples() -> list[str]:
    names = []
    for info in pkgutil.walk_packages(thermal_edge.__path__, "thermal_edge."):
        spec = importlib.util.find_spec(info.name)
        if spec and spec.origin and spec.origin.endswith(".py"):
            with open(spec.origin, encoding="utf-8") as fh:
                if ">>> " in fh.read():
                    names.append(info.name)
    return names


MODULES = _modules_with_examples()


def test_the_package_has_examples() -> None:
    assert "thermal_edge.lptn.elements" in MODULES and "thermal_edge.lptn.simulate" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name: str) -> None:
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    if result.attempted == 0:
        pytest.skip(f"every example in {name} is marked +SKIP (it needs a running bus or service)")
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples in {name} failed (see the output above)"
