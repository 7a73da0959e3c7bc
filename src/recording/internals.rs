//! Filter internals and link statistics: the JSON payloads of `/vehicle_<id>/internals` and
//! `/links/stats`, with their JSON schemas.
//!
//! The structs are plain serde types: the recorder serializes them, the ground station and the
//! replay deserialize the same types. Every field is always present (an absent optional value
//! is `null`). Floats must be finite: JSON has no NaN (serde_json writes it as `null`, which
//! then does not read back as a number).

use serde::{Deserialize, Serialize};

/// Schema name of `/vehicle_<id>/internals`.
pub const COOP_UPDATE_SCHEMA_NAME: &str = "cooploc.CoopUpdate";
/// Schema name of `/links/stats`.
pub const LINK_STATS_SCHEMA_NAME: &str = "cooploc.LinkStats";

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

/// Traffic with one peer over the last statistics window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PeerLinkStats {
    /// The peer's system id.
    pub sysid: u8,
    /// The link (URL or socket address) the peer is heard on.
    pub link: String,
    pub rx_packets: u64,
    pub tx_packets: u64,
    /// Packets missing from the peer's sequence numbers.
    pub lost_packets: u64,
    /// `lost / (received + lost)`, 0 when nothing was expected.
    pub loss_ratio: f64,
    pub rx_bytes_per_s: f64,
    pub tx_bytes_per_s: f64,
}

/// Link statistics of the recording process.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LinkStatsRecord {
    /// System id of the recording process.
    pub sysid: u8,
    /// Length of the window the counts and rates cover, s.
    pub window_s: f64,
    pub peers: Vec<PeerLinkStats>,
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

/// JSON schema (draft 2020-12) of [`LinkStatsRecord`].
pub const LINK_STATS_SCHEMA: &str = r##"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "cooploc.LinkStats",
  "description": "Per-peer traffic of a cooploc process over one statistics window",
  "type": "object",
  "properties": {
    "sysid": {"type": "integer", "minimum": 0, "maximum": 255, "description": "system id of the recording process"},
    "window_s": {"type": "number", "description": "window the counts and rates cover, s"},
    "peers": {
      "type": "array",
      "items": {
        "type": "object",
        "properties": {
          "sysid": {"type": "integer", "minimum": 0, "maximum": 255},
          "link": {"type": "string"},
          "rx_packets": {"type": "integer", "minimum": 0},
          "tx_packets": {"type": "integer", "minimum": 0},
          "lost_packets": {"type": "integer", "minimum": 0},
          "loss_ratio": {"type": "number", "minimum": 0, "maximum": 1},
          "rx_bytes_per_s": {"type": "number", "minimum": 0},
          "tx_bytes_per_s": {"type": "number", "minimum": 0}
        },
        "required": ["sysid", "link", "rx_packets", "tx_packets", "lost_packets", "loss_ratio", "rx_bytes_per_s", "tx_bytes_per_s"],
        "additionalProperties": false
      }
    }
  },
  "required": ["sysid", "window_s", "peers"],
  "additionalProperties": false
}"##;

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use serde_json::Value;

    pub(crate) fn sample_update() -> CoopUpdateRecord {
        CoopUpdateRecord {
            vehicle: 2,
            epoch: 17,
            t_us: 12_500_000,
            participants: vec![1, 2, 3],
            ranges: vec![
                RangeRecord { from: 2, to: 1, range_m: 25.5, sigma_m: 0.3 },
                RangeRecord { from: 2, to: 3, range_m: 40.25, sigma_m: 0.3 },
            ],
            innovation: vec![0.12, -0.4],
            innovation_sigma: vec![0.5, 0.6],
            nis: 1.75,
            nis_dof: 2,
            nees: Some(2.5),
            nees_dof: Some(3),
        }
    }

    pub(crate) fn sample_stats() -> LinkStatsRecord {
        LinkStatsRecord {
            sysid: 2,
            window_s: 1.0,
            peers: vec![PeerLinkStats {
                sysid: 1,
                link: "127.0.0.1:14601".into(),
                rx_packets: 50,
                tx_packets: 48,
                lost_packets: 2,
                loss_ratio: 2.0 / 52.0,
                rx_bytes_per_s: 4000.0,
                tx_bytes_per_s: 3900.0,
            }],
        }
    }

    /// Checks that every object of `value` has exactly the properties the schema lists, all of
    /// them required, and that the scalar types agree (a drift check between struct and schema).
    fn conforms(schema: &Value, value: &Value, path: &str) {
        let types: Vec<&str> = match &schema["type"] {
            Value::String(s) => vec![s.as_str()],
            Value::Array(a) => a.iter().map(|t| t.as_str().unwrap()).collect(),
            other => panic!("{path}: no type in schema: {other}"),
        };
        let actual = match value {
            Value::Null => "null",
            Value::Bool(_) => "boolean",
            Value::Number(n) if n.is_u64() || n.is_i64() => "integer",
            Value::Number(_) => "number",
            Value::String(_) => "string",
            Value::Array(_) => "array",
            Value::Object(_) => "object",
        };
        assert!(
            types.contains(&actual) || (actual == "integer" && types.contains(&"number")),
            "{path}: {actual} is not one of {types:?}"
        );
        match value {
            Value::Object(map) => {
                let props = schema["properties"].as_object().unwrap();
                let mut keys: Vec<&String> = map.keys().collect();
                let mut listed: Vec<&String> = props.keys().collect();
                let mut required: Vec<&str> =
                    schema["required"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
                keys.sort();
                listed.sort();
                required.sort();
                assert_eq!(keys, listed, "{path}: fields and schema properties differ");
                assert_eq!(keys.iter().map(|k| k.as_str()).collect::<Vec<_>>(), required, "{path}: not all required");
                for (k, v) in map {
                    conforms(&props[k], v, &format!("{path}.{k}"));
                }
            }
            Value::Array(items) => items.iter().for_each(|v| conforms(&schema["items"], v, &format!("{path}[]"))),
            _ => {}
        }
    }

    #[test]
    fn schemas_describe_the_structs() {
        let schema: Value = serde_json::from_str(COOP_UPDATE_SCHEMA).unwrap();
        let mut rec = sample_update();
        conforms(&schema, &serde_json::to_value(&rec).unwrap(), "update");
        rec.nees = None;
        rec.nees_dof = None;
        conforms(&schema, &serde_json::to_value(&rec).unwrap(), "update");
        let schema: Value = serde_json::from_str(LINK_STATS_SCHEMA).unwrap();
        conforms(&schema, &serde_json::to_value(sample_stats()).unwrap(), "stats");
    }

    #[test]
    fn records_round_trip_through_json() {
        let rec = sample_update();
        assert_eq!(serde_json::from_slice::<CoopUpdateRecord>(&serde_json::to_vec(&rec).unwrap()).unwrap(), rec);
        let st = sample_stats();
        assert_eq!(serde_json::from_slice::<LinkStatsRecord>(&serde_json::to_vec(&st).unwrap()).unwrap(), st);
    }
}
