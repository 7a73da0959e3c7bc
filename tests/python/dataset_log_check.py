#!/usr/bin/env python3
"""Opens a data set log written by `cooploc dataset mrclam --out` with independent readers: the
Python `mcap` reader (with mcap-protobuf-support) for the channels, schemas and metadata, and
pymavlink (bindings generated from the dialect XML) for every raw frame.

Usage: dataset_log_check.py DIALECT_XML LOG
Prints one JSON object: per robot the ODOMETRY and COOPLOC_RANGE_BEARING frames pymavlink
decoded (and how many frames it could not), the truth and estimate messages, and the first
observation's fields; raises naming what is missing.
"""
import atexit
import contextlib
import json
import os
import sys
import shutil
import tempfile

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from pymavlink.generator import mavgen

xml_path, path = sys.argv[1], sys.argv[2]
out_dir = tempfile.mkdtemp(prefix="cooploc-mavgen-")
atexit.register(shutil.rmtree, out_dir, ignore_errors=True)
opts = mavgen.Opts(os.path.join(out_dir, "cooploc_dialect.py"), wire_protocol="2.0", language="Python3", validate=True)
with contextlib.redirect_stdout(sys.stderr):
    assert mavgen.mavgen(opts, [xml_path]), "mavgen rejected " + xml_path
sys.path.insert(0, out_dir)
import cooploc_dialect  # noqa: E402

with open(path, "rb") as f:
    reader = make_reader(f, decoder_factories=[DecoderFactory()])
    summary = reader.get_summary()
    assert summary is not None, "no summary: the log was not finished"
    metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    ds = metadata.get("cooploc.dataset")
    assert ds and ds.get("kind") == "mrclam", f"cooploc.dataset metadata: {ds}"
    robots = [int(r) for r in ds["robots"].split(",")]
    assert "cooploc.dataset.landmarks" in metadata
    channels = {c.topic: c for c in summary.channels.values()}
    schemas = summary.schemas
    for r in robots:
        for topic, schema in [(f"/vehicle_{r}/truth_pose", "foxglove.PoseInFrame"), (f"/vehicle_{r}/truth", "foxglove.LocationFix")]:
            c = channels.get(topic)
            assert c is not None, f"missing channel {topic}"
            assert schemas[c.schema_id].name == schema, f"{topic}: {schemas[c.schema_id].name}"
        assert channels[f"/vehicle_{r}/mavlink/rx"].message_encoding == "mavlink.frame"
    out = {"robots": {}}
    mav = cooploc_dialect.MAVLink(None)
    mav.robust_parsing = False
    for r in robots:
        counts = {"ODOMETRY": 0, "COOPLOC_RANGE_BEARING": 0, "bad": 0, "truth": 0, "pose": 0}
        first = None
        for _, channel, _, decoded in reader.iter_decoded_messages(topics=[f"/vehicle_{r}/truth_pose", f"/vehicle_{r}/pose"]):
            assert decoded.frame_id == "ned", decoded.frame_id
            counts["truth" if channel.topic.endswith("/truth_pose") else "pose"] += 1
        for _, channel, message in reader.iter_messages(topics=[f"/vehicle_{r}/mavlink/rx"]):
            try:
                m = mav.decode(bytearray(message.data))
            except Exception:  # noqa: BLE001 (any decoding failure counts)
                counts["bad"] += 1
                continue
            name = m.get_type()
            assert m.get_srcSystem() == r, f"frame of system {m.get_srcSystem()} on robot {r}'s channel"
            counts[name] = counts.get(name, 0) + 1
            if name == "COOPLOC_RANGE_BEARING" and first is None:
                first = {"time_usec": m.time_usec, "range": m.range, "bearing": m.bearing, "observer": m.observer,
                         "target": m.target, "target_kind": m.target_kind}
        counts["first_observation"] = first
        out["robots"][str(r)] = counts
    print(json.dumps(out))
