//! The experiment's figures, after the paper's Figs. 1-4, as PNG and SVG (plotters).
//!
//! Text is drawn with DejaVu Sans embedded in the binary (`fonts/`, Bitstream Vera licence in
//! `fonts/DejaVuSans-LICENSE.txt`) through plotters' pure-Rust `ab_glyph` renderer: no system
//! font library (fontconfig, freetype) is needed, so the same binary starts as a node on a
//! minimal vehicle computer.

use std::path::{Path, PathBuf};

use super::report::ReportError;
use plotters::coord::Shift;
use plotters::prelude::*;

use super::report::{ScheduleSummary, Tracks};
use crate::estimation::Method;

/// The embedded font, registered once as plotters' "sans-serif".
fn register_font() -> Result<(), ReportError> {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, include_bytes!("fonts/DejaVuSans.ttf")).is_ok()
    });
    if ok { Ok(()) } else { Err(ReportError::Plot("the embedded font fonts/DejaVuSans.ttf could not be read".into())) }
}

/// A figure drawn, or why not.
type Drawn = Result<(), ReportError>;

/// A plotting backend's error, as text (its types differ per backend).
fn plot_err(e: impl std::fmt::Display) -> ReportError {
    ReportError::Plot(e.to_string())
}

fn color(m: Method) -> RGBColor {
    match m {
        Method::DeadReckoning => RGBColor(40, 40, 40),
        Method::NoPropagation => RGBColor(214, 39, 40),
        Method::Decentralized => RGBColor(31, 119, 180),
        Method::Centralized => RGBColor(44, 160, 44),
        Method::CovarianceIntersection => RGBColor(255, 127, 14),
    }
}

fn label(m: Method) -> &'static str {
    match m {
        Method::DeadReckoning => "dead reckoning",
        Method::NoPropagation => "no covariance transfer",
        Method::Decentralized => "decentralized (covariance transfer)",
        Method::Centralized => "centralized EKF",
        Method::CovarianceIntersection => "covariance intersection",
    }
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(23, 190, 207),
];

fn draw_errors<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    s: &ScheduleSummary,
    methods: &[Method],
    title: &str,
) -> Result<(), ReportError>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(plot_err)?;
    let root = root.titled(title, ("sans-serif", 22)).map_err(plot_err)?;
    let platforms: Vec<_> = s.methods.first().map(|m| m.platforms.iter().map(|p| p.id).collect()).unwrap_or_default();
    let panels = root.split_evenly((2, platforms.len().max(1)));
    for (row, what) in ["position error RMS (m)", "heading error RMS (deg)"].iter().enumerate() {
        for (col, &id) in platforms.iter().enumerate() {
            let curves: Vec<_> = s.curves.iter().filter(|c| c.platform == id && methods.contains(&c.method)).collect();
            let t_max = curves.iter().filter_map(|c| c.t_s.last().copied()).fold(1.0, f64::max);
            let y = |c: &super::report::Curve| if row == 0 { c.pos_rms_m.clone() } else { c.heading_rms_deg.clone() };
            let y_max = curves.iter().flat_map(|c| y(c)).fold(1e-6, f64::max) * 1.05;
            let mut chart = ChartBuilder::on(&panels[row * platforms.len() + col])
                .caption(format!("platform {id}"), ("sans-serif", 16))
                .margin(8)
                .x_label_area_size(30)
                .y_label_area_size(50)
                .build_cartesian_2d(0.0..t_max, 0.0..y_max)
                .map_err(plot_err)?;
            chart.configure_mesh().x_desc("time (s)").y_desc(*what).draw().map_err(plot_err)?;
            for c in &curves {
                let rgb = color(c.method);
                let width = if c.method == Method::Centralized { 1 } else { 2 };
                let series = chart
                    .draw_series(LineSeries::new(c.t_s.iter().copied().zip(y(c)), rgb.stroke_width(width)))
                    .map_err(plot_err)?;
                if row == 0 && col == 0 {
                    series
                        .label(label(c.method))
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], rgb.stroke_width(2)));
                }
            }
            if row == 0 && id == platforms[0] {
                chart
                    .configure_series_labels()
                    .position(SeriesLabelPosition::UpperLeft)
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK)
                    .draw()
                    .map_err(plot_err)?;
            }
        }
    }
    root.present().map_err(plot_err)?;
    Ok(())
}

