"""The container scripts' logic (scripts/image-*.sh, container-lib.sh,
container-compare.py, slurm-local.sh) with recording stand-ins for buildah,
podman, docker, mmdebstrap, apptainer and the host's Python: no image is built,
nothing is pulled, nothing needs a container tool, slurm or the network.

The stand-ins keep a little state (which images "exist") in a directory, and
append each command line to a log that the tests read back.  PATH holds only
the stand-ins and the few ordinary tools the scripts use, so the real buildah
or docker of a development machine is never called.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = ROOT / "scripts"
TOOLS = ["bash", "sh", "awk", "cat", "cp", "rm", "mkdir", "ls", "find", "head", "cut", "du",
         "date", "basename", "dirname", "wc", "grep", "sed", "tr", "mv", "touch", "env", "id",
         "chmod", "sleep", "seq", "nproc", "hostname", "mktemp", "ln", "timeout", "tail"]

STAND_IN = r'''#!{python}
"""Recording stand-in for buildah / podman / docker / mmdebstrap / apptainer."""
import os, sys, pathlib, shutil
tool = pathlib.Path(sys.argv[0]).name
args = sys.argv[1:]
state = pathlib.Path(os.environ["SHIM_STATE"])
with open(os.environ["SHIM_LOG"], "a") as f:
    f.write(" ".join([tool] + args) + "\n")
images = state / "images"
have = images.read_text().split() if images.exists() else []

def add(name):
    images.write_text("\n".join(have + [name]) + "\n")

def opt(flag):
    return args[args.index(flag) + 1] if flag in args else None

if tool == "mmdebstrap":
    pathlib.Path(args[-1]).write_bytes(b"rootfs")
    sys.exit(0)
if tool in ("apptainer", "singularity"):
    pathlib.Path(args[-2]).write_bytes(b"sif")
    sys.exit(0)
if args[:1] == ["info"]:
    # DOCKER_INFO_RC=1: a client without its daemon; BUILDAH_/PODMAN_INFO_RC: a broken storage
    rc = int(os.environ.get(tool.upper() + "_INFO_RC", "0"))
    if rc:
        print("Client: Docker Engine - Community\n", file=sys.stderr)
        print(os.environ.get("INFO_ERROR", "Cannot connect to the Docker daemon at "
              "unix:///var/run/docker.sock. Is the docker daemon running?"), file=sys.stderr)
    sys.exit(rc)
sub = args[0]
if sub in ("inspect", "exists") or args[:2] in (["image", "exists"], ["image", "inspect"]):
    name = args[-1]
    if name not in have:
        sys.exit(1)
    if "--format" in args:
        print("2750000000")
    sys.exit(0)
if sub == "images":
    print("2.75 GB" if args[-1] in have else "")
    sys.exit(0)
if sub == "from":
    print(opt("--name") or "working-container")
    sys.exit(0)
if sub == "commit":
    add(args[-1])
    sys.exit(0)
if sub == "import":
    add(args[-1])
    sys.exit(0)
if sub == "build":
    ctx = pathlib.Path(args[-1])
    (state / "context.txt").write_text(
        "\n".join(sorted(str(p.relative_to(ctx)) for p in ctx.rglob("*") if p.is_file())))
    if os.environ.get("SHIM_BUILD_FAILS"):
        sys.exit(1)
    add(opt("-t"))
    sys.exit(0)
if sub == "run":
    vol = opt("--volume")
    host = pathlib.Path(vol.split(":")[0])
    (host / "demo").mkdir(parents=True, exist_ok=True)
    shutil.copy(os.environ["SHIM_RESULT"], host / "demo" / "peak-flux.json")
    (host / "demo" / "peak-flux.md").write_text("| method | recovery |\n")
    sys.exit(0)
if sub in ("push", "save"):
    dest = args[-1].split(":")[1] if sub == "push" else opt("-o")
    pathlib.Path(dest).write_bytes(b"archive")
    sys.exit(0)
sys.exit(0)   # add, config, rm
'''

HOST_PYTHON = r'''#!/bin/bash
# stand-in for .venv/bin/python: records pip calls, fakes their results
echo "python $*" >> "$SHIM_LOG"
if [ "$1 $2 $3" = "-m pip freeze" ]; then
  printf 'numpy==2.4.6\nhitops==0.1.0\n-e git+https://x/hitops.git@abc#egg=hitops\nfoo @ file:///tmp/foo.whl\n'
  exit 0
fi
if [ "$1 $2 $3" = "-m pip wheel" ]; then
  while [ $# -gt 0 ]; do
    if [ "$1" = "--wheel-dir" ]; then touch "$2/hitops-0.1.0-py3-none-any.whl"; fi
    shift
  done
  exit 0
fi
exit 1
'''


def image_from_cabs():
    img = yaml.safe_load((ROOT / "cabs" / "images.yml").read_text())["vars"]["hitops"]["image"]
    return f"{img['registry']}/{img['name']}:{img['version']}"


IMAGE = image_from_cabs()


class Env:
    """A PATH of stand-ins plus ordinary tools, a build cache and a command log."""

    def __init__(self, tmp_path: Path, stand_ins=("buildah", "mmdebstrap")):
        self.bin = tmp_path / "bin"
        self.bin.mkdir()
        self.state = tmp_path / "state"
        self.state.mkdir()
        self.cache = tmp_path / "cache"
        self.log = tmp_path / "commands.log"
        self.log.touch()
        for tool in TOOLS:
            real = shutil.which(tool)
            if real:
                (self.bin / tool).symlink_to(real)
        (self.bin / "python3").symlink_to(sys.executable)
        for name in stand_ins:
            self.add(name)
        self.host_py = tmp_path / "host-python"
        self.host_py.write_text(HOST_PYTHON)
        self.host_py.chmod(0o755)
        self.env = {"PATH": str(self.bin), "HOME": str(tmp_path), "SHIM_LOG": str(self.log),
                    "SHIM_STATE": str(self.state), "HITOPS_BUILD_CACHE": str(self.cache),
                    "HITOPS_PYTHON": str(self.host_py), "LANG": "C.UTF-8"}

    def add(self, name):
        path = self.bin / name
        path.write_text(STAND_IN.replace("{python}", sys.executable))
        path.chmod(0o755)

    def run(self, script, *args, **extra):
        env = dict(self.env, **{k: str(v) for k, v in extra.items()})
        return subprocess.run(["bash", str(SCRIPTS / script), *args], env=env, cwd=ROOT,
                              capture_output=True, text=True, timeout=60)

    def commands(self):
        return self.log.read_text().splitlines()

    def wheelhouse(self):
        wh = self.cache / "wheelhouse"
        wh.mkdir(parents=True)
        (wh / "hitops-0.1.0-py3-none-any.whl").write_bytes(b"wheel")
        (wh / "numpy-2.4.6-cp311-cp311-manylinux_2_28_x86_64.whl").write_bytes(b"wheel")


def lib(env, call, **extra):
    return subprocess.run(["bash", "-c", f". {SCRIPTS / 'container-lib.sh'}; {call}"],
                          env=dict(env.env, **extra), capture_output=True, text=True, timeout=30)


def test_image_name_follows_cabs_images_yml(tmp_path):
    out = lib(Env(tmp_path), "image_name")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == IMAGE == "ghcr.io/hitops/hitops:0.1.0"


@pytest.mark.parametrize("stand_ins, extra, expected", [
    (("buildah", "podman", "docker"), {}, "buildah"),
    (("podman", "docker"), {}, "podman"),
    (("docker",), {"DOCKER_INFO_RC": "0"}, "docker"),
    (("buildah", "docker"), {"HITOPS_CONTAINER_TOOL": "docker"}, "docker"),
])
def test_pick_tool(tmp_path, stand_ins, extra, expected):
    env = Env(tmp_path, stand_ins)
    out = lib(env, "pick_tool", **extra)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == expected


@pytest.mark.parametrize("stand_ins, extra, message", [
    # no apt-get on this PATH, so these stop where the install would start
    (("docker",), {"DOCKER_INFO_RC": "1"},
     "no working container builder (buildah not installed; podman not installed; docker installed, "
     "but `docker info` failed: Cannot connect to the Docker daemon at unix:///var/run/docker.sock. "
     "Is the docker daemon running?) and no apt-get to install one: install buildah"),
    ((), {}, "no apt-get to install one: install buildah"),
    # a buildah that is installed but fails is not reinstalled
    (("buildah",), {"BUILDAH_INFO_RC": "1", "INFO_ERROR": "kernel does not support overlay"},
     "(buildah installed, but `buildah info` failed: kernel does not support overlay; podman not "
     "installed; docker not installed): fix buildah (see 'buildah info')"),
    (("buildah",), {"HITOPS_CONTAINER_TOOL": "podman"}, "podman is not on PATH"),
    (("docker",), {"HITOPS_CONTAINER_TOOL": "docker", "DOCKER_INFO_RC": "1"},
     "HITOPS_CONTAINER_TOOL=docker but docker is installed, but `docker info` failed: Cannot connect"),
    (("buildah",), {"HITOPS_CONTAINER_TOOL": "rkt"}, "use buildah, podman or docker"),
])
def test_pick_tool_failures_are_one_line_with_the_remedy(tmp_path, stand_ins, extra, message):
    out = lib(Env(tmp_path, stand_ins), "pick_tool", **extra)
    assert out.returncode != 0
    assert message in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr


# ---- the builder's choice and its installation (issue 30), as tests/test_setup.py
# does for WSClean: stand-ins for apt-get, sudo and id.  apt-get's stand-in puts
# recording stand-ins for the packages it installs on PATH; sudo's drops the
# caller's environment as sudo's env_reset does.

def _installer(env, *, uid, sudo, apt=True):
    """apt-get / sudo / id stand-ins in env's bin; returns the apt-get call log."""
    calls = env.state / "apt-get.calls"

    def script(name, text):
        path = env.bin / name
        if path.is_symlink() or path.exists():
            path.unlink()
        path.write_text("#!/bin/bash\n" + text)
        path.chmod(0o755)

    script("id", f'[ "$1" = -u ] || exit 2\necho {uid}\n')
    if apt:
        stand_in = STAND_IN.replace("{python}", sys.executable)
        (env.state / "stand-in").write_text(stand_in)
        script("apt-get", f"""
printf '%s|DEBIAN_FRONTEND=%s|SUDO_USER=%s\\n' "$*" "${{DEBIAN_FRONTEND-}}" "${{SUDO_USER-}}" >> {calls}
echo "Reading package lists..."
[ -z "${{APT_FAILS-}}" ] || {{ echo "E: Unable to locate package buildah"; exit 100; }}
if [ "$1" = install ]; then
    for pkg in "${{@:4}}"; do
        {shutil.which('cp')} {env.state / 'stand-in'} {env.bin}/$pkg
        {shutil.which('chmod')} +x {env.bin}/$pkg
    done
fi
""")
    if sudo:
        script("sudo", f"""
printf '%s\\n' "$*" >> {env.state / 'sudo.calls'}
exec {shutil.which('env')} -i PATH="$PATH" SHIM_LOG="$SHIM_LOG" SHIM_STATE="$SHIM_STATE" SUDO_USER=tester "$@"
""")
    return calls


