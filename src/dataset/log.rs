//! A data set as a cooploc MCAP log, and back.
//!
//! The log holds what each robot's node would have logged from its vehicle, on the same
//! channels ([`crate::recording`]): `/vehicle_<id>/mavlink/rx` carries, from system `<id>`,
//! each command as an ODOMETRY (body-frame `vx` and `yawspeed`, estimator type NAIVE: see
//! [`wire::command_to_odometry`]) and each observation as a COOPLOC_RANGE_BEARING (target kind
//! 0: a teammate, 1: a landmark). The ground truth is the simulator's truth channels
//! (`/vehicle_<id>/truth_pose`, and `/vehicle_<id>/truth` about a nominal geodetic origin at
//! UTIAS so that Foxglove's map shows it). Log times are the data's own times.
//!
//! Metadata `cooploc.dataset` says what the log is (name, kind, start, end, robots, what the
//! reader dropped), `cooploc.dataset.landmarks` holds the landmark map, `cooploc.dataset.view`
//! names the method and regime whose estimates the estimate channels show (when the import ran
//! one, for viewing: a replay recomputes everything from the inputs), and the attachment
//! `noise.toml` the noise model the import used ([`super::noise`]), so that a replay runs with
//! the figures the import was made with.

use std::collections::BTreeMap;
use std::path::Path;

use super::noise::NoiseModel;
use super::run::{Outcome, TrackPoint};
use super::{Command, Dataset, ImportCounts, Landmark, Observation, Robot, TruthPose};
use crate::estimation::PlatformId;
use crate::protocol::MavMessage;
use crate::protocol::wire::{self, GeoOrigin, RangeBearingReport};
use crate::recording::{Direction, Link, Log, PositionEstimate, Recorder, RecorderOptions, TruthSample, topics};
use crate::time::TimeUs;

/// Name of the metadata record that marks a data set log.
pub const DATASET_METADATA: &str = "cooploc.dataset";
/// Name of the metadata record with the landmark map.
pub const LANDMARKS_METADATA: &str = "cooploc.dataset.landmarks";
/// Longest span a data set log may claim, s (one week).
pub const MAX_SPAN_S: f64 = 7.0 * 86_400.0;
/// Name of the metadata record that says whose estimates the log shows.
pub const VIEW_METADATA: &str = "cooploc.dataset.view";
/// Name of the attachment with the noise model.
pub const NOISE_ATTACHMENT: &str = "noise.toml";
/// MAVLink component id of the frames (a camera-and-odometry source on the robot).
const COMPONENT: u8 = 1;
/// The nominal geodetic origin of the data set's floor (the University of Toronto Institute
/// for Aerospace Studies): only for the map views.
pub const UTIAS_ORIGIN: GeoOrigin = GeoOrigin { lat_deg: 43.782_2, lon_deg: -79.466_5, alt_m: 0.0 };

