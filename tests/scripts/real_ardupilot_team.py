#!/usr/bin/env python3
"""Three rovers on the real ArduPilot firmware (its SITL build), navigating without GNSS on cooploc.

Runs three ArduRover SITL instances (one per rover, real time), a `cooploc node` beside each on its
SERIAL0 port (TCP 5760 + 10 * instance), a range emulator and a mission driver on SERIAL1 (TCP
5762 + 10 * instance), and prints, per rover, the error of ArduPilot's own EKF3 estimate
(GLOBAL_POSITION_INT) against the simulator's truth (SIMSTATE) over the GNSS-less part: RMS and
final. It builds nothing: it runs the `ardurover` binary it is given.

- Set-ups: `nognss`: no GNSS from power-on (no Unix time, no origin: each node gives the
  autopilot the team's origin by SET_GPS_GLOBAL_ORIGIN and starts from its known start pose);
  `gnss-lost`: GNSS (and a compass for its yaw) until 60 s into the mission, then
  SIM_GPS1_ENABLE 0; each node starts from the autopilot's estimate then
  (`init_from_autopilot`) and switches EKF3 to source set 2 (ExternalNav);
  `gnss-glitch`: GNSS throughout, but from 60 s into the mission to 120 s the simulator's receiver
  reports every rover 0.0003 deg of latitude (33 m) north of where it is (SIM_GPS1_GLTCH_X), its
  fix still 3D: the nodes start as with `gnss-lost`; what they do at the glitch is theirs (a
  node takes over when its autopilot's EKF reports the glitch) and ArduPilot alone keeps its
  GNSS set, as without a companion. Scored from the glitch on.
- Methods: `dcl` and `dr` (cooploc nodes; EKF3 fuses their ODOMETRY as external navigation),
  `alone` (no cooploc: EKF3 on its own wheel encoders and IMU, EK3_SRC1_VELXY 7).
- Equal terms: the same sensors on both sides (IMU and wheel encoders, no compass: COMPASS_USE 0,
  and for ArduPilot alone no yaw source but its gyros), and the simulator's sensor errors switched
  on where it offers them (per rover: a gyro drift, SIM_DRIFT_SPEED/SIM_DRIFT_TIME, and an
  accelerometer bias, SIM_ACC1_BIAS; the SITL wheel encoder has no scale or slip error to offer).
- Ranges: one per pair of rovers per second (on the team's 1 s grid of Unix time), measured by
  the lower id's radio, from the truth of the two simulators (SIMSTATE, interpolated to the
  epoch's instant) plus N(0, 0.1 m), the paper's ranging error; sent to that rover's node as its
  ranging device would (`--ranges`, crates/cooploc-node/src/node/ranging.rs).
- Missions in AUTO: each rover drives its own rectangle, twice without GNSS, three times when
  GNSS goes at 60 s (>= 300 m without GNSS either way).
- What the driver does beyond a ground station's usual: for ArduPilot alone it gives the origin
  and the home, and rolls each rover 2 s in MANUAL before AUTO (EKF3 on wheel encoders alone
  keeps no location at rest, and AUTO then never starts its mission). Every arming check stays
  on (until the twentieth session the driver turned off the VisOdom check with GNSS lost: the
  nodes sent no ODOMETRY before the take-over; the profile's `odometry_with_gnss` now sends it
  from the start, and EKF3 leaves it out on its GNSS source set).

- `--restart-node K --restart-at-s S`: node K is killed (SIGKILL) S seconds into the mission and
  started again at once with the same command line, as a supervisor would; every node keeps its
  navigation state (`state_file = "node.state"`), so the restarted one restores it. The driver
  prints the restarted rover's EKF3 error around the restart.
- `--down-s D`: the killed node stays down D seconds before it is started again (default 0), and
  `--without-state`: its state file goes with it (a companion whose disk was lost, or a node that
  died before its first save): what ArduPilot's EKF3 does without the node's ODOMETRY, second by
  second (its error and its EKF_STATUS_REPORT flags), and what the node does when it comes back
  with nothing but its start-up configuration.

usage: real_ardupilot_team.py --ardurover PATH --setup nognss|gnss-lost|gnss-glitch --method dcl|dr|alone
       [--defaults rover.parm] [--cooploc PATH] [--out DIR] [--seed N] [--json FILE]
       [--restart-node K --restart-at-s S [--down-s D] [--without-state]]
"""

