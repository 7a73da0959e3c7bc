//! What a node writes into its MCAP log besides the frames (see logs/README.md): its own events
//! (the clock ticks, initialisation and end of input its core saw: with the raw frames they let
//! `cooploc replay` call the core exactly as the node did), the metadata that rebuilds its core,
//! the attachment names, and its cooperative updates' internals ([`CoopUpdateRecord`], which the
//! core emits). The schema of the node's log, in one place beside the runner that writes it and
//! the replay that reads it; no I/O here.
//!
//! The structs are plain serde types: the runner serializes them, the replay deserializes the
//! same types. Every field is always present (an absent optional value is `null`). Floats must
//! be finite: JSON has no NaN (serde_json writes it as `null`, which then does not read back as
//! a number).

use crate::estimation::PlatformId;
use crate::estimation::ins::InsState;
use serde::{Deserialize, Serialize};

use crate::time::TimeUs;

use super::core::NodeConfig;

/// Topic of the node's own events (clock ticks given to the core, end of input), in JSON: with
/// the raw frames they let `cooploc replay` call the core exactly as the node did.
pub fn events_topic(id: PlatformId) -> String {
    format!("/vehicle_{id}/node/events")
}

/// Schema name of [`NodeEvent`] records.
pub const NODE_EVENT_SCHEMA_NAME: &str = "cooploc.NodeEvent";
/// JSON schema of [`NodeEvent`].
pub const NODE_EVENT_SCHEMA: &str = r#"{"type":"object","title":"cooploc.NodeEvent","properties":{"kind":{"type":"string","enum":["poll","end_of_input","run_pending","init"]},"wall_us":{"type":"integer"},"t0_us":{"type":"integer"},"origin":{"type":"array","items":{"type":"number"},"description":"latitude, longitude (deg) and altitude (m) of the origin, when it came from the vehicle"},"state":{"type":"object","description":"the start state, when it came from the autopilot's estimate: pos_ned_m, vel_ned_m_s, att_frd_to_ned (w, x, y, z)"}},"required":["kind"]}"#;

/// A start state in the node's log (the hand-over start's, which replay cannot rebuild from the
/// frames alone without the decoder's clock).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StartState {
    pub pos_ned_m: [f64; 3],
    pub vel_ned_m_s: [f64; 3],
    /// w, x, y, z.
    pub att_frd_to_ned: [f64; 4],
}

impl StartState {
    pub fn of(s: &InsState) -> Self {
        let q = s.att_frd_to_ned.quaternion();
        StartState { pos_ned_m: s.pos_ned_m.into(), vel_ned_m_s: s.vel_ned_m_s.into(), att_frd_to_ned: [q.w, q.i, q.j, q.k] }
    }

    /// The state (biases zero), exactly as logged.
    pub fn state(&self) -> InsState {
        let [w, i, j, k] = self.att_frd_to_ned;
        InsState {
            pos_ned_m: self.pos_ned_m.into(),
            vel_ned_m_s: self.vel_ned_m_s.into(),
            att_frd_to_ned: nalgebra::UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(w, i, j, k)),
            accel_bias_frd_m_s2: nalgebra::Vector3::zeros(),
            gyro_bias_frd_rad_s: nalgebra::Vector3::zeros(),
            odometer_scale_error: 0.0,
        }
    }
}

/// One call the runner made on its core other than `handle` (whose inputs are the frames).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NodeEvent {
    Poll {
        wall_us: u64,
    },
    EndOfInput,
    RunPending,
    /// The core was created at `t0_us` (from the SIM_STATE frame last recorded, when the
    /// metadata says so), about the vehicle's origin when it came from the vehicle.
    Init {
        t0_us: u64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        origin: Option<[f64; 3]>,
        /// The state it started from, when it came from the autopilot's estimate (the hand-over
        /// start): position and velocity NED, attitude quaternion w, x, y, z.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        state: Option<StartState>,
    },
    /// TIMESYNC gave a new mapping of the vehicle's boot clock to the companion's clock
    /// (companion time minus boot time, us, and the round trip of the answer it came from):
    /// the decoder took it from here on.
    Clock {
        offset_us: i64,
        rtt_us: i64,
    },
    /// The start state given with its time was refused as stale: the vehicle's first sample
    /// came long after it (`node::runner::STALE_START_US`); the node waited for SIM_STATE.
    StartRefused {
        given_t0_us: u64,
        vehicle_t_us: u64,
    },
    /// A range from the ranging device beside the vehicle link (`cooploc node --ranges`), as the
    /// core took it.
    Range {
        epoch: u32,
        range: crate::estimation::RangeSample,
    },
}

/// Name of the attachment holding node `id`'s vehicle profile in a log.
pub fn vehicle_attachment_name(id: PlatformId) -> String {
    format!("vehicle.{id}.toml")
}

/// Name of the metadata record describing node `id` in a log.
pub fn metadata_name(id: PlatformId) -> String {
    format!("cooploc.node.{id}")
}

