#!/usr/bin/env python3
"""Per-node cost against team size, from criterion's medians.

Run `cargo bench --bench throughput -- team` and `cargo bench --bench estimation --
cooperative_event` first; this reads target/criterion/{team,cooperative_event}/N/new/estimates.json,
prints the README's table and writes docs/images/team-scaling.png.

team/N runs N node cores for 4 s of vehicle time (benches/throughput.rs), so one node's CPU time
per second of real-time operation is the median / (4 N): its share of one core.
"""
import json
import math
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]
CRIT = ROOT / "target" / "criterion"
SIZES = [3, 8, 16, 32, 64]
VEHICLE_SECONDS = 4.0


def median_s(group, n):
    f = CRIT / group / str(n) / "new" / "estimates.json"
    if not f.exists():
        sys.exit(f"missing {f}: run the benches first (see the docstring)")
    return json.loads(f.read_text())["median"]["point_estimate"] * 1e-9


def main():
    node = [median_s("team", n) / (VEHICLE_SECONDS * n) for n in SIZES]
    event = [median_s("cooperative_event", n) for n in SIZES]
    print("| team size | one node, CPU per second (share of a core) | of which the joint update (`cooperative_event/N`) |")
    print("|---|---|---|")
    for n, a, e in zip(SIZES, node, event):
        print(f"| {n} | {a * 1e3:.2f} ms ({a * 100:.2f} %) | {e * 1e3:.2f} ms |")
    # Growth exponents between neighbouring sizes.
    for (n0, a0), (n1, a1) in zip(zip(SIZES, node), list(zip(SIZES, node))[1:]):
        print(f"{n0} -> {n1}: node x{a1 / a0:.2f} (exponent {math.log(a1 / a0) / math.log(n1 / n0):.2f})")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    ax.loglog(SIZES, [a * 1e3 for a in node], "o-", label="one node, whole protocol (team/N)")
    ax.loglog(SIZES, [e * 1e3 for e in event], "s--", label="the joint update alone (cooperative_event/N)")
    ref = node[-1] * 1e3
    ax.loglog(SIZES, [ref * (n / SIZES[-1]) ** 3 for n in SIZES], ":", color="grey", label="N^3")
    ax.axhline(50.0, color="red", lw=0.8)
    ax.text(SIZES[0], 55.0, "5 % of a core at 1 Hz", color="red", fontsize=8)
    ax.set_xticks(SIZES)
    ax.set_xticklabels([str(n) for n in SIZES])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("team size N (each member ranging to up to 6 neighbours, 1 Hz)")
    ax.set_ylabel("CPU ms per second of operation")
    ax.set_title("Per-node cost against team size (criterion medians)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = ROOT / "docs" / "images" / "team-scaling.png"
    fig.savefig(out)
    print(f"wrote {out.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
