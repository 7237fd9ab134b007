"""write_atomically: the old file stays whole when a write fails, and no temporary file is left."""

import pytest

from cps_mapping.atomic_file import write_atomically

pytestmark = pytest.mark.unit


def test_a_write_replaces_the_file_whole(tmp_path):
    path = tmp_path / "a.json"
    write_atomically(str(path), lambda s: s.write("new"), binary=False)
    assert path.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "a.bin"
    path.write_bytes(b"old")

    def fails(stream):
        stream.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_atomically(str(path), fails)
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["a.bin"]
