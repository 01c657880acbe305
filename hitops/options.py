"""Typed option objects made from a tool's schema (hitops/schemas/<tool>.yml).

``options_class("diagnose")`` is a frozen dataclass with one field per schema
input, typed from its ``dtype`` and defaulting to the schema's default, so the
options that travel through a tool's pipeline are the schema's and nothing
else (the CLI and the cab come from the same schema: hitops/schema.py).

A schema with a ``sections`` block (calibrate's: input, tracking, n0, output,
run) gets one frozen dataclass per section (``section_classes``) and an options
class holding the inputs of no section (the positional sets) and one field per
section, as QuartiCal's configuration nests its options by stage.  The Python
API takes the sections; the command line and the cab stay flat, one flag per
input, and ``from_flat`` turns the flags into sections.  Every section checks
its schema ``choices`` when it is made, so a value the command line's parser
refuses is refused in Python with the same one line.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import Any, Dict, Mapping, Optional, Tuple

from .errors import InputError
from .schema import load_schema

_TYPES = {"str": str, "int": int, "float": float, "bool": bool, "MS": str, "File": str,
          "Directory": str, "URI": str}


def _class_name(*parts: str) -> str:
    return "".join(word.capitalize() for part in parts for word in part.split("_")) + "Options"


def _fields(tool: str, names) -> list:
    """Dataclass fields of the named inputs, typed and defaulted from the schema
    (required ones first)."""
    inputs = load_schema(tool)["inputs"]
    required, optional = [], []
    for name in names:
        spec = inputs[name]
        kind = _TYPES.get(spec.get("dtype", "str"), Any)
        if spec.get("required"):
            required.append((name, kind))
        else:
            default = spec.get("default")
            optional.append((name, kind if default is not None else Optional[kind],
                             dataclasses.field(default=default)))
    return required + optional


def check_choices(tool: str, values: Mapping[str, Any]) -> None:
    """The schema's ``choices`` of every input in ``values``: one line naming the flag."""
    inputs = load_schema(tool)["inputs"]
    for name, value in values.items():
        choices = inputs[name].get("choices") if name in inputs else None
        if choices and value is not None and value not in choices:
            flag = "--" + name.replace("_", "-")
            raise InputError(f"{flag}: unknown value {value!r}; choose one of "
                             f"{', '.join(map(str, choices))}")


def section_names(tool: str) -> Dict[str, Tuple[str, ...]]:
    """{section: its inputs} as the schema declares them ({} for a flat tool)."""
    return {name: tuple(inputs) for name, inputs in
            (load_schema(tool).get("sections") or {}).items()}


def _reducer(tool: str, section):
    """``__reduce__`` of a generated options class: the class is made from the schema in each
    process (it has no importable name), so an instance pickles as (tool, section, values)
    and is made again there (a dask worker receives the run's plan this way)."""
    def reduce(self):
        return _remake, (tool, section, {f.name: getattr(self, f.name)
                                         for f in dataclasses.fields(self)})
    return reduce


def _remake(tool: str, section, values: Dict[str, Any]):
    cls = options_class(tool) if section is None else section_classes(tool)[section]
    return cls(**values)


@lru_cache(maxsize=None)
def section_classes(tool: str) -> Dict[str, type]:
    """{section: frozen dataclass of its inputs}, each checking its choices when made."""
    classes = {}
    for section, names in section_names(tool).items():
        def post_init(self, _tool=tool):
            check_choices(_tool, dataclasses.asdict(self))
        classes[section] = dataclasses.make_dataclass(
            _class_name(section), _fields(tool, names), frozen=True,
            namespace={"__post_init__": post_init, "__reduce__": _reducer(tool, section),
                       "__doc__": f"The {section} options of hitops {tool} "
                                  f"(hitops/schemas/{tool}.yml)."})
    return classes


@lru_cache(maxsize=None)
def options_class(tool: str) -> type:
    """Frozen dataclass ``<Tool>Options`` of ``tool``'s inputs.

    A flat tool: one field per input.  A tool with sections: the inputs of no
    section, then one field per section (defaulting to the section's defaults),
    with ``from_flat(values)`` and ``flat()`` between the two forms.
    """
    inputs = load_schema(tool)["inputs"]
    sections = section_names(tool)
    if not sections:
        return dataclasses.make_dataclass(_class_name(tool), _fields(tool, inputs), frozen=True)
    in_sections = {name for names in sections.values() for name in names}
    top = [name for name in inputs if name not in in_sections]
    classes = section_classes(tool)
    fields = _fields(tool, top) + [
        (section, cls, dataclasses.field(default_factory=cls)) for section, cls in classes.items()]

    @classmethod
    def from_flat(cls, values: Mapping[str, Any]):
        """The options from one value per input (the command line's form); an input
        missing from ``values`` takes its schema default."""
        unknown = sorted(set(values) - set(inputs))
        if unknown:
            raise InputError(f"unknown option(s) of hitops {tool}: {', '.join(unknown)}")
        made = {section: classes[section](**{n: values[n] for n in names if n in values})
                for section, names in sections.items()}
        return cls(**{name: values[name] for name in top if name in values}, **made)

    def flat(self) -> Dict[str, Any]:
        """One value per input, as the command line gives them."""
        out = {name: getattr(self, name) for name in top}
        for section in sections:
            out.update(dataclasses.asdict(getattr(self, section)))
        return out

    return dataclasses.make_dataclass(
        _class_name(tool), fields, frozen=True,
        namespace={"from_flat": from_flat, "flat": flat, "__reduce__": _reducer(tool, None),
                   "__doc__": f"The options of hitops {tool} in sections "
                              f"({', '.join(sections)}; hitops/schemas/{tool}.yml)."})


def flat_entry(tool: str, function):
    """``function`` (which takes the inputs of no section, then the sections) called with
    one keyword per input, as the command line and Stimela's cab give them.

    The entry's signature is the schema's, flat: required inputs first, every other input a
    keyword with its schema default (tests/test_schema_defaults.py checks it), so the
    command's implementation lists no option a second time.
    """
    import functools
    import inspect

    cls = options_class(tool)
    sections = section_names(tool)
    params = []
    for name, spec in load_schema(tool)["inputs"].items():
        default = inspect.Parameter.empty if spec.get("required") else spec.get("default")
        params.append(inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                        default=default))
    params.sort(key=lambda p: p.default is not inspect.Parameter.empty)
    signature = inspect.Signature(params)

    @functools.wraps(function)
    def entry(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        opts = cls.from_flat(bound.arguments)
        top = {f.name: getattr(opts, f.name) for f in dataclasses.fields(cls)
               if f.name not in sections}
        return function(*top.values(), **{s: getattr(opts, s) for s in sections})

    entry.__signature__ = signature
    entry.__doc__ = (f"hitops {tool} with one keyword per option, as the command line gives "
                     f"them (hitops/schemas/{tool}.yml); the sections are made from them and "
                     f"passed to {function.__module__}.{function.__name__}.")
    return entry
