"""Type stubs of cooploc._native (python/src/lib.rs)."""

from typing import Optional, Sequence, Tuple

__version__: str
CHI2_2DOF_95: float
EARTH_RADIUS_M: float
PALETTE: list[str]
MAX_REORDER: int

Origin = Tuple[float, float, float]

def ellipse95(nn: float, ne: float, ee: float) -> Optional[Tuple[float, float, float]]:
    """(semi_major_m, semi_minor_m, bearing_deg) of the 95 % ellipse of [[nn, ne], [ne, ee]] (m^2);
    None for a non-finite entry or a negative larger eigenvalue."""

def position_nees(error_ned: Sequence[float], cov6: Sequence[float]) -> Optional[float]:
    """e^T P^-1 e over N, E, D; cov6 = (NN, NE, ND, EE, ED, DD); None unless P is positive definite."""

def geo_to_ned(lat: float, lon: float, alt: float, origin: Origin) -> Tuple[float, float, float]:
    """(lat, lon in degrees, alt in m) to flat-Earth NED (m) about origin = (lat, lon, alt)."""

def ned_to_geo(north: float, east: float, down: float, origin: Origin) -> Tuple[float, float, float]:
    """Flat-Earth NED (m) about origin to (lat, lon, alt), the longitude wrapped to [-180, 180)."""

def frames(data: bytes) -> list[Tuple[int, int, int, str]]:
    """(sysid, compid, seq, message name) of every whole MAVLink frame with a valid CRC in data."""

def check_frame(frame: bytes) -> Tuple[str, Optional[list[int]]]:
    """(name, COOPLOC_EPOCH participants or None) of the first MAVLink 2 frame, checked as the node
    checks it and against its system id; ValueError names what is wrong."""

def read_log(path: str, topics: Optional[Sequence[str]] = None) -> dict:
    """A cooploc MCAP log: end ("complete", "truncated", "corrupt: ..."), metadata, topics
    {topic: (encoding, schema, count)}, messages [(topic, log_time_ns, data)] of the given topics.
    OSError when it cannot be read, ValueError when it is not MCAP."""

def mrclam(dir: str, methods: Sequence[str], regimes: Sequence[str], excerpt_s: Optional[float] = None) -> list[dict]:
    """Every method in every regime on an MRCLAM data set folder: one dict per (regime, method)
    with the table's figures of `cooploc dataset mrclam`. ValueError for unknown names or bad data."""

def experiment_json(scenario: str, runs: int, methods: Sequence[str], schedules: Optional[Sequence[str]] = None, seed: int = 1) -> str:
    """The Monte Carlo of `cooploc experiment` as JSON (see cooploc.experiment)."""

def estimate_from_frame(frame: bytes) -> dict:
    """The checked COOPLOC_ESTIMATE of the first MAVLink 2 frame; ValueError names what is wrong."""

class SequenceTracker:
    """Frames received, lost, late and repeated from one MAVLink sender on one link
    (``protocol::sequence``: the one rule of the node, the ground station and this package)."""

    received: int
    lost: int
    late: int
    repeats: int
    restarts: int
    last: Optional[int]
    def __init__(self) -> None: ...
    def observe(self, seq: int) -> None: ...
    def loss_fraction(self) -> Optional[float]: ...

class EpochTally:
    """Disagreements and heals from COOPLOC_EPOCH reports (``view::health::EpochTally``)."""

    disagreements: int
    heals: int
    unhealed_since: Optional[int]
    last_epoch: Optional[int]
    dropped: int
    repeats: int
    epochs_held: int
    nodes: list[int]
    def __init__(self) -> None: ...
    def add(self, epoch: int, announcer: int, state: int, digest: int, participants: Sequence[int]) -> str: ...
    def node(self, announcer: int) -> dict[str, int]: ...

class RateWindow:
    """Amounts over the last ``window_s`` seconds, bounded at any rate (``gcs::link::RateWindow``)."""

    def __init__(self, window_s: float = 10.0) -> None: ...
    def add(self, now_s: float, amount: int = 1) -> None: ...
    def total(self, now_s: float) -> int: ...
    def rate(self, now_s: float, since_s: Optional[float] = None) -> float: ...

def sim_state_from_frame(frame: bytes, origin: Origin) -> Tuple[float, float, float]: ...

