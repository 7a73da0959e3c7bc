"""The cooploc Python package (python/, issue 35) as a user meets it, under pytest: installed in the
test virtualenv by tests/run-all.sh, imported by name, each function against the library's result
handed over by tests/python_package.rs, and bad input answered with a Python exception, never a
crash (a crash ends pytest with a failure). The Rust test writes what the library computes (frames
as hex, expected values) to a JSON file named by COOPLOC_BINDINGS_SPEC.

The checks run in order as the module loads (later ones use the objects earlier ones made); each
becomes one pytest test, `test_binding[WHAT]`, that fails with what it found:

    COOPLOC_BINDINGS_SPEC=spec.json .venv/bin/python -m pytest -q tests/python/test_bindings.py
"""

import json
import math
import os

import pytest

CHECKS = []  # (what, ok, detail), in the order they ran


def check(what, ok, detail=""):
    CHECKS.append((what, bool(ok), detail))


def raises(exc, fn, *args, **kwargs):
    try:
        fn(*args, **kwargs)
    except exc as e:
        return str(e) or type(e).__name__
    except Exception:  # the wrong exception is a failure too
        return None
    return None


import cooploc  # noqa: E402  (an ImportError here fails the collection: pytest exits non-zero)

if "COOPLOC_BINDINGS_SPEC" not in os.environ:
    raise RuntimeError("COOPLOC_BINDINGS_SPEC names no file: tests/python_package.rs writes it (cargo test --test python_package)")
spec = json.load(open(os.environ["COOPLOC_BINDINGS_SPEC"]))

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
      cooploc.check_frame(bytes.fromhex(spec["epoch_frame"])) == ("COOPLOC_EPOCH_SET", [1, 2, 3]))
check("check_frame: an epoch in the list form and its participants",
      cooploc.check_frame(bytes.fromhex(spec["epoch_list_frame"])) == ("COOPLOC_EPOCH", [1, 2, 3]))
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

# A team of planar robots stepped from numpy: the paper's decentralized method (each robot's own
# filter, Psi and the store of Eq. 10) against a joint EKF over the whole team written here in
# numpy, on the same wheel samples and ranges: equal to rounding. The naive method (no
# cross-covariances) is not, so the reference can tell.
def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi

