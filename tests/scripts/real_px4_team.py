#!/usr/bin/env python3
"""Three rovers on the real PX4 firmware (its SIH software-in-the-loop build), navigating without
GNSS on cooploc: the PX4 counterpart of real_ardupilot_team.py.

Runs three PX4 SIH instances (airframe 10045, Ackermann rover, real time, each from its own
start: PX4_HOME_LAT/LON), a `cooploc node` beside each on its onboard link, a wheel-odometry
emulator and a range emulator, a mission driver on each GCS link, and prints, per rover, the
error of PX4's own EKF2 estimate (GLOBAL_POSITION_INT) against SIH's truth
(HIL_STATE_QUATERNION) over the GNSS-less part: RMS and final. It builds nothing: it runs the
`px4` binary it is given (build/px4_sitl_sih/bin/px4, its etc/ beside bin/).

- Ports, instance i (PX4's own SITL start-up): the onboard link, PX4 UDP 14580+i sending to
  127.0.0.1:14540+i; the GCS link, PX4 18570+i (the driver's socket, after its first datagram);
  SIH's truth, HIL_STATE_QUATERNION at 25 Hz to 127.0.0.1:19410+i. MAV_SYS_ID = i+1.
- Set-ups: `nognss`: no GNSS from power-on (SENS_EN_GPSSIM 0, SYS_HAS_GPS 0, EKF2_GPS_CTRL 0),
  no compass (SENS_EN_MAGSIM 0, SYS_HAS_MAG 0, EKF2_MAG_TYPE 5); the team's origin goes to each
  EKF2 by SET_GPS_GLOBAL_ORIGIN (see --origin) and each node starts from its rover's known
  start pose. `gnss-lost`: GNSS and a compass until 60 s into the mission, then SIM_GPS_USED 0
  (SIH's receiver reports no fix) and EKF2's magnetometer fusion off (VEHICLE_CMD_ESTIMATOR_SENSOR_ENABLE);
  each node starts from PX4's estimate then (`init_from_autopilot`); PX4 has no source sets, so
  EKF2 simply fuses the node's ODOMETRY once it comes. Three laps.
- Methods: `dcl` and `dr` (cooploc nodes; EKF2 fuses their ODOMETRY as external vision:
  EKF2_EV_CTRL 13 = horizontal position, velocity, yaw), `alone` (no cooploc: EKF2 fuses the SAME
  emulated wheel odometry as an external-vision body-frame velocity, EKF2_EV_CTRL 4, and its IMU).
  Height from the simulated barometer in all three (EKF2_HGT_REF 1): the same vertical source on
  both sides, and not scored.
- Wheel odometry: PX4's SIH simulates no wheel encoder (no wheel distance, no WHEEL_DISTANCE),
  so this driver stands in for one: from SIH's truth (HIL_STATE_QUATERNION, 25 Hz) the
  body-frame forward speed times a per-rover scale error (1 + scale) plus N(0, 0.05 m/s), as
  ODOMETRY (child frame BODY_FRD, vy = vz = 0, pose NaN, estimator VIO, stamped in PX4's boot
  time) from component 197 of the rover's system id, one per truth sample (25 Hz). To the node
  it is its `odometry` input; for PX4 alone it goes to PX4 itself.
- The onboard link goes through a small relay in this driver (a companion's MAVLink router):
  PX4 <-> 127.0.0.1:14540+i <-> the node's `udpin:` port; the odometry component's frames join
  the stream to the node there (a node on `udpin` answers whoever sent last, so the emulator
  cannot send to it directly).
- Ranges: one per pair of rovers per second (on the team's 1 s grid of Unix time), measured by
  the lower id's radio, from SIH's truth (interpolated to the epoch's instant) plus N(0, 0.1 m),
  sent to that rover's node (`--ranges`), exactly as real_ardupilot_team.py does.
- Missions in AUTO.MISSION: each rover drives its own rectangle twice, three times when GNSS goes
  at 60 s (>= 300 m without GNSS either way).
- Scored: EKF2's GLOBAL_POSITION_INT (20 Hz) against the truth interpolated at its time_boot_ms
  (both PX4's simulated clock), horizontal, from the mission start (or the GNSS loss) to its end.

What PX4 did that the project's PX4 assumptions (sitl/vehicles/px4-rover.toml, the node) had not,
and what the driver does about it (each has an option to turn the workaround off, or, for the two
fixed in the node, back on):

- Fixed in the node: before the node named the frame per profile, its ODOMETRY said frame_id
  LOCAL_FRD. EKF2 fused it (EV position, velocity and yaw) but took an FRD pose as a frame of
  unknown heading (ev_yaw_control.cpp: yaw_align = false): no heading reference, no global
  position, no arming ("Preflight Fail: no heading reference"), and the relay rewrote frame_id to
  LOCAL_NED. The node now sends LOCAL_NED where the profile says `odometry_frame = "local_ned"`
  (px4-sih-rover.toml does); --odometry-frame ned keeps the old rewrite (default: as-sent).
- PX4's HIGHRES_IMU has EKF2's IMU bias estimates taken out. EKF2 fusing the node's ODOMETRY
  learns the node's errors as biases and hands them back in the node's IMU: EKF2_IMU_CTRL 4 (no
  bias estimation) for dcl and dr (--ekf2-bias).
- SIH's simulated clock (PX4's boot clock, TIMESYNC's tc1) ran 0.8 % slower than real time at
  PX4_SIM_SPEED_FACTOR 1 (its lockstep sleeps a little long each 4 ms step); the node's TIMESYNC
  mapping (the fastest of 16 answers) then lags by up to ~0.1 s, ranges are gated and records
  contradicted. PX4_SIM_SPEED_FACTOR 1.008 runs it at 1.000x on this machine (--sim-speed).
- Fixed in the node: PX4 converges its own TIMESYNC with the companion after 500 answers and then
  takes ODOMETRY's time_usec as the companion's clock. Before the node answered in PX4's clock, it
  answered PX4's requests in Unix time but stamped ODOMETRY in PX4's boot time, and the relay
  withheld PX4's TIMESYNC requests from the node. The node now answers them in PX4's boot clock
  (by its mapping), and not at all before it has one; --px4-timesync drop keeps the old
  withholding (default: pass).
- PX4 alone (no compass, no GNSS, a velocity-only odometry) has no heading and no position: the
  driver gives its surveyed start heading (MAV_CMD_EXTERNAL_ATTITUDE_ESTIMATE) and position
  (MAV_CMD_EXTERNAL_POSITION_ESTIMATE); an origin alone leaves EKF2's global position near
  latitude 0, longitude 0 (EKF2 keeps a global position state of its own).

usage: real_px4_team.py --px4 PATH --setup nognss|gnss-lost --method dcl|dr|alone [--out DIR] [--cooploc PATH]
       [--origin driver|node] [--px4-timesync pass|drop] [--odometry-frame as-sent|ned]
       [--ekf2-bias off|on] [--sim-speed F] [--profile FILE] [--seed N] [--json FILE]
"""
import argparse
import bisect
import glob
import json
import math
import os
import random
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from real_team_common import free_udp_port, geo_to_ned, ned_to_geo, stop_all, until  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

