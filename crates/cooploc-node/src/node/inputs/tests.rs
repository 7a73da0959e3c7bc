use super::*;
use crate::node::profile::YawRateSource;
use crate::protocol::dialect::cooploc::{
    HIGHRES_IMU_DATA, HighresImuUpdatedFlags, MavFrame, ODOMETRY_DATA, RAW_IMU_DATA, SCALED_IMU2_DATA, SYSTEM_TIME_DATA,
    WHEEL_DISTANCE_DATA,
};

fn inputs(edit: impl FnOnce(&mut Inputs)) -> VehicleInputs {
    let mut cfg = Inputs::default();
    edit(&mut cfg);
    VehicleInputs::new(cfg)
}

fn imu(e: Vec<VehicleEvent>) -> ImuSample {
    match e.as_slice() {
        [VehicleEvent::Input(NodeInput::Imu(s))] => *s,
        other => panic!("expected one IMU sample, got {other:?}"),
    }
}

fn odo(e: Vec<VehicleEvent>) -> OdometerSample {
    match e.as_slice() {
        [VehicleEvent::Input(NodeInput::Odometer(s))] => *s,
        other => panic!("expected one odometer sample, got {other:?}"),
    }
}

fn raw(time_usec: u64, acc: [i16; 3], gyro: [i16; 3]) -> MavMessage {
    MavMessage::RAW_IMU(RAW_IMU_DATA {
        time_usec,
        xacc: acc[0],
        yacc: acc[1],
        zacc: acc[2],
        xgyro: gyro[0],
        ygyro: gyro[1],
        zgyro: gyro[2],
        ..Default::default()
    })
}

fn scaled2(ms: u32, zacc: i16) -> MavMessage {
    MavMessage::SCALED_IMU2(SCALED_IMU2_DATA { time_boot_ms: ms, zacc, ..Default::default() })
}

fn highres(time_usec: u64, id: u8, fields: u16, zacc: f32) -> MavMessage {
    MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
        time_usec,
        zacc,
        id,
        fields_updated: HighresImuUpdatedFlags::from_bits_truncate(fields),
        ..Default::default()
    })
}

fn wheels(time_usec: u64, count: u8, d: &[f64]) -> MavMessage {
    let mut distance = [0.0; 16];
    distance[..d.len()].copy_from_slice(d);
    MavMessage::WHEEL_DISTANCE(WHEEL_DISTANCE_DATA { time_usec, distance, count })
}

fn system_time(unix_us: u64, boot_ms: u32) -> MavMessage {
    MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA { time_unix_usec: unix_us, time_boot_ms: boot_ms })
}

#[test]
fn raw_imu_is_scaled_and_instantaneous_samples_are_averaged_over_their_interval() {
    let mut d = inputs(|c| c.imu = ImuMessage::RawImu);
    // the first sample is held over its (unknown) interval
    let s = imu(d.decode(&raw(1_000_000, [0, 0, -1000], [0, 0, 10])));
    assert_eq!(s.t, TimeUs(1_000_000));
    assert!((s.specific_force_frd_m_s2[2] + 9.80665).abs() < 1e-12);
    assert!((s.angular_rate_frd_rad_s[2] - 0.01).abs() < 1e-12);
    // the next is the mean of the two readings (trapezoid over 25 ms)
    let s = imu(d.decode(&raw(1_025_000, [100, 0, -1000], [0, 0, 30])));
    assert!((s.specific_force_frd_m_s2[0] - 0.5 * 0.980665).abs() < 1e-12);
    assert!((s.angular_rate_frd_rad_s[2] - 0.02).abs() < 1e-12);
    // after a gap the sample is held, not averaged with a reading from long ago
    let s = imu(d.decode(&raw(1_525_000, [200, 0, -1000], [0, 0, 0])));
    assert!((s.specific_force_frd_m_s2[0] - 2.0 * 0.980665).abs() < 1e-12);
    // a saturated axis and a repeat are refused and counted
    assert!(d.decode(&raw(1_550_000, [i16::MIN, 0, -1000], [0, 0, 0])).is_empty());
    assert!(d.decode(&raw(1_525_000, [0, 0, -1000], [0, 0, 0])).is_empty());
    assert_eq!((d.counters.imu, d.counters.imu_invalid, d.counters.imu_out_of_order), (3, 1, 1));
    // another IMU's RAW_IMU is not ours
    let mut other = RAW_IMU_DATA { time_usec: 1_600_000, id: 1, ..Default::default() };
    other.zacc = -1000;
    assert!(d.decode(&MavMessage::RAW_IMU(other)).is_empty());
    assert_eq!(d.counters.imu_other, 1);
}

