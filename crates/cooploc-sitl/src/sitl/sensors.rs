//! Sensor error models: IMU, odometer and inter-platform ranging, drawn per run and per
//! platform from the scenario's numbers.
//!
//! - IMU (rate `imu_rate_hz`; each sample is the mean over its interval `(t_{k-1}, t_k]`):
//!   measured = truth mean + bias + white noise. Accelerometer bias per axis ~ N(0,
//!   `accel_bias_ug`), drawn once per run; white noise of density `accel_noise_ug_per_sqrt_hz`,
//!   so a per-sample sigma of `density * sqrt(rate)`. Gyro bias per axis ~ N(0, `gyro_bias_deg_h`);
//!   angle random walk `gyro_arw_deg_per_sqrt_h`, a rate-noise density of
//!   `ARW * pi/180 / 60` rad/sqrt(s) and so a per-sample sigma of that times `sqrt(rate)`. Optional
//!   bias random walks step the bias between samples (held constant within one).
//! - Odometer (rate `odometer_rate_hz`, samples at `m / rate`, `m >= 1`): the true forward speed
//!   at that instant times `1 + scale_error` (`scale_error ~ N(0, odometer_scale_sigma)` per run)
//!   plus white noise `odometer_sigma_m_s`.
//! - Wheels (the wheeled robots, `model = "planar"`; rate `wheels.rate_hz`, samples at
//!   `m / rate`): each sample's forward speed is the mean of the true speeds at the ends of its
//!   interval (the mean over the interval within a segment of constant acceleration) and its yaw
//!   rate the heading turned divided by the interval (exact), plus white noise `speed_sigma_m_s`
//!   and `yaw_rate_sigma_deg_s`.
//! - Ranging: at each epoch of a schedule, one range per unordered pair of platforms, measured by
//!   the lower id (`from`) to the higher (`to`): the true 3-D distance plus N(0, `sigma_m`).
//!
//! Randomness: every draw comes from its own ChaCha8 stream, seeded from `(seed, run, platform or
//! pair, stream kind)`; ranging noise is seeded per pair and per epoch. So the IMU noise does not
//! change with the ranging schedule or the odometer rate, the accelerometer noise does not change
//! with the gyro's settings, and a range at 100 s has the same noise under every schedule that
//! ranges at 100 s.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::scenario::Scenario;
use super::truth::Trajectory;
use crate::estimation::unicycle::wrap_angle;
use crate::estimation::{ImuSample, OdometerSample, PlatformId, RangeSample, WheelSample};
use crate::time::TimeUs;

pub use crate::estimation::spec::{DEG_PER_H_RAD_S, DEG_PER_SQRT_H_RAD_PER_SQRT_S, MICRO_G_M_S2};

/// The scenario's sensor numbers in SI units, per sample where that applies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorModel {
    pub imu_period_us: u64,
    pub odometer_period_us: u64,
    /// Odometer rate, Hz: sample `m` is at `round(m * 1e6 / rate)` us, so a rate whose period
    /// is not a whole number of microseconds (15 Hz) keeps its average rate exactly.
    pub odometer_rate_hz: f64,
    pub end: TimeUs,
    /// Per-axis standard deviation of the constant accelerometer bias, m/s^2.
    pub accel_bias_sigma_m_s2: f64,
    /// Accelerometer white-noise density (velocity random walk), m/s^2/sqrt(Hz).
    pub accel_noise_density_m_s2_per_sqrt_hz: f64,
    /// Per-axis, per-sample accelerometer white noise, m/s^2 (density times sqrt(rate)).
    pub accel_noise_sigma_m_s2: f64,
    /// Accelerometer bias random walk, m/s^2/sqrt(s).
    pub accel_bias_walk_m_s2_per_sqrt_s: f64,
    /// Per-axis standard deviation of the constant gyro bias, rad/s.
    pub gyro_bias_sigma_rad_s: f64,
    /// Angle random walk, rad/sqrt(s): the gyro white-noise density in rad/s/sqrt(Hz).
    pub gyro_arw_rad_per_sqrt_s: f64,
    /// Per-axis, per-sample gyro white noise, rad/s (ARW times sqrt(rate)).
    pub gyro_noise_sigma_rad_s: f64,
    /// Gyro bias random walk, rad/s/sqrt(s).
    pub gyro_bias_walk_rad_s_per_sqrt_s: f64,
    pub odometer_sigma_m_s: f64,
    pub odometer_scale_sigma: f64,
    pub range_sigma_m: f64,
    /// The radios' reach, m (see [`crate::sitl::scenario::Ranging::max_range_m`]).
    pub range_max_m: Option<f64>,
    /// The wheeled robots' odometry, when the scenario has any.
    pub wheels: Option<WheelModel>,
}

