//! `cooploc._native`: the Rust library's functions for Python (issue 35). The pure-Python
//! package `cooploc` (python/cooploc/) re-exports them; its type stubs are
//! python/cooploc/_native.pyi. Every function here calls the library's own (the same code the
//! node, the ground station and the logs use): nothing is re-implemented. Bad input raises a
//! Python exception (`ValueError`, or `TypeError` from the argument conversion); nothing here
//! panics on input.

use cooploc::estimation::consistency;
use cooploc::geodesy::{self, GeoOrigin, Geodetic};
use cooploc::protocol::MavMessage;
use cooploc::protocol::wire;
use mavlink_core::Message as _;
use nalgebra::{Matrix3, Vector3};
use numpy::PyArrayMethods as _;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The 95 % horizontal error ellipse of an N/E position covariance (m^2):
/// `(semi_major_m, semi_minor_m, bearing_deg)`, the bearing of the major axis from north towards
/// east in (-90, 90]; `None` for a non-finite entry or a negative larger eigenvalue
/// (`estimation::consistency::ellipse95_axes`, what every display of cooploc draws).
#[pyfunction]
fn ellipse95(nn: f64, ne: f64, ee: f64) -> Option<(f64, f64, f64)> {
    consistency::ellipse95_axes(nn, ne, ee).map(|(a, b, angle)| (a, b, angle.to_degrees()))
}

/// Position NEES `e^T P^-1 e` over N, E, D: `error_ned` (m), `cov6` the upper triangle of P
/// (NN, NE, ND, EE, ED, DD, m^2: COOPLOC_ESTIMATE.pos_covariance's order). `None` unless P is
/// positive definite and the result finite (`estimation::consistency::position_nees`).
#[pyfunction]
fn position_nees(error_ned: [f64; 3], cov6: [f64; 6]) -> Option<f64> {
    let [nn, ne, nd, ee, ed, dd] = cov6;
    let p = Matrix3::new(nn, ne, nd, ne, ee, ed, nd, ed, dd);
    consistency::position_nees(&Vector3::from(error_ned), &p)
}

fn origin(o: [f64; 3]) -> PyResult<GeoOrigin> {
    let [lat_deg, lon_deg, alt_m] = o;
    if !(lat_deg.is_finite() && lon_deg.is_finite() && alt_m.is_finite()) || lat_deg.abs() >= 90.0 {
        return Err(PyValueError::new_err(format!(
            "origin {o:?}: (lat, lon, alt) must be finite, the latitude inside (-90, 90)"
        )));
    }
    Ok(GeoOrigin { lat_deg, lon_deg, alt_m })
}

/// Latitude, longitude (degrees) and altitude (m) to the flat-Earth NED position (m) about
/// `origin` = (lat, lon, alt) (any sequence of three numbers), the longitude difference taken the short way round
/// (`geodesy::geodetic_to_ned`).
#[pyfunction]
fn geo_to_ned(lat: f64, lon: f64, alt: f64, origin: [f64; 3]) -> PyResult<(f64, f64, f64)> {
    let p = geodesy::geodetic_to_ned(&self::origin(origin)?, &Geodetic { lat_deg: lat, lon_deg: lon, alt_m: alt });
    Ok((p[0], p[1], p[2]))
}

/// Inverse of `geo_to_ned`: NED (m) about `origin` to (lat, lon, alt), the longitude wrapped to
/// [-180, 180) (`geodesy::ned_to_geodetic`).
#[pyfunction]
fn ned_to_geo(north: f64, east: f64, down: f64, origin: [f64; 3]) -> PyResult<(f64, f64, f64)> {
    let g = geodesy::ned_to_geodetic(&self::origin(origin)?, &Vector3::new(north, east, down));
    Ok((g.lat_deg, g.lon_deg, g.alt_m))
}

/// Every whole MAVLink 1 or 2 frame with a valid CRC in `data` (a datagram, a stream's bytes),
/// in order: `(sysid, compid, seq, name)`, `name` the message's name in the cooploc dialect
/// (`"UNDECODED"` for a frame whose CRC is right but whose payload the dialect refuses). Bytes
/// between frames are skipped, as the node's framer skips them (`protocol::framing`).
#[pyfunction]
fn frames(data: &[u8]) -> Vec<(u32, u8, u8, String)> {
    cooploc::protocol::framing::frames(data)
        .map(|f| {
            let name = f.message.as_ref().map_or("UNDECODED", |m| m.message_name());
            (f.header.system_id, f.header.component_id, f.header.sequence, name.to_string())
        })
        .collect()
}

/// The COOPLOC_ESTIMATE in the first MAVLink 2 frame of `frame`, checked as the ground station
/// checks it (`protocol::wire::estimate_from_message`: finite fields, no negative variance, a
/// known method) and its platform against the frame's system id, as a dict: `platform`, `t_us`,
/// `epoch`, `method`, `position_ned_m`, `velocity_ned_m_s`, `yaw_rad`, `pos_covariance` (the six
/// entries of the wire), `yaw_variance`, `nis`, `participants`, `ranges`. `ValueError` names what
/// is wrong: no frame, another message, a field out of range.
#[pyfunction]
fn estimate_from_frame<'py>(py: Python<'py>, frame: &[u8]) -> PyResult<Bound<'py, PyDict>> {
    let (header, msg) = wire::from_frame(frame).map_err(refused)?;
    let MavMessage::COOPLOC_ESTIMATE(m) = &msg else {
        return Err(PyValueError::new_err(format!("{} is not a COOPLOC_ESTIMATE", msg.message_name())));
    };
    let e = wire::estimate_from_message(m).map_err(refused)?;
    speaks_for(&header, "COOPLOC_ESTIMATE", e.platform)?;
    let c = &e.position_covariance_m2;
    let d = PyDict::new(py);
    d.set_item("platform", e.platform)?;
    d.set_item("t_us", e.t.0)?;
    d.set_item("epoch", e.epoch)?;
    d.set_item("method", e.method.short_name())?;
    d.set_item("position_ned_m", (e.position_ned_m[0], e.position_ned_m[1], e.position_ned_m[2]))?;
    d.set_item("velocity_ned_m_s", (e.velocity_ned_m_s[0], e.velocity_ned_m_s[1], e.velocity_ned_m_s[2]))?;
    d.set_item("yaw_rad", e.yaw_rad)?;
    d.set_item("pos_covariance", [c[(0, 0)], c[(0, 1)], c[(0, 2)], c[(1, 1)], c[(1, 2)], c[(2, 2)]])?;
    d.set_item("yaw_variance", e.yaw_variance_rad2)?;
    d.set_item("nis", e.nis)?;
    d.set_item("participants", e.participants)?;
    d.set_item("ranges", e.ranges)?;
    Ok(d)
}

/// Methods by their short names (`estimation::Method::short_name`); `ValueError` names an
/// unknown one.
fn parse_methods(names: &[String]) -> PyResult<Vec<cooploc::estimation::Method>> {
    names
        .iter()
        .map(|m| {
            cooploc::estimation::Method::from_short_name(m).ok_or_else(|| PyValueError::new_err(format!("unknown method {m:?}")))
        })
        .collect()
}

/// `ValueError` unless the platform message `name` speaks for is the frame's sender.
fn speaks_for(header: &mavlink_core::MavHeader, name: &str, platform: u16) -> PyResult<()> {
    if header.system_id == u32::from(platform) {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!("{name} of platform {platform} sent by system {}", header.system_id)))
    }
}