def _lines(path):
    return path.read_text().splitlines() if path.exists() else []


def _installed_from_debian(calls, sudo_user=""):
    """apt-get update, then install of both packages, DEBIAN_FRONTEND reaching apt-get."""
    apt = _lines(calls)
    assert [c.split("|")[0] for c in apt] == ["update -q", "install -y -q buildah mmdebstrap"]
    # SUDO_USER empty: apt-get ran directly; "tester": through sudo, whose reset
    # environment still carried DEBIAN_FRONTEND
    assert all(c.endswith(f"|DEBIAN_FRONTEND=noninteractive|SUDO_USER={sudo_user}") for c in apt)


def _chosen(stderr):
    lines = [line for line in stderr.splitlines() if "container builder: " in line]
    assert len(lines) == 1, stderr   # said once, also when image-base.sh needs the builder
    return lines[0].split("container builder: ", 1)[1]


DAEMONLESS = ("docker installed, but `docker info` failed: Cannot connect to the Docker daemon at "
              "unix:///var/run/docker.sock. Is the docker daemon running?")


def _build_on_issue_30s_machine(tmp_path, uid):
    """`make image`'s script where issue 30 met it: a docker client without its
    daemon, no buildah, no podman, no sudo."""
    env = Env(tmp_path, ("docker",))
    calls = _installer(env, uid=uid, sudo=False)
    env.wheelhouse()
    return env, calls, env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1, DOCKER_INFO_RC=1)


