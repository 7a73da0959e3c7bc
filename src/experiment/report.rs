//! Summaries, tables, files and plots of an experiment. Everything here derives from the
//! [`RunResult`]s; nothing is recomputed or typed in, except the paper's own figures, which are
//! printed beside ours for comparison.

use std::fmt::Write as _;
use std::path::Path;

use serde::Serialize;

use super::{ExperimentSpec, RunResult};
use crate::estimation::Method;
use crate::estimation::PlatformId;

/// The paper's section 4 figures, for the side-by-side columns.
pub const PAPER_NOTES: &[&str] = &[
    "paper, 1 Hz ranging: dead reckoning final position error 6-12 m, heading error 0.5 deg;",
    "       cooperative final position error up to 3 m (-50% to -75%), heading under 0.23 deg (-54%);",
    "paper, four events: covariance transfer vs none, position -24.1% on average (-10.3% to -49.3%),",
    "       heading -11.9% on average (-7.1% to -13.6%).",
];

/// Final-error statistics of one platform under one method, over runs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlatformStats {
    pub id: PlatformId,
    pub final_pos_err_mean_m: f64,
    pub final_pos_err_rms_m: f64,
    pub final_heading_err_mean_abs_deg: f64,
    pub final_heading_err_rms_deg: f64,
    /// Run average of the final NEES (15 states for an INS, 3 for a wheeled robot).
    pub final_nees_mean: f64,
    pub nees_states: usize,
}

/// One method under one schedule.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MethodStats {
    pub method: Method,
    pub platforms: Vec<PlatformStats>,
    /// RMS over runs of the formation-mean final position error (the average of the platforms'
    /// error vectors): the common-mode part that inter-platform ranges cannot observe.
    pub formation_mean_err_rms_m: f64,
    /// RMS over runs and platforms of each platform's final error about that mean: the part
    /// that ranges do observe.
    pub about_mean_err_rms_m: f64,
}

impl MethodStats {
    /// Average over platforms of a per-platform statistic.
    pub fn average(&self, f: impl Fn(&PlatformStats) -> f64) -> f64 {
        self.platforms.iter().map(f).sum::<f64>() / self.platforms.len() as f64
    }
}

/// Relative change of `method` against `baseline`, per platform, in percent (negative = better).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Reduction {
    pub method: Method,
    pub baseline: Method,
    pub pos_percent: Vec<f64>,
    pub heading_percent: Vec<f64>,
}

impl Reduction {
    pub fn mean(v: &[f64]) -> f64 {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// RMS over runs of the error at every truth sample.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Curve {
    pub method: Method,
    pub platform: PlatformId,
    pub t_s: Vec<f64>,
    pub pos_rms_m: Vec<f64>,
    pub heading_rms_deg: Vec<f64>,
}

/// Everything about one schedule.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScheduleSummary {
    pub schedule: String,
    pub runs: usize,
    pub methods: Vec<MethodStats>,
    pub reductions: Vec<Reduction>,
    /// 95% band of the run-averaged 15-state NEES of a consistent filter.
    pub nees_band: (f64, f64),
    #[serde(skip)]
    pub curves: Vec<Curve>,
}

impl ScheduleSummary {
    pub fn method(&self, m: Method) -> Option<&MethodStats> {
        self.methods.iter().find(|s| s.method == m)
    }
}

fn rms(v: impl Iterator<Item = f64> + Clone) -> f64 {
    let n = v.clone().count() as f64;
    (v.map(|x| x * x).sum::<f64>() / n).sqrt()
}

fn mean(v: impl Iterator<Item = f64> + Clone) -> f64 {
    let n = v.clone().count() as f64;
    v.sum::<f64>() / n
}

/// One platform's sums per instant: (position, heading).
type InstantSums = (Vec<f64>, Vec<f64>);

/// The per-instant sums over runs of each filter run's squared position and heading errors, by
/// schedule, method and platform, added one run at a time in run order: [`rms`]'s sums of each
/// instant's values in its order (the same bits), so that a Monte Carlo need not keep every
/// run's trace (1,000 runs' traces are gigabytes). The first run added sets the instants; a
/// later run whose trace is shorter panics, as indexing did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CurveSums {
    /// `[schedule][method][platform]`.
    sums: Vec<Vec<Vec<InstantSums>>>,
    runs: usize,
}

