"""The cooploc Python package (python/, issue 35) as a user meets it: installed in the test
virtualenv by tests/run-all.sh, imported by name, each function against the library's result
passed in by tests/python_package.rs, and bad input answered with a Python exception, never a
crash. Argument: a JSON file written by the Rust test (frames as hex, expected values).
Prints PASS/FAIL lines and exits 1 on any failure."""

import json
import math
import os
import sys

failures = []


def check(what, ok, detail=""):
    print("%s %s%s" % ("PASS" if ok else "FAIL", what, "" if ok else ": %r" % (detail,)))
    if not ok:
        failures.append(what)


def raises(exc, fn, *args, **kwargs):
    try:
        fn(*args, **kwargs)
    except exc as e:
        return str(e) or type(e).__name__
    except Exception:  # the wrong exception is a failure too
        return None
    return None


import cooploc  # noqa: E402  (after the helpers: an ImportError here is the first failure)

spec = json.load(open(sys.argv[1]))

check("version", cooploc.__version__ == spec["version"], cooploc.__version__)
here = os.path.realpath(os.path.dirname(cooploc.__file__))
check("the package is this checkout's python/cooploc", here == os.path.realpath(spec["package_dir"]), here)

# The frames of a datagram: three frames with noise between them, as the node's framer reads it.
data = bytes.fromhex(spec["datagram"])
got = cooploc.frames(data)
want = [tuple(f) for f in spec["datagram_frames"]]
check("frames: every frame of a datagram with noise between them", got == want, (got, want))
check("frames: nothing in garbage", cooploc.frames(b"\xfd\x00garbage" * 10) == [])
check("frames: a datagram cut short loses its last frame only", cooploc.frames(data[:-1]) == want[:-1])

# An estimate frame, checked as the ground station checks it.
e = cooploc.estimate_from_frame(bytes.fromhex(spec["estimate_frame"]))
x = spec["estimate"]
check("estimate: platform, epoch, method", (e["platform"], e["epoch"], e["method"]) == (x["platform"], x["epoch"], x["method"]), e)
check("estimate: position and covariance as the wire carries them (f32)",
      all(abs(a - b) <= 1e-6 * max(1.0, abs(b)) for a, b in zip(e["position_ned_m"], x["position_ned_m"]))
      and all(abs(a - b) <= 1e-6 * max(1.0, abs(b)) for a, b in zip(e["pos_covariance"], x["pos_covariance"])), e)
for name in ("estimate_wrong_system", "estimate_nan", "estimate_negative_variance", "heartbeat_frame"):
    msg = raises(ValueError, cooploc.estimate_from_frame, bytes.fromhex(spec[name]))
    check("estimate: %s refused with ValueError" % name, msg is not None, msg)
    print("     (%s)" % msg)
damaged = bytearray(bytes.fromhex(spec["estimate_frame"]))
damaged[12] ^= 0x40
check("estimate: a damaged byte (CRC) refused", raises(ValueError, cooploc.estimate_from_frame, bytes(damaged)) is not None)
check("estimate: a truncated frame refused", raises(ValueError, cooploc.estimate_from_frame, bytes(damaged[:20])) is not None)
check("estimate: no bytes refused", raises(ValueError, cooploc.estimate_from_frame, b"") is not None)
check("estimate: not bytes -> TypeError", raises(TypeError, cooploc.estimate_from_frame, 42) is not None)

# Any cooploc message, checked as the node checks it.
check("check_frame: an epoch and its participants",
      cooploc.check_frame(bytes.fromhex(spec["epoch_frame"])) == ("COOPLOC_EPOCH", [1, 2, 3]))
check("check_frame: a range", cooploc.check_frame(bytes.fromhex(spec["range_frame"])) == ("COOPLOC_RANGE", None))
check("check_frame: a heartbeat is not checked", cooploc.check_frame(bytes.fromhex(spec["heartbeat_frame"])) == ("HEARTBEAT", None))
for name in ("epoch_twice", "epoch_other_announcer", "range_negative", "range_other_system", "estimate_nan"):
    msg = raises(ValueError, cooploc.check_frame, bytes.fromhex(spec[name]))
    check("check_frame: %s refused with ValueError" % name, msg is not None, msg)
    print("     (%s)" % msg)
check("check_frame: garbage refused", raises(ValueError, cooploc.check_frame, b"\xfd" + bytes(40)) is not None)
check("PALETTE is the library's", list(cooploc.PALETTE) == spec["palette"], cooploc.PALETTE)

