//! The paper's experiment (section 4) as a Monte Carlo comparison of every method on the same
//! simulated inputs. Pure computation: the world of [`crate::sitl`], the INS of
//! [`crate::estimation::ins`], and a [`Team`] per method; files and plots are in [`report`].
//!
//! One run draws every sensor error and noise once ([`World::run_inputs`]); each method then
//! filters exactly those samples, and each ranging schedule adds its ranges (the ranges of the
//! four-event schedule are the 1 Hz ranges at those epochs). Dead reckoning ignores ranges, so it
//! runs once per run and serves both schedules.

pub mod faults;
mod plots;
pub mod report;

use nalgebra::{DVector, Vector3};
use serde::Serialize;

use crate::estimation::consistency::nees;
use crate::estimation::ins::{self, InsConfig, InsInitialSigma, InsState};
use crate::estimation::nav::{Drive, NavFilter, NavModel, NavState};
use crate::estimation::unicycle::wrap_angle;
use crate::estimation::{CoopMeasurement, EstimationError, Method, PlatformFilter, PlatformId, RangeSample, Team};
use crate::sitl::scenario::{Scenario, ScenarioError};
use crate::sitl::world::{PlatformRun, RunInputs, World};
use crate::time::TimeUs;

/// What went wrong in an experiment.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error("run {run}, method {method}, platform {platform}, t = {t}: {source}")]
    Filter { run: u32, method: Method, platform: PlatformId, t: TimeUs, source: EstimationError },
    #[error("invalid experiment settings: {0}")]
    Settings(String),
}

/// The filter settings a scenario implies: its sensor numbers become the INS noise model and
/// initial uncertainty (every number lives in the scenario file).
pub fn ins_settings(world: &World) -> (InsConfig, InsInitialSigma) {
    let s: &Scenario = world.scenario();
    crate::node::profile::VehicleProfile::from_spec(&s.vehicle()).ins_settings(s.latitude_deg)
}

/// The navigation model platform `id` runs: the INS of [`ins_settings`], or, for a wheeled
/// robot, the planar filter with the noise of the scenario's `[wheels]` and its `[initial]`
/// position and yaw sigmas.
pub fn nav_model(world: &World, id: PlatformId) -> NavModel {
    let s = world.scenario();
    crate::node::profile::VehicleProfile::from_spec(&s.vehicle_of(id)).nav_model(s.latitude_deg)
}

/// Platform `id`'s initial state in run `run` for its model ([`initial_state`]; a wheeled
/// robot keeps the position and the heading).
pub fn initial_nav_state(world: &World, seed: u64, run: u32, id: PlatformId) -> Result<(TimeUs, NavState), ScenarioError> {
    let (t0, s) = initial_state(world, seed, run, id)?;
    Ok((t0, NavState::for_model(&nav_model(world, id), s)))
}

/// A platform's initial filter state in run `run` (truth at time zero plus the errors the
/// scenario's `[initial]` sigmas draw; zero biases and scale error), and its time.
pub fn initial_state(world: &World, seed: u64, run: u32, id: PlatformId) -> Result<(TimeUs, InsState), ScenarioError> {
    state_from(world.initial_estimate(seed, run, id)?)
}

/// The filter state of an initial estimate drawn at any time (see [`World::estimate_at`]).
pub fn state_from(init: crate::sitl::world::InitialEstimate) -> Result<(TimeUs, InsState), ScenarioError> {
    Ok((init.truth.t, init.ins_state()))
}

/// Error of one platform's estimate at one instant.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ErrorSample {
    pub t_s: f64,
    /// Horizontal (N, E) position error, m.
    pub pos_err_m: f64,
    /// The same as a vector, truth minus estimate, N and E, m.
    pub pos_err_ne_m: [f64; 2],
    /// Yaw error, degrees (truth minus estimate).
    pub heading_err_deg: f64,
}

/// One platform's outcome in one filter run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlatformOutcome {
    pub id: PlatformId,
    /// Error at every truth sample.
    pub trace: Vec<ErrorSample>,
    /// NEES of the 15 navigation and bias error states at the end of the run (a wheeled
    /// robot: its 3 states).
    pub final_nees: f64,
    /// How many error states that NEES has (its chi-square degrees of freedom).
    pub nees_states: usize,
    /// Estimated horizontal track at every truth sample (N, E), m.
    pub track_ne_m: Vec<[f64; 2]>,
    /// The filter's position at its last input, and that input's time (what a node reports at
    /// the end of the same inputs).
    #[serde(skip)]
    pub final_position_ned_m: Vector3<f64>,
    #[serde(skip)]
    pub final_t: TimeUs,
}

