"""One of the paper's figures from Python (issue 35): the position error over time of dead
reckoning, collaborative localization without covariance propagation, and the decentralized
method with it, RMS over Monte Carlo runs of the paper scenario with ranging at 1 Hz
(Wang et al., section 4; `cooploc experiment` draws the same curves into experiment-out/).

    python examples/python/paper_figure.py OUT.png [RUNS]

RUNS: Monte Carlo runs (50 by default, as `cooploc experiment`). Needs the cooploc package and
matplotlib (bash tests/run-all.sh installs both into .venv).
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import cooploc  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
SCENARIO = os.path.join(ROOT, "sitl", "scenarios", "paper.toml")
METHODS = [("dr", "dead reckoning"), ("naive", "no covariance propagation"), ("dcl", "decentralized (paper)")]


def main(argv):
    if len(argv) not in (2, 3):
        sys.exit(__doc__)
    runs = int(argv[2]) if len(argv) == 3 else 50
    summary = cooploc.experiment(SCENARIO, runs, [m for m, _ in METHODS], schedules=["1hz"])[0]
    platforms = sorted({c["platform"] for c in summary["curves"]})
    fig, axes = plt.subplots(1, len(platforms), figsize=(4.5 * len(platforms), 3.6), sharey=True)
    for ax, pid in zip(axes, platforms):
        for (method, label), curve in zip(METHODS, [c for c in summary["curves"] if c["platform"] == pid]):
            ax.plot(curve["t_s"], curve["pos_rms_m"], label=label,
                    color="#" + cooploc.PALETTE[METHODS.index((method, label))])
        ax.set_title("platform %d" % pid)
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("horizontal position error, RMS over %d runs (m)" % runs)
    axes[0].legend(loc="upper left")
    fig.suptitle("Paper scenario, ranging at 1 Hz")
    fig.tight_layout()
    fig.savefig(argv[1], dpi=110)
    for m in summary["methods"]:
        finals = ", ".join("%d: %.2f m" % (p["id"], p["final_pos_err_rms_m"]) for p in m["platforms"])
        print("%-24s final position RMS %s" % (m["method"], finals))
    print("wrote %s" % argv[1])


if __name__ == "__main__":
    main(sys.argv)