# Logs: a committed one, the same cut short (its writer killed), not a log, no file.
for key, end in (("log", "complete"), ("cut_log", "truncated")):
    want = spec[key]
    d = cooploc.read_log(want["path"])
    check("read_log %s: %d messages, end %s" % (key, want["messages"], d["end"]),
          len(d["messages"]) == want["messages"] and (d["end"] == "complete") == want["complete"]
          and (d["end"] == end or not want["complete"]), (len(d["messages"]), d["end"]))
    check("read_log %s: topic counts and metadata" % key,
          d["topics"].get("/coop/1/rx", (None, None, 0))[2] == want["coop_1_rx"]
          and sorted(d["metadata"]) == sorted(want["metadata"]), (d["topics"].get("/coop/1/rx"), sorted(d["metadata"])))
    only = cooploc.read_log(want["path"], topics=["/vehicle_1/internals"])["messages"]
    epochs = [json.loads(data)["epoch"] for topic, _, data in only]
    check("read_log %s: the internals of vehicle 1, JSON, in order" % key,
          epochs == want["internals_epochs"] and all(t == "/vehicle_1/internals" for t, _, _ in only), epochs[:5])
check("read_log: not MCAP -> ValueError", raises(ValueError, cooploc.read_log, spec["not_a_log"]) is not None)
check("read_log: no file -> OSError", raises(OSError, cooploc.read_log, spec["no_file"]) is not None)
check("read_log: topics not a list of str -> TypeError",
      raises(TypeError, cooploc.read_log, spec["log"]["path"], topics=5) is not None)

# The MRCLAM excerpt: every method in two regimes, the library's figures exactly.
mr = spec["mrclam"]
got = [[o["regime"], o["method"], o["pos_rmse_m"], o["heading_rmse_deg"], o["avg_nees"], o["epochs"], len(o["robots"])]
       for o in cooploc.mrclam(mr["dir"], ["dr", "dcl", "ci"], ["no-landmarks", "full-map"])]
check("mrclam: the table's figures equal the library's run, in (regime, method) order", got == mr["runs"], (got, mr["runs"]))
check("mrclam: an unknown method -> ValueError", raises(ValueError, cooploc.mrclam, mr["dir"], ["kalman"], ["full-map"]) is not None)
check("mrclam: an unknown regime -> ValueError", raises(ValueError, cooploc.mrclam, mr["dir"], ["dr"], ["moon"]) is not None)
check("mrclam: no data set there -> ValueError", raises(ValueError, cooploc.mrclam, spec["no_file"], ["dr"], ["full-map"]) is not None)
check("mrclam: a negative excerpt -> ValueError",
      raises(ValueError, cooploc.mrclam, mr["dir"], ["dr"], ["full-map"], excerpt_s=-1.0) is not None)

# The numbers of the library, as the Rust test computed them.
a, b, bearing = cooploc.ellipse95(*spec["ellipse_in"])
check("ellipse95 equals the library's", [a, b, bearing] == spec["ellipse_out"], (a, b, bearing))
check("position_nees equals the library's", cooploc.position_nees(*spec["nees_in"]) == spec["nees_out"])
check("geo_to_ned equals the library's", list(cooploc.geo_to_ned(*spec["geo_in"], spec["origin"])) == spec["geo_out"])
check("ned_to_geo equals the library's", list(cooploc.ned_to_geo(*spec["ned_in"], spec["origin"])) == spec["ned_out"])

# Wrong shapes and types: an exception, never a crash.
check("position_nees: two error entries -> TypeError/ValueError",
      raises((TypeError, ValueError), cooploc.position_nees, (1.0, 2.0), (1, 0, 0, 1, 0, 1)) is not None)
check("position_nees: five covariance entries -> TypeError/ValueError",
      raises((TypeError, ValueError), cooploc.position_nees, (1.0, 2.0, 0.0), (1, 0, 0, 1, 0)) is not None)
check("position_nees: not positive definite -> None", cooploc.position_nees((1, 0, 0), (1, 2, 0, 1, 0, 1)) is None)
check("ellipse95: a string -> TypeError", raises(TypeError, cooploc.ellipse95, "1", 0.0, 1.0) is not None)
check("ellipse95: NaN -> None", cooploc.ellipse95(float("nan"), 0.0, 1.0) is None)
check("geo_to_ned: an origin at the pole -> ValueError",
      raises(ValueError, cooploc.geo_to_ned, 0.0, 0.0, 0.0, (90.0, 0.0, 0.0)) is not None)
check("geo_to_ned: an origin of two numbers -> TypeError/ValueError",
      raises((TypeError, ValueError), cooploc.geo_to_ned, 0.0, 0.0, 0.0, (34.7, 0.0)) is not None)
check("geo_to_ned: NaN origin -> ValueError",
      raises(ValueError, cooploc.geo_to_ned, 0.0, 0.0, 0.0, (math.nan, 0.0, 0.0)) is not None)
check("MAVProxy's entry point is the package's", callable(getattr(cooploc, "init", None)))

# The one sequence rule: numbers outside a byte refused, nothing counted for them.
t = cooploc.SequenceTracker()
for q in (10, 13, 12, 14, 14):
    t.observe(q)
