"""The web page, the live Foxglove channels and a log's Foxglove channels show the same team.

Independent of the Rust crate: the live channels are read with a Foxglove WebSocket client
(`websockets`, protobuf classes built from the schemas the server advertises), the log with the
`mcap` reader and `mcap-protobuf-support`, the page's view from its JSON (`GET /api/state`).

Usage:
  view_agreement_check.py listen ws://HOST:PORT OUT.json --vehicles 1,2,3 --until-t T
      subscribes to every channel, records each protobuf message (as a dict) and JSON message,
      prints `subscribed` once subscribed, and stops when every vehicle's estimate has reached
      vehicle time T (or after --timeout s);
  view_agreement_check.py compare LIVE.json STATE.json LOG.mcap
      checks that, for every vehicle, the three carry the same colours, frames and ellipses:
      - colour: the page's `style.color`, the live and logged LocationFix colours, and the
        live and logged ellipse colours (rgb) are one colour;
      - frames: the live and logged messages use the same frame ids (`ned` for poses and
        ellipses, `vehicle_<id>` for locations) and the same `/tf` (`world` -> `ned`);
      - ellipses: for every estimate time the live and logged ellipses both hold, they are equal
        (size, orientation, position); the page's ellipse of the newest estimate equals the
        ellipse both draw at that time (semi-axes and bearing, to 1e-9).
Prints `PASS ...` / `FAIL ...` lines; exits 1 on any failure.
"""

import base64
import json
import math
import struct
import sys
import time

from google.protobuf import descriptor_pb2, descriptor_pool, json_format
from google.protobuf.message_factory import GetMessageClass

failures = 0


def check(name, ok, why=""):
    global failures
    print(("PASS %s" % name) if ok else ("FAIL %s: %s" % (name, why)), flush=True)
    if not ok:
        failures += 1


def message_class(schema_name, schema_b64):
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return GetMessageClass(pool.FindMessageTypeByName(schema_name))


def as_dict(msg):
    return json_format.MessageToDict(msg, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)


def listen(url, out_path, vehicles, until_t, timeout):
    from websockets.sync.client import connect

    deadline = time.monotonic() + timeout
    channels, classes, subs, records = {}, {}, {}, []
    reached = {v: False for v in vehicles}
    announced = False
    with connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10, max_size=None) as ws:
        next_sub = 1
        while time.monotonic() < deadline and not all(reached.values()):
            try:
                msg = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            if isinstance(msg, str):
                m = json.loads(msg)
                if m.get("op") != "advertise":
                    continue
                new = []
                for ch in m["channels"]:
                    if ch["id"] in channels:
                        continue
                    channels[ch["id"]] = ch
                    if ch["encoding"] == "protobuf":
                        classes[ch["id"]] = message_class(ch["schemaName"], ch["schema"])
                    subs[next_sub] = ch["id"]
                    new.append({"id": next_sub, "channelId": ch["id"]})
                    next_sub += 1
                if new:
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    if not announced:
                        print("subscribed", flush=True)
                        announced = True
                continue
            if msg[0] != 0x01:
                continue
            sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
            ch = channels[subs[sub_id]]
            payload = msg[13:]
            if ch["encoding"] == "protobuf":
                value = as_dict(classes[ch["id"]].FromString(payload))
            else:
                value = json.loads(payload)
            records.append({"topic": ch["topic"], "log_time": log_time, "msg": value})
            if ch["topic"].endswith("/estimate") and value.get("t_s", 0) >= until_t:
                reached[value["vehicle"]] = True
    with open(out_path, "w") as f:
        json.dump({"channels": {c["topic"]: c["schemaName"] for c in channels.values()}, "records": records}, f)
    missing = [v for v, ok in reached.items() if not ok]
    if missing:
        sys.exit("the live channels did not reach t = %s s for vehicles %s" % (until_t, missing))
    print("listened: %d messages" % len(records), flush=True)