ORIGIN = (47.397742, 8.545594, 488.0)  # PX4 SITL's default home (Zurich), the team's origin (px4-rover.toml)
RANGE_SIGMA_M = 0.1  # the paper's Table 1
ODOM_SIGMA_M_S = 0.05  # the emulated wheel odometry's white noise
ODOM_COMPID = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY: the wheel-odometry component
# Each rover: start (north, east, m), heading (deg), rectangle (north, east sides, m; negative east
# turns left), and its wheel odometry's scale error.
ROVERS = [
    dict(start=(0.0, 0.0), heading=0.0, rect=(80.0, 20.0), scale=0.02),
    dict(start=(0.0, 30.0), heading=0.0, rect=(60.0, -25.0), scale=-0.015),
    dict(start=(-10.0, 60.0), heading=0.0, rect=(70.0, 25.0), scale=0.01),
]
LAPS = {"nognss": 2, "gnss-lost": 3}  # the GNSS-less part >= 300 m (with GNSS lost at 60 s, a third lap)
GNSS_LOSS_S = 60.0  # into the mission, set-up gnss-lost
PX4_AUTO, PX4_AUTO_MISSION, PX4_AUTO_LOITER = 4, 4, 3





def params_for(i, setup, method, ekf2_bias=False):
    p = {
        # no GNSS
        "SENS_EN_GPSSIM": 0, "SYS_HAS_GPS": 0, "EKF2_GPS_CTRL": 0,
        # no compass on either side
        "SENS_EN_MAGSIM": 0, "SYS_HAS_MAG": 0, "EKF2_MAG_TYPE": 5,
    } if setup == "nognss" else {
        # GNSS (SIH's simulated receiver) and a compass for its yaw until the loss; at the loss the
        # driver sets SIM_GPS_USED 0 (no fix) and turns EKF2's magnetometer fusion off
        # (VEHICLE_CMD_ESTIMATOR_SENSOR_ENABLE): the scored part uses neither
        "EKF2_MAG_TYPE": 0,
    }
    p.update({
        # height from the barometer (all methods alike)
        "EKF2_HGT_REF": 1,
        # the rectangles' corners taken at speed (as ArduPilot's WP_RADIUS 2)
        "NAV_ACC_RAD": 2.0,
    })
    if method == "alone":
        p["EKF2_EV_CTRL"] = 4  # external vision: velocity only (the wheel odometry)
    else:
        p["EKF2_EV_CTRL"] = 13  # external vision: horizontal position, velocity, yaw (the node's ODOMETRY)
        if not ekf2_bias:
            # PX4's HIGHRES_IMU has EKF2's bias estimates taken out; EKF2 on the node's ODOMETRY learns
            # the node's own errors as IMU biases (its gyro z bias wandered 200-1000 deg/h where EKF2
            # alone kept 40) and hands them back to the node in its IMU: a feedback loop. EKF2 keeps
            # its gravity fusion but estimates no IMU bias (SIH's IMU has none to learn).
            p["EKF2_IMU_CTRL"] = 4
    return p


