"""Foxglove WebSocket in and out: a robot's `foxglove_bridge` as a live source, and the live
estimate served to the Foxglove app.

    for raw, arrival in bridge_messages("ws://robot:8765", topics, stop):   # a source
        stream.push(raw, arrival)

    EstimateWriter(FoxgloveSink(port=8765), model, name, h).write(estimate, knots)
    EstimateWriter(BridgePublisher("ws://robot:8765"), ...)   # into the robot's ROS 2 graph

The source speaks the Foxglove WebSocket protocol as a client (subprotocol
`foxglove.websocket.v1`, which `foxglove_bridge` serves, or `foxglove.sdk.v1`, foxglove-sdk's):
it subscribes to the advertised channels whose topics the config maps, and turns each Message
Data frame (opcode 1: subscription id u32, receive time u64 ns, payload) into a `RawMessage`
with the channel's schema, as the MCAP reader gives it. A connection that drops is reconnected
with backoff; the source ends after `reconnect_s` without one.
"""

from __future__ import annotations

import contextlib
import json
import struct
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping
from typing import Any

import foxglove
from mcap.records import Schema
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from estimator.errors import LogError
from estimator.io.live import Reconnect
from estimator.io.logs.source import RawMessage
from estimator.io.mcap_writer import RELIABLE_QOS, cdr_encoder

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
MESSAGE_DATA = 1  # server binary opcode
_HEAD = struct.Struct("<BIQ")  # opcode, subscription id, receive timestamp (ns)


def bridge_messages(
    url: str,
    topics: Collection[str],
    stop: threading.Event,
    reconnect_s: float = 10.0,
    log: Callable[[str], None] = print,
) -> Iterator[tuple[RawMessage, float]]:
    """(message, arrival on `time.perf_counter`) from a Foxglove WebSocket server, for the
    channels on `topics`; reconnects with backoff until `reconnect_s` without a connection."""
    retry = Reconnect(url, reconnect_s, log)
    while not stop.is_set():
        try:
            ws = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=2.0)  # type: ignore[arg-type]
        except InvalidURI as err:
            raise LogError(f"--source {url!r}: {err}") from None
        except (OSError, InvalidHandshake, TimeoutError) as err:
            if retry.failed(err):
                continue
            return
        log(f"source {url}: connected ({ws.subprotocol})")
        retry.succeeded()
        with ws, contextlib.suppress(ConnectionClosed):
            yield from _session(ws, url, topics, stop, log)
        if stop.is_set():
            return
        log(f"source {url}: disconnected; reconnecting")
        retry.lost()


def _session(
    ws: ClientConnection,
    url: str,
    topics: Collection[str],
    stop: threading.Event,
    log: Callable[[str], None],
) -> Iterator[tuple[RawMessage, float]]:
    """One connection: subscribe to what is advertised on `topics`, yield its messages."""
    channels: dict[int, tuple[str, str, Schema, str]] = {}  # subscription → channel
    next_id = 1
    while not stop.is_set():
        try:
            frame = ws.recv(timeout=0.5)
        except TimeoutError:
            continue
        arrival = time.perf_counter()
        if isinstance(frame, str):
            try:
                op = json.loads(frame)
            except json.JSONDecodeError:
                log(f"source {url}: a text frame that is not JSON (skipped)")
                continue
            if op.get("op") == "advertise":
                subscribe = []
                for ch in op.get("channels", []):
                    if ch.get("topic") not in topics or ch.get("encoding") != "cdr":
                        continue
                    schema = Schema(
                        id=int(ch["id"]),
                        name=str(ch.get("schemaName", "")),
                        encoding=str(ch.get("schemaEncoding") or "ros2msg"),
                        data=str(ch.get("schema", "")).encode(),
                    )
                    channels[next_id] = (ch["topic"], schema.name, schema, "cdr")
                    subscribe.append({"id": next_id, "channelId": int(ch["id"])})
                    next_id += 1
                if subscribe:
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subscribe}))
            continue
        if len(frame) < _HEAD.size or frame[0] != MESSAGE_DATA:
            continue  # (time, service responses, ...)
        _, sub, t_ns = _HEAD.unpack_from(frame)
        channel = channels.get(sub)
        if channel is None:
            continue
        topic, msg_type, schema, encoding = channel
        yield (
            RawMessage(topic, msg_type, schema, encoding, t_ns, bytes(frame[_HEAD.size :])),
            (arrival),
        )