#[test]
fn highres_imu_honours_its_id_and_fields_updated() {
    let mut d = inputs(|c| c.imu_id = 2);
    assert!(d.decode(&highres(10, 0, 0x3f, -9.8)).is_empty());
    assert_eq!(d.counters.imu_other, 1);
    // only the magnetometer is fresh: a repeat of the last IMU values
    assert!(d.decode(&highres(20, 2, 0b1_1100_0000, -9.8)).is_empty());
    assert_eq!(d.counters.imu_not_updated, 1);
    let s = imu(d.decode(&highres(30, 2, 0x3f, -9.8)));
    assert_eq!(s.t, TimeUs(30));
    // averages are taken as they are (PX4): no trapezoid
    let s = imu(d.decode(&highres(5030, 2, 0x1fff, -9.6)));
    assert_eq!(s.specific_force_frd_m_s2[2], -9.6f32 as f64);
}

#[test]
fn time_boot_ms_wraps_without_a_step() {
    let mut d = inputs(|c| c.imu = ImuMessage::ScaledImu2);
    let before = u32::MAX - 15; // 49.7 days of uptime
    let t0 = imu(d.decode(&scaled2(before, -1000))).t;
    let t1 = imu(d.decode(&scaled2(before.wrapping_add(20), -1000))).t;
    assert_eq!(t1.0 - t0.0, 20_000, "20 ms across the wrap");
    assert_eq!(d.counters.time_wraps, 1);
    // a frame from before the wrap that arrives late is placed before it, not 49 days ahead
    assert!(d.decode(&scaled2(before + 5, -1000)).is_empty());
    assert_eq!(d.counters.imu_out_of_order, 1);
    let t2 = imu(d.decode(&scaled2(before.wrapping_add(40), -1000))).t;
    assert_eq!(t2.0 - t1.0, 20_000);
}

#[test]
fn a_unix_team_clock_maps_boot_stamps_with_system_time_and_back() {
    let mut d = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Unix;
    });
    // before any SYSTEM_TIME the team time of a boot stamp is unknown: held
    assert!(d.decode(&raw(5_000_000, [0, 0, -1000], [0; 3])).is_empty());
    // a SYSTEM_TIME without Unix time (no RTC yet) does not help
    assert!(d.decode(&system_time(0, 5_010)).is_empty());
    assert!(d.decode(&raw(5_020_000, [0, 0, -1000], [0; 3])).is_empty());
    let unix0 = 1_795_000_000_000_000u64; // 2026-11-18
    // the first one with Unix time releases what was held, in order, in Unix time
    let released: Vec<TimeUs> = d
        .decode(&system_time(unix0, 5_030))
        .into_iter()
        .map(|e| match e {
            VehicleEvent::Input(NodeInput::Imu(s)) => s.t,
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(released, [TimeUs(unix0 - 30_000), TimeUs(unix0 - 10_000)]);
    assert_eq!(d.counters.waiting_for_clock, 0);
    let s = imu(d.decode(&raw(5_040_000, [0, 0, -1000], [0; 3])));
    assert_eq!(s.t, TimeUs(unix0 + 10_000));
    assert_eq!(d.to_vehicle_time(s.t), 5_040_000);
    // a SYSTEM_TIME that disagrees by a second is counted, not adopted (the filter's time would jump)
    d.decode(&system_time(unix0 + 1_050_000, 5_050));
    assert_eq!(d.counters.clock_disagreements, 1);
    assert_eq!(imu(d.decode(&raw(5_070_000, [0, 0, -1000], [0; 3]))).t, TimeUs(unix0 + 40_000));
    // an estimate's time_boot_ms in the team clock: taken in, or only looked at (a stamp seconds
    // behind the samples, looked at many times, is no reboot and no stale stamp)
    assert_eq!(d.team_time_of_boot_ms(5_060), Some(TimeUs(unix0 + 30_000)));
    for _ in 0..5 {
        assert_eq!(d.peek_team_time_of_boot_ms(2_070), Some(TimeUs(unix0 - 2_960_000)));
    }
    assert_eq!((d.counters.reboots, d.counters.stale_stamps), (0, 0));
    // a source that stamps in Unix time already needs no SYSTEM_TIME
    let mut u = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Unix;
    });
    assert_eq!(imu(u.decode(&raw(unix0 + 30_000, [0, 0, -1000], [0; 3]))).t, TimeUs(unix0 + 30_000));
}