def frames(data):
    """(msgid, start, end) of each MAVLink frame in a datagram."""
    k = 0
    while k < len(data):
        if data[k] == 0xFD and k + 10 <= len(data):
            n = 12 + data[k + 1] + (13 if data[k + 2] & 1 else 0)
            yield data[k + 7] | (data[k + 8] << 8) | (data[k + 9] << 16), k, k + n
            k += n
        elif data[k] == 0xFE and k + 6 <= len(data):
            n = 8 + data[k + 1]
            yield data[k + 5], k, k + n
            k += n
        else:
            return


class Relay:
    """The onboard link through this driver: PX4 <-> 127.0.0.1:14540+i <-> the node's udpin port.
    `inject(bytes)` puts the odometry component's frames on the way to the node."""

    def __init__(self, i, node_port, drop_px4_timesync, ned):
        self.px4 = ("127.0.0.1", 14580 + i)
        self.node = ("127.0.0.1", node_port)
        self.a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.a.bind(("127.0.0.1", 14540 + i))
        self.b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.b.bind(("127.0.0.1", 0))
        self.drop = drop_px4_timesync
        self.ned = ned
        self.rewritten = 0
        self.node_est = []  # the node's own estimate (its LOCAL_POSITION_NED to PX4): (PX4 time s, north, east)
        self.dropped = 0
        self.to_node = 0
        self.to_px4 = 0
        self.stop = False
        threading.Thread(target=self.run, daemon=True).start()

    def inject(self, data):
        self.b.sendto(data, self.node)

    def run(self):
        while not self.stop:
            r, _, _ = select.select([self.a, self.b], [], [], 0.2)
            for s in r:
                data, _ = s.recvfrom(65536)
                if s is self.a:
                    if self.drop and b"\x6f\x00\x00" in data:
                        # PX4's TIMESYNC requests (id 111, tc1 = 0) kept from the node
                        keep = b""
                        for msgid, a, b in frames(data):
                            if msgid == 111 and data[a + 10:a + 18] == b"\x00" * 8:
                                self.dropped += 1
                                continue
                            keep += data[a:b]
                        data = keep
                        if not data:
                            continue
                    self.to_node += 1
                    self.b.sendto(data, self.node)
                else:
                    if b"\x20\x00\x00" in data:
                        for msgid, a, b in frames(data):
                            if msgid == 32 and data[a] == 0xFD:
                                pl = data[a + 10:a + 10 + data[a + 1]] + bytes(28)
                                t_ms, x, y = struct.unpack_from("<Iff", pl)
                                self.node_est.append((t_ms * 1e-3, x, y))
                    if self.ned and b"\x4b\x01\x00" in data:
                        data = self.odometry_to_ned(data)
                    self.to_px4 += 1
                    self.a.sendto(data, self.px4)

    def odometry_to_ned(self, data):
        """The node's ODOMETRY with frame_id LOCAL_FRD (20) as LOCAL_NED (1): EKF2 takes an FRD pose as
        a frame of unknown heading and never declares its yaw aligned (see --odometry-frame)."""
        out = bytearray(data)
        for msgid, a, b in frames(data):
            if msgid == 331 and data[a] == 0xFD and data[a + 1] > 228 and out[a + 10 + 228] == 20:
                out[a + 10 + 228] = 1
                n = data[a + 1]
                crc = mavutil.x25crc(bytes(out[a + 1:a + 10 + n]))
                crc.accumulate(bytes([91]))  # ODOMETRY's CRC_EXTRA
                out[a + 10 + n] = crc.crc & 0xFF
                out[a + 11 + n] = crc.crc >> 8
                self.rewritten += 1
        return bytes(out)


