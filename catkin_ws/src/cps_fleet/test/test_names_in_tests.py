"""Tests speak the names contract (issue 33): no test, test support (cps_harness) or benchmark spells
a graph name of the contract by hand; they build it from `cps_fleet.names`, so that a renamed topic
is renamed everywhere at once. The scan reads every string in the code (docstrings are prose and
left alone) and fails naming file:line for each name of the contract it finds:

- a name of the digital tissue or twin (`/tissue/...`, `/twin/...`, also under another namespace),
- one of the contract's absolute names (`/fleet/estop`, `/tf`, `/diagnostics`, ...),
- a robot's name (`/scout/odom`, `{r}/points_filtered/draco`, `scout/base_link`, ...): any
  `<namespace>/<name>` whose name is one of names.py's relative names,
- an absolute name put together by hand from the module (`f"/{r}/{names.ODOM}"`),
- the fixed frame `"map"`.

Only where the name itself is what a test tests may it be spelled: ALLOWED lists those places."""

import ast
import os
import re

from cps_fleet import names

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", ".."))
SRC = os.path.join(ROOT, "catkin_ws", "src")

# (file relative to the repository, function or "" for the whole file): why it spells names.
ALLOWED = {
    ("catkin_ws/src/cps_fleet/test/test_names_in_tests.py", ""): "the scan's own patterns and examples",
}

# Names of the module that are not a robot's, a map server's or a node's port: found by the other
# patterns (tissue, twin), or words too common to be a name on their own.
_NOT_A_ROBOT_NAME = {"MAP_FRAME", "TWIN_NS", "COMPRESSED_SUFFIX", "TISSUE_NODELET_MANAGER", "MAP_SERVER"}


def _relative_names():
    """Every relative name of names.py (`odom`, `points_filtered/draco`, `cloud_throttle/status`,
    the map server's `octomap_binary`, its private `ready` as `map_server/ready`, the base frame)."""
    found = {names.base_frame("r").split("/", 1)[1]}
    for key, value in vars(names).items():
        if not key.isupper() or not isinstance(value, str) or key in _NOT_A_ROBOT_NAME:
            continue
        if value.startswith("~"):
            found |= {f"{node}/{value[1:]}" for node in (names.MAP_SERVER, names.CLOUD_THROTTLE)}
        elif not value.startswith("/") and not value.startswith(("tissue/", "twin/")):
            found.add(value)
    return sorted(found, key=len, reverse=True)


def _absolute_names():
    """The module's absolute names, and the root namespace's nodes it names."""
    found = {v for k, v in vars(names).items() if k.isupper() and isinstance(v, str) and v.startswith("/")}
    return sorted(found | {names.absolute(names.TISSUE_NODELET_MANAGER)}, key=len, reverse=True)


_SEGMENT = r"[\w{}\[\]().'\"]+"  # one segment of a name, or an f-string's placeholder
_END = r"(?![\w.-])"
PATTERNS = (
    ("the tissue's or twin's", re.compile(rf"/(?:{names.TWIN_NS}|tissue){_END}")),
    ("the tissue's or twin's", re.compile(rf"(?<![\w./-])(?:{names.TWIN_NS}|tissue)/\w")),
    ("an absolute", re.compile(rf"(?<![\w.-])(?:{'|'.join(map(re.escape, _absolute_names()))}){_END}(?!/)")),
    ("a robot's", re.compile(rf"(?<![\w.-])/?(?:{_SEGMENT}/)+(?:{'|'.join(map(re.escape, _relative_names()))}){_END}")),
    ("a hand-built", re.compile(r"(?<![\w.-])/\{[^}]*\}.*\{names\.|(?<![\w.-])/\{names\.")),
)
FRAME_KEYWORDS = {"frame_id", "child_frame_id", "frame", "target_frame", "source_frame", "fixed_frame"}


def scanned_files():
    """Every test file, the conftests, cps_harness's support code and nodes, and the benchmarks."""
    found = []
    for top, dirs, files in os.walk(SRC):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        rel = os.path.relpath(top, SRC).split(os.sep)
        in_test = "test" in rel[1:]
        in_harness = rel[0] == "cps_harness" and len(rel) > 1 and rel[1] in ("src", "nodes")
        for name in sorted(files):
            path = os.path.join(top, name)
            if name.endswith(".py") and (in_test or in_harness or top == SRC):
                found.append(path)
            elif in_harness and rel[1] == "nodes":
                found.append(path)
    for top, dirs, files in os.walk(os.path.join(ROOT, "bench")):
        dirs[:] = sorted(d for d in dirs if d not in ("out", "__pycache__"))
        found += [os.path.join(top, n) for n in sorted(files) if n.endswith(".py")]
    return found