/// Why a log is not a usable data set log.
#[derive(Debug, thiserror::Error)]
pub enum DatasetLogError {
    #[error("the log is not a data set log (no {DATASET_METADATA} metadata)")]
    NotADataset,
    #[error("metadata {record}: {problem}")]
    Metadata { record: &'static str, problem: String },
    #[error("the log's {NOISE_ATTACHMENT}: {0}")]
    Noise(String),
    #[error("robot {robot}: {problem}")]
    Robot { robot: PlatformId, problem: String },
    #[error("writing the log: {0}")]
    Write(String),
}

fn counts_to_string(c: &ImportCounts) -> BTreeMap<String, String> {
    let join = |v: Vec<String>| v.join(",");
    BTreeMap::from([
        ("unknown_barcodes".into(), join(c.unknown_barcodes.iter().map(|(r, b, n)| format!("{r}:{b}:{n}")).collect())),
        ("self_observations".into(), join(c.self_observations.iter().map(|(r, n)| format!("{r}:{n}")).collect())),
        ("repeated_command_times".into(), join(c.repeated_command_times.iter().map(|(r, n)| format!("{r}:{n}")).collect())),
        ("repeated_truth_times".into(), join(c.repeated_truth_times.iter().map(|(r, n)| format!("{r}:{n}")).collect())),
    ])
}

/// Writes `ds` (and the noise model) as a log at `path`; with `view`, also that run's
/// estimates on the estimate channels (`/vehicle_<id>/pose`, `ellipse`, `location`), so that
/// Foxglove shows them beside the truth. A replay reads only the inputs.
pub fn write(ds: &Dataset, noise: &NoiseModel, path: &Path, view: Option<&Outcome>) -> Result<u64, DatasetLogError> {
    let w = |e: crate::recording::RecorderError| DatasetLogError::Write(e.to_string());
    let options = RecorderOptions { geo_origin: Some(UTIAS_ORIGIN), ..RecorderOptions::default() };
    let mut rec = Recorder::create(path, options).map_err(w)?;
    let robots: Vec<String> = ds.robots.iter().map(|r| r.id.to_string()).collect();
    let mut meta = BTreeMap::from([
        ("name".to_string(), ds.name.clone()),
        ("kind".to_string(), "mrclam".to_string()),
        ("t0_us".to_string(), ds.t0.0.to_string()),
        ("t_end_us".to_string(), ds.t_end.0.to_string()),
        ("robots".to_string(), robots.join(",")),
    ]);
    meta.extend(counts_to_string(&ds.counts));
    rec.metadata(DATASET_METADATA, meta).map_err(w)?;
    let landmarks = ds
        .landmarks
        .iter()
        .map(|l| (l.id.to_string(), format!("{:?},{:?},{:?},{:?}", l.n_m, l.e_m, l.sigma_n_m, l.sigma_e_m)))
        .collect();
    rec.metadata(LANDMARKS_METADATA, landmarks).map_err(w)?;
    let toml = toml::to_string(noise).map_err(|e| DatasetLogError::Write(e.to_string()))?;
    rec.attachment(NOISE_ATTACHMENT, "application/toml", toml.as_bytes()).map_err(w)?;
    if let Some(o) = view {
        let entries = BTreeMap::from([
            ("method".to_string(), o.method.short_name().to_string()),
            ("regime".to_string(), o.regime.name().to_string()),
        ]);
        rec.metadata(VIEW_METADATA, entries).map_err(w)?;
    }
    // Everything in time order, robot by robot at one instant.
    enum Item<'a> {
        Command(&'a Command),
        Observation(&'a Observation),
        Truth(&'a TruthPose),
        Estimate(&'a TrackPoint),
    }
    let mut items: Vec<(TimeUs, PlatformId, u8, Item)> = Vec::new();
    for r in &ds.robots {
        rec.declare_link(Link::Vehicle(r.id as u8), format!("dataset:{}/Robot{}", ds.name, r.id));
        items.extend(r.commands.iter().map(|c| (c.t, r.id, 0, Item::Command(c))));
        items.extend(r.observations.iter().map(|o| (o.t, r.id, 1, Item::Observation(o))));
        items.extend(r.truth.iter().map(|p| (p.t, r.id, 2, Item::Truth(p))));
    }
    for (id, track) in view.map(|o| &o.track[..]).unwrap_or_default() {
        items.extend(track.iter().map(|p| (p.t, *id, 3, Item::Estimate(p))));
    }
    items.sort_by_key(|(t, id, kind, _)| (*t, *id, *kind));
    let mut seq = vec![0u8; 256];
    for (t, id, _, item) in &items {
        let wall_ns = t.0.saturating_mul(1000);
        let msg = match item {
            Item::Truth(p) => {
                let truth = TruthSample { t: *t, pos_ned_m: nalgebra::Vector3::new(p.n_m, p.e_m, 0.0), yaw_rad: Some(p.yaw_rad) };
                rec.truth(*id, wall_ns, &truth).map_err(w)?;
                continue;
            }
            Item::Estimate(p) => {
                let mut cov = nalgebra::Matrix3::zeros();
                cov.fixed_view_mut::<2, 2>(0, 0).copy_from(&p.cov.fixed_view::<2, 2>(0, 0));
                let est = PositionEstimate {
                    t: p.t,
                    pos_ned_m: nalgebra::Vector3::new(p.n_m, p.e_m, 0.0),
                    cov_ned_m2: cov,
                    yaw_rad: Some(p.yaw_rad),
                    vel_ned_m_s: None,
                };
                rec.estimate(*id, wall_ns, &est).map_err(w)?;
                continue;
            }
            Item::Command(c) => wire::command_to_odometry(c),
            Item::Observation(o) => wire::range_bearing_to_message(&RangeBearingReport {
                t: o.t,
                observer: *id,
                target: o.target,
                range_m: o.range_m,
                bearing_rad: o.bearing_rad,
            }),
        };
        let s = &mut seq[usize::from(*id as u8)];
        *s = s.wrapping_add(1);
        let header = mavlink_core::MavHeader { system_id: u32::from(*id), component_id: COMPONENT, sequence: *s };
        rec.frame(Link::Vehicle(*id as u8), Direction::Rx, wall_ns, &wire::to_frame(header, &msg)).map_err(w)?;
    }
    let stats = rec.finish().map_err(w)?;
    Ok(stats.messages_written)
}

/// A data set read back from a log.
#[derive(Debug, Clone)]
pub struct LoggedDataset {
    pub dataset: Dataset,
    pub noise: NoiseModel,
    /// Frames on a robot's vehicle channel that were not a usable command or observation
    /// (undecodable, another system's, implausible), skipped.
    pub rejected_frames: usize,
}

fn meta_field<'a>(m: &'a BTreeMap<String, String>, record: &'static str, name: &str) -> Result<&'a str, DatasetLogError> {
    m.get(name).map(String::as_str).ok_or_else(|| DatasetLogError::Metadata { record, problem: format!("no field {name}") })
}

fn parse_counts(m: &BTreeMap<String, String>) -> ImportCounts {
    let pairs = |name: &str| -> Vec<(PlatformId, usize)> {
        m.get(name)
            .map(|s| {
                s.split(',')
                    .filter_map(|p| p.split_once(':'))
                    .filter_map(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
                    .collect()
            })
            .unwrap_or_default()
    };
    let unknown = m
        .get("unknown_barcodes")
        .map(|s| {
            s.split(',')
                .filter_map(|p| {
                    let mut it = p.split(':');
                    Some((it.next()?.parse().ok()?, it.next()?.parse().ok()?, it.next()?.parse().ok()?))
                })
                .collect()
        })
        .unwrap_or_default();
    ImportCounts {
        unknown_barcodes: unknown,
        self_observations: pairs("self_observations"),
        repeated_command_times: pairs("repeated_command_times"),
        repeated_truth_times: pairs("repeated_truth_times"),
    }
}

/// Whether the log is a data set log.
pub fn is_dataset_log(log: &Log) -> bool {
    log.metadata_named(DATASET_METADATA).is_some()
}

/// Reads a data set log (see the module documentation).
pub fn read(log: &Log) -> Result<LoggedDataset, DatasetLogError> {
    const META: &str = DATASET_METADATA;
    let m = &log.metadata_named(META).ok_or(DatasetLogError::NotADataset)?.entries;
    let bad = |problem: String| DatasetLogError::Metadata { record: META, problem };
    let t0 = TimeUs(meta_field(m, META, "t0_us")?.parse().map_err(|e| bad(format!("t0_us: {e}")))?);
    let t_end = TimeUs(meta_field(m, META, "t_end_us")?.parse().map_err(|e| bad(format!("t_end_us: {e}")))?);
    if t_end < t0 {
        return Err(bad(format!("t_end_us {} is before t0_us {}", t_end.0, t0.0)));
    }
    // A data set's span is hours at most; a longer one is damage (and would be scored at 10 Hz).
    if t_end.secs_since(t0) > MAX_SPAN_S {
        return Err(bad(format!("the span {} s is longer than {MAX_SPAN_S} s", t_end.secs_since(t0))));
    }
    let mut ids: Vec<PlatformId> = Vec::new();
    for s in meta_field(m, META, "robots")?.split(',') {
        let id: PlatformId = s.parse().map_err(|e| bad(format!("robots: {s:?}: {e}")))?;
        if id == 0 || id > 255 || ids.contains(&id) {
            return Err(bad(format!("robots: {id} is not a distinct system id 1-255")));
        }
        ids.push(id);
    }
    let lm = &log
        .metadata_named(LANDMARKS_METADATA)
        .ok_or(DatasetLogError::Metadata { record: LANDMARKS_METADATA, problem: "missing".into() })?
        .entries;
    let mut landmarks = Vec::new();
    for (id, v) in lm {
        let bad = |problem: String| DatasetLogError::Metadata {
            record: LANDMARKS_METADATA,
            problem: format!("landmark {id}: {problem}"),
        };
        let id: u16 = id.parse().map_err(|e| bad(format!("{e}")))?;
        let f: Vec<f64> =
            v.split(',').map(str::parse::<f64>).collect::<Result<_, _>>().map_err(|e| bad(format!("{v:?}: {e}")))?;
        if f.len() != 4 || f.iter().any(|x| !x.is_finite()) || f[2] < 0.0 || f[3] < 0.0 {
            return Err(bad(format!("{v:?}: expected four finite numbers n,e,sigma_n,sigma_e")));
        }
        landmarks.push(Landmark { id, n_m: f[0], e_m: f[1], sigma_n_m: f[2], sigma_e_m: f[3] });
    }
    landmarks.sort_by_key(|l| l.id);
    let noise_text = log
        .attachments
        .iter()
        .find(|a| a.name == NOISE_ATTACHMENT)
        .ok_or_else(|| DatasetLogError::Noise("missing".into()))
        .and_then(|a| std::str::from_utf8(&a.data).map_err(|e| DatasetLogError::Noise(e.to_string())))?;
    let noise = NoiseModel::from_toml_str(noise_text).map_err(DatasetLogError::Noise)?;
    let mut rejected = 0;
    let mut robots = Vec::new();
    for &id in &ids {
        let robot_err = |problem: String| DatasetLogError::Robot { robot: id, problem };
        let mut r = Robot { id, ..Robot::default() };
        for msg in log.topic(&topics::frames(Link::Vehicle(id as u8), Direction::Rx)) {
            let Ok((header, m)) = wire::from_any_frame(&msg.data) else {
                rejected += 1;
                continue;
            };
            if header.system_id != u32::from(id) {
                rejected += 1;
                continue;
            }
            match &m {
                MavMessage::ODOMETRY(o) => match wire::command_from_odometry(o) {
                    Ok(c) => r.commands.push(c),
                    Err(_) => rejected += 1,
                },
                MavMessage::COOPLOC_RANGE_BEARING(o) => match wire::range_bearing_from_message(o) {
                    Ok(rb) if rb.observer == id => r.observations.push(Observation {
                        t: rb.t,
                        target: rb.target,
                        range_m: rb.range_m,
                        bearing_rad: rb.bearing_rad,
                    }),
                    _ => rejected += 1,
                },
                _ => {}
            }
        }
        for msg in log.topic(&topics::truth_pose(id)) {
            let pose: foxglove::messages::PoseInFrame =
                msg.protobuf().map_err(|e| robot_err(format!("{}: {e}", topics::truth_pose(id))))?;
            let Some((p, q)) = pose.pose.and_then(|p| Some((p.position?, p.orientation?))) else {
                rejected += 1;
                continue;
            };
            let yaw = 2.0 * q.z.atan2(q.w);
            if ![p.x, p.y, yaw].iter().all(|v| v.is_finite()) {
                rejected += 1;
                continue;
            }
            let t = TimeUs(msg.log_time_ns / 1000);
            r.truth.push(TruthPose { t, n_m: p.x, e_m: p.y, yaw_rad: crate::estimation::unicycle::wrap_angle(yaw) });
        }
        // In time order, as the importer wrote them; a log edited out of order is refused.
        for (what, sorted) in [
            ("commands", r.commands.windows(2).all(|w| w[0].t < w[1].t)),
            ("observations", r.observations.windows(2).all(|w| w[0].t <= w[1].t)),
            ("ground truth", r.truth.windows(2).all(|w| w[0].t < w[1].t)),
        ] {
            if !sorted {
                return Err(robot_err(format!("its {what} are not in time order")));
            }
        }
        if r.truth.is_empty() {
            return Err(robot_err("no ground truth".into()));
        }
        robots.push(r);
    }
    let dataset =
        Dataset { name: meta_field(m, META, "name")?.to_string(), t0, t_end, robots, landmarks, counts: parse_counts(m) };
    Ok(LoggedDataset { dataset, noise, rejected_frames: rejected })
}