class Rover:
    """One SIH instance: its GCS link (commands, EKF2 estimate, status) and its truth link."""

    def __init__(self, i, log, rng):
        self.i, self.sysid, self.log = i, i + 1, log
        self.rng = rng
        self.lock = threading.Lock()
        self.truth = []  # (sim s, north, east, wall s)
        self.truth_wall = []  # (wall s, north, east)
        self.ekf = []  # (sim s, north, east)
        self.est_flags = None
        self.est_flags_seen = set()
        self.armed = False
        self.mode = None
        self.texts = []
        self.origin = None
        self.mission_requests = []
        self.mission_ack = None
        self.mission_state = None
        self.mission_seq = None
        self.odom_sink = None  # where the emulated wheel odometry goes (bytes), None: nowhere yet
        self.odom_sent = 0
        self.stop = False
        self.conn = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % (18570 + i), source_system=255,
                                               source_component=190, dialect="common")
        self.truth_conn = mavutil.mavlink_connection("udpin:127.0.0.1:%d" % (19410 + i), source_system=254, dialect="common")
        self.odom_mav = mavlink2.MAVLink(None, srcSystem=self.sysid, srcComponent=ODOM_COMPID)
        deadline = time.time() + 120
        while True:
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)  # a GCS: PX4's GCS link takes this socket as its partner
            if self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0) is not None:
                break
            if time.time() > deadline:
                raise RuntimeError("rover %d: no heartbeat on the GCS link" % self.sysid)
        for msg_id, us in ((33, 50000), (32, 50000), (230, 500000), (42, 500000)):
            self.cmd(511, msg_id, us)
        threading.Thread(target=self.read, daemon=True).start()
        threading.Thread(target=self.read_truth, daemon=True).start()

    def say(self, text):
        line = "%8.1f rover %d %s" % (time.time() % 1e5, self.sysid, text)
        print(line, flush=True)
        self.log.write(line + "\n")
        self.log.flush()

    def cmd(self, command, *p):
        p = list(p) + [0] * (7 - len(p))
        self.conn.mav.command_long_send(self.sysid, 1, command, 0, *p)

    def read_truth(self):
        while not self.stop:
            m = self.truth_conn.recv_match(type="HIL_STATE_QUATERNION", blocking=True, timeout=0.5)
            if m is None:
                continue
            now = time.time()
            n, e = geo_to_ned(ORIGIN, m.lat * 1e-7, m.lon * 1e-7)
            t = m.time_usec * 1e-6
            with self.lock:
                self.truth.append((t, n, e))
                self.truth_wall.append((now, n, e))
            # the wheel odometry: body-frame forward speed, scale error and white noise
            w, x, y, z = m.attitude_quaternion
            vn, ve, vd = m.vx * 0.01, m.vy * 0.01, m.vz * 0.01
            fwd = (1 - 2 * (y * y + z * z)) * vn + 2 * (x * y + w * z) * ve + 2 * (x * z - w * y) * vd
            speed = fwd * (1.0 + ROVERS[self.i]["scale"]) + self.rng.gauss(0.0, ODOM_SIGMA_M_S)
            sink = self.odom_sink
            if sink is not None:
                nan = float("nan")
                vcov = [nan] * 21
                vcov[0] = ODOM_SIGMA_M_S ** 2
                vcov[6] = vcov[11] = 0.1 ** 2  # vy = vz = 0: a rover's wheels slip little sideways (the node's NHC sigma)
                for k in range(21):
                    if k not in (0, 6, 11):
                        vcov[k] = 0.0 if k < 15 else nan
                msg = self.odom_mav.odometry_encode(m.time_usec, mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD,
                                                    nan, nan, nan, [nan, 0, 0, 0], speed, 0.0, 0.0, nan, nan, nan,
                                                    [nan] * 21, vcov, 0, mavlink2.MAV_ESTIMATOR_TYPE_VIO, 0)
                sink(msg.pack(self.odom_mav))
                self.odom_sent += 1

    def read(self):
        beat = 0.0
        while not self.stop:
            if time.time() - beat > 1.0:
                beat = time.time()
                self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)  # a GCS (PX4's data-link loss check)
            m = self.conn.recv_match(blocking=True, timeout=0.2)
            if m is None:
                continue
            if m.get_srcSystem() != self.sysid:
                continue
            ty = m.get_type()
            with self.lock:
                if ty == "GLOBAL_POSITION_INT":
                    if m.lat != 0 or m.lon != 0:
                        n, e = geo_to_ned(ORIGIN, m.lat * 1e-7, m.lon * 1e-7)
                        self.ekf.append((m.time_boot_ms * 1e-3, n, e))
                elif ty == "ESTIMATOR_STATUS":
                    if self.est_flags is None or (m.flags ^ self.est_flags) & ~0x40:
                        self.say("ESTIMATOR_STATUS flags 0x%04x" % m.flags)
                    self.est_flags = m.flags
                    self.est_flags_seen.add(m.flags)
                elif ty == "HEARTBEAT" and m.get_srcComponent() == 1:
                    self.armed = bool(m.base_mode & 128)
                    if m.custom_mode != self.mode:
                        self.say("mode 0x%08x armed %s" % (m.custom_mode, self.armed))
                    self.mode = m.custom_mode
                elif ty == "STATUSTEXT":
                    self.texts.append(m.text)
                    self.say("says: " + m.text)
                elif ty == "GPS_GLOBAL_ORIGIN":
                    o = (m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3)
                    if self.origin != o:
                        self.say("origin %.7f %.7f %.1f" % o)
                    self.origin = o
                elif ty in ("MISSION_REQUEST", "MISSION_REQUEST_INT"):
                    self.mission_requests.append(m.seq)
                elif ty == "MISSION_CURRENT":
                    self.mission_state = getattr(m, "mission_state", None)
                    self.mission_seq = m.seq
                elif ty == "MISSION_ACK":
                    self.mission_ack = m.type

    def truth_at(self, t, wall=False):
        """Truth (north, east) at sim time t (or wall time), interpolated; None outside."""
        with self.lock:
            tr = self.truth_wall if wall else self.truth
            k = bisect.bisect_left(tr, (t,))
            if k == 0 or k >= len(tr):
                return None
            a, b = tr[k - 1], tr[k]
        if b[0] - a[0] > 0.5:
            return None
        f = (t - a[0]) / (b[0] - a[0]) if b[0] > a[0] else 0.0
        return (a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))

    def upload_mission(self, waypoints):
        self.mission_requests.clear()
        self.mission_ack = None
        self.conn.mav.mission_count_send(self.sysid, 1, len(waypoints), 0)
        deadline = time.time() + 30
        while self.mission_ack is None and time.time() < deadline:
            while self.mission_requests:
                seq = self.mission_requests.pop(0)
                lat, lon = ned_to_geo(ORIGIN, *waypoints[seq])
                self.conn.mav.mission_item_int_send(self.sysid, 1, seq, 6, 16, 0, 1, 0, 0, 0, float("nan"),
                                                    int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0, 0)
            time.sleep(0.02)
        if self.mission_ack != 0:
            raise RuntimeError("rover %d refused the mission (MISSION_ACK %s)" % (self.sysid, self.mission_ack))

    def set_origin(self, own_start=False):
        """The team's origin, or (PX4 alone) the rover's own surveyed start: EKF2's local position
        starts at 0, 0, so its origin is where it stands."""
        lat, lon = ned_to_geo(ORIGIN, *ROVERS[self.i]["start"]) if own_start else ORIGIN[:2]
        self.conn.mav.set_gps_global_origin_send(self.sysid, int(round(lat * 1e7)), int(round(lon * 1e7)), int(ORIGIN[2] * 1e3), 0)


