"""The containerised/HPC route as far as it can be checked without a container
tool or slurm (tests/test_image_scripts.py covers the build scripts with
stand-ins, tests/test_cluster_slurm.py a real one-node slurm when present):

* the container definitions parse and name only files that exist;
* the cabs name the hitops image, and Stimela's singularity backend and slurm
  wrapper build the expected command lines.  For the latter, stand-ins for
  `singularity` and `srun` record the command line Stimela builds and then
  run the wrapped command here, so the step really runs.
"""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
IMAGE = "ghcr.io/hitops/hitops:0.1.0"

DOCKER_INSTRUCTIONS = {"FROM", "RUN", "CMD", "LABEL", "EXPOSE", "ENV", "ADD", "COPY",
                       "ENTRYPOINT", "VOLUME", "USER", "WORKDIR", "ARG", "ONBUILD",
                       "STOPSIGNAL", "HEALTHCHECK", "SHELL"}


def docker_instructions(text):
    """(instruction, arguments) of a Dockerfile, continuation lines joined."""
    out, current = [], ""
    for raw in text.splitlines():
        line = raw.strip()
        if not current and (not line or line.startswith("#")):
            continue
        current += " " + line.rstrip("\\").strip() if current else line.rstrip("\\").strip()
        if not line.endswith("\\"):
            word, _, args = current.partition(" ")
            out.append((word, args))
            current = ""
    assert not current, "Dockerfile ends inside a continued line"
    return out


def test_dockerfile_parses_and_installs_offline_from_the_wheelhouse():
    instructions = docker_instructions((ROOT / "docker" / "Dockerfile").read_text())
    words = [w for w, _ in instructions]
    # ARG BASE before FROM: scripts/image-base.sh passes a locally made base
    assert words[:2] == ["ARG", "FROM"] and instructions[1][1] == "${BASE}"
    assert instructions[0][1] == "BASE=debian:bookworm-slim"
    assert set(words) <= DOCKER_INSTRUCTIONS, set(words) - DOCKER_INSTRUCTIONS
    for word, args in instructions:
        if word == "COPY":
            # scripts/image-build.sh copies these into the build context
            for src in args.split()[:-1]:
                assert (ROOT / src).exists(), f"COPY {src}: no such file in the repository"
                assert src in ("cabs", "recipes"), f"COPY {src}: not in the staged build context"
    text = " ".join(a for _, a in instructions)
    assert "wsclean" in text
    # offline: only the wheelhouse (bind-mounted, not a layer), never the index
    assert "--mount=type=bind,source=wheelhouse,target=/wheelhouse" in text
    assert "pip install --no-index --find-links /wheelhouse 'hitops[hpc]'" in text
    assert "CASASITECONFIG=/opt/hitops/casasiteconfig.py" in text
    # the image tag documented in the Dockerfile is the one the cabs name
    assert IMAGE in (ROOT / "docker" / "Dockerfile").read_text()


def test_apptainer_definition_bootstraps_from_the_image_archive():
    """docker/hitops.def is not a second recipe: it starts from the archive of the
    image docker/Dockerfile built (scripts/image-archive.sh writes it)."""
    text = (ROOT / "docker" / "hitops.def").read_text()
    header = dict(re.findall(r"^(Bootstrap|From):\s*(.+)$", text, re.M))
    assert header == {"Bootstrap": "docker-archive", "From": "{{ archive }}"}
    sections = re.findall(r"^%(\w+)", text, re.M)
    assert set(sections) <= {"arguments", "test", "runscript", "labels", "help", "environment"}
    assert "post" not in sections and "files" not in sections
    arguments = text.split("\n%arguments\n", 1)[1].split("\n%", 1)[0]
    default = dict(line.strip().split("=", 1) for line in arguments.strip().splitlines())
    version = IMAGE.rsplit(":", 1)[1]
    assert default == {"archive": f"hitops-{version}.docker.tar"}
    archive_script = (ROOT / "scripts" / "image-archive.sh").read_text()
    assert 'tar=$CACHE/hitops-$version.docker.tar' in archive_script


