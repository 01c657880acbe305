"""The set-up steps (scripts/setup.sh, called by the Makefile) on a machine without WSClean.

The WSClean tests run ``make wsclean``, the path ``make setup/run/test`` take,
with stand-ins for ``apt-get``, ``sudo`` and ``id`` first on a PATH that holds
only the few tools the step needs and no ``wsclean``. The stand-ins record
their arguments and the environment that reached them: issue 11 was a root
machine where ``$SUDO DEBIAN_FRONTEND=noninteractive apt-get`` ran the
assignment as a command. The sudo stand-in drops the caller's environment as
sudo's env_reset does, so a variable set in front of ``sudo`` does not reach
apt-get here either.

The CASA test runs the casa-config and numba-cache steps for an environment
that never had them, under an empty HOME, and then imports casatools offline.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]

# what `make wsclean` and scripts/setup.sh run besides bash builtins and the stand-ins
TOOLS = ("make", "bash", "env", "dirname", "mkdir", "tail")


def _write_script(path: Path, text: str) -> None:
    path.write_text("#!/bin/bash\n" + text)
    path.chmod(0o755)


def _machine(tmp_path: Path, *, uid: int, sudo: bool, wsclean: bool = False) -> dict:
    """A PATH with stand-ins and the needed tools only; returns the environment."""
    bin_dir = tmp_path / "bin"
    tools = tmp_path / "tools"
    bin_dir.mkdir()
    tools.mkdir()
    for name in TOOLS:
        found = shutil.which(name)
        assert found, f"{name} is needed to run the set-up step"
        (tools / name).symlink_to(found)
    calls = tmp_path / "apt-get.calls"
    # one line per call: the arguments, then what the environment carried
    _write_script(bin_dir / "apt-get", f"""
printf '%s|DEBIAN_FRONTEND=%s|SUDO_USER=%s\\n' "$*" "${{DEBIAN_FRONTEND-}}" "${{SUDO_USER-}}" >> {calls}
if [ "$1" = install ]; then
    for package in "$@"; do    # each package's command appears, as Debian's would
        case $package in
        wsclean) command=wsclean ;;
        chromium) command=chromium ;;
        chromium-driver) command=chromedriver ;;
        *) continue ;;
        esac
        printf '#!/bin/bash\\necho "%s (stand-in)"\\n' "$command" > {bin_dir}/$command
        /bin/chmod +x {bin_dir}/$command
    done
fi
""")
    _write_script(bin_dir / "id", f"""
[ "$1" = -u ] || {{ echo "id stand-in: only -u" >&2; exit 2; }}
echo {uid}
""")
    if sudo:
        # like sudo: VAR=value arguments are set, the caller's environment is
        # reset, SUDO_USER names the caller
        _write_script(bin_dir / "sudo", f"""
printf '%s\\n' "$*" >> {tmp_path / 'sudo.calls'}
exec /usr/bin/env -i PATH="$PATH" SUDO_USER=tester "$@"
""")
    if wsclean:
        _write_script(bin_dir / "wsclean", 'echo "WSClean version 3.1 (stand-in)"\n')
    path = f"{bin_dir}:{tools}"
    # the Makefile puts $VENV/bin first; neither it nor our PATH may hold a real wsclean
    assert wsclean or shutil.which("wsclean", path=f"{ROOT / '.venv' / 'bin'}:{path}") is None
    return {"PATH": path, "HOME": str(tmp_path), "LC_ALL": "C",
            # the step's log goes to $VENV/setup.log: keep the stand-ins' lines out of .venv's
            "VENV": str(tmp_path / "venv")}


def _make_wsclean(env: dict, target: str = "wsclean") -> subprocess.CompletedProcess:
    return subprocess.run([shutil.which("make"), "--no-print-directory", "-C", str(ROOT), target],
                          env=env, capture_output=True, text=True, timeout=60)


def _apt_calls(tmp_path: Path) -> list[str]:
    calls = tmp_path / "apt-get.calls"
    return calls.read_text().splitlines() if calls.exists() else []


def _user_lines(stderr: str) -> list[str]:
    """stderr without make's own "make: *** [...] Error 1" trailer."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith("make: ***")]


def test_wsclean_installed_as_root_without_sudo(tmp_path):
    env = _machine(tmp_path, uid=0, sudo=False)
    done = _make_wsclean(env)
    assert done.returncode == 0, done.stderr
    calls = _apt_calls(tmp_path)
    assert [c.split("|")[0] for c in calls] == ["update -q", "install -y -q wsclean"]
    for call in calls:
        assert "|DEBIAN_FRONTEND=noninteractive|" in call
        assert call.endswith("|SUDO_USER=")  # apt-get called directly
    assert not (tmp_path / "sudo.calls").exists()


