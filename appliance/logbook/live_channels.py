"""The live view's channels, known before the first message: every topic a session or a traverse
writes (:data:`topics.PROTO_TOPIC_SCHEMAS`, :data:`topics.JSON_TOPIC_SCHEMAS`) with exactly the
schema the logbook registers for it in the MCAP file.

The live view creates them all before its server listens.  foxglove-sdk advertises a channel created
while a client is connected by queueing the advertisement and only then recording the channel as
advertised to that client, so a fast client's subscription can arrive in between and be refused
("Unknown channel ID"); the channels that exist when a client connects are advertised before the
server reads anything from it, so that client cannot be refused.
"""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass

from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap_protobuf.schema import build_file_descriptor_set

from appliance.logbook.topics import JSON_SCHEMAS, JSON_TOPIC_SCHEMAS, PROTO_TOPIC_SCHEMAS


@dataclass(frozen=True)
class ChannelSpec:
    """One topic's channel as the logbook writes it: names and encodings as in the MCAP file."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str


def proto_schema_data(schema_name: str) -> bytes:
    """The serialized FileDescriptorSet of the Foxglove protobuf schema ``schema_name`` (``foxglove.Log``),
    as the logbook registers it."""
    short = schema_name.removeprefix("foxglove.")
    module = importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2")
    return bytes(build_file_descriptor_set(getattr(module, short)).SerializeToString())


def json_schema_data(schema_name: str) -> bytes:
    """The JSON schema ``schema_name`` (``viper.Capture``) as the logbook registers it."""
    return json.dumps(JSON_SCHEMAS[schema_name]).encode()


def session_channels() -> list[ChannelSpec]:
    """Every topic a session or a traverse may write, sorted by topic."""
    specs = [ChannelSpec(topic, name, SchemaEncoding.Protobuf, proto_schema_data(name), MessageEncoding.Protobuf)
             for topic, name in PROTO_TOPIC_SCHEMAS.items()]
    specs += [ChannelSpec(topic, name, SchemaEncoding.JSONSchema, json_schema_data(name), MessageEncoding.JSON)
              for topic, name in JSON_TOPIC_SCHEMAS.items()]
    return sorted(specs, key=lambda s: s.topic)
