//! The simulated vehicle's parameters, served with MAVLink's parameter protocol as an autopilot
//! serves its own: a ground station (MAVProxy, QGroundControl, Mission Planner) fetches them when
//! it connects (PARAM_REQUEST_LIST), reads one (PARAM_REQUEST_READ by name or index) and may try
//! to set one (PARAM_SET).
//!
//! The table describes the simulated vehicle honestly and is read-only: the simulator's
//! behaviour is set by its scenario, not by parameters. A PARAM_SET is answered, as ArduPilot and
//! PX4 answer a write they do not take, with a PARAM_VALUE holding the unchanged value, so the
//! ground station sees that nothing changed. Names follow the autopilot the vehicle behaves as
//! (`SYSID_THISMAV` for ArduPilot and cooploc, `MAV_SYS_ID` for PX4).

use super::personality::Autopilot;
use super::vehicle::VehicleConfig;
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{MavParamType, PARAM_VALUE_DATA};

/// One parameter: its name (at most 16 bytes), value and MAVLink type.
#[derive(Debug, Clone, PartialEq)]
pub struct Param {
    pub name: &'static str,
    pub value: f32,
    pub kind: MavParamType,
}

/// A vehicle's parameter table, in a fixed order (the indices a ground station sees).
#[derive(Debug, Clone, PartialEq)]
pub struct ParamTable {
    params: Vec<Param>,
}

/// What a parameter request asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParamQuery<'a> {
    /// Every parameter (PARAM_REQUEST_LIST).
    All,
    /// One, by name (PARAM_REQUEST_READ with index -1, or PARAM_SET).
    Name(&'a str),
    /// One, by index (PARAM_REQUEST_READ).
    Index(u16),
}

impl ParamTable {
    /// The table of a simulated vehicle.
    pub fn for_vehicle(config: &VehicleConfig, sysid: u8) -> ParamTable {
        use MavParamType::*;
        let p = |name, value: f64, kind| Param { name, value: value as f32, kind };
        let hz = |period_us: u64| if period_us == 0 { 0.0 } else { 1e6 / period_us as f64 };
        let mut params = match config.autopilot {
            Autopilot::Px4 => {
                vec![p("MAV_SYS_ID", f64::from(sysid), MAV_PARAM_TYPE_INT32), p("MAV_COMP_ID", 1.0, MAV_PARAM_TYPE_INT32)]
            }
            Autopilot::ArduPilot | Autopilot::Cooploc => {
                vec![p("SYSID_THISMAV", f64::from(sysid), MAV_PARAM_TYPE_INT16), p("SYSID_MYGCS", 255.0, MAV_PARAM_TYPE_INT16)]
            }
        };
        params.push(p(
            "SIM_IMU_HZ",
            if config.wheel_track_m.is_some() { 0.0 } else { hz(config.imu_period_us) },
            MAV_PARAM_TYPE_REAL32,
        ));
        params.push(p("SIM_ODOM_HZ", hz(config.odometer_period_us), MAV_PARAM_TYPE_REAL32));
        params.push(p("SIM_RANGE_HZ", config.range_period_us.map_or(0.0, hz), MAV_PARAM_TYPE_REAL32));
        params.push(p("SIM_GRAVITY", config.gravity_m_s2, MAV_PARAM_TYPE_REAL32));
        ParamTable { params }
    }

    pub fn len(&self) -> usize {
        self.params.len()
    }

    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    pub fn get(&self, name: &str) -> Option<&Param> {
        self.params.iter().find(|p| p.name == name)
    }

