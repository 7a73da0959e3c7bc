//! The world of one scenario: its trajectories and sensor models, and the inputs of a run.

use std::sync::OnceLock;

use nalgebra::{UnitQuaternion, Vector3};

use super::scenario::{PlatformModel, Scenario, ScenarioError};
use super::sensors::{self, ImuStream, OdometerStream, SensorErrors, SensorModel, Stream, WheelStream};
use super::truth::{Earth, Trajectory, TruthState};
use crate::estimation::ins::InsState;
use crate::estimation::{ImuSample, OdometerSample, PlatformId, RangeSample, WheelSample};
use crate::time::TimeUs;

/// A validated scenario made into trajectories and sensor models. Cheap to query; every run is a
/// pure function of `(seed, run)`.
#[derive(Debug, Clone)]
pub struct World {
    scenario: Scenario,
    earth: Earth,
    model: SensorModel,
    /// In increasing id order.
    trajectories: Vec<Trajectory>,
    /// What a perfect IMU reports over each sample period of each trajectory (in trajectory
    /// order), computed by the first [`World::run_inputs`]: every run draws its sensor errors over
    /// the same truth, so a Monte Carlo study computes it once instead of once per run.
    imu_truth: OnceLock<Vec<Vec<ImuSample>>>,
}

/// One platform's inputs for one run.
#[derive(Debug, Clone, PartialEq)]
pub struct PlatformRun {
    pub id: PlatformId,
    /// The sensor errors drawn for this run.
    pub errors: SensorErrors,
    /// The sensor errors at the end of the run (the biases walk when a bias walk is configured).
    pub final_errors: SensorErrors,
    /// An INS platform's IMU and odometer samples (empty for a wheeled robot).
    pub imu: Vec<ImuSample>,
    pub odometer: Vec<OdometerSample>,
    /// A wheeled robot's wheel samples (empty for an INS platform).
    pub wheel: Vec<WheelSample>,
    /// Truth at `k / truth_rate_hz`, `k = 0..`, up to the end of the run, for error evaluation.
    pub truth: Vec<TruthState>,
}

/// Every platform's inputs for one run (ranging comes separately, per schedule:
/// [`World::ranges`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RunInputs {
    pub seed: u64,
    pub run: u32,
    /// In increasing id order.
    pub platforms: Vec<PlatformRun>,
}

/// A filter's initial estimate for one run: the truth at time zero plus errors drawn from the
/// scenario's `[initial]` sigmas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InitialEstimate {
    pub truth: TruthState,
    /// Estimate minus truth, per NED axis, m.
    pub pos_error_ned_m: Vector3<f64>,
    /// Estimate minus truth, per NED axis, m/s.
    pub vel_error_ned_m_s: Vector3<f64>,
    /// Estimate minus truth of roll, pitch and yaw, rad (truth has roll = pitch = 0).
    pub attitude_error_rad: Vector3<f64>,
}

impl InitialEstimate {
    pub fn pos_ned_m(&self) -> Vector3<f64> {
        self.truth.pos_ned_m + self.pos_error_ned_m
    }

    pub fn vel_ned_m_s(&self) -> Vector3<f64> {
        self.truth.vel_ned_m_s + self.vel_error_ned_m_s
    }

    /// Body->NED attitude with Euler angles (roll, pitch, yaw) = truth + error.
    pub fn attitude(&self) -> UnitQuaternion<f64> {
        let e = self.attitude_error_rad;
        UnitQuaternion::from_euler_angles(e[0], e[1], self.truth.yaw_rad + e[2])
    }

    /// The INS filter state this estimate starts: its position, velocity and attitude; zero
    /// biases and scale error.
    pub fn ins_state(&self) -> InsState {
        InsState {
            pos_ned_m: self.pos_ned_m(),
            vel_ned_m_s: self.vel_ned_m_s(),
            att_frd_to_ned: self.attitude(),
            accel_bias_frd_m_s2: Vector3::zeros(),
            gyro_bias_frd_rad_s: Vector3::zeros(),
            odometer_scale_error: 0.0,
        }
    }
}

/// One event of a run, in time order (see [`World::events`]).
#[derive(Debug, Clone, PartialEq)]
pub enum SimEvent {
    Imu(PlatformId, ImuSample),
    Odometer(PlatformId, OdometerSample),
    Wheel(PlatformId, WheelSample),
    /// All ranges of one epoch.
    Ranges(TimeUs, Vec<RangeSample>),
}