/// What a log must hold to rebuild node `cfg`'s core (`cooploc replay`): the configuration and
/// how it started (the INS settings come from the scenario, attached to the log).
pub fn node_metadata(cfg: &NodeConfig, init: Option<(Option<TimeUs>, &InsState)>) -> std::collections::BTreeMap<String, String> {
    let mut m = std::collections::BTreeMap::new();
    m.insert("id".into(), cfg.id.to_string());
    m.insert("method".into(), cfg.method.short_name().into());
    m.insert("model".into(), cfg.model.name().into());
    m.insert("encoding".into(), cfg.encoding.name().to_string());
    m.insert("team".into(), cfg.team.iter().map(|p| p.to_string()).collect::<Vec<_>>().join(","));
    m.insert("epoch_timeout_us".into(), cfg.epoch_timeout_us.to_string());
    m.insert("retry_us".into(), cfg.retry_us.to_string());
    m.insert("retry_follows_cadence".into(), cfg.retry_follows_cadence.to_string());
    m.insert("history_us".into(), cfg.history_us.to_string());
    m.insert("max_lag_us".into(), cfg.max_lag_us.to_string());
    m.insert("range_grace_us".into(), cfg.range_grace_us.to_string());
    m.insert("max_lead_us".into(), cfg.max_lead_us.to_string());
    m.insert("gate_probability".into(), format!("{:e}", cfg.gate_probability));
    m.insert("independent_start".into(), cfg.independent_start.to_string());
    m.insert("echo_ranges".into(), cfg.echo_ranges.to_string());
    match init {
        Some((t0, state)) => {
            m.insert("init".into(), "state".into());
            // without a time, the state is taken at the first IMU or wheel sample (the Init event's)
            if let Some(t0) = t0 {
                m.insert("t0_us".into(), t0.0.to_string());
            }
            m.insert("initial_state".into(), serde_json::to_string(state).unwrap_or_default());
        }
        None => {
            m.insert("init".into(), "sim_state".into());
        }
    }
    m
}

/// Schema name of [`CoopUpdateRecord`] (`/vehicle_<id>/internals`).
pub const COOP_UPDATE_SCHEMA_NAME: &str = "cooploc.CoopUpdate";

/// One range of a cooperative update.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RangeRecord {
    /// Platform (system) id that measured.
    pub from: u16,
    /// Platform id that was ranged.
    pub to: u16,
    pub range_m: f64,
    pub sigma_m: f64,
}

/// One cooperative (joint) update, as the vehicle `vehicle` ran it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CoopUpdateRecord {
    /// Platform id of the vehicle whose node ran the update.
    pub vehicle: u16,
    /// Ranging epoch.
    pub epoch: u32,
    /// Filter time of the epoch, us (the vehicle's clock).
    pub t_us: u64,
    /// Platform ids of the participants, in broadcast order (the joint state's order).
    pub participants: Vec<u16>,
    /// The ranges used.
    pub ranges: Vec<RangeRecord>,
    /// Innovation `z - h(x)` of the stacked measurement (one entry per scalar measurement, in the
    /// order of `ranges` for range measurements), m.
    pub innovation: Vec<f64>,
    /// Square roots of the diagonal of the innovation covariance `S`, same order, m.
    pub innovation_sigma: Vec<f64>,
    /// Normalised innovation squared `r^T S^-1 r`.
    pub nis: f64,
    /// Its degrees of freedom (the number of scalar measurements).
    pub nis_dof: u32,
    /// Normalised estimation error squared of this vehicle's position after the update, when the
    /// truth is known (simulation).
    pub nees: Option<f64>,
    /// Degrees of freedom of `nees`.
    pub nees_dof: Option<u32>,
}

/// JSON schema (draft 2020-12) of [`CoopUpdateRecord`].
pub const COOP_UPDATE_SCHEMA: &str = r##"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "cooploc.CoopUpdate",
  "description": "One cooperative (joint) update of a cooploc node",
  "type": "object",
  "properties": {
    "vehicle": {"type": "integer", "minimum": 0, "maximum": 65535, "description": "platform id of the vehicle whose node ran the update"},
    "epoch": {"type": "integer", "minimum": 0, "description": "ranging epoch"},
    "t_us": {"type": "integer", "minimum": 0, "description": "filter time of the epoch, us"},
    "participants": {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 65535}, "description": "platform ids in broadcast order"},
    "ranges": {
      "type": "array",
      "items": {
        "type": "object",
        "properties": {
          "from": {"type": "integer", "minimum": 0, "maximum": 65535},
          "to": {"type": "integer", "minimum": 0, "maximum": 65535},
          "range_m": {"type": "number"},
          "sigma_m": {"type": "number"}
        },
        "required": ["from", "to", "range_m", "sigma_m"],
        "additionalProperties": false
      }
    },
    "innovation": {"type": "array", "items": {"type": "number"}, "description": "z - h(x) of the stacked measurement, m"},
    "innovation_sigma": {"type": "array", "items": {"type": "number"}, "description": "sqrt(diag S), m"},
    "nis": {"type": "number", "description": "normalised innovation squared"},
    "nis_dof": {"type": "integer", "minimum": 0},
    "nees": {"type": ["number", "null"], "description": "NEES of the own position when the truth is known"},
    "nees_dof": {"type": ["integer", "null"], "minimum": 0}
  },
  "required": ["vehicle", "epoch", "t_us", "participants", "ranges", "innovation", "innovation_sigma", "nis", "nis_dof", "nees", "nees_dof"],
  "additionalProperties": false
}"##;

/// Records one cooperative update on `/vehicle_<update.vehicle>/internals` (the runner's call,
/// and the tests').
pub fn record_update<W: std::io::Write>(
    rec: &mut crate::recording::Recorder<W>,
    wall_ns: u64,
    update: &CoopUpdateRecord,
) -> Result<(), crate::recording::RecorderError> {
    rec.json_message(
        &crate::recording::topics::internals(update.vehicle),
        COOP_UPDATE_SCHEMA_NAME,
        COOP_UPDATE_SCHEMA,
        wall_ns,
        update,
    )
}