    /// The PARAM_VALUEs that answer `query` (none for an unknown name or index).
    pub fn answer(&self, query: ParamQuery<'_>) -> Vec<MavMessage> {
        let count = u16::try_from(self.params.len()).unwrap_or(u16::MAX);
        let value = |index: usize| {
            let p = &self.params[index];
            MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
                param_value: p.value,
                param_count: count,
                param_index: u16::try_from(index).unwrap_or(u16::MAX),
                param_id: p.name.into(),
                param_type: p.kind,
            })
        };
        match query {
            ParamQuery::All => (0..self.params.len()).map(value).collect(),
            ParamQuery::Name(name) => self.params.iter().position(|p| p.name == name).map(value).into_iter().collect(),
            ParamQuery::Index(i) => (usize::from(i) < self.params.len()).then(|| value(usize::from(i))).into_iter().collect(),
        }
    }
}

/// A MAVLink `param_id`: the bytes up to the first NUL (all 16 when there is none); `None` when
/// they are not UTF-8.
pub fn param_name(id: &[u8; 16]) -> Option<&str> {
    let len = id.iter().position(|&b| b == 0).unwrap_or(id.len());
    std::str::from_utf8(&id[..len]).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::wire::GeoOrigin;
    use crate::simulator::vehicle::StreamDefaults;

    fn config(autopilot: Autopilot) -> VehicleConfig {
        VehicleConfig {
            platform: 3,
            defaults: StreamDefaults::default(),
            origin: GeoOrigin { lat_deg: 34.7, lon_deg: 0.0, alt_m: 0.0 },
            gravity_m_s2: 9.8,
            odometer_sigma_m_s: 0.1,
            imu_period_us: 10_000,
            odometer_period_us: 100_000,
            range_period_us: Some(1_000_000),
            autopilot,
            wheel_track_m: None,
            unix_time: true,
            gnss: true,
            gnss_lost_at: None,
            gnss_back_at: None,
            gnss_glitch_m: None,
        }
    }

    fn fields(m: &MavMessage) -> (String, f32, u16, u16) {
        let MavMessage::PARAM_VALUE(v) = m else { panic!("not a PARAM_VALUE: {m:?}") };
        (param_name(&v.param_id).unwrap().to_string(), v.param_value, v.param_index, v.param_count)
    }

    #[test]
    fn a_list_request_gets_every_parameter_with_its_index_and_the_count() {
        let t = ParamTable::for_vehicle(&config(Autopilot::ArduPilot), 3);
        let all = t.answer(ParamQuery::All);
        assert_eq!(all.len(), t.len());
        for (i, m) in all.iter().enumerate() {
            let (_, _, index, count) = fields(m);
            assert_eq!((usize::from(index), usize::from(count)), (i, t.len()));
        }
        assert_eq!(fields(&all[0]), ("SYSID_THISMAV".to_string(), 3.0, 0, t.len() as u16));
        assert_eq!(t.get("SIM_IMU_HZ").unwrap().value, 100.0);
        assert_eq!(t.get("SIM_RANGE_HZ").unwrap().value, 1.0);
    }

    #[test]
    fn reads_by_name_and_index_and_nothing_for_unknown_ones() {
        let t = ParamTable::for_vehicle(&config(Autopilot::Px4), 3);
        assert_eq!(fields(&t.answer(ParamQuery::Name("MAV_SYS_ID"))[0]).1, 3.0);
        assert!(t.get("SYSID_THISMAV").is_none(), "PX4 names its system id MAV_SYS_ID");
        assert_eq!(fields(&t.answer(ParamQuery::Index(1))[0]).0, "MAV_COMP_ID");
        assert!(t.answer(ParamQuery::Name("NO_SUCH")).is_empty());
        assert!(t.answer(ParamQuery::Index(t.len() as u16)).is_empty());
    }

    #[test]
    fn param_names_stop_at_the_first_nul_or_take_all_sixteen_bytes() {
        let mut id = [0u8; 16];
        id[..4].copy_from_slice(b"ABCD");
        assert_eq!(param_name(&id), Some("ABCD"));
        assert_eq!(param_name(b"ABCDEFGHIJKLMNOP"), Some("ABCDEFGHIJKLMNOP"));
        id[0] = 0xff;
        assert_eq!(param_name(&id), None);
    }
}
