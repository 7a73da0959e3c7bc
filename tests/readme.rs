//! The README's two set-up commands, in their order, on a clean clone of this repository: the
//! first (`cargo run --release -- demo`) leaves its log under logs/, and the second
//! (`bash tests/run-all.sh`) must still pass. The second is what CI runs on a clean clone; here
//! the README is checked to name exactly these two commands in this order, the demo runs in a
//! fresh clone (this build's binary, the clone's working directory, a shortened scenario and
//! ephemeral ports), and the part of the test suite that reads logs/ then finds exactly the
//! committed logs, each with its golden summary, and not the demo's new one (before this was
//! fixed, `tests/replay.rs` took the demo's log for a committed one and failed).

mod common;

use std::path::Path;
use std::process::Command;

fn setup_commands(readme: &str) -> Vec<String> {
    let section = readme.split("## Set-up commands").nth(1).expect("a Set-up commands section");
    let section = section.split("\n## ").next().unwrap();
    section
        .lines()
        .filter(|l| l.starts_with('|'))
        .filter_map(|l| l.trim_end_matches('|').rsplit('|').next())
        .filter_map(|cell| cell.trim().strip_prefix('`').and_then(|c| c.strip_suffix('`')))
        .map(str::to_string)
        .collect()
}

#[test]
fn the_readme_commands_work_in_order_on_a_clean_clone() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    assert_eq!(setup_commands(&readme), ["cargo run --release -- demo", "bash tests/run-all.sh"], "the README's set-up commands");

    let clone = std::env::temp_dir().join(format!("cooploc-readme-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&clone);
    let git = Command::new("git").args(["clone", "--quiet", "--local"]).arg(root).arg(&clone).status();
    match git {
        Ok(s) if s.success() => {}
        _ if std::env::var("CI").as_deref() == Ok("true") => panic!("git clone of the repository failed: {git:?}"),
        _ => {
            eprintln!("SKIPPED: git clone of the repository failed ({git:?})");
            return;
        }
    }
    let committed_before = common::committed_logs(&clone.join("logs"));
    assert!(committed_before.len() >= 2, "the clone holds the committed logs: {committed_before:?}");

    // 1. The demo, as `cargo run --release -- demo` runs it, from the clone's root.
    let out = Command::new(env!("CARGO_BIN_EXE_cooploc"))
        .args(["demo", "--duration-s", "20", "--http", "127.0.0.1:0", "--foxglove", "127.0.0.1:0"])
        .current_dir(&clone)
        .output()
        .expect("running cooploc demo");
    assert!(out.status.success(), "the demo failed: {}", String::from_utf8_lossy(&out.stderr));
    let demo_log = clone.join("logs/demo-1-0.mcap");
    assert!(demo_log.is_file(), "the demo's default log, logs/demo-1-0.mcap");
    let status = Command::new("git").args(["status", "--porcelain"]).current_dir(&clone).output().unwrap();
    assert!(status.stdout.is_empty(), "the demo's output is ignored by git: {}", String::from_utf8_lossy(&status.stdout));

    // 2. What the test suite reads from logs/: the committed logs and their golden summaries only.
    let after = common::committed_logs(&clone.join("logs"));
    assert_eq!(after, committed_before, "the demo's log is not taken for a committed one");
    for log in &after {
        let summary = log.with_extension("summary.json");
        assert!(summary.is_file(), "{} has its golden summary", log.display());
    }
    // And the demo's log is a log: it replays.
    let replay = Command::new(env!("CARGO_BIN_EXE_cooploc")).arg("replay").arg(&demo_log).output().unwrap();
    assert!(replay.status.success(), "cooploc replay of the demo's log: {}", String::from_utf8_lossy(&replay.stderr));
    let _ = std::fs::remove_dir_all(&clone);
}

/// The relative links of a markdown text: `](target)`, less web addresses and in-page anchors,
/// the anchor cut off.
fn relative_links(text: &str) -> Vec<String> {
    text.split("](")
        .skip(1)
        .filter_map(|rest| rest.split(')').next())
        .map(|t| t.split('#').next().unwrap_or("").trim().to_string())
        .filter(|t| !t.is_empty() && !t.contains("://") && !t.starts_with("mailto:"))
        .collect()
}

/// The README is a front door: at most 300 lines, the set-up commands before any other
/// command, every chapter under docs/ linked from it, and no link in it or in a chapter that
/// leads nowhere.
#[test]
fn the_readme_is_a_short_front_door_whose_links_all_lead_somewhere() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let lines = readme.lines().count();
    assert!(lines <= 300, "the README has {lines} lines: what does not belong at the front door goes to a docs/ chapter");
    let first_command = readme.find("`cargo run --release -- demo`").expect("the demo command");
    let before = &readme[..first_command];
    assert!(
        !before.contains("```") && !before.contains("`cargo ") && !before.contains("`bash "),
        "no command comes before the set-up commands"
    );

    let mut chapters: Vec<_> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    chapters.sort();
    assert!(chapters.len() >= 8, "the chapters under docs/: {chapters:?}");
    let mut broken = Vec::new();
    for file in std::iter::once(root.join("README.md")).chain(chapters.iter().cloned()) {
        let text = std::fs::read_to_string(&file).unwrap();
        let dir = file.parent().unwrap();
        for link in relative_links(&text) {
            if !dir.join(&link).exists() {
                broken.push(format!("{}: {link}", file.strip_prefix(root).unwrap().display()));
            }
        }
    }
    assert!(broken.is_empty(), "links that lead nowhere: {broken:#?}");
    for chapter in &chapters {
        let name = format!("docs/{}", chapter.file_name().unwrap().to_string_lossy());
        assert!(readme.contains(&format!("]({name})")), "the README links {name}");
    }
}

#[test]
fn relative_links_are_found_and_web_addresses_left_out() {
    let text = "see [a](docs/a.md), [b](b.md#part), ![i](images/x.png), [w](https://x.org/y) and [here](#top)";
    assert_eq!(relative_links(text), ["docs/a.md", "b.md", "images/x.png"]);
}