impl SimEvent {
    pub fn time(&self) -> TimeUs {
        match self {
            SimEvent::Imu(_, s) => s.t,
            SimEvent::Odometer(_, s) => s.t,
            SimEvent::Wheel(_, s) => s.t,
            SimEvent::Ranges(t, _) => *t,
        }
    }
}

impl World {
    /// Validates `scenario` and builds its world.
    pub fn new(scenario: &Scenario) -> Result<World, ScenarioError> {
        scenario.validate()?;
        let earth = Earth::new(scenario.latitude_deg, scenario.gravity_m_s2);
        let mut trajectories: Vec<Trajectory> = scenario.platforms.iter().map(|p| Trajectory::new(p, earth)).collect();
        trajectories.sort_by_key(|t| t.id());
        Ok(World {
            scenario: scenario.clone(),
            earth,
            model: SensorModel::from_scenario(scenario),
            trajectories,
            imu_truth: OnceLock::new(),
        })
    }

    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    pub fn earth(&self) -> &Earth {
        &self.earth
    }

    pub fn sensor_model(&self) -> &SensorModel {
        &self.model
    }

    /// The trajectories, in increasing id order.
    pub fn platforms(&self) -> &[Trajectory] {
        &self.trajectories
    }

    /// What platform `id` navigates with.
    pub fn platform_model(&self, id: PlatformId) -> PlatformModel {
        self.scenario.platforms.iter().find(|p| p.id == id).map_or(PlatformModel::Ins, |p| p.model)
    }

    /// Platform ids, increasing.
    pub fn platform_ids(&self) -> Vec<PlatformId> {
        self.trajectories.iter().map(|t| t.id()).collect()
    }

    pub fn trajectory(&self, id: PlatformId) -> Result<&Trajectory, ScenarioError> {
        self.trajectories.iter().find(|t| t.id() == id).ok_or(ScenarioError::UnknownPlatform(id))
    }

    /// End of the run.
    pub fn end(&self) -> TimeUs {
        self.model.end
    }

    /// The sensor errors platform `id` gets in run `run`.
    pub fn sensor_errors(&self, seed: u64, run: u32, id: PlatformId) -> Result<SensorErrors, ScenarioError> {
        self.trajectory(id)?;
        Ok(sensors::draw_errors(&self.model, seed, run, id))
    }