fn refused(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Checks the cooploc message in the first MAVLink 2 frame of `frame` as the node and the ground
/// station check it (`protocol::wire`'s `*_from_message`: finite values, ranges of values, no
/// platform listed twice, ...), and that the platform it speaks for is the frame's system id
/// (an estimate's `platform`, an epoch's `announcer`, a range's `from_platform`, a fragment's
/// `platform`, a range-and-bearing's `observer`, a store-held's `announcer`). Returns `(name, participants)`: the message's
/// name and, for COOPLOC_EPOCH and COOPLOC_EPOCH_SET, its participants (`None` otherwise). Messages outside the cooploc
/// set are not checked. `ValueError` names what is wrong (no frame, a bad CRC, a payload the
/// dialect refuses, a field out of range, another system's platform).
#[pyfunction]
fn check_frame(frame: &[u8]) -> PyResult<(String, Option<Vec<u16>>)> {
    let (header, msg) = wire::from_frame(frame).map_err(refused)?;
    let name = msg.message_name();
    let speaks_for = |platform| speaks_for(&header, name, platform);
    let participants = match &msg {
        MavMessage::COOPLOC_ESTIMATE(m) => {
            speaks_for(wire::estimate_from_message(m).map_err(refused)?.platform)?;
            None
        }
        MavMessage::COOPLOC_EPOCH(_) | MavMessage::COOPLOC_EPOCH_SET(_) => {
            let a = wire::epoch_of(&msg).expect("an epoch announcement").map_err(refused)?;
            speaks_for(a.announcer)?;
            Some(a.participants)
        }
        MavMessage::COOPLOC_RANGE(m) => {
            speaks_for(wire::range_from_message(m).map_err(refused)?.1.from)?;
            None
        }
        MavMessage::COOPLOC_STATE_FRAGMENT(m) => {
            speaks_for(wire::fragment_from_message(m).map_err(refused)?.platform)?;
            None
        }
        MavMessage::COOPLOC_STORE_FRAGMENT(m) => {
            speaks_for(wire::store_fragment_from_message(m).map_err(refused)?.platform)?;
            None
        }
        MavMessage::COOPLOC_RANGE_BEARING(m) => {
            speaks_for(wire::range_bearing_from_message(m).map_err(refused)?.observer)?;
            None
        }
        MavMessage::COOPLOC_STORE_HELD(m) => {
            speaks_for(wire::store_held_from_message(m).map_err(refused)?.announcer)?;
            None
        }
        _ => None,
    };
    Ok((name.to_string(), participants))
}

/// Reads a cooploc MCAP log (logs/README.md: its topics and encodings) as a dict:
/// - `end`: `"complete"`, `"truncated"` (its writer was killed: everything up to the last complete
///   chunk is there) or `"corrupt: REASON"` (everything before the damage is there);
/// - `metadata`: `{name: {key: value}}` (the node's configuration, the scenario, ...);
/// - `topics`: `{topic: (message_encoding, schema_name or None, messages in the log)}`;
/// - `messages`: `[(topic, log_time_ns, data)]` in file order, only of the topics named in
///   `topics` when given (all otherwise). `data` is the message's bytes: a MAVLink frame (see
///   `frames`, `check_frame`), JSON (`json.loads`) or protobuf, as `topics` says.
///
/// `OSError` when the file cannot be opened or read, `ValueError` when it is not an MCAP file
/// (`recording::read_log`, what `cooploc replay` reads).
#[pyfunction]
#[pyo3(signature = (path, topics = None))]
fn read_log<'py>(py: Python<'py>, path: std::path::PathBuf, topics: Option<Vec<String>>) -> PyResult<Bound<'py, PyDict>> {
    use cooploc::recording::LogEnd;
    let log = open_log(&path)?;
    let d = PyDict::new(py);
    d.set_item(
        "end",
        match &log.end {
            LogEnd::Complete => "complete".to_string(),
            LogEnd::Truncated => "truncated".to_string(),
            LogEnd::Corrupt { reason } => format!("corrupt: {reason}"),
        },
    )?;
    let metadata = PyDict::new(py);
    for m in &log.metadata {
        metadata.set_item(&m.name, m.entries.clone())?;
    }
    d.set_item("metadata", metadata)?;
    let mut counts: std::collections::BTreeMap<&str, u64> = std::collections::BTreeMap::new();
    for m in &log.messages {
        *counts.entry(m.topic()).or_default() += 1;
    }
    let channels = PyDict::new(py);
    for c in log.channels.values() {
        let schema = c.schema.as_ref().map(|s| s.name.clone());
        channels.set_item(&c.topic, (c.message_encoding.clone(), schema, counts.get(c.topic.as_str()).copied().unwrap_or(0)))?;
    }
    d.set_item("topics", channels)?;
    let wanted = |t: &str| topics.as_ref().is_none_or(|ts| ts.iter().any(|x| x == t));
    let messages: Vec<(String, u64, Bound<'py, pyo3::types::PyBytes>)> = log
        .messages
        .iter()
        .filter(|m| wanted(m.topic()))
        .map(|m| (m.topic().to_string(), m.log_time_ns, pyo3::types::PyBytes::new(py, &m.data)))
        .collect();
    d.set_item("messages", messages)?;
    Ok(d)
}

/// Every `method` in every `regime` on a UTIAS MRCLAM data set folder (`dir`), as
/// `cooploc dataset mrclam DIR --method .. --regime ..` runs them with the committed noise model
/// (`dataset::run::run`, in parallel): one dict per (regime, method), in that order, with the
/// table's figures (`pos_rmse_m`, `heading_rmse_deg`, `avg_nees`, `avg_nees_position`,
/// `avg_nees_heading`, `in_bound_share`, `samples`, `masked`, `landmark_updates`,
/// `landmark_gated`, `robot_updates`, `robot_gated`, `epochs`, `refused`) and `robots`, a list of
/// `(id, pos_rmse_m, heading_rmse_deg, samples, masked)`. `excerpt_s`: only the data set's first
/// seconds. Methods by their short names (`dr`, `naive`, `dcl`, `ci`, `central`), regimes
/// `no-landmarks`, `map-blind`, `full-map`. `ValueError` for an unknown name or an unreadable
/// data set (the message names the file and line). The GIL is released while it runs.
#[pyfunction]
#[pyo3(signature = (dir, methods, regimes, excerpt_s = None))]
fn mrclam<'py>(
    py: Python<'py>,
    dir: std::path::PathBuf,
    methods: Vec<String>,
    regimes: Vec<String>,
    excerpt_s: Option<f64>,
) -> PyResult<Vec<Bound<'py, PyDict>>> {
    use cooploc::dataset::run::{Regime, Settings, run_all};
    let methods = parse_methods(&methods)?;
    let regimes: Vec<Regime> = regimes
        .iter()
        .map(|r| Regime::from_name(r).ok_or_else(|| PyValueError::new_err(format!("unknown regime {r:?}"))))
        .collect::<PyResult<_>>()?;
    if excerpt_s.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
        return Err(PyValueError::new_err(format!("excerpt_s {excerpt_s:?}: expected a positive number of seconds")));
    }
    let outcomes = py
        .detach(|| {
            let mut ds = cooploc::dataset::mrclam::read_folder(&dir).map_err(|e| e.to_string())?;
            if let Some(s) = excerpt_s {
                ds = ds.excerpt(s);
            }
            let settings = Settings::new(cooploc::dataset::noise::NoiseModel::mrclam());
            run_all(&ds, &settings, &regimes, &methods).map_err(|e| e.to_string())
        })
        .map_err(PyValueError::new_err)?;
    outcomes
        .iter()
        .map(|(o, _)| {
            let d = PyDict::new(py);
            d.set_item("regime", o.regime.name())?;
            d.set_item("method", o.method.short_name())?;
            for (k, v) in [
                ("pos_rmse_m", o.pos_rmse_m),
                ("heading_rmse_deg", o.heading_rmse_deg),
                ("avg_nees", o.avg_nees),
                ("avg_nees_position", o.avg_nees_position),
                ("avg_nees_heading", o.avg_nees_heading),
                ("in_bound_share", o.in_bound_share),
            ] {
                d.set_item(k, v)?;
            }
            for (k, v) in [
                ("samples", o.samples),
                ("masked", o.masked),
                ("landmark_updates", o.landmark_updates),
                ("landmark_gated", o.landmark_gated),
                ("robot_updates", o.robot_updates),
                ("robot_gated", o.robot_gated),
                ("epochs", o.epochs),
                ("refused", o.refused),
            ] {
                d.set_item(k, v)?;
            }
            let robots: Vec<_> = o.robots.iter().map(|r| (r.id, r.pos_rmse_m, r.heading_rmse_deg, r.samples, r.masked)).collect();
            d.set_item("robots", robots)?;
            Ok(d)
        })
        .collect()
}

/// The Monte Carlo experiment of `cooploc experiment` on a scenario file: `runs` runs of
/// `methods` (short names) over `schedules` (the scenario's names; all when `None`), seed
/// `seed`, in parallel; returns JSON (the package's `experiment` parses it): a list with one
/// entry per schedule, the summary `cooploc experiment` prints and writes (`experiment::report`:
/// per method and platform the final errors, NEES, reductions) and `curves`, the RMS over runs of
/// the position and heading errors at every truth sample per method and platform (the paper's
/// figures). `ValueError` for a bad scenario, name or count. The GIL is released while it runs.
#[pyfunction]
#[pyo3(signature = (scenario, runs, methods, schedules = None, seed = 1))]
fn experiment_json(
    py: Python<'_>,
    scenario: std::path::PathBuf,
    runs: u32,
    methods: Vec<String>,
    schedules: Option<Vec<String>>,
    seed: u64,
) -> PyResult<String> {
    use cooploc::experiment::{ExperimentSpec, InputSource, report, run_experiment};
    let methods = parse_methods(&methods)?;
    py.detach(|| {
        let scenario = cooploc::sitl::scenario::Scenario::from_path(&scenario).map_err(|e| e.to_string())?;
        let world = cooploc::sitl::world::World::new(&scenario).map_err(|e| e.to_string())?;
        let schedules = schedules.unwrap_or_else(|| scenario.ranging.schedules.iter().map(|s| s.name.clone()).collect());
        let spec = ExperimentSpec { runs, seed, methods, schedules, source: InputSource::World };
        let mc = run_experiment(&world, &spec, &|| {}).map_err(|e| e.to_string())?;
        let summaries = report::summarize(&spec, &mc.runs, &mc.curves);
        let out: Vec<serde_json::Value> = summaries
            .iter()
            .map(|s| {
                let mut v = serde_json::to_value(s).map_err(|e| e.to_string())?;
                v["curves"] = serde_json::to_value(&s.curves).map_err(|e| e.to_string())?;
                Ok(v)
            })
            .collect::<Result<_, String>>()?;
        serde_json::to_string(&out).map_err(|e| e.to_string())
    })
    .map_err(PyValueError::new_err)
}

