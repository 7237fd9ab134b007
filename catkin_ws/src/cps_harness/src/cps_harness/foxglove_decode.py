"""Foxglove SDK messages read back the way a viewer reads them: encoded, then decoded with the
schema they carry (its protobuf FileDescriptorSet) by the protobuf runtime, for tests. The SDK's
own message objects cannot be read field by field."""

import functools

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory


@functools.lru_cache(maxsize=None)
def _message_class(name: str, schema: bytes):
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def decode(message):
    """A foxglove.messages object as the protobuf message a viewer decodes from its bytes."""
    schema = message.get_schema()
    assert schema.encoding == "protobuf", schema.encoding
    return _message_class(schema.name, bytes(schema.data)).FromString(message.encode())


def decode_bytes(schema_name: str, schema: bytes, data: bytes):
    """Bytes logged on a channel with the protobuf `schema` named `schema_name`, decoded."""
    return _message_class(schema_name, bytes(schema)).FromString(data)