fn draw_tracks<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, tracks: &Tracks) -> Result<(), ReportError>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(plot_err)?;
    let all = tracks.truth.iter().flat_map(|(_, t)| t.iter());
    let (mut n0, mut n1, mut e0, mut e1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in all {
        n0 = n0.min(p[0]);
        n1 = n1.max(p[0]);
        e0 = e0.min(p[1]);
        e1 = e1.max(p[1]);
    }
    // Same scale on both axes.
    let span = (n1 - n0).max(e1 - e0) * 1.1 + 1.0;
    let (nc, ec) = ((n0 + n1) / 2.0, (e0 + e1) / 2.0);
    let mut chart = ChartBuilder::on(&root)
        .caption("Platform trajectories (truth) and run-0 estimates", ("sans-serif", 22))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(55)
        .build_cartesian_2d(ec - span / 2.0..ec + span / 2.0, nc - span / 2.0..nc + span / 2.0)
        .map_err(plot_err)?;
    chart.configure_mesh().x_desc("east (m)").y_desc("north (m)").draw().map_err(plot_err)?;
    for (k, (id, t)) in tracks.truth.iter().enumerate() {
        let c = PALETTE[k % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(t.iter().map(|p| (p[1], p[0])), c.stroke_width(3)))
            .map_err(plot_err)?
            .label(format!("platform {id} truth"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(3)));
        if let Some(start) = t.first() {
            chart.draw_series([Circle::new((start[1], start[0]), 5, c.filled())]).map_err(plot_err)?;
        }
    }
    for (method, id, t) in &tracks.estimated {
        let k = tracks.truth.iter().position(|(i, _)| i == id).unwrap_or(0);
        let c = PALETTE[k % PALETTE.len()];
        let style = if *method == Method::DeadReckoning { c.mix(0.5).stroke_width(1) } else { BLACK.mix(0.6).stroke_width(1) };
        let series = chart.draw_series(LineSeries::new(t.iter().map(|p| (p[1], p[0])), style)).map_err(plot_err)?;
        if k == 0 {
            series
                .label(format!("{} estimate", label(*method)))
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style));
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(plot_err)?;
    root.present().map_err(plot_err)?;
    Ok(())
}

/// One figure to draw: what, under which file stem, at which size.
struct Figure<'a> {
    stem: String,
    size: (u32, u32),
    what: Drawing<'a>,
}

enum Drawing<'a> {
    Tracks(&'a Tracks),
    Errors { summary: &'a ScheduleSummary, methods: Vec<Method>, title: String },
}

impl Drawing<'_> {
    fn draw<DB: DrawingBackend>(&self, area: DrawingArea<DB, Shift>) -> Drawn
    where
        DB::ErrorType: 'static,
    {
        match self {
            Drawing::Tracks(tracks) => draw_tracks(area, tracks),
            Drawing::Errors { summary, methods, title } => draw_errors(area, summary, methods, title),
        }
    }
}

/// Writes the figures, each as PNG and SVG, all files at once on the cores (rayon); returns
/// the paths written, in figure order, PNG before SVG.
pub fn write_plots(dir: &Path, summaries: &[ScheduleSummary], tracks: &Tracks) -> Result<Vec<PathBuf>, ReportError> {
    use rayon::prelude::*;
    register_font()?;
    let mut figures = Vec::new();
    if !tracks.truth.is_empty() {
        figures.push(Figure { stem: "fig1_trajectories".into(), size: (900, 900), what: Drawing::Tracks(tracks) });
    }
    let paper: [(&str, &str, &[Method], &str); 3] = [
        (
            "fig2_dead_reckoning_vs_cooperative",
            "1hz",
            &[Method::DeadReckoning, Method::NoPropagation, Method::Decentralized],
            "Dead reckoning vs cooperative localization (1 Hz ranging)",
        ),
        (
            "fig3_centralized_vs_decentralized",
            "1hz",
            &[Method::Centralized, Method::Decentralized],
            "Centralized EKF vs decentralized (1 Hz ranging)",
        ),
        (
            "fig4_covariance_transfer_vs_none",
            "four-events",
            &[Method::NoPropagation, Method::Decentralized],
            "Covariance transfer vs none (ranging at 1, 100, 200, 300 s)",
        ),
    ];
    for (stem, schedule, methods, title) in paper {
        if let Some(summary) = summaries.iter().find(|s| s.schedule == schedule) {
            let what = Drawing::Errors { summary, methods: methods.to_vec(), title: title.into() };
            figures.push(Figure { stem: stem.into(), size: (1500, 800), what });
        }
    }
    for summary in summaries {
        let methods: Vec<Method> = summary.methods.iter().map(|m| m.method).collect();
        let title = format!("All methods, schedule {} ({} runs)", summary.schedule, summary.runs);
        let stem = format!("errors_all_methods_{}", summary.schedule);
        figures.push(Figure { stem, size: (1500, 800), what: Drawing::Errors { summary, methods, title } });
    }
    let files: Vec<(&Figure, bool)> = figures.iter().flat_map(|f| [(f, false), (f, true)]).collect();
    files
        .par_iter()
        .map(|&(figure, svg)| {
            let path = dir.join(format!("{}.{}", figure.stem, if svg { "svg" } else { "png" }));
            if svg {
                figure.what.draw(SVGBackend::new(&path, figure.size).into_drawing_area())?;
            } else {
                figure.what.draw(BitMapBackend::new(&path, figure.size).into_drawing_area())?;
            }
            Ok(path)
        })
        .collect::<Vec<Result<PathBuf, ReportError>>>()
        .into_iter()
        .collect()
}