#[test]
fn an_autopilot_reboot_is_told_from_a_late_frame() {
    let mut d = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Unix;
    });
    let unix0 = 1_795_000_000_000_000u64;
    d.decode(&system_time(unix0, 600_000));
    let s = imu(d.decode(&raw(600_000_000, [0, 0, -1000], [0; 3])));
    assert_eq!(s.t, TimeUs(unix0));
    // one frame 2 s old: dropped, not a reboot
    assert!(d.decode(&raw(598_000_000, [0, 0, -1000], [0; 3])).is_empty());
    assert_eq!((d.counters.stale_stamps, d.counters.reboots), (1, 0));
    assert_eq!(d.decode(&raw(600_010_000, [0, 0, -1000], [0; 3])).len(), 1);
    // the autopilot reboots: its clock restarts; three stamps confirm it
    for k in 0..3 {
        assert!(d.decode(&raw(2_000_000 + k * 10_000, [0, 0, -1000], [0; 3])).is_empty());
    }
    assert_eq!(d.counters.reboots, 1);
    // the new boot's mapping comes from its SYSTEM_TIME: 10 min later in Unix time
    let unix1 = unix0 + 600_000_000;
    d.decode(&system_time(unix1, 2_030));
    let s = imu(d.decode(&raw(2_040_000, [0, 0, -1000], [0; 3])));
    assert_eq!(s.t, TimeUs(unix1 + 10_000));
}

#[test]
fn wheel_distances_are_differentiated_with_resets_bridged() {
    let mut d = inputs(|c| {
        c.odometer = OdometerMessage::WheelDistance;
        c.wheels = vec![0, 1];
        c.wheel_track_m = Some(0.5);
    });
    assert!(d.decode(&wheels(1_000_000, 2, &[10.0, 10.0])).is_empty());
    // 50 ms: left 0.11 m, right 0.09 m: 2 m/s, turning right at 0.8 rad/s
    let s = odo(d.decode(&wheels(1_050_000, 2, &[10.11, 10.09])));
    assert_eq!(s.t, TimeUs(1_025_000), "stamped at the middle of the interval");
    assert!((s.speed_m_s - 2.0).abs() < 1e-9);
    assert!((d.last_wheel_yaw_rate_rad_s.unwrap() - 0.8).abs() < 1e-9);
    // the encoder counters reset to zero: counted, and the next interval starts from there
    assert!(d.decode(&wheels(1_100_000, 2, &[0.0, 0.0])).is_empty());
    assert_eq!(d.counters.wheel_resets, 1);
    let s = odo(d.decode(&wheels(1_150_000, 2, &[0.1, 0.1])));
    assert!((s.speed_m_s - 2.0).abs() < 1e-9);
    // a message without the wheel, a count change, a gap
    assert!(d.decode(&wheels(1_200_000, 1, &[0.2])).is_empty());
    assert_eq!(d.counters.odometer_invalid, 1);
    assert!(d.decode(&wheels(3_000_000, 2, &[3.0, 3.0])).is_empty());
    assert_eq!(d.counters.wheel_gaps, 1);
    // driving backwards is a negative speed, not a reset
    let s = odo(d.decode(&wheels(3_100_000, 2, &[2.9, 2.9])));
    assert!((s.speed_m_s + 1.0).abs() < 1e-9);
    assert_eq!(d.counters.wheel_resets, 1);
}

