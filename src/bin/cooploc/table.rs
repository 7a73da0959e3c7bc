//! The final error table `cooploc demo` and `cooploc replay` print.

use cooploc::experiment::FilterRun;

/// One row per method: final horizontal position error and heading error per platform and their
/// mean (the experiment's definitions: truth minus estimate at the run's last truth sample).
pub fn print_methods(runs: &[FilterRun]) {
    let Some(first) = runs.first() else { return };
    let ids: Vec<String> = first.platforms.iter().map(|p| format!("{:>10}", format!("pos {} m", p.id))).collect();
    let hd: Vec<String> = first.platforms.iter().map(|p| format!("{:>11}", format!("hdg {} deg", p.id))).collect();
    println!("{:<13}{}{:>10} |{}{:>11}", "method", ids.join(""), "mean m", hd.join(""), "mean deg");
    for r in runs {
        let pos: Vec<f64> = r.platforms.iter().map(|p| p.final_error().pos_err_m).collect();
        let hdg: Vec<f64> = r.platforms.iter().map(|p| p.final_error().heading_err_deg.abs()).collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        println!(
            "{:<13}{}{:>10.2} |{}{:>11.3}",
            r.method.short_name(),
            pos.iter().map(|v| format!("{v:>10.2}")).collect::<String>(),
            mean(&pos),
            hdg.iter().map(|v| format!("{v:>11.3}")).collect::<String>(),
            mean(&hdg)
        );
    }
}