Resolved = Tuple[int, float, Optional[float], Tuple[float, float, float]]

class TruthTrack:
    """A simulated vehicle's truth and its estimates' errors (``gcs::truth::TruthTrack``)."""

    latest: Optional[Tuple[int, float, Optional[float]]]
    times: list[int]
    positions: list[Tuple[float, float, float]]
    pending: int
    samples: int
    stale: int
    restarts: int
    untimed: int
    unavailable: int
    dropped: int
    def __init__(self, history: int = 4096, pending_max: int = 64, max_gap_us: int = 1_000_000,
                 restart_us: int = 5_000_000) -> None: ...
    def sim_state(self, ned: Tuple[float, float, float]) -> list[Resolved]: ...
    def timed(self, t_us: int) -> list[Resolved]: ...
    def estimate(self, t_us: int, ned: Tuple[float, float, float], cov6: Sequence[float]) -> list[Resolved]: ...
    def truth_at(self, t_us: int) -> Optional[Tuple[float, float, float]]: ...
    def reset_truth(self) -> None: ...
    def restart_estimates(self) -> None: ...

def replay(path: str) -> dict[int, dict]: ...
def compare_methods(path: str, methods: Sequence[str]) -> dict[str, dict[int, dict]]: ...

class PlanarTeam:
    """A team of planar robots under one method, stepped from numpy arrays (``estimation::team``)."""

    ids: list[int]
    method: str
    def __init__(self, method: str, poses, ids: Optional[Sequence[int]] = None, t0_s: float = 0.0,
                 pos_sigma_m: float = 0.1, yaw_sigma_rad: float = 0.01, speed_sigma_m_s: float = 0.05,
                 yaw_rate_sigma_rad_s: float = 0.01, rate_hz: float = 10.0) -> None: ...
    def propagate(self, t_s: float, speed, yaw_rate) -> None: ...
    def ranges(self, pairs, ranges, sigma_m: float) -> Optional[float]: ...
    def poses(self): ...
    def covariances(self): ...

def scenario_run(scenario: str, seed: int = 1, run: int = 0, schedule: str = "1hz") -> dict:
    """One run of a simulated scenario as numpy arrays, what ``cooploc experiment`` feeds its
    filters: ``ids``; ``platforms`` (per platform its initial estimate ``t0_s``,
    ``position_ned_m``, ``velocity_ned_m_s``, ``attitude_wxyz``; ``imu_t_s``,
    ``specific_force_frd_m_s2``, ``angular_rate_frd_rad_s``; ``odometer_t_s``, ``speed_m_s``;
    ``truth_t_s``, ``truth_position_ned_m``); ``epochs``, ``(t_s, pairs, ranges_m, sigma_m)`` per
    ranging epoch; ``ins_config`` and ``initial_sigma`` (the settings :class:`InsTeam` takes).
    ValueError for a bad file, schedule, or a planar robot in the scenario."""

class InsTeam:
    """A team of INS vehicles (the paper's model, 3-D ranges) under one method, stepped from numpy
    arrays (``estimation::team`` of ``estimation::nav::NavFilter``)."""

    ids: list[int]
    method: str
    def __init__(self, method: str, positions, velocities, attitudes, ins_config: dict, initial_sigma: dict,
                 ids: Optional[Sequence[int]] = None, t0_s: float = 0.0) -> None: ...
    def imu(self, t_s: float, specific_force, angular_rate, ids: Optional[Sequence[int]] = None) -> None: ...
    def odometer(self, t_s: float, speed, ids: Optional[Sequence[int]] = None) -> None: ...
    def ranges(self, pairs, ranges, sigma_m) -> Optional[float]: ...
    def positions(self): ...
    def position_covariances(self): ...
    def times(self) -> list[float]: ...

def log_series(path: str) -> dict[int, dict]:
    """Each vehicle's series in a cooploc log as numpy arrays: ``estimate`` and ``truth``
    (``log_time_s``, ``position_ned_m`` (n, 3), ``yaw_rad``), ``updates`` (``log_time_s``,
    ``epoch``, ``t_s``, ``participants``, ``nis``, ``nis_dof``, ``nees``) and ``undecodable``.
    OSError when the file cannot be read, ValueError when it is not an MCAP file."""
