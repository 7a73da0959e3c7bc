//! The node's last navigation state on disk (`cooploc node --state-file FILE`), so that a node
//! restarted with the arguments of its first start (by its supervisor, after a crash or a
//! reboot of the companion) starts from where its vehicle was a moment ago instead of from a
//! stale start state. Sans-io: the text of the file in, the state to start from out; the runner
//! reads and writes the file (whole or not at all, a temporary file renamed over it).
//!
//! The shell writes the filter's nominal state and error covariance every [`SAVE_EVERY_US`] of
//! the team clock and at the end. At start, the saved state is taken at the vehicle's first
//! sample `t1` when it is for this platform, this model and this origin, and `t1` is at most
//! [`MAX_RESTORE_AGE_US`] after it; it is then carried across the gap by
//! [`coast`](crate::estimation::coast::coast) (constant velocity, the covariance grown by what a
//! land vehicle can do meanwhile). Anything else is refused with its reason, and the node starts
//! as it would have without the file.

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

use crate::estimation::coast::{CoastBounds, GapDrift, GapFix, coast, coast_to_fix};
use crate::estimation::ins::InsState;
use crate::estimation::nav::{NavFilter, NavModel, NavState};
use crate::estimation::planar::PlanarState;
use crate::estimation::{PlatformFilter, PlatformId};
use crate::geodesy::GeoOrigin;
use crate::time::TimeUs;

/// How often the state is written (team clock), us.
pub const SAVE_EVERY_US: u64 = 1_000_000;

/// The oldest saved state a node restores, against its vehicle's first sample, us. Beyond it the
/// coasted covariance (hundreds of metres) says the state is worth nothing.
pub const MAX_RESTORE_AGE_US: u64 = 30_000_000;

/// The file's format version.
pub const FORMAT: u32 = 1;

/// The nominal state, by model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case")]
pub enum SavedNominal {
    Ins(InsState),
    Planar(PlanarState),
}

/// One saved state: what the file holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SavedState {
    pub format: u32,
    pub platform: PlatformId,
    /// Team clock, us.
    pub t_us: u64,
    /// The NED frame's origin: latitude, longitude (deg), altitude (m).
    pub origin: [f64; 3],
    pub nominal: SavedNominal,
    /// The error covariance, row by row (`n x n`: 16 for the INS, 3 for the planar robot).
    pub covariance: Vec<f64>,
    /// When it was written, by the companion's Unix clock, us (absent in files of older nodes):
    /// a team clock that is the autopilot's boot clock cannot tell a file of the boot before.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub written_unix_us: Option<u64>,
}

impl SavedState {
    /// The state of `filter` (platform `id`, about `origin`) now.
    pub fn of(id: PlatformId, origin: &GeoOrigin, filter: &NavFilter) -> SavedState {
        let nominal = match filter {
            NavFilter::Ins(f) => SavedNominal::Ins(*f.state()),
            NavFilter::Planar(f) => SavedNominal::Planar(f.state()),
        };
        let p = filter.covariance();
        SavedState {
            format: FORMAT,
            platform: id,
            t_us: filter.time().0,
            origin: [origin.lat_deg, origin.lon_deg, origin.alt_m],
            nominal,
            covariance: p.transpose().as_slice().to_vec(),
            written_unix_us: None,
        }
    }

    /// The same, written at `unix_us` by the companion's clock (0: the clock is not set).
    pub fn written_at(self, unix_us: u64) -> SavedState {
        SavedState { written_unix_us: (unix_us > 0).then_some(unix_us), ..self }
    }

    /// Why a file written by the companion's clock more than [`MAX_RESTORE_AGE_US`] before
    /// `now_unix_us` is not restored; None when it is younger, or when either time is unknown or
    /// the clock is behind the file's (a companion without a real-time clock after a reboot: the
    /// team clock's check alone decides then).
    pub fn wall_age_refusal(&self, now_unix_us: u64) -> Option<String> {
        let written = self.written_unix_us?;
        let age = now_unix_us.checked_sub(written)?;
        (now_unix_us > 0 && age > MAX_RESTORE_AGE_US).then(|| {
            format!(
                "written {:.1} s ago by the companion's clock (at most {:.0} s): the vehicle has gone on since",
                age as f64 / 1e6,
                MAX_RESTORE_AGE_US as f64 / 1e6
            )
        })
    }

    /// The file's text.
    pub fn to_text(&self) -> String {
        serde_json::to_string(self).expect("a saved state is plain numbers") + "\n"
    }

