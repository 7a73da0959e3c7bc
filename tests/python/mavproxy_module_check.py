"""The MAVProxy module tools/mavproxy/mavproxy_cooploc.py against a live team.

Usage: mavproxy_module_check.py COOPLOC_BINARY

1. The module's pure functions, without MAVProxy: the 95 % ellipse of a known covariance and its
   map polygon, the disagreement/heal counters on a synthetic sequence of epoch reports, the
   flat-Earth origin conversion, the sequence-loss counter across the wrap at 255; the error
   against the truth: the inverse conversion (round trip to 1e-9 m), interpolation, NEES (known
   value, P not positive definite), SIM_STATE stamping by the next timed frame, estimates held
   until the truth covers them, SIM_STATE validation. Then the module in a stand-in MAVProxy
   (no process, no wx), with a simulator's SIM_STATE / HIGHRES_IMU / ODOMETRY for the error.
2. A live run (about 30 s): `cooploc sitl` (paper scenario, speed 2), three `cooploc node`s that
   log to MCAP, and MAVProxy with the cooploc dialect (MDEF, --dialect cooploc) and
   `module load cooploc`, its masters the three vehicles and the three nodes' cooperative
   sockets, target system 1. Commands reach MAVProxy on its stdin (it reads commands there when
   neither --daemon nor --non-interactive is given): `cooploc refresh 0`, then `cooploc status`.
   Then everything is stopped (the nodes with SIGTERM, which finishes their logs) and checked:
   - the module loaded, no Python traceback in MAVProxy's output, no module error;
   - `cooploc status` lists vehicles 1, 2, 3, each with an estimate that equals, field for field
     (repr of the decoded floats), the COOPLOC_ESTIMATE of the same time_usec in the node's own log
     (/coop/<id>/tx), and the ellipse computed from that message;
   - MAVProxy's tlog has each vehicle's HEARTBEAT (type 10, ground rover, from (id, 1)) and each
     node's (type 18 from (id, 191)); PARAM_VALUE SYSID_THISMAV = 1 from system 1, and MAVProxy
     said it received all parameters;
   - after `cooploc refresh 0`, at least one accepted COMMAND_ACK (REQUEST_MESSAGE) per vehicle;
   - the status file (`cooploc set statusfile`) was written every second;
   - per vehicle `error_m` (below LIVE_ERROR_BOUND_M), a finite `nees`, and `error_t_us` an
     estimate time in the node's log (the truth: `cooploc sitl`'s SIM_STATE).
Prints one `PASS name` / `FAIL name: why` line per check and exits 1 on any failure.
"""
import importlib.util
import math
import os
import queue
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
MODULE_PATH = os.path.join(ROOT, "python", "cooploc", "mavproxy.py")
FIELDS = ("x", "y", "z", "vx", "vy", "vz", "yaw", "nis")

results = []


def check(name, ok, why=""):
    results.append((name, bool(ok)))
    print(("PASS %s" % name) if ok else ("FAIL %s: %s" % (name, why)), flush=True)