def read_log(path):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    records, schemas, factory, decoders = [], {}, DecoderFactory(), {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if channel.message_encoding == "protobuf":
                if channel.id not in decoders:
                    decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
                value = as_dict(decoders[channel.id](message.data))
            elif channel.message_encoding == "json":
                value = json.loads(message.data)
            else:
                continue
            schemas[channel.topic] = schema.name if schema else None
            records.append({"topic": channel.topic, "log_time": message.log_time, "msg": value})
    return {"channels": schemas, "records": records}


def rgb(color):
    return tuple(round(255 * color.get(k, 0.0)) for k in ("r", "g", "b"))


def hex_rgb(h):
    return tuple(int(h[i:i + 2], 16) for i in (1, 3, 5))


def by_topic(data, topic):
    return [r["msg"] for r in data["records"] if r["topic"] == topic]


def ellipses(data, vid):
    """Ellipse sphere by its estimate time t_us."""
    out = {}
    for m in by_topic(data, "/vehicle_%d/ellipse" % vid):
        for e in m.get("entities", []):
            t = {kv["key"]: kv["value"] for kv in e.get("metadata", [])}.get("t_us")
            out[int(t)] = (e["frame_id"], e["spheres"][0], e.get("texts", []))
    return out


def quat_yaw(q):
    return 2.0 * math.atan2(q.get("z", 0.0), q.get("w", 0.0))


def compare(live_path, state_path, log_path):
    live = json.load(open(live_path))
    state = json.load(open(state_path))
    log = read_log(log_path)
    vehicles = {v["id"]: v for v in state["vehicles"]}
    check("the page shows vehicles", len(vehicles) >= 1, list(vehicles))
    for topic in sorted(set(live["channels"]) & set(log["channels"])):
        check("%s: one schema live and logged" % topic, live["channels"][topic] == log["channels"][topic],
              (live["channels"][topic], log["channels"][topic]))
    live_tf = {(m["parent_frame_id"], m["child_frame_id"], json.dumps(m["rotation"], sort_keys=True)) for m in by_topic(live, "/tf")}
    log_tf = {(m["parent_frame_id"], m["child_frame_id"], json.dumps(m["rotation"], sort_keys=True)) for m in by_topic(log, "/tf")}
    check("/tf: one transform world -> ned, live and logged", live_tf == log_tf and len(live_tf) == 1
          and next(iter(live_tf))[:2] == ("world", "ned"), (live_tf, log_tf))
    for vid, v in sorted(vehicles.items()):
        page_rgb = hex_rgb(v["style"]["color"])
        check("vehicle %d: page name" % vid, v["style"]["name"] == "vehicle %d" % vid, v["style"])
        colours = {"page": page_rgb}
        frames = {}
        for name, data in (("live", live), ("log", log)):
            fixes = by_topic(data, "/vehicle_%d/location" % vid)
            check("vehicle %d: %s locations" % (vid, name), len(fixes) > 0)
            if fixes:
                colours[name + " location"] = rgb(fixes[-1]["color"])
                frames[name + " location"] = {f["frame_id"] for f in fixes}
            truth = by_topic(data, "/vehicle_%d/truth" % vid)
            if truth:
                colours[name + " truth"] = rgb(truth[-1]["color"])
            ell = ellipses(data, vid)
            if ell:
                last = ell[max(ell)]
                colours[name + " ellipse"] = rgb(last[1]["color"])
                frames[name + " ellipse"] = {e[0] for e in ell.values()}
                labels = {t["text"] for e in ell.values() for t in e[2]}
                check("vehicle %d: %s ellipse labelled with the page's name" % (vid, name), labels == {v["style"]["name"]}, labels)
            poses = by_topic(data, "/vehicle_%d/pose" % vid)
            if poses:
                frames[name + " pose"] = {p["frame_id"] for p in poses}
        check("vehicle %d: one colour on the page, live and in the log" % vid, len(set(colours.values())) == 1, colours)
        check("vehicle %d: frames" % vid,
              frames.get("live location") == frames.get("log location") == {"vehicle_%d" % vid}
              and frames.get("live ellipse") == frames.get("log ellipse") == {"ned"}
              and frames.get("live pose") == frames.get("log pose") == {"ned"}, frames)
        live_ell, log_ell = ellipses(live, vid), ellipses(log, vid)
        common = sorted(set(live_ell) & set(log_ell))
        check("vehicle %d: live and logged ellipses at %d common times" % (vid, len(common)), len(common) >= 5,
              (len(live_ell), len(log_ell)))
        differ = [t for t in common if live_ell[t][1] != log_ell[t][1]]
        check("vehicle %d: live and logged ellipses identical" % vid, not differ,
              differ[:3] and (live_ell[differ[0]], log_ell[differ[0]]))
        e = v["estimate"]
        t_us = round(e["t_s"] * 1e6)
        page = e["ellipse95"]
        drawn = log_ell.get(t_us)
        check("vehicle %d: the page's newest estimate (t_us %d) is drawn in the log" % (vid, t_us),
              drawn is not None and live_ell.get(t_us) == drawn, sorted(log_ell)[-3:])
        if drawn and page:
            sphere = drawn[1]
            major, minor = sphere["size"]["x"] / 2, sphere["size"]["y"] / 2
            bearing = math.degrees(quat_yaw(sphere["pose"]["orientation"]))
            d = (bearing - page["major_bearing_deg"] + 180.0) % 360.0 - 180.0
            check("vehicle %d: the page's ellipse is the one Foxglove draws" % vid,
                  abs(major - page["semi_major_m"]) <= 1e-9 * max(1.0, major)
                  and abs(minor - page["semi_minor_m"]) <= 1e-9 * max(1.0, major) and abs(d) < 1e-7,
                  ((major, minor, bearing), page))
            pos = sphere["pose"]["position"]
            check("vehicle %d: at the page's position" % vid,
                  abs(pos["x"] - e["pos_ned_m"][0]) < 1e-9 and abs(pos["y"] - e["pos_ned_m"][1]) < 1e-9, (pos, e["pos_ned_m"]))
    health_live, health_log = by_topic(live, "/team/health"), by_topic(log, "/team/health")
    check("team health live and logged", len(health_live) > 0 and len(health_log) > 0, (len(health_live), len(health_log)))
    if health_live:
        names = {n["id"]: (n["name"], n["color"]) for n in health_live[-1]["nodes"]}
        check("team health names and colours are the page's",
              all(names.get(vid) == (v["style"]["name"], v["style"]["color"]) for vid, v in vehicles.items()), names)
    print("view_agreement_check: %d failed" % failures)
    sys.exit(1 if failures else 0)


def main():
    if len(sys.argv) >= 2 and sys.argv[1] == "listen":
        import argparse

        ap = argparse.ArgumentParser()
        ap.add_argument("mode")
        ap.add_argument("url")
        ap.add_argument("out")
        ap.add_argument("--vehicles", required=True)
        ap.add_argument("--until-t", type=float, required=True)
        ap.add_argument("--timeout", type=float, default=90.0)
        a = ap.parse_args()
        listen(a.url, a.out, [int(x) for x in a.vehicles.split(",")], a.until_t, a.timeout)
    elif len(sys.argv) == 5 and sys.argv[1] == "compare":
        compare(sys.argv[2], sys.argv[3], sys.argv[4])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