    /// Reads and checks a file's text: every number finite, the quaternion a rotation, the
    /// covariance square, symmetric and positive semi-definite (a state the model does not
    /// estimate, such as an odometer scale with no error, has zero variance).
    pub fn parse(text: &str) -> Result<SavedState, String> {
        let s: SavedState = serde_json::from_str(text).map_err(|e| format!("not a saved state: {e}"))?;
        if s.format != FORMAT {
            return Err(format!("format {} (this node reads {FORMAT})", s.format));
        }
        if !s.origin.iter().all(|v| v.is_finite()) || s.origin[0].abs() > 90.0 || s.origin[1].abs() > 180.0 {
            return Err(format!("origin {:?} is no latitude, longitude and altitude", s.origin));
        }
        let numbers: Vec<f64> = match &s.nominal {
            SavedNominal::Ins(x) => {
                let q = x.att_frd_to_ned.quaternion();
                if (q.norm() - 1.0).abs() > 1e-6 {
                    return Err(format!("attitude quaternion of norm {} is no rotation", q.norm()));
                }
                [x.pos_ned_m, x.vel_ned_m_s, x.accel_bias_frd_m_s2, x.gyro_bias_frd_rad_s]
                    .iter()
                    .flat_map(|v| v.iter().copied())
                    .chain([x.odometer_scale_error])
                    .collect()
            }
            SavedNominal::Planar(x) => x.pos_ned_m.iter().copied().chain([x.yaw_rad]).collect(),
        };
        if !numbers.iter().all(|v| v.is_finite()) {
            return Err("a state value is not finite".into());
        }
        let position = s.nav_state().position_ned_m();
        if position.norm() > 1e7 {
            return Err(format!("position {:.0} m from the origin", position.norm()));
        }
        let n = s.dim();
        if s.covariance.len() != n * n {
            return Err(format!("covariance of {} values, {} expected", s.covariance.len(), n * n));
        }
        let p = s.covariance_matrix();
        if !p.iter().all(|v| v.is_finite()) {
            return Err("a covariance value is not finite".into());
        }
        if (&p - p.transpose()).amax() > 1e-9 * p.amax().max(1e-300) {
            return Err("covariance not symmetric".into());
        }
        if !crate::estimation::kalman::is_psd(&p, 1e-9) {
            return Err("covariance not positive semi-definite".into());
        }
        Ok(s)
    }

    fn dim(&self) -> usize {
        match self.nominal {
            SavedNominal::Ins(_) => crate::estimation::ins::ERROR_DIM,
            SavedNominal::Planar(_) => 3,
        }
    }

    pub fn covariance_matrix(&self) -> DMatrix<f64> {
        let n = self.dim();
        DMatrix::from_row_slice(n, n, &self.covariance)
    }

    pub fn nav_state(&self) -> NavState {
        match self.nominal {
            SavedNominal::Ins(x) => NavState::Ins(x),
            SavedNominal::Planar(x) => NavState::Planar(x),
        }
    }

    pub fn geo_origin(&self) -> GeoOrigin {
        GeoOrigin { lat_deg: self.origin[0], lon_deg: self.origin[1], alt_m: self.origin[2] }
    }

    /// The state and covariance to start platform `id` (running `model`, about `origin`) from at
    /// its vehicle's first sample `t1`, carried across the gap; or why not.
    pub fn restore_at(
        &self,
        id: PlatformId,
        model: &NavModel,
        origin: &GeoOrigin,
        t1: TimeUs,
        bounds: &CoastBounds,
    ) -> Result<(NavState, DMatrix<f64>), String> {
        let age = self.age_at(id, model, origin, t1)?;
        coast(&self.nav_state(), &self.covariance_matrix(), age as f64 / 1e6, bounds).map_err(|e| e.to_string())
    }

    /// The same, given what the autopilot's estimate says at `t1` ([`super::autopilot_fix`]):
    /// its heading, and its position and velocity when it vouches for them, grown from the
    /// saved state's by the drift of the IMU `model` describes ([`GapDrift::of_model`]), the
    /// rest as [`Self::restore_at`] with `land`.
    pub fn restore_to_fix(
        &self,
        id: PlatformId,
        model: &NavModel,
        origin: &GeoOrigin,
        t1: TimeUs,
        land: &CoastBounds,
        fix: &GapFix,
    ) -> Result<(NavState, DMatrix<f64>), String> {
        let age = self.age_at(id, model, origin, t1)?;
        let drift = GapDrift::of_model(model);
        coast_to_fix(&self.nav_state(), &self.covariance_matrix(), age as f64 / 1e6, land, &drift, fix).map_err(|e| e.to_string())
    }