def joint_ekf_vs_team(method="dcl", seed=3, seconds=20.0, rate=10.0):
    rng = np.random.default_rng(seed)
    n = 3
    truth = np.array([[0.0, 0.0, 0.3], [20.0, 5.0, 1.2], [-10.0, 15.0, -0.7]])
    est0 = truth + np.column_stack([rng.normal(0, 0.1, n), rng.normal(0, 0.1, n), rng.normal(0, 0.01, n)])
    ss, ws, ps, ys = 0.05, 0.01, 0.1, 0.01
    team = cooploc.PlanarTeam(method, est0, pos_sigma_m=ps, yaw_sigma_rad=ys, speed_sigma_m_s=ss, yaw_rate_sigma_rad_s=ws, rate_hz=rate)
    x = est0.copy()
    P = np.diag(np.tile([ps**2, ps**2, ys**2], n))
    sn2 = (ss * math.sqrt(1 / rate)) ** 2
    wn2 = (ws * math.sqrt(1 / rate)) ** 2
    dt = 1.0 / rate
    steps = int(seconds * rate)
    nis = []
    for k in range(1, steps + 1):
        t = k * dt
        v_true = np.array([1.0, 1.5, 0.8])
        w_true = np.array([0.05 * math.sin(0.3 * t), -0.04, 0.03 * math.cos(0.2 * t)])
        for i in range(n):
            truth[i, 0] += v_true[i] * math.cos(truth[i, 2]) * dt
            truth[i, 1] += v_true[i] * math.sin(truth[i, 2]) * dt
            truth[i, 2] = wrap(truth[i, 2] + w_true[i] * dt)
        v = v_true + rng.normal(0, ss, n)
        w = w_true + rng.normal(0, ws, n)
        team.propagate(t, v, w)
        Phi = np.eye(3 * n)
        Q = np.zeros((3 * n, 3 * n))
        for i in range(n):
            s_, c_ = math.sin(x[i, 2] + 0.5 * w[i] * dt), math.cos(x[i, 2] + 0.5 * w[i] * dt)
            b = 3 * i
            Phi[b, b + 2] = -v[i] * s_ * dt
            Phi[b + 1, b + 2] = v[i] * c_ * dt
            G = np.array([[c_ * dt, -v[i] * s_ * dt * dt / 2], [s_ * dt, v[i] * c_ * dt * dt / 2], [0.0, dt]])
            Q[b:b + 3, b:b + 3] = G @ np.diag([sn2 / dt, wn2 / dt]) @ G.T
            x[i] += [v[i] * c_ * dt, v[i] * s_ * dt, w[i] * dt]
            x[i, 2] = wrap(x[i, 2])
        P = Phi @ P @ Phi.T + Q
        P = 0.5 * (P + P.T)
        if k % int(rate) == 0:
            pairs, z = [], []
            for i in range(n):
                for j in range(i + 1, n):
                    pairs.append((i + 1, j + 1))
                    z.append(math.hypot(*(truth[i, :2] - truth[j, :2])) + rng.normal(0, 0.1))
            got = team.ranges(np.array(pairs, dtype=np.int64), np.array(z), 0.1)
            H = np.zeros((len(z), 3 * n))
            r = np.zeros(len(z))
            for m, ((a, b), zm) in enumerate(zip(pairs, z)):
                i, j = a - 1, b - 1
                d = x[i, :2] - x[j, :2]
                h = math.hypot(*d)
                H[m, 3 * i:3 * i + 2] = d / h
                H[m, 3 * j:3 * j + 2] = -d / h
                r[m] = zm - h
            R = 0.01 * np.eye(len(z))
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            dx = K @ r
            x += dx.reshape(n, 3)
            x[:, 2] = [wrap(a) for a in x[:, 2]]
            IKH = np.eye(3 * n) - K @ H
            P = IKH @ P @ IKH.T + K @ R @ K.T
            P = 0.5 * (P + P.T)
            nis.append((got, float(r @ np.linalg.solve(S, r))))
    poses, covs = team.poses(), team.covariances()
    blocks = np.array([P[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
    dpose = np.abs(poses - x)
    dpose[:, 2] = [abs(wrap(a)) for a in (poses[:, 2] - x[:, 2])]
    nis_diff = max((abs(a - b) / b for a, b in nis if a is not None), default=float("nan"))
    return float(dpose.max()), float(np.abs(covs - blocks).max() / np.abs(blocks).max()), nis_diff


pose_d, cov_d, nis_d = joint_ekf_vs_team("dcl")
check("PlanarTeam dcl equals a joint EKF over the team (poses, covariances, NIS to 1e-9)",
      pose_d < 1e-9 and cov_d < 1e-9 and nis_d < 1e-9, (pose_d, cov_d, nis_d))
pose_n, cov_n, _ = joint_ekf_vs_team("naive")
check("PlanarTeam naive does not (the reference tells them apart)", pose_n > 0.01 and cov_n > 0.01, (pose_n, cov_n))
team = cooploc.PlanarTeam("dcl", np.zeros((2, 3)))
before = team.poses()
check("PlanarTeam: poses of shape (n, 2) -> ValueError", raises(ValueError, cooploc.PlanarTeam, "dcl", np.zeros((2, 2))) is not None)
check("PlanarTeam: an unknown method -> ValueError", raises(ValueError, cooploc.PlanarTeam, "kalman", np.zeros((2, 3))) is not None)
check("PlanarTeam: three speeds for two robots -> ValueError",
      raises(ValueError, team.propagate, 0.1, np.ones(3), np.zeros(3)) is not None)
check("PlanarTeam: a NaN speed -> ValueError", raises(ValueError, team.propagate, 0.1, np.array([1.0, float("nan")]), np.zeros(2)) is not None)
check("PlanarTeam: a gap longer than the model's -> ValueError, nothing stepped",
      raises(ValueError, team.propagate, 100.0, np.ones(2), np.zeros(2)) is not None and np.array_equal(team.poses(), before))
check("PlanarTeam: a range to a stranger -> ValueError",
      raises(ValueError, team.ranges, np.array([[1, 7]]), np.array([3.0]), 0.1) is not None)
check("PlanarTeam: pairs and ranges of different lengths -> ValueError",
      raises(ValueError, team.ranges, np.array([[1, 2]]), np.array([3.0, 4.0]), 0.1) is not None)
check("PlanarTeam: pairs of floats -> TypeError/ValueError",
      raises((TypeError, ValueError), team.ranges, np.array([[1.0, 2.0]]), np.array([3.0]), 0.1) is not None)
team.propagate(0.1, np.array([1.0, 1.0]), np.zeros(2))
check("PlanarTeam: time going back -> ValueError", raises(ValueError, team.propagate, 0.05, np.ones(2), np.zeros(2)) is not None)

# A team of INS vehicles stepped from numpy over one run of the paper scenario (its arrays from
# scenario_run) ends where the library's experiment filter of the same method ends, to the last
# bit: IMU, then odometer, then ranges at each instant, as `cooploc experiment` steps them.
ins = spec["ins_team"]
sr = cooploc.scenario_run(ins["scenario"], ins["seed"], ins["run"], ins["schedule"])
plats = sr["platforms"]
check("scenario_run: the paper's three platforms", sr["ids"] == [p["id"] for p in plats] and len(plats) == 3, sr["ids"])
imu_t, odo_t = plats[0]["imu_t_s"], plats[0]["odometer_t_s"]
check("scenario_run: every platform's IMU and odometer on the same instants (the paper's)",
      all(np.array_equal(p["imu_t_s"], imu_t) and np.array_equal(p["odometer_t_s"], odo_t) for p in plats))
force = np.stack([p["specific_force_frd_m_s2"] for p in plats], axis=1)
rate = np.stack([p["angular_rate_frd_rad_s"] for p in plats], axis=1)
speed = np.stack([p["speed_m_s"] for p in plats], axis=1)
epochs = sr["epochs"]


def ins_team(method):
    return cooploc.InsTeam(method, np.array([p["position_ned_m"] for p in plats]),
                           np.array([p["velocity_ned_m_s"] for p in plats]), np.array([p["attitude_wxyz"] for p in plats]),
                           sr["ins_config"], sr["initial_sigma"], ids=sr["ids"], t0_s=plats[0]["t0_s"])


def step_run(team):
    o = e = 0

    def due(upto, strictly):
        nonlocal o, e
        while o < len(odo_t) and (odo_t[o] < upto if strictly else odo_t[o] <= upto):
            team.odometer(odo_t[o], speed[o])
            o += 1
        while e < len(epochs) and (epochs[e][0] < upto if strictly else epochs[e][0] <= upto):
            team.ranges(epochs[e][1], epochs[e][2], epochs[e][3])
            e += 1

    for k in range(len(imu_t)):
        due(imu_t[k], True)
        team.imu(imu_t[k], force[k], rate[k])
        due(imu_t[k], False)
    due(float("inf"), False)
    return team


for method, expected in sorted(ins["final_positions"].items()):
    got = step_run(ins_team(method)).positions()
    check("InsTeam %s over a paper run ends where the experiment's filter ends, to the last bit" % method,
          np.array_equal(got, np.array(expected)), (got.tolist(), expected))
team = ins_team("dcl")
pos0 = team.positions()
check("InsTeam: positions of shape (3, 2) -> ValueError",
      raises(ValueError, cooploc.InsTeam, "dcl", np.zeros((3, 2)), np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)),
             sr["ins_config"], sr["initial_sigma"]) is not None)
check("InsTeam: a zero quaternion -> ValueError",
      raises(ValueError, cooploc.InsTeam, "dcl", np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 4)),
             sr["ins_config"], sr["initial_sigma"]) is not None)