def load_module():
    sys.dont_write_bytecode = True  # no __pycache__ in tools/mavproxy
    spec = importlib.util.spec_from_file_location("mavproxy_cooploc", MODULE_PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# ---- 1. pure functions ------------------------------------------------------------------------

def pure_checks(cl):
    close = lambda a, b, tol=1e-9: abs(a - b) <= tol  # noqa: E731

    # A covariance whose 95 % semi-axes are 3 m and 1 m, the major one 30 deg east of north.
    def cov(a, b, bearing_deg):
        l1, l2 = a * a / cl.CHI2_2DOF_95, b * b / cl.CHI2_2DOF_95
        c, s = math.cos(math.radians(bearing_deg)), math.sin(math.radians(bearing_deg))
        return (l1 * c * c + l2 * s * s, (l1 - l2) * c * s, l1 * s * s + l2 * c * c)

    e = cl.ellipse95(*cov(3.0, 1.0, 30.0))
    check("ellipse 3 m x 1 m at 30 deg", e and close(e[0], 3.0) and close(e[1], 1.0) and close(e[2], 30.0), e)
    e2 = cl.ellipse95(*cov(2.0, 0.5, -60.0))
    check("ellipse bearing -60 deg", e2 and close(e2[2], -60.0) and close(e2[0], 2.0), e2)
    e3 = cl.ellipse95(*cov(2.0, 0.5, 120.0))  # the same axis as -60
    check("ellipse bearing in (-90, 90]", e3 and close(e3[2], -60.0), e3)
    e4 = cl.ellipse95(1.0, 0.0, 4.0)
    check("ellipse along east is +90", e4 and close(e4[2], 90.0) and close(e4[0], math.sqrt(4 * cl.CHI2_2DOF_95)), e4)
    check("ellipse of NaN / negative is None",
          cl.ellipse95(float("nan"), 0, 1) is None and cl.ellipse95(-1.0, 0.0, -1.0) is None)
    pts = cl.ellipse_points_ne(10.0, -5.0, 3.0, 1.0, 30.0, segments=36)
    b = math.radians(30.0)
    on = all(close(((n - 10) * math.cos(b) + (ee + 5) * math.sin(b)) ** 2 / 9.0
                   + (-(n - 10) * math.sin(b) + (ee + 5) * math.cos(b)) ** 2 / 1.0, 1.0, 1e-9) for n, ee in pts)
    tip = pts[0]
    check("ellipse polygon: closed, on the ellipse, major tip at the bearing",
          len(pts) == 37 and pts[0] == pts[-1] and on
          and close(tip[0], 10 + 3 * math.cos(b)) and close(tip[1], -5 + 3 * math.sin(b)), pts[:2])
    poly = cl.ellipse_polygon_latlon(0.0, 0.0, (3.0, 1.0, 30.0), (34.7, 0.0, 0.0), segments=8)
    check("ellipse polygon in lat/lon", len(poly) == 9 and all(len(p) == 2 for p in poly)
          and close(poly[0][0], 34.7 + math.degrees(3 * math.cos(b) / 6378137.0), 1e-12), poly[0])

    # Origin: lat = lat0 + deg(N / R), lon = lon0 + deg(E / (R cos lat0)), alt = alt0 - D.
    lat, lon, alt = cl._cooploc.ned_to_geo(1000.0, -2000.0, -5.0, (34.7, 1.5, 10.0))
    R = 6378137.0
    check("origin conversion", close(lat, 34.7 + math.degrees(1000.0 / R), 1e-12)
          and close(lon, 1.5 + math.degrees(-2000.0 / (R * math.cos(math.radians(34.7)))), 1e-12)
          and close(alt, 15.0), (lat, lon, alt))
    check("default origin 34.7 0 0", tuple(cl.DEFAULT_ORIGIN) == (34.7, 0.0, 0.0), cl.DEFAULT_ORIGIN)

    # Sequence loss, the library's one rule (cooploc.SequenceTracker, protocol::sequence): across
    # the wrap 250..255, 0, (1 lost), 2, 3; then 3 -> 7 (4, 5, 6 lost); 5 late (its loss taken
    # back); 7 again (a repeat); 200 -> a restarted sender (followed, nothing lost).
    s = cl._cooploc.SequenceTracker()
    for q in (250, 251, 252, 253, 254, 255, 0, 2, 3, 7):
        s.observe(q)
    check("sequence loss with wrap at 255", s.received == 10 and s.lost == 4 and close(s.loss_fraction(), 4 / 14),
          (s.received, s.lost))
    for q in (5, 7, 200, 201):
        s.observe(q)
    check("late, repeated and restarted senders are not loss", (s.lost, s.late, s.repeats, s.restarts, s.last)
          == (3, 1, 1, 1, 201), s)
    check("no sequence rule of the module's own", not hasattr(cl, "SeqLoss") and not hasattr(cl, "seq_gap"))

    # Epoch reports, by the library's tally (cooploc.EpochTally, view::health): agree, disagree
    # (3's digest), disagree (2's participants), agree.
    check("no tally of the module's own", not hasattr(cl, "EpochTracker") and not hasattr(cl, "majority_pair"))
    T = cl._cooploc.EpochTally
    t = T()
    A = cl.EPOCH_APPLIED
    out = lambda tally, a: tally.node(a)["outvoted"]  # noqa: E731
    for a in (1, 2, 3):
        t.add(1, a, A, 7, [1, 2, 3])
    for a, d in ((1, 8), (2, 8), (3, 9)):
        t.add(2, a, A, d, [1, 2, 3])
    for a, p in ((1, [1, 2, 3]), (2, [1, 2]), (3, [1, 2, 3])):
        t.add(3, a, cl.EPOCH_PARTIAL if a == 2 else A, 10, p)
    for a in (1, 2, 3):
        t.add(4, a, A, 11, [1, 2, 3])
    check("agree, disagree, disagree, agree: disagreements 2, heals 1",
          t.disagreements == 2 and t.heals == 1 and t.unhealed_since is None, (t.disagreements, t.heals))
    check("per vehicle: who differed from the majority",
          (out(t, 1), out(t, 2), out(t, 3)) == (0, 1, 1), (out(t, 1), out(t, 2), out(t, 3)))
    check("per vehicle: heals, partial", [t.node(a)["heals"] for a in (1, 2, 3)] == [1, 1, 1]
          and t.node(2)["partial"] == 1 and t.node(1)["partial"] == 0)
    check("repeat report ignored", t.add(4, 1, A, 99, [1]) == "repeat" and t.disagreements == 2 and t.repeats == 1)
    check("collecting is not a report", t.add(5, 1, cl.EPOCH_COLLECTING, 1, [1]) == "ignored")
    check("an unknown state is not a report", t.add(5, 1, 9, 1, [1]) == "ignored")
    t.add(5, 2, cl.EPOCH_STORE_WANTED, 1, [1, 3])
    t.add(5, 2, cl.EPOCH_STORE_WANTED, 1, [1, 3])
    check("store wanted counted once per epoch", t.node(2)["store_wanted"] == 1)
    # Tie of two: the lowest announcer's pair is the majority.
    t2 = T()
    t2.add(1, 5, A, 1, [4, 5])
    t2.add(1, 4, A, 2, [4, 5])
    check("tie goes to the lowest announcer", (out(t2, 4), out(t2, 5)) == (0, 1) and t2.disagreements == 1)
    t2.add(1, 6, A, 1, [4, 5])
    check("majority re-evaluated", (out(t2, 4), out(t2, 5), out(t2, 6)) == (1, 0, 0))
    # No heal by an epoch that is not after the disagreement.
    t3 = T()
    for a, d in ((1, 1), (2, 2)):
        t3.add(10, a, A, d, [1, 2])
    for a in (1, 2):
        t3.add(9, a, A, 5, [1, 2])
    check("an earlier agreeing epoch does not heal", t3.heals == 0 and t3.unhealed_since == 10)
    # A heal taken from the first reports of an epoch is withdrawn when a late one disagrees
    # (the same sequence as src/view/health.rs's test).
    t5 = T()
    for a in (1, 2, 3):
        t5.add(1, a, A, 7, [1, 2, 3])
    for ep in (2, 3):
        for a, d in ((1, 8), (2, 8), (3, 9)):
            t5.add(ep, a, A, d, [1, 2, 3])
    check("a late disagreeing report withdraws the heal",
          (t5.disagreements, t5.heals, t5.unhealed_since) == (2, 0, 3), (t5.disagreements, t5.heals, t5.unhealed_since))
    for a in (1, 2, 3):
        t5.add(4, a, A, 10, [1, 2, 3])
    check("then the next agreeing epoch heals", (t5.heals, t5.unhealed_since) == (1, None), (t5.heals, t5.unhealed_since))
    # Bounded tables.
    t4 = T()
    for ep in range(300):
        t4.add(ep, 1, A, ep, [1, 2])
        t4.add(ep, 2, A, ep + (ep % 2), [1, 2])
    check("at most 256 epochs, evicted ones still counted", t4.epochs_held == 256 and out(t4, 2) == 150
          and t4.disagreements == 150, (t4.epochs_held, out(t4, 2)))
    for a in range(100, 200):
        t4.add(1000, a, A, 0, [a])
    check("at most 64 announcers", len(t4.nodes) == 64 and t4.dropped == 100 - 62, (len(t4.nodes), t4.dropped))

    check("method names", cl.method_name(2) == "decentralized" and cl.method_name(4) == "covariance_intersection")
    check("palette by platform", cl.colour_rgb(1) == (0x1f, 0x77, 0xb4) and cl.colour_rgb(11) == cl.colour_rgb(1)
          and cl.colour_rgb(10) == (0x17, 0xbe, 0xcf))
    check("frame header", cl.frame_header(bytes([0xFD, 9, 1, 0, 42, 3, 191, 0x4A, 0xEE, 0x00]))
          == (61002, 3, 191, 42, 1))
    truth_pure_checks(cl)


def truth_pure_checks(cl):
    """The error against the truth: conversion, interpolation, NEES, stamping, resolution."""
    close = lambda a, b, tol=1e-9: abs(a - b) <= tol  # noqa: E731
    # geo_to_ned inverts ned_to_geo to 1e-9 m; across the antimeridian to 1e-8 m (a longitude
    # near 180 deg is a double with a step of 2.8e-14 deg, 3e-9 m: 1e-9 m is below its resolution).
    def worst_round_trip(origins):
        worst = 0.0
        for origin in origins:
            for ned in ((0.0, 0.0, 0.0), (1000.0, -2000.0, -5.0), (-3000.0, 2500.0, 12.5), (250.0, 1500.0, 0.0)):
                back = cl._cooploc.geo_to_ned(*cl._cooploc.ned_to_geo(*ned, origin), origin)
                worst = max(worst, max(abs(a - b) for a, b in zip(back, ned)))
        return worst
    w = worst_round_trip(((34.7, 0.0, 0.0), (34.7, 1.5, 10.0), (-45.0, -2.0, -3.0)))
    check("truth: geo_to_ned inverts ned_to_geo to 1e-9 m", w <= 1e-9, w)
    w = worst_round_trip(((-45.0, 179.99, -3.0), (60.0, -179.995, 0.0)))
    check("truth: geo_to_ned inverts ned_to_geo across the antimeridian (1e-8 m)", w <= 1e-8, w)
    n, e, d = cl._cooploc.geo_to_ned(34.7 + math.degrees(100.0 / 6378137.0), -179.99, 5.0, (34.7, 179.99, 2.0))
    check("truth: longitude difference the short way round", close(n, 100.0, 1e-6) and close(d, -3.0)
          and close(e, math.radians(0.02) * 6378137.0 * math.cos(math.radians(34.7)), 1e-6), (n, e, d))
    # Interpolation between two samples; a sample's own time; outside the span; across a gap
    # (cooploc.TruthTrack: the ground station's gcs::truth).
    T = cl._cooploc.TruthTrack
    it = T()
    for n, tt in ((0.0, 1_000_000), (10.0, 2_000_000), (0.0, 4_000_000)):
        it.sim_state((n, -0.4 * n, 0.2 * n))
        it.timed(tt)
    p = it.truth_at(1_250_000)
    check("truth: linear interpolation between two samples", p and all(close(a, b) for a, b in zip(p, (2.5, -1.0, 0.5))), p)
    check("truth: a sample's own time, none outside the span or across a gap over 1 s",
          it.truth_at(2_000_000) == (10.0, -4.0, 2.0)
          and it.truth_at(999_999) is None and it.truth_at(4_000_001) is None
          and it.truth_at(3_000_000) is None and T().truth_at(1) is None)
    # NEES.
    nees = cl.position_nees((1.0, 2.0, 0.0), (1.0, 0.0, 0.0, 4.0, 0.0, 1.0))
    check("truth: NEES of e = (1, 2, 0), P = diag(1, 4, 1) is 2", nees is not None and close(nees, 2.0), nees)
    # A full P: e^T P^-1 e by Cramer's rule.
    P = [[4.0, 1.0, 0.5], [1.0, 3.0, -0.25], [0.5, -0.25, 2.0]]
    ev = (1.0, -2.0, 0.5)

    def det(m):
        return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))
    x = [det([[ev[r] if c == k else P[r][c] for c in range(3)] for r in range(3)]) / det(P) for k in range(3)]
    want = sum(a * b for a, b in zip(ev, x))
    got = cl.position_nees(ev, (4.0, 1.0, 0.5, 3.0, -0.25, 2.0))
    check("truth: NEES with correlations", got is not None and close(got, want, 1e-12), (got, want))
    check("truth: NEES of a P not positive definite (or not finite) is None",
          cl.position_nees((1.0, 2.0, 0.0), (1.0, 2.0, 0.0, 1.0, 0.0, 1.0)) is None
          and cl.position_nees((1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 1.0, 0.0, 0.0)) is None
          and cl.position_nees((1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0, 0.0, 1.0)) is None
          and cl.position_nees((1.0, 0.0, 0.0), (float("nan"), 0.0, 0.0, 1.0, 0.0, 1.0)) is None
          and cl.position_nees((1.0, 0.0, 0.0), (1.0, float("inf"), 0.0, 1.0, 0.0, 1.0)) is None
          and cl.position_nees((float("nan"), 0.0, 0.0), (1.0, 0.0, 0.0, 1.0, 0.0, 1.0)) is None)
    # Stamping: a SIM_STATE takes the time of the next timed frame; one still waiting when the
    # next SIM_STATE comes is placed at the last known time; none known: dropped.
    t = T()
    t.sim_state((1.0, 0.0, 0.0))
    t.sim_state((2.0, 0.0, 0.0))          # the first: no time known yet
    t.timed(1_000_000)                     # stamps the second
    t.timed(1_020_000)
    t.sim_state((3.0, 0.0, 0.0))
    t.timed(2_000_000)                     # stamps the third at 2 s
    t.sim_state((4.0, 0.0, 0.0))
    t.sim_state((5.0, 0.0, 0.0))           # the fourth: placed at the last known time, 2 s: equal, dropped
    t.timed(3_000_000)                     # the fifth at 3 s
    check("truth: stamped by the next timed frame, a waiting one at the last known time",
          list(t.times) == [1_000_000, 2_000_000, 3_000_000]
          and [p[0] for p in t.positions] == [2.0, 3.0, 5.0] and t.untimed == 1 and t.stale == 1,
          (list(t.times), list(t.positions), t.untimed, t.stale))
    t.sim_state((6.0, 0.0, 0.0))
    t.timed(2_500_000)                     # a small step back: dropped
    t.sim_state((7.0, 0.0, 0.0))
    t.timed(100_000_000)
    t.sim_state((8.0, 0.0, 0.0))
    t.timed(1_000)                         # 99.999 s back: a restart
    check("truth: a step back is stale, more than 5 s back a restart",
          list(t.times) == [1_000] and t.restarts == 1 and t.stale == 2, (list(t.times), t.restarts, t.stale))
    # Estimates before the truth covers them wait, then resolve.
    t = T()
    cov = (1.0, 0.0, 0.0, 4.0, 0.0, 1.0)
    t.sim_state((0.0, 0.0, 0.0))
    t.timed(1_000_000)
    r0 = t.estimate(500_000, (0.0, 0.0, 0.0), cov)       # before the truth: unavailable
    r1 = t.estimate(1_500_000, (0.0, -2.0, 0.0), cov)    # waits
    r2 = t.estimate(1_800_000, (0.0, 0.0, 0.0), cov)     # waits
    pending = t.pending
    t.sim_state((2.0, 0.0, 0.0))
    r3 = t.timed(2_000_000)
    check("truth: estimates wait for the truth, then resolve (error, NEES)",
          r0 == [] and r1 == [] and r2 == [] and pending == 2 and t.unavailable == 1 and len(r3) == 2
          and r3[0][0] == 1_500_000 and close(r3[0][1], math.sqrt(5.0)) and close(r3[0][2], 2.0)
          and t.latest[0] == 1_800_000 and close(t.latest[1], 1.6) and close(t.latest[2], 2.56) and t.pending == 0,
          (r0, r1, r2, r3, t.latest))
    t2 = T(pending_max=4)
    for k in range(10):
        t2.estimate(k, (0.0, 0.0, 0.0), cov)
    check("truth: pending estimates bounded", t2.pending == 4 and t2.dropped == 6, t2.pending)

    # SIM_STATE validation and the integer fields: cooploc.sim_state_from_frame, on the frame's
    # bytes (protocol::wire's check, the ground station's).
    from pymavlink.dialects.v20 import common as cd
    packer = cd.MAVLink(None, srcSystem=3, srcComponent=1)

    def sim(**kw):
        f = dict(q1=1.0, q2=0.0, q3=0.0, q4=0.0, roll=0.0, pitch=0.0, yaw=0.0, xacc=0.0, yacc=0.0, zacc=0.0,
                 xgyro=0.0, ygyro=0.0, zgyro=0.0, lat=34.7, lon=0.0, alt=0.0, std_dev_horz=0.0, std_dev_vert=0.0,
                 vn=0.0, ve=0.0, vd=0.0, lat_int=0, lon_int=0)
        f.update(kw)
        return bytes(cd.MAVLink_sim_state_message(**f).pack(packer))
    o = (34.7, 0.0, 0.0)
    f32 = lambda x: struct.unpack("<f", struct.pack("<f", x))[0]  # noqa: E731 (SIM_STATE's float fields)
    a = cl._cooploc.sim_state_from_frame(sim(lat=10.0, lon=10.0, alt=3.0, lat_int=347_000_100, lon_int=-200), o)
    b = cl._cooploc.sim_state_from_frame(sim(lat=34.70001, lon=-0.00002, alt=3.0), o)
    check("truth: SIM_STATE lat_int/lon_int preferred when non-zero, else lat/lon",
          close(a[0], math.radians(347_000_100 * 1e-7 - 34.7) * 6378137.0, 1e-6)
          and close(a[1], math.radians(-200 * 1e-7) * 6378137.0 * math.cos(math.radians(34.7)), 1e-6)
          and a[2] == -3.0 and close(b[0], math.radians(f32(34.70001) - 34.7) * 6378137.0, 1e-6), (a, b))
    bad = [sim(lat=float("nan")), sim(lat_int=910_000_000), sim(lat=-90.5), sim(alt=float("inf")),
           sim(vn=float("nan")), sim(q1=0.5), sim(lon=float("inf")), b"\xfd\x00garbage"]
    refused = 0
    for frame in bad:
        try:
            cl._cooploc.sim_state_from_frame(frame, o)
        except ValueError:
            refused += 1
    check("truth: SIM_STATE with a non-finite field, |lat| > 90 or a bad quaternion refused",
          refused == len(bad), "%d of %d refused" % (refused, len(bad)))
    check("no truth rules of the module's own", not any(hasattr(cl, n) for n in (
        "TruthTrack", "interpolate_truth", "sim_state_ned", "geo_to_ned", "ned_to_geo", "RateWindow")))