/// Frames received, lost, late and repeated from one MAVLink sender on one link, by their
/// sequence numbers (`protocol::sequence::SequenceTracker`: the one rule of the node, the ground
/// station and the MAVProxy module). `observe(seq)` takes each frame's number (0..=255).
#[pyclass(name = "SequenceTracker", module = "cooploc._native")]
#[derive(Default)]
struct PySequenceTracker(cooploc::protocol::sequence::SequenceTracker);

#[pymethods]
impl PySequenceTracker {
    #[new]
    fn new() -> Self {
        Self::default()
    }

    /// One frame's sequence number; `ValueError` outside 0..=255.
    fn observe(&mut self, seq: i64) -> PyResult<()> {
        let seq = u8::try_from(seq).map_err(|_| PyValueError::new_err(format!("sequence number {seq} outside 0..=255")))?;
        self.0.observe(seq);
        Ok(())
    }

    #[getter]
    fn received(&self) -> u64 {
        self.0.received
    }

    #[getter]
    fn lost(&self) -> u64 {
        self.0.lost
    }

    /// Frames that came after a later one (their loss taken back).
    #[getter]
    fn late(&self) -> u64 {
        self.0.late
    }

    /// The same number twice in a row.
    #[getter]
    fn repeats(&self) -> u64 {
        self.0.repeats
    }

    /// Jumps back beyond the reordering window: the sender started its numbers again.
    #[getter]
    fn restarts(&self) -> u64 {
        self.0.restarts
    }

    /// The last number followed (None before the first frame).
    #[getter]
    fn last(&self) -> Option<u8> {
        self.0.last()
    }

    /// Lost / (received + lost); None before two frames.
    fn loss_fraction(&self) -> Option<f64> {
        self.0.loss_fraction()
    }

    fn __repr__(&self) -> String {
        let t = &self.0;
        format!(
            "SequenceTracker(received={}, lost={}, late={}, repeats={}, restarts={})",
            t.received, t.lost, t.late, t.repeats, t.restarts
        )
    }
}

/// Disagreements and heals of a team from its COOPLOC_EPOCH reports (`view::health::EpochTally`:
/// the rules of the ground station, its page and Foxglove channels). `add(epoch, announcer,
/// state, digest, participants)` takes one report whose announcer was checked against its
/// sender; it answers `"report"`, `"store_wanted"`, `"repeat"`, `"ignored"` (COLLECTING, or a
/// state that is none of COOPLOC_EPOCH_STATE) or `"dropped"` (beyond the bounds).
#[pyclass(name = "EpochTally", module = "cooploc._native")]
#[derive(Default)]
struct PyEpochTally(cooploc::view::health::EpochTally);

#[pymethods]
impl PyEpochTally {
    #[new]
    fn new() -> Self {
        Self::default()
    }

    fn add(&mut self, epoch: u32, announcer: u16, state: i64, digest: u64, participants: Vec<u16>) -> &'static str {
        use cooploc::protocol::wire::EpochState;
        let state = match state {
            1 => EpochState::COOPLOC_EPOCH_STATE_APPLIED,
            2 => EpochState::COOPLOC_EPOCH_STATE_PARTIAL,
            3 => EpochState::COOPLOC_EPOCH_STATE_FAILED,
            4 => EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED,
            _ => return "ignored",
        };
        let a = wire::EpochAnnouncement {
            epoch,
            t: cooploc::time::TimeUs(0),
            announcer,
            participants,
            state,
            digest,
            incomplete: Vec::new(),
        };
        self.0.on_epoch(&a).name()
    }

    #[getter]
    fn disagreements(&self) -> u64 {
        self.0.disagreements
    }

    #[getter]
    fn heals(&self) -> u64 {
        self.0.heals
    }

    /// The latest disagreeing epoch not yet followed by an agreeing one (None: in agreement).
    #[getter]
    fn unhealed_since(&self) -> Option<u32> {
        self.0.unhealed_since
    }

    #[getter]
    fn last_epoch(&self) -> Option<u32> {
        self.0.last_epoch
    }

    #[getter]
    fn dropped(&self) -> u64 {
        self.0.dropped
    }

    #[getter]
    fn repeats(&self) -> u64 {
        self.0.repeats
    }

    #[getter]
    fn epochs_held(&self) -> usize {
        self.0.epochs_held()
    }

    /// The nodes counted, by platform id.
    #[getter]
    fn nodes(&self) -> Vec<u16> {
        self.0.nodes.keys().copied().collect()
    }

    /// One node's counts: `reports`, `outvoted`, `heals`, `partial`, `failed`, `store_wanted`
    /// (all 0 for a node not heard).
    fn node<'py>(&self, py: Python<'py>, announcer: u16) -> PyResult<Bound<'py, PyDict>> {
        let c = self.0.nodes.get(&announcer).copied().unwrap_or_default();
        let d = PyDict::new(py);
        for (k, v) in [
            ("reports", c.reports),
            ("outvoted", c.outvoted),
            ("heals", c.heals),
            ("partial", c.partial),
            ("failed", c.failed),
            ("store_wanted", c.store_wanted),
        ] {
            d.set_item(k, v)?;
        }
        Ok(d)
    }
}

/// Amounts (bytes, frames, estimates) over the last `window_s` seconds, in buckets of a fortieth
/// of the window: bounded memory at any rate (`gcs::link::RateWindow`, the ground station's).
/// Times are seconds of any monotonic clock (`time.monotonic()`), at or after 0.
#[pyclass(name = "RateWindow", module = "cooploc._native")]
struct PyRateWindow(cooploc::gcs::link::RateWindow);

/// A time in seconds as the package takes them: finite, at or after 0, before year 2540.
fn seconds(t_s: f64) -> PyResult<f64> {
    if t_s.is_finite() && (0.0..1.8e10).contains(&t_s) {
        Ok(t_s)
    } else {
        Err(PyValueError::new_err(format!("time {t_s} s: a finite, non-negative clock reading")))
    }
}

fn wall_ns(now_s: f64) -> PyResult<cooploc::gcs::WallNs> {
    Ok(cooploc::gcs::WallNs((seconds(now_s)? * 1e9) as u64))
}

#[pymethods]
impl PyRateWindow {
    #[new]
    #[pyo3(signature = (window_s = 10.0))]
    fn new(window_s: f64) -> PyResult<Self> {
        if !(window_s.is_finite() && window_s > 0.0 && window_s <= 86_400.0) {
            return Err(PyValueError::new_err(format!("window {window_s} s: in (0, 86400]")));
        }
        Ok(Self(cooploc::gcs::link::RateWindow::new((window_s * 1e9) as u64)))
    }

    /// `amount` (>= 0) received at `now_s`.
    #[pyo3(signature = (now_s, amount = 1))]
    fn add(&mut self, now_s: f64, amount: u64) -> PyResult<()> {
        self.0.push(wall_ns(now_s)?, amount);
        Ok(())
    }

    /// The amount over the window ending at `now_s`.
    fn total(&self, now_s: f64) -> PyResult<u64> {
        Ok(self.0.total(wall_ns(now_s)?))
    }

    /// Amount per second over the window ending at `now_s`, over the time since `since_s` (the
    /// first amount's time when None) when that is shorter, at least 0.1 s; 0 before any amount.
    #[pyo3(signature = (now_s, since_s = None))]
    fn rate(&self, now_s: f64, since_s: Option<f64>) -> PyResult<f64> {
        let now = wall_ns(now_s)?;
        Ok(match since_s {
            Some(since) => self.0.bytes_per_s(now, wall_ns(since)?),
            None => self.0.per_s(now),
        })
    }
}

/// A SIM_STATE frame's truth in the team's NED frame about `origin`: `(north, east, down)` m,
/// checked as the ground station checks it (`protocol::wire::sim_state_from_message`: the 1e-7
/// degree integers when non-zero, else the float fields; a non-finite field, a latitude outside
/// [-90, 90] or a quaternion whose norm is not 1 is refused with `ValueError`, as is a frame that
/// is no SIM_STATE).
#[pyfunction]
fn sim_state_from_frame(frame: &[u8], origin: [f64; 3]) -> PyResult<(f64, f64, f64)> {
    let origin = self::origin(origin)?;
    let (_, msg) = wire::from_frame(frame).map_err(refused)?;
    let MavMessage::SIM_STATE(m) = &msg else {
        return Err(PyValueError::new_err(format!("{} is not a SIM_STATE", msg.message_name())));
    };
    let p = wire::sim_state_from_message(m, &origin).map_err(refused)?.pos_ned_m;
    Ok((p[0], p[1], p[2]))
}

