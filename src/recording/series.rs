//! A log's per-vehicle series as columns: the estimates (`/vehicle_<id>/pose`), the truth
//! (`/vehicle_<id>/truth_pose`) and the cooperative updates (`/vehicle_<id>/internals`), what a
//! plot or a notebook wants from a log without decoding its messages (`cooploc.log_series` in
//! Python). A message that does not decode is counted and left out, never a panic.

use std::collections::BTreeSet;

use foxglove::messages::PoseInFrame;

use super::reader::{Log, LoggedMessage};
use super::topics;
use crate::node::log::CoopUpdateRecord;

/// Poses in frame `ned`, one entry per message, in file order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PoseSeries {
    /// When the process recorded each, wall clock ns since the UNIX epoch.
    pub log_time_ns: Vec<u64>,
    pub pos_ned_m: Vec<[f64; 3]>,
    /// Yaw from north, clockwise seen from above, rad (the pose's orientation is a yaw).
    pub yaw_rad: Vec<f64>,
}

/// The cooperative updates a vehicle's node ran, one entry per update, in file order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct UpdateSeries {
    pub log_time_ns: Vec<u64>,
    pub epoch: Vec<u32>,
    /// The epoch's instant, the vehicle's clock, us.
    pub t_us: Vec<u64>,
    /// How many platforms took part.
    pub participants: Vec<u32>,
    pub nis: Vec<f64>,
    pub nis_dof: Vec<u32>,
    /// The vehicle's position NEES after the update (NaN where the truth was not known).
    pub nees: Vec<f64>,
}

/// One vehicle's series.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct VehicleSeries {
    pub id: u16,
    pub estimate: PoseSeries,
    pub truth: PoseSeries,
    pub updates: UpdateSeries,
    /// Messages of these topics that did not decode (left out).
    pub undecodable: u64,
}

/// Every vehicle of the log with a pose, truth or internals topic, in id order.
pub fn vehicle_series(log: &Log) -> Vec<VehicleSeries> {
    let ids: BTreeSet<u16> = log
        .channels
        .values()
        .filter_map(|c| c.topic.strip_prefix("/vehicle_")?.split_once('/'))
        .filter(|(_, rest)| ["pose", "truth_pose", "internals"].contains(rest))
        .filter_map(|(id, _)| id.parse().ok())
        .collect();
    ids.into_iter()
        .map(|id| {
            let mut v = VehicleSeries { id, ..VehicleSeries::default() };
            v.undecodable += poses(log.topic(&topics::pose(id)), &mut v.estimate);
            v.undecodable += poses(log.topic(&topics::truth_pose(id)), &mut v.truth);
            for m in log.topic(&topics::internals(id)) {
                match m.json::<CoopUpdateRecord>() {
                    Ok(u) => {
                        let s = &mut v.updates;
                        s.log_time_ns.push(m.log_time_ns);
                        s.epoch.push(u.epoch);
                        s.t_us.push(u.t_us);
                        s.participants.push(u.participants.len() as u32);
                        s.nis.push(u.nis);
                        s.nis_dof.push(u.nis_dof);
                        s.nees.push(u.nees.unwrap_or(f64::NAN));
                    }
                    Err(_) => v.undecodable += 1,
                }
            }
            v
        })
        .collect()
}

/// Appends the poses of `messages` to `out`; returns how many did not decode.
fn poses<'a>(messages: impl Iterator<Item = &'a LoggedMessage>, out: &mut PoseSeries) -> u64 {
    let mut bad = 0;
    for m in messages {
        let pose = m.protobuf::<PoseInFrame>().ok().and_then(|p| p.pose);
        let (Some(p), Some(q)) =
            (pose.as_ref().and_then(|p| p.position.as_ref()), pose.as_ref().and_then(|p| p.orientation.as_ref()))
        else {
            bad += 1;
            continue;
        };
        out.log_time_ns.push(m.log_time_ns);
        out.pos_ned_m.push([p.x, p.y, p.z]);
        out.yaw_rad.push(2.0 * q.z.atan2(q.w));
    }
    bad
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The committed demo log: three vehicles, each with its estimates, truth and updates; the
    /// poses read back as the recorder wrote them (the pose topic's last estimate is the one the
    /// recorder was given, its yaw a wrapped angle).
    #[test]
    fn the_demo_log_gives_three_vehicles_with_every_series() {
        let log = super::super::read_log(concat!(env!("CARGO_MANIFEST_DIR"), "/logs/demo-dcl-30s.mcap")).unwrap();
        let all = vehicle_series(&log);
        assert_eq!(all.iter().map(|v| v.id).collect::<Vec<_>>(), vec![1, 2, 3]);
        for v in &all {
            assert_eq!(v.undecodable, 0, "vehicle {}", v.id);
            assert_eq!(v.estimate.pos_ned_m.len(), log.topic(&topics::pose(v.id)).count());
            assert_eq!(v.truth.pos_ned_m.len(), log.topic(&topics::truth_pose(v.id)).count());
            assert_eq!(v.updates.epoch.len(), log.topic(&topics::internals(v.id)).count());
            assert!(!v.estimate.pos_ned_m.is_empty() && !v.truth.pos_ned_m.is_empty() && !v.updates.epoch.is_empty());
            assert!(v.estimate.yaw_rad.iter().chain(&v.truth.yaw_rad).all(|y| y.abs() <= std::f64::consts::PI + 1e-12));
            assert!(v.updates.epoch.windows(2).all(|w| w[0] < w[1]), "vehicle {}: epochs in order", v.id);
            assert!(v.updates.participants.iter().all(|&n| (1..=3).contains(&n)));
            // the estimate stays within a few metres of the truth in this 30 s demo
            let (e, t) = (v.estimate.pos_ned_m.last().unwrap(), v.truth.pos_ned_m.last().unwrap());
            assert!(((e[0] - t[0]).powi(2) + (e[1] - t[1]).powi(2)).sqrt() < 20.0, "vehicle {}: {e:?} vs {t:?}", v.id);
        }
    }

    /// A pose message that does not decode is counted and left out.
    #[test]
    fn an_undecodable_pose_is_counted_not_read() {
        let log = super::super::read_log(concat!(env!("CARGO_MANIFEST_DIR"), "/logs/demo-dcl-30s.mcap")).unwrap();
        let mut m = log.topic(&topics::pose(1)).next().unwrap().clone();
        m.data = vec![0xff; 7];
        let mut out = PoseSeries::default();
        assert_eq!(poses(std::iter::once(&m), &mut out), 1);
        assert!(out.pos_ned_m.is_empty());
    }
}
