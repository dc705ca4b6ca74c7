"""Decoders independent of the code that wrote the files: Google's protobuf runtime for Foxglove's schemas."""

from __future__ import annotations

import base64
from typing import Any


def protobuf_class(schema_name: str, file_descriptor_set: bytes) -> Any:
    """A message class built by Google's protobuf runtime from a schema's FileDescriptorSet (a decoder independent
    of the foxglove SDK that wrote it)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def ws_schema_class(channel: dict[str, Any]) -> Any:
    assert channel["schemaEncoding"] == "protobuf"
    return protobuf_class(channel["schemaName"], base64.b64decode(channel["schema"]))
