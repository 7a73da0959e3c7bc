//! Truth: where each vehicle is, how it moves, and what a perfect IMU on it senses.
//!
//! World model (the INS mechanises the same one):
//!
//! - navigation frame: a local NED tangent plane fixed to the Earth at the scenario latitude `L`;
//!   flat Earth, constant gravity `g^n = [0, 0, g]`, Earth rate
//!   `w_ie^n = 7.292115e-5 [cos L, 0, -sin L]` rad/s; no transport rate (the frame does not move);
//! - body frame FRD; yaw from north, clockwise seen from above; land vehicles on level ground, so
//!   roll = pitch = 0, the D coordinate is constant and the body->NED rotation is `R = Rz(yaw)`;
//!   the vehicle never slips: its velocity is `speed [cos yaw, sin yaw, 0]`;
//! - a profile is a list of segments of constant longitudinal acceleration `a` and yaw rate `r`;
//!   within a segment speed and yaw are linear in time, and position is the integral of velocity
//!   (Gauss-Legendre quadrature from precomputed one-second knots: error far below a micrometre);
//! - a perfect IMU senses, in body axes,
//!   `w_ib^b = [0, 0, r] + R^T w_ie^n` and `f^b = R^T (a^n + 2 w_ie^n x v^n - g^n)` with
//!   `a^n = a [cos yaw, sin yaw, 0] + speed r [-sin yaw, cos yaw, 0]`; an IMU sample holds their
//!   means over its interval `(t_{k-1}, t_k]`, integrated by 5-node Gauss-Legendre quadrature split
//!   at segment boundaries (exact to rounding for these smooth integrands).
//!
//! At a segment boundary the state is continuous; acceleration and yaw rate are those of the
//! segment that starts there. Past the end of the last segment the last segment continues.

use nalgebra::{UnitQuaternion, Vector3};

use super::scenario::PlatformSpec;
use crate::estimation::unicycle::wrap_angle;
use crate::estimation::{ImuSample, PlatformId};
use crate::time::TimeUs;

/// Earth rotation rate, rad/s (WGS-84).
pub const EARTH_RATE_RAD_S: f64 = 7.292_115e-5;

/// The Earth as the navigation frame sees it: constant gravity and rotation, NED components.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Earth {
    /// `[0, 0, g]`, m/s^2.
    pub gravity_ned_m_s2: Vector3<f64>,
    /// `w_ie^n = EARTH_RATE [cos L, 0, -sin L]`, rad/s.
    pub rate_ned_rad_s: Vector3<f64>,
}

impl Earth {
    pub fn new(latitude_deg: f64, gravity_m_s2: f64) -> Self {
        let lat = latitude_deg.to_radians();
        Earth {
            gravity_ned_m_s2: Vector3::new(0.0, 0.0, gravity_m_s2),
            rate_ned_rad_s: EARTH_RATE_RAD_S * Vector3::new(lat.cos(), 0.0, -lat.sin()),
        }
    }
}

/// A vehicle's true state at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthState {
    pub t: TimeUs,
    pub pos_ned_m: Vector3<f64>,
    pub vel_ned_m_s: Vector3<f64>,
    /// Yaw from north, clockwise seen from above, wrapped to (-pi, pi].
    pub yaw_rad: f64,
    /// Forward speed (body x velocity), m/s.
    pub speed_m_s: f64,
    pub yaw_rate_rad_s: f64,
    /// Longitudinal acceleration (rate of change of speed), m/s^2.
    pub accel_m_s2: f64,
    /// Body (FRD) to NED rotation.
    pub attitude: UnitQuaternion<f64>,
}

/// Distance between position knots within a segment.
const KNOT_US: u64 = 1_000_000;

