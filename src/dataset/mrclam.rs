//! The UTIAS MRCLAM data sets (Leung, Halpern, Barfoot, Liu, "The UTIAS Multi-Robot
//! Cooperative Localization and Mapping Dataset", IJRR 30(8), 2011) read into a [`Dataset`].
//!
//! A folder holds `Barcodes.dat` (subject, barcode), `Landmark_Groundtruth.dat` (subject, x, y,
//! x and y standard deviations), and per robot `RobotN_Odometry.dat` (time, commanded forward and
//! angular speed), `RobotN_Measurement.dat` (time, **barcode**, range, bearing) and
//! `RobotN_Groundtruth.dat` (time, x, y, orientation). Lines starting with `#` are the files' own
//! header comments; columns are separated by blanks or tabs; CRLF and LF are both accepted.
//! Subjects 1-5 are the robots, the others landmarks.
//!
//! What the reader does with what it finds:
//! - a line with the wrong number of columns, a field that is not a number (or not finite), a
//!   time that goes backwards, a missing file: an error naming the file and the line;
//! - an observation of a barcode not in `Barcodes.dat` (a mis-read) or of the robot's own
//!   barcode: dropped and counted ([`ImportCounts`]);
//! - two command rows with one time stamp: the later one is kept (counted); two ground-truth rows
//!   with one time stamp: the second is dropped (counted);
//! - times are read as decimal strings into microseconds exactly (no float rounding).
//!
//! Axes are mapped to NED as the [module documentation](super) says.

use std::collections::BTreeMap;
use std::path::Path;

use super::{Command, Dataset, ImportCounts, Landmark, Observation, Robot, Target, TruthPose};
use crate::estimation::PlatformId;
use crate::time::TimeUs;

/// Number of robots in every MRCLAM data set.
pub const ROBOTS: PlatformId = 5;

/// Why a data set cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{file}: {source}")]
    Io { file: String, source: std::io::Error },
    #[error("{file}:{line}: {problem}")]
    Line { file: String, line: usize, problem: String },
    #[error("{file}: {problem}")]
    File { file: String, problem: String },
}

/// A data line: its number in the file (from 1) and its fields.
struct Row<'a> {
    line: usize,
    fields: Vec<&'a str>,
}

/// The data lines of `text`: comments and blank lines skipped, each with exactly `columns`
/// fields.
fn rows<'a>(file: &str, text: &'a str, columns: usize) -> Result<Vec<Row<'a>>, DatasetError> {
    let mut out = Vec::new();
    for (k, raw) in text.split('\n').enumerate() {
        let line = raw.trim_end_matches('\r').trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != columns {
            return Err(DatasetError::Line {
                file: file.into(),
                line: k + 1,
                problem: format!("{} fields, expected {columns} (a truncated or damaged line?): {line:?}", fields.len()),
            });
        }
        out.push(Row { line: k + 1, fields });
    }
    Ok(out)
}

fn bad(file: &str, line: usize, problem: String) -> DatasetError {
    DatasetError::Line { file: file.into(), line, problem }
}

/// A finite number.
fn number(file: &str, row: &Row, col: usize, what: &str) -> Result<f64, DatasetError> {
    let s = row.fields[col];
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(bad(file, row.line, format!("{what} {s:?} is not a finite number"))),
    }
}

/// A non-negative integer.
fn integer(file: &str, row: &Row, col: usize, what: &str) -> Result<u32, DatasetError> {
    let s = row.fields[col];
    s.parse::<u32>().map_err(|_| bad(file, row.line, format!("{what} {s:?} is not a non-negative integer")))
}

/// A time in seconds with up to six decimals, as microseconds, exactly.
pub fn parse_time_us(s: &str) -> Option<u64> {
    let (int, frac) = s.split_once('.').unwrap_or((s, ""));
    if int.is_empty() || !int.bytes().all(|b| b.is_ascii_digit()) || frac.len() > 6 || !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let mut us: u64 = int.parse::<u64>().ok()?.checked_mul(1_000_000)?;
    if !frac.is_empty() {
        us = us.checked_add(frac.parse::<u64>().ok()? * 10u64.pow(6 - frac.len() as u32))?;
    }
    Some(us)
}

fn time(file: &str, row: &Row) -> Result<TimeUs, DatasetError> {
    let s = row.fields[0];
    parse_time_us(s)
        .map(TimeUs)
        .ok_or_else(|| bad(file, row.line, format!("time {s:?} is not seconds with at most six decimals")))
}

/// Checks that `t` does not go back from `prev`.
fn not_backwards(file: &str, row: &Row, prev: Option<TimeUs>, t: TimeUs) -> Result<(), DatasetError> {
    match prev {
        Some(p) if t < p => Err(bad(
            file,
            row.line,
            format!(
                "time {} s is before the previous line's {} s (the file must be in time order)",
                t.as_secs_f64(),
                p.as_secs_f64()
            ),
        )),
        _ => Ok(()),
    }
}