type Resolved = (u64, f64, Option<f64>, (f64, f64, f64));

/// The truth of one simulated vehicle and its estimates' errors against it: the ground station's
/// rules (`gcs::truth::TruthTrack`). `sim_state(ned)` takes a SIM_STATE's position (it waits
/// for the time of the next timed frame), `timed(t_us)` the time of a HIGHRES_IMU or ODOMETRY;
/// `estimate(t_us, ned, cov6)` an estimate (cov6: NN, NE, ND, EE, ED, DD), held until the truth
/// covers its time (the last `pending_max`). Each returns the errors it resolved, in time order:
/// `(t_us, horizontal error m, NEES or None, truth (N, E, D))`.
#[pyclass(name = "TruthTrack", module = "cooploc._native")]
struct PyTruthTrack {
    track: cooploc::gcs::truth::TruthTrack,
    pending: std::collections::VecDeque<(u64, Vector3<f64>, Matrix3<f64>)>,
    pending_max: usize,
    latest: Option<(u64, f64, Option<f64>)>,
    unavailable: u64,
    dropped: u64,
}

impl PyTruthTrack {
    fn resolve(&mut self) -> Vec<Resolved> {
        use cooploc::gcs::truth::ErrorState;
        let mut out = Vec::new();
        let track = &self.track;
        let unavailable = &mut self.unavailable;
        self.pending.retain(|(t, pos, cov)| match track.judge(cooploc::time::TimeUs(*t), pos, cov) {
            ErrorState::Pending => true,
            ErrorState::Unavailable => {
                *unavailable += 1;
                false
            }
            ErrorState::Known(e) => {
                let p = e.truth_ned_m;
                out.push((*t, e.horizontal_m, e.nees, (p[0], p[1], p[2])));
                false
            }
        });
        out.sort_by_key(|r| r.0);
        if let Some(&(t, err, nees, _)) = out.last()
            && self.latest.is_none_or(|(lt, _, _)| t >= lt)
        {
            self.latest = Some((t, err, nees));
        }
        out
    }
}

fn ned(p: (f64, f64, f64)) -> PyResult<Vector3<f64>> {
    let v = Vector3::new(p.0, p.1, p.2);
    if v.iter().all(|x| x.is_finite()) { Ok(v) } else { Err(PyValueError::new_err(format!("position {p:?} is not finite"))) }
}

#[pymethods]
impl PyTruthTrack {
    #[new]
    #[pyo3(signature = (history = 4096, pending_max = 64, max_gap_us = 1_000_000, restart_us = 5_000_000))]
    fn new(history: usize, pending_max: usize, max_gap_us: u64, restart_us: u64) -> Self {
        PyTruthTrack {
            track: cooploc::gcs::truth::TruthTrack::new(history, restart_us, max_gap_us),
            pending: std::collections::VecDeque::new(),
            pending_max: pending_max.max(1),
            latest: None,
            unavailable: 0,
            dropped: 0,
        }
    }

    fn sim_state(&mut self, ned: (f64, f64, f64)) -> PyResult<Vec<Resolved>> {
        let point = cooploc::gcs::TruthPoint {
            t: None,
            rx: cooploc::gcs::WallNs(0),
            pos_ned_m: self::ned(ned)?,
            vel_ned_m_s: Vector3::zeros(),
            yaw_rad: 0.0,
        };
        let placed = self.track.sim_state(point);
        Ok(if matches!(placed, Some(cooploc::gcs::truth::Placed::Timed { .. })) { self.resolve() } else { Vec::new() })
    }

    fn timed(&mut self, t_us: u64) -> Vec<Resolved> {
        let placed = self.track.timed(cooploc::time::TimeUs(t_us));
        if matches!(placed, Some(cooploc::gcs::truth::Placed::Timed { .. })) { self.resolve() } else { Vec::new() }
    }

    fn estimate(&mut self, t_us: u64, ned: (f64, f64, f64), cov6: [f64; 6]) -> PyResult<Vec<Resolved>> {
        let [nn, ne, nd, ee, ed, dd] = cov6;
        let cov = Matrix3::new(nn, ne, nd, ne, ee, ed, nd, ed, dd);
        if self.pending.len() == self.pending_max {
            self.pending.pop_front();
            self.dropped += 1;
        }
        self.pending.push_back((t_us, self::ned(ned)?, cov));
        Ok(self.resolve())
    }

    /// The truth at `t_us`, interpolated; None outside its span or across a gap.
    fn truth_at(&self, t_us: u64) -> Option<(f64, f64, f64)> {
        self.track.truth_at(cooploc::time::TimeUs(t_us)).map(|p| (p[0], p[1], p[2]))
    }

    /// Forgets the truth (the origin changed) and the latest error.
    fn reset_truth(&mut self) {
        self.track.reset();
        self.latest = None;
    }

    /// The node restarted: its held estimates and its latest error are forgotten.
    fn restart_estimates(&mut self) {
        self.pending.clear();
        self.latest = None;
    }

    /// `(t_us, horizontal error m, NEES or None)` of the newest estimate with an error.
    #[getter]
    fn latest(&self) -> Option<(u64, f64, Option<f64>)> {
        self.latest
    }

    /// The timed samples' times, us, ascending.
    #[getter]
    fn times(&self) -> Vec<u64> {
        self.track.samples().iter().filter_map(|p| p.t.map(|t| t.0)).collect()
    }

    #[getter]
    fn positions(&self) -> Vec<(f64, f64, f64)> {
        self.track.samples().iter().map(|p| (p.pos_ned_m[0], p.pos_ned_m[1], p.pos_ned_m[2])).collect()
    }

    /// Estimates waiting for the truth.
    #[getter]
    fn pending(&self) -> usize {
        self.pending.len()
    }

    #[getter]
    fn samples(&self) -> u64 {
        self.track.counts.samples
    }

    #[getter]
    fn stale(&self) -> u64 {
        self.track.counts.stale
    }

    #[getter]
    fn restarts(&self) -> u64 {
        self.track.counts.restarts
    }

    #[getter]
    fn untimed(&self) -> u64 {
        self.track.counts.untimed
    }

    #[getter]
    fn unavailable(&self) -> u64 {
        self.unavailable
    }

    #[getter]
    fn dropped(&self) -> u64 {
        self.dropped
    }
}

fn open_log(path: &std::path::Path) -> PyResult<cooploc::recording::Log> {
    use cooploc::recording::ReadError;
    cooploc::recording::read_log(path).map_err(|e| match e {
        ReadError::Open { .. } | ReadError::Io { .. } => pyo3::exceptions::PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(format!("{}: {e}", path.display())),
    })
}

/// Estimates as numpy arrays: `t_s` (n), `epoch` (n), `position_ned_m` (n, 3),
/// `velocity_ned_m_s` (n, 3), `yaw_rad` (n), `position_covariance_m2` (n, 3, 3), `nis` (n).
fn estimate_arrays<'py>(py: Python<'py>, es: &[wire::EstimateReport]) -> PyResult<Bound<'py, PyDict>> {
    use numpy::{IntoPyArray, PyArray2, PyArray3};
    let n = es.len();
    let d = PyDict::new(py);
    d.set_item("t_s", es.iter().map(|e| e.t.as_secs_f64()).collect::<Vec<_>>().into_pyarray(py))?;
    d.set_item("epoch", es.iter().map(|e| e.epoch).collect::<Vec<_>>().into_pyarray(py))?;
    let rows3 = |f: &dyn Fn(&wire::EstimateReport) -> Vector3<f64>| -> PyResult<Bound<'py, PyArray2<f64>>> {
        let flat: Vec<f64> = es.iter().flat_map(|e| f(e).iter().copied().collect::<Vec<_>>()).collect();
        flat.into_pyarray(py).reshape([n, 3])
    };
    d.set_item("position_ned_m", rows3(&|e| e.position_ned_m)?)?;
    d.set_item("velocity_ned_m_s", rows3(&|e| e.velocity_ned_m_s)?)?;
    d.set_item("yaw_rad", es.iter().map(|e| e.yaw_rad).collect::<Vec<_>>().into_pyarray(py))?;
    let cov: Vec<f64> =
        es.iter().flat_map(|e| e.position_covariance_m2.transpose().iter().copied().collect::<Vec<_>>()).collect();
    let cov: Bound<'py, PyArray3<f64>> = cov.into_pyarray(py).reshape([n, 3, 3])?;
    d.set_item("position_covariance_m2", cov)?;
    d.set_item("nis", es.iter().map(|e| e.nis).collect::<Vec<_>>().into_pyarray(py))?;
    Ok(d)
}

