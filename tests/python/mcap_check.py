#!/usr/bin/env python3
"""Checks a cooploc MCAP log with independent readers: the Python `mcap` library, its protobuf
decoder (`mcap-protobuf-support`) and pymavlink.

Usage: mcap_check.py LOG EXPECT_JSON
EXPECT_JSON: {"sysid", "vehicle", "lat", "lon", "alt", "cov_enu" (9 floats), "nis", "epoch",
              "heartbeat_type", "coop_rx_hex", "attachment_name", "attachment_text",
              "config": {...}, "message_count"}
Lists the channels and schemas, checks the documented topics, encodings and schema names
(logs/README.md), decodes every message and compares the fields given in EXPECT_JSON.
Prints one line "mcap_check: OK ..." and exits 0, or raises (non-zero exit) naming the problem.
"""
import json
import math
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from pymavlink.dialects.v20 import common as mavlink2


def check(cond, what):
    if not cond:
        raise AssertionError(what)


def close(a, b, tol=1e-9):
    return math.isclose(a, b, rel_tol=0.0, abs_tol=tol)


def frame_len(data):
    if data[0] == 0xFE:
        return 8 + data[1]
    if data[0] == 0xFD:
        return 12 + data[1] + (13 if data[2] & 0x01 else 0)
    raise AssertionError("not a MAVLink frame: first byte 0x%02x" % data[0])