/// A planar robot's decoder: each WHEEL_DISTANCE interval is a drive sample stamped at its end,
/// with the differential drive's yaw rate; IMU messages are not its input.
#[test]
fn a_planar_robots_wheels_are_its_drive_samples() {
    let cfg = Inputs::default().planar_wheels(0.5);
    let mut d = VehicleInputs::new(cfg).wheel_drive();
    assert!(d.decode(&wheels(1_000_000, 2, &[10.0, 10.0])).is_empty());
    let e = d.decode(&wheels(1_050_000, 2, &[10.11, 10.09]));
    let [VehicleEvent::Input(NodeInput::Wheel(s))] = e.as_slice() else { panic!("one wheel sample, got {e:?}") };
    assert_eq!(s.t, TimeUs(1_050_000), "stamped at the end of its interval");
    assert!((s.speed_m_s - 2.0).abs() < 1e-9 && (s.yaw_rate_rad_s - 0.8).abs() < 1e-9, "{s:?}");
    // a reset is bridged as for an odometer
    assert!(d.decode(&wheels(1_100_000, 2, &[0.0, 0.0])).is_empty());
    assert_eq!(d.counters.wheel_resets, 1);
    let e = d.decode(&wheels(1_150_000, 2, &[0.1, 0.1]));
    assert!(matches!(e.as_slice(), [VehicleEvent::Input(NodeInput::Wheel(s))] if (s.speed_m_s - 2.0).abs() < 1e-9));
    // the IMU is not a planar robot's input
    assert!(d.decode(&highres(1_150_000, 0, 0x3F, -9.8)).is_empty());
    assert_eq!(d.counters.imu, 0);
}

fn highres_gyro(time_usec: u64, z: f32) -> MavMessage {
    let mut m = highres(time_usec, 0, 0x3F, -9.8);
    if let MavMessage::HIGHRES_IMU(h) = &mut m {
        h.zgyro = z;
    }
    m
}

fn wheel_sample(e: &[VehicleEvent]) -> Vec<WheelSample> {
    e.iter()
        .map(|e| match e {
            VehicleEvent::Input(NodeInput::Wheel(s)) => *s,
            other => panic!("expected wheel samples, got {other:?}"),
        })
        .collect()
}

/// A planar robot with a yaw-rate gyro: each wheel interval's yaw rate is the gyro's mean over
/// that interval, whichever of the two streams comes first; an interval the gyro never covers
/// falls back to the wheels' own yaw rate after half a second, counted.
#[test]
fn a_yaw_rate_gyro_gives_the_wheel_intervals_their_yaw_rate() {
    let cfg = Inputs { yaw_rate: YawRateSource::Gyro, ..Inputs::default().planar_wheels(0.5) };
    let mut d = VehicleInputs::new(cfg).wheel_drive();
    // gyro at 100 Hz: 0.2 rad/s until 1.02 s, then 0.4 rad/s
    for k in 95..=102u64 {
        assert!(d.decode(&highres_gyro(k * 10_000, 0.2)).is_empty());
    }
    assert!(d.decode(&wheels(1_000_000, 2, &[10.0, 10.0])).is_empty());
    // the wheels say straight ahead; the gyro knows better. (1.0, 1.02] is covered: released now
    let got = wheel_sample(&d.decode(&wheels(1_020_000, 2, &[10.04, 10.04])));
    assert_eq!(got.len(), 1);
    assert!((got[0].speed_m_s - 2.0).abs() < 1e-9 && (got[0].yaw_rate_rad_s - 0.2).abs() < 1e-7, "{got:?}");
    // a wheel interval before its gyro samples: held, then released with the gyro's mean
    assert!(d.decode(&wheels(1_060_000, 2, &[10.12, 10.12])).is_empty());
    assert!(d.decode(&highres_gyro(1_030_000, 0.4)).is_empty());
    assert!(d.decode(&highres_gyro(1_040_000, 0.4)).is_empty());
    assert!(d.decode(&highres_gyro(1_050_000, 0.4)).is_empty());
    let got = wheel_sample(&d.decode(&highres_gyro(1_060_000, 0.4)));
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].t, TimeUs(1_060_000));
    assert!((got[0].yaw_rate_rad_s - 0.4).abs() < 1e-7, "{got:?}");
    // the gyro stops: after 0.5 s of wheels the wheels' yaw rate is taken, counted
    let mut out = Vec::new();
    for k in 1..=30u64 {
        let dist = 10.12 + 0.04 * k as f64;
        out.extend(d.decode(&wheels(1_060_000 + k * 20_000, 2, &[dist + 0.001 * k as f64, dist - 0.001 * k as f64])));
    }
    let got = wheel_sample(&out);
    assert!(!got.is_empty() && d.counters.gyro_missing as usize == got.len(), "{:?}", d.counters);
    // 2 mm more on the left per 20 ms over a 0.5 m track: 0.2 rad/s to the right
    assert!(got.iter().all(|s| (s.yaw_rate_rad_s - 0.2).abs() < 1e-6), "{got:?}");
    assert!(got.windows(2).all(|w| w[0].t < w[1].t));
}

