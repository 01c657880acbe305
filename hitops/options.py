"""Typed option objects made from a tool's schema (hitops/schemas/<tool>.yml).

``options_class("calibrate")`` is a frozen dataclass with one field per schema
input, typed from its ``dtype`` and defaulting to the schema's default, so the
options that travel through a tool's pipeline are the schema's and nothing
else (the CLI and the cab come from the same schema: hitops/schema.py).
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import Any, Optional

from .errors import InputError
from .schema import load_schema

_TYPES = {"str": str, "int": int, "float": float, "bool": bool, "MS": str, "File": str,
          "Directory": str, "URI": str}


@lru_cache(maxsize=None)
def options_class(tool: str) -> type:
    """Frozen dataclass ``<Tool>Options`` of ``tool``'s inputs (required ones first)."""
    inputs = load_schema(tool)["inputs"]
    required, optional = [], []
    for name, spec in inputs.items():
        kind = _TYPES.get(spec.get("dtype", "str"), Any)
        if spec.get("required"):
            required.append((name, kind))
        else:
            default = spec.get("default")
            optional.append((name, kind if default is not None else Optional[kind],
                             dataclasses.field(default=default)))
    name = "".join(part.capitalize() for part in tool.split("_")) + "Options"
    return dataclasses.make_dataclass(name, required + optional, frozen=True)


def make_options(tool: str, values: dict):
    """Options of ``tool`` from a mapping holding (at least) every schema input.

    The schema's ``choices`` are checked here, so the Python API refuses what
    the command line's parser refuses, with the same one line.
    """
    cls = options_class(tool)
    inputs = load_schema(tool)["inputs"]
    for name, spec in inputs.items():
        choices = spec.get("choices")
        value = values.get(name)
        if choices and value is not None and value not in choices:
            flag = "--" + name.replace("_", "-")
            raise InputError(f"{flag}: unknown value {value!r}; choose one of "
                             f"{', '.join(map(str, choices))}")
    return cls(**{f.name: values[f.name] for f in dataclasses.fields(cls)})