/// `Barcodes.dat`: barcode -> subject.
pub fn parse_barcodes(file: &str, text: &str) -> Result<BTreeMap<u32, u16>, DatasetError> {
    let mut out = BTreeMap::new();
    let mut subjects = std::collections::BTreeSet::new();
    for row in rows(file, text, 2)? {
        let subject = integer(file, &row, 0, "subject")?;
        let barcode = integer(file, &row, 1, "barcode")?;
        let subject = u16::try_from(subject).map_err(|_| bad(file, row.line, format!("subject {subject} is out of range")))?;
        if out.insert(barcode, subject).is_some() {
            return Err(bad(file, row.line, format!("barcode {barcode} is listed twice")));
        }
        if !subjects.insert(subject) {
            return Err(bad(file, row.line, format!("subject {subject} is listed twice")));
        }
    }
    for id in 1..=ROBOTS {
        if !subjects.contains(&id) {
            return Err(DatasetError::File { file: file.into(), problem: format!("no barcode for robot {id} (subject {id})") });
        }
    }
    Ok(out)
}

/// `Landmark_Groundtruth.dat`.
pub fn parse_landmarks(file: &str, text: &str) -> Result<Vec<Landmark>, DatasetError> {
    let mut out: Vec<Landmark> = Vec::new();
    for row in rows(file, text, 5)? {
        let id = integer(file, &row, 0, "subject")?;
        let id = u16::try_from(id)
            .ok()
            .filter(|&s| s > ROBOTS)
            .ok_or_else(|| bad(file, row.line, format!("subject {id} is not a landmark (subjects 1-{ROBOTS} are the robots)")))?;
        let (x, y) = (number(file, &row, 1, "x")?, number(file, &row, 2, "y")?);
        let (sx, sy) = (number(file, &row, 3, "x std-dev")?, number(file, &row, 4, "y std-dev")?);
        if sx < 0.0 || sy < 0.0 {
            return Err(bad(file, row.line, "a negative standard deviation".into()));
        }
        if out.iter().any(|l| l.id == id) {
            return Err(bad(file, row.line, format!("landmark {id} is listed twice")));
        }
        out.push(Landmark { id, n_m: x, e_m: -y, sigma_n_m: sx, sigma_e_m: sy });
    }
    out.sort_by_key(|l| l.id);
    Ok(out)
}

/// `RobotN_Odometry.dat`: the commands, and how many rows repeated a time stamp.
pub fn parse_odometry(file: &str, text: &str) -> Result<(Vec<Command>, usize), DatasetError> {
    let mut out: Vec<Command> = Vec::new();
    let mut repeated = 0;
    for row in rows(file, text, 3)? {
        let t = time(file, &row)?;
        not_backwards(file, &row, out.last().map(|c| c.t), t)?;
        let c = Command {
            t,
            speed_m_s: number(file, &row, 1, "forward velocity")?,
            yaw_rate_rad_s: -number(file, &row, 2, "angular velocity")?,
        };
        if c.speed_m_s.abs() > crate::estimation::planar::MAX_SPEED_M_S
            || c.yaw_rate_rad_s.abs() > crate::estimation::planar::MAX_YAW_RATE_RAD_S
        {
            return Err(bad(file, row.line, format!("implausible command {} m/s, {} rad/s", c.speed_m_s, -c.yaw_rate_rad_s)));
        }
        match out.last_mut() {
            Some(last) if last.t == t => {
                *last = c;
                repeated += 1;
            }
            _ => out.push(c),
        }
    }
    Ok((out, repeated))
}

/// What [`parse_measurements`] read: the observations kept, and the ones dropped.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Measurements {
    pub observations: Vec<Observation>,
    /// Unknown barcode -> how many observations of it.
    pub unknown: BTreeMap<u32, usize>,
    /// Observations of the robot's own barcode.
    pub own: usize,
}

/// `RobotN_Measurement.dat` of robot `id`: observations of known barcodes other than its own;
/// the others counted.
pub fn parse_measurements(
    file: &str,
    text: &str,
    id: PlatformId,
    barcodes: &BTreeMap<u32, u16>,
) -> Result<Measurements, DatasetError> {
    let mut out: Vec<Observation> = Vec::new();
    let (mut unknown, mut own) = (BTreeMap::new(), 0);
    let mut prev = None;
    for row in rows(file, text, 4)? {
        let t = time(file, &row)?;
        not_backwards(file, &row, prev, t)?;
        prev = Some(t);
        let barcode = integer(file, &row, 1, "barcode")?;
        let range_m = number(file, &row, 2, "range")?;
        let bearing = number(file, &row, 3, "bearing")?;
        if range_m <= 0.0 {
            return Err(bad(file, row.line, format!("range {range_m} m is not positive")));
        }
        let Some(&subject) = barcodes.get(&barcode) else {
            *unknown.entry(barcode).or_insert(0) += 1;
            continue;
        };
        if subject == id {
            own += 1;
            continue;
        }
        let target = if subject <= ROBOTS { Target::Robot(subject) } else { Target::Landmark(subject) };
        out.push(Observation { t, target, range_m, bearing_rad: -bearing });
    }
    Ok(Measurements { observations: out, unknown, own })
}

