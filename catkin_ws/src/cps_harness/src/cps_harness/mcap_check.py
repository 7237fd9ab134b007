"""A recorded MCAP read back as a viewer reads it, for tests and benchmarks: the PyPI `mcap`
reader and `mcap-ros1-support`'s decoder, which builds each message class from the definition
stored in the file (not from the classes installed here). Every message of every channel is
decoded; what fails is listed, never raised.

`npm_read` reads it with readers no one here wrote and that share no code with our writer: the npm
libraries Foxglove and Lichtblick read MCAP with (js/mcap_read.js), installed by
cps_harness.foxglove_probe's installer at pinned versions. (The PyPI `rosbags` reader, which the
issue also names, reads only ROS 2 MCAP: it refuses a `ros1` profile.)
"""

import dataclasses
import json
import os
import subprocess
from collections import defaultdict
from typing import Dict, List

from mcap.reader import make_reader
from mcap_ros1.decoder import DecoderFactory


@dataclasses.dataclass
class McapContents:
    profile: str
    types: Dict[str, str]  # topic -> ROS type (the channel's schema name)
    messages: Dict[str, List[object]]  # topic -> decoded messages, in log order
    errors: List[str]


def read_ros1_mcap(path: str, keep=None) -> McapContents:
    """Decode every message of `path`; `keep(topic)` False: decoded and counted but not kept."""
    messages, types, errors = defaultdict(list), {}, []
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        profile = reader.get_header().profile
        for schema, channel, _message, decoded in reader.iter_decoded_messages(log_time_order=True):
            types[channel.topic] = schema.name if schema else ""
            if channel.message_encoding != "ros1" or schema is None or schema.encoding != "ros1msg":
                errors.append(
                    f"{channel.topic}: encoding {channel.message_encoding}, schema {schema and schema.encoding}"
                )
                continue
            if keep is None or keep(channel.topic):
                messages[channel.topic].append(decoded)
            else:
                messages[channel.topic].append(None)
    return McapContents(profile, types, dict(messages), errors)


# Foxglove's MCAP reader, its decompression (lz4, zstd: WebAssembly shipped in the npm packages) and
# its ROS 1 definition parser and message reader, pinned.
NPM_READER_PACKAGES = (
    "@mcap/core@2.2.2",
    "@mcap/nodejs@1.0.2",
    "@mcap/support@1.1.0",
    "@foxglove/rosmsg@5.0.5",
    "@foxglove/rosmsg-serialization@2.0.4",
)
READER_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "js", "mcap_read.js")
# The workspace's out/ (ignored by git), beside the Foxglove probe's client.
READER_FOLDER = os.path.join(os.path.dirname(os.path.abspath(__file__)), *[os.pardir] * 5, "out", "npm-mcap-reader")


def install_reader(folder: str = None) -> str:
    """The node_modules folder of NPM_READER_PACKAGES (installed on first use; ClientMissing if npm cannot)."""
    from cps_harness.foxglove_probe import install_client

    return install_client(folder or READER_FOLDER, packages=NPM_READER_PACKAGES)


def npm_read(path: str, modules: str = None, timeout_s: float = 600.0) -> dict:
    """The npm readers' report on the MCAP at `path`: profile, library, message_count (the file's
    statistics), per topic {type, messages, decoded, errors, first} and decode_errors in all."""
    modules = modules or install_reader()
    result = subprocess.run(
        ["node", READER_SCRIPT, str(path)],
        env={**os.environ, "NODE_PATH": modules},
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    if result.returncode != 0 or not result.stdout.strip():
        raise RuntimeError(f"the npm MCAP reader failed ({result.returncode}): {result.stderr.strip()[-800:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])