impl CurveSums {
    /// Adds one run's traces (call in run order).
    pub fn add(&mut self, r: &RunResult) {
        let zero = std::iter::empty::<f64>().sum::<f64>(); // what `Sum` starts from
        if self.runs == 0 {
            self.sums = r
                .schedules
                .iter()
                .map(|(_, runs)| {
                    runs.iter()
                        .map(|fr| fr.platforms.iter().map(|p| (vec![zero; p.trace.len()], vec![zero; p.trace.len()])).collect())
                        .collect()
                })
                .collect();
        }
        self.runs += 1;
        for ((_, runs), by_method) in r.schedules.iter().zip(&mut self.sums) {
            for (fr, by_platform) in runs.iter().zip(by_method.iter_mut()) {
                for (p, (pos, heading)) in fr.platforms.iter().zip(by_platform.iter_mut()) {
                    let len = pos.len();
                    for ((ps, hs), e) in pos.iter_mut().zip(heading.iter_mut()).zip(&p.trace[..len]) {
                        *ps += e.pos_err_m * e.pos_err_m;
                        *hs += e.heading_err_deg * e.heading_err_deg;
                    }
                }
            }
        }
    }

    /// The RMS curves of position and heading error of schedule `si`, method `mi`, platform `pi`.
    fn curve(&self, si: usize, mi: usize, pi: usize) -> (Vec<f64>, Vec<f64>) {
        let n = self.runs as f64;
        let finish = |v: &Vec<f64>| v.iter().map(|s| (s / n).sqrt()).collect();
        let (pos, heading) = &self.sums[si][mi][pi];
        (finish(pos), finish(heading))
    }
}

/// Summarises every schedule of an experiment: its runs in run order (the first whole, for the
/// curves' instants) and the sums of all of them.
pub fn summarize(spec: &ExperimentSpec, results: &[RunResult], sums: &CurveSums) -> Vec<ScheduleSummary> {
    let runs = results.len();
    spec.schedules
        .iter()
        .enumerate()
        .map(|(si, name)| {
            let by_method = |mi: usize| results.iter().map(move |r| &r.schedules[si].1[mi]);
            let mut methods = Vec::new();
            let mut curves = Vec::new();
            for (mi, &method) in spec.methods.iter().enumerate() {
                let first = by_method(mi).next().expect("at least one run");
                let mut platforms = Vec::new();
                for (pi, p) in first.platforms.iter().enumerate() {
                    let finals = by_method(mi).map(|r| r.platforms[pi].final_error());
                    platforms.push(PlatformStats {
                        id: p.id,
                        final_pos_err_mean_m: mean(finals.clone().map(|e| e.pos_err_m)),
                        final_pos_err_rms_m: rms(finals.clone().map(|e| e.pos_err_m)),
                        final_heading_err_mean_abs_deg: mean(finals.clone().map(|e| e.heading_err_deg.abs())),
                        final_heading_err_rms_deg: rms(finals.clone().map(|e| e.heading_err_deg)),
                        final_nees_mean: mean(by_method(mi).map(|r| r.platforms[pi].final_nees)),
                        nees_states: p.nees_states,
                    });
                    let (pos_rms_m, heading_rms_deg) = sums.curve(si, mi, pi);
                    curves.push(Curve {
                        method,
                        platform: p.id,
                        t_s: p.trace.iter().map(|e| e.t_s).collect(),
                        pos_rms_m,
                        heading_rms_deg,
                    });
                }
                let (mut common, mut relative, mut count) = (0.0, 0.0, 0usize);
                for r in by_method(mi) {
                    let errs: Vec<[f64; 2]> = r.platforms.iter().map(|p| p.final_error().pos_err_ne_m).collect();
                    let n = errs.len() as f64;
                    let mean = [errs.iter().map(|e| e[0]).sum::<f64>() / n, errs.iter().map(|e| e[1]).sum::<f64>() / n];
                    common += mean[0] * mean[0] + mean[1] * mean[1];
                    relative += errs.iter().map(|e| (e[0] - mean[0]).powi(2) + (e[1] - mean[1]).powi(2)).sum::<f64>();
                    count += errs.len();
                }
                methods.push(MethodStats {
                    method,
                    platforms,
                    formation_mean_err_rms_m: (common / runs as f64).sqrt(),
                    about_mean_err_rms_m: (relative / count as f64).sqrt(),
                });
            }
            let mut reductions = Vec::new();
            let pairs = [
                (Method::NoPropagation, Method::DeadReckoning),
                (Method::Decentralized, Method::DeadReckoning),
                (Method::Centralized, Method::DeadReckoning),
                (Method::CovarianceIntersection, Method::DeadReckoning),
                (Method::Decentralized, Method::NoPropagation),
                (Method::Decentralized, Method::Centralized),
            ];
            for (m, b) in pairs {
                let (Some(ms), Some(bs)) = (methods.iter().find(|s| s.method == m), methods.iter().find(|s| s.method == b))
                else {
                    continue;
                };
                let change = |a: f64, b: f64| 100.0 * (a - b) / b;
                reductions.push(Reduction {
                    method: m,
                    baseline: b,
                    pos_percent: ms
                        .platforms
                        .iter()
                        .zip(&bs.platforms)
                        .map(|(a, b)| change(a.final_pos_err_mean_m, b.final_pos_err_mean_m))
                        .collect(),
                    heading_percent: ms
                        .platforms
                        .iter()
                        .zip(&bs.platforms)
                        .map(|(a, b)| change(a.final_heading_err_mean_abs_deg, b.final_heading_err_mean_abs_deg))
                        .collect(),
                });
            }
            let nees_band = crate::estimation::consistency::average_nees_band(15, runs, 0.95);
            ScheduleSummary { schedule: name.clone(), runs, methods, reductions, nees_band, curves }
        })
        .collect()
}