# ---- 2. the module in a stand-in MAVProxy (no process, no wx) --------------------------------

class FakeConsole:
    def __init__(self):
        self.status = {}
        self.lines = []

    def set_status(self, name, text="", row=0, **_):
        self.status[name] = text

    def writeln(self, text, **_):
        self.lines.append(text)


class FakeMav:
    def __init__(self):
        self.sent = []

    def command_long_send(self, *args):
        self.sent.append(args)


class FakeMaster:
    """A MAVProxy link: its number, pymavlink's message hooks, a parser and a sender."""

    def __init__(self, linknum, parser):
        self.linknum = linknum
        self.message_hooks = []
        self.parser = parser
        self.mav = FakeMav()

    def deliver(self, module, frame):
        """What MAVProxy does with a frame: decode, post_message (hooks), then the modules."""
        m = self.parser.decode(bytearray(frame))
        for hook in list(self.message_hooks):
            hook(self, m)
        module.mavlink_packet(m)


class FakeLiveGraph:
    def __init__(self):
        self.values = []

    def add_values(self, values):
        self.values.append(values)

    def is_alive(self):
        return True


class FakeGraph:
    def __init__(self, fields):
        self.fields = fields
        self.livegraph = FakeLiveGraph()


class FakeGraphModule:
    name = "graph"

    def __init__(self):
        self.graphs = []


