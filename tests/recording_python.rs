//! Cross-check of the MCAP log format with independent readers: a log with every channel kind,
//! written by [`cooploc::recording::Recorder`], read by the pinned Python `mcap` library, its
//! protobuf decoder and pymavlink (tests/python/mcap_check.py).

mod common;

use std::collections::BTreeMap;
use std::process::Command;

use cooploc::node::log::{CoopUpdateRecord, RangeRecord};
use cooploc::protocol::dialect::cooploc::{MavAutopilot, MavType};
use cooploc::protocol::wire::{self, GeoOrigin};
use cooploc::recording::record_update;
use cooploc::recording::{
    Direction, LinkStatsRecord, PeerLinkStats, PositionEstimate, Recorder, RecorderOptions, TruthSample, read_log,
};
use cooploc::time::TimeUs;
use mavlink_core::MavHeader;
use nalgebra::{Matrix3, Vector3};
use serde_json::json;

fn heartbeat(sysid: u8, seq: u8) -> Vec<u8> {
    let msg = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
    wire::to_frame(MavHeader { system_id: u32::from(sysid), component_id: 191, sequence: seq }, &msg)
}

#[test]
fn python_mcap_reads_every_channel_kind() {
    let Some(python) = common::python("the Python mcap cross-check of the log format") else { return };
    let dir = std::env::temp_dir().join(format!("cooploc-recording-python-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("every_kind.mcap");

    let origin = GeoOrigin { lat_deg: 47.397742, lon_deg: 8.545594, alt_m: 488.0 };
    let t0 = 1_750_000_000_000_000_000u64;
    let mut rec = Recorder::create(&path, RecorderOptions { geo_origin: Some(origin), ..Default::default() }).unwrap();
    rec.declare_link(cooploc::recording::Link::Vehicle(2), "udpout:127.0.0.1:14540");
    rec.declare_link(cooploc::recording::Link::Coop(2), "0.0.0.0:14600");
    let coop_rx = heartbeat(3, 7);
    for (i, (link, dir)) in [
        (cooploc::recording::Link::Vehicle(2), Direction::Rx),
        (cooploc::recording::Link::Vehicle(2), Direction::Tx),
        (cooploc::recording::Link::Coop(2), Direction::Rx),
        (cooploc::recording::Link::Coop(2), Direction::Tx),
    ]
    .into_iter()
    .enumerate()
    {
        let frame = if i == 2 { coop_rx.clone() } else { heartbeat(2, i as u8) };
        rec.frame(link, dir, t0 + i as u64 * 1000, &frame).unwrap();
    }
    #[rustfmt::skip]
    let cov = Matrix3::new(
        4.0, 0.5, 0.1,
        0.5, 1.0, -0.2,
        0.1, -0.2, 9.0,
    );
    let est = PositionEstimate {
        t: TimeUs(12_500_000),
        pos_ned_m: Vector3::new(120.0, -35.0, -2.0),
        cov_ned_m2: cov,
        yaw_rad: Some(0.3),
        vel_ned_m_s: Some(Vector3::new(1.5, 0.2, 0.0)),
    };
    rec.estimate(2, t0 + 10_000, &est).unwrap();
    rec.truth(2, t0 + 11_000, &TruthSample { t: TimeUs(12_500_000), pos_ned_m: Vector3::new(121.0, -34.0, -2.0), yaw_rad: None })
        .unwrap();
    let update = CoopUpdateRecord {
        vehicle: 2,
        epoch: 41,
        t_us: 12_500_000,
        participants: vec![1, 2, 3],
        ranges: vec![RangeRecord { from: 2, to: 1, range_m: 25.5, sigma_m: 0.3 }],
        innovation: vec![0.25],
        innovation_sigma: vec![0.4],
        nis: 0.390625,
        nis_dof: 1,
        nees: None,
        nees_dof: None,
    };
    record_update(&mut rec, t0 + 12_000, &update).unwrap();
    let stats = LinkStatsRecord {
        sysid: 2,
        window_s: 1.0,
        peers: vec![PeerLinkStats {
            sysid: 3,
            link: "127.0.0.1:14603".into(),
            rx_packets: 10,
            tx_packets: 11,
            lost_packets: 0,
            loss_ratio: 0.0,
            rx_bytes_per_s: 500.0,
            tx_bytes_per_s: 550.0,
        }],
    };
    rec.link_stats(t0 + 13_000, &stats).unwrap();
    let config = BTreeMap::from([("sysid".to_string(), "2".to_string()), ("epoch_wait_us".to_string(), "200000".to_string())]);
    rec.metadata("config", config.clone()).unwrap();
    let scenario = "[world]\nvehicles = 3\n";
    rec.attachment("scenario.toml", "application/toml", scenario.as_bytes()).unwrap();
    let written = rec.finish().unwrap().messages_written;

    // The Rust reader agrees first.
    let log = read_log(&path).unwrap();
    assert!(log.is_complete());
    assert_eq!(log.messages.len() as u64, written);

    let g = wire::ned_to_geodetic(&origin, &est.pos_ned_m);
    let cov_enu = cooploc::view::foxglove::cov_ned_to_enu(&cov);
    let cov_enu: Vec<f64> = (0..3).flat_map(|r| (0..3).map(move |c| cov_enu[(r, c)])).collect();
    let expect = json!({
        "sysid": 2, "vehicle": 2,
        "lat": g.lat_deg, "lon": g.lon_deg, "alt": g.alt_m, "cov_enu": cov_enu,
        "nis": update.nis, "epoch": update.epoch,
        "heartbeat_type": MavType::MAV_TYPE_ONBOARD_CONTROLLER as u8,
        "coop_rx_hex": coop_rx.iter().map(|b| format!("{b:02x}")).collect::<String>(),
        "attachment_name": "scenario.toml", "attachment_text": scenario,
        "config": config, "message_count": written,
    });
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new(&python)
        .arg(root.join("tests/python/mcap_check.py"))
        .arg(&path)
        .arg(expect.to_string())
        .output()
        .expect("running tests/python/mcap_check.py");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "mcap_check.py failed:\n{stdout}\n{stderr}");
    assert!(stdout.contains("mcap_check: OK"), "{stdout}");
    let _ = std::fs::remove_dir_all(&dir);
}
