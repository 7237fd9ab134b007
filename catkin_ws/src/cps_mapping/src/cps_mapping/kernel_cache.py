"""The map server's numba kernels, cached by what they compile and built where the code is built.

numba's own cache (`cache=True`) finds a kernel by its source file's path and trusts it only while
the file's mtime and size are unchanged: a second checkout, an install space or a `git checkout`
that touches the file cannot use kernels another one compiled, and the map server compiled for
20-70 s at its start while the robots' clouds arrived (issue 29).

Here a module's kernels live in `<its folder>/__pycache__/numba_kernels/<key>/`, key = SHA-256 of
the module's source + numba's version + Python's version, and numba's freshness stamp is that same
hash: any copy of the same source, at any path and with any mtime, finds the same kernels, and an
edited source finds none (never stale ones). `build()` compiles them (ci/setup.sh, `catkin_make
install`, and bringup before a mission when they are missing); the nodes, which may run as
`nobody`, only read them: a kernel missing from a folder they cannot write is compiled in memory
and not saved (`compiled_kernels()` names it, the map server reports it).

Usage: `@kernel_cache.njit(nogil=True)` in place of `@numba.njit(cache=True, nogil=True)`.
"""

import hashlib
import os
import sys

import numba
from numba.core.caching import CompileResultCacheImpl, FunctionCache, _CacheLocator

KERNEL_FOLDER = os.path.join("__pycache__", "numba_kernels")
# Written by build() once every kernel of the module is in the folder.
BUILT_MARKER = "BUILT"
# The module whose kernels build() compiles (the map server's ray casting and .bt writer).
MAP_KERNELS_MODULE = "cps_mapping.log_odds_grid"

_KERNELS = []  # every dispatcher made by njit() in this process


def source_key(py_file):
    """What a module's kernels are compiled from: its source's hash, numba's and Python's versions."""
    with open(py_file, "rb") as stream:
        digest = hashlib.sha256(stream.read()).hexdigest()[:24]
    return f"{digest}-numba{numba.__version__}-py{sys.version_info[0]}{sys.version_info[1]}"


def cache_dir(py_file):
    """The folder of `py_file`'s kernels for its current content."""
    return os.path.join(os.path.dirname(os.path.abspath(py_file)), KERNEL_FOLDER, source_key(py_file))


class _ContentKeyedLocator(_CacheLocator):
    """numba's cache locator keyed by content: the folder and the freshness stamp come from
    `source_key`, never from the path or the mtime."""

    def __init__(self, py_func, py_file):
        self._lineno = py_func.__code__.co_firstlineno
        self._key = source_key(py_file)
        self._cache_path = cache_dir(py_file)

    def ensure_cache_path(self):
        os.makedirs(self._cache_path, exist_ok=True)  # no write probe: a reader never writes (see save_overload)

    def get_cache_path(self):
        return self._cache_path

    def get_source_stamp(self):
        return self._key

    def get_disambiguator(self):
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file):
        return cls(py_func, py_file)


class _ContentKeyedImpl(CompileResultCacheImpl):
    _locator_classes = [_ContentKeyedLocator]


class _KernelCache(FunctionCache):
    """FunctionCache in the content-keyed folder; a kernel compiled by a process that cannot write
    the folder (a node run as `nobody`) is kept in memory only, never an error."""

    _impl_class = _ContentKeyedImpl

    def save_overload(self, sig, data):
        try:
            self._impl.locator.ensure_cache_path()
        except OSError:
            return
        if os.access(self._cache_path, os.W_OK):
            super().save_overload(sig, data)


def njit(**options):
    """numba.njit whose machine code is cached by content (this module's docstring)."""

    def wrap(py_func):
        dispatcher = numba.njit(**options)(py_func)
        dispatcher._cache = _KernelCache(dispatcher.py_func)
        _KERNELS.append(dispatcher)
        return dispatcher

    return wrap


def compiled_kernels():
    """Names of the kernels this process compiled (rather than loaded from the cache)."""
    return tuple(sorted({d.py_func.__name__ for d in _KERNELS if d.stats.cache_misses}))


def map_kernels_file():
    """The source file of the map server's kernels, found without importing numba's work."""
    import importlib.util

    return importlib.util.find_spec(MAP_KERNELS_MODULE).origin


def is_built(py_file=None):
    """True when the kernels of `py_file` (default: the map server's) are in its cache folder."""
    return os.path.exists(os.path.join(cache_dir(py_file or map_kernels_file()), BUILT_MARKER))
