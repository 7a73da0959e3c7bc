//! Three node cores exchange real MAVLink frames in process over the paper scenario and must
//! reproduce the offline experiment's run of the same method on the same inputs, bit for bit:
//! the decentralized protocol (broadcast at the epoch, joint update after the wait, write-back at
//! the epoch's time and replay to the present) loses nothing.

use std::collections::VecDeque;

use cooploc::estimation::{Method, RangeSample};
use cooploc::experiment::{initial_state, ins_settings, run_filter};
use cooploc::node::core::{NodeConfig, NodeCore, NodeInput, NodeOutput};
use cooploc::protocol::record::Encoding;
use cooploc::protocol::wire::{self, from_frame, to_frame};
use cooploc::sitl::world::SimEvent;
use cooploc::sitl::{PAPER_TOML, Scenario, World};
use cooploc::time::TimeUs;
use mavlink_core::MavHeader;

fn run_network(
    world: &World,
    method: Method,
    schedule: &str,
    seed: u64,
    run: u32,
) -> (Vec<NodeCore>, Vec<(TimeUs, Vec<RangeSample>)>) {
    let (ins, initial_sigma) = ins_settings(world);
    let mut nodes: Vec<NodeCore> = world
        .platform_ids()
        .into_iter()
        .map(|id| {
            let (t0, state) = initial_state(world, seed, run, id).unwrap();
            let cfg = NodeConfig {
                id,
                method,
                ins,
                initial_sigma,
                encoding: Encoding::F64,
                epoch_wait_us: 500_000,
                history_us: 3_000_000,
            };
            NodeCore::new(cfg, t0, state).unwrap()
        })
        .collect();
    let index = |id| world.platform_ids().iter().position(|&p| p == id).unwrap();
    let mut sent_ranges = Vec::new();
    let mut epoch = 0u32;
    let mut queue: VecDeque<(usize, NodeInput)> = VecDeque::new();
    for event in world.events(schedule, seed, run).unwrap() {
        match event {
            SimEvent::Imu(id, s) => queue.push_back((index(id), NodeInput::Imu(s))),
            SimEvent::Odometer(id, s) => queue.push_back((index(id), NodeInput::Odometer(s))),
            SimEvent::Ranges(t, samples) => {
                epoch += 1;
                sent_ranges.push((t, samples.iter().map(wire::range_as_sent).collect()));
                for r in samples {
                    queue.push_back((index(r.from), NodeInput::OwnRange { epoch, range: r }));
                }
            }
        }
        // Deliver everything this input causes, through real frames, to every other node.
        while let Some((i, input)) = queue.pop_front() {
            for output in nodes[i].handle(input) {
                if let NodeOutput::ToPeers(msg) = output {
                    let header = MavHeader { system_id: u32::from(nodes[i].id()), component_id: 191, sequence: 0 };
                    let (_, decoded) = from_frame(&to_frame(header, &msg)).unwrap();
                    for j in (0..nodes.len()).filter(|&j| j != i) {
                        queue.push_back((j, NodeInput::Peer(Box::new(decoded.clone()))));
                    }
                }
            }
        }
    }
    // The run ends at the last epoch's instant: close it everywhere, deliver, then run it.
    for i in 0..nodes.len() {
        for output in nodes[i].end_of_input() {
            if let NodeOutput::ToPeers(msg) = output {
                for j in (0..nodes.len()).filter(|&j| j != i) {
                    let _ = nodes[j].handle(NodeInput::Peer(Box::new(msg.clone())));
                }
            }
        }
    }
    for node in &mut nodes {
        node.run_pending();
    }
    (nodes, sent_ranges)
}

#[test]
fn three_nodes_reproduce_the_experiment_bit_for_bit() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    for method in [Method::Decentralized, Method::NoPropagation] {
        let (nodes, sent_ranges) = run_network(&world, method, "1hz", 1, 0);
        let inputs = world.run_inputs(1, 0);
        let reference = run_filter(&world, &inputs, &sent_ranges, method).unwrap();
        for (node, (p, outcome)) in nodes.iter().zip(inputs.platforms.iter().zip(&reference.platforms)) {
            assert_eq!(node.stats.epochs_applied, 380, "{method} node {}: {:?}", node.id(), node.stats);
            assert_eq!(node.stats.rejected_inputs + node.stats.fragments_rejected + node.stats.records_incomplete, 0);
            let truth = p.truth.last().unwrap();
            let err = truth.pos_ned_m - node.filter().position_ned_m();
            let reference_err = outcome.final_error().pos_err_ne_m;
            assert_eq!([err[0], err[1]], reference_err, "{method} node {}: final error differs from the experiment's", node.id());
        }
    }
}
