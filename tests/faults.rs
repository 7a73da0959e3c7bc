//! The fault-injection harness (src/experiment/faults.rs) over every case of issue 10, 20 seeded
//! runs each, three node shells (fed the datagrams' bytes) on the paper scenario: whatever the links and the nodes do, every
//! node stays consistent, none ends meaningfully worse than dead reckoning, every disagreement
//! of the nodes' stores is detected by the nodes themselves and healed within 3 epochs of the
//! fault's end, and moderate datagram loss costs (almost) nothing.
//! `cargo run --release -- faults` prints the same numbers as a table (docs/robustness.md).

use cooploc::estimation::Method;
use cooploc::experiment::faults::{CaseSummary, FaultCase, RunOutcome, run_case, standard_cases, summarize};
use cooploc::protocol::record::Encoding;
use cooploc::sitl::{PAPER_TOML, Scenario, World};
use rayon::prelude::*;

const RUNS: u32 = 20;

/// Every case of `cases` run `runs` times (seeded runs 0..runs, in parallel): the runs of each.
fn run_cases(world: &World, cases: &[FaultCase], runs: u32) -> Vec<Vec<RunOutcome>> {
    let jobs: Vec<(usize, u32)> = (0..cases.len()).flat_map(|c| (0..runs).map(move |r| (c, r))).collect();
    let outcomes: Vec<(usize, RunOutcome)> = jobs
        .par_iter()
        .map(|&(c, r)| (c, run_case(world, &cases[c].faults, Method::Decentralized, "1hz", 1, r, Encoding::F64).unwrap()))
        .collect();
    (0..cases.len()).map(|c| outcomes.iter().filter(|(k, _)| *k == c).map(|(_, o)| o.clone()).collect()).collect()
}

fn summaries() -> Vec<CaseSummary> {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let cases = standard_cases();
    let outcomes = run_cases(&world, &cases, RUNS);
    cases.iter().enumerate().map(|(c, case)| summarize(case.name, &outcomes[c])).collect()
}