import argparse
import bisect
import json
import math
import os
import random
import shutil
import socket
import subprocess
import sys
import threading
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from real_team_common import free_udp_port, geo_to_ned, ned_to_geo, stop_all, until  # noqa: E402

ORIGIN = (-35.363261, 149.165230, 584.0)  # ArduPilot's SITL home (CMAC), the team's origin
RANGE_SIGMA_M = 0.1  # the paper's Table 1
GNSS_LOSS_S = 60.0  # into the mission, set-ups gnss-lost and gnss-glitch
GLITCH_S = 60.0  # how long the glitch lasts (gnss-glitch)
GLITCH_DEG = 0.0003  # its offset, degrees of latitude (33 m north)
# Each rover: start (north, east, m), heading (deg), its rectangle (north, east sides, m, signed:
# negative east turns left), and the simulator's sensor errors.
ROVERS = [
    dict(start=(0.0, 0.0), heading=0.0, rect=(80.0, 20.0), drift=(0.05, 5), acc_bias=(0.05, -0.03)),
    dict(start=(0.0, 30.0), heading=0.0, rect=(60.0, -25.0), drift=(-0.04, 6), acc_bias=(-0.04, 0.05)),
    dict(start=(-10.0, 60.0), heading=0.0, rect=(70.0, 25.0), drift=(0.03, 4), acc_bias=(0.03, 0.04)),
]
# Laps: the GNSS-less part at least 300 m (with GNSS lost at 60 s, a third lap)
LAPS = {"nognss": 2, "gnss-lost": 3, "gnss-glitch": 3}





def params_for(i, setup, method):
    r = ROVERS[i]
    p = {
        # the simulator's wheel encoders (left and right, 0.30 m apart)
        "WENC_TYPE": 10, "WENC_POS_Y": -0.15, "WENC2_TYPE": 10, "WENC2_POS_Y": 0.15,
        # no compass on either side
        "COMPASS_USE": 0, "COMPASS_USE2": 0, "COMPASS_USE3": 0, "COMPASS_ENABLE": 0,
        # the simulator's sensor errors
        "SIM_DRIFT_SPEED": r["drift"][0], "SIM_DRIFT_TIME": r["drift"][1],
        "SIM_ACC1_BIAS_X": r["acc_bias"][0], "SIM_ACC1_BIAS_Y": r["acc_bias"][1],
        "SIM_ACC2_BIAS_X": r["acc_bias"][0], "SIM_ACC2_BIAS_Y": r["acc_bias"][1],
        "WP_SPEED": 3, "CRUISE_SPEED": 3,
        # the rectangles' corners are taken at speed: a wide acceptance radius keeps the
        # laps' length about the same however the estimate sits
        "WP_RADIUS": 2,
    }
    if setup == "nognss":
        p.update({"GPS1_TYPE": 0, "SIM_GPS1_ENABLE": 0})
    else:
        # with GNSS, its yaw from the compass (EKF3's GSF yaw estimator needs motion, and no
        # position comes before it); the scored GNSS-less part uses none (source set 2)
        p.update({"COMPASS_USE": 1, "COMPASS_ENABLE": 1})
    if method == "alone":
        # EKF3 alone: wheel encoders for velocity, no position or yaw source but its gyros
        p.update({"EK3_SRC1_POSXY": 0, "EK3_SRC1_VELXY": 7, "EK3_SRC1_YAW": 0, "EK3_SRC1_POSZ": 1})
        if setup != "nognss":
            p.update({"EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3, "EK3_SRC1_YAW": 1,
                      "EK3_SRC2_POSXY": 0, "EK3_SRC2_VELXY": 7, "EK3_SRC2_YAW": 0, "EK3_SRC2_POSZ": 1})
    else:
        # external navigation: cooploc's ODOMETRY (VISO_TYPE 1: MAVLink)
        p.update({"VISO_TYPE": 1, "EK3_SRC1_POSXY": 6, "EK3_SRC1_VELXY": 6, "EK3_SRC1_YAW": 6, "EK3_SRC1_POSZ": 1})
        if setup != "nognss":
            # (every arming check on: the nodes send ODOMETRY from their start, the profile's
            # odometry_with_gnss, which EKF3 leaves out on source set 1; before, they sent none
            # until the take-over, and ArduPilot refused to arm, "VisOdom: not healthy", unless
            # the driver turned that check off)
            p.update({"EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3, "EK3_SRC1_YAW": 1,
                      "EK3_SRC2_POSXY": 6, "EK3_SRC2_VELXY": 6, "EK3_SRC2_YAW": 6, "EK3_SRC2_POSZ": 1})
    return p