def test_no_builder_as_root_installs_buildah_and_builds(tmp_path):
    env, calls, out = _build_on_issue_30s_machine(tmp_path, uid=0)
    assert out.returncode == 0, out.stderr
    _installed_from_debian(calls)
    assert not (env.state / "sudo.calls").exists()
    assert ("installing buildah and mmdebstrap from Debian (apt-get install buildah mmdebstrap; "
            f"output in {env.cache}/apt-get.log)") in out.stderr
    assert "Reading package lists" in (env.cache / "apt-get.log").read_text()
    assert _chosen(out.stderr) == (f"buildah (installed now from Debian; passed over: podman not "
                                   f"installed; {DAEMONLESS})")
    cmds = env.commands()
    # the installed tools did the work: mmdebstrap's base, then buildah's build
    assert any(c.startswith("mmdebstrap ") for c in cmds)
    assert any(c.startswith("buildah build --isolation chroot --build-arg "
                            "BASE=localhost/hitops-base:bookworm ") for c in cmds)
    assert not any(c.startswith("docker ") and c != "docker info" for c in cmds)


def test_no_builder_not_root_installs_through_sudo(tmp_path):
    env = Env(tmp_path, ())
    calls = _installer(env, uid=1000, sudo=True)
    out = lib(env, "pick_tool")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "buildah"
    _installed_from_debian(calls, sudo_user="tester")
    assert _lines(env.state / "sudo.calls") == [
        "env DEBIAN_FRONTEND=noninteractive apt-get update -q",
        "env DEBIAN_FRONTEND=noninteractive apt-get install -y -q buildah mmdebstrap"]
    assert "(sudo apt-get install buildah mmdebstrap;" in out.stderr
    assert _chosen(out.stderr) == ("buildah (installed now from Debian; passed over: "
                                   "podman not installed; docker not installed)")