    /// Platform `id`'s IMU samples in run `run`, lazily.
    pub fn imu(&self, seed: u64, run: u32, id: PlatformId) -> Result<ImuStream<'_>, ScenarioError> {
        Ok(ImuStream::new(self.trajectory(id)?, &self.model, seed, run))
    }

    /// Platform `id`'s odometer samples in run `run`, lazily.
    pub fn odometer(&self, seed: u64, run: u32, id: PlatformId) -> Result<OdometerStream<'_>, ScenarioError> {
        Ok(OdometerStream::new(self.trajectory(id)?, &self.model, seed, run))
    }

    /// Platform `id`'s truth at `k / truth_rate_hz`, `k = 0..`, up to the end of the run.
    pub fn truth_samples(&self, id: PlatformId) -> Result<Vec<TruthState>, ScenarioError> {
        Ok(self.truth_of(self.trajectory(id)?))
    }

    fn truth_of(&self, traj: &Trajectory) -> Vec<TruthState> {
        let period = self.scenario.truth_period_us();
        (0..).map(|k| k * period).take_while(|&t| t <= self.end().0).map(|t| traj.truth_at(TimeUs(t))).collect()
    }

    /// All inputs of one run except ranging.
    pub fn run_inputs(&self, seed: u64, run: u32) -> RunInputs {
        let imu_truth = self.imu_truth.get_or_init(|| {
            let period = self.model.imu_period_us;
            let ends = (1..).map(|k| k * period).take_while(|&t| t <= self.model.end.0);
            let of = |traj: &Trajectory| ends.clone().map(|t| traj.imu_mean(TimeUs(t - period), TimeUs(t))).collect();
            self.trajectories
                .iter()
                .map(|traj| if self.platform_model(traj.id()) == PlatformModel::Planar { Vec::new() } else { of(traj) })
                .collect()
        });
        let platforms = self
            .trajectories
            .iter()
            .zip(imu_truth)
            .map(|(traj, imu_truth)| {
                let errors = sensors::draw_errors(&self.model, seed, run, traj.id());
                let truth = self.truth_of(traj);
                if self.platform_model(traj.id()) == PlatformModel::Planar {
                    let wheel = WheelStream::new(traj, &self.model, seed, run).collect();
                    let (imu, odometer) = (Vec::new(), Vec::new());
                    return PlatformRun { id: traj.id(), errors, final_errors: errors, imu, odometer, wheel, truth };
                }
                let mut stream = ImuStream::new(traj, &self.model, seed, run).over_truth(imu_truth);
                let imu: Vec<ImuSample> = stream.by_ref().collect();
                let (accel_bias_m_s2, gyro_bias_rad_s) = stream.biases();
                PlatformRun {
                    id: traj.id(),
                    errors,
                    final_errors: SensorErrors { accel_bias_m_s2, gyro_bias_rad_s, ..errors },
                    imu,
                    odometer: OdometerStream::new(traj, &self.model, seed, run).collect(),
                    wheel: Vec::new(),
                    truth,
                }
            })
            .collect();
        RunInputs { seed, run, platforms }
    }

    /// The ranges of one run under the named schedule: per epoch, one range per pair of platforms.
    pub fn ranges(&self, schedule: &str, seed: u64, run: u32) -> Result<Vec<(TimeUs, Vec<RangeSample>)>, ScenarioError> {
        let epochs = self.scenario.range_epochs(schedule)?;
        Ok(epochs
            .into_iter()
            .map(|t| (t, sensors::ranges_at(&self.trajectories, self.model.range_sigma_m, self.model.range_max_m, t, seed, run)))
            .collect())
    }

    /// Every sensor event of one run, merged in time order. At equal times, IMU and wheel
    /// samples come first (a filter propagates to `t` before it takes a measurement at `t`), then
    /// odometer samples, then the ranges; within a kind, increasing platform id. The samples are those of
    /// [`World::run_inputs`] and [`World::ranges`] for the same `(seed, run)`.
    pub fn events(&self, schedule: &str, seed: u64, run: u32) -> Result<SimEvents<'_>, ScenarioError> {
        let epochs = self.scenario.range_epochs(schedule)?;
        let ins = |t: &Trajectory| self.platform_model(t.id()) == PlatformModel::Ins;
        Ok(SimEvents {
            world: self,
            seed,
            run,
            imu: self.trajectories.iter().map(|t| ins(t).then(|| ImuStream::new(t, &self.model, seed, run))).collect(),
            odometer: self.trajectories.iter().map(|t| ins(t).then(|| OdometerStream::new(t, &self.model, seed, run))).collect(),
            wheel: self.trajectories.iter().map(|t| (!ins(t)).then(|| WheelStream::new(t, &self.model, seed, run))).collect(),
            epochs: epochs.into_iter().peekable(),
        })
    }

    /// The initial estimate a filter on platform `id` starts from in run `run`.
    pub fn initial_estimate(&self, seed: u64, run: u32, id: PlatformId) -> Result<InitialEstimate, ScenarioError> {
        self.estimate_drawn(seed, run, id, TimeUs(0), &[u64::from(id)])
    }

    /// An independent estimate of platform `id` at time `t` with the `[initial]` errors (a node
    /// started or restarted at `t` from the vehicle's own fix); `draw` tells apart several
    /// draws of one run.
    pub fn estimate_at(
        &self,
        seed: u64,
        run: u32,
        id: PlatformId,
        t: TimeUs,
        draw: u64,
    ) -> Result<InitialEstimate, ScenarioError> {
        self.estimate_drawn(seed, run, id, t, &[u64::from(id), t.0, draw])
    }

    fn estimate_drawn(
        &self,
        seed: u64,
        run: u32,
        id: PlatformId,
        t: TimeUs,
        key: &[u64],
    ) -> Result<InitialEstimate, ScenarioError> {
        let truth = self.trajectory(id)?.truth_at(t);
        let init = &self.scenario.initial;
        let mut rng = sensors::stream_rng(seed, run, Stream::Initial, key);
        let mut draw3 = |sigma: [f64; 3]| Vector3::from_fn(|k, _| sigma[k] * sensors::normal(&mut rng));
        let mut pos_error_ned_m = draw3([init.position_sigma_m; 3]);
        if self.platform_model(id) == PlatformModel::Planar {
            // a wheeled robot on level ground knows its height
            pos_error_ned_m[2] = 0.0;
        }
        let vel_error_ned_m_s = draw3([init.velocity_sigma_m_s; 3]);
        let rp = init.roll_pitch_sigma_deg.to_radians();
        let attitude_error_rad = draw3([rp, rp, init.yaw_sigma_deg.to_radians()]);
        Ok(InitialEstimate { truth, pos_error_ned_m, vel_error_ned_m_s, attitude_error_rad })
    }
}