/// The wheel odometry model in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelModel {
    pub rate_hz: f64,
    pub speed_sigma_m_s: f64,
    pub yaw_rate_sigma_rad_s: f64,
    pub track_m: f64,
}

impl SensorModel {
    /// Converts a (validated) scenario's sensor numbers.
    pub fn from_scenario(scenario: &Scenario) -> Self {
        let s = &scenario.sensors;
        let rate_sqrt = s.imu_rate_hz.sqrt();
        let arw = s.gyro_arw_deg_per_sqrt_h * DEG_PER_SQRT_H_RAD_PER_SQRT_S;
        SensorModel {
            imu_period_us: scenario.imu_period_us(),
            odometer_period_us: scenario.odometer_period_us(),
            odometer_rate_hz: scenario.sensors.odometer_rate_hz,
            end: scenario.end(),
            accel_bias_sigma_m_s2: s.accel_bias_ug * MICRO_G_M_S2,
            accel_noise_density_m_s2_per_sqrt_hz: s.accel_noise_ug_per_sqrt_hz * MICRO_G_M_S2,
            accel_noise_sigma_m_s2: s.accel_noise_ug_per_sqrt_hz * MICRO_G_M_S2 * rate_sqrt,
            accel_bias_walk_m_s2_per_sqrt_s: s.accel_bias_walk_ug_per_sqrt_s * MICRO_G_M_S2,
            gyro_bias_sigma_rad_s: s.gyro_bias_deg_h * DEG_PER_H_RAD_S,
            gyro_arw_rad_per_sqrt_s: arw,
            gyro_noise_sigma_rad_s: arw * rate_sqrt,
            gyro_bias_walk_rad_s_per_sqrt_s: s.gyro_bias_walk_deg_h_per_sqrt_s * DEG_PER_H_RAD_S,
            odometer_sigma_m_s: s.odometer_sigma_m_s,
            odometer_scale_sigma: s.odometer_scale_sigma,
            range_sigma_m: scenario.ranging.sigma_m,
            range_max_m: scenario.ranging.max_range_m,
            wheels: scenario.wheels.map(|w| WheelModel {
                rate_hz: w.rate_hz,
                speed_sigma_m_s: w.speed_sigma_m_s,
                yaw_rate_sigma_rad_s: w.yaw_rate_sigma_deg_s.to_radians(),
                track_m: w.track_m,
            }),
        }
    }
}

/// The errors one platform's sensors were given for one run (for reports, and for filters that
/// are told the truth, e.g. to check consistency).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorErrors {
    /// Accelerometer bias at the start of the run (constant unless a bias walk is configured).
    pub accel_bias_m_s2: Vector3<f64>,
    /// Gyro bias at the start of the run (constant unless a bias walk is configured).
    pub gyro_bias_rad_s: Vector3<f64>,
    /// Odometer scale factor error: reading = (1 + this) * true speed + noise.
    pub odometer_scale_error: f64,
}