def test_no_builder_neither_root_nor_sudo_is_one_line(tmp_path):
    env, calls, out = _build_on_issue_30s_machine(tmp_path, uid=1000)
    assert out.returncode != 0
    assert out.stderr.strip().splitlines() == [
        "image-build.sh: no working container builder (buildah not installed; podman not installed; "
        f"{DAEMONLESS}) and installing buildah needs root: run 'apt-get install buildah mmdebstrap' "
        "as root (or install sudo), then rerun"]
    assert _lines(calls) == [] and env.commands() == ["docker info"]


def test_a_failed_apt_get_shows_its_tail_and_one_line(tmp_path):
    env = Env(tmp_path, ())
    _installer(env, uid=0, sudo=False)
    out = lib(env, "pick_tool", APT_FAILS="1")
    assert out.returncode != 0
    assert "E: Unable to locate package buildah" in out.stderr   # apt-get's own reason, from the log
    assert out.stderr.strip().splitlines()[-1] == (
        f"bash: apt-get update failed (full output in {env.cache}/apt-get.log): fix the cause shown "
        "above, or install buildah yourself, then rerun")


@pytest.mark.parametrize("stand_ins, extra, chosen, probed", [
    # buildah first: the others are not even asked
    (("buildah", "podman", "docker"), {},
     "buildah (passed over: podman comes after buildah; docker comes after buildah)", ["buildah"]),
    # a working podman before a daemon-less docker, which is then not asked
    (("podman", "docker"), {"DOCKER_INFO_RC": "1"},
     "podman (passed over: buildah not installed; docker comes after podman)", ["podman"]),
    # a podman whose storage fails is passed over, with its reason
    (("podman", "docker"), {"PODMAN_INFO_RC": "1", "INFO_ERROR": "cannot set up namespace"},
     "docker (passed over: buildah not installed; podman installed, but `podman info` failed: "
     "cannot set up namespace)", ["podman", "docker"]),
])
def test_the_first_working_builder_is_chosen_and_nothing_installed(tmp_path, stand_ins, extra, chosen,
                                                                   probed):
    env = Env(tmp_path, stand_ins)
    calls = _installer(env, uid=0, sudo=False)
    out = lib(env, "pick_tool", **extra)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == chosen.split()[0]
    assert _chosen(out.stderr) == chosen
    assert env.commands() == [f"{tool} info" for tool in probed]
    assert _lines(calls) == []