SETUP = "nognss"


def mission_for(i):
    r = ROVERS[i]
    n0, e0 = r["start"]
    dn, de = r["rect"]
    return [(n0 + dn, e0), (n0 + dn, e0 + de), (n0, e0 + de), (n0, e0)] * LAPS[SETUP]



def ulog_fusion(px4_dir, from_s):
    """From PX4's own flight log (its estimator_status_flags, 1 Hz), the share of samples after
    `from_s` (PX4 time) in which EKF2 fused external vision position, velocity and yaw, and had
    its yaw aligned. Needs pyulog; None without it or without a log."""
    try:
        from pyulog import ULog
    except ImportError:
        return None
    logs = sorted(glob.glob(os.path.join(px4_dir, "log", "*", "*.ulg")))
    if not logs:
        return None
    try:
        u = ULog(logs[-1], ["estimator_status_flags"])
        d = [x for x in u.data_list if x.name == "estimator_status_flags" and x.multi_id == 0][0].data
    except Exception as e:  # a log cut short by the end of the run
        return {"error": str(e)[:100]}
    keep = [k for k, t in enumerate(d["timestamp"]) if t * 1e-6 >= from_s]
    if not keep:
        return None
    return {f: round(sum(float(d[f][k]) for k in keep) / len(keep), 3)
            for f in ("cs_ev_pos", "cs_ev_vel", "cs_ev_yaw", "cs_yaw_align", "cs_inertial_dead_reckoning")}


