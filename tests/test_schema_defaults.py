"""One schema per tool holds for the Python functions too.

For every tool with a schema (hitops/schemas/<tool>.yml), the Python function
``hitops.<tool>.<tool>`` and the command's entry ``hitops.<tool>.app.run``
take exactly the schema's inputs, with the schema's defaults; a required input
has no Python default.  The CLI and the cab are built from the same schema
(tests/test_schema.py), so all four agree.
"""

from __future__ import annotations

import importlib
import inspect

import pytest

from hitops.schema import load_schema, tools

NO_DEFAULT = inspect.Parameter.empty


def python_function(tool):
    return getattr(importlib.import_module(f"hitops.{tool}"), tool)


def test_every_tool_is_checked():
    # the four tools the issue names at least; a new schema is picked up by itself
    assert {"simulate", "calibrate", "diagnose", "compare"} <= set(tools())


@pytest.mark.parametrize("tool", tools())
@pytest.mark.parametrize("entry", ["function", "app"])
def test_python_signature_matches_schema(tool, entry):
    func = (python_function(tool) if entry == "function"
            else importlib.import_module(f"hitops.{tool}.app").run)
    params = inspect.signature(func).parameters
    inputs = load_schema(tool)["inputs"]
    assert not any(p.kind is p.VAR_KEYWORD for p in params.values()), \
        f"{func.__module__}.{func.__name__} hides its parameters behind **kwargs"
    assert set(params) == set(inputs), (
        f"{tool}: only in Python {sorted(set(params) - set(inputs))}, "
        f"only in the schema {sorted(set(inputs) - set(params))}")
    for name, spec in inputs.items():
        default = params[name].default
        if spec.get("required"):
            assert default is NO_DEFAULT, f"{tool}.{name} is required in the schema but " \
                                          f"has the Python default {default!r}"
        else:
            assert default is not NO_DEFAULT, f"{tool}.{name}: no Python default"
            assert default == spec.get("default"), (
                f"{tool}.{name}: Python default {default!r}, schema default "
                f"{spec.get('default')!r}")
            assert type(default) is type(spec.get("default")), f"{tool}.{name}: types differ"

