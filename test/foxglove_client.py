"""A client of the Foxglove WebSocket protocol for the tests, on the `websockets` package.

What Foxglove and Lichtblick do when they connect: the handshake with the protocol's
subprotocol, the server's ``serverInfo`` / ``advertise`` / ``advertiseServices`` JSON, a
``subscribe``, binary message data (opcode 1: subscription id, receive time in ns, payload),
and service calls (opcode 2 out, opcode 3 or ``serviceCallFailure`` back). The protocol is
``foxglove.websocket.v1``; foxglove-sdk's server (0.30) accepts it only under its newer name
``foxglove.sdk.v1`` (the same messages), so both are offered.

Also the protobuf wire format, enough to read a ``foxglove.FrameTransforms``.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from collections import defaultdict

from websockets.sync.client import connect

SUBPROTOCOLS = ['foxglove.sdk.v1', 'foxglove.websocket.v1']
MESSAGE_DATA, SERVICE_CALL_REQUEST, SERVICE_CALL_RESPONSE = 1, 2, 3


class FoxgloveClient:
    def __init__(self, url: str, timeout: float = 10.0):
        self.ws = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=timeout,
                          max_size=None, legacy=True)    # a connection kept across calls
        self.channels: dict[str, dict] = {}       # by topic
        self.services: dict[str, dict] = {}       # by name
        self.messages: dict[int, list[tuple[int, bytes]]] = defaultdict(list)  # by subscription
        self.responses: dict[int, tuple[str, bytes] | str] = {}                 # by call id
        self.server_info: dict | None = None
        self._next_id = 1
        self._lock = threading.Condition()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    @property
    def subprotocol(self) -> str | None:
        return self.ws.subprotocol

    def _read(self) -> None:
        try:
            for frame in self.ws:
                with self._lock:
                    if isinstance(frame, str):
                        self._on_json(json.loads(frame))
                    else:
                        self._on_binary(frame)
                    self._lock.notify_all()
        except Exception:   # the connection closed
            pass

    def _on_json(self, message: dict) -> None:
        op = message['op']
        if op == 'serverInfo':
            self.server_info = message
        elif op == 'advertise':
            for channel in message['channels']:
                self.channels[channel['topic']] = channel
        elif op == 'unadvertise':
            gone = set(message['channelIds'])
            self.channels = {t: c for t, c in self.channels.items() if c['id'] not in gone}
        elif op == 'advertiseServices':
            for service in message['services']:
                self.services[service['name']] = service
        elif op == 'serviceCallFailure':
            self.responses[message['callId']] = message['message']

    def _on_binary(self, frame: bytes) -> None:
        if frame[0] == MESSAGE_DATA:
            subscription, stamp = struct.unpack_from('<IQ', frame, 1)
            self.messages[subscription].append((stamp, bytes(frame[13:])))
        elif frame[0] == SERVICE_CALL_RESPONSE:
            _, call, length = struct.unpack_from('<III', frame, 1)
            encoding = frame[13:13 + length].decode()
            self.responses[call] = (encoding, bytes(frame[13 + length:]))

    def _wait(self, predicate, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                found = predicate()
                if found:
                    return found
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f'timed out after {timeout:g} s waiting for {what}')
                self._lock.wait(min(left, 0.1))

    def channel(self, topic: str, timeout: float = 20.0) -> dict:
        return self._wait(lambda: self.channels.get(topic), timeout, f'channel {topic}')

    def service(self, name: str, timeout: float = 20.0) -> dict:
        return self._wait(lambda: self.services.get(name), timeout, f'service {name}')

    def subscribe(self, topic: str, timeout: float = 20.0) -> int:
        channel = self.channel(topic, timeout)
        with self._lock:
            subscription = self._next_id
            self._next_id += 1
        self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
            {'id': subscription, 'channelId': channel['id']}]}))
        return subscription

    def message(self, subscription: int, accept=lambda payload: True,
                timeout: float = 20.0) -> tuple[int, bytes]:
        """The first message on ``subscription`` whose payload ``accept`` takes:
        (receive time ns, payload)."""
        def found():
            return next((m for m in self.messages[subscription] if accept(m[1])), None)
        return self._wait(found, timeout, f'a message on subscription {subscription}')

    def call(self, name: str, payload: bytes, encoding: str = 'cdr',
             timeout: float = 30.0) -> bytes:
        """Call a service; its response's payload (AssertionError on a call failure)."""
        service = self.service(name)
        with self._lock:
            call = self._next_id
            self._next_id += 1
        data = encoding.encode()
        self.ws.send(struct.pack('<BIII', SERVICE_CALL_REQUEST, service['id'], call, len(data))
                     + data + payload)
        answer = self._wait(lambda: self.responses.get(call), timeout, f'the answer of {name}')
        assert not isinstance(answer, str), f'{name} failed: {answer}'
        assert answer[0] == encoding
        return answer[1]

    def close(self) -> None:
        self.ws.close()
        self._thread.join(5.0)


# -- protobuf, as far as foxglove.FrameTransforms needs ---------------------------------------

def _varint(data: bytes, at: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, at


def protobuf_fields(data: bytes) -> dict[int, list]:
    """Field number -> values: ints (varint), bytes (length-delimited), floats (fixed64 as
    double, fixed32 as float)."""
    fields: dict[int, list] = defaultdict(list)
    at = 0
    while at < len(data):
        key, at = _varint(data, at)
        number, kind = key >> 3, key & 7
        if kind == 0:
            value, at = _varint(data, at)
        elif kind == 1:
            value, at = struct.unpack_from('<d', data, at)[0], at + 8
        elif kind == 2:
            length, at = _varint(data, at)
            value, at = data[at:at + length], at + length
        elif kind == 5:
            value, at = struct.unpack_from('<f', data, at)[0], at + 4
        else:
            raise ValueError(f'protobuf wire type {kind} not handled')
        fields[number].append(value)
    return fields


def frame_transforms(payload: bytes) -> list[dict]:
    """A foxglove.FrameTransforms message: one dict per transform (fields as foxglove's
    FrameTransform.proto numbers them; absent numbers are 0, as proto3 omits them)."""
    def vector(data: bytes, names: str) -> tuple[float, ...]:
        values = protobuf_fields(data)
        return tuple(values.get(k + 1, [0.0])[0] for k in range(len(names)))
    out = []
    for raw in protobuf_fields(payload).get(1, []):
        fields = protobuf_fields(raw)
        stamp = protobuf_fields(fields.get(1, [b''])[0])
        out.append({
            'stamp': stamp.get(1, [0])[0] + stamp.get(2, [0])[0] * 1e-9,
            'parent': fields.get(2, [b''])[0].decode(),
            'child': fields.get(3, [b''])[0].decode(),
            'translation': vector(fields.get(4, [b''])[0], 'xyz'),
            'rotation': vector(fields.get(5, [b''])[0], 'xyzw'),
        })
    return out