#[test]
fn every_fault_case_stays_consistent_detects_and_heals() {
    let all = summaries();
    let base = all.iter().find(|s| s.name == "fault-free").unwrap().final_rms_m;
    let free_nees = all.iter().find(|s| s.name == "fault-free").unwrap().team_nees;
    let mut problems = Vec::new();
    for s in &all {
        eprintln!("{s:?}");
        assert_eq!(s.runs, RUNS as usize);
        // Consistency, on the team's joint NEES (one chi-square sample per run): never
        // overconfident (under the band's top), and not much more conservative than the
        // fault-free filter, which itself sits at the band's bottom (its non-holonomic
        // constraint is tuned above the truth's zero, as in the experiment).
        if s.team_nees.is_nan() || s.team_nees > s.team_nees_band.1 {
            problems.push(format!("{}: team NEES {:.2} above the 95% band {:?}", s.name, s.team_nees, s.team_nees_band));
        }
        if s.team_nees < 0.85 * free_nees {
            problems.push(format!("{}: team NEES {:.2}, far under the fault-free {free_nees:.2}", s.name, s.team_nees));
        }
        if s.worse_than_dr > 0 {
            problems.push(format!("{}: {} nodes ended worse than dead reckoning by more than 3 sigma", s.name, s.worse_than_dr));
        }
        if s.runs_detected != s.runs_diverged {
            problems.push(format!("{}: {} runs diverged, only {} detected", s.name, s.runs_diverged, s.runs_detected));
        }
        if s.runs_not_recovered > 0 {
            problems.push(format!("{}: {} runs not back in agreement 3 epochs after the fault", s.name, s.runs_not_recovered));
        }
        if s.failed > 0 {
            problems.push(format!("{}: {} joint updates refused", s.name, s.failed));
        }
    }
    let rms = |name: &str| all.iter().find(|s| s.name == name).unwrap().final_rms_m;
    for (name, allowed) in [
        ("coop loss 1%", 0.10),
        ("coop loss 10%", 0.10),
        ("coop loss 30%", 0.30),
        ("coop loss 30%, packed datagrams", 0.30),
        ("coop loss 30%, packed, 5x real time", 0.30),
        // A damaged datagram costs at most what a lost one does: the shell takes its frames
        // before the damage and refuses the rest.
        ("damaged datagrams 10%", 0.10),
        ("damaged datagrams 30%, packed", 0.30),
    ] {
        if rms(name) > base * (1.0 + allowed) {
            problems.push(format!(
                "{name}: RMS {:.2} m against fault-free {base:.2} m (allowed +{:.0}%)",
                rms(name),
                allowed * 100.0
            ));
        }
    }
    for name in ["coop loss 50%", "coop loss 50%, packed datagrams", "coop loss 50%, packed, 5x real time"] {
        let heavy = all.iter().find(|s| s.name == name).unwrap();
        if heavy.final_rms_m > heavy.dr_rms_m {
            problems.push(format!("{name}: RMS {:.2} m worse than dead reckoning {:.2} m", heavy.final_rms_m, heavy.dr_rms_m));
        }
    }
    // The faults that break agreement are seen: a stall, a restart, a join and a leave each
    // make the stores diverge in every run. A node that was away (dead, not yet started, out of
    // radio range) applied nothing meanwhile: the others' store is valid for it, it is left out
    // once and takes their store, and the team goes on with the exact method, without a heal.
    for name in ["node 3 killed, back after 20 s", "node 3 joins at 100 s", "node 3 leaves for 60 s"] {
        let s = all.iter().find(|s| s.name == name).unwrap();
        if s.runs_diverged != RUNS as usize || s.stores_adopted < u64::from(RUNS) || s.heals > 0 {
            problems.push(format!("{name}: expected a divergence and a store adopted in every run, and no heal ({s:?})"));
        }
    }
    // Restored at once, node 3 is left out of its first epoch and takes the team's store in every
    // run, without a heal. On the signed team (the harness's default) its teammates stop waiting
    // for its record of the epoch it was killed in as soon as it answers their request "no
    // record" (unsigned, they wait the timeout:
    // `a_signed_team_does_not_wait_for_a_record_its_restarted_teammate_will_never_send`). They
    // run that epoch before its first record comes, so the harness sees its restored store
    // beside theirs at that epoch and the next, until it takes theirs: a divergence seen, never
    // run on. (Before the answer, the teammates ran both epochs in one step and the harness,
    // which samples each node's digest when its last epoch changes, saw no divergence; node 3's
    // store was the same.)
    let restored = all.iter().find(|s| s.name == "node 3 killed, restarted at once from its saved state").unwrap();
    if restored.runs_not_recovered > 0 || restored.stores_adopted < u64::from(RUNS) || restored.heals > 0 {
        problems.push(format!("restored at once: expected a store adopted in every run and no heal ({restored:?})"));
    }
    // A stalled node wakes up with the others' records of the epochs it slept through in its
    // sockets: it runs them as the others did, without itself (its store takes their update, its
    // filter nothing), so the stores never diverge and nothing is healed.
    for name in ["node 3 stalled 3 s", "node 3 stalled 10 s"] {
        let s = all.iter().find(|s| s.name == name).unwrap();
        if s.bystood < u64::from(RUNS) || s.runs_diverged > 0 || s.heals > 0 {
            problems.push(format!("{name}: expected epochs run as a bystander, no divergence and no heal ({s:?})"));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// Damage meets the node shell, not the core: datagrams arrive with a byte changed or cut
/// short, the shell refuses what no longer checks out (its frames before the damage are taken),
/// the core never sees a damaged record and resends what was lost, and the team ends exactly
/// where it ends without the damage.
#[test]
fn damaged_datagrams_are_refused_by_the_shell_and_cost_nothing_in_the_end() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let case = |name: &str| standard_cases().into_iter().find(|c| c.name == name).unwrap().faults;
    for run in 0..2 {
        let clean = run_case(&world, &case("fault-free"), Method::Decentralized, "1hz", 1, run, Encoding::F64).unwrap();
        for name in ["damaged datagrams 10%", "damaged datagrams 30%, packed"] {
            let got = run_case(&world, &case(name), Method::Decentralized, "1hz", 1, run, Encoding::F64).unwrap();
            for (node, free) in got.nodes.iter().zip(&clean.nodes) {
                assert!(node.coop_refused > 0, "{name}, run {run}: node {} refused no datagram", node.id);
                assert_eq!(free.coop_refused, 0);
                let s = &node.stats;
                assert_eq!(
                    (s.records_undecodable, s.fragments_rejected, s.records_implausible),
                    (0, 0, 0),
                    "{name}, run {run}: node {} saw a damaged record",
                    node.id
                );
                assert!(s.records_resent > free.stats.records_resent, "{name}: what was lost is sent again");
                assert_eq!(
                    node.final_err_m, free.final_err_m,
                    "{name}, run {run}: node {} ends where it ends without damage",
                    node.id
                );
            }
        }
    }
}

/// Which datagrams a lossy network loses does not change what 30% loss costs (resends recover
/// every record): the same world run under ten other draws of the loss (`Faults::link_seed`, as
/// a relay with its own seed draws them) ends within 1% of the run's own draw, and its error over
/// the whole run too. (A restart is another matter: its phase against the epochs moves the whole
/// run, see tests/processes.rs.)
#[test]
fn what_thirty_percent_loss_costs_does_not_depend_on_which_datagrams_are_lost() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let loss = standard_cases().into_iter().find(|c| c.name == "coop loss 30%, packed, 5x real time").unwrap().faults;
    let team = |o: &cooploc::experiment::faults::RunOutcome| {
        let rms = |f: &dyn Fn(&cooploc::experiment::faults::NodeOutcome) -> f64| {
            (o.nodes.iter().map(|n| f(n).powi(2)).sum::<f64>() / o.nodes.len() as f64).sqrt()
        };
        let resent: u64 = o.nodes.iter().map(|n| n.stats.records_resent).sum();
        (rms(&|n| n.final_err_m), rms(&|n| n.rms_err_m), resent)
    };
    let own = team(&run_case(&world, &loss, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap());
    let others: Vec<(f64, f64, u64)> = (0..10u64)
        .into_par_iter()
        .map(|s| {
            let faults = cooploc::experiment::faults::Faults { link_seed: Some(1000 + s), ..loss.clone() };
            team(&run_case(&world, &faults, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap())
        })
        .collect();
    assert!(others.iter().any(|o| o.2 != own.2), "the other draws lost other datagrams: {own:?} {others:?}");
    for (s, (fin, run, _)) in others.iter().enumerate() {
        assert!((fin / own.0 - 1.0).abs() < 0.01, "link seed {s}: final {fin:.3} m against {:.3} m", own.0);
        assert!((run / own.1 - 1.0).abs() < 0.01, "link seed {s}: over the run {run:.3} m against {:.3} m", own.1);
    }
}

/// Two members that disagree on whether a third that just left is absent do not run the next
/// epoch on different sets: the one that still waits for it goes on collecting the epoch before,
/// and the other, waiting on the next epoch for its record (a record carries the store after the
/// epoch before, so it comes once that epoch is run), sees it still collecting and waits one
/// epoch timeout more instead of running without it. Traced in run 17 of "node 3 leaves for
/// 60 s, 10% loss, delay 0-300 ms": node 2 ran epoch 152 alone 0.13 s before node 1's record of
/// it went, and the team healed. These are the runs of that case, of its first 200, that healed
/// without the rule (17, 32, 43, 52, 147, 151 and 192 with resends limited by what they carry;
/// 36, 80 and 100 before); with it none of the 200 did.
#[test]
fn a_member_still_collecting_the_epoch_before_is_waited_for_not_run_without() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let case = standard_cases().into_iter().find(|c| c.name == "node 3 leaves for 60 s, 10% loss, delay 0-300 ms").unwrap();
    let healed: Vec<(u32, Vec<u64>)> = [17u32, 32, 36, 43, 52, 80, 100, 147, 151, 192]
        .into_par_iter()
        .map(|r| (r, run_case(&world, &case.faults, Method::Decentralized, "1hz", 1, r, Encoding::F64).unwrap()))
        .map(|(r, o)| (r, o.nodes.iter().map(|n| n.stats.heals).collect::<Vec<_>>()))
        .filter(|(_, heals)| heals.iter().any(|&h| h > 0))
        .collect();
    assert!(healed.is_empty(), "runs that healed (run, heals per node): {healed:?}");
}

/// A restart's cost depends on its phase against the team's epochs (docs/robustness.md, "The
/// phase of a restart"), node 3 down for 0.05-0.4 s around epoch 114 and restored from its saved
/// state: killed at the epoch's instant (before its record of it) it ends the team worse than
/// killed in the 0.1 s after it (before its record goes: the team waits an epoch timeout for it),
/// and that worse than killed once the epoch ran with it; within each phase the gap changes
/// little. Ranges leave the team's common position unobserved, so what a restart does to it stays
/// for the rest of the run. (`-- --nocapture` prints the ratios.)
#[test]
fn a_restart_costs_what_its_phase_against_the_epochs_gives() {
    use cooploc::experiment::faults::{Faults, Outage};
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let team = |f: &Faults| {
        let o = run_case(&world, f, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap();
        (o.nodes.iter().map(|n| n.final_err_m.powi(2)).sum::<f64>() / o.nodes.len() as f64).sqrt()
    };
    let clean = team(&Faults { speed: 5.0, ..Faults::default() });
    let epoch_s = world.ranges("1hz", 1, 0).unwrap()[113].0.0 as f64 / 1e6;
    let phase = |offsets: &[f64]| -> Vec<f64> {
        let cases: Vec<(f64, f64)> = offsets.iter().flat_map(|&o| [0.05, 0.2, 0.4].map(|gap| (o, gap))).collect();
        cases
            .into_par_iter()
            .map(|(o, gap)| {
                let from_s = epoch_s + o;
                let kill = Some(Outage { node: 2, from_s, until_s: from_s + gap });
                team(&Faults { kill, restore: true, packed: true, speed: 5.0, ..Faults::default() }) / clean
            })
            .collect()
    };
    let range = |r: &[f64]| r.iter().fold((f64::MAX, 0.0f64), |(lo, hi), &x| (lo.min(x), hi.max(x)));
    let at = range(&phase(&[0.0]));
    let before_record = range(&phase(&[0.02, 0.05, 0.09]));
    let ran = range(&phase(&[0.11, 0.2, 0.3, 0.5]));
    eprintln!(
        "killed at epoch 114's instant: {at:.3?}x; before its record went: {before_record:.3?}x; after the epoch ran: {ran:.3?}x"
    );
    assert!(at.0 > before_record.1 && before_record.0 > ran.1, "{at:?} {before_record:?} {ran:?}");
    for (name, (lo, hi)) in [("at the instant", at), ("before the record", before_record), ("after the epoch", ran)] {
        assert!(hi / lo < 1.1, "{name}: the gap moved the cost from {lo:.3}x to {hi:.3}x");
    }
}

/// Node 3 killed 0.05 s after epoch 114's instant (before its record of it went) and restored
/// 0.2 s later: its record of epoch 114 will never come. It says so twice: it answers its
/// teammates' request for that record "no record" (COOPLOC_EPOCH_STATE_NO_RECORD), and its first
/// record after the restart carries the epoch it first broadcast (its own reference, before any
/// joint update). A signed team, which believes what its members say of themselves, runs epoch
/// 114 without it at once (at the answer, the sooner); an unsigned one (where a forger could say
/// the same of a genuine teammate) waits the epoch timeout. The joint update is written back at
/// the epoch's time either way.
#[test]
fn a_signed_team_does_not_wait_for_a_record_its_restarted_teammate_will_never_send() {
    use cooploc::experiment::faults::{Faults, Outage};
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let epoch_s = world.ranges("1hz", 1, 0).unwrap()[113].0.0 as f64 / 1e6;
    let kill = Some(Outage { node: 2, from_s: epoch_s + 0.05, until_s: epoch_s + 0.25 });
    let signed = Faults { kill, restore: true, packed: true, speed: 5.0, ..Faults::default() };
    let unsigned = Faults { unsigned: true, ..signed.clone() };
    let [s, u] = [&signed, &unsigned].map(|f| run_case(&world, f, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap());
    let timeout_us = cooploc::node::core::NodeConfig::for_model(
        1,
        Method::Decentralized,
        cooploc::experiment::nav_model(&world, 1),
        Encoding::F64,
        vec![1],
    )
    .epoch_timeout_us;
    for k in 0..2 {
        let (a, b) = (&s.nodes[k], &u.nodes[k]);
        eprintln!(
            "node {}: signed waited at most {:.3} s (not waited {}, partial {}), final {:.3} m, rms {:.3} m; unsigned {:.3} s (not waited {}, partial {}), final {:.3} m, rms {:.3} m",
            a.id,
            a.stats.longest_wait_us as f64 / 1e6,
            a.stats.epochs_not_waited,
            a.stats.epochs_partial,
            a.final_err_m,
            a.rms_err_m,
            b.stats.longest_wait_us as f64 / 1e6,
            b.stats.epochs_not_waited,
            b.stats.epochs_partial,
            b.final_err_m,
            b.rms_err_m
        );
        assert_eq!(b.stats.epochs_not_waited, 0, "node {}: an unsigned team believed a record", a.id);
        assert!(b.stats.longest_wait_us >= timeout_us, "node {}: unsigned, it never waited a timeout", a.id);
        assert!(a.stats.epochs_not_waited >= 1, "node {}: signed, it still waited", a.id);
        assert!(a.stats.longest_wait_us < timeout_us / 2, "node {}: signed, it waited {} us", a.id, a.stats.longest_wait_us);
        assert!(
            (a.final_err_m - b.final_err_m).abs() < 0.01,
            "node {}: {:.3} m signed, {:.3} m unsigned",
            a.id,
            a.final_err_m,
            b.final_err_m
        );
    }
    // Unsigned, the restarted node waits at its first epoch for teammates still waiting on the
    // epoch before; signed, it does not. In both it is left out of its first epoch and takes the
    // team's store, and nothing is healed: no epoch runs on its restored store. (The harness sees
    // that store beside the team's after the epochs it did not take part in: signed, its "no
    // record" answer lets the teammates run epoch 114 before its first record, so two epochs;
    // unsigned one. Before that answer existed the signed count was 0: the teammates ran 114
    // and 115 in one step, and the harness samples each node's digest when its last epoch
    // changes.)
    let (s3, u3) = (&s.nodes[2].stats, &u.nodes[2].stats);
    eprintln!(
        "node 3: longest wait signed {:.3} s, unsigned {:.3} s; left out {} / {}, stores adopted {} / {}; epochs after which the stores differed: signed {}, unsigned {}",
        s3.longest_wait_us as f64 / 1e6,
        u3.longest_wait_us as f64 / 1e6,
        s3.epochs_excluded,
        u3.epochs_excluded,
        s3.stores_adopted,
        u3.stores_adopted,
        s.divergent_epochs,
        u.divergent_epochs
    );
    assert!(u3.longest_wait_us >= timeout_us / 2, "unsigned: node 3 never waited for its teammates");
    assert!(s3.longest_wait_us < timeout_us / 2, "signed: node 3 waited {} us", s3.longest_wait_us);
    for (name, run) in [("signed", &s), ("unsigned", &u)] {
        let node3 = &run.nodes[2].stats;
        assert!(node3.epochs_excluded >= 1 && node3.stores_adopted >= 1, "{name}: node 3 did not take the team's store");
        let heals: u64 = run.nodes.iter().map(|n| n.stats.heals).sum();
        assert_eq!(heals, 0, "{name}: an epoch ran on diverged stores");
    }
}

/// A left-out node of a team whose store is larger than one fragment series (255 fragments of
/// 204 bytes, 52,020 B) still rejoins exactly: ten 16-state vehicles side by side, 100 m apart,
/// radios reaching 310 m; node 5 out of radio range from 20 s to 30 s. Its teammates' store (45
/// blocks of 16 x 16, 92 KB) comes back to it in two parts, it is adopted, and nobody heals
/// with the covariance-intersection bound. (Before stores went as parts, a store over one series
/// was not kept for teammates: node 5 was left out of every epoch to the end of the run, 16 of
/// them, and applied 19 of 60.) With 30% of the datagrams lost, a part needs several answers
/// to arrive whole: the node keeps what came and takes the store all the same.
#[test]
fn a_left_out_node_of_a_ten_member_team_takes_a_store_of_two_parts_and_nobody_heals() {
    use cooploc::experiment::faults::{Faults, Outage};
    use cooploc::protocol::fragment::MAX_RECORD_LEN;
    let paper = Scenario::from_toml_str(PAPER_TOML).unwrap();
    let world = World::new(&paper.side_by_side(10, 100.0, 310.0, 60.0)).unwrap();
    let store_bytes = 45 * (6 + 16 * 16 * 8);
    assert!(store_bytes > MAX_RECORD_LEN, "the store must need more than one series for this test to mean anything");
    let leave = vec![Outage { node: 4, from_s: 20.0, until_s: 30.0 }];
    for (loss, run) in [(0.0, 0), (0.3, 1), (0.3, 2)] {
        let faults = Faults { leave: leave.clone(), coop_loss: loss, links_until_s: 60.0, ..Faults::default() };
        eprintln!("{:.0}% datagram loss, run {run}:", loss * 100.0);
        let out = run_case(&world, &faults, Method::Decentralized, "1hz", 1, run, Encoding::F64).unwrap();
        a_left_out_node_takes_the_store(&out);
        assert_eq!(out.last_divergent_epoch.map(|e| e <= 32), Some(true), "the stores agree again after the rejoin: {out:?}");
    }
}

/// A `NodeStats` count summed over a run's nodes.
fn team_sum(out: &cooploc::experiment::faults::RunOutcome, f: fn(&cooploc::node::core::NodeStats) -> u64) -> u64 {
    out.nodes.iter().map(|n| f(&n.stats)).sum()
}

fn a_left_out_node_takes_the_store(out: &cooploc::experiment::faults::RunOutcome) {
    let sum = |f| team_sum(out, f);
    for n in &out.nodes {
        eprintln!(
            "node {}: applied {} excluded {} adopted {} sent {} refused {} heals {}; final {:.2} m (dead reckoning {:.2})",
            n.id,
            n.stats.epochs_applied,
            n.stats.epochs_excluded,
            n.stats.stores_adopted,
            n.stats.stores_sent,
            n.stats.stores_refused,
            n.stats.heals,
            n.final_err_m,
            n.dr_final_err_m
        );
    }
    let left = &out.nodes[4].stats;
    assert!(left.epochs_excluded >= 1 && left.stores_adopted >= 1, "node 5 must be left out and take a store: {left:?}");
    assert_eq!(sum(|s| s.heals), 0, "nobody heals with the bound");
    assert!(sum(|s| s.stores_sent) >= 1);
    // Only the two participants with the lowest ids (1 and 2) answer.
    assert!(out.nodes.iter().filter(|n| n.id > 2).all(|n| n.stats.stores_sent == 0), "only nodes 1 and 2 answer");
}

/// Sixteen vehicles side by side (`cooploc faults --side-by-side 16`), four of them out of radio
/// range in turn (overlapping), with 10% datagram loss: every returning member is left out once
/// or more, takes the team's store (120 blocks of 16 x 16, 247 KB: five parts), nobody heals,
/// and the team ends where the loss-free run ends (issue 36 asks for 15%). Before a node that
/// times out followed the set its peers ran the epoch on, and waited again for a member as soon
/// as it speaks, this run ended 2.00 m against 0.65 m: the team healed instead, and node 13
/// was never left out to take the store (docs/robustness.md, "A large team").
#[test]
fn four_members_of_a_sixteen_member_team_leave_and_come_back_without_a_heal() {
    use cooploc::experiment::faults::large_team_cases;
    let paper = Scenario::from_toml_str(PAPER_TOML).unwrap();
    let world = World::new(&paper.side_by_side(16, 100.0, 310.0, 60.0)).unwrap();
    let cases = large_team_cases(16, 60.0);
    let case = |name: &str| cases.iter().find(|c| c.name == name).unwrap().faults.clone();
    let run = |f| run_case(&world, &f, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap();
    let (base, left) = (run(case("fault-free")), run(case("coop loss 10%, four members leave and come back")));
    let rms = |o: &cooploc::experiment::faults::RunOutcome| {
        (o.nodes.iter().map(|n| n.final_err_m.powi(2)).sum::<f64>() / o.nodes.len() as f64).sqrt()
    };
    eprintln!("fault-free {:.3} m, 10% loss and four leave {:.3} m", rms(&base), rms(&left));
    for k in [3, 6, 9, 12] {
        let s = &left.nodes[k].stats;
        assert!(s.epochs_excluded >= 1 && s.stores_adopted >= 1, "node {}: {s:?}", k + 1);
    }
    assert_eq!(left.nodes.iter().map(|n| n.stats.heals).sum::<u64>(), 0);
    // Issue 36's bar for a large team's faults: within 15% of the run without them.
    assert!((rms(&left) / rms(&base) - 1.0).abs() < 0.15, "{} against {}", rms(&left), rms(&base));

    // The same with the store paced at 20,000 B/s per answerer (a radio's share; the 247 KB
    // store takes several epochs), five runs: every returning member takes one store and nobody
    // heals. Without two rules run 3 healed twice on 14 nodes of 16 and the five runs ended at
    // 1.15 m RMS against 0.57 loss-free: a member that took the store after its record went
    // (carrying the old one) is left out of that epoch but brings the store forward by it
    // instead of asking afresh for a new one (this test fails without it); and the epochs the
    // team passes over are those the records it runs on ask for, not a left-out member's,
    // which some nodes held and others not (they split the team at epoch 48; its own test is
    // the core's `a_left_out_members_request_to_pass_epochs_over_does_not_count`).
    let paced =
        cooploc::experiment::faults::Faults { store_bps: 20_000, ..case("coop loss 10%, four members leave and come back") };
    let runs: Vec<_> = (0..5u32)
        .into_par_iter()
        .map(|r| {
            let run = |f| run_case(&world, f, Method::Decentralized, "1hz", 1, r, Encoding::F64).unwrap();
            (run(&case("fault-free")), run(&paced))
        })
        .collect();
    for (r, (base, out)) in runs.iter().enumerate() {
        let sum = |f| team_sum(out, f);
        let (excluded, adopted, sent) = (sum(|s| s.epochs_excluded), sum(|s| s.stores_adopted), sum(|s| s.store_fragments_sent));
        eprintln!(
            "paced, run {r}: {:.3} m, fault-free {:.3} m; {excluded} epochs left out, {adopted} stores taken, {sent} fragments sent",
            rms(out),
            rms(base)
        );
        // One store each: a member that takes it just after its record went does not ask for
        // another (without the rule up to 6 stores, 91 epochs left out and 10,343 fragments).
        for k in [3, 6, 9, 12] {
            let s = &out.nodes[k].stats;
            assert_eq!(s.stores_adopted, 1, "paced, run {r}, node {}: {s:?}", k + 1);
        }
        assert_eq!(out.nodes.iter().map(|n| n.stats.heals).sum::<u64>(), 0, "paced, run {r}");
        assert!((rms(out) / rms(base) - 1.0).abs() < 0.15, "paced, run {r}: {} against {}", rms(out), rms(base));
    }
}

/// A team whose epochs take longer to resolve than they come (50% datagram loss and 0-1 s of
/// latency at 1 Hz, real time: each epoch waits for records that cross the link twice or more)
/// falls further behind every epoch. It used to run nearly every epoch partial and heal it with
/// the bound, until the bound's inflation made it worse than dead reckoning (303.80 m final RMS
/// over 20 runs, 34 node-runs worse than dead reckoning, team NEES infinite (292 per node) against a band of
/// 4.58-7.61, before the records could ask the team to pass epochs over). Now a member an
/// epoch timeout behind asks, every node that runs the epoch on the same records passes over
/// the same ones after it, and the team stays consistent and better than dead reckoning.
#[test]
fn a_team_that_falls_behind_passes_over_the_same_epochs_and_stays_consistent() {
    const RUNS: u32 = 4;
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let case = standard_cases().into_iter().find(|c| c.name == "coop loss 50%, packed datagrams").unwrap();
    let faults = cooploc::experiment::faults::Faults { delay_ms: (0, 1000), ..case.faults };
    let runs: Vec<_> = (0..RUNS)
        .into_par_iter()
        .map(|r| run_case(&world, &faults, Method::Decentralized, "1hz", 1, r, Encoding::F64).unwrap())
        .collect();
    let s = summarize("50% loss, 0-1 s latency", &runs);
    eprintln!("{s:?}");
    for (r, run) in runs.iter().enumerate() {
        for n in &run.nodes {
            assert!(n.stats.skips_asked > 0 && n.stats.epochs_strided > 0, "run {r}, node {}: nothing passed over", n.id);
        }
    }
    assert_eq!(s.worse_than_dr, 0, "nodes worse than dead reckoning: {s:?}");
    assert!(s.final_rms_m < s.dr_rms_m, "{s:?}");
    assert!(s.team_nees <= s.team_nees_band.1, "team NEES {:.2} above its band {:?}", s.team_nees, s.team_nees_band);
    assert_eq!(s.failed, 0);
}

/// What a team clock that is off costs (issue 31, item 2; `cooploc faults --clock-sweep` prints
/// the whole sweep, docs/node.md "Time without GNSS"). A node whose clock is d ahead takes its
/// state at each epoch d before the instant its teammates ranged at, v x d along its track (1 cm
/// per ms at the paper's 10 m/s). Measured over 10 runs: at 5 ms the team is where it is with one
/// clock (-0.5% whole-run RMS) and consistent; at 45 ms it still applies every epoch and loses
/// 1-5% of its accuracy, but 0.45 m of timing error against 0.1 m of ranging noise makes it
/// overconfident (team NEES 47-56 against a band of 4.05-8.33: no range model here knows the
/// clocks are apart); past half the profiles' 100 ms epoch grid the ranging node names every
/// epoch by the next grid instant, its teammates refuse its records as implausible, and the
/// epochs run partial: the error doubles.
#[test]
fn a_clock_off_by_less_than_half_the_epoch_grid_costs_little_and_past_it_splits_the_epochs() {
    const RUNS: u32 = 10;
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let names = [
        "fault-free",
        "node 1's clock 5 ms ahead",
        "node 3's clock 5 ms ahead",
        "node 1's clock 45 ms ahead",
        "node 3's clock 45 ms ahead",
        "node 1's clock 55 ms ahead",
    ];
    let cases: Vec<_> =
        cooploc::experiment::faults::clock_offset_cases().into_iter().filter(|c| names.contains(&c.name)).collect();
    assert_eq!(cases.len(), names.len());
    let outcomes = run_cases(&world, &cases, RUNS);
    let get = |name: &str| {
        let c = cases.iter().position(|c| c.name == name).unwrap();
        let runs = &outcomes[c];
        let s = summarize(name, runs);
        eprintln!("{name}: whole-run RMS {:.3} m, team NEES {:.2} {:?}, {s:?}", s.run_rms_m, s.team_nees, s.team_nees_band);
        s
    };
    let base = get("fault-free");
    let all_epochs = u64::from(RUNS) * 3 * 380;
    for name in &names[1..5] {
        let s = get(name);
        assert_eq!((s.applied, s.partial, s.implausible), (all_epochs, 0, 0), "{name}: every epoch named alike and applied");
        assert!(s.run_rms_m < 1.10 * base.run_rms_m, "{name}: {:.3} m against {:.3} m", s.run_rms_m, base.run_rms_m);
        if name.contains(" 5 ms") {
            assert!(
                (s.run_rms_m / base.run_rms_m - 1.0).abs() < 0.01,
                "{name}: {:.3} against {:.3}",
                s.run_rms_m,
                base.run_rms_m
            );
            assert!(s.team_nees <= s.team_nees_band.1, "{name}: team NEES {:.2} above {:?}", s.team_nees, s.team_nees_band);
        } else {
            assert!(
                s.team_nees > s.team_nees_band.1,
                "{name}: team NEES {:.2} inside its band: does a range model now know the clocks are apart? (docs/node.md says not)",
                s.team_nees
            );
        }
    }
    let split = get("node 1's clock 55 ms ahead");
    assert!(split.implausible > 0 && split.partial > 0, "{split:?}");
    assert!(split.run_rms_m > 1.5 * base.run_rms_m, "{:.3} against {:.3}", split.run_rms_m, base.run_rms_m);
}

/// A store larger than the link carries in an epoch still comes back whole (issue 36, item 3).
/// The ten-member team of the test above, its 92 KB store paced at 20,000 B/s per answerer
/// (`cooploc node --store-bps 20000`: 7 fragments an answer, once per retry interval), takes
/// several epochs to cross. Node 5, back from out of range, is left out of each of them, keeps
/// the records they ran on, and once the store is whole brings it forward by them and adopts
/// it: nobody heals, and the stores agree again before the run ends. With 10% and 30% of the
/// datagrams lost, the fragments lost are sent again (node 5 says what it holds), and the store
/// costs the answerers little more than the loss itself. (With the want dropped as soon as
/// another epoch resolved, as before, node 5 asked afresh at every epoch and never held a whole
/// store: left out of 16 epochs, no store taken, 0.74 m at the end against its dead reckoning's
/// 0.59 m.)
#[test]
fn a_store_paced_over_several_epochs_is_brought_forward_and_adopted() {
    use cooploc::experiment::faults::{Faults, Outage};
    let paper = Scenario::from_toml_str(PAPER_TOML).unwrap();
    let world = World::new(&paper.side_by_side(10, 100.0, 310.0, 60.0)).unwrap();
    let leave = vec![Outage { node: 4, from_s: 20.0, until_s: 30.0 }];
    let mut loss_free_cost = 0;
    for loss in [0.0, 0.1, 0.3] {
        let faults =
            Faults { leave: leave.clone(), coop_loss: loss, links_until_s: 60.0, store_bps: 20_000, ..Faults::default() };
        eprintln!("{:.0}% datagram loss:", loss * 100.0);
        let out = run_case(&world, &faults, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap();
        a_left_out_node_takes_the_store(&out);
        let left = &out.nodes[4].stats;
        eprintln!("node 5: {} epochs brought forward", left.store_epochs_replayed);
        assert!(left.store_epochs_replayed >= 2, "the store came over several epochs: {left:?}");
        for n in &out.nodes[..2] {
            let per_answer = 20_000 * 100_000 / 1_000_000 / 252;
            assert!(n.stats.store_fragments_sent <= per_answer * n.stats.stores_sent, "node {} paced: {:?}", n.id, n.stats);
        }
        // What the store cost the answerers: node 5 says what it holds before each repeated
        // request (COOPLOC_STORE_HELD), so a fragment lost is sent again, not the whole store
        // round again: each fragment takes 1 / (1 - loss) sends on average; half as many again
        // is the margin for the requests and reports lost too (without the reports, 3.6 and 6.3
        // times the loss-free cost at 10% and 30%).
        let cost: u64 = out.nodes[..2].iter().map(|n| n.stats.store_fragments_sent).sum();
        eprintln!("the answerers sent {cost} fragments");
        if loss == 0.0 {
            loss_free_cost = cost;
        }
        let bound = 1.5 * loss_free_cost as f64 / (1.0 - loss);
        assert!(cost as f64 <= bound, "{cost} fragments sent at {loss} loss, {loss_free_cost} loss-free");
        assert!(
            out.last_divergent_epoch.is_some_and(|e| e < 55),
            "the stores agree again before the end: {:?}",
            out.last_divergent_epoch
        );
        assert!(out.nodes[4].final_err_m < out.nodes[4].dr_final_err_m);
    }
    // On an unsigned team what node 5 holds is neither sent nor believed (a forger speaking for
    // it could make the answerers leave out what it lacks): the store still comes, round after
    // round of it.
    let faults = Faults { leave, coop_loss: 0.1, links_until_s: 60.0, store_bps: 20_000, unsigned: true, ..Faults::default() };
    let out = run_case(&world, &faults, Method::Decentralized, "1hz", 1, 0, Encoding::F64).unwrap();
    a_left_out_node_takes_the_store(&out);
    let cost: u64 = out.nodes[..2].iter().map(|n| n.stats.store_fragments_sent).sum();
    eprintln!("unsigned, 10% loss: the answerers sent {cost} fragments");
    assert!(cost as f64 > 1.5 * loss_free_cost as f64 / 0.9, "{cost}: what node 5 says it holds was believed unsigned");
}

/// Radios that reach 400 m (the paper's vehicles are 115-750 m apart): no range involves
/// vehicle 3 in about a quarter of the epochs. On the signed team it then says "no range" in
/// place of its record and takes its share of the others' update as a bystander. Under 10%
/// datagram loss, and with node 3 away for 60 s at 10% loss and 0-300 ms of delay (it comes
/// back with a word that carries its old store: left out, it takes the team's), 20 runs each:
/// no heal, no refused update, every divergence detected and mended, the team's NEES in its
/// band, and the final RMS within 1% of the loss-free run's.
#[test]
fn members_out_of_every_range_say_no_range_and_the_team_stays_exact_under_loss() {
    let mut scenario = Scenario::from_toml_str(PAPER_TOML).unwrap();
    scenario.ranging.max_range_m = Some(400.0);
    let world = World::new(&scenario).unwrap();
    let names = ["fault-free", "coop loss 10%", "node 3 leaves for 60 s, 10% loss, delay 0-300 ms"];
    let cases: Vec<_> = standard_cases().into_iter().filter(|c| names.contains(&c.name)).collect();
    assert_eq!(cases.len(), names.len());
    let outcomes = run_cases(&world, &cases, RUNS);
    let mut base = None;
    for (c, case) in cases.iter().enumerate() {
        let runs = &outcomes[c];
        let said: u64 = runs.iter().map(|o| team_sum(o, |s| s.no_range_said)).sum();
        let heard: u64 = runs.iter().map(|o| team_sum(o, |s| s.no_range_heard)).sum();
        let bystood: u64 = runs.iter().map(|o| team_sum(o, |s| s.epochs_unranged)).sum();
        let s = summarize(case.name, runs);
        eprintln!("{}: {said} words said, {heard} heard, {bystood} epochs taken as a bystander; {s:?}", case.name);
        // The words are in use: node 3 says some 90 per run, some 30 in the run it is away for
        // 60 s of (it then comes back with its old store, and is left out until it has the team's).
        let least = 20 * u64::from(RUNS);
        assert!(said > least && heard > least && bystood > least, "{}", case.name);
        assert_eq!((s.heals, s.failed, s.runs_not_recovered), (0, 0, 0), "{s:?}");
        assert_eq!(s.runs_detected, s.runs_diverged, "{s:?}");
        assert!((s.team_nees_band.0..=s.team_nees_band.1).contains(&s.team_nees), "{s:?}");
        let base = *base.get_or_insert(s.final_rms_m);
        assert!(s.final_rms_m <= 1.01 * base, "{}: {:.2} m against {base:.2} m loss-free", case.name, s.final_rms_m);
    }
}
