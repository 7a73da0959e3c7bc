//! Real data sets, as cooploc sees them: robots driven by their own motion inputs, observing
//! each other and known landmarks, with ground truth.
//!
//! - [`mrclam`]: the reader of the UTIAS Multi-Robot Cooperative Localization and Mapping data
//!   sets (Leung et al., IJRR 2011) into a [`Dataset`], with errors that name file and line.
//! - [`run`]: the model (a planar robot driven by its commanded speeds, range and bearing to
//!   teammates as cooperative measurements, to landmarks as local ones, chi-square gating) and
//!   every method over a data set in three regimes, scored against the ground truth. Pure
//!   computation.
//! - [`noise`]: the noise model (the figures in `mrclam_noise.toml` next to the reader) and how
//!   they are estimated from a data set against its ground truth.
//! - [`identify`]: the noise model identified from the data's own innovations (maximum
//!   likelihood), without the ground truth.
//! - [`log`]: a data set as a cooploc MCAP log (the same MAVLink frames and channels a node
//!   logs) and back.
//!
//! Frames: MRCLAM's world frame has x and y on the floor and angles counter-clockwise; cooploc
//! works in NED with yaw clockwise from north. The reader maps `N = x`, `E = -y`, `yaw = -theta`,
//! and likewise bearings and yaw rates change sign: a right-handed z-up frame seen as NED.

pub mod identify;
pub mod log;
pub mod mrclam;
pub mod noise;
pub mod run;

use crate::estimation::PlatformId;
use crate::time::TimeUs;

pub use crate::estimation::inputs::{Command, Target};

/// One camera observation: range and bearing of a target from the observer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    pub t: TimeUs,
    pub target: Target,
    pub range_m: f64,
    /// From the observer's heading, clockwise seen from above, rad.
    pub bearing_rad: f64,
}

/// A ground-truth pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthPose {
    pub t: TimeUs,
    pub n_m: f64,
    pub e_m: f64,
    /// Clockwise from north, rad.
    pub yaw_rad: f64,
}

/// A landmark of known position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Landmark {
    pub id: u16,
    pub n_m: f64,
    pub e_m: f64,
    /// Standard deviation of the surveyed position along N and E, m.
    pub sigma_n_m: f64,
    pub sigma_e_m: f64,
}

/// One robot's inputs and truth, each in time order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Robot {
    pub id: PlatformId,
    pub commands: Vec<Command>,
    pub observations: Vec<Observation>,
    pub truth: Vec<TruthPose>,
}

/// What the reader dropped or merged, per robot where it applies.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ImportCounts {
    /// Observations of a barcode not in the barcode table: (robot, barcode, count).
    pub unknown_barcodes: Vec<(PlatformId, u32, usize)>,
    /// Observations of a robot's own barcode, per robot.
    pub self_observations: Vec<(PlatformId, usize)>,
    /// Command rows that repeat the previous row's time (the later row is kept), per robot.
    pub repeated_command_times: Vec<(PlatformId, usize)>,
    /// Ground-truth rows that repeat the previous row's time (dropped), per robot.
    pub repeated_truth_times: Vec<(PlatformId, usize)>,
}

impl ImportCounts {
    pub fn unknown_barcode_total(&self) -> usize {
        self.unknown_barcodes.iter().map(|c| c.2).sum()
    }
    pub fn self_observation_total(&self) -> usize {
        self.self_observations.iter().map(|c| c.1).sum()
    }
}

/// A data set: robots, landmarks, and the span it covers.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// Its name (e.g. the folder's).
    pub name: String,
    /// The first ground-truth time of any robot: the filters start there, at the truth.
    pub t0: TimeUs,
    /// The last time of any record.
    pub t_end: TimeUs,
    pub robots: Vec<Robot>,
    pub landmarks: Vec<Landmark>,
    pub counts: ImportCounts,
}

impl Dataset {
    pub fn robot(&self, id: PlatformId) -> Option<&Robot> {
        self.robots.iter().find(|r| r.id == id)
    }

    pub fn landmark(&self, id: u16) -> Option<&Landmark> {
        self.landmarks.iter().find(|l| l.id == id)
    }

    /// The part of the data set in `[t0, t0 + seconds]` (a test excerpt): every record in it,
    /// the landmarks, the counts of the whole.
    /// The stretch from `from_s` to `to_s` seconds after the first ground-truth time: its
    /// commands (the one in force at the start moved to the start), observations and ground
    /// truth, `t0` at the start.
    pub fn window(&self, from_s: f64, to_s: f64) -> Dataset {
        let start = TimeUs(self.t0.0.saturating_add((from_s.max(0.0) * 1e6) as u64));
        let end = TimeUs(self.t0.0.saturating_add((to_s.max(0.0) * 1e6) as u64)).min(self.t_end);
        let robots = self
            .robots
            .iter()
            .map(|r| {
                let k = r.commands.partition_point(|c| c.t <= start);
                let mut commands: Vec<Command> =
                    r.commands[k.saturating_sub(1)..].iter().filter(|c| c.t <= end).copied().collect();
                if let Some(c) = commands.first_mut() {
                    c.t = c.t.max(start);
                }
                Robot {
                    id: r.id,
                    commands,
                    observations: r.observations.iter().filter(|o| o.t >= start && o.t <= end).copied().collect(),
                    truth: r.truth.iter().filter(|p| p.t >= start && p.t <= end).copied().collect(),
                }
            })
            .collect();
        Dataset { t0: start, t_end: end.max(start), robots, ..self.clone() }
    }

    pub fn excerpt(&self, seconds: f64) -> Dataset {
        let end = TimeUs(self.t0.0.saturating_add((seconds * 1e6) as u64));
        let robots = self
            .robots
            .iter()
            .map(|r| Robot {
                id: r.id,
                commands: r.commands.iter().filter(|c| c.t <= end).copied().collect(),
                observations: r.observations.iter().filter(|o| o.t <= end).copied().collect(),
                truth: r.truth.iter().filter(|p| p.t <= end).copied().collect(),
            })
            .collect();
        Dataset { t_end: end.min(self.t_end), robots, ..self.clone() }
    }
}

/// The ground truth of a robot at `t`, interpolated between the samples around it when they are
/// at most `max_gap_us` apart (None in a longer gap, before the first or after the last).
pub fn truth_at(truth: &[TruthPose], t: TimeUs, max_gap_us: u64) -> Option<TruthPose> {
    let k = truth.partition_point(|p| p.t < t);
    let after = truth.get(k)?;
    if after.t == t {
        return Some(*after);
    }
    let before = truth.get(k.checked_sub(1)?)?;
    if after.t.0 - before.t.0 > max_gap_us {
        return None;
    }
    let a = (t.0 - before.t.0) as f64 / (after.t.0 - before.t.0) as f64;
    let dyaw = crate::estimation::unicycle::wrap_angle(after.yaw_rad - before.yaw_rad);
    Some(TruthPose {
        t,
        n_m: before.n_m + a * (after.n_m - before.n_m),
        e_m: before.e_m + a * (after.e_m - before.e_m),
        yaw_rad: crate::estimation::unicycle::wrap_angle(before.yaw_rad + a * dyaw),
    })
}

/// Longest ground-truth gap interpolated over, µs: a longer gap is masked from scoring.
pub const MAX_TRUTH_GAP_US: u64 = 500_000;
