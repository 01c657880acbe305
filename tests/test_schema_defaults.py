"""One schema per tool holds for the Python functions too.

For every tool with a schema (hitops/schemas/<tool>.yml), the Python function
``hitops.<tool>.<tool>`` and the command's entry ``hitops.<tool>.app.run``
take exactly the schema's inputs, with the schema's defaults; a required input
has no Python default.  The CLI and the cab are built from the same schema
(tests/test_schema.py), so all four agree.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect

import pytest

from hitops.options import section_classes, section_names
from hitops.schema import load_schema, tools

NO_DEFAULT = inspect.Parameter.empty


def python_function(tool):
    return getattr(importlib.import_module(f"hitops.{tool}"), tool)


def test_every_tool_is_checked():
    # the four tools the issue names at least; a new schema is picked up by itself
    assert {"simulate", "calibrate", "diagnose", "compare"} <= set(tools())


def _check_defaults(where: str, params, inputs, names) -> None:
    for name in names:
        spec = inputs[name]
        default = params[name].default
        if spec.get("required"):
            assert default is NO_DEFAULT, f"{where}.{name} is required in the schema but " \
                                          f"has the Python default {default!r}"
        else:
            assert default is not NO_DEFAULT, f"{where}.{name}: no Python default"
            assert default == spec.get("default"), (
                f"{where}.{name}: Python default {default!r}, schema default "
                f"{spec.get('default')!r}")
            assert type(default) is type(spec.get("default")), f"{where}.{name}: types differ"


@pytest.mark.parametrize("tool", tools())
@pytest.mark.parametrize("entry", ["function", "app"])
def test_python_signature_matches_schema(tool, entry):
    func = (python_function(tool) if entry == "function"
            else importlib.import_module(f"hitops.{tool}.app").run)
    params = inspect.signature(func).parameters
    inputs = load_schema(tool)["inputs"]
    assert not any(p.kind is p.VAR_KEYWORD for p in params.values()), \
        f"{func.__module__}.{func.__name__} hides its parameters behind **kwargs"
    sections = section_names(tool)
    if entry == "function" and sections:
        # a tool with sections: the inputs of no section, then one parameter per section
        # whose default is the section with the schema's defaults (checked below)
        top = [n for n in inputs if not any(n in names for names in sections.values())]
        assert list(params) == top + list(sections), f"{tool}: {list(params)}"
        _check_defaults(tool, params, inputs, top)
        for section in sections:
            assert params[section].default == section_classes(tool)[section](), section
        return
    assert set(params) == set(inputs), (
        f"{tool}: only in Python {sorted(set(params) - set(inputs))}, "
        f"only in the schema {sorted(set(inputs) - set(params))}")
    _check_defaults(tool, params, inputs, inputs)


@pytest.mark.parametrize("tool", [t for t in tools() if section_names(t)])
def test_every_input_is_in_one_section(tool):
    inputs = load_schema(tool)["inputs"]
    sections = section_names(tool)
    placed = [n for names in sections.values() for n in names]
    assert len(placed) == len(set(placed)), f"{tool}: an input in two sections"
    assert set(placed) <= set(inputs), f"{tool}: unknown {sorted(set(placed) - set(inputs))}"
    required = {n for n, spec in inputs.items() if spec.get("required")}
    # the positional inputs (the sets) are the only ones outside every section
    assert set(inputs) - set(placed) == required
    for section, cls in section_classes(tool).items():
        assert [f.name for f in dataclasses.fields(cls)] == list(sections[section])
        for f in dataclasses.fields(cls):
            assert f.default == inputs[f.name].get("default"), f"{section}.{f.name}"


def test_sections_refuse_a_bad_choice_as_the_command_line_does():
    from hitops.calibrate import TrackingOptions, calibrate_flat
    from hitops.errors import InputError
    with pytest.raises(InputError, match=r"^--tracker: unknown value 'kalman'; choose one of "
                                         r"count, smooth, antenna$"):
        TrackingOptions(tracker="kalman")
    # the flat entry refuses it too, before any set is opened (the paths do not exist)
    with pytest.raises(InputError, match=r"--jump-action: unknown value 'ignore'"):
        calibrate_flat("/nonexistent/a.ms", "/nonexistent/b.ms", jump_action="ignore")


def test_flat_and_sections_round_trip():
    from hitops.calibrate.inputs import CalibrateOptions
    flat = {"ref_ms": "a.ms", "target_ms": "b.ms", "tracker": "antenna", "method": "pwc,cfpt",
            "chunk_rows": 100, "offset_model": "point"}
    opts = CalibrateOptions.from_flat(flat)
    assert (opts.tracking.tracker, opts.output.method, opts.run.chunk_rows,
            opts.n0.offset_model) == ("antenna", "pwc,cfpt", 100, "point")
    back = opts.flat()
    assert {k: back[k] for k in flat} == flat
    assert len(back) == len(load_schema("calibrate")["inputs"])
