#!/usr/bin/env python3
"""MAVLink 2 signing with pymavlink, to check cooploc's signing against an independent one.

Usage: signing_interop.py PASSPHRASE [HEX_FRAME ...]

Prints one line `frame HEX`: a HEARTBEAT from system 7, component 191, signed by pymavlink with
the key SHA-256(PASSPHRASE) (as MAVProxy's `signing setup` derives it), link id 5, the current
time. Then, for each HEX_FRAME, `ok TYPE SYSID` if pymavlink accepts it as signed with that key
(no unsigned frame allowed), or `refused REASON`.
"""

import hashlib
import sys
import time

from pymavlink.dialects.v20 import common as mav


class Sink:
    def __init__(self):
        self.data = b""

    def write(self, b):
        self.data += b


def main():
    key = hashlib.sha256(sys.argv[1].encode()).digest()
    sink = Sink()
    tx = mav.MAVLink(sink, srcSystem=7, srcComponent=191)
    tx.signing.secret_key = key
    tx.signing.link_id = 5
    tx.signing.sign_outgoing = True
    # the signing clock: 10 us units since 2015-01-01 00:00 UTC
    tx.signing.timestamp = int((time.time() - 1420070400) * 1e5)
    tx.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
    print("frame " + sink.data.hex(), flush=True)
    for hexframe in sys.argv[2:]:
        rx = mav.MAVLink(None)
        rx.signing.secret_key = key
        rx.signing.timestamp = int((time.time() - 1420070400) * 1e5)
        try:
            msgs = rx.parse_buffer(bytes.fromhex(hexframe)) or []
            good = [m for m in msgs if m.get_type() != "BAD_DATA"]
            if good:
                m = good[0]
                print("ok %s %d" % (m.get_type(), m.get_srcSystem()), flush=True)
            else:
                print("refused bad_data", flush=True)
        except mav.MAVError as e:
            print("refused " + str(e).replace(" ", "_"), flush=True)


if __name__ == "__main__":
    main()