def node_summary(path):
    """The node's closing figures, from its output."""
    out = {}
    try:
        text = open(path).read()
    except OSError:
        return out
    m = re.search(r"done: .*?pos_ned_m \[([^\]]*)\].*?epochs_applied (\d+) epochs_partial (\d+) epochs_skipped (\d+)", text)
    if m:
        out.update(epochs_applied=int(m.group(2)), epochs_partial=int(m.group(3)), epochs_skipped=int(m.group(4)))
    for k in ("epoch_disagreements", "records_contradicted", "ranges_gated", "late_messages", "clock_disagreements",
              "odometer", "odometry_from_autopilot", "imu_rate_changes"):
        for mm in re.finditer(r"(%s): (\d+)" % k, text):
            out[mm.group(1)] = int(mm.group(2))
    m = re.search(r"vehicle_lost (\d+)", text)
    if m:
        out["vehicle_lost"] = int(m.group(1))
    m = re.search(r"origin (given|the autopilot)[^\n]*", text)
    if m:
        out["origin"] = m.group(0)[:160]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--px4", required=True, help="PX4's SIH SITL binary (build/px4_sitl_sih/bin/px4)")
    ap.add_argument("--cooploc", default=None, help="the cooploc binary (default: target/release/cooploc)")
    ap.add_argument("--setup", choices=["nognss", "gnss-lost"], required=True)
    ap.add_argument("--method", choices=["dcl", "dr", "alone"], required=True)
    ap.add_argument("--origin", choices=["driver", "node"], default="driver",
                    help="who gives EKF2 the team's origin: the driver before any odometry (default), or the node's own offer")
    ap.add_argument("--px4-timesync", choices=["pass", "drop"], default="pass",
                    help="PX4's own TIMESYNC requests to the node: passed (default; the node answers in PX4's boot clock) "
                         "or withheld (the old workaround, from before the node did)")
    ap.add_argument("--odometry-frame", choices=["as-sent", "ned"], default="as-sent",
                    help="the node's ODOMETRY frame_id on its way to PX4: as the node sends it (default; LOCAL_NED per the "
                         "profile), or rewritten LOCAL_FRD -> LOCAL_NED (the old workaround)")
    ap.add_argument("--sim-speed", type=float, default=1.008,
                    help="PX4_SIM_SPEED_FACTOR: SIH's lockstep sleeps a little long each 4 ms step and runs ~0.8 %% slow "
                         "on a 1.0; a slow simulated clock drifts from the companion's (see the docstring)")
    ap.add_argument("--ekf2-bias", choices=["off", "on"], default="off",
                    help="dcl, dr: EKF2's IMU bias estimation (EKF2_IMU_CTRL 7) or none (4, the default; see params_for)")
    ap.add_argument("--profile", default=None, help="the nodes' vehicle profile (default: sitl/vehicles/px4-sih-rover.toml)")
    ap.add_argument("--out", default=None, help="run folder (default: a new one under /tmp)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the range and odometry noise")
    ap.add_argument("--json", default=None, help="write the result here too")
    ap.add_argument("--timeout-s", type=float, default=420.0, help="give up on the mission after this long")
    args = ap.parse_args()
    global SETUP
    SETUP = args.setup
    # Ctrl-C and a plain kill end the run cleanly (a background job starts with SIGINT ignored)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    px4 = os.path.abspath(args.px4)
    etc = os.path.join(os.path.dirname(os.path.dirname(px4)), "etc")
    if not os.path.isfile(px4) or not os.path.isdir(etc):
        sys.exit("error: need the px4 binary (%s) and its etc/ (%s)" % (px4, etc))
    cooploc = os.path.abspath(args.cooploc or os.path.join(root, "target", "release", "cooploc"))
    profile = os.path.abspath(args.profile or os.path.join(root, "sitl", "vehicles", "px4-sih-rover.toml"))
    out = os.path.abspath(args.out or "/tmp/real-px4-%s-%s-%d" % (args.setup, args.method, os.getpid()))
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    log = open(os.path.join(out, "driver.log"), "w")
    rng = random.Random(args.seed)
    procs = []
    nodes_started = []
    relays = []
    rovers = []
    result = None

    def spawn(cmd, cwd, name, env=None):
        f = open(os.path.join(out, name), "w")
        p = subprocess.Popen(cmd, cwd=cwd, stdout=f, stderr=subprocess.STDOUT, env=env)
        procs.append(p)
        return p

    try:
        key = os.path.join(out, "team.key")
        with open(key, "w") as f:
            f.write("%064x\n" % random.Random(args.seed + 1000).getrandbits(256))
        coop_ports = [free_udp_port() for _ in ROVERS]
        range_ports = [free_udp_port() for _ in ROVERS]
        node_ports = [free_udp_port() for _ in ROVERS]
        for i, r in enumerate(ROVERS):
            d = os.path.join(out, "r%d" % (i + 1))
            os.makedirs(os.path.join(d, "px4"))
            env = dict(os.environ, PX4_SYS_AUTOSTART="10045", PX4_SIMULATOR="sihsim", PX4_SIM_MODEL="sihsim_rover_ackermann")
            lat, lon = ned_to_geo(ORIGIN, *r["start"])
            if args.sim_speed != 1.0:
                env["PX4_SIM_SPEED_FACTOR"] = "%g" % args.sim_speed
            env.update(PX4_HOME_LAT="%.8f" % lat, PX4_HOME_LON="%.8f" % lon, PX4_HOME_ALT="%.1f" % ORIGIN[2],
                       PX4_HOME_YAW="%.4f" % math.radians(r["heading"]))
            for k, v in params_for(i, args.setup, args.method, args.ekf2_bias == "on").items():
                env["PX4_PARAM_" + k] = str(v)
            spawn([px4, "-i", str(i), "-d", "-w", os.path.join(d, "px4"), etc], os.path.join(d, "px4"), "px4_%d.out" % (i + 1), env)
        time.sleep(2.0)
        rovers = [Rover(i, log, random.Random(args.seed * 100 + i)) for i in range(len(ROVERS))]
        for rv in rovers:
            rv.say("connected")
        if args.setup == "nognss" and (args.origin == "driver" or args.method == "alone"):
            # the team's origin first, before any odometry reaches EKF2
            until(rovers, lambda rv: rv.origin is not None,
                  lambda rv, _: (rv.set_origin(), rv.cmd(512, 49)), 60, "the origin", every_s=1.0)
        if args.method != "alone":
            for i, r in enumerate(ROVERS):
                d = os.path.join(out, "r%d" % (i + 1))
                relay = Relay(i, node_ports[i], args.px4_timesync == "drop", args.odometry_frame == "ned")
                relays.append(relay)
                rovers[i].odom_sink = relay.inject
                peers = ", ".join('"127.0.0.1:%d"' % p for j, p in enumerate(coop_ports) if j != i)
                with open(os.path.join(d, "node.toml"), "w") as f:
                    f.write('id = %d\nvehicle = "udpin:127.0.0.1:%d"\nvehicle_config = "%s"\nteam = [1, 2, 3]\n'
                            'method = "%s"\ncoop_bind = "127.0.0.1:%d"\npeer = [%s]\nteam_key = "%s"\n'
                            'ranges = "udpin:127.0.0.1:%d"\nrange_grace_ms = 300\n'
                            'log = "node.mcap"\nidle_exit_s = 3.0\n'
                            % (i + 1, node_ports[i], profile, args.method, coop_ports[i], peers, key, range_ports[i]))
                    if args.setup == "nognss":
                        # a known start pose (surveyed, as the paper's platforms start)
                        f.write("init_ned = [%.3f, %.3f, 0.0]\ninit_rpy_deg = [0.0, 0.0, %.1f]\n" % (r["start"][0], r["start"][1], r["heading"]))
                    else:
                        # the hand-over start: from PX4's estimate when its GNSS fix goes (PX4 has no EKF
                        # source sets: EKF2 takes the node's ODOMETRY as soon as it comes)
                        f.write("init_from_autopilot = true\n")
                nodes_started.append(spawn([cooploc, "node", "--config", "node.toml"], d, "node%d.out" % (i + 1)))
        else:
            for rv in rovers:
                rv.odom_sink = lambda data, rv=rv: rv.conn.write(data)

        # wait for the origin and a global position
        def ask(rv, waited):
            rv.cmd(512, 49)
            if args.method == "alone" and args.setup == "nognss" and waited > 3:
                # PX4 alone has no heading source (no compass, no GNSS, a velocity-only odometry): EKF2
                # never declares its yaw aligned, gives no global position and refuses to arm ("no
                # heading reference"). Its surveyed start heading, as the nodes get theirs
                # (MAV_CMD_EXTERNAL_ATTITUDE_ESTIMATE, 620: heading deg, accuracy 2 deg = the node's yaw_sigma_deg)
                rv.cmd(620, 0, 0, ROVERS[rv.i]["heading"], 0, 0, 0, 2.0)
                # and its surveyed start position: EKF2 keeps a global position of its own, which an
                # origin set before any position aiding leaves near latitude 0, longitude 0 (EKF2
                # alone on a velocity gets no position reset; MAV_CMD_EXTERNAL_POSITION_ESTIMATE,
                # 43003, as COMMAND_INT: accuracy 0.5 m = the node's position_sigma_m)
                lat, lon = ned_to_geo(ORIGIN, *ROVERS[rv.i]["start"])
                rv.conn.mav.command_int_send(rv.sysid, 1, 0, 43003, 0, 0, 0, 0, 0.5, 0,
                                             int(round(lat * 1e7)), int(round(lon * 1e7)), ORIGIN[2])
        until(rovers, lambda rv: rv.origin is not None and len(rv.ekf) > 0 and math.dist(rv.ekf[-1][1:], ROVERS[rv.i]["start"]) < 5.0,
              ask, 90, "origin and a global position at the start", every_s=2.0)
        for rv in rovers:
            rv.say("origin %s, EKF2 at %s" % (rv.origin, rv.ekf[-1][1:]))
        time.sleep(3.0)
        for i, rv in enumerate(rovers):
            rv.upload_mission(mission_for(i))
            rv.say("mission of %d waypoints" % len(mission_for(i)))
        # AUTO.MISSION, then arm (PX4 refuses to arm in Manual without RC)
        until(rovers, lambda rv: rv.mode is not None and (rv.mode >> 16) & 0xFF == PX4_AUTO and (rv.mode >> 24) == PX4_AUTO_MISSION,
              lambda rv, _: rv.cmd(176, 1, PX4_AUTO, PX4_AUTO_MISSION), 60, "AUTO.MISSION")
        until(rovers, lambda rv: rv.armed, lambda rv, _: rv.cmd(400, 1), 60, "armed", every_s=2.0)
        start = time.time()
        start_sim = [rv.truth[-1][0] for rv in rovers]
        for rv in rovers:
            rv.say("armed, AUTO.MISSION")

        # the range emulator, on the team's 1 s grid of Unix time, until every mission is over
        dev = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        epochs = 0
        gnss_lost_at = start + GNSS_LOSS_S if args.setup == "gnss-lost" else start
        gnss_off = args.setup == "nognss"
        lost_sim = list(start_sim)
        done_at = None
        next_epoch = math.floor(time.time()) + 1
        n_items = len(mission_for(0))
        while True:
            now = time.time()
            if not gnss_off and now >= gnss_lost_at:
                for k, rv in enumerate(rovers):
                    rv.conn.mav.param_set_send(rv.sysid, 1, b"SIM_GPS_USED", 0.0, 6)  # no satellites: no fix
                    rv.cmd(43006, 6, 0, 0)  # EKF2: magnetometer fusion off
                    lost_sim[k] = rv.truth[-1][0]
                    rv.say("GNSS lost (SIM_GPS_USED 0), compass fusion off")
                gnss_off = True
            if now >= next_epoch + 0.06:
                t = next_epoch
                next_epoch += 1
                pos = [rv.truth_at(t, wall=True) for rv in rovers]
                if args.method != "alone" and all(p is not None for p in pos):
                    for i in range(len(rovers)):
                        for j in range(i + 1, len(rovers)):
                            d = math.hypot(pos[i][0] - pos[j][0], pos[i][1] - pos[j][1]) + rng.gauss(0.0, RANGE_SIGMA_M)
                            line = "RANGE,%d,%d,%.3f,%.2f,%d\n" % (t, j + 1, d, RANGE_SIGMA_M, t * 1_000_000)
                            dev.sendto(line.encode(), ("127.0.0.1", range_ports[i]))
                    epochs += 1
            finished = [(not rv.armed) or rv.mission_state == 5
                        or (rv.mode is not None and (rv.mode >> 24) == PX4_AUTO_LOITER and now - start > 20)
                        or (rv.mission_seq == n_items - 1 and rv.truth_at(rv.truth[-1][0]) is not None
                            and math.dist(rv.truth[-1][1:], ROVERS[rv.i]["start"]) < 2.5 and now - start > 60)
                        for rv in rovers]
            if all(finished) and done_at is None:
                done_at = now
            if done_at is not None and now > done_at + 2.0:
                break
            if now - start > args.timeout_s:
                print("timeout: the missions did not all end", flush=True)
                break
            time.sleep(0.01)
        result = {"setup": args.setup, "method": args.method, "origin": args.origin, "px4_timesync": args.px4_timesync,
                  "odometry_frame": args.odometry_frame, "sim_speed_factor": args.sim_speed, "ekf2_bias": args.ekf2_bias,
                  "epochs_ranged": epochs, "rovers": []}
        for k, rv in enumerate(rovers):
            with rv.lock:
                ekf = [x for x in rv.ekf if x[0] >= lost_sim[k]]
                truth = [x for x in rv.truth if x[0] >= lost_sim[k]]
            errs = []
            for (t, n, e) in ekf:
                p = rv.truth_at(t)
                if p is not None:
                    errs.append(math.hypot(n - p[0], e - p[1]))
            path = sum(math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in zip(truth, truth[1:]))
            rms = math.sqrt(sum(x * x for x in errs) / len(errs)) if errs else float("nan")
            with rv.lock:
                k0 = bisect.bisect_left(rv.truth, (lost_sim[k],))
                (s0, s1), (w0, w1) = (rv.truth[k0][0], rv.truth[-1][0]), (rv.truth_wall[k0][0], rv.truth_wall[-1][0])
            rtf = (s1 - s0) / (w1 - w0) if w1 > w0 else float("nan")  # PX4's simulated time against real time
            node_errs = []
            if k < len(relays):
                for (t, n, e) in [x for x in relays[k].node_est if x[0] >= lost_sim[k]]:
                    p = rv.truth_at(t)
                    if p is not None:
                        node_errs.append(math.hypot(n - p[0], e - p[1]))
            node_rms = math.sqrt(sum(x * x for x in node_errs) / len(node_errs)) if node_errs else float("nan")
            with open(os.path.join(out, "trace%d.json" % rv.sysid), "w") as f:
                json.dump({"truth": truth, "ekf": ekf, "node": relays[k].node_est if k < len(relays) else []}, f)
            flags = sorted(rv.est_flags_seen)
            result["rovers"].append({"sysid": rv.sysid, "path_m": path, "rms_m": rms, "final_m": errs[-1] if errs else float("nan"),
                                     "max_m": max(errs) if errs else float("nan"), "samples": len(errs),
                                     "node_own_rms_m": node_rms, "node_own_final_m": node_errs[-1] if node_errs else float("nan"),
                                     "sim_rate": rtf, "start_s": lost_sim[k],
                                     "estimator_flags": ["0x%04x" % f for f in flags], "odometry_sent": rv.odom_sent,
                                     "mission_state": rv.mission_state, "texts": rv.texts[-20:]})
            rv.say("%s %s: %.0f m without GNSS, EKF2 error RMS %.2f m, final %.2f m (%d samples); node's own RMS %.2f m; sim %.3fx real time"
                   % (args.setup, args.method, path, rms, result["rovers"][-1]["final_m"], len(errs), node_rms, rtf))
        all_errs = [r["rms_m"] for r in result["rovers"]]
        result["team_rms_m"] = math.sqrt(sum(x * x for x in all_errs) / len(all_errs))
        print("team RMS %.2f m (%s, %s)" % (result["team_rms_m"], args.setup, args.method), flush=True)
        for rv in rovers:
            rv.cmd(400, 0, 21196)
        for r in relays:
            result.setdefault("relay", []).append({"to_node": r.to_node, "to_px4": r.to_px4, "px4_timesync_dropped": r.dropped,
                                                   "odometry_frame_rewritten": r.rewritten})
    finally:
        # the nodes first, by Ctrl-C: each says its summary in its node.out
        stop_all(procs, nodes_started)
        for rv in rovers:
            rv.stop = True
        for r in relays:
            r.stop = True
        log.close()
    if result is None:
        sys.exit(1)
    # whether EKF2 fused external vision (its own log: PX4's console does not say), and the nodes' figures
    for k in range(len(ROVERS)):
        fusion = ulog_fusion(os.path.join(out, "r%d" % (k + 1), "px4"), result["rovers"][k]["start_s"])
        result["rovers"][k]["ekf2_fusion"] = fusion
        if args.method != "alone":
            result["rovers"][k]["node"] = node_summary(os.path.join(out, "node%d.out" % (k + 1)))
        print("rover %d EKF2 vision: %s" % (k + 1, fusion), flush=True)
        if args.method != "alone":
            print("rover %d node: %s" % (k + 1, result["rovers"][k]["node"]), flush=True)
    for path in [os.path.join(out, "result.json")] + ([args.json] if args.json else []):
        with open(path, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