class BridgePublisher:
    """The estimate published into a robot's ROS 2 graph through its `foxglove_bridge`, as a
    client of the protocol with the bridge's `clientPublish` capability: each topic is
    advertised as a client channel (CDR, its ros2msg schema) on first use and each message
    sent as Client Message Data (opcode 1, channel id u32, payload); the bridge publishes
    them as ordinary topics. Only standard ROS 2 types go (`ROS_TYPES`): the contact array
    is physfuse's own type, which the robot's graph does not know."""

    ROS_TYPES = frozenset(
        {
            "nav_msgs/msg/Odometry",
            "sensor_msgs/msg/JointState",
            "geometry_msgs/msg/WrenchStamped",
            "geometry_msgs/msg/AccelStamped",
            "diagnostic_msgs/msg/DiagnosticArray",
        }
    )

    def __init__(self, url: str, timeout_s: float = 5.0) -> None:
        try:
            self.ws = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=timeout_s)  # type: ignore[arg-type]
        except (OSError, InvalidHandshake, InvalidURI, TimeoutError) as err:
            raise LogError(f"--bridge-publish {url}: cannot connect ({err})") from None
        info = self._server_info(url, timeout_s)
        if "clientPublish" not in info.get("capabilities", []):
            self.ws.close()
            raise LogError(
                f"--bridge-publish {url}: the bridge does not offer clientPublish (its "
                f"capabilities: {', '.join(info.get('capabilities', [])) or 'none'}); start "
                "foxglove_bridge with capabilities including clientPublish"
            )
        encodings = info.get("supportedEncodings") or ["cdr"]
        if "cdr" not in encodings:
            self.ws.close()
            raise LogError(f"--bridge-publish {url}: the bridge takes {encodings}, not cdr")
        self.channels: dict[str, int] = {}

    def _server_info(self, url: str, timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                frame = self.ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
            except TimeoutError:
                break
            if isinstance(frame, str):
                op = json.loads(frame)
                if op.get("op") == "serverInfo":
                    return dict(op)
        self.ws.close()
        raise LogError(f"--bridge-publish {url}: no serverInfo within {timeout_s:g} s")

    def write(
        self,
        topic: str,
        msg_type: str,
        fields: Mapping[str, Any],
        log_time_ns: int,
        *,
        qos: str = RELIABLE_QOS,
    ) -> None:
        if msg_type not in self.ROS_TYPES:
            return
        text, encode = cdr_encoder(msg_type)
        channel = self.channels.get(topic)
        if channel is None:
            channel = self.channels[topic] = len(self.channels) + 1
            advertise = {
                "id": channel,
                "topic": topic,
                "encoding": "cdr",
                "schemaName": msg_type,
                "schema": text,
                "schemaEncoding": "ros2msg",
            }
            self.ws.send(json.dumps({"op": "advertise", "channels": [advertise]}))
        self.ws.send(struct.pack("<BI", MESSAGE_DATA, channel) + encode(fields))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """(The ROS graph has no place for it.)"""

    def flush(self) -> None:
        """(Frames leave as they are sent.)"""

    def finish(self) -> None:
        if self.channels:
            self.ws.send(
                json.dumps({"op": "unadvertise", "channelIds": list(self.channels.values())})
            )
        self.ws.close()


class FoxgloveSink:
    """The estimate served live on a Foxglove WebSocket server (foxglove-sdk): the same topics
    and ROS 2 messages (CDR, ros2msg schemas) as the MCAP file, for the Foxglove app or any
    client of the protocol. port 0: any free one (`port`)."""

    def __init__(self, port: int, host: str = "0.0.0.0") -> None:  # (all interfaces: a LAN)
        self.server = foxglove.start_server(name="physfuse", host=host, port=port)
        self.port = self.server.port
        self.channels: dict[str, foxglove.Channel] = {}

    def write(
        self,
        topic: str,
        msg_type: str,
        fields: Mapping[str, Any],
        log_time_ns: int,
        *,
        qos: str = RELIABLE_QOS,
    ) -> None:
        text, encode = cdr_encoder(msg_type)
        channel = self.channels.get(topic)
        if channel is None:
            schema = foxglove.Schema(name=msg_type, encoding="ros2msg", data=text.encode())
            channel = self.channels[topic] = foxglove.Channel(
                topic, message_encoding="cdr", schema=schema
            )
        channel.log(encode(fields), log_time=int(log_time_ns))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """(The protocol has no metadata records; the MCAP file keeps them.)"""

    def flush(self) -> None:
        """(Messages leave as they are logged.)"""

    def finish(self) -> None:
        for channel in self.channels.values():
            channel.close()
        self.server.stop()