/// An autopilot reboot drops the gyro samples and the wheel intervals of the boot before
/// (counted), and the robot navigates on the new boot's gyro at once.
#[test]
fn a_reboot_does_not_leave_a_gyro_robot_waiting() {
    let cfg = Inputs { yaw_rate: YawRateSource::Gyro, ..Inputs::default().planar_wheels(0.5) };
    let mut d = VehicleInputs::new(cfg).wheel_drive();
    for k in 0..=20u64 {
        d.decode(&highres_gyro(100_000_000 + k * 10_000, 0.1));
    }
    assert!(d.decode(&wheels(100_000_000, 2, &[5.0, 5.0])).is_empty());
    assert_eq!(wheel_sample(&d.decode(&wheels(100_050_000, 2, &[5.1, 5.1]))).len(), 1);
    // a wheel interval the gyro has not reached when the autopilot reboots
    assert!(d.decode(&wheels(100_300_000, 2, &[5.6, 5.6])).is_empty());
    for k in 0..=12u64 {
        d.decode(&highres_gyro(1_000_000 + k * 10_000, -0.3));
    }
    assert_eq!(d.counters.reboots, 1);
    assert_eq!(d.counters.gyro_missing, 1, "the interval of the boot before: {:?}", d.counters);
    assert!(d.decode(&wheels(1_050_000, 2, &[0.0, 0.0])).is_empty());
    let got = wheel_sample(&d.decode(&wheels(1_100_000, 2, &[0.1, 0.1])));
    assert_eq!(got.len(), 1, "released on the new boot's gyro");
    assert!((got[0].yaw_rate_rad_s + 0.3).abs() < 1e-6 && (got[0].speed_m_s - 2.0).abs() < 1e-9, "{got:?}");
}

#[test]
fn odometry_from_the_autopilots_own_ekf_is_not_an_odometer() {
    let mut d = inputs(|_| {});
    let mut m = ODOMETRY_DATA {
        time_usec: 100,
        vx: 3.0,
        child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
        estimator_type: MavEstimatorType::MAV_ESTIMATOR_TYPE_AUTOPILOT,
        ..Default::default()
    };
    assert!(d.decode(&MavMessage::ODOMETRY(m.clone())).is_empty());
    assert_eq!(d.counters.odometry_from_autopilot, 1);
    m.estimator_type = MavEstimatorType::MAV_ESTIMATOR_TYPE_UNKNOWN;
    assert_eq!(odo(d.decode(&MavMessage::ODOMETRY(m))).speed_m_s, 3.0);
}

#[test]
fn an_imu_rate_change_is_measured_and_counted() {
    let mut d = inputs(|_| {});
    let mut t = 0;
    for _ in 0..50 {
        t += 5_000;
        imu(d.decode(&highres(t, 0, 0x3f, -9.8)));
    }
    assert_eq!(d.imu_rate_hz(), Some(200.0));
    // the autopilot falls back to 50 Hz (a ground station overrode the rate)
    for _ in 0..50 {
        t += 20_000;
        imu(d.decode(&highres(t, 0, 0x3f, -9.8)));
    }
    assert_eq!(d.imu_rate_hz(), Some(50.0));
    assert_eq!(d.counters.imu_rate_changes, 1);
    // jitter of a few percent is no change
    for k in 0..50 {
        t += if k % 2 == 0 { 19_000 } else { 21_000 };
        imu(d.decode(&highres(t, 0, 0x3f, -9.8)));
    }
    assert_eq!(d.counters.imu_rate_changes, 1);
}

