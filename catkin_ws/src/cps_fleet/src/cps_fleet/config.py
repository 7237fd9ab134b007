"""YAML configuration files with errors that name the file, the line and what is wrong.

`load_yaml_document` parses a file into plain dicts/lists and remembers where every value
came from, so that the validators in `cps_fleet.fleet` (and any package's own config reader)
can say ``fleet.yaml:12: robots[1].type: unknown robot type 'tank' (known: ...)``.
"""

import difflib
import math
import os

import yaml


class ConfigError(ValueError):
    """A configuration file is missing, malformed or holds a value that is not allowed."""

    def __init__(self, path, line, message):
        self.path = path
        self.line = line
        self.message = message
        where = f"{path}:{line}" if line else str(path)
        super().__init__(f"{where}: {message}")


class Document:
    """A parsed YAML file: its data and the line of every key path in it."""

    def __init__(self, path, data, lines):
        self.path = path
        self.data = data
        self._lines = lines

    def line(self, key_path):
        """1-based line of `key_path` (a tuple of keys and indices), or of its nearest parent."""
        key_path = tuple(key_path)
        while key_path not in self._lines and key_path:
            key_path = key_path[:-1]
        return self._lines.get(key_path, 1)

    def error(self, key_path, message):
        name = _dotted(key_path)
        return ConfigError(self.path, self.line(key_path), f"{name}: {message}" if name else message)


def _dotted(key_path):
    out = ""
    for key in key_path:
        out += f"[{key}]" if isinstance(key, int) else (f".{key}" if out else str(key))
    return out


def load_yaml_document(path):
    """Parse `path`; raise ConfigError for a missing file, a YAML syntax error or a non-mapping top."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as stream:
            text = stream.read()
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read file: {exc.strerror}") from exc
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(path, mark.line + 1 if mark else None, f"YAML syntax error: {problem}") from exc
    if root is None:
        raise ConfigError(path, None, "file is empty")
    lines = {}
    data = _construct(root, (), lines)
    if not isinstance(data, dict):
        raise ConfigError(path, root.start_mark.line + 1, "top level must be a mapping")
    return Document(path, data, lines)


def _construct(node, key_path, lines):
    lines[key_path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        out = {}
        for key_node, value_node in node.value:
            key = key_node.value
            out[key] = _construct(value_node, key_path + (key,), lines)
            lines[key_path + (key,)] = key_node.start_mark.line + 1
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_construct(child, key_path + (i,), lines) for i, child in enumerate(node.value)]
    loader = yaml.SafeLoader("")
    try:
        return loader.construct_object(node, deep=True)
    finally:
        loader.dispose()


class Reader:
    """Typed access to one mapping of a Document, raising ConfigError with the line."""

    def __init__(self, document, key_path=()):
        self.doc = document
        self.key_path = tuple(key_path)
        value = document.data
        for key in self.key_path:
            value = value[key]
        if not isinstance(value, dict):
            raise document.error(self.key_path, "must be a mapping")
        self.value = value

    def has(self, key):
        return key in self.value

    def known_keys(self, *keys):
        """This reader, if every key of its mapping is one of `keys`; else ConfigError at the first
        unknown one (a typo, or a setting nothing reads), naming the nearest known key."""
        for key in self.value:
            if key not in keys:
                near = difflib.get_close_matches(str(key), keys, n=1)
                hint = f" (did you mean '{near[0]}'?)" if near else ""
                raise self.error(key, f"unknown key '{key}'{hint}; known keys: {', '.join(keys)}")
        return self

    def child(self, key, required=True):
        if key not in self.value:
            if required:
                raise self.doc.error(self.key_path, f"missing key '{key}'")
            return None
        return Reader(self.doc, self.key_path + (key,))

    def items(self, key):
        """Readers over a list of mappings under `key`."""
        value = self.get(key, list)
        return [Reader(self.doc, self.key_path + (key, i)) for i in range(len(value))]

    def get(self, key, kind, default=None, required=None):
        if required is None:
            required = default is None
        if key not in self.value:
            if required:
                raise self.doc.error(self.key_path, f"missing key '{key}'")
            return default
        value = self.value[key]
        path = self.key_path + (key,)
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise self.doc.error(path, f"must be a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise self.doc.error(path, f"must be finite, got {value!r}")
            return value
        if kind is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise self.doc.error(path, f"must be an integer, got {value!r}")
            return value
        if kind is bool:
            if not isinstance(value, bool):
                raise self.doc.error(path, f"must be true or false, got {value!r}")
            return value
        if kind is str:
            if not isinstance(value, str) or not value:
                raise self.doc.error(path, f"must be a non-empty string, got {value!r}")
            return value
        if not isinstance(value, kind):
            raise self.doc.error(path, f"must be a {kind.__name__}, got {type(value).__name__}")
        return value

    def number(self, key, default=None, low=None, high=None, low_open=False):
        """A finite float within [low, high] (or (low, high] with low_open)."""
        value = self.get(key, float, default)
        if value is None:
            return None
        too_low = low is not None and (value <= low if low_open else value < low)
        if too_low or (high is not None and value > high):
            bracket = "(" if low_open else "["
            raise self.doc.error(self.key_path + (key,), f"{value} is outside {bracket}{low}, {high}]")
        return value

    def error(self, key, message):
        return self.doc.error(self.key_path + ((key,) if key is not None else ()), message)

    def path_of(self, key):
        """A path value resolved relative to the file's folder."""
        relative = self.get(key, str)
        return os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(self.doc.path)), relative))