@pytest.mark.parametrize("script", ["image-check.sh", "image-archive.sh"])
def test_check_and_archive_install_the_builder_too(tmp_path, script):
    env = Env(tmp_path, ("docker",))
    calls = _installer(env, uid=0, sudo=False)
    out = env.run(script, DOCKER_INFO_RC=1)
    # buildah installed; its storage is empty, so they say what to run first
    _installed_from_debian(calls)
    assert out.returncode != 0
    assert out.stderr.strip().splitlines()[-1] == (
        f"{script}: ghcr.io/hitops/hitops:0.1.0 is not in buildah's storage: run `make image` first")


def test_build_with_buildah_makes_the_base_then_builds_offline(tmp_path):
    env = Env(tmp_path)
    env.wheelhouse()
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1)
    assert out.returncode == 0, out.stderr
    cmds = env.commands()
    tar = f"{env.cache}/bookworm-minbase.tar"
    ctx = f"{env.cache}/context"
    # one probe of the builder: image-base.sh takes the one image-build.sh chose
    assert cmds[0] == "buildah info" and cmds.count("buildah info") == 1
    assert cmds[1].startswith("buildah inspect --type image localhost/hitops-base:bookworm")
    assert cmds[2] == (f"mmdebstrap --quiet --variant=minbase --format=tar --include=ca-certificates "
                       f"bookworm {tar}.part")
    assert "buildah from scratch" in cmds
    assert f"buildah add working-container {tar} /" in cmds
    assert "buildah commit --rm --quiet working-container localhost/hitops-base:bookworm" in cmds
    build = [c for c in cmds if c.startswith("buildah build")]
    assert build == [f"buildah build --isolation chroot --build-arg BASE=localhost/hitops-base:bookworm "
                     f"-f {ROOT}/docker/Dockerfile -t {IMAGE} {ctx}"]
    # the context: the wheelhouse, cabs and recipes, nothing else from the checkout
    files = (env.state / "context.txt").read_text().splitlines()
    assert "wheelhouse/hitops-0.1.0-py3-none-any.whl" in files
    assert {f.split("/")[0] for f in files} == {"wheelhouse", "cabs", "recipes"}
    assert "cabs/images.yml" in files and "recipes/fpt-demo.yml" in files
    assert f"built {IMAGE}" in out.stderr and "size 2.75 GB" in out.stderr
    # a second build reuses the base: no mmdebstrap, no import
    env.log.write_text("")
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1)
    assert out.returncode == 0, out.stderr
    assert not [c for c in env.commands() if c.startswith(("mmdebstrap", "buildah commit"))]