/// Replays every node of a cooploc log (`replay::replay_nodes`, what `cooploc replay` runs: each
/// node's core fed the frames and events it logged): per platform id a dict with `method`, the
/// estimates it `recorded` (what it sent) and those the replay `replayed`, as numpy arrays
/// (`t_s`, `epoch`, `position_ned_m` (n, 3), `velocity_ned_m_s` (n, 3), `yaw_rad`,
/// `position_covariance_m2` (n, 3, 3), `nis`), `identical` (every estimate equal, bit for bit)
/// and `imu_replayed`. `OSError` for a file that cannot be read, `ValueError` for one that is not
/// a cooploc log or that replay refuses (the message says why). The GIL is released while it runs.
#[pyfunction]
fn replay<'py>(py: Python<'py>, path: std::path::PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let log = open_log(&path)?;
    let nodes = py.detach(|| cooploc::replay::replay_nodes(&log)).map_err(|e| PyValueError::new_err(e.to_string()))?;
    let out = PyDict::new(py);
    for n in &nodes {
        let d = PyDict::new(py);
        d.set_item("method", n.method.short_name())?;
        d.set_item("recorded", estimate_arrays(py, &n.recorded)?)?;
        d.set_item("replayed", estimate_arrays(py, &n.replayed)?)?;
        d.set_item("identical", n.matches())?;
        d.set_item("imu_replayed", n.imu_replayed)?;
        out.set_item(n.id, d)?;
    }
    Ok(out)
}

/// Every method of `methods` (short names) run offline on the inputs a cooploc log's vehicles
/// sent (`replay::compare_methods`, what `cooploc replay --compare` runs; the log needs its
/// `cooploc.run` metadata, as `cooploc demo` writes it): per method, per platform id, numpy
/// arrays at every truth sample, `t_s`, `pos_err_m`, `pos_err_ne_m` (n, 2), `heading_err_deg`,
/// `track_ne_m` (n, 2), and the run's `final_nees` with its `nees_states`. Errors as
/// [`replay`]; `ValueError` names an unknown method. The GIL is released while it runs.
#[pyfunction]
fn compare_methods<'py>(py: Python<'py>, path: std::path::PathBuf, methods: Vec<String>) -> PyResult<Bound<'py, PyDict>> {
    use numpy::IntoPyArray;
    let methods = parse_methods(&methods)?;
    let log = open_log(&path)?;
    let runs =
        py.detach(|| cooploc::replay::compare_methods(&log, &methods)).map_err(|e| PyValueError::new_err(e.to_string()))?;
    let out = PyDict::new(py);
    for run in &runs {
        let per = PyDict::new(py);
        for p in &run.platforms {
            let n = p.trace.len();
            let d = PyDict::new(py);
            d.set_item("t_s", p.trace.iter().map(|e| e.t_s).collect::<Vec<_>>().into_pyarray(py))?;
            d.set_item("pos_err_m", p.trace.iter().map(|e| e.pos_err_m).collect::<Vec<_>>().into_pyarray(py))?;
            let ne: Vec<f64> = p.trace.iter().flat_map(|e| e.pos_err_ne_m).collect();
            d.set_item("pos_err_ne_m", ne.into_pyarray(py).reshape([n, 2])?)?;
            d.set_item("heading_err_deg", p.trace.iter().map(|e| e.heading_err_deg).collect::<Vec<_>>().into_pyarray(py))?;
            let track: Vec<f64> = p.track_ne_m.iter().flatten().copied().collect();
            let m = p.track_ne_m.len();
            d.set_item("track_ne_m", track.into_pyarray(py).reshape([m, 2])?)?;
            d.set_item("final_nees", p.final_nees)?;
            d.set_item("nees_states", p.nees_states)?;
            per.set_item(p.id, d)?;
        }
        out.set_item(run.method.short_name(), per)?;
    }
    Ok(out)
}

/// A team of planar robots (N, E, yaw; wheel odometry as speed and yaw rate) under one method,
/// stepped from numpy arrays: the estimation core for experiments on one's own data
/// (`estimation::team::Team` of `estimation::planar::PlanarFilter`, what the nodes and
/// `cooploc dataset` run). `poses` is an (n, 3) array of the robots' initial [north m, east m,
/// yaw rad], `ids` their platform ids (1..=n when None). The wheel noise is given per sample
/// at `rate_hz`. Every input is checked: a wrong shape, a non-finite value, time going
/// backwards or an unknown id raises `ValueError` and leaves the team as it was.
#[pyclass(name = "PlanarTeam", module = "cooploc._native")]
struct PyPlanarTeam {
    team: cooploc::estimation::team::Team<cooploc::estimation::planar::PlanarFilter>,
    ids: Vec<u16>,
}

/// A platform id given from Python (a range's end) that must be one of the team's `ids`.
fn team_member(ids: &[u16], v: i64) -> PyResult<u16> {
    u16::try_from(v)
        .ok()
        .filter(|id| ids.contains(id))
        .ok_or_else(|| PyValueError::new_err(format!("platform {v} is not in the team {ids:?}")))
}

fn estimation_error(e: cooploc::estimation::EstimationError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn time_us(t_s: f64) -> PyResult<cooploc::time::TimeUs> {
    Ok(cooploc::time::TimeUs((seconds(t_s)? * 1e6).round() as u64))
}

#[pymethods]
impl PyPlanarTeam {
    #[new]
    #[pyo3(signature = (method, poses, ids = None, t0_s = 0.0, pos_sigma_m = 0.1, yaw_sigma_rad = 0.01,
                        speed_sigma_m_s = 0.05, yaw_rate_sigma_rad_s = 0.01, rate_hz = 10.0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        method: &str,
        poses: numpy::PyReadonlyArray2<'_, f64>,
        ids: Option<Vec<u16>>,
        t0_s: f64,
        pos_sigma_m: f64,
        yaw_sigma_rad: f64,
        speed_sigma_m_s: f64,
        yaw_rate_sigma_rad_s: f64,
        rate_hz: f64,
    ) -> PyResult<Self> {
        use cooploc::estimation::planar::{PlanarConfig, PlanarFilter, PlanarSigma, PlanarState};
        let method = parse_methods(&[method.to_string()])?[0];
        let poses = poses.as_array();
        if poses.ncols() != 3 || poses.nrows() == 0 {
            return Err(PyValueError::new_err(format!("poses of shape {:?}: (n, 3) expected, n >= 1", poses.shape())));
        }
        let n = poses.nrows();
        let ids = ids.unwrap_or_else(|| (1..=n as u16).collect());
        if ids.len() != n {
            return Err(PyValueError::new_err(format!("{} ids for {n} poses", ids.len())));
        }
        if !(rate_hz.is_finite() && rate_hz > 0.0) {
            return Err(PyValueError::new_err(format!("rate_hz {rate_hz}: positive")));
        }
        let config = PlanarConfig::from_sample_sigmas(speed_sigma_m_s, yaw_rate_sigma_rad_s, rate_hz);
        let sigma = PlanarSigma { pos_m: pos_sigma_m, yaw_rad: yaw_sigma_rad };
        let t0 = time_us(t0_s)?;
        let mut members = Vec::with_capacity(n);
        for (k, &id) in ids.iter().enumerate() {
            let row = poses.row(k);
            let state = PlanarState { pos_ned_m: Vector3::new(row[0], row[1], 0.0), yaw_rad: row[2] };
            if !row.iter().all(|v| v.is_finite()) {
                return Err(PyValueError::new_err(format!("pose {k} is not finite")));
            }
            members.push((id, PlanarFilter::new(config, t0, state, sigma).map_err(estimation_error)?));
        }
        let team = cooploc::estimation::team::Team::new(method, members).map_err(estimation_error)?;
        Ok(PyPlanarTeam { team, ids })
    }

    /// Every robot's wheel sample over the interval ending at `t_s`: `speed` (m/s) and
    /// `yaw_rate` (rad/s, clockwise seen from above), (n,) arrays in the order of `ids`.
    fn propagate(
        &mut self,
        t_s: f64,
        speed: numpy::PyReadonlyArray1<'_, f64>,
        yaw_rate: numpy::PyReadonlyArray1<'_, f64>,
    ) -> PyResult<()> {
        use cooploc::estimation::WheelSample;
        let t = time_us(t_s)?;
        let (speed, yaw_rate) = (speed.as_array(), yaw_rate.as_array());
        let n = self.ids.len();
        if speed.len() != n || yaw_rate.len() != n {
            return Err(PyValueError::new_err(format!(
                "speed of {} and yaw_rate of {} values for {n} robots",
                speed.len(),
                yaw_rate.len()
            )));
        }
        if !speed.iter().chain(yaw_rate.iter()).all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("a speed or yaw rate is not finite"));
        }
        // every robot stepped on a copy first, so that an error leaves the team as it was
        let mut stepped = Vec::with_capacity(n);
        for (k, &id) in self.ids.iter().enumerate() {
            let mut f = self.team.filter(id).expect("a member").clone();
            let sample = WheelSample { t, speed_m_s: speed[k], yaw_rate_rad_s: yaw_rate[k] };
            f.propagate(&sample).map_err(|e| PyValueError::new_err(format!("robot {id}: {e}")))?;
            stepped.push(f);
        }
        for (&id, f) in self.ids.iter().zip(stepped) {
            *self.team.filter_mut(id).expect("a member") = f;
        }
        Ok(())
    }

    /// One epoch of horizontal ranges between robots: `pairs` an (m, 2) integer array of
    /// (from, to) platform ids, `ranges` (m,) in metres, each with standard deviation `sigma_m`.
    /// Returns the joint update's NIS (None for dead reckoning and covariance intersection).
    fn ranges(
        &mut self,
        pairs: numpy::PyReadonlyArray2<'_, i64>,
        ranges: numpy::PyReadonlyArray1<'_, f64>,
        sigma_m: f64,
    ) -> PyResult<Option<f64>> {
        use cooploc::estimation::CoopMeasurement;
        let (pairs, ranges) = (pairs.as_array(), ranges.as_array());
        if pairs.ncols() != 2 || pairs.nrows() != ranges.len() {
            return Err(PyValueError::new_err(format!(
                "pairs of shape {:?} and {} ranges: (m, 2) and (m,) expected",
                pairs.shape(),
                ranges.len()
            )));
        }
        if !(sigma_m.is_finite() && sigma_m > 0.0) {
            return Err(PyValueError::new_err(format!("sigma_m {sigma_m}: positive")));
        }
        let id = |v: i64| team_member(&self.ids, v);
        let mut measurements = Vec::with_capacity(ranges.len());
        for (k, &range_m) in ranges.iter().enumerate() {
            let (from, to) = (id(pairs[(k, 0)])?, id(pairs[(k, 1)])?);
            if from == to || !(range_m.is_finite() && range_m >= 0.0) {
                return Err(PyValueError::new_err(format!("range {k}: {from} to {to}, {range_m} m")));
            }
            measurements.push(CoopMeasurement::PlanarRange { from, to, range_m, sigma_m });
        }
        let d = self.team.cooperative_event(&measurements).map_err(estimation_error)?;
        Ok(d.map(|d| d.nis))
    }

    /// The robots' poses, an (n, 3) array of [north m, east m, yaw rad] in the order of `ids`.
    fn poses<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, numpy::PyArray2<f64>>> {
        use numpy::IntoPyArray;
        let flat: Vec<f64> = self
            .ids
            .iter()
            .flat_map(|&id| {
                let s = self.team.filter(id).expect("a member").state();
                [s.pos_ned_m[0], s.pos_ned_m[1], s.yaw_rad]
            })
            .collect();
        flat.into_pyarray(py).reshape([self.ids.len(), 3])
    }

    /// Each robot's error covariance, an (n, 3, 3) array over [north, east, yaw].
    fn covariances<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, numpy::PyArray3<f64>>> {
        use cooploc::estimation::PlatformFilter;
        use numpy::IntoPyArray;
        let flat: Vec<f64> = self
            .ids
            .iter()
            .flat_map(|&id| self.team.filter(id).expect("a member").covariance().transpose().as_slice().to_vec())
            .collect();
        flat.into_pyarray(py).reshape([self.ids.len(), 3, 3])
    }

    #[getter]
    fn ids(&self) -> Vec<u16> {
        self.ids.clone()
    }

    #[getter]
    fn method(&self) -> &'static str {
        self.team.method().short_name()
    }
}