/// 5-node Gauss-Legendre rule on [-1, 1]: (node, weight).
const GL5: [(f64, f64); 5] = [
    (0.0, 0.568_888_888_888_888_9),
    (-0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (0.538_469_310_105_683_1, 0.478_628_670_499_366_5),
    (-0.906_179_845_938_664, 0.236_926_885_056_189_1),
    (0.906_179_845_938_664, 0.236_926_885_056_189_1),
];

/// Integrates `f` over `[a, b]` with the 5-node Gauss-Legendre rule.
fn gauss5<const N: usize>(a: f64, b: f64, f: impl Fn(f64) -> [f64; N]) -> [f64; N] {
    let half = 0.5 * (b - a);
    let mid = 0.5 * (a + b);
    let mut acc = [0.0; N];
    for (x, w) in GL5 {
        let v = f(mid + half * x);
        for (s, vi) in acc.iter_mut().zip(v) {
            *s += w * half * vi;
        }
    }
    acc
}

#[derive(Debug, Clone, Copy)]
struct SegmentPlan {
    start_us: u64,
    /// Exclusive end; `u64::MAX` for the last segment (it continues).
    end_us: u64,
    speed0_m_s: f64,
    yaw0_rad: f64,
    accel_m_s2: f64,
    yaw_rate_rad_s: f64,
    /// Index of this segment's first position knot (at `start_us`).
    first_knot: usize,
}

impl SegmentPlan {
    fn speed(&self, tau_s: f64) -> f64 {
        self.speed0_m_s + self.accel_m_s2 * tau_s
    }
    fn yaw(&self, tau_s: f64) -> f64 {
        self.yaw0_rad + self.yaw_rate_rad_s * tau_s
    }
    /// Horizontal velocity (N, E) at `tau_s` into the segment.
    fn vel_ne(&self, tau_s: f64) -> [f64; 2] {
        let (s, c) = self.yaw(tau_s).sin_cos();
        let v = self.speed(tau_s);
        [v * c, v * s]
    }
    /// Horizontal displacement from `a` to `b` seconds into the segment, in steps of at most a knot.
    fn displacement_ne(&self, a: f64, b: f64) -> [f64; 2] {
        let step = KNOT_US as f64 * 1e-6;
        let n = ((b - a) / step).ceil().max(1.0) as usize;
        let h = (b - a) / n as f64;
        let mut acc = [0.0; 2];
        for i in 0..n {
            let d = gauss5(a + i as f64 * h, a + (i + 1) as f64 * h, |t| self.vel_ne(t));
            acc[0] += d[0];
            acc[1] += d[1];
        }
        acc
    }
}

#[derive(Debug, Clone, Copy)]
struct Knot {
    t_us: u64,
    pos_ne_m: [f64; 2],
}

/// One vehicle's truth trajectory.
#[derive(Debug, Clone)]
pub struct Trajectory {
    id: PlatformId,
    earth: Earth,
    down_m: f64,
    segments: Vec<SegmentPlan>,
    knots: Vec<Knot>,
}

impl Trajectory {
    /// Builds the trajectory of a validated platform spec.
    pub fn new(spec: &PlatformSpec, earth: Earth) -> Self {
        let mut segments = Vec::with_capacity(spec.segments.len());
        let mut knots = Vec::new();
        let mut start_us = 0u64;
        let mut speed = spec.start_speed_m_s;
        let mut yaw = spec.start_yaw_deg.to_radians();
        let mut pos = [spec.start_ned_m[0], spec.start_ned_m[1]];
        for (k, seg) in spec.segments.iter().enumerate() {
            let dur_us = (seg.duration_s * 1e6).round() as u64;
            let last = k + 1 == spec.segments.len();
            let plan = SegmentPlan {
                start_us,
                end_us: if last { u64::MAX } else { start_us + dur_us },
                speed0_m_s: speed,
                yaw0_rad: yaw,
                accel_m_s2: seg.accel_m_s2,
                yaw_rate_rad_s: seg.yaw_rate_deg_s.to_radians(),
                first_knot: knots.len(),
            };
            // Knots every KNOT_US from the segment start, up to its end.
            let mut off = 0u64;
            while off < dur_us {
                knots.push(Knot { t_us: start_us + off, pos_ne_m: pos });
                let next = (off + KNOT_US).min(dur_us);
                let d = plan.displacement_ne(off as f64 * 1e-6, next as f64 * 1e-6);
                pos[0] += d[0];
                pos[1] += d[1];
                off = next;
            }
            let dur_s = dur_us as f64 * 1e-6;
            speed = plan.speed(dur_s);
            yaw = plan.yaw(dur_s);
            segments.push(plan);
            start_us += dur_us;
        }
        Trajectory { id: spec.id, earth, down_m: spec.start_ned_m[2], segments, knots }
    }

    pub fn id(&self) -> PlatformId {
        self.id
    }

    pub fn earth(&self) -> &Earth {
        &self.earth
    }

    /// Index of the segment in force at `t_us` (the last one that starts at or before it).
    fn segment_index(&self, t_us: u64) -> usize {
        self.segments.partition_point(|s| s.start_us <= t_us).saturating_sub(1)
    }

    fn segment_at(&self, t_us: u64) -> &SegmentPlan {
        &self.segments[self.segment_index(t_us)]
    }

    /// The true state at `t`.
    pub fn truth_at(&self, t: TimeUs) -> TruthState {
        let i = self.segment_index(t.0);
        let seg = &self.segments[i];
        let tau = (t.0 - seg.start_us) as f64 * 1e-6;
        // The last knot of this segment at or before t.
        let seg_knots_end = self.segments.get(i + 1).map_or(self.knots.len(), |s| s.first_knot);
        let k = (seg.first_knot + ((t.0 - seg.start_us) / KNOT_US) as usize).min(seg_knots_end - 1);
        let knot = self.knots[k];
        let d = seg.displacement_ne((knot.t_us - seg.start_us) as f64 * 1e-6, tau);
        let pos_ned_m = Vector3::new(knot.pos_ne_m[0] + d[0], knot.pos_ne_m[1] + d[1], self.down_m);
        let [vn, ve] = seg.vel_ne(tau);
        let yaw = wrap_angle(seg.yaw(tau));
        TruthState {
            t,
            pos_ned_m,
            vel_ned_m_s: Vector3::new(vn, ve, 0.0),
            yaw_rad: yaw,
            speed_m_s: seg.speed(tau),
            yaw_rate_rad_s: seg.yaw_rate_rad_s,
            accel_m_s2: seg.accel_m_s2,
            attitude: UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        }
    }

    /// Angular rate `w_ib^b` and specific force `f^b` at `tau_s` into `seg`, as
    /// `[wx, wy, wz, fx, fy, fz]`.
    fn imu_rates(&self, seg: &SegmentPlan, tau_s: f64) -> [f64; 6] {
        let (s, c) = seg.yaw(tau_s).sin_cos();
        let v = seg.speed(tau_s);
        let w_ie = self.earth.rate_ned_rad_s;
        let vel = Vector3::new(v * c, v * s, 0.0);
        let acc =
            Vector3::new(seg.accel_m_s2 * c - v * seg.yaw_rate_rad_s * s, seg.accel_m_s2 * s + v * seg.yaw_rate_rad_s * c, 0.0);
        let f_n = acc + 2.0 * w_ie.cross(&vel) - self.earth.gravity_ned_m_s2;
        // R^T x for R = Rz(yaw).
        let to_body = |x: Vector3<f64>| [c * x[0] + s * x[1], -s * x[0] + c * x[1], x[2]];
        let w = to_body(w_ie);
        let f = to_body(f_n);
        [w[0], w[1], w[2] + seg.yaw_rate_rad_s, f[0], f[1], f[2]]
    }

    /// Exact IMU increments over `(t0, t1]`: `(dtheta, dv)`, the integrals of `w_ib^b` (rad) and
    /// `f^b` (m/s) in body axes.
    pub fn imu_increments(&self, t0: TimeUs, t1: TimeUs) -> (Vector3<f64>, Vector3<f64>) {
        let mut acc = [0.0; 6];
        let mut a = t0.0;
        while a < t1.0 {
            let seg = self.segment_at(a);
            let b = seg.end_us.min(t1.0);
            let tau = |us: u64| (us - seg.start_us) as f64 * 1e-6;
            let part = gauss5(tau(a), tau(b), |x| self.imu_rates(seg, x));
            for (s, p) in acc.iter_mut().zip(part) {
                *s += p;
            }
            a = b;
        }
        (Vector3::new(acc[0], acc[1], acc[2]), Vector3::new(acc[3], acc[4], acc[5]))
    }

    /// What a perfect IMU reports for the interval `(t0, t1]`: the mean rates, stamped `t1`.
    pub fn imu_mean(&self, t0: TimeUs, t1: TimeUs) -> ImuSample {
        let dt = t1.secs_since(t0);
        let (dtheta, dv) = self.imu_increments(t0, t1);
        ImuSample { t: t1, specific_force_frd_m_s2: dv / dt, angular_rate_frd_rad_s: dtheta / dt }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sitl::scenario::{Scenario, tests::SMALL};

    fn small() -> (Scenario, Vec<Trajectory>) {
        let s = Scenario::from_toml_str(SMALL).unwrap();
        let earth = Earth::new(s.latitude_deg, s.gravity_m_s2);
        let t = s.platforms.iter().map(|p| Trajectory::new(p, earth)).collect();
        (s, t)
    }

    /// Closed form of the position within a segment of constant acceleration `a` and yaw rate
    /// `r != 0`, via complex exponentials: `int (v0 + a t) e^{i(y0 + r t)} dt`.
    fn closed_form_ne(v0: f64, y0: f64, a: f64, r: f64, t: f64) -> [f64; 2] {
        // Antiderivative F(t) = -i (v0 + a t) e^{i y}/r + a e^{i y}/r^2.
        let f = |t: f64| {
            let (s, c) = (y0 + r * t).sin_cos();
            let v = v0 + a * t;
            // -i v (c + i s)/r = (v s - i v c)/r ; a (c + i s)/r^2
            [v * s / r + a * c / (r * r), -v * c / r + a * s / (r * r)]
        };
        let (f1, f0) = (f(t), f(0.0));
        [f1[0] - f0[0], f1[1] - f0[1]]
    }

    #[test]
    fn position_matches_closed_form_over_a_long_profile() {
        // One platform turning and accelerating for 380 s in a few segments.
        let spec: PlatformSpec = toml::from_str(
            r#"
id = 7
start_ned_m = [10.0, -20.0, -2.0]
start_yaw_deg = 80.0
start_speed_m_s = 9.0
segments = [
  { duration_s = 100.0, accel_m_s2 = 0.02, yaw_rate_deg_s = 1.5 },
  { duration_s = 130.0, accel_m_s2 = -0.01, yaw_rate_deg_s = -5.5 },
  { duration_s = 150.0, accel_m_s2 = 0.005, yaw_rate_deg_s = 0.7 },
]"#,
        )
        .unwrap();
        let traj = Trajectory::new(&spec, Earth::new(34.7, 9.80665));
        let mut pos = [10.0, -20.0];
        let (mut v, mut y) = (9.0, 80f64.to_radians());
        let mut t0 = 0.0;
        let mut worst = 0.0f64;
        for seg in &spec.segments {
            let r = seg.yaw_rate_deg_s.to_radians();
            // Check at a few odd instants inside the segment, and at its end.
            for frac in [0.123_457, 0.5, 0.987_654_3, 1.0] {
                let tau = (seg.duration_s * frac * 1e6).round() * 1e-6;
                let d = closed_form_ne(v, y, seg.accel_m_s2, r, tau);
                let truth = traj.truth_at(TimeUs::from_secs_f64(t0 + tau));
                worst = worst.max((truth.pos_ned_m[0] - pos[0] - d[0]).abs()).max((truth.pos_ned_m[1] - pos[1] - d[1]).abs());
                assert_eq!(truth.pos_ned_m[2], -2.0);
            }
            let d = closed_form_ne(v, y, seg.accel_m_s2, r, seg.duration_s);
            pos = [pos[0] + d[0], pos[1] + d[1]];
            v += seg.accel_m_s2 * seg.duration_s;
            y += r * seg.duration_s;
            t0 += seg.duration_s;
        }
        assert!(worst < 1e-9, "worst position error {worst} m");
        let end = traj.truth_at(TimeUs::from_secs_f64(380.0));
        assert!((end.speed_m_s - v).abs() < 1e-12 && (end.yaw_rad - wrap_angle(y)).abs() < 1e-12);
    }

    #[test]
    fn state_is_continuous_across_segment_boundaries() {
        let (_, trajs) = small();
        let traj = &trajs[0];
        for boundary_us in [3_000_000u64, 7_000_000] {
            let before = traj.truth_at(TimeUs(boundary_us - 1));
            let at = traj.truth_at(TimeUs(boundary_us));
            // One microsecond apart: position moves by about v * 1e-6, velocity by a * 1e-6.
            assert!((at.pos_ned_m - before.pos_ned_m - before.vel_ned_m_s * 1e-6).norm() < 1e-9);
            assert!((at.vel_ned_m_s - before.vel_ned_m_s).norm() < 1e-5);
            assert!((at.speed_m_s - before.speed_m_s).abs() < 1e-5);
            assert!(wrap_angle(at.yaw_rad - before.yaw_rad).abs() < 1e-6);
            // The new segment's acceleration and yaw rate take over at the boundary.
            assert_ne!(at.accel_m_s2, before.accel_m_s2);
        }
        let boundary = traj.truth_at(TimeUs(3_000_000));
        assert_eq!(boundary.accel_m_s2, -0.3);
        assert!((boundary.yaw_rate_rad_s - 6f64.to_radians()).abs() < 1e-15);
    }

    #[test]
    fn velocity_is_the_derivative_of_position_and_attitude_matches_yaw() {
        let (_, trajs) = small();
        for traj in &trajs {
            for t_us in [500_000u64, 2_999_000, 4_321_000, 9_000_000] {
                let h = 1_000u64;
                let (a, m, b) = (traj.truth_at(TimeUs(t_us - h)), traj.truth_at(TimeUs(t_us)), traj.truth_at(TimeUs(t_us + h)));
                let fd = (b.pos_ned_m - a.pos_ned_m) / (2.0 * h as f64 * 1e-6);
                assert!((fd - m.vel_ned_m_s).norm() < 1e-6, "{fd} vs {}", m.vel_ned_m_s);
                let fwd = m.attitude * Vector3::x();
                assert!((fwd * m.speed_m_s - m.vel_ned_m_s).norm() < 1e-12);
            }
        }
    }

    #[test]
    fn imu_increments_match_brute_force_integration_of_truth() {
        // Independent route: evaluate the defining formulas from truth_at's velocity, yaw and
        // rates at many points (composite Simpson, 1000 panels per piece, split by hand at the
        // 3 s segment boundary) and compare with the quadrature, over intervals that end at,
        // straddle, or avoid a boundary.
        let (s, trajs) = small();
        let earth = Earth::new(s.latitude_deg, s.gravity_m_s2);
        let traj = &trajs[0];
        // Defining rates at t; `left` takes the limit from the left (1 us earlier: the rates'
        // derivatives are below 1 per s^2, so that is exact to 1e-6 of a rate).
        let rates = |t_us: u64, left: bool| {
            let st = traj.truth_at(TimeUs(if left { t_us - 1 } else { t_us }));
            let r_t = st.attitude.inverse();
            let acc =
                st.accel_m_s2 * (st.attitude * Vector3::x()) + st.speed_m_s * st.yaw_rate_rad_s * (st.attitude * Vector3::y());
            let f_b = r_t * (acc + 2.0 * earth.rate_ned_rad_s.cross(&st.vel_ned_m_s) - earth.gravity_ned_m_s2);
            let w_b = Vector3::new(0.0, 0.0, st.yaw_rate_rad_s) + r_t * earth.rate_ned_rad_s;
            (w_b, f_b)
        };
        let simpson = |t0: u64, t1: u64| {
            let n = 1000u64;
            let h_us = (t1 - t0) / n;
            assert_eq!(h_us * n, t1 - t0);
            let (mut dth, mut dv) = (Vector3::zeros(), Vector3::zeros());
            for i in 0..=n {
                let w = if i == 0 || i == n {
                    1.0
                } else if i % 2 == 1 {
                    4.0
                } else {
                    2.0
                };
                let (w_b, f_b) = rates(t0 + i * h_us, i == n);
                dth += w * w_b;
                dv += w * f_b;
            }
            let h = h_us as f64 * 1e-6 / 3.0;
            (dth * h, dv * h)
        };
        let cases: [(u64, u64, &[u64]); 4] = [
            (2_995_000, 3_000_000, &[]),
            (2_997_000, 3_002_000, &[3_000_000]),
            (6_000_000, 6_005_000, &[]),
            (1_000_000, 2_000_000, &[]),
        ];
        for (t0, t1, cuts) in cases {
            let bounds: Vec<u64> = std::iter::once(t0).chain(cuts.iter().copied()).chain(std::iter::once(t1)).collect();
            let (mut dth, mut dv) = (Vector3::zeros(), Vector3::zeros());
            for w in bounds.windows(2) {
                let (a, b) = simpson(w[0], w[1]);
                dth += a;
                dv += b;
            }
            let (q_th, q_v) = traj.imu_increments(TimeUs(t0), TimeUs(t1));
            let (e_th, e_v) = ((q_th - dth).norm(), (q_v - dv).norm());
            assert!(e_th < 1e-15 && e_v < 1e-12, "({t0}, {t1}]: dtheta err {e_th}, dv err {e_v}");
        }
    }

    #[test]
    fn velocity_increments_close_exactly_on_a_straight_leg() {
        // With no turning, R is constant and v is linear in t, so
        // v(t1) - v(t0) = R sum(dv_k) + (g - 2 w_ie x v_mid) (t1 - t0) holds exactly.
        let (s, trajs) = small();
        let earth = Earth::new(s.latitude_deg, s.gravity_m_s2);
        let traj = &trajs[0]; // 0-3 s: accelerating at 0.5 m/s^2, yaw constant
        let (a, b) = (traj.truth_at(TimeUs(0)), traj.truth_at(TimeUs(3_000_000)));
        let mut dv_body = Vector3::zeros();
        for k in 0..600u64 {
            dv_body += traj.imu_increments(TimeUs(k * 5_000), TimeUs((k + 1) * 5_000)).1;
        }
        let v_mid = (a.vel_ned_m_s + b.vel_ned_m_s) / 2.0;
        let predicted =
            a.vel_ned_m_s + a.attitude * dv_body + (earth.gravity_ned_m_s2 - 2.0 * earth.rate_ned_rad_s.cross(&v_mid)) * 3.0;
        let err = (predicted - b.vel_ned_m_s).norm();
        assert!(err < 1e-11, "velocity closure error {err} m/s");
        // The Coriolis term matters at this level: leaving it out breaks the closure.
        let without = a.vel_ned_m_s + a.attitude * dv_body + earth.gravity_ned_m_s2 * 3.0;
        assert!((without - b.vel_ned_m_s).norm() > 1e-4);
    }

    /// A straightforward strapdown integrator of the truth IMU samples (attitude from the gyro
    /// minus Earth rate, velocity from specific force plus gravity and Coriolis, position from
    /// velocity), run from the true initial state. Any sign or frame error in the IMU model
    /// (Earth rate, Coriolis, gravity, R vs R^T) makes it drift by metres within seconds.
    #[test]
    fn strapdown_integration_of_truth_imu_reproduces_truth() {
        let (s, trajs) = small();
        let earth = Earth::new(s.latitude_deg, s.gravity_m_s2);
        let dt_us = s.imu_period_us();
        for traj in &trajs {
            let start = traj.truth_at(TimeUs(0));
            let (mut q, mut v, mut p) = (start.attitude, start.vel_ned_m_s, start.pos_ned_m);
            let mut t = 0u64;
            while t < 10_000_000 {
                let t1 = t + dt_us;
                let dt = dt_us as f64 * 1e-6;
                let (dth, dvb) = traj.imu_increments(TimeUs(t), TimeUs(t1));
                // Velocity: body increment rotated at the mid-interval attitude.
                let q_mid = UnitQuaternion::from_scaled_axis(-earth.rate_ned_rad_s * dt / 2.0)
                    * q
                    * UnitQuaternion::from_scaled_axis(dth / 2.0);
                let v_pred = v + (q_mid * dvb) + (earth.gravity_ned_m_s2 - 2.0 * earth.rate_ned_rad_s.cross(&v)) * dt;
                let v_new = v + (q_mid * dvb) + (earth.gravity_ned_m_s2 - earth.rate_ned_rad_s.cross(&(v + v_pred))) * dt;
                p += (v + v_new) * dt / 2.0;
                v = v_new;
                q = UnitQuaternion::from_scaled_axis(-earth.rate_ned_rad_s * dt) * q * UnitQuaternion::from_scaled_axis(dth);
                t = t1;
            }
            let end = traj.truth_at(TimeUs(t));
            let att_err = (end.attitude.inverse() * q).scaled_axis().norm();
            let (v_err, p_err) = ((v - end.vel_ned_m_s).norm(), (p - end.pos_ned_m).norm());
            assert!(att_err < 1e-10, "platform {}: attitude error {att_err} rad", traj.id());
            assert!(v_err < 1e-6, "platform {}: velocity error {v_err} m/s", traj.id());
            assert!(p_err < 1e-5, "platform {}: position error {p_err} m", traj.id());
        }
    }

    #[test]
    fn stationary_imu_senses_gravity_and_earth_rate_exactly() {
        let spec: PlatformSpec = toml::from_str(
            "id = 1\nstart_ned_m = [0.0, 0.0, 0.0]\nstart_yaw_deg = 90.0\nstart_speed_m_s = 0.0\n\
             segments = [{ duration_s = 1.0, accel_m_s2 = 0.0, yaw_rate_deg_s = 0.0 }]",
        )
        .unwrap();
        let earth = Earth::new(34.7, 9.8);
        let traj = Trajectory::new(&spec, earth);
        let m = traj.imu_mean(TimeUs(0), TimeUs(5_000));
        assert!((m.specific_force_frd_m_s2 - Vector3::new(0.0, 0.0, -9.8)).norm() < 1e-14);
        // Facing east: body x = east, body y = south, so north Earth rate shows on -y.
        let l = 34.7f64.to_radians();
        let expect = EARTH_RATE_RAD_S * Vector3::new(0.0, -l.cos(), -l.sin());
        assert!((m.angular_rate_frd_rad_s - expect).norm() < 1e-18, "{}", m.angular_rate_frd_rad_s);
        assert_eq!(m.t, TimeUs(5_000));
    }
}
