#!/usr/bin/env python3
"""A vehicle built independently with pymavlink, in the ways real autopilots send their streams.

Usage: autopilot_vehicle.py KIND
KIND: ardupilot  RAW_IMU (int16 mG / mrad/s, the latest sample, time_usec since boot) at 40 Hz,
                 SCALED_IMU2 and HIGHRES_IMU ids 0 and 1 (not the profile's IMU), WHEEL_DISTANCE
                 (two wheels, cumulative, reset to zero half way) at 20 Hz, SYSTEM_TIME at 1 Hz
                 (the team's Unix clock); refuses the WHEEL_DISTANCE rate request.
      px4        HIGHRES_IMU (float, averaged) at 200 Hz with two IMU ids: id 0 turns at
                 0.2 rad/s (a wrong IMU: the profile asks for id 1), id 1 is right; ODOMETRY
                 from PX4's own EKF (estimator AUTOPILOT, 5 m/s: must be refused) and from a
                 wheel-odometry source (estimator NAIVE); time since boot; SYSTEM_TIME.
      scaled2    SCALED_IMU2 (time_boot_ms) at 50 Hz starting 5 s before time_boot_ms wraps
                 (49.7 days of uptime), WHEEL_DISTANCE, SYSTEM_TIME.
      robot      a wheeled robot without IMU: WHEEL_DISTANCE of its left and right wheels (0.5 m
                 apart) at 20 Hz over a quarter circle to the right (20 m of arc, reset to zero
                 half way), SYSTEM_TIME at 1 Hz.
      robot-gyro the same quarter circle, but the wheels turn alike (they give the speed) and a
                 yaw-rate gyro (SCALED_IMU2 z, mrad/s, 40 Hz) gives the turn.
      origin     as ardupilot, with GPS_GLOBAL_ORIGIN at 1 Hz (the EKF origin, for a node whose
                 profile gives none).
      signed     as ardupilot with MAVLink 2 signing on the port (key: SHA-256 of "the vehicle's
                 key"): every frame signed, the node's frames checked; and a forger's unsigned
                 RAW_IMU (5 g north) after every tenth sample, which the node must refuse.
The vehicle drives straight north at 2 m/s on level ground for 10 s (at 10x real time), the node
starting at rest: only a working odometer gets it to 20 m. Binds 127.0.0.1:0, prints
"port N", waits for the node's HEARTBEAT, answers its SET_MESSAGE_INTERVAL requests with
COMMAND_ACK, and checks the ODOMETRY the node sends back (pose frame LOCAL_FRD, PX4 LOCAL_NED). Prints one JSON line at the end.
"""
import hashlib
import json
import math
import socket
import sys
import time

from pymavlink.dialects.v20 import common as mav

G = 9.80665
EARTH_RATE = 7.292115e-5
UNIX0_US = 1_795_000_000_000_000  # Unix time of the autopilot's boot, us (2026-11)
SPEED = 2.0
DURATION_S = 10.0
TRACK = 0.5  # the robot's wheels apart, m
SYSID = 1


