//! `cooploc check`: connects to an autopilot as its companion would, listens for a while, and
//! says what arrives against what a vehicle profile needs, and the autopilot parameters to set
//! (the analysis is [`cooploc::node::survey`]).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use cooploc::node::autopilot::{TimeSync, TimesyncReply};
use cooploc::node::profile::VehicleProfile;
use cooploc::node::survey::{Survey, advice};
use cooploc::node::vehicle_link::VehicleLink;
use cooploc::protocol::MavMessage;
use cooploc::protocol::dialect::cooploc::{COMMAND_LONG_DATA, MavAutopilot, MavCmd, MavType};
use cooploc::protocol::wire;
use mavlink_core::MavHeader;

#[derive(clap::Args)]
pub struct Args {
    /// MAVLink URL of the autopilot, as `cooploc node --vehicle` takes it.
    #[arg(long)]
    vehicle: String,
    /// The vehicle profile to check what arrives against (and to say which parameters it needs).
    #[arg(long)]
    vehicle_config: Option<PathBuf>,
    /// How long to listen, s.
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// The system id to speak as (the vehicle's: a companion shares it), compid 191.
    #[arg(long, default_value_t = 1)]
    id: u8,
    /// The autopilot port's signing key (as `cooploc node --vehicle-key`).
    #[arg(long, value_name = "FILE")]
    vehicle_key: Option<PathBuf>,
}

fn unix_now_ns() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as i64)
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !(args.seconds.is_finite() && args.seconds > 0.0 && args.seconds <= 3600.0) {
        anyhow::bail!("--seconds {}: more than 0, at most 3600", args.seconds);
    }
    if args.id == 0 {
        anyhow::bail!("--id 0: a MAVLink system id is 1..=255");
    }
    let profile = match &args.vehicle_config {
        Some(p) => Some(VehicleProfile::from_path(p)?),
        None => None,
    };
    let key = match &args.vehicle_key {
        Some(p) => Some(cooploc::protocol::signing::TeamKey::from_file(p).context("--vehicle-key")?),
        None => None,
    };
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let survey = rt.block_on(async {
        let mut link = VehicleLink::open(&args.vehicle).await?;
        if let Some(k) = &key {
            link.sign(k, args.id);
        }
        let mut survey = Survey::default();
        let mut sync = TimeSync::default();
        let start = Instant::now();
        let end = start + Duration::from_secs_f64(args.seconds);
        let mut seq = 0u8;
        let mut header = || {
            seq = seq.wrapping_add(1);
            MavHeader { system_id: u32::from(args.id), component_id: wire::COMPANION_COMPID, sequence: seq }
        };
        let mut next_beat = start;
        let mut buf = vec![0u8; 65_536];
        let mut asked_version = false;
        while Instant::now() < end {
            let now = Instant::now();
            if now >= next_beat {
                next_beat = now + Duration::from_secs(1);
                let hb = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
                link.send(&header(), &hb).await;
                if let Some(req) = sync.poll(start.elapsed().as_micros() as u64, unix_now_ns(), args.id) {
                    link.send(&header(), &req).await;
                }
                if !asked_version {
                    asked_version = true;
                    let ask = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                        command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
                        param1: 148.0,
                        target_system: args.id,
                        target_component: 1,
                        ..Default::default()
                    });
                    link.send(&header(), &ask).await;
                }
            }
            let wait = next_beat.min(end).saturating_duration_since(Instant::now());
            let Ok(got) = tokio::time::timeout(wait, link.recv(&mut buf)).await else { continue };
            let frames = match got {
                Ok(f) => f,
                Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => anyhow::bail!("the vehicle closed the link"),
                Err(_) => continue,
            };
            let wall_us = start.elapsed().as_micros() as u64;
            for (h, msg, bytes) in frames {
                let Some(f) = cooploc::protocol::framing::frame_at_start(&bytes) else { continue };
                survey.frame(h, msg.as_ref(), f.message_id, f.signed, wall_us);
                if let Some(MavMessage::TIMESYNC(m)) = &msg
                    && h.system_id == u32::from(args.id)
                    && let TimesyncReply::Sample = sync.on_message(m, unix_now_ns(), (h.system_id as u8, h.component_id), None)
                    && let Some((_, rtt)) = sync.offset_us()
                {
                    survey.timesync(rtt);
                }
            }
        }
        anyhow::Ok(survey)
    })?;
    print(&survey, profile.as_ref(), &args);
    Ok(())
}

fn print(survey: &Survey, profile: Option<&VehicleProfile>, args: &Args) {
    let r = survey.report(profile);
    let clock = match r.vehicle_s {
        Some(v) => format!("{:.1} s of the vehicle's clock (by SYSTEM_TIME) in {:.1} s", v, r.wall_s),
        None => format!("{:.1} s (wall: no SYSTEM_TIME)", r.wall_s),
    };
    println!("cooploc check on {}: {clock}", args.vehicle);
    match r.autopilot {
        Some((sys, ap, ty)) => {
            let version = survey.flight_sw_version.map_or("version unknown (AUTOPILOT_VERSION gave none)".to_string(), |v| {
                format!("firmware {}.{}.{}", v >> 24, (v >> 16) & 0xFF, (v >> 8) & 0xFF)
            });
            println!("autopilot: system {sys}, {ap:?}, {ty:?}, {version}");
        }
        None => println!("autopilot: no HEARTBEAT from a component 1"),
    }
    let comps: Vec<String> = survey.components.iter().map(|((s, c), (t, _))| format!("{s}/{c} {t:?}")).collect();
    println!("components: {}", if comps.is_empty() { "none".into() } else { comps.join(", ") });
    println!("messages (rate between the first and the last, in the vehicle's time where it says it):");
    for m in &r.rates {
        let src: Vec<String> = m.sources.iter().map(|(s, c)| format!("{s}/{c}")).collect();
        println!("  {:>6} {:<28} {:>6} {:>8.2} Hz  from {}", m.id, m.name, m.count, m.hz, src.join(","));
    }
    let unix = match r.unix_time {
        Some(true) => "SYSTEM_TIME carries Unix time",
        Some(false) => "SYSTEM_TIME carries no Unix time (no GNSS)",
        None => "no SYSTEM_TIME",
    };
    let sync = match survey.timesync_rtt_us {
        Some(rtt) => format!("TIMESYNC answered {} times, quickest round trip {rtt} us", survey.timesync_answers),
        None => "TIMESYNC unanswered".into(),
    };
    println!("clocks: {unix}; {sync}");
    println!(
        "signing: {} signed frames, {} unsigned; frames of other dialects: {}",
        survey.signed_frames, survey.unsigned_frames, r.other_dialect
    );
    let Some(p) = profile else {
        println!("(give --vehicle-config to check what a node on this vehicle needs)");
        return;
    };
    println!("against {}:", p.name);
    for (ok, text) in &r.checks {
        println!("  [{}] {text}", if *ok { "ok" } else { "!!" });
    }
    if let Some((_, ap, _)) = r.autopilot {
        let params = advice(ap, survey.flight_sw_version, p);
        if !params.is_empty() {
            println!("autopilot parameters for this profile:");
            for (name, value, why) in params {
                println!("  {name} = {value}    # {why}");
            }
        }
    }
}