/// One run of a simulated scenario as numpy arrays, what `cooploc experiment` feeds its filters
/// (`sitl::World::run_inputs`, `World::ranges`, `experiment::initial_state`): `scenario` a
/// scenario file (`sitl/scenarios/paper.toml`), `seed` and `run` the draw, `schedule` one of its
/// ranging schedules. Returns a dict: `ids`; `platforms`, one dict per platform in id order with
/// its initial estimate (`t0_s`, `position_ned_m` (3,), `velocity_ned_m_s` (3,), `attitude_wxyz`
/// (4,), body FRD to NED), its IMU samples (`imu_t_s` (k,), `specific_force_frd_m_s2` (k, 3),
/// `angular_rate_frd_rad_s` (k, 3)), odometer samples (`odometer_t_s`, `speed_m_s`) and truth
/// (`truth_t_s`, `truth_position_ned_m` (k, 3)); `epochs`, one `(t_s, pairs (m, 2), ranges_m (m,),
/// sigma_m (m,))` per ranging epoch; `ins_config` and `initial_sigma`, the filter's settings as
/// dicts ([`InsTeam`] takes them). A planar robot's platform has no IMU: such a scenario is
/// refused (`ValueError`), as is a bad file, schedule or run.
#[pyfunction]
#[pyo3(signature = (scenario, seed = 1, run = 0, schedule = "1hz"))]
fn scenario_run<'py>(
    py: Python<'py>,
    scenario: std::path::PathBuf,
    seed: u64,
    run: u32,
    schedule: &str,
) -> PyResult<Bound<'py, PyDict>> {
    use cooploc::estimation::nav::NavModel;
    use numpy::IntoPyArray;
    let bad = |e: &dyn std::fmt::Display| PyValueError::new_err(format!("{}: {e}", scenario.display()));
    let sc = cooploc::sitl::scenario::Scenario::from_path(&scenario).map_err(|e| bad(&e))?;
    let world = cooploc::sitl::world::World::new(&sc).map_err(|e| bad(&e))?;
    let epochs = world.ranges(schedule, seed, run).map_err(|e| bad(&e))?;
    let inputs = world.run_inputs(seed, run);
    let ids = world.platform_ids();
    let mut settings = None;
    let platforms = pyo3::types::PyList::empty(py);
    for p in &inputs.platforms {
        let NavModel::Ins { config, initial_sigma } = cooploc::experiment::nav_model(&world, p.id) else {
            return Err(bad(&format!("platform {} is a planar robot (no IMU): InsTeam runs INS platforms", p.id)));
        };
        // (InsTeam takes one setting for the whole team: a scenario whose vehicles differ is refused)
        if settings.get_or_insert((config, initial_sigma)) != &(config, initial_sigma) {
            return Err(bad(&format!("platform {} has other IMU settings than the first: InsTeam takes one for all", p.id)));
        }
        let (t0, state) = cooploc::experiment::initial_state(&world, seed, run, p.id).map_err(|e| bad(&e))?;
        let q = state.att_frd_to_ned.into_inner();
        let d = PyDict::new(py);
        d.set_item("id", p.id)?;
        d.set_item("t0_s", t0.as_secs_f64())?;
        d.set_item("position_ned_m", state.pos_ned_m.as_slice().to_vec().into_pyarray(py))?;
        d.set_item("velocity_ned_m_s", state.vel_ned_m_s.as_slice().to_vec().into_pyarray(py))?;
        d.set_item("attitude_wxyz", vec![q.w, q.i, q.j, q.k].into_pyarray(py))?;
        let times = |t: &mut dyn Iterator<Item = cooploc::time::TimeUs>| t.map(|t| t.as_secs_f64()).collect::<Vec<f64>>();
        let rows = |v: Vec<f64>, n: usize| v.into_pyarray(py).reshape([n, 3]);
        let k = p.imu.len();
        d.set_item("imu_t_s", times(&mut p.imu.iter().map(|s| s.t)).into_pyarray(py))?;
        d.set_item(
            "specific_force_frd_m_s2",
            rows(p.imu.iter().flat_map(|s| s.specific_force_frd_m_s2.iter().copied()).collect(), k)?,
        )?;
        d.set_item(
            "angular_rate_frd_rad_s",
            rows(p.imu.iter().flat_map(|s| s.angular_rate_frd_rad_s.iter().copied()).collect(), k)?,
        )?;
        d.set_item("odometer_t_s", times(&mut p.odometer.iter().map(|s| s.t)).into_pyarray(py))?;
        d.set_item("speed_m_s", p.odometer.iter().map(|s| s.speed_m_s).collect::<Vec<f64>>().into_pyarray(py))?;
        d.set_item("truth_t_s", times(&mut p.truth.iter().map(|s| s.t)).into_pyarray(py))?;
        d.set_item(
            "truth_position_ned_m",
            rows(p.truth.iter().flat_map(|s| s.pos_ned_m.iter().copied()).collect(), p.truth.len())?,
        )?;
        platforms.append(d)?;
    }
    let out = PyDict::new(py);
    out.set_item("ids", ids)?;
    out.set_item("platforms", platforms)?;
    let list = pyo3::types::PyList::empty(py);
    for (t, samples) in &epochs {
        let pairs: Vec<i64> = samples.iter().flat_map(|r| [i64::from(r.from), i64::from(r.to)]).collect();
        let pairs = pairs.into_pyarray(py).reshape([samples.len(), 2])?;
        let ranges: Vec<f64> = samples.iter().map(|r| r.range_m).collect();
        let sigmas: Vec<f64> = samples.iter().map(|r| r.sigma_m).collect();
        list.append((t.as_secs_f64(), pairs, ranges.into_pyarray(py), sigmas.into_pyarray(py)))?;
    }
    out.set_item("epochs", list)?;
    if let Some((config, sigma)) = settings {
        let json = py.import("json")?;
        let to_dict = |v: String| json.call_method1("loads", (v,));
        out.set_item("ins_config", to_dict(serde_json::to_string(&config).map_err(|e| bad(&e))?)?)?;
        out.set_item("initial_sigma", to_dict(serde_json::to_string(&sigma).map_err(|e| bad(&e))?)?)?;
    }
    Ok(out)
}