class Rover:
    """One SITL instance, seen from its mission port: truth, EKF estimate, status."""

    def __init__(self, i, port, log):
        self.i, self.sysid, self.log = i, i + 1, log
        self.lock = threading.Lock()
        self.truth = []  # (wall s, north, east, alt)
        self.ekf = []  # (wall s, north, east)
        self.ekf_flags = None
        self.had_position = False
        self.mission_state = None
        self.home = False
        self.give_origin = False
        self.want_auto = False
        self.auto_sent = 0.0
        self.origin_sent = 0.0
        self.armed = False
        self.mode = None
        self.texts = []
        self.origin = None
        self.mission_requests = []
        self.mission_ack = None
        self.conn = None
        deadline = time.time() + 120
        while self.conn is None:
            try:
                self.conn = mavutil.mavlink_connection("tcp:127.0.0.1:%d" % port, source_system=255,
                                                       source_component=190, dialect="ardupilotmega", autoreconnect=True)
            except OSError:
                if time.time() > deadline:
                    raise
                time.sleep(0.5)
        self.conn.wait_heartbeat(timeout=120)
        for msg_id in (164, 193, 33, 49, 42):  # SIMSTATE, EKF_STATUS_REPORT, GLOBAL_POSITION_INT, GPS_GLOBAL_ORIGIN, MISSION_CURRENT
            self.conn.mav.command_long_send(self.sysid, 1, 511, 0, msg_id, 50000 if msg_id in (164, 33) else (100000 if msg_id == 193 else 500000), 0, 0, 0, 0, 0)
        self.stop = False
        self.thread = threading.Thread(target=self.read, daemon=True)
        self.thread.start()

    def say(self, text):
        line = "%8.1f rover %d %s" % (time.time() % 1e5, self.sysid, text)
        print(line, flush=True)
        self.log.write(line + "\n")

    def read(self):
        while not self.stop:
            m = self.conn.recv_match(blocking=True, timeout=0.2)
            if m is None:
                continue
            now = time.time()
            ty = m.get_type()
            if m.get_srcSystem() != self.sysid:
                continue
            with self.lock:
                if ty == "SIMSTATE":
                    n, e = geo_to_ned(ORIGIN, m.lat * 1e-7, m.lng * 1e-7)
                    self.truth.append((now, n, e, 0.0))
                elif ty == "GLOBAL_POSITION_INT":
                    # EKF3's estimate as latitude and longitude: each rover's EKF has its own
                    # origin when it had GNSS, so its local frame is not the team's
                    if m.lat != 0 or m.lon != 0:
                        n, e = geo_to_ned(ORIGIN, m.lat * 1e-7, m.lon * 1e-7)
                        self.ekf.append((now, n, e))
                elif ty == "EKF_STATUS_REPORT":
                    if m.flags != self.ekf_flags:
                        self.say("EKF flags 0x%04x" % m.flags)
                    self.had_position |= bool(m.flags & 0x18)  # horizontal position, relative or absolute
                    if self.want_auto and (m.flags & 0x18) and self.mission_state != 3 and now - self.auto_sent > 0.3:
                        # EKF3 alone at rest keeps a position only in short windows: AUTO and the
                        # mission start go in one of them (from this thread, at once)
                        self.auto_sent = now
                        self.conn.mav.command_long_send(self.sysid, 1, 176, 0, 1, self.conn.mode_mapping()["AUTO"], 0, 0, 0, 0, 0)
                        self.conn.mav.command_long_send(self.sysid, 1, 300, 0, 0, 0, 0, 0, 0, 0, 0)
                    # (only once EKF3 runs: an origin set before its cores initialise is lost)
                    if self.give_origin and self.origin is None and (m.flags & 0x401) == 0x001 and now - self.origin_sent > 2.0:
                        self.origin_sent = now
                        self.conn.mav.set_gps_global_origin_send(self.sysid, int(ORIGIN[0] * 1e7), int(ORIGIN[1] * 1e7), int(ORIGIN[2] * 1e3), 0)
                    self.ekf_flags = m.flags
                elif ty == "HEARTBEAT" and m.get_srcComponent() == 1:
                    self.armed = bool(m.base_mode & 128)
                    self.mode = m.custom_mode
                elif ty == "STATUSTEXT":
                    self.texts.append(m.text)
                    self.say("says: " + m.text)
                elif ty == "GPS_GLOBAL_ORIGIN":
                    if self.origin is None:
                        self.say("origin %.7f %.7f" % (m.latitude * 1e-7, m.longitude * 1e-7))
                    self.origin = (m.latitude, m.longitude)
                elif ty in ("MISSION_REQUEST", "MISSION_REQUEST_INT"):
                    self.mission_requests.append(m.seq)
                elif ty == "HOME_POSITION":
                    self.home = True
                elif ty == "MISSION_CURRENT":
                    self.mission_state = getattr(m, "mission_state", 3)
                elif ty == "MISSION_ACK":
                    self.mission_ack = m.type

    def truth_at(self, t):
        """Truth (north, east) at wall time t, interpolated; None outside what arrived."""
        with self.lock:
            k = bisect.bisect_left(self.truth, (t,))
            if k == 0 or k >= len(self.truth):
                return None
            a, b = self.truth[k - 1], self.truth[k]
        if b[0] - a[0] > 0.5:
            return None  # a gap in the truth: no interpolation across it
        f = (t - a[0]) / (b[0] - a[0]) if b[0] > a[0] else 0.0
        return (a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))

    def upload_mission(self, waypoints):
        """waypoints: [(north, east)] about the team's origin, as NAV_WAYPOINT items."""
        items = [(0, 0)] + waypoints  # item 0: home, replaced by the autopilot
        self.mission_requests.clear()
        self.mission_ack = None
        self.conn.mav.mission_count_send(self.sysid, 1, len(items), 0)
        sent = set()
        deadline = time.time() + 30
        while self.mission_ack is None and time.time() < deadline:
            while self.mission_requests:
                seq = self.mission_requests.pop(0)
                n, e = items[seq]
                lat, lon = ned_to_geo(ORIGIN, n, e)
                self.conn.mav.mission_item_int_send(self.sysid, 1, seq, 6, 16, 0, 1, 0, 0, 0, 0,
                                                    int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0, 0)
                sent.add(seq)
            time.sleep(0.02)
        if self.mission_ack != 0:
            raise RuntimeError("rover %d refused the mission (MISSION_ACK %s, items sent %s)" % (self.sysid, self.mission_ack, sorted(sent)))

    def set_mode(self, name):
        mapping = self.conn.mode_mapping()
        self.conn.mav.command_long_send(self.sysid, 1, 176, 0, 1, mapping[name], 0, 0, 0, 0, 0)

    def arm(self):
        self.conn.mav.command_long_send(self.sysid, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)

    def set_param(self, name, value):
        self.conn.mav.param_set_send(self.sysid, 1, name.encode(), float(value), 9)