def test_a_base_directory_left_by_older_scripts_is_made_again_as_a_tar(tmp_path):
    # before --format=tar, mmdebstrap wrote a directory named bookworm-minbase.tar
    env = Env(tmp_path)
    env.wheelhouse()
    old = env.cache / "bookworm-minbase.tar"
    (old / "etc").mkdir(parents=True)
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1)
    assert out.returncode == 0, out.stderr
    assert any(c.startswith("mmdebstrap ") for c in env.commands())
    assert old.is_file() and old.read_bytes() == b"rootfs"


def test_build_with_docker_imports_the_base_without_isolation_flags(tmp_path):
    env = Env(tmp_path, ("docker", "mmdebstrap"))
    env.wheelhouse()
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1, DOCKER_INFO_RC=0)
    assert out.returncode == 0, out.stderr
    cmds = env.commands()
    assert (f"docker import --change CMD [\"/bin/bash\"] {env.cache}/bookworm-minbase.tar "
            f"localhost/hitops-base:bookworm") in cmds
    assert (f"docker build --build-arg BASE=localhost/hitops-base:bookworm -f {ROOT}/docker/Dockerfile "
            f"-t {IMAGE} {env.cache}/context") in cmds


def test_without_mmdebstrap_the_tool_pulls_debian(tmp_path):
    env = Env(tmp_path, ("podman",))
    env.wheelhouse()
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1)
    assert out.returncode == 0, out.stderr
    assert any(c.startswith("podman build --isolation chroot --build-arg BASE=debian:bookworm-slim ")
               for c in env.commands())
    assert "pulls debian:bookworm-slim" in out.stderr


def test_build_failures_name_what_failed(tmp_path):
    env = Env(tmp_path)
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1)
    assert out.returncode != 0 and "no hitops wheel in" in out.stderr
    env.wheelhouse()
    out = env.run("image-build.sh", HITOPS_SKIP_WHEELHOUSE=1, SHIM_BUILD_FAILS=1)
    assert out.returncode != 0
    assert out.stderr.strip().splitlines()[-1] == "image-build.sh: buildah build failed (see above)"


def test_wheelhouse_pins_the_host_versions_and_rebuilds_hitops(tmp_path):
    env = Env(tmp_path)
    wh = env.cache / "wheelhouse"
    wh.mkdir(parents=True)
    (wh / "hitops-0.0.9-py3-none-any.whl").write_bytes(b"old")
    out = env.run("image-wheelhouse.sh")
    assert out.returncode == 0, out.stderr
    # editable, direct-URL and hitops's own lines cannot be constraints
    assert (env.cache / "constraints.txt").read_text() == "numpy==2.4.6\n"
    wheel = [c for c in env.commands() if c.startswith("python -m pip wheel")]
    assert wheel == [f"python -m pip wheel --quiet --wheel-dir {wh} --find-links {wh} "
                     f"--constraint {env.cache}/constraints.txt {ROOT}[hpc]"]
    assert not (wh / "hitops-0.0.9-py3-none-any.whl").exists()
    assert (wh / "hitops-0.1.0-py3-none-any.whl").exists()


def test_wheelhouse_without_the_venv_says_make_setup(tmp_path):
    env = Env(tmp_path)
    out = env.run("image-wheelhouse.sh", HITOPS_PYTHON=tmp_path / "missing" / "python")
    assert out.returncode != 0 and "run `make setup` first" in out.stderr


def _results(path, recovery):
    path.mkdir(parents=True, exist_ok=True)
    payload = {"rows": [{"method": "PWC (PWC_DATA)", "recovery": recovery,
                         "fit": str(path / "images" / "pwc-imfit.json")}]}
    (path / "peak-flux.json").write_text(json.dumps(payload))
    return path / "peak-flux.json"