#[test]
fn inputs_wait_at_most_ten_seconds_for_the_team_clock() {
    let mut d = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Unix;
    });
    // 12 s of 40 Hz IMU and no SYSTEM_TIME (lost, or the autopilot has no RTC yet)
    for k in 0..480u64 {
        assert!(d.decode(&raw(1_000_000 + k * 25_000, [0, 0, -1000], [0; 3])).is_empty());
    }
    let unix0 = 1_795_000_000_000_000u64;
    let released = d.decode(&system_time(unix0, 13_000));
    // the last 10 s are kept (401 samples), the 2 s before dropped and counted
    assert_eq!(released.len() as u64 + d.counters.waiting_for_clock, 480);
    assert_eq!(released.len(), 401);
    assert_eq!(d.counters.waiting_for_clock, 79);
}

fn own_range(time_usec: u64) -> MavMessage {
    crate::protocol::wire::range_to_message(
        &crate::estimation::RangeSample { t: TimeUs(time_usec), from: 1, to: 2, range_m: 10.0, sigma_m: 0.1 },
        7,
    )
}

fn times(events: Vec<VehicleEvent>) -> Vec<TimeUs> {
    events
        .into_iter()
        .map(|e| match e {
            VehicleEvent::Input(NodeInput::Imu(s)) => s.t,
            VehicleEvent::Input(NodeInput::OwnRange { range, .. }) => range.t,
            other => panic!("{other:?}"),
        })
        .collect()
}

/// An autopilot without GNSS (SYSTEM_TIME says 0, as ArduPilot's SITL measured): the unix
/// clock never maps, every input waits and is dropped; the companion's clock through TIMESYNC
/// maps them, to the team's Unix time and back.
#[test]
fn without_gnss_only_the_companions_clock_maps_boot_stamps() {
    let unix0 = 1_795_000_000_000_000i64;
    let mut unix = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Unix;
    });
    let mut companion = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Companion;
    });
    for d in [&mut unix, &mut companion] {
        assert!(d.decode(&raw(5_000_000, [0, 0, -1000], [0; 3])).is_empty());
        assert!(d.decode(&system_time(0, 5_010)).is_empty());
        assert_eq!(d.counters.system_time_without_unix, 1);
        // a TIMESYNC mapping means nothing to a unix clock
        d.set_companion_offset(unix0 - 4_000_000);
    }
    assert!(unix.decode(&raw(5_020_000, [0, 0, -1000], [0; 3])).is_empty());
    assert_eq!(unix.clock_source(), None);
    let got = times(companion.decode(&raw(5_020_000, [0, 0, -1000], [0; 3])));
    assert_eq!(got, [TimeUs(unix0 as u64 + 1_000_000), TimeUs(unix0 as u64 + 1_020_000)]);
    assert_eq!(companion.clock_source(), Some(ClockSource::Timesync));
    assert_eq!(companion.to_vehicle_time(TimeUs(unix0 as u64 + 1_020_000)), 5_020_000);
    // a later mapping (the crystals drift) replaces it
    companion.set_companion_offset(unix0 - 4_000_300);
    assert_eq!(imu(companion.decode(&raw(5_045_000, [0, 0, -1000], [0; 3]))).t, TimeUs(unix0 as u64 + 1_044_700));
    // a GNSS time that disagrees with the companion's clock is counted (is NTP running?)
    companion.decode(&system_time(unix0 as u64 + 2_000_000, 5_050));
    assert_eq!(companion.counters.clock_disagreements, 1);
    assert_eq!(companion.clock_source(), Some(ClockSource::Timesync));
}

