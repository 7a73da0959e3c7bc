//! The command line itself: what clap accepts before any command runs.

use std::process::Command;

fn run(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_cooploc")).args(args).output().unwrap();
    (out.status.code(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

/// A negative number is a value, in a list (`--init-ned -150,20,0`) or alone, in every
/// subcommand: the error that follows is about what is really wrong.
#[test]
fn negative_numbers_are_values_everywhere() {
    let (code, out) = run(&["node", "--init-ned", "-150,20,0", "--init-vel-ned", "-1,0,0"]);
    assert_eq!(code, Some(2), "{out}");
    assert!(!out.contains("unexpected argument"), "{out}");
    assert!(out.contains("--id <ID>"), "the missing arguments are named: {out}");
    let (code, out) = run(&["budget", "--epoch-hz", "-1"]);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("--epoch-hz -1: more than 0"), "the command's own check refuses it: {out}");
    let (code, out) = run(&["gcs", "--origin-lon-deg", "-79.5", "--no-such-flag"]);
    assert_eq!(code, Some(2), "{out}");
    assert!(out.contains("'--no-such-flag'") && !out.contains("'-79.5'"), "{out}");
}

/// The one binary (a node on a vehicle computer too) links no system font library: the plots
/// draw with an embedded font (plotters' pure-Rust ab_glyph), not fontconfig and freetype.
#[test]
fn the_binary_needs_no_font_libraries() {
    let out = match Command::new("ldd").arg(env!("CARGO_BIN_EXE_cooploc")).output() {
        Ok(out) => out,
        Err(e) if std::env::var_os("CI").is_none() => {
            eprintln!("skipped: ldd not found ({e})");
            return;
        }
        Err(e) => panic!("ldd is needed under CI: {e}"),
    };
    let libs = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{libs}");
    for lib in ["fontconfig", "freetype", "libpng", "libexpat"] {
        assert!(!libs.contains(lib), "the binary links {lib}:\n{libs}");
    }
}
