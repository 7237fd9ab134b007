"""A recorded MCAP read back as a viewer reads it, for tests and benchmarks: the PyPI `mcap`
reader and `mcap-ros1-support`'s decoder, which builds each message class from the definition
stored in the file (not from the classes installed here). Every message of every channel is
decoded; what fails is listed, never raised."""

import dataclasses
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
