"""The workspace as a package set: one BSD-3-Clause LICENSE matching every package.xml, a
CHANGELOG.rst entry for every package's version, and an exec_depend for every third-party module
a package's code imports."""

import ast
import glob
import os
import re
import xml.etree.ElementTree as ET

import pytest

SRC = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", ".."))
ROOT = os.path.dirname(os.path.dirname(SRC))
PACKAGES = sorted(os.path.basename(os.path.dirname(p)) for p in glob.glob(os.path.join(SRC, "*", "package.xml")))

# Imported module -> its rosdep key: Debian's package where Debian 12 has it, `<name>-pip` otherwise.
ROSDEP_KEY = {
    "numpy": "python3-numpy",
    "yaml": "python3-yaml",
    "scipy": "python3-scipy",
    "matplotlib": "python3-matplotlib",
    "PIL": "python3-pil",
    "numba": "python3-numba",
    "pyqtgraph": "python3-pyqtgraph",
    "rospkg": "python3-rospkg",
    "DracoPy": "python3-dracopy-pip",
    "octomap": "python3-octomap-python-pip",
    "pybullet": "python3-pybullet-pip",
    "rospy": "rospy",
    "rosbag": "rosbag",
    "rosgraph": "rosgraph",
    "tf2_ros": "tf2_ros",
    "catkin": "catkin",
    "python_qt_binding": "python_qt_binding",
    "genpy": "genpy",
}


def _package_xml(package):
    return ET.parse(os.path.join(SRC, package, "package.xml")).getroot()


def _imports(package):
    """Top-level modules imported by the package's library and nodes (not its tests)."""
    files = glob.glob(os.path.join(SRC, package, "src", "**", "*.py"), recursive=True)
    files += glob.glob(os.path.join(SRC, package, "nodes", "*"))
    modules = set()
    for path in files:
        with open(path, encoding="utf-8") as stream:
            tree = ast.parse(stream.read(), path)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                modules.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                modules.add(node.module.split(".")[0])
    return modules


def test_one_bsd3_license_for_the_workspace():
    with open(os.path.join(ROOT, "LICENSE")) as stream:
        assert stream.readline().strip() == "BSD 3-Clause License"
    assert {_package_xml(p).findtext("license") for p in PACKAGES} == {"BSD-3-Clause"}


@pytest.mark.parametrize("package", PACKAGES)
def test_changelog_has_the_package_version(package):
    version = _package_xml(package).findtext("version")
    with open(os.path.join(SRC, package, "CHANGELOG.rst")) as stream:
        text = stream.read()
    assert f"Changelog for package {package}" in text
    assert re.search(rf"^{re.escape(version)} \(\d{{4}}-\d\d-\d\d\)$", text, re.M), version


@pytest.mark.parametrize("package", PACKAGES)
def test_every_imported_dependency_has_an_exec_depend(package):
    declared = {e.text for e in _package_xml(package) if e.tag in ("exec_depend", "depend")}
    needed = {ROSDEP_KEY[m] for m in _imports(package) if m in ROSDEP_KEY}
    # and every workspace package it imports: what a package.xml leaves out (cps_mapping no longer
    # lists cps_sim) its code must not import
    needed |= {m for m in _imports(package) if m in PACKAGES and m != package}
    assert needed <= declared, f"{package}/package.xml lacks exec_depend {sorted(needed - declared)}"


TEST_SUPPORT = "cps_harness"


@pytest.mark.parametrize("package", [p for p in PACKAGES if p != TEST_SUPPORT])
def test_test_support_stays_out_of_the_runtime_path(package):
    """A runtime package's library and nodes never import cps_harness (the tests' and benches'
    toolkit): a robot or twin never loads test support (the manager never loads the legacy
    estimator nor the simulated link, which live there). Nor does its package.xml declare it, even
    as a test_depend: the harness depends on the packages whose missions it runs, and catkin orders
    test dependencies like build dependencies (a cycle)."""
    declared = {e.text for e in _package_xml(package) if e.tag.endswith("depend")}
    assert TEST_SUPPORT not in _imports(package) and TEST_SUPPORT not in declared, package