/// The table printed for one schedule.
pub fn table(s: &ScheduleSummary) -> String {
    let mut out = String::new();
    let _ =
        writeln!(out, "schedule {} ({} runs): final errors at the end of the run, mean and RMS over runs", s.schedule, s.runs);
    let _ = writeln!(
        out,
        "{:<12} {:>8} | {:>9} {:>9} | {:>11} {:>11} | {:>8}",
        "method", "platform", "pos mean", "pos RMS", "hdg mean|.|", "hdg RMS", "NEES"
    );
    let _ = writeln!(out, "{}", "-".repeat(82));
    for m in &s.methods {
        for p in &m.platforms {
            let _ = writeln!(
                out,
                "{:<12} {:>8} | {:>7.2} m {:>7.2} m | {:>7.3} deg {:>7.3} deg | {:>8.1}",
                m.method.short_name(),
                p.id,
                p.final_pos_err_mean_m,
                p.final_pos_err_rms_m,
                p.final_heading_err_mean_abs_deg,
                p.final_heading_err_rms_deg,
                p.final_nees_mean
            );
        }
        // NEES of different state sizes do not average (a mixed team)
        let one_size = m.platforms.windows(2).all(|w| w[0].nees_states == w[1].nees_states);
        let nees = if one_size { format!("{:>8.1}", m.average(|p| p.final_nees_mean)) } else { format!("{:>8}", "-") };
        let _ = writeln!(
            out,
            "{:<12} {:>8} | {:>7.2} m {:>7.2} m | {:>7.3} deg {:>7.3} deg | {nees}",
            m.method.short_name(),
            "avg",
            m.average(|p| p.final_pos_err_mean_m),
            m.average(|p| p.final_pos_err_rms_m),
            m.average(|p| p.final_heading_err_mean_abs_deg),
            m.average(|p| p.final_heading_err_rms_deg),
        );
    }
    let mut sizes: Vec<usize> = s.methods.iter().flat_map(|m| m.platforms.iter().map(|p| p.nees_states)).collect();
    sizes.sort_unstable();
    sizes.dedup();
    for dim in sizes.into_iter().rev() {
        let band = if dim == 15 { s.nees_band } else { crate::estimation::consistency::average_nees_band(dim, s.runs, 0.95) };
        let who = if dim == 15 { "an INS" } else { "a wheeled robot" };
        let _ = writeln!(
            out,
            "NEES of a consistent filter ({dim} states, {who}, run average): 95% band [{:.1}, {:.1}]",
            band.0, band.1
        );
    }
    let _ = writeln!(
        out,
        "final position error split, RMS over runs: formation mean (common mode, unobservable from ranges) | about that mean"
    );
    for m in &s.methods {
        let _ = writeln!(
            out,
            "  {:<12} {:>7.2} m | {:>7.2} m",
            m.method.short_name(),
            m.formation_mean_err_rms_m,
            m.about_mean_err_rms_m
        );
    }
    let _ = writeln!(out, "change of the mean final error, per platform (negative = smaller error):");
    for r in &s.reductions {
        let fmt = |v: &[f64]| v.iter().map(|x| format!("{x:+.1}%")).collect::<Vec<_>>().join(" ");
        let _ = writeln!(
            out,
            "  {:>11} vs {:<11} position {} (avg {:+.1}%)   heading {} (avg {:+.1}%)",
            r.method.short_name(),
            r.baseline.short_name(),
            fmt(&r.pos_percent),
            Reduction::mean(&r.pos_percent),
            fmt(&r.heading_percent),
            Reduction::mean(&r.heading_percent)
        );
    }
    for line in PAPER_NOTES {
        let _ = writeln!(out, "{line}");
    }
    out
}

