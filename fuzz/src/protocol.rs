//! Targets that drive the protocol modules themselves — the world's
//! [`Server`](geese_world::server::Server) and an agent process's
//! [`Host`](geese_agent::host::Host) — with one hostile message in the middle of a step,
//! then run the step (and the run) to its end. The other targets feed decoders as the
//! modules call them; these feed the modules, so that a panic in what is done with a
//! decoded value (a range, a cell, a step number) is found too.
//!
//! An input is a selector byte (which handler gets the message; its top bit picks a
//! variant) and the message's bytes.
use crate::corpus;
use geese_agent::host::{Host, Input, Next as HostNext};
use geese_orchestrator::distributed::launch::{net_spec, NetOptions};
use geese_orchestrator::RunConfig;
use geese_proto::decode;
use geese_proto::keys::{self, AgentRange};
use geese_proto::net::{NetRunSpec, ReportMsg, RunInfo};
use geese_world::hub::Released;
use geese_world::server::{Next as ServerNext, Server};
use geese_world::Layout;
use std::hint::black_box;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

const RUN: &str = "fuzz";

fn ranges() -> (AgentRange, AgentRange) {
    (AgentRange { first: 0, last: 1 }, AgentRange { first: 2, last: 3 })
}

/// A run of 4 agents (all at the hub, so genes cross processes), 3 steps.
fn spec() -> &'static NetRunSpec {
    static S: OnceLock<NetRunSpec> = OnceLock::new();
    S.get_or_init(|| {
        let mut c = RunConfig { steps: 3, seed: 1, ..Default::default() };
        c.world.agents = 4;
        c.world.layout = Layout::Paper;
        let spec = c.validate().expect("the fuzz run configuration is valid");
        let mut ns = net_spec(&spec, &NetOptions::default(), RUN).expect("net spec");
        ns.expect_orchestrator = false;
        ns
    })
}

/// A server with both processes present and step 1 begun; what it published.
fn server_in_step_1(now: Instant) -> Option<(Server, Released)> {
    let mut s = Server::new(spec().clone(), now).ok()?;
    let (a, b) = ranges();
    s.on_presence(true, &keys::agents_presence(RUN, a));
    s.on_presence(true, &keys::agents_presence(RUN, b));
    match s.next(now) {
        ServerNext::Publish(out) => Some((s, out)),
        _ => None,
    }
}

/// The world's messages of step 1 for process 0–1 (tick, then its percepts), and the
/// run information a joining process gets.
fn host_material() -> &'static (RunInfo, Vec<Vec<u8>>) {
    static M: OnceLock<(RunInfo, Vec<Vec<u8>>)> = OnceLock::new();
    M.get_or_init(|| {
        let (s, out) = server_in_step_1(Instant::now()).expect("step 1 begins");
        let (a, _) = ranges();
        let wanted = [keys::tick(RUN), keys::host_percepts(RUN, a)];
        let msgs = wanted.iter().filter_map(|k| out.iter().find(|(key, _)| key == k).map(|(_, b)| b.clone())).collect();
        (s.run_info(), msgs)
    })
}

/// One hostile message to the world server in the middle of step 1, then the run to its
/// end (every deadline passes at once). True if the step's report counted nothing
/// hostile.
pub fn world_server(b: &[u8]) -> bool {
    let Some((&sel, payload)) = b.split_first() else { return false };
    let now = Instant::now();
    let Some((mut s, _)) = server_in_step_1(now) else { return false };
    let (a, _) = ranges();
    let mut out = match sel % 5 {
        0 => {
            s.on_action(&keys::agents_action(RUN, a), payload);
            Vec::new()
        }
        1 => s.on_gene_bundle(&keys::agents_genes(RUN, a), payload),
        2 => s.on_gene_batch(&keys::cell_genes_from(RUN, 0, 0, a), payload),
        3 => {
            s.on_control(payload);
            Vec::new()
        }
        _ => s.on_presence(sel & 0x80 != 0, &String::from_utf8_lossy(payload)),
    };
    s.flush_genes(&mut out);
    black_box(out.len());
    let mut clean = false;
    let mut t = now;
    for _ in 0..12 {
        t += Duration::from_secs(3600);
        match s.next(t) {
            ServerNext::Publish(msgs) => {
                for (_, bytes) in msgs.iter().filter(|(k, _)| *k == keys::report(RUN)) {
                    if let Ok(ReportMsg::Step(r)) = decode::<ReportMsg>(bytes) {
                        if r.report.step == 1 {
                            clean = r.net.hostile == 0;
                        }
                    }
                }
            }
            ServerNext::Finished { .. } => break,
            ServerNext::Wait(_) => {}
        }
    }
    clean
}