check("SequenceTracker: gap, late, repeat", (t.received, t.lost, t.late, t.repeats, t.last) == (5, 1, 1, 1, 14), t)
check("SequenceTracker: 256 -> ValueError", raises(ValueError, t.observe, 256) is not None)
check("SequenceTracker: -1 -> ValueError", raises(ValueError, t.observe, -1) is not None)
check("SequenceTracker: a string -> TypeError", raises(TypeError, t.observe, "7") is not None)
check("SequenceTracker: refused numbers count nothing", t.received == 5, t)

# The ground station's rate window: per second over the window, bounded at any rate.
w = cooploc.RateWindow(2.0)
for i in range(50):
    w.add(100.0 + i * 0.1, 100)  # 1000 a second for 5 s
check("RateWindow: the rate over its window", abs(w.rate(104.9) - 1000.0) <= 1000.0 / 40 + 50, w.rate(104.9))
check("RateWindow: nothing once silent", w.total(120.0) == 0 and w.rate(120.0) == 0.0)
check("RateWindow: a NaN time -> ValueError", raises(ValueError, w.add, float("nan")) is not None)
check("RateWindow: a negative amount -> OverflowError/TypeError/ValueError",
      raises((OverflowError, TypeError, ValueError), w.add, 1.0, -5) is not None)
check("RateWindow: a zero window -> ValueError", raises(ValueError, cooploc.RateWindow, 0.0) is not None)

# A committed log replayed, and three methods run on its inputs: numpy arrays, the library's figures.
import numpy as np  # noqa: E402
rp = cooploc.replay(spec["log"]["path"])
for nid, same, imu, count, last_n in spec["replay"]["nodes"]:
    node = rp[nid]
    rec = node["recorded"]
    check("replay: node %d as the library replays it" % nid, node["identical"] == same and node["imu_replayed"] == imu
          and isinstance(rec["position_ned_m"], np.ndarray) and rec["position_ned_m"].shape == (count, 3)
          and rec["position_covariance_m2"].shape == (count, 3, 3) and rec["t_s"].shape == (count,)
          and float(rec["position_ned_m"][-1, 0]) == last_n, (node["identical"], node["imu_replayed"], rec["position_ned_m"].shape))
    check("replay: node %d's covariances are symmetric" % nid,
          np.array_equal(rec["position_covariance_m2"], np.transpose(rec["position_covariance_m2"], (0, 2, 1))))
cm = cooploc.compare_methods(spec["log"]["path"], ["dr", "dcl", "ci"])
for method, pid, n, err, heading, nees in spec["replay"]["compared"]:
    d = cm[method][pid]
    check("compare_methods: %s platform %d as the library runs it" % (method, pid),
          d["t_s"].shape == (n,) and d["pos_err_ne_m"].shape == (n, 2) and float(d["pos_err_m"][-1]) == err
          and float(d["heading_err_deg"][-1]) == heading and d["final_nees"] == nees,
          (d["t_s"].shape, float(d["pos_err_m"][-1]), err))
check("compare_methods: an unknown method -> ValueError",
      raises(ValueError, cooploc.compare_methods, spec["log"]["path"], ["kalman"]) is not None)
check("replay: not a log -> ValueError", raises(ValueError, cooploc.replay, spec["not_a_log"]) is not None)
check("replay: no file -> OSError", raises(OSError, cooploc.replay, spec["no_file"]) is not None)

# The ground station's truth track: bad input is an exception, never a crash.
tt = cooploc.TruthTrack()
check("TruthTrack: a NaN position -> ValueError", raises(ValueError, tt.sim_state, (float("nan"), 0.0, 0.0)) is not None)
check("TruthTrack: two coordinates -> TypeError/ValueError", raises((TypeError, ValueError), tt.sim_state, (1.0, 2.0)) is not None)
check("TruthTrack: five covariance entries -> TypeError/ValueError",
      raises((TypeError, ValueError), tt.estimate, 1, (0.0, 0.0, 0.0), (1, 0, 0, 1, 0)) is not None)
check("TruthTrack: a negative time -> OverflowError/TypeError/ValueError",
      raises((OverflowError, TypeError, ValueError), tt.timed, -1) is not None)
check("sim_state_from_frame: garbage -> ValueError", raises(ValueError, cooploc.sim_state_from_frame, b"\xfd" + bytes(30), (34.7, 0.0, 0.0)) is not None)
check("sim_state_from_frame: no bytes -> ValueError", raises(ValueError, cooploc.sim_state_from_frame, b"", (34.7, 0.0, 0.0)) is not None)

print("bindings_check: %d failed%s" % (len(failures), (": " + "; ".join(failures)) if failures else ""))
sys.exit(1 if failures else 0)