def main():
    path, expect = sys.argv[1], json.loads(sys.argv[2])
    sysid, vid = expect["sysid"], expect["vehicle"]
    frames = {
        "/vehicle_%d/mavlink/rx" % sysid: "rx",
        "/vehicle_%d/mavlink/tx" % sysid: "tx",
        "/coop/%d/rx" % sysid: "rx",
        "/coop/%d/tx" % sysid: "tx",
    }
    documented = {topic: ("mavlink.frame", None, None) for topic in frames}
    documented.update(
        {
            "/vehicle_%d/location" % vid: ("protobuf", "foxglove.LocationFix", "protobuf"),
            "/vehicle_%d/pose" % vid: ("protobuf", "foxglove.PoseInFrame", "protobuf"),
            "/vehicle_%d/ellipse" % vid: ("protobuf", "foxglove.SceneUpdate", "protobuf"),
            "/vehicle_%d/truth" % vid: ("protobuf", "foxglove.LocationFix", "protobuf"),
            "/vehicle_%d/truth_pose" % vid: ("protobuf", "foxglove.PoseInFrame", "protobuf"),
            "/tf": ("protobuf", "foxglove.FrameTransform", "protobuf"),
            "/vehicle_%d/internals" % vid: ("json", "cooploc.CoopUpdate", "jsonschema"),
            "/links/stats": ("json", "cooploc.LinkStats", "jsonschema"),
        }
    )

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        check(summary is not None, "no summary section")
        stats = summary.statistics
        check(stats.message_count == expect["message_count"], "message count %d" % stats.message_count)

        # Channels and schemas.
        by_topic = {}
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            by_topic[channel.topic] = (channel, schema)
            print("channel %-28s %-14s schema %s" % (channel.topic, channel.message_encoding, schema.name if schema else "-"), file=sys.stderr)
        check(set(by_topic) == set(documented), "topics %s, documented %s" % (sorted(by_topic), sorted(documented)))
        for topic, (encoding, schema_name, schema_encoding) in documented.items():
            channel, schema = by_topic[topic]
            check(channel.message_encoding == encoding, "%s: encoding %s" % (topic, channel.message_encoding))
            if schema_name is None:
                check(channel.schema_id == 0, "%s: schema id %d" % (topic, channel.schema_id))
            else:
                check(schema.name == schema_name and schema.encoding == schema_encoding, "%s: schema %s/%s" % (topic, schema.name, schema.encoding))
                if schema_encoding == "jsonschema":
                    js = json.loads(schema.data)
                    check(js.get("type") == "object" and js.get("properties"), "%s: not a JSON schema of an object" % topic)
        for topic, direction in frames.items():
            meta = by_topic[topic][0].metadata
            check(meta.get("dialect") == "cooploc" and meta.get("direction") == direction and "link" in meta, "%s: metadata %s" % (topic, meta))

        # Every message, decoded.
        seen = {}
        factory, decoders = DecoderFactory(), {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            topic = channel.topic
            seen[topic] = seen.get(topic, 0) + 1
            check(message.log_time == message.publish_time, "%s: publish_time != log_time" % topic)
            if channel.message_encoding == "mavlink.frame":
                data = message.data
                check(len(data) == frame_len(data), "%s: frame length %d" % (topic, len(data)))
                mav = mavlink2.MAVLink(None)
                mav.robust_parsing = False
                msgs = mav.parse_buffer(data) or []
                check(len(msgs) == 1, "%s: pymavlink decoded %d messages" % (topic, len(msgs)))
                check(msgs[0].get_type() == "HEARTBEAT" and msgs[0].type == expect["heartbeat_type"], "%s: %s" % (topic, msgs[0]))
                if topic == "/coop/%d/rx" % sysid:
                    check(data.hex() == expect["coop_rx_hex"], "%s: bytes differ" % topic)
            elif channel.message_encoding == "protobuf":
                if channel.id not in decoders:
                    decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
                msg = decoders[channel.id](message.data)
                if topic == "/vehicle_%d/location" % vid:
                    check(close(msg.latitude, expect["lat"]) and close(msg.longitude, expect["lon"]) and close(msg.altitude, expect["alt"], 1e-6),
                          "location %r %r %r" % (msg.latitude, msg.longitude, msg.altitude))
                    check(all(close(a, b) for a, b in zip(msg.position_covariance, expect["cov_enu"])) and len(msg.position_covariance) == 9,
                          "covariance %s" % list(msg.position_covariance))
                    check(msg.position_covariance_type == 3, "covariance type %d (want KNOWN = 3)" % msg.position_covariance_type)
                    check(msg.timestamp.seconds * 10**9 + msg.timestamp.nanos == message.log_time, "location timestamp")
                elif topic == "/vehicle_%d/pose" % vid:
                    check(msg.frame_id == "ned", "pose frame %s" % msg.frame_id)
                elif topic == "/vehicle_%d/ellipse" % vid:
                    e = msg.entities[0]
                    check(e.frame_id == "ned" and len(e.spheres) == 1 and e.spheres[0].size.x >= e.spheres[0].size.y > 0, "ellipse %s" % e)
                elif topic == "/tf":
                    check((msg.parent_frame_id, msg.child_frame_id) == ("world", "ned"), "tf %s" % msg)
            else:
                obj = json.loads(message.data)
                js = json.loads(schema.data)
                check(set(obj) == set(js["required"]), "%s: keys %s" % (topic, sorted(obj)))
                if topic == "/vehicle_%d/internals" % vid:
                    check(obj["epoch"] == expect["epoch"] and close(obj["nis"], expect["nis"]), "internals %s" % obj)
        check(set(seen) == set(documented), "messages on %s" % sorted(seen))
        check(sum(seen.values()) == expect["message_count"], "read %d messages" % sum(seen.values()))

        # Metadata and attachments.
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        check(metadata.get("cooploc", {}).get("format_version") == "1", "metadata %s" % metadata)
        check(metadata.get("config") == expect["config"], "config metadata %s" % metadata.get("config"))
        attachments = list(reader.iter_attachments())
        check(len(attachments) == 1 and attachments[0].name == expect["attachment_name"], "attachments %s" % [a.name for a in attachments])
        check(attachments[0].data.decode() == expect["attachment_text"], "attachment text")

    print("mcap_check: OK %d messages on %d channels" % (sum(seen.values()), len(seen)))


if __name__ == "__main__":
    main()
