"""Reading what the Foxglove output wrote, independently of foxglove-sdk: protobuf messages
decoded with the schema (a FileDescriptorSet) the channel itself carries, MCAP read with the
``mcap`` reader, and the live server spoken to over a WebSocket (Foxglove WebSocket protocol:
subprotocol ``foxglove.sdk.v1``, JSON ``serverInfo``/``advertise``, ``subscribe`` with
subscription ids, binary message data = opcode 0x01, uint32 subscription id, uint64 log time
(little-endian), payload)."""

from __future__ import annotations

import base64
import json
import struct
import time

UNKNOWN_CHANNEL = "Unknown channel ID: "  # foxglove-sdk's status message for a subscription it refused


def decode(schema_name: str, schema_encoding: str, schema: bytes, data: bytes):
    """One message as a protobuf object (or a dict for JSON channels)."""
    if schema_encoding == "jsonschema":
        return json.loads(data)
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    assert schema_encoding == "protobuf", schema_encoding
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name)).FromString(data)


def read_mcap(path) -> tuple[dict, dict]:
    """(topic -> (schema name, schema encoding, message encoding), topic -> [decoded messages])."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.topic: (summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding,
                              c.message_encoding) for c in summary.channels.values()}
        messages: dict = {}
        for schema, channel, message in reader.iter_messages():
            messages.setdefault(channel.topic, []).append(
                (message.log_time, decode(schema.name, schema.encoding, schema.data, message.data)))
    return channels, messages


class LiveClient:
    """A WebSocket client of the live server: collects advertised channels, subscribes to
    them all and decodes what arrives."""

    def __init__(self, port: int, timeout_s: float = 5.0):
        import websocket

        self.ws = websocket.create_connection(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                              timeout=timeout_s)
        self.server_info = None
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self.messages: dict[str, list] = {}
        self.retries = 0  # subscriptions the server refused and this client sent again

    def poll(self, until, timeout_s: float = 5.0) -> None:
        """Handle frames until ``until(self)`` holds; subscribes to every channel advertised."""
        import websocket

        deadline = time.monotonic() + timeout_s
        while not until(self):
            if time.monotonic() > deadline:
                raise TimeoutError(f"have {sorted(self.messages)} of "
                                   f"{sorted(c['topic'] for c in self.channels.values())}")
            self.ws.settimeout(max(0.05, deadline - time.monotonic()))
            try:
                opcode, data = self.ws.recv_data()
            except websocket.WebSocketTimeoutException:
                continue
            if opcode == websocket.ABNF.OPCODE_TEXT:
                self._text(json.loads(data))
            elif opcode == websocket.ABNF.OPCODE_BINARY and data[0] == 0x01:
                subscription, log_time = struct.unpack_from("<IQ", data, 1)
                channel = self.channels[self.subscriptions[subscription]]
                schema = channel["schema"]
                raw = base64.b64decode(schema) if channel["schemaEncoding"] == "protobuf" else schema.encode()
                self.messages.setdefault(channel["topic"], []).append(
                    (log_time, decode(channel["schemaName"], channel["schemaEncoding"], raw, bytes(data[13:]))))

    def _text(self, msg: dict) -> None:
        if msg["op"] == "serverInfo":
            self.server_info = msg
        elif msg["op"] == "advertise":
            for channel in msg["channels"]:
                self.channels[channel["id"]] = channel
            self._subscribe([channel["id"] for channel in msg["channels"]])
        elif msg["op"] == "status" and msg.get("message", "").startswith(UNKNOWN_CHANNEL):
            # foxglove-sdk 0.30.3's server can refuse a subscription that arrives while the channel
            # it has just advertised is still being registered; it says so, and by then it knows the
            # channel: subscribe again, as a viewer would (seen once in CI, 2026-11).
            channel_id = int(msg["message"].removeprefix(UNKNOWN_CHANNEL))
            if channel_id in self.channels and self.retries < 10:
                self.retries += 1
                time.sleep(0.05)
                self._subscribe([channel_id])

    def _subscribe(self, channel_ids: list[int]) -> None:
        new = []
        for channel_id in channel_ids:
            sub_id = len(self.subscriptions) + 1
            self.subscriptions[sub_id] = channel_id
            new.append({"id": sub_id, "channelId": channel_id})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))

    def topics(self) -> dict[str, dict]:
        return {c["topic"]: c for c in self.channels.values()}

    def close(self) -> None:
        self.ws.close()