/// What stopped the experiment's files or figures from being written.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{what}: {source}")]
    Io {
        what: String,
        #[source]
        source: std::io::Error,
    },
    #[error("writing {path}: {source}")]
    Csv {
        path: String,
        #[source]
        source: csv::Error,
    },
    #[error("summary.json: {0}")]
    Json(#[from] serde_json::Error),
    #[error("plotting: {0}")]
    Plot(String),
}

/// Writes `summary.json`, `final_errors.csv`, `error_curves.csv` and the plots into `dir`, the
/// tables and the plots at once (rayon).
pub fn write_all(
    dir: &Path,
    spec: &ExperimentSpec,
    scenario_name: &str,
    results: &[RunResult],
    summaries: &[ScheduleSummary],
    tracks: &Tracks,
    plots: bool,
) -> Result<Vec<std::path::PathBuf>, ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Io { what: format!("creating {}", dir.display()), source })?;
    let (tables, plots) = rayon::join(
        || write_tables(dir, spec, scenario_name, results, summaries),
        || if plots { super::plots::write_plots(dir, summaries, tracks) } else { Ok(Vec::new()) },
    );
    let mut written = tables?;
    written.extend(plots?);
    Ok(written)
}

/// `summary.json`, `final_errors.csv` and `error_curves.csv`.
fn write_tables(
    dir: &Path,
    spec: &ExperimentSpec,
    scenario_name: &str,
    results: &[RunResult],
    summaries: &[ScheduleSummary],
) -> Result<Vec<std::path::PathBuf>, ReportError> {
    let mut written = Vec::new();

    #[derive(Serialize)]
    struct Json<'a> {
        scenario: &'a str,
        runs: u32,
        seed: u64,
        position_error: &'static str,
        schedules: &'a [ScheduleSummary],
    }
    let path = dir.join("summary.json");
    let json = Json {
        scenario: scenario_name,
        runs: spec.runs,
        seed: spec.seed,
        position_error: "horizontal (north, east) distance between estimate and truth at the end of the run",
        schedules: summaries,
    };
    std::fs::write(&path, serde_json::to_string_pretty(&json)?)
        .map_err(|source| ReportError::Io { what: format!("writing {}", path.display()), source })?;
    written.push(path);

    let path = dir.join("final_errors.csv");
    let csv_err = |source| ReportError::Csv { path: path.display().to_string(), source };
    let mut w = csv::Writer::from_path(&path).map_err(csv_err)?;
    w.write_record(["run", "schedule", "method", "platform", "final_pos_err_m", "final_heading_err_deg", "final_nees"])
        .map_err(csv_err)?;
    for r in results {
        for (schedule, runs) in &r.schedules {
            for fr in runs {
                for p in &fr.platforms {
                    let e = p.final_error();
                    w.write_record([
                        r.run.to_string(),
                        schedule.clone(),
                        fr.method.short_name().to_string(),
                        p.id.to_string(),
                        format!("{:.6}", e.pos_err_m),
                        format!("{:.6}", e.heading_err_deg),
                        format!("{:.4}", p.final_nees),
                    ])
                    .map_err(csv_err)?;
                }
            }
        }
    }
    w.flush().map_err(|source| ReportError::Io { what: format!("writing {}", path.display()), source })?;
    written.push(path);

    let path = dir.join("error_curves.csv");
    let csv_err = |source| ReportError::Csv { path: path.display().to_string(), source };
    let mut w = csv::Writer::from_path(&path).map_err(csv_err)?;
    w.write_record(["schedule", "method", "platform", "t_s", "pos_rms_m", "heading_rms_deg"]).map_err(csv_err)?;
    for s in summaries {
        for c in &s.curves {
            for k in 0..c.t_s.len() {
                w.write_record([
                    s.schedule.clone(),
                    c.method.short_name().to_string(),
                    c.platform.to_string(),
                    format!("{:.3}", c.t_s[k]),
                    format!("{:.6}", c.pos_rms_m[k]),
                    format!("{:.6}", c.heading_rms_deg[k]),
                ])
                .map_err(csv_err)?;
            }
        }
    }
    w.flush().map_err(|source| ReportError::Io { what: format!("writing {}", path.display()), source })?;
    written.push(path);
    Ok(written)
}

/// Truth and estimated tracks of run 0, for the trajectory figure.
#[derive(Debug, Clone, Default)]
pub struct Tracks {
    /// `(platform, truth N/E track)`.
    pub truth: Vec<(PlatformId, Vec<[f64; 2]>)>,
    /// `(method, platform, estimated N/E track)`.
    pub estimated: Vec<(Method, PlatformId, Vec<[f64; 2]>)>,
}