def test_wsclean_installed_through_sudo_when_not_root(tmp_path):
    env = _machine(tmp_path, uid=1000, sudo=True)
    done = _make_wsclean(env)
    assert done.returncode == 0, done.stderr
    calls = _apt_calls(tmp_path)
    assert [c.split("|")[0] for c in calls] == ["update -q", "install -y -q wsclean"]
    for call in calls:
        # DEBIAN_FRONTEND survived sudo's environment reset
        assert call.endswith("|DEBIAN_FRONTEND=noninteractive|SUDO_USER=tester")
    assert len((tmp_path / "sudo.calls").read_text().splitlines()) == 2


def test_wsclean_missing_without_root_or_sudo_is_one_clear_error(tmp_path):
    env = _machine(tmp_path, uid=1000, sudo=False)
    done = _make_wsclean(env)
    assert done.returncode != 0
    lines = _user_lines(done.stderr)
    assert len(lines) == 1, done.stderr
    # names what failed and the remedy
    assert "WSClean" in lines[0] and "root" in lines[0] and "apt-get install wsclean" in lines[0]
    assert _apt_calls(tmp_path) == []


def test_wsclean_present_is_left_alone(tmp_path):
    env = _machine(tmp_path, uid=0, sudo=False, wsclean=True)
    done = _make_wsclean(env)
    assert done.returncode == 0, done.stderr
    assert _apt_calls(tmp_path) == []
    assert "WSClean found" in done.stdout


def test_browser_installed_when_missing_and_left_alone_when_present(tmp_path):
    env = _machine(tmp_path, uid=0, sudo=False)
    # the browser alone is there: its WebDriver is still missing, so both are installed
    _write_script(tmp_path / "bin" / "chromium", 'echo "Chromium (stand-in)"\n')
    done = _make_wsclean(env, "browser")
    assert done.returncode == 0, done.stderr
    assert [c.split("|")[0] for c in _apt_calls(tmp_path)] == [
        "update -q", "install -y -q chromium chromium-driver"]
    again = _make_wsclean(env, "browser")
    assert again.returncode == 0 and "Chromium found" in again.stdout
    assert len(_apt_calls(tmp_path)) == 2          # nothing more installed


def test_casa_config_and_numba_cache_on_a_fresh_machine(tmp_path):
    # A second environment that never had the configuration, sharing this
    # environment's installed packages (hitops, casatools, casadata) through a
    # .pth file instead of a 2 GB reinstall; sys.prefix is its own.
    venv = tmp_path / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    shared = sysconfig.get_paths()["purelib"]
    (Path(purelib) / "hitops-shared.pth").write_text(f"import site; site.addsitedir({shared!r})\n")

    home, cache = tmp_path / "home", tmp_path / "cache"
    home.mkdir()
    cache.mkdir()
    keep = ("PATH", "LANG", "LC_ALL", "TMPDIR")
    env = {k: v for k, v in os.environ.items() if k in keep}
    # no CASASITECONFIG, HITOPS_CASA_CONFIG or NUMBA_CACHE_DIR from the caller (make test sets some)
    env.update(HOME=str(home), XDG_CACHE_HOME=str(cache), VENV=str(venv))

    done = subprocess.run(["bash", str(ROOT / "scripts" / "setup.sh"), "casa-config", "numba-cache"],
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert len(done.stdout.splitlines()) == 2, done.stdout  # one line per step

    config = venv / "etc" / "hitops" / "casasiteconfig.py"
    text = config.read_text()
    import casadata
    assert f"measurespath = {str(Path(casadata.__file__).parent / '__data__')!r}" in text
    assert "measures_auto_update = False" in text and "data_auto_update = False" in text
    assert (venv / "numba-cache").is_dir()
    # nothing per user: not the old ~/.cache/hitops, not CASA's ~/.casa/config.py
    assert not (cache / "hitops").exists() and not (home / ".cache" / "hitops").exists()
    assert not (home / ".casa" / "config.py").exists()

    imported = subprocess.run(
        [str(py), "-c", "from hitops.casa_env import ensure_casa_offline; print(ensure_casa_offline()); "
                        "import casatools; print(casatools.version_string())"],
        env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert imported.returncode == 0, imported.stderr
    printed = imported.stdout.splitlines()
    assert printed[0] == str(config)
    assert printed[-1].startswith("6.7")
