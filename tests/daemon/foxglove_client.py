"""A Foxglove WebSocket protocol client (foxglove.sdk.v1, the
SDK's name for foxglove.websocket.v1) for the viewer's tests and
bench: reads serverInfo and advertise, subscribes by topic, and decodes the binary messageData frames
(opcode 1, subscription id, timestamp, payload) with the protobuf schemas the server advertises."""

import base64
import json
import struct
import time

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
"""The SDK (0.30) speaks foxglove.sdk.v1, the successor of foxglove.websocket.v1 (same messages)."""
MESSAGE_DATA = 1


class FoxgloveClient:
    def __init__(self, url: str, timeout_s: float = 10.0):
        self._connection = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=timeout_s, max_size=1 << 26)
        self.ws = self._connection.__enter__()
        self.timeout_s = timeout_s
        self.server_info: dict | None = None
        self.channels: dict[str, dict] = {}
        self.subscriptions: dict[int, dict] = {}
        self.bytes_received = 0
        self._classes: dict[int, type] = {}

    def close(self) -> None:
        self._connection.__exit__(None, None, None)

    def wait_for_topics(self, topics) -> None:
        """Read control messages until every topic is advertised."""
        deadline = time.monotonic() + self.timeout_s
        while not set(topics) <= set(self.channels):
            self._handle(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))

    def subscribe(self, topics) -> None:
        self.wait_for_topics(topics)
        subs = []
        for topic in topics:
            sub_id = len(self.subscriptions) + 1
            self.subscriptions[sub_id] = self.channels[topic]
            subs.append({"id": sub_id, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def next_message(self, timeout_s: float | None = None) -> tuple[str, int, object]:
        """(topic, timestamp ns, decoded message) of the next messageData frame."""
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        while True:
            frame = self.ws.recv(timeout=max(0.01, deadline - time.monotonic()))
            decoded = self._handle(frame)
            if decoded is not None:
                return decoded

    def _handle(self, frame):
        self.bytes_received += len(frame)
        if isinstance(frame, str):
            message = json.loads(frame)
            if message["op"] == "serverInfo":
                self.server_info = message
            elif message["op"] == "advertise":
                for channel in message["channels"]:
                    self.channels[channel["topic"]] = channel
            return None
        opcode = frame[0]
        if opcode != MESSAGE_DATA:
            return None
        sub_id, stamp = struct.unpack_from("<IQ", frame, 1)
        payload = bytes(frame[13:])
        channel = self.subscriptions[sub_id]
        return channel["topic"], stamp, self.decode(channel, payload)

    def decode(self, channel: dict, payload: bytes):
        if channel["encoding"] == "json":
            return json.loads(payload)
        if channel["encoding"] != "protobuf":
            raise ValueError(f"encoding {channel['encoding']!r}")
        cls = self._classes.get(channel["id"])
        if cls is None:
            files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
            pool = descriptor_pool.DescriptorPool()
            for f in files.file:
                pool.Add(f)
            cls = self._classes[channel["id"]] = message_factory.GetMessageClass(
                pool.FindMessageTypeByName(channel["schemaName"]))
        return cls.FromString(payload)