/// The merged, time-ordered event stream of one run (from [`World::events`]), generated lazily.
#[derive(Debug, Clone)]
pub struct SimEvents<'a> {
    world: &'a World,
    seed: u64,
    run: u32,
    imu: Vec<Option<ImuStream<'a>>>,
    odometer: Vec<Option<OdometerStream<'a>>>,
    wheel: Vec<Option<WheelStream<'a>>>,
    epochs: std::iter::Peekable<std::vec::IntoIter<TimeUs>>,
}

impl Iterator for SimEvents<'_> {
    type Item = SimEvent;

    fn next(&mut self) -> Option<SimEvent> {
        // (time, kind, index): the smallest goes next; kind 0 = IMU or wheels (a platform has
        // one or the other), 1 = odometer, 2 = ranges.
        let peek = |i: usize| {
            let imu = self.imu[i].as_ref().and_then(|s| s.peek_time());
            imu.or_else(|| self.wheel[i].as_ref().and_then(|s| s.peek_time())).map(|t| (t, 0u8, i))
        };
        let drive = (0..self.imu.len()).filter_map(peek);
        let odo = self.odometer.iter().enumerate().filter_map(|(i, s)| s.as_ref()?.peek_time().map(|t| (t, 1u8, i)));
        let rng = self.epochs.peek().map(|&t| (t, 2u8, 0));
        let (t, kind, i) = drive.chain(odo).chain(rng).min()?;
        let ids = &self.world.trajectories;
        match kind {
            0 => match (&mut self.imu[i], &mut self.wheel[i]) {
                (Some(imu), _) => imu.next().map(|s| SimEvent::Imu(ids[i].id(), s)),
                (None, Some(wheel)) => wheel.next().map(|s| SimEvent::Wheel(ids[i].id(), s)),
                (None, None) => None,
            },
            1 => self.odometer[i].as_mut()?.next().map(|s| SimEvent::Odometer(ids[i].id(), s)),
            _ => {
                self.epochs.next();
                Some(SimEvent::Ranges(
                    t,
                    sensors::ranges_at(ids, self.world.model.range_sigma_m, self.world.model.range_max_m, t, self.seed, self.run),
                ))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sitl::scenario::PAPER_TOML;
    use crate::sitl::scenario::tests::SMALL;

    fn small() -> World {
        World::new(&Scenario::from_toml_str(SMALL).unwrap()).unwrap()
    }

    /// The perfect IMU computed once for every run gives every run the samples a stream
    /// computing it sample by sample gives, bit for bit, in the first run and in later ones.
    #[test]
    fn the_shared_imu_truth_changes_no_sample() {
        let world = small();
        for run in [0, 5] {
            let inputs = world.run_inputs(9, run);
            for (traj, p) in world.trajectories.iter().zip(&inputs.platforms) {
                let own: Vec<ImuSample> = ImuStream::new(traj, &world.model, 9, run).collect();
                assert!(!own.is_empty());
                assert_eq!(p.imu, own, "platform {}, run {run}", p.id);
            }
        }
        assert!(world.imu_truth.get().is_some_and(|t| t.iter().all(|v| !v.is_empty())));
    }

    #[test]
    fn runs_are_deterministic_and_runs_differ() {
        let world = small();
        let a = world.run_inputs(42, 3);
        assert_eq!(a, world.run_inputs(42, 3));
        assert_eq!(world.ranges("1hz", 42, 3).unwrap(), world.ranges("1hz", 42, 3).unwrap());
        let b = world.run_inputs(42, 4);
        let c = world.run_inputs(43, 3);
        for other in [&b, &c] {
            for (p, q) in a.platforms.iter().zip(&other.platforms) {
                assert_ne!(p.errors, q.errors);
                assert!(p.imu.iter().zip(&q.imu).all(|(x, y)| x != y), "every IMU sample differs");
                assert!(p.odometer.iter().zip(&q.odometer).all(|(x, y)| x != y));
                assert_eq!(p.truth, q.truth);
            }
        }
        assert_ne!(world.ranges("1hz", 42, 3).unwrap(), world.ranges("1hz", 42, 4).unwrap());
        // Platforms get independent streams.
        assert_ne!(a.platforms[0].errors.accel_bias_m_s2, a.platforms[1].errors.accel_bias_m_s2);
    }

    #[test]
    fn sizes_and_time_stamps() {
        let world = small();
        let run = world.run_inputs(1, 0);
        assert_eq!(run.platforms.iter().map(|p| p.id).collect::<Vec<_>>(), vec![1, 2]);
        for p in &run.platforms {
            assert_eq!(p.imu.len(), 2000);
            assert_eq!(p.imu[0].t, TimeUs(5_000));
            assert_eq!(p.imu.last().unwrap().t, TimeUs(10_000_000));
            assert!(p.imu.windows(2).all(|w| w[1].t.0 - w[0].t.0 == 5_000));
            assert_eq!(p.odometer.len(), 100);
            assert_eq!(p.truth.len(), 101);
            assert_eq!(p.truth[0].t, TimeUs(0));
            assert_eq!(p.truth[100].t, TimeUs(10_000_000));
        }
    }

    #[test]
    fn ranging_schedule_and_odometer_rate_do_not_change_the_imu() {
        let world = small();
        let mut s = world.scenario().clone();
        s.ranging.schedules[0].every_s = Some(0.5);
        s.sensors.odometer_rate_hz = 20.0;
        s.ranging.sigma_m = 0.3;
        let other = World::new(&s).unwrap();
        let (a, b) = (world.run_inputs(8, 2), other.run_inputs(8, 2));
        for (p, q) in a.platforms.iter().zip(&b.platforms) {
            assert_eq!(p.imu, q.imu);
        }
        // A range at the same epoch has the same noise whichever schedule asked for it.
        let one_hz = world.ranges("1hz", 8, 2).unwrap();
        let events = world.ranges("two-events", 8, 2).unwrap();
        assert_eq!(events[0], one_hz[0]);
        assert_eq!(events[1], one_hz[4]);
        // Changing the gyro model does not change the accelerometer samples.
        let mut s = world.scenario().clone();
        s.sensors.gyro_arw_deg_per_sqrt_h = 5.0;
        s.sensors.gyro_bias_deg_h = 10.0;
        let c = World::new(&s).unwrap().run_inputs(8, 2);
        for (p, q) in a.platforms.iter().zip(&c.platforms) {
            assert!(p.imu.iter().zip(&q.imu).all(|(x, y)| x.specific_force_frd_m_s2 == y.specific_force_frd_m_s2));
            assert!(p.imu.iter().zip(&q.imu).all(|(x, y)| x.angular_rate_frd_rad_s != y.angular_rate_frd_rad_s));
        }
    }

    #[test]
    fn event_stream_is_ordered_and_matches_the_vectors() {
        let world = small();
        let events: Vec<SimEvent> = world.events("1hz", 5, 1).unwrap().collect();
        let run = world.run_inputs(5, 1);
        let ranges = world.ranges("1hz", 5, 1).unwrap();
        let rank = |e: &SimEvent| match e {
            SimEvent::Imu(id, s) => (s.t, 0, *id),
            SimEvent::Odometer(id, s) => (s.t, 1, *id),
            SimEvent::Wheel(id, s) => (s.t, 0, *id),
            SimEvent::Ranges(t, _) => (*t, 2, 0),
        };
        assert!(events.windows(2).all(|w| rank(&w[0]) < rank(&w[1])), "strictly ordered by (t, kind, id)");
        assert_eq!(events.len(), 2 * 2000 + 2 * 100 + 10);
        for p in &run.platforms {
            let imu: Vec<ImuSample> = events
                .iter()
                .filter_map(|e| match e {
                    SimEvent::Imu(id, s) if *id == p.id => Some(*s),
                    _ => None,
                })
                .collect();
            assert_eq!(imu, p.imu);
            let odo: Vec<OdometerSample> = events
                .iter()
                .filter_map(|e| match e {
                    SimEvent::Odometer(id, s) if *id == p.id => Some(*s),
                    _ => None,
                })
                .collect();
            assert_eq!(odo, p.odometer);
        }
        let evr: Vec<(TimeUs, Vec<RangeSample>)> = events
            .iter()
            .filter_map(|e| match e {
                SimEvent::Ranges(t, r) => Some((*t, r.clone())),
                _ => None,
            })
            .collect();
        assert_eq!(evr, ranges);
        // At a ranging epoch, both platforms' IMU samples ending then come before the ranges.
        let at = events.iter().position(|e| matches!(e, SimEvent::Ranges(..))).unwrap();
        assert!(matches!(events[at - 1], SimEvent::Odometer(2, s) if s.t == TimeUs(1_000_000)));
        assert!(matches!(events[at - 3], SimEvent::Imu(2, s) if s.t == TimeUs(1_000_000)));
    }

    #[test]
    fn initial_estimate_errors_follow_the_configured_sigmas() {
        let world = small();
        let init = world.scenario().initial;
        let (mut pos, mut vel, mut rp, mut yaw) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for run in 0..4000 {
            let e = world.initial_estimate(2, run, 2).unwrap();
            assert_eq!(e.truth, world.trajectory(2).unwrap().truth_at(TimeUs(0)));
            pos.extend(e.pos_error_ned_m.iter());
            vel.extend(e.vel_error_ned_m_s.iter());
            rp.extend([e.attitude_error_rad[0], e.attitude_error_rad[1]]);
            yaw.push(e.attitude_error_rad[2]);
        }
        let std = |xs: &[f64]| (xs.iter().map(|x| x * x).sum::<f64>() / xs.len() as f64).sqrt();
        for (what, got, want) in [
            ("position", std(&pos), init.position_sigma_m),
            ("velocity", std(&vel), init.velocity_sigma_m_s),
            ("roll/pitch", std(&rp), init.roll_pitch_sigma_deg.to_radians()),
            ("yaw", std(&yaw), init.yaw_sigma_deg.to_radians()),
        ] {
            assert!((got / want - 1.0).abs() < 0.05, "{what}: {got} vs {want}");
        }
        let e = world.initial_estimate(2, 0, 2).unwrap();
        let (r, p, y) = e.attitude().euler_angles();
        assert!((r - e.attitude_error_rad[0]).abs() < 1e-12 && (p - e.attitude_error_rad[1]).abs() < 1e-12);
        assert!((y - e.truth.yaw_rad - e.attitude_error_rad[2]).abs() < 1e-12);
        assert_eq!(world.initial_estimate(2, 0, 9).unwrap_err(), ScenarioError::UnknownPlatform(9));
    }

    #[test]
    fn paper_world_builds_and_keeps_its_vehicles_apart() {
        let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
        assert_eq!(world.platform_ids(), vec![1, 2, 3]);
        let run = world.run_inputs(1, 0);
        for p in &run.platforms {
            assert_eq!((p.imu.len(), p.odometer.len(), p.truth.len()), (76_000, 3_800, 3_801));
            assert!(
                p.imu.iter().all(|s| s
                    .specific_force_frd_m_s2
                    .iter()
                    .chain(s.angular_rate_frd_rad_s.iter())
                    .all(|x| x.is_finite()))
            );
        }
        assert_eq!(world.ranges("1hz", 1, 0).unwrap().iter().map(|(_, r)| r.len()).sum::<usize>(), 380 * 3);
        // Pairwise distances stay between 100 m and 800 m over the run (as paper.toml says).
        for t in (0..=380).map(|s| TimeUs(s * 1_000_000)) {
            let p: Vec<_> = world.platforms().iter().map(|tr| tr.truth_at(t).pos_ned_m).collect();
            for (i, j) in [(0, 1), (0, 2), (1, 2)] {
                let d = (p[i] - p[j]).norm();
                assert!((100.0..800.0).contains(&d), "platforms {i}, {j} are {d} m apart at {t}");
            }
        }
    }
}