    /// How long before `t1` the state was saved, us, when it is for platform `id`, `model` and
    /// `origin`, of this clock and at most [`MAX_RESTORE_AGE_US`] old.
    fn age_at(&self, id: PlatformId, model: &NavModel, origin: &GeoOrigin, t1: TimeUs) -> Result<u64, String> {
        if self.platform != id {
            return Err(format!("saved by platform {}, this is {id}", self.platform));
        }
        let kind = match self.nominal {
            SavedNominal::Ins(_) => "ins",
            SavedNominal::Planar(_) => "planar",
        };
        if kind != model.name() {
            return Err(format!("saved by the {kind} model, this node runs the {} model", model.name()));
        }
        let o = self.geo_origin();
        if (o.lat_deg - origin.lat_deg).abs() > 1e-7
            || (o.lon_deg - origin.lon_deg).abs() > 1e-7
            || (o.alt_m - origin.alt_m).abs() > 0.01
        {
            return Err(format!(
                "saved about the origin {:.7}, {:.7}, {:.2} m; this node's is {:.7}, {:.7}, {:.2} m",
                o.lat_deg, o.lon_deg, o.alt_m, origin.lat_deg, origin.lon_deg, origin.alt_m
            ));
        }
        if t1.0 < self.t_us {
            return Err(format!(
                "saved at t {} us, after the vehicle's first sample at {} us (another clock: the autopilot rebooted?)",
                self.t_us, t1.0
            ));
        }
        let age = t1.0 - self.t_us;
        if age > MAX_RESTORE_AGE_US {
            return Err(format!("{:.1} s old (at most {:.0} s)", age as f64 / 1e6, MAX_RESTORE_AGE_US as f64 / 1e6));
        }
        Ok(age)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::ins::{InsConfig, InsInitialSigma};
    use nalgebra::{UnitQuaternion, Vector3};

    const ORIGIN: GeoOrigin = GeoOrigin { lat_deg: 34.7, lon_deg: 113.6, alt_m: 100.0 };

    fn model() -> NavModel {
        NavModel::Ins { config: InsConfig::default(), initial_sigma: InsInitialSigma::for_tests() }
    }

    fn filter() -> NavFilter {
        let state = InsState {
            pos_ned_m: Vector3::new(120.0, -40.0, 0.5),
            vel_ned_m_s: Vector3::new(5.0, 8.66, 0.0),
            att_frd_to_ned: UnitQuaternion::from_euler_angles(0.0, 0.0, 1.047),
            accel_bias_frd_m_s2: Vector3::new(1e-3, 0.0, 0.0),
            gyro_bias_frd_rad_s: Vector3::zeros(),
            odometer_scale_error: 0.0,
        };
        NavFilter::new(model(), TimeUs(50_000_000), NavState::Ins(state)).unwrap()
    }

    #[test]
    fn a_saved_state_reads_back_exactly() {
        let f = filter();
        let saved = SavedState::of(3, &ORIGIN, &f);
        let back = SavedState::parse(&saved.to_text()).unwrap();
        assert_eq!(back, saved);
        assert_eq!(back.covariance_matrix(), f.covariance());
        assert_eq!(back.t_us, 50_000_000);
        // restored at its own time: exactly the filter's state and covariance
        let (state, p) = back.restore_at(3, &model(), &ORIGIN, TimeUs(50_000_000), &CoastBounds::LAND).unwrap();
        assert_eq!(state, NavState::Ins(*f.ins().unwrap().state()));
        assert!((p - f.covariance()).amax() < 1e-15);
    }

    #[test]
    fn a_state_restored_later_has_moved_on_and_grown() {
        let saved = SavedState::of(3, &ORIGIN, &filter());
        let (state, p) = saved.restore_at(3, &model(), &ORIGIN, TimeUs(52_000_000), &CoastBounds::LAND).unwrap();
        let NavState::Ins(x) = state else { panic!("an INS state") };
        assert!((x.pos_ned_m - Vector3::new(130.0, -22.68, 0.5)).norm() < 1e-9);
        let before = saved.covariance_matrix();
        // 2 s at 2 m/s^2: 4 m of position sigma added per axis (in quadrature, with the velocity's share)
        assert!(p[(0, 0)] > before[(0, 0)] + 15.9);
        assert!(p[(3, 3)] > before[(3, 3)] + 15.9);
    }

    #[test]
    fn a_state_of_another_platform_model_origin_or_clock_is_refused_with_its_reason() {
        let saved = SavedState::of(3, &ORIGIN, &filter());
        let at = |id, origin: &GeoOrigin, t| saved.restore_at(id, &model(), origin, TimeUs(t), &CoastBounds::LAND);
        assert!(at(2, &ORIGIN, 50_000_000).unwrap_err().contains("platform 3"));
        let elsewhere = GeoOrigin { lat_deg: 34.8, ..ORIGIN };
        assert!(at(3, &elsewhere, 50_000_000).unwrap_err().contains("origin"));
        assert!(at(3, &ORIGIN, 49_999_999).unwrap_err().contains("rebooted"));
        assert!(at(3, &ORIGIN, 50_000_000 + MAX_RESTORE_AGE_US + 1).unwrap_err().contains("s old"));
        assert!(at(3, &ORIGIN, 50_000_000 + MAX_RESTORE_AGE_US).is_ok());
        let planar = NavModel::Planar {
            config: crate::estimation::planar::PlanarConfig::from_sample_sigmas(0.05, 0.01, 20.0),
            initial_sigma: crate::estimation::planar::PlanarSigma { pos_m: 0.1, yaw_rad: 0.01 },
        };
        let e = saved.restore_at(3, &planar, &ORIGIN, TimeUs(50_000_000), &CoastBounds::LAND).unwrap_err();
        assert!(e.contains("planar"), "{e}");
    }

    #[test]
    fn a_file_written_long_ago_by_the_companions_clock_is_refused() {
        let saved = SavedState::of(3, &ORIGIN, &filter()).written_at(1_000_000_000_000_000);
        assert_eq!(SavedState::parse(&saved.to_text()).unwrap(), saved);
        assert_eq!(saved.wall_age_refusal(1_000_000_000_000_000 + MAX_RESTORE_AGE_US), None);
        let why = saved.wall_age_refusal(1_000_000_000_000_000 + MAX_RESTORE_AGE_US + 1).unwrap();
        assert!(why.contains("companion's clock"), "{why}");
        // a clock behind the file's, an unset clock, a file of an older node: not judged
        assert_eq!(saved.wall_age_refusal(5), None);
        assert_eq!(saved.wall_age_refusal(0), None);
        assert_eq!(SavedState::of(3, &ORIGIN, &filter()).wall_age_refusal(u64::MAX), None);
        assert_eq!(SavedState::of(3, &ORIGIN, &filter()).written_at(0).written_unix_us, None);
    }

    #[test]
    fn damaged_files_are_refused_with_what_is_wrong() {
        let good = SavedState::of(3, &ORIGIN, &filter());
        let text = good.to_text();
        assert!(SavedState::parse("").unwrap_err().contains("not a saved state"));
        assert!(SavedState::parse(&text[..text.len() / 2]).unwrap_err().contains("not a saved state"));
        let with = |f: &dyn Fn(&mut SavedState)| {
            let mut s = good.clone();
            f(&mut s);
            SavedState::parse(&serde_json::to_string(&s).unwrap())
        };
        assert!(with(&|s| s.format = 2).unwrap_err().contains("format 2"));
        assert!(with(&|s| s.origin[0] = 91.0).unwrap_err().contains("origin"));
        assert!(with(&|s| s.covariance.pop().map(drop).unwrap_or(())).unwrap_err().contains("255 values"));
        assert!(with(&|s| s.covariance[1] += 1.0).unwrap_err().contains("symmetric"));
        assert!(with(&|s| s.covariance[0] = -1.0).unwrap_err().contains("positive semi-definite"));
        assert!(
            with(&|s| if let SavedNominal::Ins(x) = &mut s.nominal {
                x.pos_ned_m[0] = 1e8
            })
            .unwrap_err()
            .contains("position")
        );
        let stretched = nalgebra::Quaternion::new(2.0, 0.0, 0.0, 0.0);
        let not_rotation = with(&|s| {
            if let SavedNominal::Ins(x) = &mut s.nominal {
                x.att_frd_to_ned = UnitQuaternion::new_unchecked(stretched)
            }
        });
        assert!(not_rotation.unwrap_err().contains("no rotation"));
        // a negative time, a fifth quaternion component: not a saved state
        assert!(SavedState::parse(&text.replacen("\"t_us\":50000000", "\"t_us\":-1", 1)).unwrap_err().contains("not a saved"));
        let five = text.replacen("\"att_frd_to_ned\":[", "\"att_frd_to_ned\":[0.5,", 1);
        assert!(SavedState::parse(&five).unwrap_err().contains("not a saved"));
    }
}
