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
pub const NODE_EVENT_SCHEMA: &str = r#"{"type":"object","title":"cooploc.NodeEvent","properties":{"kind":{"type":"string","enum":["poll","end_of_input","run_pending","init","clock","start_refused","restored","range"]},"wall_us":{"type":"integer"},"t0_us":{"type":"integer"},"origin":{"type":"array","items":{"type":"number"},"description":"latitude, longitude (deg) and altitude (m) of the origin, when it came from the vehicle"},"state":{"type":"object","description":"init: the start state, when it came from the autopilot's estimate: pos_ned_m, vel_ned_m_s, att_frd_to_ned (w, x, y, z); restored: the saved state the node started from (platform, t_us, origin, nominal, covariance)"}},"required":["kind"]}"#;

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
    /// The node started from the state it had saved (`cooploc node --state-file`), `age_us`
    /// older than the vehicle's first sample and carried across that gap: `state` is what the
    /// core was made from at its time (`state.t_us`).
    Restored {
        state: super::saved::SavedState,
        age_us: u64,
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

/// Name of the attachment holding the navigation state node `id` read from its state file at
/// the start (`cooploc node --state-file`, [`super::saved::SavedState::to_text`]): what a
/// replay offers its shell to restore, as the node's shell was offered it.
pub fn saved_state_attachment_name(id: PlatformId) -> String {
    format!("saved-state.{id}.txt")
}

/// Name of the metadata record describing node `id` in a log.
pub fn metadata_name(id: PlatformId) -> String {
    format!("cooploc.node.{id}")
}

/// How a logged node started: with a state given at the start (its time, or None: taken at the
/// first IMU or wheel sample, which the Init event says), or from what the vehicle sends
/// (SIM_STATE, or the autopilot's estimate when GNSS goes: the Init event holds it).
#[derive(Debug, Clone, PartialEq)]
pub enum LogStart {
    Given { t0: Option<TimeUs>, state: InsState },
    FromVehicle,
}

/// What a log holds about one node (metadata record `cooploc.node.<id>`), written and read by
/// this one type: the node's configuration (its navigation model comes from the vehicle profile
/// attached to the log, or the scenario), how it started, and its origin (None: the vehicle
/// gave it, and the Init event says which). Logs written before a field existed read with the
/// value the node then ran with.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeLogHeader {
    pub id: PlatformId,
    pub method: crate::estimation::Method,
    /// The navigation model's name (`NavModel::name`).
    pub model: String,
    pub encoding: crate::protocol::record::Encoding,
    pub team: Vec<PlatformId>,
    pub epoch_timeout_us: u64,
    pub retry_us: u64,
    pub retry_follows_cadence: bool,
    pub history_us: u64,
    pub max_lag_us: u64,
    /// These five: None in a log written before they existed (the node ran with the defaults
    /// of [`NodeConfig::for_model`]).
    pub range_grace_us: Option<u64>,
    pub max_lead_us: Option<u64>,
    pub gate_probability: Option<f64>,
    pub independent_start: Option<bool>,
    pub echo_ranges: Option<bool>,
    /// None in a log written before it existed: the node did not believe what a record said of
    /// its sender ([`NodeConfig::authenticated_peers`]).
    pub authenticated_peers: Option<bool>,
    /// None in a log written before they existed, and when the node ran without them: no
    /// schedule, no airtime slots ([`NodeConfig::epoch_period_us`], [`NodeConfig::slot_us`]).
    pub epoch_period_us: Option<u64>,
    pub slot_us: Option<u64>,
    /// None in a log written before it existed, and when the node ran without a range grid:
    /// own ranges at another instant refused ([`NodeConfig::range_snap_us`]).
    pub range_snap_us: Option<u64>,
    /// Whether the node started at its autopilot's hand-over (`cooploc node
    /// --init-from-autopilot`): None in a log written before it existed, where the Init event
    /// says it (it holds the autopilot's state).
    pub hand_over: Option<bool>,
    pub start: LogStart,
    pub origin: Option<crate::protocol::wire::GeoOrigin>,
}

/// A field of a node's log header that is missing or does not read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("field {field}: {problem}")]
pub struct HeaderError {
    pub field: String,
    pub problem: String,
}