bad_config = dict(sr["ins_config"], gyro_noise=1.0)
check("InsTeam: an unknown ins_config field -> ValueError naming it",
      "gyro_noise" in (raises(ValueError, cooploc.InsTeam, "dcl", np.zeros((3, 3)), np.zeros((3, 3)),
                              np.tile([1.0, 0, 0, 0], (3, 1)), bad_config, sr["initial_sigma"]) or ""))
no_sigma = {k: v for k, v in sr["initial_sigma"].items() if k != "pos_ned_m"}
check("InsTeam: an initial_sigma without pos_ned_m -> ValueError naming it",
      "pos_ned_m" in (raises(ValueError, cooploc.InsTeam, "dcl", np.zeros((3, 3)), np.zeros((3, 3)),
                             np.tile([1.0, 0, 0, 0], (3, 1)), sr["ins_config"], no_sigma) or ""))
check("InsTeam: a NaN specific force -> ValueError",
      raises(ValueError, team.imu, imu_t[0], np.full((3, 3), float("nan")), rate[0]) is not None)
check("InsTeam: IMU for a stranger -> ValueError", raises(ValueError, team.imu, imu_t[0], force[0][:1], rate[0][:1], ids=[9]) is not None)
check("InsTeam: an odometer at a time the vehicles are not at -> ValueError",
      raises(ValueError, team.odometer, imu_t[3], speed[0]) is not None)
