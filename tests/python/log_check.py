#!/usr/bin/env python3
"""Opens a log recorded by `cooploc demo` with the Python `mcap` reader (an independent
implementation) and checks the channels and schemas logs/README.md documents.

Usage: log_check.py LOG
Prints "log_check: OK ..." and exits 0, or raises naming what is missing.
"""
import json
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

path = sys.argv[1]
with open(path, "rb") as f:
    reader = make_reader(f, decoder_factories=[DecoderFactory()])
    summary = reader.get_summary()
    assert summary is not None, "no summary: the log was not finished"
    channels = {c.topic: c for c in summary.channels.values()}
    schemas = summary.schemas
    metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    attachments = [a.name for a in reader.iter_attachments()]

    run = metadata.get("cooploc.run")
    assert run and {"seed", "run", "schedule"} <= set(run), f"cooploc.run metadata: {run}"
    assert "scenario.toml" in attachments, attachments
    nodes = sorted(int(n.rsplit(".", 1)[1]) for n in metadata if n.startswith("cooploc.node."))
    assert nodes == [1, 2, 3], nodes

    def expect(topic, encoding, schema_name=None):
        c = channels.get(topic)
        assert c is not None, f"missing channel {topic}"
        assert c.message_encoding == encoding, f"{topic}: encoding {c.message_encoding}, expected {encoding}"
        if schema_name is None:
            assert c.schema_id == 0, f"{topic}: raw frames have no schema"
        else:
            s = schemas[c.schema_id]
            assert s.name == schema_name, f"{topic}: schema {s.name}, expected {schema_name}"

    for n in nodes:
        for d in ("rx", "tx"):
            expect(f"/vehicle_{n}/mavlink/{d}", "mavlink.frame")
            expect(f"/coop/{n}/{d}", "mavlink.frame")
        expect(f"/vehicle_{n}/location", "protobuf", "foxglove.LocationFix")
        expect(f"/vehicle_{n}/pose", "protobuf", "foxglove.PoseInFrame")
        expect(f"/vehicle_{n}/ellipse", "protobuf", "foxglove.SceneUpdate")
        expect(f"/vehicle_{n}/truth", "protobuf", "foxglove.LocationFix")
        expect(f"/vehicle_{n}/node/events", "json", "cooploc.NodeEvent")
        expect(f"/vehicle_{n}/internals", "json", "cooploc.CoopUpdate")
    expect("/coop/255/rx", "mavlink.frame")

    counts = {}
    fixes = 0
    factory = DecoderFactory()
    for schema, channel, message in reader.iter_messages():
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
        if channel.message_encoding == "mavlink.frame":
            assert message.data[0] in (0xFD, 0xFE), f"{channel.topic}: not a MAVLink frame"
        elif channel.topic.endswith("/location"):
            decoded = factory.decoder_for("protobuf", schema)(message.data)
            assert 34.0 < decoded.latitude < 35.5, decoded.latitude
            fixes += 1
        elif channel.topic.endswith("/internals"):
            u = json.loads(message.data)
            assert len(u["participants"]) == 3 and len(u["innovation"]) == u["nis_dof"] == len(u["ranges"]), u
            assert u["nis"] >= 0, u
        elif channel.message_encoding == "json":
            json.loads(message.data)
    assert fixes > 0
    assert all(counts.get(f"/vehicle_{n}/mavlink/rx", 0) > 1000 for n in nodes), counts
print(f"log_check: OK {path}: {len(channels)} channels, {sum(counts.values())} messages, nodes {nodes}")