/// Which independent random stream a draw comes from.
#[derive(Debug, Clone, Copy)]
#[repr(u64)]
pub(crate) enum Stream {
    AccelBias = 1,
    GyroBias = 2,
    AccelNoise = 3,
    GyroNoise = 4,
    AccelBiasWalk = 5,
    GyroBiasWalk = 6,
    OdometerScale = 7,
    OdometerNoise = 8,
    Range = 9,
    Initial = 10,
    WheelSpeed = 11,
    WheelYawRate = 12,
}

/// SplitMix64 finaliser: a bijective mix of 64 bits.
fn splitmix64(z: u64) -> u64 {
    let mut z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The random stream for `(seed, run, stream, key...)`.
pub(crate) fn stream_rng(seed: u64, run: u32, stream: Stream, key: &[u64]) -> ChaCha8Rng {
    let mut h = splitmix64(seed);
    for part in [u64::from(run), stream as u64].iter().chain(key) {
        h = splitmix64(h ^ part);
    }
    ChaCha8Rng::seed_from_u64(h)
}

pub(crate) fn normal(rng: &mut ChaCha8Rng) -> f64 {
    rng.sample::<f64, _>(StandardNormal)
}

fn normal3(rng: &mut ChaCha8Rng, sigma: f64) -> Vector3<f64> {
    let (x, y, z) = (normal(rng), normal(rng), normal(rng));
    sigma * Vector3::new(x, y, z)
}

/// Draws one platform's sensor errors for one run.
pub fn draw_errors(model: &SensorModel, seed: u64, run: u32, platform: PlatformId) -> SensorErrors {
    let key = [u64::from(platform)];
    SensorErrors {
        accel_bias_m_s2: normal3(&mut stream_rng(seed, run, Stream::AccelBias, &key), model.accel_bias_sigma_m_s2),
        gyro_bias_rad_s: normal3(&mut stream_rng(seed, run, Stream::GyroBias, &key), model.gyro_bias_sigma_rad_s),
        odometer_scale_error: model.odometer_scale_sigma * normal(&mut stream_rng(seed, run, Stream::OdometerScale, &key)),
    }
}

/// One platform's IMU samples for one run, lazily: samples end at `k * period`, `k = 1..`, up to
/// the end of the run.
#[derive(Debug, Clone)]
pub struct ImuStream<'a> {
    traj: &'a Trajectory,
    model: SensorModel,
    next_us: u64,
    accel_bias: Vector3<f64>,
    gyro_bias: Vector3<f64>,
    accel_noise: ChaCha8Rng,
    gyro_noise: ChaCha8Rng,
    accel_walk: ChaCha8Rng,
    gyro_walk: ChaCha8Rng,
    /// The perfect IMU's samples `k = 1..` of this trajectory at this period, when the caller
    /// has them ([`ImuStream::over_truth`]); computed sample by sample otherwise.
    truth: &'a [ImuSample],
}

impl<'a> ImuStream<'a> {
    pub fn new(traj: &'a Trajectory, model: &SensorModel, seed: u64, run: u32) -> Self {
        let errors = draw_errors(model, seed, run, traj.id());
        let key = [u64::from(traj.id())];
        ImuStream {
            traj,
            model: *model,
            next_us: model.imu_period_us,
            accel_bias: errors.accel_bias_m_s2,
            gyro_bias: errors.gyro_bias_rad_s,
            accel_noise: stream_rng(seed, run, Stream::AccelNoise, &key),
            gyro_noise: stream_rng(seed, run, Stream::GyroNoise, &key),
            accel_walk: stream_rng(seed, run, Stream::AccelBiasWalk, &key),
            gyro_walk: stream_rng(seed, run, Stream::GyroBiasWalk, &key),
            truth: &[],
        }
    }

    /// The same stream over the perfect IMU's samples computed beforehand: `truth[k]` must be
    /// `traj.imu_mean` over `(k T, (k + 1) T]` for this trajectory and the model's period `T`
    /// (the same numbers, not recomputed). Samples past its end are computed.
    pub(crate) fn over_truth(self, truth: &'a [ImuSample]) -> Self {
        ImuStream { truth, ..self }
    }

