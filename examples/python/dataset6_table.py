"""The data set 6 table of `cooploc dataset mrclam`, from Python (issue 35).

    python examples/python/dataset6_table.py MRCLAM_Dataset6

Every method in every regime on a UTIAS MRCLAM data set folder (unpacked; see docs/real-data.md),
printed as the CLI prints the first columns of its table: the same figures to the last digit
(docs/python.md). Needs the cooploc package (bash tests/run-all.sh installs it into .venv).
"""

import sys
import time

import cooploc

METHODS = ["dr", "naive", "dcl", "ci", "centralized"]
REGIMES = ["no-landmarks", "map-blind", "full-map"]


def main(argv):
    if len(argv) != 2:
        sys.exit(__doc__)
    started = time.monotonic()
    rows = cooploc.mrclam(argv[1], METHODS, REGIMES)
    print("%-13s%-12s%7s%9s%9s%8s" % ("regime", "method", "pos m", "hdg deg", "NEES", "in 95%"))
    for o in rows:
        print("%-13s%-12s%7.3f%9.2f%9.2f%7.1f%%" % (o["regime"], o["method"], o["pos_rmse_m"], o["heading_rmse_deg"],
                                                 o["avg_nees"], 100.0 * o["in_bound_share"]))
    print("%d runs in %.2f s" % (len(rows), time.monotonic() - started))


if __name__ == "__main__":
    main(sys.argv)
