//! `cooploc demo` as the README runs it (shortened to 60 s of the paper scenario at 5x real time
//! so that there is time to look): the dashboard address is printed, headless Chromium loads the
//! page during the run and finds every vehicle with its estimate, a screenshot is saved
//! (target/demo-screenshot.png), and at the end the table has every method, every node was
//! replayed bit for bit from the log, and the log is under the given path.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

#[test]
fn the_demo_serves_the_page_during_the_run_and_prints_the_table() {
    let chromium = common::chromium("the demo's browser test");
    let dir = std::env::temp_dir().join(format!("cooploc-demo-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("demo.mcap");
    let mut child = Command::new(env!("CARGO_BIN_EXE_cooploc"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["demo", "--speed", "5", "--duration-s", "60", "--http", "127.0.0.1:0", "--foxglove", "127.0.0.1:0", "--log"])
        .arg(&log)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let out = child.stdout.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let mut lines = Vec::new();
    let url = loop {
        let line = rx.recv_timeout(Duration::from_secs(60)).expect("the dashboard's address");
        lines.push(line.clone());
        if let Some(u) = line.strip_prefix("dashboard: ") {
            break u.to_string();
        }
    };
    if let Some(chromium) = chromium {
        std::thread::sleep(Duration::from_secs(4)); // estimates on the page (12 s of a 60 s run at 5x)
        let target = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).parent().unwrap().to_path_buf();
        let run = |extra: &[&str]| {
            let profile = dir.join(format!("chromium-{}", extra.len()));
            Command::new(&chromium)
                .args(["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking"])
                .args(["--disable-component-update", "--disable-sync", "--hide-scrollbars", "--virtual-time-budget=3000"])
                .arg(format!("--user-data-dir={}", profile.display()))
                .args(extra)
                .arg(&url)
                .stdin(Stdio::null())
                .output()
                .expect("running chromium")
        };
        let dom = run(&["--dump-dom"]);
        let html = String::from_utf8_lossy(&dom.stdout);
        for id in 1..=3 {
            assert!(html.contains(&format!("id=\"vehicle-{id}\"")), "vehicle {id} is not on the page:\n{html}");
        }
        let shot = target.join("demo-screenshot.png");
        let _ = std::fs::remove_file(&shot);
        let s = run(&["--window-size=1400,900", &format!("--screenshot={}", shot.display())]);
        assert!(s.status.success() && shot.exists(), "no screenshot");
    }
    let status = child.wait().unwrap();
    lines.extend(rx.iter());
    let text = lines.join("\n");
    eprintln!("{text}");
    assert!(status.success(), "the demo failed");
    for m in ["dr", "naive", "dcl", "centralized", "ci"] {
        assert!(lines.iter().any(|l| l.starts_with(&format!("{m} "))), "no row for {m}");
    }
    assert_eq!(text.matches("identical bit for bit").count(), 3, "every node replays bit for bit");
    assert!(!text.contains(" partial,") || text.contains(" 0 partial,"));
    assert!(log.exists());
    let _ = std::fs::remove_dir_all(&dir);
}