impl PlatformOutcome {
    pub fn final_error(&self) -> ErrorSample {
        *self.trace.last().expect("a run has at least one truth sample")
    }
}

/// One method's filter run over one run's inputs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FilterRun {
    pub method: Method,
    pub platforms: Vec<PlatformOutcome>,
}

/// The error state of an estimate against the truth, and its covariance: the INS's 15 states
/// (no odometer scale), the planar robot's 3.
fn final_error(nav: &NavFilter, run: &PlatformRun, k: usize) -> (DVector<f64>, nalgebra::DMatrix<f64>) {
    let truth = &run.truth[k];
    let d = truth.pos_ned_m - position_at(nav, truth.t);
    let f = match nav {
        NavFilter::Ins(f) => f,
        NavFilter::Planar(p) => {
            let e = DVector::from_vec(vec![d[0], d[1], wrap_angle(truth.yaw_rad - p.yaw_rad())]);
            return (e, p.covariance());
        }
    };
    let x = f.state();
    let mut e = DVector::zeros(15);
    e.fixed_rows_mut::<3>(ins::POS).copy_from(&d);
    e.fixed_rows_mut::<3>(ins::VEL).copy_from(&(truth.vel_ned_m_s - x.vel_ned_m_s));
    e.fixed_rows_mut::<3>(ins::ATT).copy_from(&ins::attitude_error_ned(&truth.attitude, &x.att_frd_to_ned));
    // the biases at the end of the run: error15 is taken there (they walk when configured)
    e.fixed_rows_mut::<3>(ins::ACCEL_BIAS).copy_from(&(run.final_errors.accel_bias_m_s2 - x.accel_bias_frd_m_s2));
    e.fixed_rows_mut::<3>(ins::GYRO_BIAS).copy_from(&(run.final_errors.gyro_bias_rad_s - x.gyro_bias_frd_rad_s));
    (e, f.covariance().view((0, 0), (15, 15)).into_owned())
}

/// The filter's position at `t`, moved from its own time along its velocity: a truth sample
/// that falls between two IMU samples (an autopilot's IMU stamps need not fall on the truth
/// grid) is compared with the estimate at the truth's instant. Zero shift on the grid.
fn position_at(f: &NavFilter, t: TimeUs) -> Vector3<f64> {
    let dt = t.secs_since(f.time());
    if dt == 0.0 { f.position_ned_m() } else { f.position_ned_m() + f.velocity_ned_m_s() * dt }
}

fn error_sample(f: &NavFilter, run: &PlatformRun, k: usize) -> ErrorSample {
    let truth = &run.truth[k];
    let d = truth.pos_ned_m - position_at(f, truth.t);
    ErrorSample {
        t_s: truth.t.as_secs_f64(),
        pos_err_m: d.xy().norm(),
        pos_err_ne_m: [d[0], d[1]],
        heading_err_deg: wrap_angle(truth.yaw_rad - f.yaw_rad()).to_degrees(),
    }
}

