"""cooploc for Python: the cooploc Rust library's functions, for ground stations, notebooks and
researchers' scripts (issue 35).

Everything here calls the library's own code (the same the node, the ground station and the logs
use) through the native submodule ``cooploc._native``; nothing is re-implemented in Python. Bad
input raises ``ValueError`` or ``TypeError``, never crashes the interpreter.

So far (the first step of issue 35):

- :func:`ellipse95`, :func:`position_nees`: the 95 % ellipse and the position NEES
  (``estimation::consistency``);
- :func:`geo_to_ned`, :func:`ned_to_geo`: the flat-Earth conversion every part of cooploc uses
  (``geodesy``);
- :func:`frames`: the MAVLink frames in a datagram or a stream's bytes (``protocol::framing``);
- :func:`estimate_from_frame`: a COOPLOC_ESTIMATE frame, checked as the ground station checks it
  (``protocol::wire``); :func:`check_frame`: any cooploc message's frame, checked as the node and
  the ground station check it;
- :func:`read_log`: a cooploc MCAP log (metadata, topics, messages; a cut or damaged log is read
  up to the damage), as ``cooploc replay`` reads it (``recording::read_log``);
- :func:`log_series`: each vehicle's estimates, truth and cooperative updates in a log as numpy
  arrays (``recording::series``);
- :func:`replay`: every node of a log replayed, its recorded and replayed estimates as numpy
  arrays (``replay::replay_nodes``); :func:`compare_methods`: any method run offline on a log's
  inputs, its errors at every truth sample as numpy arrays (``replay::compare_methods``);
- :func:`mrclam`: every method in every regime on a UTIAS MRCLAM data set, the figures of
  ``cooploc dataset mrclam``'s table as dicts (``dataset::run::run``);
- :func:`experiment`: the Monte Carlo of ``cooploc experiment``, its summary and RMS curves
  (``experiment::run_experiment``, ``experiment::report``);
- :class:`PlanarTeam`: a team of planar robots under one method (``dr``, ``naive``, ``dcl``, ``ci``,
  ``centralized``), stepped from numpy arrays of wheel speeds, yaw rates and ranges
  (``estimation::team``, ``estimation::planar``);
- :class:`InsTeam`, :func:`scenario_run`: a team of INS vehicles (the paper's model) under one
  method, stepped from numpy arrays of IMU samples, odometer speeds and 3-D ranges, and one run of
  a simulated scenario as such arrays (``estimation::team``, ``estimation::nav``,
  ``sitl::World::run_inputs``): stepped over a run it ends where ``cooploc experiment``'s filter
  does, to the last bit;
- :class:`EpochTally`: disagreements and heals from COOPLOC_EPOCH reports, the rules of every
  cooploc display (``view::health``);
- :class:`RateWindow`: amounts a second over a sliding window, bounded at any rate (the ground
  station's, ``gcs::link``);
- :class:`TruthTrack`, :func:`sim_state_from_frame`: a simulated vehicle's truth (SIM_STATE,
  checked and converted) and its estimates' errors and NEES against it, the ground station's rules
  (``gcs::truth``);
- :class:`SequenceTracker`: frames lost, late and repeated by their MAVLink sequence numbers, the
  one rule of the node, the ground station and the MAVProxy module (``protocol::sequence``);
- :data:`PALETTE`: the colour of each platform on every cooploc display (``view::PALETTE``).

The MAVProxy module is :mod:`cooploc.mavproxy`; MAVProxy's ``module load cooploc`` finds this
package (its loader tries ``MAVProxy.modules.mavproxy_cooploc``, then ``cooploc``) and calls
:func:`init`.
"""

import json as _json

from cooploc._native import (
    CHI2_2DOF_95,
    EARTH_RADIUS_M,
    MAX_REORDER,
    PALETTE,
    EpochTally,
    InsTeam,
    PlanarTeam,
    RateWindow,
    SequenceTracker,
    TruthTrack,
    __version__,
    check_frame,
    compare_methods,
    ellipse95,
    estimate_from_frame,
    experiment_json,
    frames,
    geo_to_ned,
    log_series,
    mrclam,
    ned_to_geo,
    position_nees,
    read_log,
    replay,
    scenario_run,
    sim_state_from_frame,
)


def experiment(scenario, runs, methods, schedules=None, seed=1):
    """The Monte Carlo of ``cooploc experiment`` on ``scenario`` (a scenario file, e.g.
    ``sitl/scenarios/paper.toml``): ``runs`` runs of ``methods`` (short names: ``dr``, ``naive``,
    ``dcl``, ``ci``, ``centralized``) over ``schedules`` (all of the scenario's when None). One dict
    per schedule: the summary ``cooploc experiment`` prints (``methods``: per method and platform
    the final errors and NEES; ``reductions``; ``nees_band``) and ``curves``: per method and
    platform, ``t_s``, ``pos_rms_m`` and ``heading_rms_deg`` over the runs (the paper's figures).
    ``ValueError`` for a bad scenario, name or count."""
    return _json.loads(experiment_json(str(scenario), runs, list(methods), schedules, seed))


def init(mpstate):
    """MAVProxy's entry point (``module load cooploc``): the module of :mod:`cooploc.mavproxy`."""
    from cooploc import mavproxy

    return mavproxy.init(mpstate)


__all__ = [
    "CHI2_2DOF_95",
    "EARTH_RADIUS_M",
    "MAX_REORDER",
    "EpochTally",
    "InsTeam",
    "PlanarTeam",
    "RateWindow",
    "PALETTE",
    "SequenceTracker",
    "TruthTrack",
    "__version__",
    "check_frame",
    "compare_methods",
    "ellipse95",
    "estimate_from_frame",
    "experiment",
    "frames",
    "geo_to_ned",
    "init",
    "log_series",
    "mrclam",
    "ned_to_geo",
    "position_nees",
    "read_log",
    "replay",
    "scenario_run",
    "sim_state_from_frame",
]
