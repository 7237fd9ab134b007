"""Files a reader never sees half-written, and two writers never trip over.

`write_atomically(path, write, binary)` writes through `write(stream)` into a temporary file of a
unique name in `path`'s folder, then renames it over `path`. A fixed temporary name (`path.tmp`)
is not enough: the map server's autosave and a save request can write the same map's sidecars at
once, and the second rename then finds its temporary file already moved away (a lost map).
"""

import os
import tempfile


def write_atomically(path, write, binary=True):
    """Write `path` through `write(stream)`, replacing it in one rename; OSError if it cannot."""
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb" if binary else "w") as stream:
            write(stream)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path
