"""Every tool's CLI agrees with its generated Stimela cab, loaded through Stimela itself.

For each schema the cab in cabs/hitops.yml is parsed with Stimela's own cab
schema, Stimela builds the command line for a full set of parameter values,
and the ``hitops`` click command must parse that command line back into the
same values.  cabs/hitops.yml must also be what ``python -m hitops.cabgen``
writes today.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from hitops import cabgen
from hitops.schema import clickify, load_schema, tools

ROOT = Path(__file__).resolve().parent.parent
CAB_FILE = ROOT / "cabs" / "hitops.yml"

SAMPLES = {"str": "some-value", "int": 7, "float": 2.5, "bool": True,
           "MS": "/data/x.ms", "File": "/data/x.json", "Directory": "/data/dir",
           "URI": "/data/x.uvfits"}


def test_cab_file_is_up_to_date():
    assert CAB_FILE.read_text() == cabgen.render(), (
        "cabs/hitops.yml is stale: run `python -m hitops.cabgen` (make cabs)")


def _stimela_cab(tool):
    from omegaconf import OmegaConf
    from stimela.kitchen.cab import get_cab_schema

    cabs = yaml.safe_load(CAB_FILE.read_text())["cabs"]
    conf = OmegaConf.merge(get_cab_schema(), OmegaConf.create(cabs[f"hitops.{tool}"]))
    return OmegaConf.to_object(conf)


def _sample(name, param):
    if param.get("choices"):
        return param["choices"][-1]
    return SAMPLES[param.get("dtype", "str")]


@pytest.mark.parametrize("tool", tools())
def test_stimela_command_line_parses_back_into_the_same_parameters(tool):
    schema = load_schema(tool)
    cab = _stimela_cab(tool)
    assert cab.command == f"hitops {tool}"
    assert set(cab.inputs) == set(schema["inputs"])
    params = {name: _sample(name, p) for name, p in schema["inputs"].items()}
    argv = cab.build_argument_list(params)
    received = {}
    command = clickify(tool, lambda **kw: received.update(kw))
    command.main(args=[str(a) for a in argv], standalone_mode=False)
    for name, value in params.items():
        assert received[name] == value, (tool, name, argv)


@pytest.mark.parametrize("tool", tools())
def test_cli_defaults_and_required_match_the_cab(tool):
    cab = _stimela_cab(tool)
    schema = load_schema(tool)["inputs"]
    command = clickify(tool, lambda **kw: None)
    by_name = {p.name: p for p in command.params}
    for name, param in cab.inputs.items():
        cli = by_name[name]
        assert bool(cli.required) == bool(param.required), (tool, name)
        default = schema[name].get("default")
        if default is not None:
            assert cli.default == default == param.default, (tool, name)
        if param.dtype == "bool":
            assert cli.is_flag and cli.default is False, (tool, name)