class FakeSlipMap:
    def __init__(self):
        self.objects = {}
        self.moves = []

    def add_object(self, obj):
        self.objects[obj.key] = obj

    def set_position(self, key, latlon, layer="", rotation=0, label=None, colour=None):
        self.moves.append((key, latlon, rotation))
        self.objects[key].latlon = latlon

    def remove_object(self, key):
        self.objects.pop(key, None)


class FakeMPState:
    def __init__(self, masters):
        self.mav_master = masters
        self.command_map, self.completions, self.completion_functions = {}, {}, {}
        self.public_modules, self.multi_instance, self.instance_count = {}, {}, {}
        self.modules = []
        self.console = FakeConsole()
        self.settings = type("S", (), {"source_system": 255})()
        self.stdin_lines = []
        self.functions = type("F", (), {})()
        self.functions.process_stdin = self._process_stdin

    def _process_stdin(self, line):
        self.stdin_lines.append(line)
        for mod, _ in self.modules:
            if mod.name == "graph" and line.startswith("graph "):
                mod.graphs.append(FakeGraph(line.split()[1:]))

    def module(self, name):
        return self.public_modules.get(name)


def quiet(fn, *args):
    """Calls fn, returning (its result, what it printed)."""
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        r = fn(*args)
    return r, buf.getvalue()


def estimate(d, t_us, vid, **kw):
    f = dict(time_usec=t_us, epoch=3, x=1.5, y=-2.25, z=0.125, vx=0.5, vy=0.25, vz=0.0, yaw=0.75,
             pos_covariance=[4.0, 1.0, 0.0, 2.0, 0.0, 1.0], yaw_variance=0.01, nis=float("nan"),
             platform=vid, method=2, participants=3, ranges=2)
    f.update(kw)
    return d.MAVLink_cooploc_estimate_message(**f)