    /// The accelerometer and gyro biases now (they walk when a bias walk is configured).
    pub fn biases(&self) -> (Vector3<f64>, Vector3<f64>) {
        (self.accel_bias, self.gyro_bias)
    }

    /// Time stamp of the next sample, if any.
    pub fn peek_time(&self) -> Option<TimeUs> {
        (self.next_us <= self.model.end.0).then_some(TimeUs(self.next_us))
    }
}

impl Iterator for ImuStream<'_> {
    type Item = ImuSample;

    fn next(&mut self) -> Option<ImuSample> {
        let t1 = self.peek_time()?;
        let t0 = TimeUs(t1.0 - self.model.imu_period_us);
        let m = &self.model;
        let k = (t1.0 / m.imu_period_us - 1) as usize;
        let truth = match self.truth.get(k) {
            Some(s) => *s,
            None => self.traj.imu_mean(t0, t1),
        };
        let sample = ImuSample {
            t: t1,
            specific_force_frd_m_s2: truth.specific_force_frd_m_s2
                + self.accel_bias
                + normal3(&mut self.accel_noise, m.accel_noise_sigma_m_s2),
            angular_rate_frd_rad_s: truth.angular_rate_frd_rad_s
                + self.gyro_bias
                + normal3(&mut self.gyro_noise, m.gyro_noise_sigma_rad_s),
        };
        let sqrt_dt = (m.imu_period_us as f64 * 1e-6).sqrt();
        if m.accel_bias_walk_m_s2_per_sqrt_s > 0.0 {
            self.accel_bias += normal3(&mut self.accel_walk, m.accel_bias_walk_m_s2_per_sqrt_s * sqrt_dt);
        }
        if m.gyro_bias_walk_rad_s_per_sqrt_s > 0.0 {
            self.gyro_bias += normal3(&mut self.gyro_walk, m.gyro_bias_walk_rad_s_per_sqrt_s * sqrt_dt);
        }
        self.next_us += m.imu_period_us;
        Some(sample)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = if self.next_us <= self.model.end.0 {
            ((self.model.end.0 - self.next_us) / self.model.imu_period_us + 1) as usize
        } else {
            0
        };
        (left, Some(left))
    }
}

/// One platform's odometer samples for one run, lazily: at `round(m / rate)`, `m = 1..`, up to
/// the end of the run.
#[derive(Debug, Clone)]
pub struct OdometerStream<'a> {
    traj: &'a Trajectory,
    model: SensorModel,
    m: u64,
    next_us: u64,
    scale: f64,
    noise: ChaCha8Rng,
}

impl<'a> OdometerStream<'a> {
    pub fn new(traj: &'a Trajectory, model: &SensorModel, seed: u64, run: u32) -> Self {
        let errors = draw_errors(model, seed, run, traj.id());
        OdometerStream {
            traj,
            model: *model,
            m: 1,
            next_us: odometer_time_us(model.odometer_rate_hz, 1),
            scale: 1.0 + errors.odometer_scale_error,
            noise: stream_rng(seed, run, Stream::OdometerNoise, &[u64::from(traj.id())]),
        }
    }

    /// Time stamp of the next sample, if any.
    pub fn peek_time(&self) -> Option<TimeUs> {
        (self.next_us <= self.model.end.0).then_some(TimeUs(self.next_us))
    }
}

impl Iterator for OdometerStream<'_> {
    type Item = OdometerSample;

    fn next(&mut self) -> Option<OdometerSample> {
        let t = self.peek_time()?;
        let speed = self.traj.truth_at(t).speed_m_s;
        self.m += 1;
        self.next_us = odometer_time_us(self.model.odometer_rate_hz, self.m);
        Some(OdometerSample { t, speed_m_s: self.scale * speed + self.model.odometer_sigma_m_s * normal(&mut self.noise) })
    }
}