SINGULARITY_SHIM = """#!/bin/bash
if [ "$1" = "--version" ]; then echo "singularity-ce version 4.1.0-recording-stand-in"; exit 0; fi
echo "singularity $*" >> "$SHIM_LOG"
if [ "$1" = "build" ]; then touch "$2"; exit 0; fi
if [ "$1" = "exec" ]; then
  shift
  while [ $# -gt 0 ]; do
    case "$1" in
      --pwd) cd "$2"; shift 2;;
      --bind|-B|--env) shift 2;;
      --*) shift;;
      *) shift; break;;
    esac
  done
  exec "$@"
fi
exit 1
"""

SRUN_SHIM = """#!/bin/bash
echo "srun $*" >> "$SHIM_LOG"
while [ $# -gt 0 ]; do
  case "$1" in
    -J|--*) shift 2;;
    *) break;;
  esac
done
exec "$@"
"""


def _executable(path, text):
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


@pytest.mark.slow
def test_singularity_and_slurm_commands_name_the_image(tmp_path):
    shims = tmp_path / "bin"
    shims.mkdir()
    _executable(shims / "singularity", SINGULARITY_SHIM)
    _executable(shims / "srun", SRUN_SHIM)
    log = tmp_path / "commands.log"
    env = dict(os.environ)
    env["PATH"] = f"{shims}:{BIN}:{env.get('PATH', '')}"
    env["SHIM_LOG"] = str(log)
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".venv" / "numba-cache"))
    out = tmp_path / "out"
    # Stimela's slurm wrapper (stimela/backends/slurm_runner.sh, 2.1.4) makes one
    # directory per step for the container's /tmp under the 'tmp' ephemeral class (/tmp
    # unless set) and never removes it (its clean-up tests -f, a file, on a directory):
    # here they go under the test's own directory
    ephemeral = tmp_path / "ephemeral"
    ephemeral.mkdir()
    cmd = [str(BIN / "stimela"), "run", "-S", "--slurm", "-s", "simulate",
           "-c", f"opts.backend.singularity.image_dir={tmp_path / 'images'}",
           "-c", f"opts.backend.singularity.ephemeral.tmp={ephemeral}",
           "-c", "opts.backend.slurm.srun_opts.cpus-per-task=2",
           str(ROOT / "recipes" / "fpt-demo.yml"), f"dir={out}"]
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    lines = log.read_text().splitlines()
    build = [l for l in lines if l.startswith("singularity build")]
    assert build and build[0].endswith(f"docker://{IMAGE}")
    # the recipe's parameter step (tagged always, so kept by -s) runs first, in the image too
    srun = {l.split()[2]: l for l in lines if l.startswith("srun")}
    assert list(srun) == ["params.fpt-demo", "simulate.fpt-demo"], list(srun)
    assert srun["simulate.fpt-demo"].startswith("srun -J simulate.fpt-demo --cpus-per-task 2")
    assert "singularity exec" in srun["simulate.fpt-demo"]
    assert re.search(f"slurm_runner.sh {re.escape(str(ephemeral))}::EPH0 -- ",
                     srun["simulate.fpt-demo"])
    assert "ghcr.io-hitops-hitops:0.1.0.simg hitops simulate" in srun["simulate.fpt-demo"]
    assert "ghcr.io-hitops-hitops:0.1.0.simg python" in srun["params.fpt-demo"]
    # the recipe file (read by the parameter step) is bound into the container
    assert str(ROOT / "recipes") in srun["params.fpt-demo"]
    # the wrapped commands really ran
    assert (out / "sim-86.ms").is_dir() and (out / "sim-230.ms").is_dir()
    written = json.loads((out / "params" / "fringefit.json").read_text())
    assert written["inputs"]["fringefit_solint"] == "20s"