def mission_for(i, laps):
    r = ROVERS[i]
    n0, e0 = r["start"]
    dn, de = r["rect"]
    lap = [(n0 + dn, e0), (n0 + dn, e0 + de), (n0, e0 + de), (n0, e0)]
    return lap * laps


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ardurover", required=True, help="the ArduRover SITL binary (build/sitl/bin/ardurover)")
    ap.add_argument("--defaults", help="ArduPilot's rover.parm (default: Tools/autotest/default_params/rover.parm beside the binary's tree)")
    ap.add_argument("--cooploc", default=None, help="the cooploc binary (default: target/release/cooploc)")
    ap.add_argument("--setup", choices=["nognss", "gnss-lost", "gnss-glitch"], required=True)
    ap.add_argument("--method", choices=["dcl", "dr", "alone"], required=True)
    ap.add_argument("--out", default=None, help="run folder (default: a new one under /tmp)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the range noise")
    ap.add_argument("--json", default=None, help="write the result here too")
    ap.add_argument("--timeout-s", type=float, default=420.0, help="give up on the mission after this long")
    ap.add_argument("--restart-node", type=int, default=None, help="kill this node (1..3) and start it again")
    ap.add_argument("--restart-at-s", type=float, default=60.0, help="... this long into the mission")
    ap.add_argument("--down-s", type=float, default=0.0, help="... and kept down this long before it starts again")
    ap.add_argument("--without-state", action="store_true", help="... and its state file removed before it starts again")
    args = ap.parse_args()
    if args.restart_node is not None and (args.method == "alone" or not 1 <= args.restart_node <= 3):
        sys.exit("error: --restart-node needs cooploc nodes (--method dcl or dr) and a node 1..3")

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    ardurover = os.path.abspath(args.ardurover)
    defaults = args.defaults or os.path.join(os.path.dirname(ardurover), "..", "..", "..", "Tools", "autotest", "default_params", "rover.parm")
    if not os.path.isfile(ardurover) or not os.path.isfile(defaults):
        sys.exit("error: need the ardurover binary (%s) and its rover.parm (%s; --defaults)" % (ardurover, defaults))
    cooploc = os.path.abspath(args.cooploc or os.path.join(root, "target", "release", "cooploc"))
    profile = os.path.join(root, "sitl", "vehicles", "ardupilot-sitl-rover.toml")
    out = os.path.abspath(args.out or "/tmp/real-ardupilot-%s-%s-%d" % (args.setup, args.method, os.getpid()))
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    log = open(os.path.join(out, "driver.log"), "w")
    rng = random.Random(args.seed)
    procs = []
    nodes_started = []

    def spawn(cmd, cwd, name):
        f = open(os.path.join(out, name), "w")
        p = subprocess.Popen(cmd, cwd=cwd, stdout=f, stderr=subprocess.STDOUT)
        procs.append(p)
        return p

    try:
        key = os.path.join(out, "team.key")
        with open(key, "w") as f:
            f.write("%064x\n" % random.Random(args.seed + 1000).getrandbits(256))
        coop_ports = [free_udp_port() for _ in ROVERS]
        range_ports = [free_udp_port() for _ in ROVERS]
        for i, r in enumerate(ROVERS):
            d = os.path.join(out, "r%d" % (i + 1))
            os.makedirs(d)
            with open(os.path.join(d, "extra.parm"), "w") as f:
                for k, v in params_for(i, args.setup, args.method).items():
                    f.write("%s %s\n" % (k, v))
            lat, lon = ned_to_geo(ORIGIN, *r["start"])
            spawn([ardurover, "--model", "rover", "--speedup", "1", "-I%d" % i, "--sysid", str(i + 1),
                   "--home", "%.8f,%.8f,%.1f,%.1f" % (lat, lon, ORIGIN[2], r["heading"]),
                   "--defaults", "%s,%s" % (defaults, os.path.join(d, "extra.parm"))], d, "sitl%d.out" % (i + 1))
        time.sleep(1.0)
        if args.method != "alone":
            for i, r in enumerate(ROVERS):
                d = os.path.join(out, "r%d" % (i + 1))
                peers = ", ".join('"127.0.0.1:%d"' % p for j, p in enumerate(coop_ports) if j != i)
                with open(os.path.join(d, "node.toml"), "w") as f:
                    f.write('id = %d\nvehicle = "tcpout:127.0.0.1:%d"\nvehicle_config = "%s"\nteam = [1, 2, 3]\n'
                            'method = "%s"\ncoop_bind = "127.0.0.1:%d"\npeer = [%s]\nteam_key = "%s"\n'
                            'ranges = "udpin:127.0.0.1:%d"\nrange_grace_ms = 300\n'
                            'log = "node.mcap"\nidle_exit_s = 3.0\nstate_file = "node.state"\n'
                            % (i + 1, 5760 + 10 * i, profile, args.method, coop_ports[i], peers, key, range_ports[i]))
                    if args.setup == "nognss":
                        # a known start pose (surveyed, as the paper's platforms start)
                        f.write("init_ned = [%.3f, %.3f, 0.0]\ninit_rpy_deg = [0.0, 0.0, %.1f]\n" % (r["start"][0], r["start"][1], r["heading"]))
                    else:
                        # the hand-over start: from the autopilot's estimate when GNSS goes
                        f.write("init_from_autopilot = true\n")
                nodes_started.append(spawn([cooploc, "node", "--config", "node.toml"], d, "node%d.out" % (i + 1)))
                time.sleep(0.3)
        port = lambda i: (5760 if args.method == "alone" else 5762) + 10 * i  # noqa: E731
        rovers = [Rover(i, port(i), log) for i in range(len(ROVERS))]
        for rv in rovers:
            rv.say("connected")

        # wait for an origin (the node's SET_GPS_GLOBAL_ORIGIN, or GNSS) and a position estimate
        t0 = time.time()
        while time.time() - t0 < 120:
            for rv in rovers:
                if rv.origin is None:
                    # no cooploc node to give the origin: the driver does, as a ground station
                    # would, once the EKF runs (its reader, at each EKF_STATUS_REPORT)
                    rv.give_origin = args.method == "alone" and args.setup == "nognss"
                    rv.conn.mav.command_long_send(rv.sysid, 1, 512, 0, 49, 0, 0, 0, 0, 0, 0)
            # (EKF3 alone on wheel encoders at rest drops its relative aiding every few seconds:
            # a position estimate once is enough)
            ready = [rv.origin is not None and rv.had_position for rv in rovers]
            if all(ready):
                break
            time.sleep(2.0)
        else:
            raise RuntimeError("no origin or position estimate after 120 s: %s" % [(rv.origin, rv.ekf_flags) for rv in rovers])
        # a home (ArduPilot runs no mission without one; EKF3 alone on wheel encoders, dropping
        # its relative aiding at rest, may never set it): its start when it has none
        def ask_or_set_home(rv, waited_s):
            rv.conn.mav.command_long_send(rv.sysid, 1, 512, 0, 242, 0, 0, 0, 0, 0, 0)
            if waited_s > 3:
                # its start, surveyed (as the nodes' init_ned): "current location" needs a
                # position EKF3 alone keeps only half the time at rest
                lat, lon = ned_to_geo(ORIGIN, *ROVERS[rv.i]["start"])
                rv.conn.mav.command_int_send(rv.sysid, 1, 0, 179, 0, 0, 0, 0, 0, 0,
                                             int(round(lat * 1e7)), int(round(lon * 1e7)), ORIGIN[2])
        until(rovers, lambda rv: rv.home, ask_or_set_home, 60, "a home")
        for i, rv in enumerate(rovers):
            rv.upload_mission(mission_for(i, LAPS[args.setup]))
            rv.say("mission of %d waypoints" % len(mission_for(i, LAPS[args.setup])))
        # arm (ArduPilot refuses for ~20 s after boot: "Gyros inconsistent") and go
        until(rovers, lambda rv: rv.armed, lambda rv, _: rv.arm(), 120, "armed", every_s=3.0)
        if args.method == "alone":
            # EKF3 alone on wheel encoders gives a location only while they turn: at rest AUTO
            # waits and never starts its mission. A push in MANUAL first (RC override, 2 s of
            # throttle, straight ahead), as a driver would roll it off its spot.
            for rv in rovers:
                rv.set_mode("MANUAL")
            time.sleep(1.0)
            t1 = time.time()
            while time.time() - t1 < 2.0:
                for rv in rovers:
                    rv.conn.mav.rc_channels_override_send(rv.sysid, 1, 1500, 0, 1700, 0, 0, 0, 0, 0)
                time.sleep(0.1)
        # AUTO, until each says so (a rover whose EKF just dropped its relative aiding refuses)
        auto = rovers[0].conn.mode_mapping()["AUTO"]
        until(rovers, lambda rv: rv.mode == auto, lambda rv, _: rv.set_mode("AUTO"), 60, "AUTO")
        # and the mission running (ArduPilot may enter AUTO without starting it: MISSION_START)
        t0 = time.time()
        for rv in rovers:
            rv.want_auto = True
        while not all(rv.mission_state == 3 for rv in rovers):
            if time.time() - t0 > 90:
                raise RuntimeError("missions not running after 90 s: %s" % [rv.mission_state for rv in rovers])
            time.sleep(0.5)
        for rv in rovers:
            rv.want_auto = False
            if args.method == "alone":
                rv.conn.mav.rc_channels_override_send(rv.sysid, 1, 0, 0, 0, 0, 0, 0, 0, 0)  # released
        start = time.time()
        for rv in rovers:
            rv.say("armed, AUTO")

        # the range emulator, on the team's 1 s grid of Unix time, until every rover is home
        dev = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        gnss_lost_at = start + GNSS_LOSS_S if args.setup != "nognss" else start
        gnss_off = args.setup == "nognss"
        glitch_ends_at = gnss_lost_at + GLITCH_S if args.setup == "gnss-glitch" else None
        epochs = 0
        done_at = None
        restart_at = start + args.restart_at_s if args.restart_node is not None else None
        restarted_at = killed_at = None
        next_epoch = math.floor(time.time()) + 1
        while True:
            now = time.time()
            if glitch_ends_at is not None and not gnss_off and now >= gnss_lost_at:
                for rv in rovers:
                    rv.set_param("SIM_GPS1_GLTCH_X", GLITCH_DEG)
                    rv.say("GNSS glitch: %.0f m north" % (GLITCH_DEG * 111_319.49))
                gnss_off = True
            if glitch_ends_at is not None and now >= glitch_ends_at:
                for rv in rovers:
                    rv.set_param("SIM_GPS1_GLTCH_X", 0)
                    rv.say("GNSS glitch over")
                glitch_ends_at = None
            if not gnss_off and now >= gnss_lost_at:
                for rv in rovers:
                    rv.set_param("SIM_GPS1_ENABLE", 0)
                    rv.say("GNSS lost")
                if args.method == "alone":
                    # ArduPilot alone: to its wheel-encoder set, as its source-switching scripts do
                    for rv in rovers:
                        rv.conn.mav.command_long_send(rv.sysid, 1, 42007, 0, 2, 0, 0, 0, 0, 0, 0)
                gnss_off = True
            if now >= next_epoch + 0.06:  # the truth around the instant has arrived
                t = next_epoch
                next_epoch += 1
                pos = [rv.truth_at(t) for rv in rovers]
                if args.method != "alone" and all(p is not None for p in pos):
                    for i in range(len(rovers)):
                        for j in range(i + 1, len(rovers)):
                            d = math.hypot(pos[i][0] - pos[j][0], pos[i][1] - pos[j][1]) + rng.gauss(0.0, RANGE_SIGMA_M)
                            line = "RANGE,%d,%d,%.3f,%.2f,%d\n" % (t, j + 1, d, RANGE_SIGMA_M, t * 1_000_000)
                            dev.sendto(line.encode(), ("127.0.0.1", range_ports[i]))
                    epochs += 1
            if restart_at is not None and killed_at is None and now >= restart_at:
                k = args.restart_node - 1
                old = nodes_started[k]
                old.kill()  # SIGKILL: no summary, no last save
                old.wait()
                killed_at = now
                rovers[k].say("node killed")
                if args.without_state:
                    state = os.path.join(out, "r%d" % (k + 1), "node.state")
                    if os.path.exists(state):
                        os.remove(state)
            if restart_at is not None and killed_at is not None and now >= killed_at + args.down_s:
                k = args.restart_node - 1
                d = os.path.join(out, "r%d" % (k + 1))
                nodes_started[k] = spawn([cooploc, "node", "--config", "node.toml"], d, "node%d-restarted.out" % (k + 1))
                rovers[k].say("node restarted after %.1f s%s" % (now - killed_at, ", its state file removed" if args.without_state else ""))
                restarted_at, restart_at = now, None
            finished = [rv.armed is False or ("Mission Complete" in " ".join(rv.texts)) for rv in rovers]
            if all(finished) and done_at is None:
                done_at = now
            if done_at is not None and now > done_at + 2.0:
                break
            if now - start > args.timeout_s:
                print("timeout: the missions did not all end", flush=True)
                break
            time.sleep(0.01)
        end = time.time()
        result = {"setup": args.setup, "method": args.method, "epochs_ranged": epochs, "rovers": []}
        for rv in rovers:
            with rv.lock:
                ekf = [x for x in rv.ekf if gnss_lost_at <= x[0] <= end]
                truth = list(rv.truth)
            errs, windows = [], {}
            for (t, n, e) in ekf:
                p = rv.truth_at(t)
                if p is not None:
                    errs.append(math.hypot(n - p[0], e - p[1]))
                    windows.setdefault(int((t - gnss_lost_at) // 10), []).append(errs[-1])
            path = 0.0
            tr = [x for x in truth if gnss_lost_at <= x[0] <= end]
            for a, b in zip(tr, tr[1:]):
                path += math.hypot(b[1] - a[1], b[2] - a[2])
            rms = math.sqrt(sum(x * x for x in errs) / len(errs)) if errs else float("nan")
            result["rovers"].append({"sysid": rv.sysid, "path_m": path, "rms_m": rms, "final_m": errs[-1] if errs else float("nan"),
                                     "samples": len(errs), "external_nav": any("external nav" in t for t in rv.texts),
                                     "mission_complete": "Mission Complete" in " ".join(rv.texts),
                                     # the error's RMS over each 10 s since the loss (or the start), m
                                     "rms_by_10_s_m": [round(math.sqrt(sum(x * x for x in w) / len(w)), 3)
                                                       for _, w in sorted(windows.items())]})
            rv.say("%s %s: %.0f m without GNSS, EKF3 error RMS %.2f m, final %.2f m (%d samples)"
                   % (args.setup, args.method, path, rms, result["rovers"][-1]["final_m"], len(errs)))
        all_errs = [r["rms_m"] for r in result["rovers"]]
        result["team_rms_m"] = math.sqrt(sum(x * x for x in all_errs) / len(all_errs))
        if restarted_at is not None:
            rv = rovers[args.restart_node - 1]
            with rv.lock:
                ekf = list(rv.ekf)
            if args.down_s > 0:
                for sec in range(int(math.ceil(restarted_at - killed_at + 10))):
                    errs = [math.hypot(n - p[0], e - p[1]) for (t, n, e) in ekf if killed_at + sec <= t < killed_at + sec + 1
                            for p in [rv.truth_at(t)] if p is not None]
                    if errs:
                        print("rover %d, %2d-%2d s after the kill: EKF3 error %.2f m (worst %.2f m)"
                              % (args.restart_node, sec, sec + 1, sum(errs) / len(errs), max(errs)), flush=True)
            windows = [("30 s before", killed_at - 30, killed_at), ("while down", killed_at, restarted_at),
                       ("10 s after", restarted_at, restarted_at + 10),
                       ("10-60 s after", restarted_at + 10, restarted_at + 60), ("10 s after to the end", restarted_at + 10, end)]
            result["restart"] = {"node": args.restart_node, "at_s": restarted_at - start, "down_s": restarted_at - killed_at,
                                 "without_state": args.without_state}
            for name, a, b in windows:
                if b - a < 0.05:
                    continue  # (not down at all)
                errs = [math.hypot(n - p[0], e - p[1]) for (t, n, e) in ekf if a <= t <= b
                        for p in [rv.truth_at(t)] if p is not None]
                worst = max(errs) if errs else float("nan")
                rms = math.sqrt(sum(x * x for x in errs) / len(errs)) if errs else float("nan")
                result["restart"][name] = {"rms_m": rms, "worst_m": worst, "samples": len(errs)}
                print("rover %d, node restarted at %.0f s, %s: EKF3 error RMS %.2f m, worst %.2f m (%d samples)"
                      % (args.restart_node, restarted_at - start, name, rms, worst, len(errs)), flush=True)
        print("team RMS %.2f m (%s, %s)" % (result["team_rms_m"], args.setup, args.method), flush=True)
        for rv in rovers:
            rv.stop = True
            rv.set_mode("HOLD")
        if args.json:
            with open(args.json, "w") as f:
                json.dump(result, f, indent=1)
        with open(os.path.join(out, "result.json"), "w") as f:
            json.dump(result, f, indent=1)
    finally:
        # the nodes first, by Ctrl-C: each says its summary in its node.out
        stop_all(procs, nodes_started)
        log.close()


if __name__ == "__main__":
    main()