def main():
    kind = sys.argv[1]
    signed = kind == "signed"
    if signed:
        kind = "ardupilot"
    lat = {"ardupilot": -35.363262, "origin": -35.363262, "scaled2": -35.363262, "px4": 47.397742, "robot": -35.363262,
           "robot-gyro": -35.363262}[kind]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    print("port %d" % sock.getsockname()[1], flush=True)
    sock.settimeout(20.0)
    _, node = sock.recvfrom(4096)  # the node's first HEARTBEAT
    sock.setblocking(False)

    class Out:
        def write(self, b):
            sock.sendto(b, node)

    m = mav.MAVLink(Out(), srcSystem=SYSID, srcComponent=1)
    m_odo = mav.MAVLink(Out(), srcSystem=SYSID, srcComponent=197)  # a wheel-odometry component
    rx = mav.MAVLink(None)
    rx.robust_parsing = True
    forger = mav.MAVLink(Out(), srcSystem=SYSID, srcComponent=1)
    if signed:
        key = hashlib.sha256(b"the vehicle's key").digest()
        now = int((time.time() - 1420070400) * 100000)
        for link_id, obj in enumerate([m, m_odo, rx]):
            obj.signing.secret_key = key
            obj.signing.link_id = link_id
            obj.signing.timestamp = now
            obj.signing.sign_outgoing = obj is not rx
    report = {"kind": kind, "requests": [], "odometry": 0, "bad_frames": [], "odometry_times": [], "odometry_n": []}

    def receive():
        while True:
            try:
                data, _ = sock.recvfrom(65536)
            except BlockingIOError:
                return
            for msg in rx.parse_buffer(data) or []:
                t = msg.get_type()
                if t == "COMMAND_LONG" and msg.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
                    asked = int(msg.param1)
                    refuse = kind in ("ardupilot", "origin") and asked == 9000
                    report["requests"].append([asked, msg.param2])
                    result = mav.MAV_RESULT_DENIED if refuse else mav.MAV_RESULT_ACCEPTED
                    m.command_ack_send(msg.command, result)
                elif t == "ODOMETRY":
                    report["odometry"] += 1
                    # ArduPilot takes a LOCAL_FRD pose only; PX4's EKF2 has no heading from one
                    # (measured on its SIH): its profile names the same axes LOCAL_NED
                    pose = mav.MAV_FRAME_LOCAL_NED if kind == "px4" else mav.MAV_FRAME_LOCAL_FRD
                    if msg.frame_id != pose or msg.child_frame_id != mav.MAV_FRAME_BODY_FRD:
                        report["bad_frames"].append([msg.frame_id, msg.child_frame_id])
                    report["odometry_times"].append(msg.time_usec)
                    report["odometry_n"].append(msg.x)

    # (vehicle time since boot, us) of the first sample, and the sample period per stream
    boot0_us = {"ardupilot": 100_000_000, "origin": 100_000_000, "px4": 100_000_000, "scaled2": (2**32 - 5000) * 1000,
                "robot": 100_000_000, "robot-gyro": 100_000_000}[kind]
    imu_period = {"ardupilot": 25_000, "origin": 25_000, "px4": 5_000, "scaled2": 20_000, "robot": 25_000, "robot-gyro": 25_000}[kind]
    wheel_period = 50_000
    w_earth = (EARTH_RATE * math.cos(math.radians(lat)), 0.0, -EARTH_RATE * math.sin(math.radians(lat)))
    t_us = 0
    next_wheel = 0
    next_time = 0
    reset_done = False
    wheel_base = 0.0
    wall0 = time.monotonic()
    while t_us <= DURATION_S * 1e6:
        boot_us = boot0_us + t_us
        boot_ms = (boot_us // 1000) % 2**32
        if t_us >= next_time:
            m.system_time_send(UNIX0_US + boot_us, boot_ms)
            if kind == "origin":
                m.gps_global_origin_send(round(lat * 1e7), round(149.165237 * 1e7), 584_000, boot_us)
            next_time += 1_000_000
        if kind in ("ardupilot", "origin"):
            m.raw_imu_send(boot_us, 0, 0, -1000, round(w_earth[0] * 1e3), 0, round(w_earth[2] * 1e3), 0, 0, 0, 0)
            if signed and (t_us // imu_period) % 10 == 0:
                forger.raw_imu_send(boot_us + imu_period // 2, 5000, 0, -1000, 0, 0, 0, 0, 0, 0, 0)
            m.scaled_imu2_send(boot_ms, 300, 0, -1000, 0, 0, 200, 0, 0, 0)
            m.highres_imu_send(boot_us, 3.0, 0, -G, 0, 0, 0.2, 0, 0, 0, 0, 0, 0, 0, 0x3F, 0)
        elif kind == "robot":
            pass  # no IMU in the navigation
        elif kind == "robot-gyro":
            turn_rate = SPEED / (SPEED * DURATION_S / (math.pi / 2))
            m.scaled_imu2_send(boot_ms, 0, 0, -1000, 0, 0, round(turn_rate * 1e3), 0, 0, 0)
        elif kind == "px4":
            m.highres_imu_send(boot_us, 0, 0, -G, w_earth[0], 0, 0.2, 0, 0, 0, 0, 0, 0, 0, 0x3F, 0)
            m.highres_imu_send(boot_us, 0, 0, -G, w_earth[0], 0, w_earth[2], 0, 0, 0, 0, 0, 0, 0, 0x3F, 1)
        else:
            m.scaled_imu2_send(boot_ms, 0, 0, -1000, round(w_earth[0] * 1e3), 0, round(w_earth[2] * 1e3), 0, 0, 0)
        if t_us >= next_wheel:
            dist = SPEED * t_us * 1e-6
            if kind == "px4":
                nan = float("nan")
                cov = [nan] + [0.0] * 20
                m.odometry_send(boot_us, mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD, 0, 0, 0, [1, 0, 0, 0],
                                5.0, 0, 0, 0, 0, 0, cov, cov, 0, mav.MAV_ESTIMATOR_TYPE_AUTOPILOT)
                m_odo.odometry_send(boot_us, mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD, nan, nan, nan,
                                    [nan, 0, 0, 0], SPEED, 0, 0, nan, nan, nan, cov, cov, 0,
                                    mav.MAV_ESTIMATOR_TYPE_NAIVE)
            else:
                if not reset_done and t_us >= DURATION_S * 1e6 / 2:
                    wheel_base = dist  # the encoder counters reset to zero
                    reset_done = True
                d = dist - wheel_base
                if kind == "robot":
                    # turning right on a circle of radius R: the left wheel runs outside
                    radius = SPEED * DURATION_S / (math.pi / 2)
                    turn = dist / radius
                    left = (radius + TRACK / 2) * turn - wheel_base * (radius + TRACK / 2) / radius
                    right = (radius - TRACK / 2) * turn - wheel_base * (radius - TRACK / 2) / radius
                    m.wheel_distance_send(boot_us, 2, [left, right] + [0.0] * 14)
                else:
                    m.wheel_distance_send(boot_us, 2, [d, d] + [0.0] * 14)
            next_wheel += wheel_period
        t_us += imu_period
        receive()
        # 10x real time
        ahead = t_us * 1e-7 - (time.monotonic() - wall0)
        if ahead > 0:
            time.sleep(ahead)
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        receive()
        time.sleep(0.01)
    times = report.pop("odometry_times")
    ns = report.pop("odometry_n")
    report["odometry_first_us"] = min(times) if times else None
    report["odometry_last_us"] = max(times) if times else None
    report["odometry_distinct"] = len(set(times))
    report["odometry_last_n"] = ns[times.index(max(times))] if times else None
    report["boot0_us"] = boot0_us
    if signed:
        report["kind"] = "signed"
        report["node_frames_goodsig"] = rx.signing.goodsig_count
        report["node_frames_refused"] = rx.signing.badsig_count + rx.signing.unsigned_count + rx.signing.reject_count
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    main()