impl NodeLogHeader {
    /// The header of a node configured as `cfg`, started as `start` (at the autopilot's
    /// hand-over or not), about `origin`.
    pub fn new(cfg: &NodeConfig, start: LogStart, hand_over: bool, origin: Option<crate::protocol::wire::GeoOrigin>) -> Self {
        NodeLogHeader {
            id: cfg.id,
            method: cfg.method,
            model: cfg.model.name().into(),
            encoding: cfg.encoding,
            team: cfg.team.clone(),
            epoch_timeout_us: cfg.epoch_timeout_us,
            retry_us: cfg.retry_us,
            retry_follows_cadence: cfg.retry_follows_cadence,
            history_us: cfg.history_us,
            max_lag_us: cfg.max_lag_us,
            range_grace_us: Some(cfg.range_grace_us),
            max_lead_us: Some(cfg.max_lead_us),
            gate_probability: Some(cfg.gate_probability),
            independent_start: Some(cfg.independent_start),
            echo_ranges: Some(cfg.echo_ranges),
            authenticated_peers: Some(cfg.authenticated_peers),
            epoch_period_us: cfg.epoch_period_us,
            slot_us: (cfg.slot_us > 0).then_some(cfg.slot_us),
            range_snap_us: (cfg.range_snap_us > 0).then_some(cfg.range_snap_us),
            hand_over: Some(hand_over),
            start,
            origin,
        }
    }

    /// The configuration the node ran with, on navigation model `model`.
    pub fn config(&self, model: crate::estimation::nav::NavModel) -> NodeConfig {
        let mut cfg = NodeConfig::for_model(self.id, self.method, model, self.encoding, self.team.clone());
        cfg.epoch_timeout_us = self.epoch_timeout_us;
        cfg.retry_us = self.retry_us;
        cfg.retry_follows_cadence = self.retry_follows_cadence;
        cfg.history_us = self.history_us;
        cfg.max_lag_us = self.max_lag_us;
        cfg.range_grace_us = self.range_grace_us.unwrap_or(cfg.range_grace_us);
        cfg.max_lead_us = self.max_lead_us.unwrap_or(cfg.max_lead_us);
        cfg.gate_probability = self.gate_probability.unwrap_or(cfg.gate_probability);
        cfg.independent_start = self.independent_start.unwrap_or(cfg.independent_start);
        cfg.echo_ranges = self.echo_ranges.unwrap_or(cfg.echo_ranges);
        cfg.authenticated_peers = self.authenticated_peers.unwrap_or(false);
        cfg.epoch_period_us = self.epoch_period_us;
        cfg.slot_us = self.slot_us.unwrap_or(0);
        cfg.range_snap_us = self.range_snap_us.unwrap_or(0);
        cfg
    }

    /// The metadata record's entries.
    pub fn to_metadata(&self) -> std::collections::BTreeMap<String, String> {
        let mut m = std::collections::BTreeMap::new();
        let mut put = |k: &str, v: String| {
            m.insert(k.to_string(), v);
        };
        put("id", self.id.to_string());
        put("method", self.method.short_name().into());
        put("model", self.model.clone());
        put("encoding", self.encoding.name().to_string());
        put("team", self.team.iter().map(|p| p.to_string()).collect::<Vec<_>>().join(","));
        put("epoch_timeout_us", self.epoch_timeout_us.to_string());
        put("retry_us", self.retry_us.to_string());
        put("retry_follows_cadence", self.retry_follows_cadence.to_string());
        put("history_us", self.history_us.to_string());
        put("max_lag_us", self.max_lag_us.to_string());
        if let Some(v) = self.range_grace_us {
            put("range_grace_us", v.to_string());
        }
        if let Some(v) = self.max_lead_us {
            put("max_lead_us", v.to_string());
        }
        if let Some(v) = self.gate_probability {
            put("gate_probability", format!("{v:e}"));
        }
        if let Some(v) = self.independent_start {
            put("independent_start", v.to_string());
        }
        if let Some(v) = self.echo_ranges {
            put("echo_ranges", v.to_string());
        }
        if let Some(v) = self.authenticated_peers {
            put("authenticated_peers", v.to_string());
        }
        if let Some(v) = self.epoch_period_us {
            put("epoch_period_us", v.to_string());
        }
        if let Some(v) = self.range_snap_us {
            put("range_snap_us", v.to_string());
        }
        if let Some(v) = self.slot_us {
            put("slot_us", v.to_string());
        }
        if let Some(v) = self.hand_over {
            put("hand_over", v.to_string());
        }
        match &self.start {
            LogStart::Given { t0, state } => {
                put("init", "state".into());
                if let Some(t0) = t0 {
                    put("t0_us", t0.0.to_string());
                }
                put("initial_state", serde_json::to_string(state).unwrap_or_default());
            }
            LogStart::FromVehicle => put("init", "sim_state".into()),
        }
        match &self.origin {
            Some(o) => {
                put("origin_lat_deg", o.lat_deg.to_string());
                put("origin_lon_deg", o.lon_deg.to_string());
                put("origin_alt_m", o.alt_m.to_string());
            }
            None => put("origin", "vehicle".into()),
        }
        m
    }

