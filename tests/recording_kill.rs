//! A recording process killed with SIGKILL leaves a log that reads up to its last flush, and
//! the recorder flushes about every second: at most about one second of messages is lost.
//!
//! The test re-runs its own test binary as the recording process (the ignored test
//! `record_forever_child`, which records only when `COOPLOC_RECORD_FOREVER` names a file), reads
//! what the child reports after each flush on stdout, kills it, and reads the file.

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use cooploc::recording::{Direction, Link, LogEnd, Recorder, RecorderOptions, read_log, wall_now_ns};

const CHILD_ENV: &str = "COOPLOC_RECORD_FOREVER";

/// A MAVLink v2 frame (message id 0, 9-byte payload) whose payload starts with `n`.
fn frame(n: u32) -> Vec<u8> {
    let mut f = vec![0xFD, 9, 0, 0, (n % 256) as u8, 9, 191, 0, 0, 0];
    f.extend(n.to_le_bytes());
    f.extend([0; 5]);
    f.extend([0xAB, 0xCD]);
    f
}

#[test]
#[ignore = "the recording process of sigkill_loses_at_most_about_a_second, which spawns it"]
fn record_forever_child() {
    let Ok(path) = std::env::var(CHILD_ENV) else { return };
    let mut rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    let mut flushes = rec.stats().flushes;
    let mut stdout = std::io::stdout().lock();
    for i in 0u32.. {
        rec.frame(Link::Coop(9), Direction::Rx, wall_now_ns(), &frame(i)).unwrap();
        let stats = rec.stats();
        if stats.flushes != flushes {
            flushes = stats.flushes;
            writeln!(stdout, "FLUSHED {} {}", stats.messages_flushed, stats.last_flush_wall_ns).unwrap();
            stdout.flush().unwrap();
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn sigkill_loses_at_most_about_a_second() {
    let dir = std::env::temp_dir().join(format!("cooploc-recording-kill-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("killed.mcap");
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args(["--ignored", "--exact", "record_forever_child", "--nocapture", "--test-threads=1"])
        .env(CHILD_ENV, &path)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawning the recording process");
    let started = Instant::now();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    let lines = std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(rest) = line.strip_prefix("FLUSHED ") {
                let mut it = rest.split(' ').map(|v| v.parse::<u64>().unwrap());
                let _ = tx.send((it.next().unwrap(), it.next().unwrap()));
            }
        }
    });

    // Two flushes reported (about 2 s of recording), then half a second more, then SIGKILL.
    let mut reported = Vec::new();
    while reported.len() < 2 {
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(r) => reported.push(r),
            Err(e) => {
                let _ = child.kill();
                panic!("the recording process reported {} flushes, then {e:?}", reported.len());
            }
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    let kill_wall_ns = wall_now_ns();
    child.kill().unwrap(); // SIGKILL on Unix
    child.wait().unwrap();
    lines.join().unwrap();
    reported.extend(rx.try_iter());
    eprintln!("killed after {:?}; flushes reported: {reported:?}", started.elapsed());

    let log = read_log(&path).unwrap();
    assert_eq!(log.end, LogEnd::Truncated, "a killed writer leaves no summary");
    // A prefix of what was written: frames 0, 1, 2, ... without a gap.
    for (i, m) in log.messages.iter().enumerate() {
        assert_eq!(u32::from_le_bytes(m.data[10..14].try_into().unwrap()), i as u32, "message {i}");
    }
    // Everything flushed before the kill is there.
    let (flushed, last_flush_ns) = *reported.last().unwrap();
    assert!(log.messages.len() as u64 >= flushed, "{} messages read, {flushed} were flushed", log.messages.len());
    // The flushes came about every second.
    for pair in reported.windows(2) {
        let gap_s = (pair[1].1 - pair[0].1) as f64 * 1e-9;
        assert!((0.9..1.6).contains(&gap_s), "flushes {gap_s:.3} s apart");
    }
    // At most about a second was lost (plus scheduling slack on a loaded machine).
    let last_ns = log.messages.last().unwrap().log_time_ns;
    let lost_s = kill_wall_ns.saturating_sub(last_ns) as f64 * 1e-9;
    eprintln!(
        "{} messages kept; the last one {lost_s:.3} s before the kill, the last flush {:.3} s before it",
        log.messages.len(),
        kill_wall_ns.saturating_sub(last_flush_ns) as f64 * 1e-9
    );
    assert!(lost_s < 1.5, "the last message kept is {lost_s:.3} s older than the kill");
    let _ = std::fs::remove_dir_all(&dir);
}