/// One wheeled robot's wheel samples for one run, lazily: at `round(m / rate)`, `m = 1..`, up
/// to the end of the run. Empty when the scenario has no `[wheels]`.
#[derive(Debug, Clone)]
pub struct WheelStream<'a> {
    traj: &'a Trajectory,
    end: TimeUs,
    model: Option<WheelModel>,
    m: u64,
    prev_us: u64,
    next_us: u64,
    speed_noise: ChaCha8Rng,
    yaw_noise: ChaCha8Rng,
}

impl<'a> WheelStream<'a> {
    pub fn new(traj: &'a Trajectory, model: &SensorModel, seed: u64, run: u32) -> Self {
        let key = [u64::from(traj.id())];
        WheelStream {
            traj,
            end: model.end,
            model: model.wheels,
            m: 1,
            prev_us: 0,
            next_us: model.wheels.map_or(u64::MAX, |w| odometer_time_us(w.rate_hz, 1)),
            speed_noise: stream_rng(seed, run, Stream::WheelSpeed, &key),
            yaw_noise: stream_rng(seed, run, Stream::WheelYawRate, &key),
        }
    }

    /// Time stamp of the next sample, if any.
    pub fn peek_time(&self) -> Option<TimeUs> {
        (self.model.is_some() && self.next_us <= self.end.0).then_some(TimeUs(self.next_us))
    }
}

impl Iterator for WheelStream<'_> {
    type Item = WheelSample;

    fn next(&mut self) -> Option<WheelSample> {
        let t = self.peek_time()?;
        let w = self.model?;
        let (a, b) = (self.traj.truth_at(TimeUs(self.prev_us)), self.traj.truth_at(t));
        let dt = (t.0 - self.prev_us) as f64 * 1e-6;
        // Speed is linear within a segment: the mean of the ends is the mean over the interval.
        let speed = 0.5 * (a.speed_m_s + b.speed_m_s);
        let yaw_rate = wrap_angle(b.yaw_rad - a.yaw_rad) / dt;
        self.prev_us = t.0;
        self.m += 1;
        self.next_us = odometer_time_us(w.rate_hz, self.m);
        Some(WheelSample {
            t,
            speed_m_s: speed + w.speed_sigma_m_s * normal(&mut self.speed_noise),
            yaw_rate_rad_s: yaw_rate + w.yaw_rate_sigma_rad_s * normal(&mut self.yaw_noise),
        })
    }
}

/// Time of odometer sample `m` at `rate_hz`, us.
fn odometer_time_us(rate_hz: f64, m: u64) -> u64 {
    (m as f64 * 1e6 / rate_hz).round() as u64
}