/// `clock = "auto"`: TIMESYNC when the autopilot answers; otherwise, after
/// [`AUTO_CLOCK_WAIT_US`] of inputs held, SYSTEM_TIME's Unix time, and what was held goes out
/// in order. A reboot forgets the mapping.
#[test]
fn an_auto_clock_takes_system_time_when_timesync_goes_unanswered() {
    let unix0 = 1_795_000_000_000_000u64;
    let mut d = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Auto;
    });
    assert!(d.decode(&system_time(unix0, 5_000)).is_empty());
    let mut released = Vec::new();
    for k in 0..=120u64 {
        released.extend(times(d.decode(&raw(5_000_000 + k * 25_000, [0, 0, -1000], [0; 3]))));
        if k < 120 {
            assert!(released.is_empty(), "held until 3 s have waited, at sample {k}");
        }
    }
    assert_eq!(released.len(), 121);
    assert_eq!(released[0], TimeUs(unix0));
    assert_eq!(d.clock_source(), Some(ClockSource::SystemTime));
    // chosen: a TIMESYNC answer now does not move the team clock
    d.set_companion_offset(12_345);
    assert_eq!(d.clock_source(), Some(ClockSource::SystemTime));
    // a reboot forgets it; TIMESYNC answers first this time
    for k in 0..3u64 {
        d.decode(&raw(1_000_000 + k * 25_000, [0, 0, -1000], [0; 3]));
    }
    assert_eq!(d.counters.reboots, 1);
    assert_eq!(d.clock_source(), None);
    d.set_companion_offset(unix0 as i64 + 7_000_000);
    // the sample that confirmed the reboot was held; both go out now
    assert_eq!(times(d.decode(&raw(1_100_000, [0, 0, -1000], [0; 3]))), [TimeUs(unix0 + 8_050_000), TimeUs(unix0 + 8_100_000)]);
    assert_eq!(d.clock_source(), Some(ClockSource::Timesync));
}

/// With an epoch grid, the vehicle's ranges go to the nearest grid instant of the team's clock
/// (two nodes' mappings differ by a little), and one far off the grid is counted.
#[test]
fn ranges_are_put_on_the_epoch_grid() {
    let unix0 = 1_795_000_000_000_000i64;
    let mut d = inputs(|c| {
        c.clock = TeamClock::Companion;
        c.epoch_grid_ms = 100;
    });
    // this node's mapping is 3.2 ms off another node's: its range of the epoch at unix0 + 1 s
    d.set_companion_offset(unix0 - 10_000_000 + 3_200);
    assert_eq!(times(d.decode(&own_range(11_000_000))), [TimeUs(unix0 as u64 + 1_000_000)]);
    assert_eq!(times(d.decode(&own_range(11_996_000))), [TimeUs(unix0 as u64 + 2_000_000)]);
    assert_eq!(d.counters.ranges_off_grid, 0);
    assert_eq!(times(d.decode(&own_range(12_030_000))), [TimeUs(unix0 as u64 + 2_000_000)]);
    assert_eq!(d.counters.ranges_off_grid, 1);
    // without a grid a range keeps its mapped time
    let mut plain = inputs(|c| c.clock = TeamClock::Companion);
    plain.set_companion_offset(unix0 - 10_000_000 + 3_200);
    assert_eq!(times(plain.decode(&own_range(11_000_000))), [TimeUs(unix0 as u64 + 1_003_200)]);
}

fn gps(time_usec: u64, fix_type: crate::protocol::dialect::cooploc::GpsFixType, north_m: f64, h_acc: u32) -> MavMessage {
    const O: GeoOrigin = GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16523, alt_m: 584.0 };
    MavMessage::GPS_RAW_INT(crate::protocol::dialect::cooploc::GPS_RAW_INT_DATA {
        time_usec,
        fix_type,
        lat: wire::deg_to_e7(O.lat_deg + north_m / 111_319.49),
        lon: wire::deg_to_e7(O.lon_deg),
        alt: 584_000,
        eph: u16::MAX,
        h_acc,
        v_acc: 2 * h_acc,
        ..Default::default()
    })
}

fn fixes(e: Vec<VehicleEvent>) -> Vec<crate::estimation::PositionFixSample> {
    e.into_iter()
        .filter_map(|e| match e {
            VehicleEvent::Input(NodeInput::PositionFix(s)) => Some(s),
            _ => None,
        })
        .collect()
}