@pytest.mark.parametrize("tool", ["buildah", "docker"])
def test_image_check_runs_the_demo_inside_and_compares(tmp_path, tool):
    env = Env(tmp_path, (tool,))
    (env.state / "images").write_text(IMAGE + "\n")
    native = tmp_path / "native"
    _results(native, 0.9951)
    inside = _results(tmp_path / "inside", 0.9951)
    out = env.run("image-check.sh", HITOPS_NATIVE_DEMO=native, SHIM_RESULT=inside, DOCKER_INFO_RC=0)
    assert out.returncode == 0, out.stderr
    assert "identical: the image's peak-flux.json" in out.stdout
    run = [c for c in env.commands() if f"{tool} run" in c][0]
    assert f"{env.cache}/check/image:/check" in run
    assert run.endswith(" stimela run /opt/hitops/recipes/fpt-demo.yml dir=/check/demo")
    if tool == "buildah":
        assert "--isolation chroot" in run
        assert env.commands()[-1].startswith("buildah rm ")   # the working container is removed


def test_image_check_reports_a_different_table(tmp_path):
    env = Env(tmp_path)
    (env.state / "images").write_text(IMAGE + "\n")
    native = tmp_path / "native"
    _results(native, 0.9951)
    inside = _results(tmp_path / "inside", 0.9952)
    out = env.run("image-check.sh", HITOPS_NATIVE_DEMO=native, SHIM_RESULT=inside)
    assert out.returncode != 0
    assert "DIFFERENT $.rows[0].recovery: 0.9951 vs 0.9952" in out.stdout
    assert "the image's peak-flux table differs from the host's" in out.stderr.splitlines()[-1]


def test_image_check_without_the_image_says_make_image(tmp_path):
    out = Env(tmp_path).run("image-check.sh")
    assert out.returncode != 0 and "run `make image` first" in out.stderr


def test_archive_and_sif(tmp_path):
    env = Env(tmp_path)
    (env.state / "images").write_text(IMAGE + "\n")
    tar = env.cache / "hitops-0.1.0.docker.tar"
    out = env.run("image-archive.sh")
    assert out.returncode == 0, out.stderr
    assert f"buildah push --quiet {IMAGE} docker-archive:{tar}:{IMAGE}" in env.commands()
    out = env.run("image-archive.sh", "--sif")
    assert out.returncode != 0
    assert "neither apptainer nor singularity is installed" in out.stderr
    assert f"apptainer build --build-arg archive={tar.name} hitops.sif docker/hitops.def" in out.stderr
    env.add("apptainer")
    out = env.run("image-archive.sh", "--sif")
    assert out.returncode == 0, out.stderr
    assert (f"apptainer build --force --build-arg archive={tar} {env.cache}/hitops-0.1.0.sif "
            f"{ROOT}/docker/hitops.def") in env.commands()
    assert "~/.singularity/ghcr.io-hitops-hitops:0.1.0.simg" in out.stderr


def test_compare_ignores_paths_and_catches_numbers(tmp_path):
    compare = [sys.executable, str(SCRIPTS / "container-compare.py")]
    a = _results(tmp_path / "a", 0.5)
    b = _results(tmp_path / "b", 0.5)
    out = subprocess.run(compare + [str(a), str(b)], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.startswith("identical:")
    c = _results(tmp_path / "c", float("nan"))
    d = _results(tmp_path / "d", float("nan"))
    assert subprocess.run(compare + [str(c), str(d)], capture_output=True).returncode == 0
    out = subprocess.run(compare + [str(a), str(c)], capture_output=True, text=True)
    assert out.returncode == 1 and "DIFFERENT" in out.stdout
    out = subprocess.run(compare + [str(a), str(tmp_path / "none.json")], capture_output=True,
                         text=True)
    assert out.returncode == 1 and "did both runs finish?" in out.stderr


def test_slurm_local_without_slurm_names_the_packages(tmp_path):
    env = Env(tmp_path, ())
    out = env.run("slurm-local.sh", "run", "--", "true")
    assert out.returncode != 0
    line = out.stderr.strip()
    assert len(line.splitlines()) == 1
    assert "not found: apt-get install slurm-wlm munge" in line and "munged" in line