/// A dict of settings (`ins_config`, `initial_sigma`) read as the library's type: through JSON,
/// so that a missing, unknown or mistyped field is named in the `ValueError`.
fn settings_text(py: Python<'_>, d: &Bound<'_, PyDict>) -> PyResult<String> {
    py.import("json")?.call_method1("dumps", (d,))?.extract()
}

/// A team of INS vehicles (the paper's model: 16 error states, IMU mechanization, odometer and
/// non-holonomic constraints; 3-D ranges, Eq. 11) under one method (`dr`, `naive`, `dcl`, `ci`,
/// `centralized`), stepped from numpy arrays: the estimation core of `cooploc experiment` and of
/// every node (`estimation::team::Team` of `estimation::nav::NavFilter`). `positions` (n, 3) and
/// `velocities` (n, 3) NED, `attitudes` (n, 4) quaternions [w, x, y, z] body FRD to NED; `ids`
/// their platform ids (1..=n when None); `ins_config` and `initial_sigma` dicts with every field of
/// `estimation::ins::InsConfig` and `InsInitialSigma` (as [`scenario_run`] gives them). Every
/// input is checked: a wrong shape, a non-finite value, time going backwards or an unknown id
/// raises `ValueError` and leaves the team as it was.
#[pyclass(name = "InsTeam", module = "cooploc._native")]
struct PyInsTeam {
    team: cooploc::estimation::team::Team<cooploc::estimation::nav::NavFilter>,
    ids: Vec<u16>,
}

/// Rows of an (n, 3) array as vectors, every value finite.
fn vectors3(what: &str, a: &numpy::PyReadonlyArray2<'_, f64>, n: usize) -> PyResult<Vec<Vector3<f64>>> {
    let a = a.as_array();
    if a.shape() != [n, 3] {
        return Err(PyValueError::new_err(format!("{what} of shape {:?}: ({n}, 3) expected", a.shape())));
    }
    if !a.iter().all(|v| v.is_finite()) {
        return Err(PyValueError::new_err(format!("{what}: a value is not finite")));
    }
    Ok(a.rows().into_iter().map(|r| Vector3::new(r[0], r[1], r[2])).collect())
}

impl PyInsTeam {
    /// The team's ids for `ids` (all, in order, when None), each once and a member.
    fn members(&self, ids: Option<Vec<u16>>) -> PyResult<Vec<u16>> {
        let Some(ids) = ids else { return Ok(self.ids.clone()) };
        for (k, id) in ids.iter().enumerate() {
            if !self.ids.contains(id) {
                return Err(PyValueError::new_err(format!("platform {id} is not in the team {:?}", self.ids)));
            }
            if ids[..k].contains(id) {
                return Err(PyValueError::new_err(format!("platform {id} given twice")));
            }
        }
        Ok(ids)
    }

    fn filter(&self, id: u16) -> &cooploc::estimation::nav::NavFilter {
        self.team.filter(id).expect("a member")
    }
}

#[pymethods]
impl PyInsTeam {
    #[new]
    #[pyo3(signature = (method, positions, velocities, attitudes, ins_config, initial_sigma, ids = None, t0_s = 0.0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        method: &str,
        positions: numpy::PyReadonlyArray2<'_, f64>,
        velocities: numpy::PyReadonlyArray2<'_, f64>,
        attitudes: numpy::PyReadonlyArray2<'_, f64>,
        ins_config: &Bound<'_, PyDict>,
        initial_sigma: &Bound<'_, PyDict>,
        ids: Option<Vec<u16>>,
        t0_s: f64,
    ) -> PyResult<Self> {
        use cooploc::estimation::ins::{InsConfig, InsInitialSigma, InsState};
        use cooploc::estimation::nav::{NavFilter, NavModel, NavState};
        let method = parse_methods(&[method.to_string()])?[0];
        let n = positions.as_array().nrows();
        if n == 0 {
            return Err(PyValueError::new_err("no vehicle: positions of shape (0, 3)"));
        }
        let pos = vectors3("positions", &positions, n)?;
        let vel = vectors3("velocities", &velocities, n)?;
        let att = attitudes.as_array();
        if att.shape() != [n, 4] || !att.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "attitudes of shape {:?}: ({n}, 4) finite [w, x, y, z] expected",
                att.shape()
            )));
        }
        let config: InsConfig = serde_json::from_str(&settings_text(py, ins_config)?)
            .map_err(|e| PyValueError::new_err(format!("ins_config: {e}")))?;
        let initial_sigma: InsInitialSigma = serde_json::from_str(&settings_text(py, initial_sigma)?)
            .map_err(|e| PyValueError::new_err(format!("initial_sigma: {e}")))?;
        let ids = ids.unwrap_or_else(|| (1..=n as u16).collect());
        if ids.len() != n {
            return Err(PyValueError::new_err(format!("{} ids for {n} vehicles", ids.len())));
        }
        let model = NavModel::Ins { config, initial_sigma };
        let t0 = time_us(t0_s)?;
        let mut members = Vec::with_capacity(n);
        for (k, &id) in ids.iter().enumerate() {
            let q = nalgebra::Quaternion::new(att[(k, 0)], att[(k, 1)], att[(k, 2)], att[(k, 3)]);
            if !(q.norm() > 0.5 && q.norm() < 2.0) {
                return Err(PyValueError::new_err(format!("attitude {k}: norm {} (a unit quaternion expected)", q.norm())));
            }
            let state = InsState {
                pos_ned_m: pos[k],
                vel_ned_m_s: vel[k],
                att_frd_to_ned: nalgebra::UnitQuaternion::from_quaternion(q),
                ..InsState::at_rest(nalgebra::UnitQuaternion::identity())
            };
            let filter = NavFilter::new(model, t0, NavState::Ins(state))
                .map_err(|e| PyValueError::new_err(format!("vehicle {id}: {e}")))?;
            members.push((id, filter));
        }
        let team = cooploc::estimation::team::Team::new(method, members).map_err(estimation_error)?;
        Ok(PyInsTeam { team, ids })
    }

    /// IMU samples at `t_s`: `specific_force` (k, 3) m/s^2 and `angular_rate` (k, 3) rad/s, body
    /// FRD, for the vehicles `ids` (all, in order, when None). A vehicle whose odometer or range
    /// falls between two IMU samples is brought to that time by a sample at it (a node holds the
    /// next sample's rates over the cut: give that sample with the cut's time).
    #[pyo3(signature = (t_s, specific_force, angular_rate, ids = None))]
    fn imu(
        &mut self,
        t_s: f64,
        specific_force: numpy::PyReadonlyArray2<'_, f64>,
        angular_rate: numpy::PyReadonlyArray2<'_, f64>,
        ids: Option<Vec<u16>>,
    ) -> PyResult<()> {
        use cooploc::estimation::ImuSample;
        use cooploc::estimation::nav::Drive;
        let t = time_us(t_s)?;
        let ids = self.members(ids)?;
        let f = vectors3("specific_force", &specific_force, ids.len())?;
        let w = vectors3("angular_rate", &angular_rate, ids.len())?;
        // every vehicle stepped on a copy first, so that an error leaves the team as it was
        let mut stepped = Vec::with_capacity(ids.len());
        for (k, &id) in ids.iter().enumerate() {
            let mut filter = self.filter(id).clone();
            let sample = ImuSample { t, specific_force_frd_m_s2: f[k], angular_rate_frd_rad_s: w[k] };
            filter.propagate(&Drive::Imu(sample)).map_err(|e| PyValueError::new_err(format!("vehicle {id}: {e}")))?;
            stepped.push(filter);
        }
        for (&id, filter) in ids.iter().zip(stepped) {
            *self.team.filter_mut(id).expect("a member") = filter;
        }
        Ok(())
    }

    /// Odometer speeds (m/s) at `t_s` for the vehicles `ids` (all, in order, when None), each
    /// vehicle already at `t_s` (its IMU sample at that time given). Applied as one batch, as the
    /// experiment applies one instant's (the centralized EKF stacks them).
    #[pyo3(signature = (t_s, speed, ids = None))]
    fn odometer(&mut self, t_s: f64, speed: numpy::PyReadonlyArray1<'_, f64>, ids: Option<Vec<u16>>) -> PyResult<()> {
        use cooploc::estimation::OdometerSample;
        let t = time_us(t_s)?;
        let ids = self.members(ids)?;
        let speed = speed.as_array();
        if speed.len() != ids.len() || !speed.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err(format!("{} speeds for {} vehicles, all finite expected", speed.len(), ids.len())));
        }
        let mut batch = Vec::with_capacity(ids.len());
        for (k, &id) in ids.iter().enumerate() {
            let f = self.filter(id);
            if f.time() != t {
                return Err(PyValueError::new_err(format!(
                    "vehicle {id} is at {} s, the odometer at {t_s} s: give its IMU sample at that time first",
                    f.time().as_secs_f64()
                )));
            }
            let m = f
                .odometer_measurement(&OdometerSample { t, speed_m_s: speed[k] })
                .map_err(|e| PyValueError::new_err(format!("vehicle {id}: {e}")))?;
            batch.push((id, m));
        }
        // (on a copy: a failed update leaves the team as it was)
        let mut team = self.team.clone();
        team.local_updates(&batch).map_err(estimation_error)?;
        self.team = team;
        Ok(())
    }

    /// One epoch of 3-D ranges (paper Eq. 11): `pairs` an (m, 2) integer array of (from, to)
    /// platform ids, `ranges` (m,) in metres, `sigma_m` (m,) their standard deviations; every
    /// vehicle of a pair already at the epoch's time. Returns the joint update's NIS (None for
    /// dead reckoning and covariance intersection).
    fn ranges(
        &mut self,
        pairs: numpy::PyReadonlyArray2<'_, i64>,
        ranges: numpy::PyReadonlyArray1<'_, f64>,
        sigma_m: numpy::PyReadonlyArray1<'_, f64>,
    ) -> PyResult<Option<f64>> {
        use cooploc::estimation::CoopMeasurement;
        let (pairs, ranges, sigma) = (pairs.as_array(), ranges.as_array(), sigma_m.as_array());
        if pairs.ncols() != 2 || pairs.nrows() != ranges.len() || sigma.len() != ranges.len() {
            return Err(PyValueError::new_err(format!(
                "pairs of shape {:?}, {} ranges and {} sigmas: (m, 2), (m,) and (m,) expected",
                pairs.shape(),
                ranges.len(),
                sigma.len()
            )));
        }
        let id = |v: i64| team_member(&self.ids, v);
        let mut measurements = Vec::with_capacity(ranges.len());
        for (k, (&range_m, &sigma_m)) in ranges.iter().zip(sigma.iter()).enumerate() {
            let (from, to) = (id(pairs[(k, 0)])?, id(pairs[(k, 1)])?);
            if from == to || !(range_m.is_finite() && range_m >= 0.0) || !(sigma_m.is_finite() && sigma_m > 0.0) {
                return Err(PyValueError::new_err(format!("range {k}: {from} to {to}, {range_m} m, sigma {sigma_m} m")));
            }
            measurements.push(CoopMeasurement::Range { from, to, range_m, sigma_m });
        }
        let mut team = self.team.clone();
        let d = team.cooperative_event(&measurements).map_err(estimation_error)?;
        self.team = team;
        Ok(d.map(|d| d.nis))
    }

    /// The vehicles' positions, an (n, 3) NED array in the order of `ids`, m.
    fn positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, numpy::PyArray2<f64>>> {
        use numpy::IntoPyArray;
        let flat: Vec<f64> = self.ids.iter().flat_map(|&id| self.filter(id).position_ned_m().as_slice().to_vec()).collect();
        flat.into_pyarray(py).reshape([self.ids.len(), 3])
    }

    /// Each vehicle's position error covariance, an (n, 3, 3) NED array, m^2.
    fn position_covariances<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, numpy::PyArray3<f64>>> {
        use cooploc::estimation::PlatformFilter;
        use numpy::IntoPyArray;
        let flat: Vec<f64> = self
            .ids
            .iter()
            .flat_map(|&id| {
                let p = self.filter(id).covariance();
                let mut block = Vec::with_capacity(9);
                for r in 0..3 {
                    block.extend((0..3).map(|c| p[(r, c)]));
                }
                block
            })
            .collect();
        flat.into_pyarray(py).reshape([self.ids.len(), 3, 3])
    }

    /// Each vehicle's filter time, s.
    fn times(&self) -> Vec<f64> {
        self.ids.iter().map(|&id| self.filter(id).time().as_secs_f64()).collect()
    }

    #[getter]
    fn ids(&self) -> Vec<u16> {
        self.ids.clone()
    }

    #[getter]
    fn method(&self) -> &'static str {
        self.team.method().short_name()
    }
}