/// GNSS fixes are inputs only once the hand-over asked for them (the team's origin given): a
/// 3D fix about the origin, its stamp less the receiver's lag, in the team's clock; a repeat
/// of the same fix, a fix without accuracy, one before the clock is mapped or long stale are
/// dropped and counted, and no fix stamp takes part in the reboot detection.
#[test]
fn gnss_fixes_are_taken_once_asked_for_once_each_and_in_the_team_clock() {
    use crate::protocol::dialect::cooploc::GpsFixType::{GPS_FIX_TYPE_2D_FIX, GPS_FIX_TYPE_3D_FIX, GPS_FIX_TYPE_RTK_FIXED};
    let origin = GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16523, alt_m: 584.0 };
    let mut d = inputs(|c| {
        c.imu = ImuMessage::RawImu;
        c.clock = TeamClock::Companion;
        c.gnss_lag_ms = 100;
    });
    assert!(fixes(d.decode(&gps(5_000_000, GPS_FIX_TYPE_3D_FIX, 10.0, 300))).is_empty(), "not asked for");
    assert_eq!(d.counters.gnss_fixes, 0);
    d.fuse_gnss(origin);
    assert!(fixes(d.decode(&gps(5_000_000, GPS_FIX_TYPE_3D_FIX, 10.0, 300))).is_empty(), "no team clock yet");
    assert_eq!(d.counters.gnss_stale, 1);
    let unix0 = 1_795_000_000_000_000u64;
    d.set_companion_offset(unix0 as i64);
    d.decode(&raw(5_150_000, [0, 0, -1000], [0; 3]));
    let got = fixes(d.decode(&gps(5_200_000, GPS_FIX_TYPE_3D_FIX, 10.0, 300)));
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].t, TimeUs(unix0 + 5_100_000), "stamped on arrival, less the 100 ms lag");
    assert!((got[0].pos_ned_m.x - 10.0).abs() < 0.01 && got[0].pos_ned_m.y.abs() < 0.01, "{:?}", got[0]);
    assert_eq!((got[0].sigma_h_m, got[0].sigma_v_m), (0.3, Some(0.6)));
    // the same fix streamed again: once
    assert!(fixes(d.decode(&gps(5_200_000, GPS_FIX_TYPE_3D_FIX, 10.0, 300))).is_empty());
    assert_eq!(d.counters.gnss_repeats, 1);
    // no 3D fix: nothing, and not counted as bad
    assert!(fixes(d.decode(&gps(5_400_000, GPS_FIX_TYPE_2D_FIX, 10.0, 300))).is_empty());
    // no accuracy at all: refused
    assert!(fixes(d.decode(&gps(5_600_000, GPS_FIX_TYPE_RTK_FIXED, 10.0, 0))).is_empty());
    assert_eq!(d.counters.gnss_invalid, 1);
    // a fix stamped 3 s before the IMU: stale; three of them are no reboot
    d.decode(&raw(9_000_000, [0, 0, -1000], [0; 3]));
    for k in 0..3 {
        assert!(fixes(d.decode(&gps(5_800_000 + k, GPS_FIX_TYPE_3D_FIX, 10.0, 300))).is_empty());
    }
    assert_eq!((d.counters.gnss_stale, d.counters.reboots), (4, 0));
    assert_eq!(fixes(d.decode(&gps(8_900_000, GPS_FIX_TYPE_3D_FIX, 12.0, 300))).len(), 1);
    assert_eq!(d.counters.gnss_fixes, 2);
    // a fix stamped in Unix time is held to the same age, against the newest IMU stamp in the
    // team's clock (unix0 + 9 s): 3.3 s old, stale; 0.15 s old, taken as stamped
    assert!(fixes(d.decode(&gps(unix0 + 5_800_000, GPS_FIX_TYPE_3D_FIX, 12.0, 300))).is_empty());
    assert_eq!(d.counters.gnss_stale, 5);
    let got = fixes(d.decode(&gps(unix0 + 8_950_000, GPS_FIX_TYPE_3D_FIX, 12.0, 300)));
    assert_eq!(got.iter().map(|f| f.t).collect::<Vec<_>>(), vec![TimeUs(unix0 + 8_850_000)]);
}
