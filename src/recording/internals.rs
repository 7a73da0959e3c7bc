//! Link statistics: the JSON payload of `/links/stats`, with its JSON schema. (A node's filter
//! internals, `/vehicle_<id>/internals`, are the node's: [`crate::node::log`].)
//!
//! The structs are plain serde types: the recorder serializes them, the ground station and the
//! replay deserialize the same types. Every field is always present (an absent optional value
//! is `null`). Floats must be finite: JSON has no NaN (serde_json writes it as `null`, which
//! then does not read back as a number).

use serde::{Deserialize, Serialize};

/// Schema name of `/links/stats`.
pub const LINK_STATS_SCHEMA_NAME: &str = "cooploc.LinkStats";

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

/// Records one cooperative update on `/vehicle_<update.vehicle>/internals` (the runner's call,
/// and the tests').
pub fn record_update<W: std::io::Write>(
    rec: &mut super::Recorder<W>,
    wall_ns: u64,
    update: &crate::node::log::CoopUpdateRecord,
) -> Result<(), super::RecorderError> {
    rec.json_message(
        &super::topics::internals(update.vehicle),
        crate::node::log::COOP_UPDATE_SCHEMA_NAME,
        crate::node::log::COOP_UPDATE_SCHEMA,
        wall_ns,
        update,
    )
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::node::log::{COOP_UPDATE_SCHEMA, CoopUpdateRecord, RangeRecord};
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