def _docstrings(tree):
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                yield first.value


def _text(node):
    """A string's text; an f-string's with each placeholder as `{its source}`."""
    if isinstance(node, ast.Constant):
        return node.value
    return "".join(
        part.value if isinstance(part, ast.Constant) else "{" + ast.unparse(part.value) + "}" for part in node.values
    )


def _is_map_frame(node, parent):
    """`"map"` where it is a frame: not a dict's key or value, an index, or another keyword's value."""
    if isinstance(parent, ast.Dict) or isinstance(parent, ast.Subscript):
        return False
    if isinstance(parent, ast.keyword):
        return parent.arg in FRAME_KEYWORDS
    return True


def literals(path):
    """(line, function, pattern, text) of every contract name spelled in the file at `path`, in
    the order of the lines."""
    return sorted(_literals(path))


def _literals(path):
    with open(path, encoding="utf-8") as stream:
        tree = ast.parse(stream.read(), path)
    skip = {id(d) for d in _docstrings(tree)}
    parents = {}
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            parents[id(child)] = node
            if isinstance(node, ast.JoinedStr):
                skip.add(id(child))  # read as part of the f-string

    def function_of(node):
        while id(node) in parents:
            node = parents[id(node)]
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                return node.name
        return ""

    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        is_string = isinstance(node, ast.Constant) and isinstance(node.value, str)
        if not (is_string or isinstance(node, ast.JoinedStr)):
            continue
        text = _text(node)
        if text == names.MAP_FRAME and _is_map_frame(node, parents.get(id(node))):
            yield node.lineno, function_of(node), "the fixed frame", text
            continue
        for kind, pattern in PATTERNS:
            match = pattern.search(text)
            if match:
                yield node.lineno, function_of(node), f"{kind} name {match.group(0)!r}", text
                break


def test_no_test_spells_a_graph_name():
    found = []
    for path in scanned_files():
        rel = os.path.relpath(path, ROOT)
        if (rel, "") in ALLOWED:
            continue
        for line, function, what, _ in literals(path):
            if (rel, function) not in ALLOWED:
                found.append(f"{rel}:{line}: {what} (use cps_fleet.names)")
    assert not found, f"{len(found)} graph names spelled by hand:\n" + "\n".join(found)


def test_the_scan_finds_each_kind_and_leaves_the_rest(tmp_path):
    path = tmp_path / "test_sample.py"
    path.write_text(
        '"""A docstring may say /tissue/stats and /scout/odom."""\n'
        'a = "/tissue/stats"\n'
        'b = f"/twin/{r}/points"\n'
        'c = f"/{robot}/points_filtered/draco:=/{robot}/points_filtered/draco/managed"\n'
        'd = "/fleet/estop"\n'
        'e = "scout/base_link"\n'
        'f = f"/{r}/{names.ODOM}"\n'
        'g = "/ts_test/tissue/stats"\n'
        'h = "python -c \\"rospy.Publisher(\'/jackal/cmd_vel/teleop\', Twist)\\""\n'
        'header.frame_id = "map"\n'
        'ok = ["/proc/1/stat", "/tmp/x/points.npz", "/writer/out", "~input:=/bench/in", {"map": 1}]\n'
        'ok2 = Marker(ns="map"), names.absolute(names.robot_topic(r, names.ODOM)), "runs/link_thesis"\n'
    )
    lines = [line for line, _, _, _ in literals(str(path))]
    assert lines == [2, 3, 4, 5, 6, 7, 8, 9, 10]


def test_the_scan_reads_every_kind_of_file():
    rel = {os.path.relpath(p, ROOT) for p in scanned_files()}
    assert "catkin_ws/src/conftest.py" in rel and "catkin_ws/src/cps_harness/nodes/link_watch" in rel
    assert "catkin_ws/src/cps_harness/src/cps_harness/mission.py" in rel and "bench/tissue_bench.py" in rel
    assert "catkin_ws/src/cps_sim/test/clock_step/sitecustomize.py" in rel
    assert not any(p.startswith("catkin_ws/src/cps_fleet/src/") for p in rel)


def test_every_allowed_place_exists():
    rel = {os.path.relpath(p, ROOT): p for p in scanned_files()}
    for file, function in ALLOWED:
        assert file in rel, file
        if function:
            assert any(f == function for _, f, _, _ in literals(rel[file])), (file, function)
