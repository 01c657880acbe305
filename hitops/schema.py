"""One parameter schema per tool, feeding both the click CLI and the Stimela cab.

Each tool (simulate, calibrate, diagnose, ...) has ``hitops/schemas/<tool>.yml``
written in Stimela's cab-parameter dialect (``info``, ``dtype``, ``default``,
``required``, ``choices``, ``policies.positional``).  From that one file:

* :func:`clickify` builds the ``hitops <tool>`` click command (same names,
  defaults, help texts), without importing Stimela so the CLI starts fast;
* :func:`cab_definition` builds the ``hitops.<tool>`` cab that
  ``python -m hitops.cabgen`` writes to ``cabs/hitops.yml``.

Consistency between the two is therefore by construction; the tests also load
the generated cab through Stimela itself and compare it with the CLI.
"""

from __future__ import annotations

import importlib.resources
from functools import lru_cache
from typing import Any, Callable, Dict

import click
import yaml

from .errors import InputError



def tools() -> list:
    """Names of the tools that have a schema (``hitops/schemas/<tool>.yml``)."""
    folder = importlib.resources.files("hitops.schemas")
    return sorted(p.name[:-4] for p in folder.iterdir() if p.name.endswith(".yml"))


_CLICK_TYPES = {
    "str": click.STRING,
    "int": click.INT,
    "float": click.FLOAT,
    "MS": click.Path(),
    "File": click.Path(),
    "Directory": click.Path(),
    # a file or a directory (a Measurement Set, or a UVFITS / FITS-IDI file)
    "URI": click.Path(),
}


@lru_cache(maxsize=None)
def load_schema(tool: str) -> Dict[str, Any]:
    """The parsed schema of one tool (``inputs``, ``outputs``, ``info``)."""
    if tool not in tools():
        raise InputError(f"unknown tool '{tool}'; known tools: {', '.join(tools())}")
    text = importlib.resources.files("hitops.schemas").joinpath(f"{tool}.yml").read_text()
    # libyaml's parser when PyYAML has it: same result, ~10x faster (CLI start-up)
    schema = yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    schema.setdefault("inputs", {})
    schema.setdefault("outputs", {})
    return schema


def defaults(tool: str) -> Dict[str, Any]:
    """Default value of every input (None where the schema gives none)."""
    return {name: p.get("default") for name, p in load_schema(tool)["inputs"].items()}


def option_name(name: str) -> str:
    """CLI spelling of a parameter: ``ref_ms`` -> ``--ref-ms``."""
    return "--" + name.replace("_", "-")


def _click_param(name: str, param: Dict[str, Any]) -> Callable:
    dtype = param.get("dtype", "str")
    help_text = param.get("info", "")
    default = param.get("default")
    required = bool(param.get("required", False))
    if (param.get("policies") or {}).get("positional"):
        return click.argument(name, type=_CLICK_TYPES.get(dtype, click.STRING),
                              required=required)
    if dtype == "bool":
        return click.option(option_name(name), name, is_flag=True, default=bool(default),
                            help=help_text, show_default=True)
    ctype = _CLICK_TYPES.get(dtype)
    if ctype is None:
        raise TypeError(f"schema parameter '{name}': dtype '{dtype}' has no CLI mapping")
    if param.get("choices"):
        ctype = click.Choice([str(c) for c in param["choices"]])
    # click >= 8.3 takes an explicit default=None as a default, which silences `required`:
    # pass a default only when the schema has one
    extra = {} if default is None else {"default": default, "show_default": True}
    return click.option(option_name(name), name, type=ctype, required=required,
                        help=help_text, **extra)


def clickify(tool: str, func: Callable) -> click.Command:
    """A click command for ``tool`` whose parameters come from its schema."""
    schema = load_schema(tool)
    command = func
    # click applies decorators bottom-up; reverse so --help lists schema order
    for name, param in reversed(list(schema["inputs"].items())):
        command = _click_param(name, param)(command)
    return click.command(name=tool, help=schema.get("info", ""))(command)


def cab_definition(tool: str) -> Dict[str, Any]:
    """The Stimela cab for one tool, built from the same schema as the CLI."""
    schema = load_schema(tool)
    cab = {
        "info": schema.get("info", ""),
        "command": f"hitops {tool}",
        "policies": {"prefix": "--", "replace": {"_": "-"}},
        "inputs": _plain(schema["inputs"]),
        "outputs": _plain(schema["outputs"]),
    }
    if schema.get("image"):
        cab["image"] = schema["image"]
    return cab


def _plain(params: Dict[str, Any]) -> Dict[str, Any]:
    """Copy of a parameter block with CLI-only keys removed."""
    cleaned = {}
    for name, param in params.items():
        cleaned[name] = {k: v for k, v in param.items() if not k.startswith("cli_")}
    return cleaned
