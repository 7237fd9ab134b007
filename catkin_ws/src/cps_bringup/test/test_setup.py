"""ci/setup.sh (what `make setup` runs) on bad set-up input: it says what is wrong and how to fix it."""

import os
import shutil
import subprocess
import tempfile

import pytest

ROOT = os.environ.get("CPS_ROOT") or os.path.abspath(os.path.join(os.path.dirname(__file__), *[".."] * 4))
SETUP = os.path.join(ROOT, "ci", "setup.sh")
# A small Debian package that this project does not need and the machine does not have.
ABSENT_PACKAGE = "sl"


def _installed(package):
    result = subprocess.run(["dpkg-query", "-W", "-f=${Status}", package], capture_output=True, text=True)
    return result.stdout == "install ok installed"


@pytest.fixture
def absent_package_list():
    """A package list readable by an unprivileged user (pytest's tmp_path is root-only)."""
    if _installed(ABSENT_PACKAGE):
        pytest.skip(f"{ABSENT_PACKAGE} is installed here, so it cannot stand for a missing package")
    folder = tempfile.mkdtemp(prefix="cps-setup-test-")
    os.chmod(folder, 0o755)
    path = os.path.join(folder, "apt-packages.txt")
    with open(path, "w") as stream:
        stream.write(f"# test list\npython3-rospy\n{ABSENT_PACKAGE}\n")
    os.chmod(path, 0o644)
    yield path
    shutil.rmtree(folder, ignore_errors=True)


def test_a_run_after_a_run_installs_and_builds_nothing():
    first = subprocess.run(["bash", SETUP], capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    second = subprocess.run(["bash", SETUP], capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr
    assert second.stdout == "", second.stdout


def test_not_root_with_packages_missing_says_which_and_how(absent_package_list):
    if os.geteuid() != 0 or not shutil.which("runuser"):
        pytest.skip("needs root to run the script as an unprivileged user")
    result = subprocess.run(
        ["runuser", "-u", "nobody", "--", "env", f"CPS_APT_PACKAGES={absent_package_list}", "bash", SETUP],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    assert f"missing Debian packages: {ABSENT_PACKAGE}" in result.stderr
    assert f"sudo apt-get update && sudo apt-get install -y --no-install-recommends {ABSENT_PACKAGE}" in result.stderr


@pytest.mark.slow
def test_no_network_to_the_registries_is_named(absent_package_list):
    if os.geteuid() != 0 or not shutil.which("unshare"):
        pytest.skip("needs root and unshare for an empty network namespace")
    result = subprocess.run(
        ["unshare", "--net", "env", f"CPS_APT_PACKAGES={absent_package_list}", "bash", SETUP],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode != 0
    assert "no network to Debian's package mirrors" in result.stderr
    assert not _installed(ABSENT_PACKAGE)


@pytest.mark.slow
def test_broken_venv_is_rebuilt(tmp_path):
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to("/nonexistent/python3")
    # PIP_COMPILE=0 (pip's --no-compile; PIP_NO_COMPILE=1 would mean the opposite): the rebuilt venv's
    # packages without their .pyc, which no node of this throw-away venv will ever run to use. The
    # claim is the rebuild and the imports below; compiling ~3700 files of the wheels was 15 of its
    # 38 CPU-s of pip (2026-11-29, alone under the heavy lock: 40.8 s -> 25.2 s wall).
    env = {**os.environ, "CPS_VENV": str(venv), "PIP_COMPILE": "0"}
    result = subprocess.run(["bash", SETUP], env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout + result.stderr
    assert ".venv is broken" in result.stdout
    check = subprocess.run(
        [str(venv / "bin" / "python"), "-c", "import rospy, numpy, DracoPy, octomap, pybullet"],
        capture_output=True,
        text=True,
    )
    assert check.returncode == 0, check.stderr