/// `RobotN_Groundtruth.dat`: the poses, and how many rows repeated a time stamp (dropped).
pub fn parse_groundtruth(file: &str, text: &str) -> Result<(Vec<TruthPose>, usize), DatasetError> {
    let mut out: Vec<TruthPose> = Vec::new();
    let mut repeated = 0;
    for row in rows(file, text, 4)? {
        let t = time(file, &row)?;
        not_backwards(file, &row, out.last().map(|p| p.t), t)?;
        if out.last().is_some_and(|p| p.t == t) {
            repeated += 1;
            continue;
        }
        let (x, y, theta) = (number(file, &row, 1, "x")?, number(file, &row, 2, "y")?, number(file, &row, 3, "orientation")?);
        out.push(TruthPose { t, n_m: x, e_m: -y, yaw_rad: crate::estimation::unicycle::wrap_angle(-theta) });
    }
    Ok((out, repeated))
}

fn read(dir: &Path, name: &str) -> Result<String, DatasetError> {
    let path = dir.join(name);
    let file = path.display().to_string();
    let bytes = std::fs::read(&path).map_err(|source| DatasetError::Io { file: file.clone(), source })?;
    String::from_utf8(bytes).map_err(|e| DatasetError::File {
        file,
        problem: format!("not text (byte {} is not UTF-8)", e.utf8_error().valid_up_to()),
    })
}