/// Runs one method over one run's inputs and ranging epochs.
pub fn run_filter(
    world: &World,
    inputs: &RunInputs,
    ranges: &[(TimeUs, Vec<RangeSample>)],
    method: Method,
) -> Result<FilterRun, ExperimentError> {
    let fail = |platform, t, source| ExperimentError::Filter { run: inputs.run, method, platform, t, source };
    let mut members = Vec::new();
    for p in &inputs.platforms {
        let (t0, state) = initial_nav_state(world, inputs.seed, inputs.run, p.id)?;
        members.push((p.id, NavFilter::new(nav_model(world, p.id), t0, state).map_err(|e| fail(p.id, t0, e))?));
    }
    // A platform is driven by its IMU samples, or a wheeled robot by its wheel samples.
    let drive = |p: &PlatformRun, k: usize| {
        if p.wheel.is_empty() { p.imu.get(k).copied().map(Drive::Imu) } else { p.wheel.get(k).copied().map(Drive::Wheel) }
    };
    let drive_t =
        |p: &PlatformRun, k: usize| if p.wheel.is_empty() { p.imu.get(k).map(|s| s.t) } else { p.wheel.get(k).map(|s| s.t) };
    let mut team = Team::new(method, members).map_err(|e| fail(0, TimeUs(0), e))?;
    let n = inputs.platforms.len();
    let mut outcomes: Vec<PlatformOutcome> = inputs
        .platforms
        .iter()
        .map(|p| PlatformOutcome {
            id: p.id,
            trace: Vec::with_capacity(p.truth.len()),
            final_nees: f64::NAN,
            nees_states: 0,
            track_ne_m: Vec::with_capacity(p.truth.len()),
            final_position_ned_m: Vector3::zeros(),
            final_t: TimeUs(0),
        })
        .collect();
    // Cursors into each platform's samples, and into the ranging epochs.
    let (mut imu, mut odo, mut truth) = (vec![0usize; n], vec![0usize; n], vec![0usize; n]);
    let mut epoch = 0usize;
    loop {
        // The next instant anything happens.
        let mut t = TimeUs(u64::MAX);
        for (i, p) in inputs.platforms.iter().enumerate() {
            for next in [drive_t(p, imu[i]), p.odometer.get(odo[i]).map(|s| s.t), p.truth.get(truth[i]).map(|s| s.t)]
                .into_iter()
                .flatten()
            {
                t = t.min(next);
            }
        }
        if let Some((te, _)) = ranges.get(epoch) {
            t = t.min(*te);
        }
        if t == TimeUs(u64::MAX) {
            break;
        }
        // IMU, then odometer, then ranges, then the truth comparison: all of one instant. A
        // platform with a measurement at `t` between two IMU samples is propagated to `t` first,
        // holding the next sample's rates over the cut (as a node does).
        let epoch_now = ranges.get(epoch).is_some_and(|(te, _)| *te == t);
        for (i, p) in inputs.platforms.iter().enumerate() {
            let Some(s) = drive(p, imu[i]) else { continue };
            let f = team.filter_mut(p.id).expect("member");
            if s.t() == t {
                f.propagate(&s).map_err(|e| fail(p.id, t, e))?;
                imu[i] += 1;
            } else if f.time() < t && (epoch_now || p.odometer.get(odo[i]).is_some_and(|o| o.t == t)) {
                f.propagate(&s.at(t)).map_err(|e| fail(p.id, t, e))?;
            }
        }
        let mut batch = Vec::new();
        for (i, p) in inputs.platforms.iter().enumerate() {
            if let Some(s) = p.odometer.get(odo[i]).filter(|s| s.t == t) {
                batch.push((p.id, team.filter(p.id).expect("member").odometer_measurement(s).map_err(|e| fail(p.id, t, e))?));
                odo[i] += 1;
            }
        }
        if !batch.is_empty() {
            team.local_updates(&batch).map_err(|e| fail(batch[0].0, t, e))?;
        }
        if let Some((te, samples)) = ranges.get(epoch).filter(|(te, _)| *te == t) {
            let meas: Vec<CoopMeasurement> = samples.iter().map(CoopMeasurement::from).collect();
            team.cooperative_event(&meas).map_err(|e| fail(samples.first().map_or(0, |r| r.from), *te, e))?;
            epoch += 1;
        }
        for (i, p) in inputs.platforms.iter().enumerate() {
            if p.truth.get(truth[i]).is_some_and(|s| s.t == t) {
                let f = team.filter(p.id).expect("member");
                outcomes[i].trace.push(error_sample(f, p, truth[i]));
                let pos = f.position_ned_m();
                outcomes[i].track_ne_m.push([pos[0], pos[1]]);
                truth[i] += 1;
            }
        }
    }
    for (i, p) in inputs.platforms.iter().enumerate() {
        let f = team.filter(p.id).expect("member");
        let (e, cov) = final_error(f, p, p.truth.len() - 1);
        outcomes[i].final_position_ned_m = f.position_ned_m();
        outcomes[i].final_t = f.time();
        outcomes[i].nees_states = e.len();
        outcomes[i].final_nees = nees(&e, &cov).map_err(|e| fail(p.id, f.time(), e))?;
    }
    Ok(FilterRun { method, platforms: outcomes })
}

/// Where a run's filter inputs come from.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum InputSource {
    /// The world's samples as they are (the paper's experiment).
    #[default]
    World,
    /// As an autopilot sends them and a node decodes them (see
    /// [`crate::simulator::personality::decoded_run`]).
    Autopilot {
        autopilot: crate::simulator::personality::Autopilot,
        inputs: crate::node::profile::Inputs,
        rates: Vec<(u32, f64)>,
    },
}

/// What to run.
#[derive(Debug, Clone, PartialEq)]
pub struct ExperimentSpec {
    pub runs: u32,
    pub seed: u64,
    pub methods: Vec<Method>,
    /// Names of ranging schedules of the scenario.
    pub schedules: Vec<String>,
    pub source: InputSource,
}

/// Every filter run of one Monte Carlo run, by schedule.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunResult {
    pub run: u32,
    /// `(schedule, filter runs in the spec's method order)`.
    pub schedules: Vec<(String, Vec<FilterRun>)>,
}