def module_checks(cl, dialect):
    from pymavlink import mavutil
    import numpy as np
    mavutil.set_dialect("cooploc")
    d = dialect
    links = [FakeMaster(0, d.MAVLink(None)), FakeMaster(1, d.MAVLink(None))]
    mp = FakeMPState(links)
    mod, printed = quiet(cl.init, mp)
    check("stand-in: module made, command registered, links hooked",
          isinstance(mod, cl.CooplocModule) and "cooploc" in mp.command_map
          and all(mod._link_hook in m.message_hooks for m in links), printed)
    senders = {v: d.MAVLink(None, srcSystem=v, srcComponent=191) for v in (1, 2, 3, 4)}

    def send(vid, msg, on=(0,)):
        frame = bytes(msg.pack(senders[vid]))
        senders[vid].seq = (senders[vid].seq + 1) % 256  # as MAVLink.send does
        for i in on:
            links[i].deliver(mod, frame)
        return frame

    now = __import__("time").monotonic
    # The same estimate on two links: one estimate, bytes once, a sequence counter per link.
    f1 = send(2, estimate(d, 1_000_000, 2), on=(0, 1))
    v = mod.vehicles[2]
    check("stand-in: a frame on two links is one estimate, its bytes counted once",
          v.estimates == 1 and v.repeats == 1 and v.bytes_rate.total(now()) == len(f1)
          and sorted(v.loss) == [0, 1], (v.estimates, v.repeats, v.bytes_rate.total(now()), len(f1)))
    e2 = estimate(d, 2_000_000, 2, x=3.1, nis=4.2)
    send(2, e2)
    send(2, estimate(d, 1_500_000, 2))            # older: ignored
    line = mod.vehicle_line(v, now())
    kv = dict(w.split("=", 1) for w in line.split()[3:])
    want = {f: cl.fmt_float(getattr(d.MAVLink(None).decode(bytearray(e2.pack(d.MAVLink(None)))), f)) for f in FIELDS}
    check("stand-in: status line holds the latest estimate (repr of the decoded floats)",
          kv["t_us"] == "2000000" and all(kv[f] == want[f] for f in FIELDS) and kv["method"] == "decentralized"
          and v.stale == 1, line)
    el = cl.ellipse95(4.0, 1.0, 2.0)
    check("stand-in: ellipse in the status line", kv["semi_major_95"] == "%.3f" % el[0]
          and kv["bearing_95_deg"] == "%.1f" % el[2], line)
    send(2, estimate(d, 10_000_000, 2))
    send(2, estimate(d, 2_000_000, 2))            # 8 s back: a restart
    check("stand-in: a jump back of more than 5 s is a restart", v.restarts == 1 and v.est.time_usec == 2_000_000,
          (v.restarts, v.est.time_usec))
    # Validation.
    before = v.estimates
    send(2, estimate(d, 3_000_000, 2, x=float("nan")))
    send(2, estimate(d, 3_000_000, 2, pos_covariance=[1, 0, 0, float("inf"), 0, 1]))
    send(2, estimate(d, 3_000_000, 3))            # platform 3 from system 2
    send(2, estimate(d, 3_000_000, 2, method=9))
    send(2, estimate(d, 3_000_000, 2, yaw_variance=-1.0))
    check("stand-in: non-finite, wrong platform, unknown method, negative variance: rejected",
          v.rejected == 5 and v.estimates == before and mod.errors == 0, (v.rejected, mod.last_rejected))
    # Sequence loss: 3 frames skipped on link 0.
    senders[2].seq = (senders[2].seq + 3) % 256
    send(2, estimate(d, 4_000_000, 2))
    kv = dict(w.split("=", 1) for w in mod.vehicle_line(v, now()).split()[3:])
    check("stand-in: sequence gaps are link loss", v.loss[0].lost == 3 and v.loss[1].lost == 0
          and kv["loss_pct"] == "0:%.2f,1:0.00" % (300.0 / (v.loss[0].received + 3))
          and type(v.loss[0]).__module__.startswith("cooploc"), (kv["loss_pct"], v.loss[0].lost))
    # Heartbeat, ack, ranges, fragments.
    send(2, d.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    send(2, d.MAVLink_command_ack_message(512, 0, 0, 0, 255, 0))
    send(2, d.MAVLink_command_ack_message(512, 1, 0, 0, 255, 0))
    send(2, d.MAVLink_command_ack_message(512, 0, 0, 0, 254, 0))  # another ground station's
    send(2, d.MAVLink_cooploc_range_message(4_000_000, 4, 10.0, 0.1, 2, 1))
    send(2, d.MAVLink_cooploc_range_message(4_000_000, 4, float("nan"), 0.1, 2, 1))
    send(2, d.MAVLink_cooploc_store_fragment_message(4_000_000, 4, 0, 10, 2, 0, 1, 10, [0] * 232))
    send(2, d.MAVLink_cooploc_store_held_message(4_000_000, 77, [1, 0, 0, 0], [0] * 4, 4, 0, 2))
    send(2, d.MAVLink_cooploc_store_held_message(4_000_000, 77, [0] * 4, [1, 0, 0, 0], 4, 0, 2))  # held of no series
    check("stand-in: heartbeat, acks, ranges, store fragments, store held",
          v.hb_type == 18 and v.acks == 1 and v.acks_refused == 1 and v.ranges == 1 and v.store_fragments == 1
          and v.store_held == 1 and v.rejected == 7,
          (v.hb_type, v.acks, v.ranges, v.store_fragments, v.store_held, v.rejected))
    # Signing: vehicle 4 signs its frames.
    senders[4].signing.secret_key = bytes(range(32))
    senders[4].signing.sign_outgoing = True
    senders[4].signing.timestamp = 1
    send(4, estimate(d, 1_000_000, 4))
    check("stand-in: signed frames (incompat_flags bit 0)", mod.vehicles[4].signed_text(now()) == "yes"
          and v.signed_text(now()) == "no")
    # Epochs: agree, disagree, disagree, agree.
    for ep, digests in ((1, (5, 5, 5)), (2, (6, 6, 7)), (3, (8, 9, 8)), (4, (10, 10, 10))):
        for vid, dg in zip((1, 2, 3), digests):
            send(vid, d.MAVLink_cooploc_epoch_message(ep * 1_000_000, ep, vid, 3, [1, 2, 3] + [0] * 61, 1, dg))
    send(1, d.MAVLink_cooploc_epoch_message(5_000_000, 5, 2, 3, [1, 2, 3] + [0] * 61, 1, 1))  # announcer 2 from 1
    team = mod.team_line()
    check("stand-in: team disagreements 2, heals 1 from COOPLOC_EPOCH",
          "disagreements=2 heals=1" in team and mod.epochs.node(3)["outvoted"] == 1 and mod.epochs.node(2)["outvoted"] == 1
          and type(mod.epochs).__module__ == "cooploc._native"
          and mod.vehicles[1].rejected == 1, team)
    # Commands.
    _, out = quiet(mod.cmd_cooploc, ["refresh", "0"])
    check("stand-in: refresh 0 sends REQUEST_MESSAGE(COOPLOC_ESTIMATE) to (0, 191) on every link",
          all(m.mav.sent == [(0, 191, 512, 0, 61002.0, 0, 0, 0, 0, 0, 0)] for m in links), [m.mav.sent for m in links])
    _, out = quiet(mod.cmd_cooploc, ["status"])
    check("stand-in: cooploc status prints a line per vehicle and the team line",
          [l.split()[2] for l in out.splitlines() if l.startswith("cooploc vehicle ")] == ["1", "2", "3", "4"]
          and "cooploc team vehicles=4" in out, out[:300])
    _, out = quiet(mod.cmd_cooploc, ["team"])
    check("stand-in: cooploc team table", out.splitlines()[0].split()[:3] == ["id", "method", "epoch"]
          and len(out.splitlines()) == 6, out)
    quiet(mod.cmd_cooploc, ["origin", "35.0", "1.0", "10"])
    check("stand-in: cooploc origin", mod.origin == (35.0, 1.0, 10.0), mod.origin)
    # The console status at most once a second.
    mod._last_status = 0.0
    quiet(mod.idle_task)
    check("stand-in: console status", mp.console.status.get("cooploc", "").startswith(
        "cooploc: 4 vehicles, epoch 4, disagreements 2, heals 1"), mp.console.status)
    # Graphs: without the graph module, a hint; with it, a graph fed each estimate of vehicle 2.
    _, out = quiet(mod.cmd_cooploc, ["graph", "nis", "2"])
    check("stand-in: graph without the graph module says how to load it", "module load graph" in out, out)
    graphmod = FakeGraphModule()
    mp.modules.append((graphmod, None))
    quiet(mod.cmd_cooploc, ["graph", "nis", "2"])
    quiet(mod.cmd_cooploc, ["graph", "ellipse", "2"])
    quiet(mod.cmd_cooploc, ["graph", "error", "2"])
    send(2, estimate(d, 5_000_000, 2, nis=3.5))
    send(3, estimate(d, 5_000_000, 3, nis=1.0))
    vals = [g.livegraph.values for g in graphmod.graphs]
    check("stand-in: graphs fed with vehicle 2's NIS and 95% semi-major axis (no truth: no error yet)",
          mp.stdin_lines[-3:] == ["graph cooploc.v2.nis", "graph cooploc.v2.ellipse", "graph cooploc.v2.error"]
          and vals == [[[3.5]], [[cl.ellipse95(4.0, 1.0, 2.0)[0]]], []], (mp.stdin_lines, vals))
    truth_module_checks(cl, d, mod, links, graphmod.graphs[2].livegraph)
    # The map: objects for each vehicle with an estimate, drawn in its colour.
    slipmap = FakeSlipMap()
    mp.public_modules["map"] = type("M", (), {"map": slipmap, "name": "map"})()
    mod._last_map = 0.0
    quiet(mod.idle_task)
    icon, poly = slipmap.objects.get("cooploc_2"), slipmap.objects.get("cooploc_2_ellipse")
    ok = icon is not None and poly is not None and mod.errors == 0
    if ok:
        est = mod.vehicles[2].est
        lat0, lon0, _ = cl._cooploc.ned_to_geo(est.x, est.y, est.z, mod.origin)
        k = 20.0 * 111_320.0  # about 20 px a metre

        def pix(latlon):
            return (int(200 + (latlon[1] - lon0) * k * math.cos(math.radians(lat0))), int(200 - (latlon[0] - lat0) * k))

        canvas = np.zeros((400, 400, 3), dtype=np.uint8)
        poly.draw(canvas, pix, None)
        icon.draw(canvas, pix, None)
        rgb = np.array(cl.colour_rgb(2), dtype=np.uint8)
        hits = np.all(canvas == rgb, axis=2)
        ys, xs = np.nonzero(hits)
        a, b, bearing = mod.vehicles[2].ellipse
        th = math.radians(bearing)
        width = 2 * 20.0 * math.sqrt((a * math.sin(th)) ** 2 + (b * math.cos(th)) ** 2)  # east extent, px
        height = 2 * 20.0 * math.sqrt((a * math.cos(th)) ** 2 + (b * math.sin(th)) ** 2)
        ok = (hits.sum() > 100 and abs(int(xs.max()) - int(xs.min()) - width) < 6
              and abs(int(ys.max()) - int(ys.min()) - height) < 6 and hits[200, 200])
    check("stand-in: map marker and 95% ellipse drawn in the vehicle's colour", ok,
          (sorted(slipmap.objects), mod.last_error))
    mod._last_map = 0.0
    quiet(mod.idle_task)
    check("stand-in: the marker then moves (set_position)", any(k == "cooploc_2" for k, _, _ in slipmap.moves))
    # A programming error inside the handling: counted and shown, never raised.
    class Broken:
        def get_type(self):
            return "COOPLOC_ESTIMATE"

        def get_srcSystem(self):
            return 2

        def get_srcComponent(self):
            return 191
    _, out = quiet(mod.mavlink_packet, Broken())
    check("stand-in: an exception in the handling is counted and shown, MAVProxy goes on",
          mod.errors == 1 and "AttributeError" in mod.team_line() and "Traceback" in out, mod.team_line())
    # Bounded vehicle table.
    for sysid in range(100, 170):
        links[0].deliver(mod, bytes(d.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(
            d.MAVLink(None, srcSystem=sysid, srcComponent=191))))
    check("stand-in: at most 64 vehicles", len(mod.vehicles) == 64 and mod.vehicles_refused > 0, len(mod.vehicles))
    quiet(mod.unload)
    check("stand-in: unload removes the hooks, the command and the map objects",
          all(mod._link_hook not in m.message_hooks for m in links) and "cooploc" not in mp.command_map
          and not slipmap.objects, sorted(slipmap.objects))

    # Another dialect in MAVProxy (its default 'all'): the frames arrive as UNKNOWN_610xx and the
    # module decodes them with its own bindings.
    mavutil.set_dialect("all")
    from pymavlink.dialects.v20 import all as alld
    links2 = [FakeMaster(0, alld.MAVLink(None))]
    mp2 = FakeMPState(links2)
    mod2, printed = quiet(cl.init, mp2)
    sender = d.MAVLink(None, srcSystem=3, srcComponent=191)
    frame = bytes(estimate(d, 7_000_000, 3, x=9.5).pack(sender))
    links2[0].deliver(mod2, frame)
    bad = bytearray(estimate(d, 8_000_000, 3).pack(sender))
    bad[-1] ^= 0xFF  # CRC
    links2[0].deliver(mod2, bytes(bad))
    v3 = mod2.vehicles.get(3)
    check("stand-in, dialect 'all': cooploc frames decoded by the module's own bindings",
          v3 is not None and v3.est is not None and v3.est.x == 9.5 and v3.rejected == 1
          and "decoding them with bindings" in printed, (printed, v3 and v3.rejected))
    mavutil.set_dialect("cooploc")


def truth_module_checks(cl, d, mod, links, error_graph):
    """Vehicle 2's truth from its simulator, (2, 1): SIM_STATE stamped by HIGHRES_IMU / ODOMETRY,
    the error of the held estimate at 5 s (x=1.5, y=-2.25, z=0.125, P = [4 1 0; 1 2 0; 0 0 1])."""
    now = time.monotonic
    sim = d.MAVLink(None, srcSystem=2, srcComponent=1)
    v = mod.vehicles[2]

    def send(msg, on=(0,)):
        frame = bytes(msg.pack(sim))
        sim.seq = (sim.seq + 1) % 256
        for i in on:
            links[i].deliver(mod, frame)

    def sim_state(lat_int, lon_int, alt, **kw):
        f = dict(q1=1.0, q2=0.0, q3=0.0, q4=0.0, roll=0.0, pitch=0.0, yaw=0.0, xacc=0.0, yacc=0.0, zacc=-9.8,
                 xgyro=0.0, ygyro=0.0, zgyro=0.0, lat=lat_int * 1e-7, lon=lon_int * 1e-7, alt=alt, std_dev_horz=0.0,
                 std_dev_vert=0.0, vn=0.0, ve=0.0, vd=0.0, lat_int=lat_int, lon_int=lon_int)
        f.update(kw)
        return d.MAVLink_sim_state_message(**f)

    def imu(t):
        return d.MAVLink_highres_imu_message(t, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)

    def odometry(t):
        return d.MAVLink_odometry_message(t, 0, 12, 0, 0, 0, [1, 0, 0, 0], 1.0, 0, 0, 0, 0, 0,
                                          [float("nan")] * 21, [0.0] * 21)

    # The truth 3 m north and 4 m east of the estimate (in degE7 steps: the exact truth is what
    # the integers give), at 4.5 s and 5.5 s.
    lat0, lon0, alt0 = mod.origin
    lat, lon, alt = cl._cooploc.ned_to_geo(1.5 + 3.0, -2.25 + 4.0, 0.125, mod.origin)
    lat_int, lon_int = int(round(lat * 1e7)), int(round(lon * 1e7))
    truth = cl._cooploc.geo_to_ned(lat_int * 1e-7, lon_int * 1e-7, 9.875, mod.origin)
    rejected = v.rejected
    send(sim_state(lat_int, lon_int, 9.875), on=(0, 1))   # on two links: one sample
    before = mod.vehicles[2].est.time_usec, mod.truths[2].latest
    send(imu(4_500_000), on=(0, 1))
    send(sim_state(lat_int, lon_int, 9.875))
    send(odometry(5_500_000))
    track = mod.truths[2]
    e = (truth[0] - 1.5, truth[1] - (-2.25), truth[2] - 0.125)
    want_err = math.hypot(e[0], e[1])
    want_nees = cl.position_nees(e, (4.0, 1.0, 0.0, 2.0, 0.0, 1.0))
    kv = dict(w.split("=", 1) for w in mod.vehicle_line(v, now()).split()[3:])
    check("stand-in: SIM_STATE of (2, 1) stamped by HIGHRES_IMU / ODOMETRY; a frame on two links used once",
          before[1] is None and list(track.times) == [4_500_000, 5_500_000] and track.stale == 0
          and mod.errors == 0 and abs(want_err - 5.0) < 0.02, (list(track.times), track.stale, mod.last_error))
    check("stand-in: error and NEES of the estimate at 5 s in the status line",
          kv.get("error_m") == repr(want_err) and kv.get("nees") == repr(want_nees) and kv.get("error_t_us") == "5000000"
          and kv.get("truth_samples") == "2" and abs(want_nees - 58.0 / 7.0) < 0.05,
          {k: kv.get(k) for k in ("error_m", "nees", "error_t_us", "truth_samples")})
    check("stand-in: graph error fed the horizontal error against the truth", error_graph.values == [[want_err]],
          error_graph.values)
    _, out = quiet(mod.cmd_cooploc, ["team"])
    head = out.splitlines()[0]
    row = [l for l in out.splitlines() if l.split()[:1] == ["2"]]
    check("stand-in: cooploc team shows the error and NEES", "error m" in head and "NEES" in head and row
          and "%.2f" % want_err in row[0].split() and "%.2f" % want_nees in row[0].split(), out)
    # A later estimate waits for the truth, then resolves; a covariance not positive definite
    # gives an error without NEES.
    send_est = lambda m: links[0].deliver(mod, bytes(m.pack(mod_senders[2])))  # noqa: E731
    mod_senders = {2: d.MAVLink(None, srcSystem=2, srcComponent=191)}
    send_est(estimate(d, 6_000_000, 2, x=1.5, y=-2.25, pos_covariance=[1.0, 2.0, 0.0, 1.0, 0.0, 1.0]))
    waiting = track.pending
    send(sim_state(lat_int, lon_int, 9.875))
    send(imu(6_500_000))
    kv = dict(w.split("=", 1) for w in mod.vehicle_line(v, now()).split()[3:])
    check("stand-in: an estimate ahead of the truth waits; P not positive definite: nees=-",
          waiting == 1 and kv.get("error_t_us") == "6000000" and kv.get("nees") == "-"
          and kv.get("error_m") == repr(want_err), (waiting, kv.get("error_t_us"), kv.get("nees")))
    # Hostile SIM_STATE: rejected, counted, nothing raised.
    send(sim_state(0, 0, 9.875, lat=float("nan")))
    send(sim_state(950_000_000, lon_int, 9.875))
    send(sim_state(lat_int, lon_int, float("inf")))
    send(sim_state(lat_int, lon_int, 9.875, q1=0.2))
    check("stand-in: bad SIM_STATEs rejected (counted), no module error",
          v.rejected == rejected + 4 and mod.errors == 0 and track.samples == 3, (v.rejected, mod.last_rejected))
    # Another system's simulator (no node): a truth track, no vehicle row.
    other = d.MAVLink(None, srcSystem=9, srcComponent=1)
    links[0].deliver(mod, bytes(sim_state(lat_int, lon_int, 9.875).pack(other)))
    check("stand-in: a simulator without a node adds no vehicle", 9 not in mod.vehicles and 9 in mod.truths)
    send_est(estimate(d, 7_000_000, 2))  # back to the usual covariance for the map checks


# ---- 3. the live run --------------------------------------------------------------------------

class Proc:
    """A child process whose output lines are collected by a thread."""

    def __init__(self, name, cmd, env=None, cwd=ROOT, stdin=None):
        self.name = name
        self.lines = []
        self.queue = queue.Queue()
        self.p = subprocess.Popen(cmd, cwd=cwd, env=env, stdin=stdin, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, errors="replace", bufsize=1)
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for line in self.p.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
            self.queue.put(line)

    def wait_line(self, pattern, timeout):
        deadline = time.time() + timeout
        while True:
            left = deadline - time.time()
            if left <= 0:
                raise RuntimeError("%s: no line matching %r in %.0f s; output:\n%s"
                                   % (self.name, pattern, timeout, "\n".join(self.lines[-20:])))
            try:
                line = self.queue.get(timeout=left)
            except queue.Empty:
                continue
            m = re.search(pattern, line)
            if m:
                return m

    def stop(self, sig=signal.SIGTERM, timeout=10):
        if self.p.poll() is None:
            self.p.send_signal(sig)
            try:
                self.p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self.thread.join(timeout=2)


def prepare_dialect(tmp):
    """MDEF folder with the cooploc dialect and fresh pymavlink bindings for it.

    pymavlink's set_dialect('cooploc') imports pymavlink.dialects.v20.cooploc and only when that
    fails runs mavgen on $MDEF/v1.0/cooploc.xml into its own package folder: a file left there by an
    older XML would be used as it is. So the check regenerates it from this tree's XML first."""
    mdef = os.path.join(tmp, "mdef")
    os.makedirs(os.path.join(mdef, "v1.0"))
    # cooploc.xml and every XML it includes (ardupilotmega.xml and what that includes)
    for x in sorted(os.listdir(os.path.join(ROOT, "dialects"))):
        if x.endswith(".xml"):
            shutil.copy(os.path.join(ROOT, "dialects", x), os.path.join(mdef, "v1.0", x))
    os.environ["MDEF"] = mdef
    os.environ["MAVLINK20"] = "1"
    from pymavlink.generator import mavgen, mavparse
    cwd = os.getcwd()
    try:
        os.chdir(tmp)  # mavgen_python_dialect uses a path relative to the working directory
        if not mavgen.mavgen_python_dialect("cooploc", mavparse.PROTOCOL_2_0):
            raise RuntimeError("mavgen refused the cooploc dialect")
    except PermissionError as e:  # a read-only pymavlink: use the bindings already there, if any
        print("note: cannot regenerate pymavlink's cooploc bindings (%s); using the installed ones" % e,
              file=sys.stderr)
    finally:
        os.chdir(cwd)
    import importlib
    importlib.invalidate_caches()
    from pymavlink.dialects.v20 import cooploc as dialect
    importlib.reload(dialect)
    return mdef, dialect


def read_log_estimates(path, vid, dialect):
    """{time_usec: [COOPLOC_ESTIMATE, ...]} of the frames node `vid` sent (its MCAP log)."""
    from mcap.reader import make_reader
    mav = dialect.MAVLink(None)
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for _, channel, message in reader.iter_messages(topics=["/coop/%d/tx" % vid]):
            if channel.message_encoding != "mavlink.frame":
                continue
            try:
                m = mav.decode(bytearray(message.data))
            except Exception:
                continue
            if m.get_type() == "COOPLOC_ESTIMATE":
                out.setdefault(m.time_usec, []).append(m)
    return out


def parse_status(lines):
    """The last `cooploc vehicle` line of each vehicle and the last team line, as dicts."""
    vehicles, team = {}, None
    for line in lines:
        i = line.find("cooploc vehicle ")
        if i >= 0:
            words = line[i:].split()
            vehicles[int(words[2])] = dict(w.split("=", 1) for w in words[3:] if "=" in w)
        i = line.find("cooploc team vehicles=")
        if i >= 0:
            team = line[i:]
    return vehicles, team


#: Bound on the horizontal error against the truth in the live run, m. The nodes start from
#: their true initial state plus the experiment's initial errors (sitl/scenarios/paper.toml:
#: 0.1 m, 0.05 m/s per axis) and run ~30 s of simulated time, odometer-aided with 0.1 m ranges
#: between them. Even with no aiding at all, the worst sensor error, the 500 ug accelerometer bias,
#: drifts 0.5 * 4.9e-3 m/s^2 * (30 s)^2 = 2.2 m in that time; seen: 0.2-0.3 m, NEES about 1,
#: 95 % semi-major axes about 0.8 m. 5 m is twice the unaided drift; a truth off by one SIM_STATE
#: period (1 s at 10 m/s), a wrong origin or frame gives 10 m and more.
LIVE_ERROR_BOUND_M = 5.0


def truth_checks_live(vid, s, sent):
    """`error_m`, `nees`, `error_t_us` of a live vehicle line against the node's log."""
    err, nees, et = s.get("error_m", "-"), s.get("nees", "-"), s.get("error_t_us", "-")
    try:
        err_v, nees_v, et_v = float(err), float(nees), int(et)
    except ValueError:
        check("vehicle %d: error_m, a finite nees and error_t_us printed (SIM_STATE truth)" % vid, False,
              "error_m=%s nees=%s error_t_us=%s truth_samples=%s" % (err, nees, et, s.get("truth_samples")))
        return
    check("vehicle %d: error_m, a finite nees and error_t_us printed (SIM_STATE truth)" % vid,
          math.isfinite(err_v) and err_v >= 0.0 and math.isfinite(nees_v) and nees_v >= 0.0, (err, nees))
    check("vehicle %d: error against the truth below %g m" % (vid, LIVE_ERROR_BOUND_M),
          err_v < LIVE_ERROR_BOUND_M, "error_m=%s" % err)
    check("vehicle %d: error_t_us is an estimate time the node logged" % vid, et_v in sent,
          "error_t_us=%d, logged %d estimate times" % (et_v, len(sent)))
    print("vehicle %d: error_m=%s nees=%s error_t_us=%s truth_samples=%s" % (vid, err, nees, et,
                                                                           s.get("truth_samples")), file=sys.stderr)


def live_run(binary, cl, tmp, mdef, dialect):
    procs = []
    try:
        sitl = Proc("sitl", [binary, "sitl", "sitl/scenarios/paper.toml", "--seed", "1", "--run", "0", "--speed", "2",
                             "--base-port", "0", "--wait-for-peers", "--sim-state-hz", "1"])
        procs.append(sitl)
        vehicles = {}
        for _ in range(3):
            m = sitl.wait_line(r"^vehicle (\d+) .* (\S+)$", 30)
            vehicles[int(m.group(1))] = m.group(2)
        nodes = {}
        node_procs = []
        for vid in sorted(vehicles):
            cmd = [binary, "node", "--scenario", "sitl/scenarios/paper.toml", "--id", str(vid), "--vehicle", "udpout:" + vehicles[vid], "--init-from-run", "1:0",
                   "--log", os.path.join(tmp, "node-%d.mcap" % vid),
                   # MAVProxy's `signing setup` signs and checks every master link alike, the
                   # simulated vehicles' (unsigned) too: this team runs unsigned, by name
                   "--insecure"]
            for other in nodes.values():
                cmd += ["--peer", other]
            p = Proc("node %d" % vid, cmd)
            procs.append(p)
            node_procs.append(p)
            nodes[vid] = p.wait_line(r"^node %d coop udp (\S+)" % vid, 30).group(1)

        # MAVProxy: `module load cooploc` (its loader tries MAVProxy.modules.mavproxy_NAME, then
        # NAME) finds the installed cooploc package, which provides init(mpstate): no copy or link
        # of the module anywhere MAVProxy looks first.
        import MAVProxy.modules
        shadow = os.path.join(os.path.dirname(MAVProxy.modules.__file__), "mavproxy_cooploc.py")
        check("no mavproxy_cooploc in MAVProxy's modules (the package is loaded)", not os.path.lexists(shadow), shadow)
        home = os.path.join(tmp, "home")
        os.makedirs(home)
        statusfile = os.path.join(tmp, "status.txt")
        tlog = os.path.join(tmp, "mav.tlog")
        env = dict(os.environ, HOME=home, MDEF=mdef, MAVLINK20="1")
        env.pop("DISPLAY", None)
        cmd = [sys.executable, os.path.join(os.path.dirname(sys.executable), "mavproxy.py"), "--dialect", "cooploc"]
        cmd += ["--master=udpout:" + vehicles[v] for v in sorted(vehicles)]
        cmd += ["--master=udpout:" + nodes[v] for v in sorted(nodes)]
        cmd += ["--state-basedir=" + home, "--target-system=1", "--source-system=255", "--logfile=" + tlog,
                "--cmd=set heartbeat 1; set param_ftp 0; module load cooploc; cooploc set statusfile " + statusfile]
        mavproxy = Proc("mavproxy", cmd, env=env, cwd=home, stdin=subprocess.PIPE)
        procs.append(mavproxy)

        def send(line):
            mavproxy.p.stdin.write(line + "\n")
            mavproxy.p.stdin.flush()

        # Let the team run (wall time; 2x simulated), then ask for estimates and the status.
        try:
            mavproxy.wait_line(r"cooploc vehicle 3 ", 1)  # nothing yet; just drains early output
        except RuntimeError:
            pass
        time.sleep(11)
        send("cooploc refresh 0")
        time.sleep(3)
        mark = len(mavproxy.lines)
        send("cooploc status")
        send("cooploc team")
        try:
            mavproxy.wait_line(r"cooploc team vehicles=", 10)
            mavproxy.wait_line(r"\bid\s+method\s+epoch", 5)
        except RuntimeError as e:
            print(e, file=sys.stderr)
        time.sleep(0.5)
        # End of its input: MAVProxy's input loop stops it cleanly (a SIGTERM makes its quit
        # handler raise SystemExit in the interpreter's shutdown, a traceback of MAVProxy's own).
        mavproxy.p.stdin.close()
        try:
            mavproxy.p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        mavproxy.stop(signal.SIGTERM, 10)
        for p in node_procs:
            p.stop(signal.SIGTERM, 15)
        sitl.stop(signal.SIGTERM, 10)

        out = mavproxy.lines
        text = "\n".join(out)
        print("---- MAVProxy output (cooploc and parameter lines) ----", file=sys.stderr)
        after_traceback = 0
        for line in out:
            if "Traceback" in line:
                after_traceback = 20
            if after_traceback or re.search(r"cooploc|arameters|rror|\bid\s+method|^\s*\d+\s+[a-z_]+\s+\d+", line):
                print("  " + line, file=sys.stderr)
            after_traceback = max(0, after_traceback - 1)

        # ---- checks ----
        check("module loaded", re.search(r"Loaded module cooploc\b", text), "no 'Loaded module cooploc'")
        check("no Python traceback in MAVProxy's output", "Traceback" not in text,
              "\n".join(l for l in out if "Traceback" in l or "Error" in l)[:2000])
        status, team = parse_status(out[mark:])
        check("team line", team is not None, "no team line")
        if team:
            m = re.search(r"errors=(\d+)", team)
            check("no module error", m and m.group(1) == "0", team)
        check("status lists vehicles 1, 2, 3", sorted(status) == [1, 2, 3], sorted(status))

        for vid in (1, 2, 3):
            s = status.get(vid)
            if s is None or s.get("t_us", "-") == "-":
                check("vehicle %d has an estimate" % vid, False, s)
                continue
            try:
                sent = read_log_estimates(os.path.join(tmp, "node-%d.mcap" % vid), vid, dialect)
            except Exception as e:
                check("vehicle %d: node log readable" % vid, False, e)
                continue
            truth_checks_live(vid, s, sent)
            t_us = int(s["t_us"])
            same_t = sent.get(t_us, [])
            check("vehicle %d: the node logged an estimate at t_us=%d" % (vid, t_us), same_t,
                  "%d estimates in the log" % sum(len(v) for v in sent.values()))
            if not same_t:
                continue

            def printed(m):
                return {f: cl.fmt_float(getattr(m, f)) for f in FIELDS}

            match = [m for m in same_t if all(printed(m)[f] == s.get(f) for f in FIELDS)
                     and str(m.epoch) == s.get("epoch") and cl.method_name(m.method) == s.get("method")
                     and str(m.participants) == s.get("participants") and str(m.ranges) == s.get("ranges")]
            check("vehicle %d: printed estimate equals the node's COOPLOC_ESTIMATE field for field" % vid, match,
                  "printed %s; logged %s" % ({f: s.get(f) for f in FIELDS}, [printed(m) for m in same_t]))
            if match:
                c = match[-1].pos_covariance
                el = cl.ellipse95(c[0], c[1], c[3])
                check("vehicle %d: ellipse from the logged covariance" % vid,
                      el and s.get("semi_major_95") == "%.3f" % el[0] and s.get("semi_minor_95") == "%.3f" % el[1]
                      and s.get("bearing_95_deg") == "%.1f" % el[2], (s.get("semi_major_95"), el))
            check("vehicle %d: estimate rate and node bytes/s > 0" % vid,
                  float(s.get("rate_hz", 0)) > 0 and float(s.get("bytes_per_s", 0)) > 0,
                  (s.get("rate_hz"), s.get("bytes_per_s")))
            check("vehicle %d: unsigned, no rejected message, heartbeat type 18" % vid,
                  s.get("signed") == "no" and s.get("rejected") == "0" and s.get("hb_type") == "18", s)

        # The tlog: heartbeats and parameters.
        from pymavlink import mavutil
        seen_hb, params, sysid_param = set(), 0, None
        if os.path.exists(tlog):
            log = mavutil.mavlink_connection(tlog, dialect="cooploc")
            while True:
                m = log.recv_match(type=["HEARTBEAT", "PARAM_VALUE"])
                if m is None:
                    break
                if m.get_type() == "HEARTBEAT":
                    seen_hb.add((m.get_srcSystem(), m.get_srcComponent(), m.type))
                elif m.get_srcSystem() == 1:
                    params += 1
                    if m.param_id == "SYSID_THISMAV":
                        sysid_param = m.param_value
        for vid in (1, 2, 3):
            check("tlog: vehicle %d heartbeat (type 10 from %d:1)" % (vid, vid), (vid, 1, 10) in seen_hb, sorted(seen_hb))
            check("tlog: node %d heartbeat (type 18 from %d:191)" % (vid, vid), (vid, 191, 18) in seen_hb,
                  sorted(seen_hb))
        check("tlog: PARAM_VALUE SYSID_THISMAV = 1 from system 1 (needs parameters in `cooploc sitl`)",
              sysid_param == 1, "%d PARAM_VALUE from system 1, SYSID_THISMAV %r" % (params, sysid_param))
        check("MAVProxy received all parameters (needs parameters in `cooploc sitl`)",
              re.search(r"Received \d+ parameters", text), "no 'Received N parameters'")

        # Refresh: an accepted COMMAND_ACK per vehicle.
        acks = {vid: int(status.get(vid, {}).get("acks", "0")) for vid in (1, 2, 3)}
        check("cooploc refresh 0 sent", re.search(r"cooploc refresh: REQUEST_MESSAGE", text), "no refresh line")
        check("acks >= 1 per vehicle after `cooploc refresh 0` (needs REQUEST_MESSAGE in `cooploc node`)",
              all(a >= 1 for a in acks.values()), acks)

        # The status file.
        blocks = 0
        if os.path.exists(statusfile):
            with open(statusfile) as f:
                blocks = sum(1 for line in f if line.startswith("cooploc time="))
        check("status file written every second", blocks >= 8, "%d status blocks" % blocks)
    finally:
        for p in reversed(procs):
            try:
                p.stop(signal.SIGKILL, 5)
            except Exception:
                pass


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: mavproxy_module_check.py COOPLOC_BINARY")
    binary = os.path.abspath(sys.argv[1])
    started = time.time()
    tmp = tempfile.mkdtemp(prefix="cooploc-mavproxy-module-")
    try:
        mdef, dialect = prepare_dialect(tmp)
        cl = load_module()
        pure_checks(cl)
        for name, fn in (("stand-in module run", lambda: module_checks(cl, dialect)),
                         ("live run", lambda: live_run(binary, cl, tmp, mdef, dialect))):
            try:
                fn()
            except Exception as e:
                import traceback
                traceback.print_exc()
                check(name, False, e)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    failed = [n for n, ok in results if not ok]
    print("mavproxy_module_check: %d checks, %d failed, %.0f s%s" % (
        len(results), len(failed), time.time() - started, "" if not failed else ": " + "; ".join(failed)))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