/// One hostile message to the host of agents 0–1 (hosting or reading cells, by the
/// selector's top bit) between the tick and the percepts of step 1, then the step to
/// its end. True if the host acted.
pub fn agent_host(b: &[u8]) -> bool {
    let Some((&sel, payload)) = b.split_first() else { return false };
    let (info, msgs) = host_material();
    let (a, _) = ranges();
    let wide = sel & 0x80 == 0;
    let Ok(mut h) = Host::new(a, info.clone(), wide) else { return false };
    black_box(h.start());
    let now = Instant::now();
    if let Some(tick) = msgs.first() {
        h.absorb(Input::Tick(tick), now);
    }
    let key;
    let input = match sel % 7 {
        0 => Input::Tick(payload),
        1 => Input::Percept { cell: u32::from(sel), bytes: payload },
        2 => Input::CellGenes { cell: u32::from(sel), bytes: payload },
        3 => Input::HostPercepts(payload),
        4 => Input::HostGenes(payload),
        5 => {
            key = String::from_utf8_lossy(payload).into_owned();
            Input::Presence { alive: sel & 0x40 != 0, key: &key }
        }
        _ => Input::Hostile,
    };
    h.absorb(input, now);
    if let Some(p) = msgs.get(1) {
        h.absorb(Input::HostPercepts(p), now);
    }
    let mut acted = false;
    let mut t = now;
    for _ in 0..6 {
        match h.next(t) {
            HostNext::Act(o) => acted |= !o.is_empty(),
            HostNext::Stopped => break,
            HostNext::Wait(_) => t += Duration::from_secs(3600),
        }
    }
    acted
}

/// Append each of `msgs`, after the selector byte `sel`, to `v`.
fn prefixed(sel: u8, msgs: Vec<Vec<u8>>, v: &mut Vec<Vec<u8>>) {
    v.extend(msgs.into_iter().map(|m| [vec![sel], m].concat()));
}

/// Seeds: a selector byte for each handler, then a valid message for it.
pub fn world_server_seeds() -> Vec<Vec<u8>> {
    let (a, _) = ranges();
    let mut v = Vec::new();
    prefixed(0, corpus::wire::intents(), &mut v);
    prefixed(1, corpus::wire::gene_bundle(), &mut v);
    prefixed(2, corpus::wire::gene_batch(), &mut v);
    prefixed(3, corpus::wire::control(), &mut v);
    let presence = vec![
        keys::agents_presence(RUN, a).into_bytes(),
        keys::cells_presence(RUN, a).into_bytes(),
        keys::orchestrator_presence(RUN).into_bytes(),
    ];
    prefixed(4, presence.clone(), &mut v);
    prefixed(0x84, presence, &mut v);
    v
}

/// Seeds: a selector byte for each input kind, then a valid message of that kind.
pub fn agent_host_seeds() -> Vec<Vec<u8>> {
    let (_, b) = ranges();
    let mut v = Vec::new();
    prefixed(0, corpus::wire::tick(), &mut v);
    prefixed(0x80 | 1, corpus::wire::percept(), &mut v);
    prefixed(0x80 | 2, corpus::wire::gene_batch(), &mut v);
    prefixed(3, corpus::wire::host_percepts(), &mut v);
    prefixed(4, corpus::wire::host_genes(), &mut v);
    let presence = vec![keys::agents_presence(RUN, b).into_bytes(), keys::world_presence(RUN).into_bytes()];
    prefixed(5, presence.clone(), &mut v);
    prefixed(0x40 | 5, presence, &mut v);
    v
}