/// Each vehicle's series in a cooploc log as numpy arrays (`recording::series`): a dict by
/// platform id of `estimate` and `truth` (`log_time_s` (n,), `position_ned_m` (n, 3), `yaw_rad`
/// (n,): the recorded poses in frame `ned`), `updates` (`log_time_s`, `epoch`, `t_s` (the epoch's
/// instant on the vehicle's clock), `participants`, `nis`, `nis_dof`, `nees` (NaN where the truth
/// was not known): the cooperative updates its node ran) and `undecodable`, the messages of those
/// topics that did not decode (left out). A cut log gives what is before the cut. `OSError` when
/// the file cannot be read, `ValueError` when it is not an MCAP file.
#[pyfunction]
fn log_series<'py>(py: Python<'py>, path: std::path::PathBuf) -> PyResult<Bound<'py, PyDict>> {
    use numpy::IntoPyArray;
    let log = open_log(&path)?;
    let secs = |ns: &[u64]| ns.iter().map(|&t| t as f64 / 1e9).collect::<Vec<f64>>().into_pyarray(py);
    let poses = |s: &cooploc::recording::series::PoseSeries| -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        d.set_item("log_time_s", secs(&s.log_time_ns))?;
        let flat: Vec<f64> = s.pos_ned_m.iter().flatten().copied().collect();
        d.set_item("position_ned_m", flat.into_pyarray(py).reshape([s.pos_ned_m.len(), 3])?)?;
        d.set_item("yaw_rad", s.yaw_rad.clone().into_pyarray(py))?;
        Ok(d)
    };
    let out = PyDict::new(py);
    for v in cooploc::recording::series::vehicle_series(&log) {
        let d = PyDict::new(py);
        d.set_item("estimate", poses(&v.estimate)?)?;
        d.set_item("truth", poses(&v.truth)?)?;
        let u = &v.updates;
        let updates = PyDict::new(py);
        updates.set_item("log_time_s", secs(&u.log_time_ns))?;
        updates.set_item("epoch", u.epoch.clone().into_pyarray(py))?;
        updates.set_item("t_s", u.t_us.iter().map(|&t| t as f64 / 1e6).collect::<Vec<f64>>().into_pyarray(py))?;
        updates.set_item("participants", u.participants.clone().into_pyarray(py))?;
        updates.set_item("nis", u.nis.clone().into_pyarray(py))?;
        updates.set_item("nis_dof", u.nis_dof.clone().into_pyarray(py))?;
        updates.set_item("nees", u.nees.clone().into_pyarray(py))?;
        d.set_item("updates", updates)?;
        d.set_item("undecodable", v.undecodable)?;
        out.set_item(v.id, d)?;
    }
    Ok(out)
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("CHI2_2DOF_95", consistency::CHI2_2DOF_95)?;
    m.add("EARTH_RADIUS_M", geodesy::EARTH_RADIUS_M)?;
    m.add_function(wrap_pyfunction!(ellipse95, m)?)?;
    m.add_function(wrap_pyfunction!(position_nees, m)?)?;
    m.add_function(wrap_pyfunction!(geo_to_ned, m)?)?;
    m.add_function(wrap_pyfunction!(ned_to_geo, m)?)?;
    m.add_function(wrap_pyfunction!(frames, m)?)?;
    m.add_function(wrap_pyfunction!(estimate_from_frame, m)?)?;
    m.add_function(wrap_pyfunction!(check_frame, m)?)?;
    m.add_function(wrap_pyfunction!(read_log, m)?)?;
    m.add_function(wrap_pyfunction!(mrclam, m)?)?;
    m.add_function(wrap_pyfunction!(experiment_json, m)?)?;
    m.add_class::<PySequenceTracker>()?;
    m.add_class::<PyEpochTally>()?;
    m.add_class::<PyRateWindow>()?;
    m.add_class::<PyTruthTrack>()?;
    m.add_class::<PyPlanarTeam>()?;
    m.add_class::<PyInsTeam>()?;
    m.add_function(wrap_pyfunction!(scenario_run, m)?)?;
    m.add_function(wrap_pyfunction!(log_series, m)?)?;
    m.add_function(wrap_pyfunction!(sim_state_from_frame, m)?)?;
    m.add_function(wrap_pyfunction!(replay, m)?)?;
    m.add_function(wrap_pyfunction!(compare_methods, m)?)?;
    m.add("MAX_REORDER", cooploc::protocol::sequence::MAX_REORDER)?;
    m.add("PALETTE", cooploc::view::PALETTE.map(|[r, g, b]| format!("{r:02x}{g:02x}{b:02x}")))?;
    Ok(())
}
