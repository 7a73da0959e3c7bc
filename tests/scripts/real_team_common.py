"""What the real-firmware team drivers (real_ardupilot_team.py, real_px4_team.py) share: the
flat-Earth conversion about the team's origin, a free UDP port, the wait-and-retry loop, and
stopping what they started."""

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time

M_PER_DEG_LAT = math.pi / 180.0 * 6378137.0


def ned_to_geo(origin, n, e):
    """(lat, lon) in degrees of the point (n, e) m from `origin` (lat, lon, ...)."""
    lat = origin[0] + n / M_PER_DEG_LAT
    lon = origin[1] + e / (M_PER_DEG_LAT * math.cos(math.radians(origin[0])))
    return lat, lon


def geo_to_ned(origin, lat, lon):
    """(n, e) in m of (lat, lon) about `origin`."""
    return ((lat - origin[0]) * M_PER_DEG_LAT, (lon - origin[1]) * M_PER_DEG_LAT * math.cos(math.radians(origin[0])))


def free_udp_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def until(rovers, done, act, timeout_s, what, every_s=1.0):
    """Calls act(rover, elapsed_s) on each rover not done(rover), every every_s, until all are
    done; an error naming `what` after timeout_s."""
    t0 = time.time()
    while not all(done(rv) for rv in rovers):
        if time.time() - t0 > timeout_s:
            raise RuntimeError("%s: not after %d s" % (what, timeout_s))
        for rv in rovers:
            if not done(rv):
                act(rv, time.time() - t0)
        time.sleep(every_s)


def stop_all(procs, nodes):
    """Stops every process of `procs`, newest first: the nodes (in `nodes`) by Ctrl-C, so that
    each writes its summary, waited for up to 10 s; the others by SIGTERM; any still running
    after 10 s killed."""
    for p in procs[::-1]:
        if p.poll() is None:
            p.send_signal(signal.SIGINT if p in nodes else signal.SIGTERM)
            if p in nodes:
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()


METHODS = ("dcl", "dr", "alone")


def load_runs(out, setup):
    """The JSON results of `setup` in folder `out`, by method (those present)."""
    runs = {}
    for m in METHODS:
        p = os.path.join(out, "%s-%s.json" % (setup, m))
        if os.path.exists(p):
            with open(p) as f:
                runs[m] = json.load(f)
    return runs


def print_table(out, setups, alone):
    """The table (docs/real-autopilot.md) of both drivers' runs in `out`: per set-up and rover the path without
    GNSS and the autopilot EKF's error (RMS / final) for each method, then the team RMS; `alone`
    names the autopilot on its own (ArduPilot, PX4)."""
    print("\n| set-up | rover | path without GNSS (m) | dcl RMS / final (m) | dr RMS / final (m) | %s alone RMS / final (m) |" % alone)
    print("|---|---|---|---|---|---|")
    for s in setups:
        runs = load_runs(out, s)
        if not runs:
            continue
        n = len(next(iter(runs.values()))["rovers"])
        for k in range(n):
            cells = []
            for m in METHODS:
                r = runs.get(m)
                cells.append("%.2f / %.2f" % (r["rovers"][k]["rms_m"], r["rovers"][k]["final_m"]) if r else "-")
            path = "/".join("%.0f" % runs[m]["rovers"][k]["path_m"] for m in METHODS if m in runs)
            print("| %s | %d | %s | %s |" % (s, k + 1, path, " | ".join(cells)))
        print("| %s | team RMS | | %s |" % (s, " | ".join("%.2f" % runs[m]["team_rms_m"] if m in runs else "-" for m in METHODS)))


if __name__ == "__main__":
    # python real_team_common.py table OUT ALONE SETUP... (the drivers' .sh scripts)
    if len(sys.argv) < 4 or sys.argv[1] != "table":
        sys.exit("usage: real_team_common.py table OUT ALONE SETUP...")
    print_table(sys.argv[2], sys.argv[4:], sys.argv[3])