    /// Reads a metadata record's entries back; a field that is missing (where logs always had
    /// it) or does not read is named.
    pub fn from_metadata(m: &std::collections::BTreeMap<String, String>) -> Result<Self, HeaderError> {
        fn get<T: std::str::FromStr>(m: &std::collections::BTreeMap<String, String>, name: &str) -> Result<T, HeaderError>
        where
            T::Err: std::fmt::Display,
        {
            let bad = |problem: String| HeaderError { field: name.into(), problem };
            m.get(name).ok_or_else(|| bad("missing".into()))?.parse::<T>().map_err(|e| bad(e.to_string()))
        }
        // A field logs did not always have.
        fn opt<T: std::str::FromStr>(m: &std::collections::BTreeMap<String, String>, name: &str) -> Result<Option<T>, HeaderError>
        where
            T::Err: std::fmt::Display,
        {
            if m.contains_key(name) { get(m, name).map(Some) } else { Ok(None) }
        }
        let bad = |field: &str, problem: &str| HeaderError { field: field.into(), problem: problem.into() };
        let method_name: String = get(m, "method")?;
        let method = crate::estimation::Method::from_short_name(&method_name).ok_or_else(|| bad("method", &method_name))?;
        let encoding_name: String = get(m, "encoding")?;
        let encoding =
            crate::protocol::record::Encoding::from_name(&encoding_name).ok_or_else(|| bad("encoding", &encoding_name))?;
        let team_text: String = get(m, "team")?;
        let team = team_text
            .split(',')
            .map(|s| s.trim().parse::<PlatformId>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| bad("team", &format!("{team_text:?}: {e}")))?;
        let start = match get::<String>(m, "init")?.as_str() {
            "state" => {
                let t0 = if m.contains_key("t0_us") { Some(TimeUs(get(m, "t0_us")?)) } else { None };
                let text: String = get(m, "initial_state")?;
                let state = serde_json::from_str(&text).map_err(|e| bad("initial_state", &e.to_string()))?;
                LogStart::Given { t0, state }
            }
            "sim_state" => LogStart::FromVehicle,
            other => return Err(bad("init", &format!("{other:?}: expected state or sim_state"))),
        };
        let origin = if m.get("origin").is_some_and(|o| o == "vehicle") {
            None
        } else {
            Some(crate::protocol::wire::GeoOrigin {
                lat_deg: get(m, "origin_lat_deg")?,
                lon_deg: get(m, "origin_lon_deg")?,
                alt_m: opt(m, "origin_alt_m")?.unwrap_or(0.0),
            })
        };
        Ok(NodeLogHeader {
            id: get(m, "id")?,
            method,
            model: opt(m, "model")?.unwrap_or_default(),
            encoding,
            team,
            epoch_timeout_us: get(m, "epoch_timeout_us")?,
            retry_us: get(m, "retry_us")?,
            // logs written before the retry interval followed the cadence: a fixed interval
            retry_follows_cadence: opt(m, "retry_follows_cadence")?.unwrap_or(false),
            history_us: get(m, "history_us")?,
            max_lag_us: get(m, "max_lag_us")?,
            range_grace_us: opt(m, "range_grace_us")?,
            max_lead_us: opt(m, "max_lead_us")?,
            gate_probability: opt(m, "gate_probability")?,
            independent_start: opt(m, "independent_start")?,
            echo_ranges: opt(m, "echo_ranges")?,
            authenticated_peers: opt(m, "authenticated_peers")?,
            epoch_period_us: opt(m, "epoch_period_us")?,
            slot_us: opt(m, "slot_us")?,
            range_snap_us: opt(m, "range_snap_us")?,
            hand_over: opt(m, "hand_over")?,
            start,
            origin,
        })
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> NodeLogHeader {
        let state = InsState {
            pos_ned_m: nalgebra::Vector3::new(1.0, -2.5, 0.25),
            vel_ned_m_s: nalgebra::Vector3::new(0.5, 0.0, 0.0),
            att_frd_to_ned: nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
            accel_bias_frd_m_s2: nalgebra::Vector3::zeros(),
            gyro_bias_frd_rad_s: nalgebra::Vector3::zeros(),
            odometer_scale_error: 0.0,
        };
        NodeLogHeader {
            id: 2,
            method: crate::estimation::Method::Decentralized,
            model: "ins".into(),
            encoding: crate::protocol::record::Encoding::F64,
            team: vec![1, 2, 3],
            epoch_timeout_us: 2_000_000,
            retry_us: 100_000,
            retry_follows_cadence: true,
            history_us: 4_000_000,
            max_lag_us: 120_000_000,
            range_grace_us: Some(100_000),
            max_lead_us: Some(30_000_000),
            gate_probability: Some(1e-6),
            independent_start: Some(true),
            echo_ranges: Some(false),
            authenticated_peers: Some(true),
            epoch_period_us: Some(1_000_000),
            slot_us: Some(270_000),
            range_snap_us: Some(100_000),
            hand_over: Some(false),
            start: LogStart::Given { t0: Some(TimeUs(1_500_000)), state },
            origin: Some(crate::protocol::wire::GeoOrigin { lat_deg: 43.07, lon_deg: -79.5, alt_m: 12.5 }),
        }
    }

    #[test]
    fn a_node_log_header_reads_back_as_written() {
        let h = header();
        assert_eq!(NodeLogHeader::from_metadata(&h.to_metadata()).unwrap(), h);
        let from_vehicle = NodeLogHeader { start: LogStart::FromVehicle, origin: None, ..header() };
        let m = from_vehicle.to_metadata();
        assert_eq!((m["init"].as_str(), m["origin"].as_str()), ("sim_state", "vehicle"));
        assert_eq!(m["hand_over"], "false");
        assert_eq!(NodeLogHeader::from_metadata(&m).unwrap(), from_vehicle);
    }

    /// A log written before the later fields existed reads with what the node then ran with.
    #[test]
    fn an_old_node_log_header_reads_with_the_settings_of_its_time() {
        let mut m = header().to_metadata();
        for k in [
            "range_grace_us",
            "max_lead_us",
            "gate_probability",
            "independent_start",
            "echo_ranges",
            "authenticated_peers",
            "epoch_period_us",
            "slot_us",
            "range_snap_us",
            "hand_over",
            "retry_follows_cadence",
            "model",
            "origin_alt_m",
        ] {
            m.remove(k);
        }
        let h = NodeLogHeader::from_metadata(&m).unwrap();
        assert_eq!((h.range_grace_us, h.echo_ranges, h.retry_follows_cadence), (None, None, false));
        assert_eq!((h.authenticated_peers, h.hand_over), (None, None));
        let model = crate::estimation::nav::NavModel::Ins {
            config: crate::estimation::ins::InsConfig::default(),
            initial_sigma: crate::estimation::ins::InsInitialSigma::for_tests(),
        };
        let cfg = h.config(model);
        assert!(!cfg.authenticated_peers, "an old log's node believed no record");
        assert_eq!((cfg.epoch_period_us, cfg.slot_us), (None, 0), "nor kept a schedule");
        assert_eq!(cfg.range_snap_us, 0, "nor took an own range at another instant");
        assert_eq!(h.origin.unwrap().alt_m, 0.0);
    }

    #[test]
    fn a_bad_node_log_header_names_its_field() {
        let cases: [(&str, Option<&str>); 5] = [
            ("team", Some("1,x,3")),
            ("method", Some("kalman")),
            ("init", Some("guess")),
            ("retry_us", Some("-5")),
            ("epoch_timeout_us", None),
        ];
        for (field, value) in cases {
            let mut m = header().to_metadata();
            match value {
                Some(v) => m.insert(field.into(), v.into()),
                None => m.remove(field),
            };
            let err = NodeLogHeader::from_metadata(&m).unwrap_err();
            assert_eq!(err.field, field, "{err}");
        }
    }
}
