"""A Foxglove WebSocket client, independent of the Rust crate, checking `cooploc gcs`.

Connects with the subprotocol `foxglove.sdk.v1` (what the foxglove SDK 0.30 server negotiates;
older clients' `foxglove.websocket.v1` is not accepted), expects `serverInfo` and `advertise`
messages naming the documented channels (`/vehicle_<id>/location` as protobuf
`foxglove.LocationFix` with its schema, `/vehicle_<id>/pose` as `foxglove.PoseInFrame`,
`/vehicle_<id>/ellipse` as `foxglove.SceneUpdate`, `/vehicle_<id>/estimate` as JSON, `/tf` as
`foxglove.FrameTransform`, `/team/health` as JSON; the truth and error channels appear only with
truth, which this test sends none of), subscribes to one vehicle's location and waits for a
binary messageData whose LocationFix (decoded here by hand from the protobuf wire format) is at
the expected latitude and longitude. Prints one JSON line with what it saw; exits non-zero on any
mismatch.

Usage: foxglove_ws_check.py ws://HOST:PORT --vehicle 2 --vehicles 1,2,3 --lat LAT --lon LON
"""

import argparse
import base64
import json
import struct
import sys
import time

from websockets.sync.client import connect


def varint(buf, i):
    shift = value = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def protobuf_fields(buf):
    """(field number, wire type, value) of a protobuf message: ints, raw 8/4-byte values, bytes."""
    i, out = 0, []
    while i < len(buf):
        key, i = varint(buf, i)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, i = varint(buf, i)
        elif wire == 1:
            value, i = buf[i:i + 8], i + 8
        elif wire == 2:
            n, i = varint(buf, i)
            value, i = buf[i:i + n], i + n
        elif wire == 5:
            value, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wire}")
        out.append((field, wire, value))
    return out


def location_fix(payload):
    """latitude (1), longitude (2), altitude (3), covariance (4, packed doubles), frame_id (7)."""
    fix = {"covariance": []}
    for field, wire, value in protobuf_fields(payload):
        if field in (1, 2, 3) and wire == 1:
            fix[{1: "latitude", 2: "longitude", 3: "altitude"}[field]] = struct.unpack("<d", value)[0]
        elif field == 4 and wire == 2:
            fix["covariance"] = list(struct.unpack(f"<{len(value) // 8}d", value))
        elif field == 4 and wire == 1:
            fix["covariance"].append(struct.unpack("<d", value)[0])
        elif field == 7 and wire == 2:
            fix["frame_id"] = value.decode()
    return fix


def fail(msg):
    print(f"FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("url")
    ap.add_argument("--vehicle", type=int, required=True)
    ap.add_argument("--vehicles", required=True)
    ap.add_argument("--lat", type=float, required=True)
    ap.add_argument("--lon", type=float, required=True)
    ap.add_argument("--timeout", type=float, default=30.0)
    args = ap.parse_args()
    ids = [int(x) for x in args.vehicles.split(",")]
    want = {f"/vehicle_{i}/location": ("protobuf", "foxglove.LocationFix") for i in ids}
    want.update({f"/vehicle_{i}/pose": ("protobuf", "foxglove.PoseInFrame") for i in ids})
    want.update({f"/vehicle_{i}/ellipse": ("protobuf", "foxglove.SceneUpdate") for i in ids})
    want.update({f"/vehicle_{i}/estimate": ("json", "cooploc.Estimate") for i in ids})
    want["/tf"] = ("protobuf", "foxglove.FrameTransform")
    want["/team/health"] = ("json", "cooploc.TeamHealth")
    target = f"/vehicle_{args.vehicle}/location"

    deadline = time.monotonic() + args.timeout
    with connect(args.url, subprotocols=["foxglove.sdk.v1"], open_timeout=10, max_size=None) as ws:
        if ws.subprotocol != "foxglove.sdk.v1":
            fail(f"negotiated subprotocol {ws.subprotocol!r}")
        server_info, channels, subscribed, fix = None, {}, None, None
        while time.monotonic() < deadline:
            msg = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
            if isinstance(msg, str):
                m = json.loads(msg)
                if m.get("op") == "serverInfo":
                    server_info = m
                elif m.get("op") == "advertise":
                    for ch in m["channels"]:
                        channels[ch["topic"]] = ch
                if server_info and subscribed is None and all(t in channels for t in want):
                    for topic, (encoding, schema_name) in want.items():
                        ch = channels[topic]
                        if ch["encoding"] != encoding:
                            fail(f"{topic}: encoding {ch['encoding']!r}, expected {encoding!r}")
                        if schema_name and ch["schemaName"] != schema_name:
                            fail(f"{topic}: schema {ch['schemaName']!r}, expected {schema_name!r}")
                        if encoding == "protobuf" and not base64.b64decode(ch.get("schema", "")):
                            fail(f"{topic}: empty protobuf schema")
                        if encoding == "json" and json.loads(ch.get("schema", "{}")).get("type") != "object":
                            fail(f"{topic}: not a JSON schema of an object")
                    subscribed = 7
                    sub = {"op": "subscribe", "subscriptions": [{"id": subscribed, "channelId": channels[target]["id"]}]}
                    ws.send(json.dumps(sub))
            else:
                if msg[0] != 0x01 or subscribed is None:
                    continue  # not messageData (e.g. time), or not ours yet
                sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
                if sub_id != subscribed:
                    fail(f"messageData for subscription {sub_id}")
                fix = location_fix(msg[13:])
                fix["log_time_ns"] = log_time
                break
        if server_info is None:
            fail("no serverInfo")
        missing = sorted(t for t in want if t not in channels)
        if missing:
            fail(f"channels not advertised: {missing} (got {sorted(channels)})")
        if fix is None:
            fail(f"no messageData on {target}")
    if abs(fix["latitude"] - args.lat) > 1e-7 or abs(fix["longitude"] - args.lon) > 1e-7:
        fail(f"location {fix['latitude']}, {fix['longitude']}: expected {args.lat}, {args.lon}")
    if fix.get("frame_id") != f"vehicle_{args.vehicle}":
        fail(f"frame_id {fix.get('frame_id')!r}")
    if len(fix["covariance"]) != 9:
        fail(f"covariance of {len(fix['covariance'])} values")
    if abs(fix["log_time_ns"] / 1e9 - time.time()) > 60:
        fail(f"log time {fix['log_time_ns']} is not the receive time")
    print(json.dumps({
        "subprotocol": ws.subprotocol,
        "server_name": server_info.get("name"),
        "channels": sorted(channels),
        "latitude": fix["latitude"],
        "longitude": fix["longitude"],
        "covariance_enu": fix["covariance"],
    }))


if __name__ == "__main__":
    main()
