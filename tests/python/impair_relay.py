"""An impairment relay for the network-namespace test (tests/netns.rs): the kernel here has no
netem, so delay, jitter (hence reordering) and loss come from this relay, which runs inside the
test's topology (the hub namespace) and sits between every pair of nodes.

For each node i the relay listens on RELAY_IP:BASE+i. A datagram that node j sends there is meant
for node i: the relay drops it with probability LOSS, else holds it DELAY +- JITTER ms and sends it
to node i from its socket BASE+j, so that node i sees (and learns) the relay's BASE+j as node j's
address and answers through the relay too. Datagrams from unknown addresses are dropped.

Usage: impair_relay.py RELAY_IP BASE LOSS DELAY_MS JITTER_MS SEED STATS_FILE ID=IP:PORT ...
Statistics (forwarded, lost, unknown, bytes per pair) are written to STATS_FILE every second and
when the process gets SIGTERM.
"""

import heapq
import json
import random
import selectors
import signal
import socket
import sys
import time


def main():
    relay_ip, base, loss, delay_ms, jitter_ms, seed, stats_path = sys.argv[1:8]
    base, loss, delay, jitter = int(base), float(loss), float(delay_ms) / 1e3, float(jitter_ms) / 1e3
    nodes = {}
    for spec in sys.argv[8:]:
        ident, addr = spec.split("=")
        host, port = addr.rsplit(":", 1)
        nodes[int(ident)] = (host, int(port))
    by_addr = {addr: ident for ident, addr in nodes.items()}
    rng = random.Random(int(seed))
    sel = selectors.DefaultSelector()
    socks = {}
    for ident in nodes:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        s.bind((relay_ip, base + ident))
        s.setblocking(False)
        socks[ident] = s
        sel.register(s, selectors.EVENT_READ, ident)
    stats = {"forwarded": 0, "lost": 0, "unknown": 0, "bytes": {}}
    queue = []
    order = 0
    running = [True]

    def stop(*_):
        running[0] = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)

    def dump():
        with open(stats_path + ".tmp", "w") as f:
            json.dump(stats, f)
        import os

        os.replace(stats_path + ".tmp", stats_path)

    print("relay ready", flush=True)
    last_dump = time.monotonic()
    while running[0]:
        now = time.monotonic()
        timeout = 0.2 if not queue else max(0.0, min(0.2, queue[0][0] - now))
        for key, _ in sel.select(timeout):
            dest = key.data
            s = key.fileobj
            while True:
                try:
                    data, src = s.recvfrom(65536)
                except BlockingIOError:
                    break
                source = by_addr.get(src)
                if source is None or source == dest:
                    stats["unknown"] += 1
                    continue
                pair = f"{source}->{dest}"
                stats["bytes"][pair] = stats["bytes"].get(pair, 0) + len(data)
                if rng.random() < loss:
                    stats["lost"] += 1
                    continue
                at = time.monotonic() + max(0.0, delay + rng.uniform(-jitter, jitter))
                order += 1
                heapq.heappush(queue, (at, order, source, dest, data))
        now = time.monotonic()
        while queue and queue[0][0] <= now:
            _, _, source, dest, data = heapq.heappop(queue)
            try:
                socks[source].sendto(data, nodes[dest])
                stats["forwarded"] += 1
            except OSError:
                stats["lost"] += 1
        if now - last_dump > 1.0:
            dump()
            last_dump = now
    dump()


if __name__ == "__main__":
    main()
