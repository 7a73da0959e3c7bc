"""MAVProxy (the pinned release from the test virtualenv) against a simulated vehicle and a node.

Usage: mavproxy_check.py VEHICLE_HOST:PORT NODE_HOST:PORT

Runs MAVProxy headless with both as masters, asks it to send SET_MESSAGE_INTERVAL (HIGHRES_IMU at
10 Hz) to system 2, stops it, and reads MAVProxy's own telemetry log (tlog) with pymavlink:
prints every (sysid:compid, type) heartbeat it received and every COMMAND_ACK.
"""
import atexit
import os
import subprocess
import sys
import shutil
import tempfile
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

vehicle, node = sys.argv[1], sys.argv[2]
home = tempfile.mkdtemp(prefix="cooploc-mavproxy-")
atexit.register(shutil.rmtree, home, ignore_errors=True)
mavproxy = os.path.join(os.path.dirname(sys.executable), "mavproxy.py")
cmd = [
    sys.executable, mavproxy,
    f"--master=udpout:{vehicle}", f"--master=udpout:{node}",
    "--daemon", "--non-interactive", f"--state-basedir={home}", "--target-system=2",
    "--source-system=255", "--logfile=" + os.path.join(home, "mav.tlog"),
    "--cmd=set heartbeat 1; long SET_MESSAGE_INTERVAL 105 100000",
]
env = dict(os.environ, HOME=home)
proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=home)
time.sleep(8)
proc.terminate()
try:
    out, _ = proc.communicate(timeout=10)
except subprocess.TimeoutExpired:
    proc.kill()
    out, _ = proc.communicate()
print(out.decode(errors="replace"), file=sys.stderr)

tlog = os.path.join(home, "mav.tlog")
if not os.path.exists(tlog):
    sys.exit(f"MAVProxy wrote no log at {tlog}")
log = mavutil.mavlink_connection(tlog)
seen = set()
while True:
    m = log.recv_match(type=["HEARTBEAT", "COMMAND_ACK"])
    if m is None:
        break
    src = f"{m.get_srcSystem()}:{m.get_srcComponent()}"
    if m.get_type() == "HEARTBEAT":
        line = f"heartbeat {src} type {m.type}"
    else:
        line = f"ack {m.command} result {m.result} from {src}"
    if line not in seen:
        seen.add(line)
        print(line)