/// Reads an official MRCLAM folder (see the module documentation).
pub fn read_folder(dir: &Path) -> Result<Dataset, DatasetError> {
    let barcodes_file = dir.join("Barcodes.dat").display().to_string();
    let barcodes = parse_barcodes(&barcodes_file, &read(dir, "Barcodes.dat")?)?;
    let landmarks_file = dir.join("Landmark_Groundtruth.dat").display().to_string();
    let landmarks = parse_landmarks(&landmarks_file, &read(dir, "Landmark_Groundtruth.dat")?)?;
    let mut counts = ImportCounts::default();
    let mut robots = Vec::new();
    for id in 1..=ROBOTS {
        let name = |kind: &str| format!("Robot{id}_{kind}.dat");
        let path = |kind: &str| dir.join(name(kind)).display().to_string();
        let (commands, repeated) = parse_odometry(&path("Odometry"), &read(dir, &name("Odometry"))?)?;
        let Measurements { observations, unknown, own } =
            parse_measurements(&path("Measurement"), &read(dir, &name("Measurement"))?, id, &barcodes)?;
        let (truth, repeated_truth) = parse_groundtruth(&path("Groundtruth"), &read(dir, &name("Groundtruth"))?)?;
        if truth.is_empty() {
            return Err(DatasetError::File { file: path("Groundtruth"), problem: "no ground truth".into() });
        }
        counts.unknown_barcodes.extend(unknown.into_iter().map(|(b, n)| (id, b, n)));
        counts.self_observations.push((id, own));
        counts.repeated_command_times.push((id, repeated));
        counts.repeated_truth_times.push((id, repeated_truth));
        robots.push(Robot { id, commands, observations, truth });
    }
    let t0 = robots.iter().map(|r| r.truth[0].t).min().expect("five robots");
    // A file that runs on for more than a week after the first ground truth holds a damaged time.
    for r in &robots {
        let lasts = [
            ("Odometry", r.commands.last().map(|c| c.t)),
            ("Measurement", r.observations.last().map(|o| o.t)),
            ("Groundtruth", r.truth.last().map(|p| p.t)),
        ];
        for (kind, last) in lasts {
            if let Some(last) = last.filter(|&t| t > t0 && t.secs_since(t0) > super::log::MAX_SPAN_S) {
                return Err(DatasetError::File {
                    file: dir.join(format!("Robot{}_{kind}.dat", r.id)).display().to_string(),
                    problem: format!(
                        "its last time {} s is {:.0} s after the first ground truth (more than a week: a damaged time?)",
                        last.as_secs_f64(),
                        last.secs_since(t0)
                    ),
                });
            }
        }
    }
    let t_end = robots
        .iter()
        .flat_map(|r| {
            [r.commands.last().map(|c| c.t), r.observations.last().map(|o| o.t), r.truth.last().map(|p| p.t)]
                .into_iter()
                .flatten()
        })
        .max()
        .expect("ground truth");
    let name = dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into_owned());
    Ok(Dataset { name, t0, t_end, robots, landmarks, counts })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_are_read_exactly() {
        assert_eq!(parse_time_us("1248444187.156"), Some(1_248_444_187_156_000));
        assert_eq!(parse_time_us("12"), Some(12_000_000));
        assert_eq!(parse_time_us("0.000001"), Some(1));
        for bad in ["", ".5", "1.2345678", "-1.0", "1e3", "1.2.3", "nan"] {
            assert_eq!(parse_time_us(bad), None, "{bad}");
        }
    }

    #[test]
    fn comments_crlf_and_tabs_are_read() {
        let text = "# header\r\n# Fomat:\r\n1248444187.156 \t  0.086 \t -0.398 \r\n\r\n1248444187.186 \t  0.05 \t 0.1 \r\n";
        let (c, rep) = parse_odometry("odo", text).unwrap();
        assert_eq!(rep, 0);
        assert_eq!(c.len(), 2);
        assert_eq!(c[0].t, TimeUs(1_248_444_187_156_000));
        assert!((c[0].yaw_rate_rad_s - 0.398).abs() < 1e-12, "counter-clockwise becomes clockwise-negative");
    }

    #[test]
    fn bad_lines_are_named_by_file_and_line() {
        let e = parse_odometry("R1_Odometry.dat", "# h\n1.0 0.1 0.0\n2.0 0.1\n").unwrap_err().to_string();
        assert!(e.starts_with("R1_Odometry.dat:3: 2 fields, expected 3"), "{e}");
        let e = parse_odometry("o", "1.0 0.1 0.0\n0.5 0.1 0.0\n").unwrap_err().to_string();
        assert!(e.starts_with("o:2: time 0.5 s is before"), "{e}");
        let e = parse_groundtruth("g", "1.0 x 0.0 0.0\n").unwrap_err().to_string();
        assert!(e.starts_with("g:1: x \"x\" is not a finite number"), "{e}");
        let e = parse_groundtruth("g", "1.0 inf 0.0 0.0\n").unwrap_err().to_string();
        assert!(e.contains("not a finite number"), "{e}");
        let e = parse_odometry("o", "1.0 100 0.0\n").unwrap_err().to_string();
        assert!(e.contains("implausible command"), "{e}");
    }

    #[test]
    fn unknown_and_own_barcodes_are_counted_and_dropped() {
        let barcodes = parse_barcodes("b", "1 5\n2 14\n3 41\n4 32\n5 23\n6 63\n").unwrap();
        let text = "1.0 14 2.0 0.1\n1.0 63 3.0 -0.2\n1.1 99 1.0 0.0\n1.2 99 1.0 0.0\n1.3 5 1.0 0.0\n";
        let Measurements { observations: obs, unknown, own } = parse_measurements("m", text, 1, &barcodes).unwrap();
        assert_eq!(obs.len(), 2);
        assert_eq!(obs[0].target, Target::Robot(2));
        assert_eq!(obs[1].target, Target::Landmark(6));
        assert!((obs[1].bearing_rad - 0.2).abs() < 1e-12);
        assert_eq!(unknown.get(&99), Some(&2));
        assert_eq!(own, 1);
    }

    #[test]
    fn repeated_stamps_keep_the_later_command_and_the_first_pose() {
        let (c, rep) = parse_odometry("o", "1.0 0.1 0.0\n1.0 0.2 0.0\n2.0 0.0 0.0\n").unwrap();
        assert_eq!((c.len(), rep), (2, 1));
        assert_eq!(c[0].speed_m_s, 0.2);
        let (g, rep) = parse_groundtruth("g", "1.0 1 2 0\n1.0 5 5 0\n2.0 1 2 0\n").unwrap();
        assert_eq!((g.len(), rep), (2, 1));
        assert_eq!((g[0].n_m, g[0].e_m), (1.0, -2.0));
    }

    #[test]
    fn barcode_table_must_name_every_robot_once() {
        assert!(parse_barcodes("b", "1 5\n2 14\n3 41\n4 32\n").unwrap_err().to_string().contains("robot 5"));
        assert!(parse_barcodes("b", "1 5\n2 5\n").unwrap_err().to_string().contains("b:2: barcode 5 is listed twice"));
    }

    #[test]
    fn a_missing_file_is_named() {
        let dir = std::env::temp_dir().join(format!("cooploc-mrclam-missing-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = read_folder(&dir).unwrap_err().to_string();
        assert!(e.contains("Barcodes.dat") && e.contains("No such file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