/// The ranges measured at `t` among `trajs`: one per unordered pair, `from` the lower id, in
/// increasing order of `(from, to)`.
pub fn ranges_at(trajs: &[Trajectory], sigma_m: f64, max_m: Option<f64>, t: TimeUs, seed: u64, run: u32) -> Vec<RangeSample> {
    let mut sorted: Vec<&Trajectory> = trajs.iter().collect();
    sorted.sort_by_key(|tr| tr.id());
    let positions: Vec<_> = sorted.iter().map(|tr| tr.truth_at(t).pos_ned_m).collect();
    let mut out = Vec::with_capacity(sorted.len() * sorted.len().saturating_sub(1) / 2);
    for i in 0..sorted.len() {
        for j in i + 1..sorted.len() {
            let (from, to) = (sorted[i].id(), sorted[j].id());
            if max_m.is_some_and(|reach| (positions[i] - positions[j]).norm() > reach) {
                continue; // out of the radios' reach
            }
            let mut rng = stream_rng(seed, run, Stream::Range, &[u64::from(from), u64::from(to), t.0]);
            let range_m = (positions[i] - positions[j]).norm() + sigma_m * normal(&mut rng);
            out.push(RangeSample { t, from, to, range_m, sigma_m });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sitl::World;
    use crate::sitl::scenario::tests::SMALL;

    fn small_world(edit: impl FnOnce(&mut Scenario)) -> World {
        let mut s = Scenario::from_toml_str(SMALL).unwrap();
        edit(&mut s);
        World::new(&s).unwrap()
    }

    /// Radios that reach only so far: the pairs farther apart do not range, the others range as
    /// they did (same noise draws); a reach that is not a positive distance is refused.
    #[test]
    fn ranges_beyond_the_radios_reach_are_not_taken() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../sitl/scenarios/paper.toml");
        let paper = Scenario::from_path(&path).unwrap();
        let all = World::new(&paper).unwrap().ranges("1hz", 1, 0).unwrap();
        let (t, first) = &all[0];
        let mut lengths: Vec<f64> = first.iter().map(|r| r.range_m).collect();
        lengths.sort_by(f64::total_cmp);
        assert!(lengths.len() == 3 && lengths[2] - lengths[0] > 10.0, "the paper's pairs are at different distances");
        let reach = 0.5 * (lengths[0] + lengths[2]);
        let mut near = paper.clone();
        near.ranging.max_range_m = Some(reach);
        let kept = World::new(&near).unwrap().ranges("1hz", 1, 0).unwrap();
        assert_eq!(kept[0].0, *t);
        let want: Vec<&RangeSample> = first.iter().filter(|r| r.range_m <= reach).collect();
        assert!(!want.is_empty() && want.len() < first.len());
        assert_eq!(kept[0].1.iter().collect::<Vec<_>>(), want);
        for bad in [0.0, -5.0, f64::NAN, f64::INFINITY] {
            let mut s = paper.clone();
            s.ranging.max_range_m = Some(bad);
            let e = s.validate().unwrap_err().to_string();
            assert!(e.contains("ranging.max_range_m"), "{e}");
        }
    }

    /// Sample standard deviation.
    fn std(xs: &[f64]) -> f64 {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    }

    fn assert_rel(what: &str, got: f64, want: f64, rel: f64) {
        assert!(((got - want) / want).abs() < rel, "{what}: got {got}, configured {want} (tolerance {:.1}%)", rel * 100.0);
    }

    #[test]
    fn unit_conversions() {
        assert!((DEG_PER_H_RAD_S * 3600.0 - 1f64.to_radians()).abs() < 1e-18);
        // 1.2 deg/sqrt(h) = 3.49e-4 rad/sqrt(s); 100 ug/sqrt(Hz) at 200 Hz = 0.01387 m/s^2.
        let m = SensorModel::from_scenario(&Scenario::from_toml_str(SMALL).unwrap());
        assert!((m.gyro_arw_rad_per_sqrt_s - 3.490_658_5e-4).abs() < 1e-11);
        assert!((m.accel_noise_sigma_m_s2 - 0.013_868_7).abs() < 1e-8);
        assert!((m.accel_noise_density_m_s2_per_sqrt_hz - 9.806_65e-4).abs() < 1e-15);
        assert!((m.gyro_bias_sigma_rad_s - 1.454_441e-5).abs() < 1e-11);
        assert!((m.accel_bias_sigma_m_s2 - 4.903_325e-3).abs() < 1e-12);
    }

    #[test]
    fn constant_biases_and_odometer_scale_have_the_configured_spread() {
        let world = small_world(|_| {});
        let m = *world.sensor_model();
        let (mut acc, mut gyro, mut scale) = (Vec::new(), Vec::new(), Vec::new());
        for run in 0..6000 {
            for id in [1, 2] {
                let e = world.sensor_errors(11, run, id).unwrap();
                acc.extend(e.accel_bias_m_s2.iter());
                gyro.extend(e.gyro_bias_rad_s.iter());
                scale.push(e.odometer_scale_error);
            }
        }
        // 36 000 draws per sensor: the sample std is within about 0.4% (1 sigma) of the truth.
        assert_rel("accelerometer bias std", std(&acc), m.accel_bias_sigma_m_s2, 0.02);
        assert_rel("gyro bias std", std(&gyro), m.gyro_bias_sigma_rad_s, 0.02);
        assert_rel("odometer scale std", std(&scale), 0.01, 0.03);
        let mean = acc.iter().sum::<f64>() / acc.len() as f64;
        assert!(mean.abs() < 4.0 * m.accel_bias_sigma_m_s2 / (acc.len() as f64).sqrt(), "accelerometer bias mean {mean}");
    }

    /// Noise of the IMU samples of one run (sample minus truth mean minus the run's bias), per
    /// axis: (accelerometer, gyro).
    fn imu_noise(world: &World, seed: u64, run: u32, id: PlatformId) -> ([Vec<f64>; 3], [Vec<f64>; 3]) {
        let traj = world.trajectory(id).unwrap();
        let e = world.sensor_errors(seed, run, id).unwrap();
        let period = world.sensor_model().imu_period_us;
        let (mut a, mut g): ([Vec<f64>; 3], [Vec<f64>; 3]) = Default::default();
        for s in world.imu(seed, run, id).unwrap() {
            let truth = traj.imu_mean(TimeUs(s.t.0 - period), s.t);
            let da = s.specific_force_frd_m_s2 - truth.specific_force_frd_m_s2 - e.accel_bias_m_s2;
            let dg = s.angular_rate_frd_rad_s - truth.angular_rate_frd_rad_s - e.gyro_bias_rad_s;
            for k in 0..3 {
                a[k].push(da[k]);
                g[k].push(dg[k]);
            }
        }
        (a, g)
    }

    fn lag1_autocorrelation(xs: &[f64]) -> f64 {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>();
        xs.windows(2).map(|w| (w[0] - mean) * (w[1] - mean)).sum::<f64>() / var
    }

    #[test]
    fn imu_white_noise_has_the_configured_density_and_is_white() {
        let world = small_world(|_| {});
        let m = *world.sensor_model();
        let (mut acc, mut gyro) = (Vec::new(), Vec::new());
        for run in 0..10 {
            for id in [1, 2] {
                let (a, g) = imu_noise(&world, 5, run, id);
                for k in 0..3 {
                    // Per axis, per run: the noise is white (2000 samples: |rho| < 4/sqrt(2000)).
                    let (ra, rg) = (lag1_autocorrelation(&a[k]), lag1_autocorrelation(&g[k]));
                    assert!(ra.abs() < 0.09 && rg.abs() < 0.09, "lag-1 autocorrelation {ra}, {rg}");
                }
                acc.extend(a.into_iter().flatten());
                gyro.extend(g.into_iter().flatten());
            }
        }
        // 120 000 samples each: std within about 0.2% (1 sigma).
        assert_rel("accelerometer noise std", std(&acc), m.accel_noise_sigma_m_s2, 0.01);
        assert_rel("gyro noise std", std(&gyro), m.gyro_noise_sigma_rad_s, 0.01);
        for (xs, sigma) in [(&acc, m.accel_noise_sigma_m_s2), (&gyro, m.gyro_noise_sigma_rad_s)] {
            let mean = xs.iter().sum::<f64>() / xs.len() as f64;
            assert!(mean.abs() < 4.0 * sigma / (xs.len() as f64).sqrt(), "noise mean {mean} vs sigma {sigma}");
        }
    }

    #[test]
    fn gyro_angle_random_walk_grows_as_arw_sqrt_t() {
        // The integrated gyro noise over the 10 s run has std ARW * sqrt(10 s).
        let world = small_world(|_| {});
        let m = *world.sensor_model();
        let dt = m.imu_period_us as f64 * 1e-6;
        let mut angles = Vec::new();
        for run in 0..300 {
            for id in [1, 2] {
                let (_, g) = imu_noise(&world, 9, run, id);
                angles.extend(g.iter().map(|axis| axis.iter().sum::<f64>() * dt));
            }
        }
        // 1800 draws: std within about 1.7% (1 sigma).
        assert_rel("angle random walk after 10 s", std(&angles), m.gyro_arw_rad_per_sqrt_s * 10f64.sqrt(), 0.07);
    }

    #[test]
    fn bias_walk_grows_as_configured() {
        // With a gyro bias walk of q, the bias after T seconds has moved by N(0, q^2 T).
        let world = small_world(|s| {
            s.sensors.gyro_bias_walk_deg_h_per_sqrt_s = 100.0;
            s.sensors.gyro_arw_deg_per_sqrt_h = 0.0;
            s.sensors.accel_noise_ug_per_sqrt_hz = 0.0;
            s.sensors.accel_bias_walk_ug_per_sqrt_s = 50.0;
        });
        let m = *world.sensor_model();
        let (mut gyro, mut acc) = (Vec::new(), Vec::new());
        for run in 0..400 {
            let (a, g) = imu_noise(&world, 3, run, 2);
            // The last sample carries the bias after 1999 steps.
            gyro.extend(g.iter().map(|axis| *axis.last().unwrap()));
            acc.extend(a.iter().map(|axis| *axis.last().unwrap()));
        }
        let t = 1999.0 * m.imu_period_us as f64 * 1e-6;
        assert_rel("gyro bias walk", std(&gyro), m.gyro_bias_walk_rad_s_per_sqrt_s * t.sqrt(), 0.1);
        assert_rel("accelerometer bias walk", std(&acc), m.accel_bias_walk_m_s2_per_sqrt_s * t.sqrt(), 0.1);
    }

    #[test]
    fn odometer_noise_and_scale_are_as_configured() {
        let world = small_world(|_| {});
        let mut residuals = Vec::new();
        for run in 0..400 {
            for id in [1, 2] {
                let traj = world.trajectory(id).unwrap();
                let scale = 1.0 + world.sensor_errors(21, run, id).unwrap().odometer_scale_error;
                let samples: Vec<_> = world.odometer(21, run, id).unwrap().collect();
                assert_eq!(samples.len(), 100);
                assert_eq!(samples[0].t, TimeUs(100_000));
                residuals.extend(samples.iter().map(|s| s.speed_m_s - scale * traj.truth_at(s.t).speed_m_s));
            }
        }
        assert_rel("odometer noise std", std(&residuals), 0.2, 0.02);
        // Without the scale error the residuals would be wider: check it is really applied.
        let world = small_world(|s| s.sensors.odometer_sigma_m_s = 0.0);
        let e = world.sensor_errors(21, 0, 1).unwrap().odometer_scale_error;
        let s = world.odometer(21, 0, 1).unwrap().nth(4).unwrap();
        let truth = world.trajectory(1).unwrap().truth_at(s.t).speed_m_s;
        assert!((s.speed_m_s / truth - 1.0 - e).abs() < 1e-12 && e != 0.0);
    }

    #[test]
    fn range_noise_is_as_configured() {
        let world = small_world(|_| {});
        let mut residuals = Vec::new();
        for run in 0..1000 {
            for (t, ranges) in world.ranges("1hz", 4, run).unwrap() {
                assert_eq!(ranges.len(), 1);
                let r = ranges[0];
                assert_eq!((r.from, r.to, r.t, r.sigma_m), (1, 2, t, 0.1));
                let d = (world.trajectory(1).unwrap().truth_at(t).pos_ned_m - world.trajectory(2).unwrap().truth_at(t).pos_ned_m)
                    .norm();
                residuals.push(r.range_m - d);
            }
        }
        assert_rel("range noise std", std(&residuals), 0.1, 0.02);
        let mean = residuals.iter().sum::<f64>() / residuals.len() as f64;
        assert!(mean.abs() < 4.0 * 0.1 / (residuals.len() as f64).sqrt());
    }
}