check("InsTeam: a range to a stranger -> ValueError",
      raises(ValueError, team.ranges, np.array([[1, 9]]), np.array([3.0]), np.array([0.1])) is not None)
check("InsTeam: a zero range sigma -> ValueError",
      raises(ValueError, team.ranges, np.array([[1, 2]]), np.array([3.0]), np.array([0.0])) is not None)
check("InsTeam: the refused inputs left the team where it was",
      np.array_equal(team.positions(), pos0) and team.times() == [plats[0]["t0_s"]] * 3, team.times())
team.imu(imu_t[1], force[1], rate[1])
check("InsTeam: time going back -> ValueError, nothing stepped",
      raises(ValueError, team.imu, imu_t[0], force[0], rate[0]) is not None and team.times() == [imu_t[1]] * 3)
check("scenario_run: a schedule the scenario lacks -> ValueError",
      raises(ValueError, cooploc.scenario_run, ins["scenario"], 1, 0, "7hz") is not None)

# Each vehicle's series in the committed log and in its first 40 %, as the library reads them.
for name, path in [("full", spec["log"]["path"]), ("cut", spec["cut_log"]["path"])]:
    got = cooploc.log_series(path)
    for want in spec["log_series"][name]:
        v = got.get(want["id"])
        check("log_series (%s log): vehicle %d there" % (name, want["id"]), v is not None, sorted(got))
        if v is None:
            continue
        est, truth, upd = v["estimate"], v["truth"], v["updates"]
        check("log_series (%s log): vehicle %d's estimates, truth and updates as the library reads them" % (name, want["id"]),
              est["position_ned_m"].shape == (want["estimate_n"], 3) and truth["position_ned_m"].shape == (want["truth_n"], 3)
              and len(est["yaw_rad"]) == want["estimate_n"] and len(est["log_time_s"]) == want["estimate_n"]
              and (want["estimate_n"] == 0 or (est["position_ned_m"][-1].tolist() == want["estimate_last"]
                                              and est["yaw_rad"][-1] == want["estimate_yaw_last"]))
              and (want["truth_n"] == 0 or truth["position_ned_m"][-1].tolist() == want["truth_last"])
              and upd["epoch"].tolist() == want["epochs"] and upd["nis"].tolist() == want["nis"]
              and v["undecodable"] == want["undecodable"],
              (est["position_ned_m"].shape, truth["position_ned_m"].shape, upd["epoch"].tolist()[-3:]))
    check("log_series (%s log): no other vehicle" % name, sorted(got) == [w["id"] for w in spec["log_series"][name]], sorted(got))
check("log_series: the cut log holds fewer estimates than the whole",
      all(c["estimate_n"] < f["estimate_n"] for c, f in zip(spec["log_series"]["cut"], spec["log_series"]["full"])))
check("log_series: not a log -> ValueError", raises(ValueError, cooploc.log_series, spec["not_a_log"]) is not None)
check("log_series: no file -> OSError", raises(OSError, cooploc.log_series, spec["no_file"]) is not None)

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



@pytest.mark.parametrize("what,ok,detail", CHECKS, ids=[c[0] for c in CHECKS])
def test_binding(what, ok, detail):
    assert ok, "%s: %r" % (what, detail)