/// One Monte Carlo run: inputs drawn once, every method over every schedule.
pub fn run_once(world: &World, spec: &ExperimentSpec, run: u32) -> Result<RunResult, ExperimentError> {
    let mut inputs = world.run_inputs(spec.seed, run);
    let mut dead_reckoning = None;
    let mut schedules = Vec::new();
    for name in &spec.schedules {
        let ranges = match &spec.source {
            InputSource::World => world.ranges(name, spec.seed, run)?,
            InputSource::Autopilot { autopilot, inputs: profile_inputs, rates } => {
                let (decoded, ranges) =
                    crate::simulator::personality::decoded_run(world, spec.seed, run, name, *autopilot, profile_inputs, rates)
                        .map_err(ExperimentError::Settings)?;
                inputs = decoded;
                ranges
            }
        };
        let mut runs = Vec::new();
        for &method in &spec.methods {
            let r = if method == Method::DeadReckoning {
                match &dead_reckoning {
                    Some(r) => Clone::clone(r),
                    None => {
                        let r = run_filter(world, &inputs, &[], method)?;
                        dead_reckoning = Some(r.clone());
                        r
                    }
                }
            } else {
                run_filter(world, &inputs, &ranges, method)?
            };
            runs.push(r);
        }
        schedules.push((name.clone(), runs));
    }
    Ok(RunResult { run, schedules })
}

impl RunResult {
    /// Keeps of every filter run only its final sample (the trace's last, what the tables and
    /// `final_errors.csv` read) and frees its estimated track: what a Monte Carlo keeps of the
    /// runs it does not plot, once their curves are summed ([`report::CurveSums`]).
    pub fn keep_final_only(&mut self) {
        for p in self.schedules.iter_mut().flat_map(|(_, runs)| runs).flat_map(|r| &mut r.platforms) {
            let last = p.trace.last().copied();
            p.trace = last.into_iter().collect();
            p.track_ne_m = Vec::new();
        }
    }
}

/// A Monte Carlo's results: every run in run order, the first whole (the one plotted), the others
/// with their final samples only ([`RunResult::keep_final_only`]), and the per-instant sums of
/// every run's squared errors that the RMS curves are made of.
#[derive(Debug, Clone)]
pub struct MonteCarlo {
    pub runs: Vec<RunResult>,
    pub curves: report::CurveSums,
}

/// Runs the whole Monte Carlo in parallel (rayon, all cores); `progress` is called after each run.
/// Runs finish in any order; each is summed into the curves in run order (the same sums in the
/// same order as over the whole results, so the same bits) as soon as the runs before it are,
/// then trimmed to its final samples. A 1,000-run study of the paper scenario held 6 GB of
/// traces and tracks to the end before; now only the runs waiting for an earlier one (about
/// one per thread).
pub fn run_experiment(world: &World, spec: &ExperimentSpec, progress: &(dyn Fn() + Sync)) -> Result<MonteCarlo, ExperimentError> {
    use rayon::prelude::*;
    if spec.runs == 0 {
        return Err(ExperimentError::Settings("at least one run is needed".into()));
    }
    if spec.methods.is_empty() {
        return Err(ExperimentError::Settings("at least one method is needed".into()));
    }
    for name in &spec.schedules {
        world.scenario().schedule(name)?;
    }
    struct InOrder {
        waiting: std::collections::BTreeMap<u32, RunResult>,
        done: Vec<RunResult>,
        curves: report::CurveSums,
    }
    let state = std::sync::Mutex::new(InOrder {
        waiting: std::collections::BTreeMap::new(),
        done: Vec::with_capacity(spec.runs as usize),
        curves: report::CurveSums::default(),
    });
    // Runs are taken in order by whichever thread is free (`par_bridge`, not a split range, whose
    // upper half would finish while the lower is still running and wait in full).
    (0..spec.runs).par_bridge().try_for_each(|run| {
        let r = run_once(world, spec, run)?;
        {
            let mut st = state.lock().unwrap_or_else(|e| e.into_inner());
            st.waiting.insert(run, r);
            loop {
                let next = st.done.len() as u32;
                let Some(mut r) = st.waiting.remove(&next) else { break };
                st.curves.add(&r);
                if next > 0 {
                    r.keep_final_only();
                }
                st.done.push(r);
            }
        }
        progress();
        Ok::<(), ExperimentError>(())
    })?;
    let st = state.into_inner().unwrap_or_else(|e| e.into_inner());
    Ok(MonteCarlo { runs: st.done, curves: st.curves })
}
