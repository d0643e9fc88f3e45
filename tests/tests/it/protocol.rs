//! The distributed protocol without a network: the world's sans-IO [`Server`] and agent
//! processes' [`Host`]s wired by an in-memory router (what the Zenoh shells do, minus
//! Zenoh), compared step for step with the in-process driver; and what a host does with
//! late, missing, duplicate, foreign and future messages, and with cell-mates that leave.
//!
//! Time is a value here: a stall shows as a wait that nothing ends, and the router
//! fails the test rather than sleeping.
use super::distributed::{config, gs2, in_process, perturbed};
use geese_agent::host::{Host, Input, Next as HostNext, Out};
use geese_orchestrator::distributed::launch::{net_spec, NetOptions};
use geese_orchestrator::run::config::RunConfig;
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{Deadlines, IntentBatch, LossRates, NetReport, ReportMsg};
use geese_proto::{decode, encode, StepReport};
use geese_world::hub::Released;
use geese_world::server::{Next as ServerNext, Server};
use geese_world::Layout;
use std::collections::BTreeSet;
use std::time::{Duration, Instant};

const RUN: &str = "mem";

fn server(cfg: &RunConfig, loss: LossRates, now: Instant) -> Server {
    let spec = cfg.clone().validate().expect("valid config");
    let opts = NetOptions {
        loss,
        deadlines: Deadlines { intent_ms: 500, gene_ms: 300, percept_ms: 100, join_ms: 1_000 },
        ..NetOptions::default()
    };
    let mut ns = net_spec(&spec, &opts, RUN).expect("net spec");
    ns.expect_orchestrator = false;
    Server::new(ns, now).expect("server")
}

/// One agent process in memory: its host and the cells it is subscribed to.
struct Proc {
    host: Host,
    range: AgentRange,
    cells: BTreeSet<u32>,
    gone: bool,
}

/// The world, its processes and what the router delivered.
struct Net {
    server: Server,
    procs: Vec<Proc>,
    reports: Vec<NetReport>,
    now: Instant,
    finished: Option<bool>,
    /// Kill the processes at these indices right after step `at` is reported.
    kills: Vec<(u64, usize)>,
}

impl Net {
    /// Processes of `per` agents each; `narrow[i]`: process i reads cells one by one.
    fn new(cfg: &RunConfig, per: u32, narrow: &[bool], loss: LossRates) -> Net {
        let now = Instant::now();
        let mut server = server(cfg, loss, now);
        let info = server.run_info();
        let mut procs = Vec::new();
        let mut first = 0;
        let mut i = 0;
        while first < cfg.world.agents {
            let count = per.min(cfg.world.agents - first);
            let range = AgentRange::new(first, count).unwrap();
            let wide = !narrow.get(i).copied().unwrap_or(false);
            let mut host = Host::new(range, info.clone(), wide).expect("host");
            let mut cells = BTreeSet::new();
            for o in host.start() {
                if let Out::Subscribe(c) = o {
                    cells.insert(c);
                }
            }
            procs.push(Proc { host, range, cells, gone: false });
            first += count;
            i += 1;
        }
        // Presence: the world sees every process (and the cell readers' tokens); the
        // processes read only the world's token, as the agent shell subscribes to.
        for p in &procs {
            if !p.host.wide() {
                server.on_presence(true, &keys::cells_presence(RUN, p.range));
            }
            server.on_presence(true, &keys::agents_presence(RUN, p.range));
        }
        Net { server, procs, reports: Vec::new(), now, finished: None, kills: Vec::new() }
    }

    /// Deliver what the world published.
    fn route(&mut self, msgs: Released) {
        let geom = self.server.world().geometry();
        for (key, bytes) in msgs {
            let now = self.now;
            if key == keys::report(RUN) {
                match decode::<ReportMsg>(&bytes).expect("report") {
                    ReportMsg::Step(r) => {
                        let step = r.report.step;
                        self.reports.push(r);
                        let due: Vec<usize> = self.kills.iter().filter(|k| k.0 == step).map(|k| k.1).collect();
                        for i in due {
                            self.leave(i);
                        }
                    }
                    ReportMsg::Done { completed, .. } => self.finished = Some(completed),
                }
                continue;
            }
            for p in self.procs.iter_mut().filter(|p| !p.gone) {
                let input = if key == keys::tick(RUN) {
                    Input::Tick(&bytes)
                } else if key == keys::ctl(RUN, "stop") {
                    Input::Stop
                } else {
                    match keys::parse(RUN, &key) {
                        Parsed::HostPercepts { to } if to == p.range => Input::HostPercepts(&bytes),
                        Parsed::HostGenes { to } if to == p.range => Input::HostGenes(&bytes),
                        Parsed::Percept { cx, cy } => {
                            let cell = (cy * geom.cols() + cx) as u32;
                            if !p.cells.contains(&cell) {
                                continue;
                            }
                            Input::Percept { cell, bytes: &bytes }
                        }
                        Parsed::Genes { cx, cy, from: None } => {
                            let cell = (cy * geom.cols() + cx) as u32;
                            if !p.cells.contains(&cell) {
                                continue;
                            }
                            Input::CellGenes { cell, bytes: &bytes }
                        }
                        _ => continue,
                    }
                };
                p.host.absorb(input, now);
            }
        }
    }

    /// Process `i` is killed: its presence goes for the world, whose release of the
    /// cells it shared ends the others' wait. The world's publisher sends the hosting
    /// processes what the hub holds for them each time it wakes, as the shell's does.
    fn leave(&mut self, i: usize) {
        let r = self.procs[i].range;
        self.procs[i].gone = true;
        let mut out = self.server.on_presence(false, &keys::agents_presence(RUN, r));
        self.server.flush_genes(&mut out);
        self.route(out);
    }

    /// Let every process act until it waits; true if any did something.
    fn run_hosts(&mut self) -> bool {
        let mut any = false;
        for i in 0..self.procs.len() {
            while !self.procs[i].gone {
                let next = self.procs[i].host.next(self.now);
                let HostNext::Act(outs) = next else { break };
                any = true;
                let range = self.procs[i].range;
                for o in outs {
                    match o {
                        Out::Genes(b) => {
                            let mut out = self.server.on_gene_bundle(&keys::agents_genes(RUN, range), &b);
                            self.server.flush_genes(&mut out);
                            self.route(out);
                        }
                        Out::Intents(b) => {
                            self.server.on_action(&keys::agents_action(RUN, range), &b);
                        }
                        Out::Subscribe(c) => {
                            self.procs[i].cells.insert(c);
                        }
                        Out::Unsubscribe(c) => {
                            self.procs[i].cells.remove(&c);
                        }
                    }
                }
            }
        }
        any
    }

    /// Run to the end; `patient`: when nothing moves, let the clock reach the
    /// deadline awaited (otherwise that is a stall and fails the test).
    fn run(&mut self, patient: bool) {
        let mut idle_rounds = 0;
        while self.finished.is_none() {
            match self.server.next(self.now) {
                ServerNext::Publish(out) => self.route(out),
                ServerNext::Finished { messages, outcome } => {
                    self.route(messages);
                    outcome.expect("the run ends well");
                    break;
                }
                ServerNext::Wait(until) => {
                    if self.run_hosts() {
                        idle_rounds = 0;
                        continue;
                    }
                    assert!(patient, "stalled at step {}: nothing left to do but wait", self.server.world().step());
                    idle_rounds += 1;
                    assert!(idle_rounds < 10, "the clock moves but nothing happens");
                    self.now = self.now.max(until);
                    // Hosts' own deadlines are shorter than the world's.
                    self.now += Duration::from_millis(1);
                }
            }
        }
    }
}

fn reports(r: &[NetReport]) -> Vec<StepReport> {
    r.iter().map(|n| n.report.clone()).collect()
}

#[test]
fn hosting_processes_in_memory_equal_the_in_process_run_and_never_wait() {
    let cfg = config(24, 200, 5, Layout::Paper);
    let expected = in_process(&cfg);
    let mut net = Net::new(&cfg, 8, &[], LossRates::default());
    net.run(false);
    assert_eq!(net.finished, Some(true));
    assert_eq!(expected, reports(&net.reports));
    assert!(net.reports.iter().skip(1).all(|r| r.net.genes_ahead == 3), "genes went ahead from step 2 on");
    assert!(net
        .reports
        .iter()
        .all(|r| r.net.hostile + r.net.intents_late + r.net.genes_late + r.net.deadline_hits == 0));
}

#[test]
fn cell_readers_and_hosting_processes_mixed_with_perturbations_equal_in_process() {
    let cfg = perturbed(250);
    let expected = in_process(&cfg);
    let mut net = Net::new(&cfg, 6, &[true, false, true, false], LossRates::default());
    net.run(false);
    assert_eq!(expected, reports(&net.reports));
    assert!(net.reports.iter().all(|r| r.net.genes_ahead == 0), "no genes ahead past a cell reader");
    assert!(net.reports.iter().all(|r| r.net.deadline_hits == 0));
    assert!(net.procs.iter().any(|p| !p.host.wide() && !p.cells.is_empty()));
}

#[test]
fn loss_is_the_same_whichever_way_genes_travel() {
    let mut cfg = config(24, 150, 4, Layout::Paper);
    cfg.world.grid = 5;
    cfg.gene_loss = 0.3;
    let loss = LossRates { intent: 0.1, percept: 0.2 };
    let mut ahead = Net::new(&cfg, 8, &[], loss);
    ahead.run(false);
    let mut during = Net::new(&cfg, 8, &[false, false, true], loss);
    during.run(false);
    let lost = |n: &Net| n.reports.iter().map(|r| r.net.percepts_lost).sum::<u32>();
    assert!(lost(&ahead) > 100);
    assert_eq!(lost(&ahead), lost(&during));
    assert_eq!(reports(&ahead.reports), reports(&during.reports));
}

#[test]
fn at_gs_2_genes_reach_cell_mates_centred_next_door_whichever_way_they_travel() {
    // An agent is registered in a 3×3 block of cells: its gene goes to every cell of the
    // block where a live agent has its centre, through the world when that agent is of
    // another process (REFERENCE §6.2: lateral transfer takes every learning agent
    // registered in the cell). None is lost, and the trajectory is the in-process one.
    let cfg = gs2(30, 150, 6);
    let expected = in_process(&cfg);
    assert!(expected.iter().all(|r| r.genes_lost == 0));
    assert!(expected.iter().map(|r| r.lt_mean).sum::<f64>() > 0.0, "no lateral transfer to compare");
    // Hosting processes (genes ahead from step 2 on), then cell readers and hosting
    // processes mixed (genes during the step, per cell and per process).
    for narrow in [&[][..], &[true, false, true][..]] {
        let mut net = Net::new(&cfg, 10, narrow, LossRates::default());
        net.run(false);
        assert_eq!(net.finished, Some(true));
        assert_eq!(expected, reports(&net.reports), "narrow {narrow:?}");
        let ahead = net.reports.iter().skip(1).all(|r| r.net.genes_ahead == 3);
        assert_eq!(ahead, narrow.is_empty());
        assert!(net.reports.iter().all(|r| r.net.hostile
            + r.net.intents_late
            + r.net.genes_late
            + r.net.deadline_hits
            == 0));
    }
    // Under loss, an agent whose percept is dropped offers no gene in any of its cells.
    let loss = LossRates { intent: 0.1, percept: 0.2 };
    let mut ahead = Net::new(&cfg, 10, &[], loss);
    ahead.run(false);
    let mut during = Net::new(&cfg, 10, &[false, true], loss);
    during.run(false);
    assert!(ahead.reports.iter().map(|r| r.net.percepts_lost).sum::<u32>() > 100);
    assert_eq!(reports(&ahead.reports), reports(&during.reports));
    assert!(during.reports.iter().all(|r| r.net.genes_late + r.net.deadline_hits == 0));
}

#[test]
fn a_process_killed_mid_run_leaves_the_others_stepping_without_a_deadline() {
    let cfg = config(24, 120, 3, Layout::Paper);
    for narrow in [&[][..], &[true, true, true][..]] {
        let mut net = Net::new(&cfg, 8, narrow, LossRates::default());
        net.kills = vec![(30, 2)];
        net.run(false);
        assert_eq!(net.finished, Some(true));
        let after = &net.reports[31..];
        assert!(after.iter().all(|r| r.report.live_agents == 16 && r.net.processes == 2));
        assert!(net.reports.iter().all(|r| r.net.intents_late + r.net.genes_late + r.net.deadline_hits == 0));
    }
}

/// A host of agents 0–1 (cells one by one) and the world's messages of step 1 for it.
fn one_host(narrow: bool) -> (Net, Released) {
    let cfg = config(4, 5, 2, Layout::Paper);
    let mut net = Net::new(&cfg, 2, &[narrow, narrow], LossRates::default());
    let ServerNext::Publish(out) = net.server.next(net.now) else { panic!("step 1 did not start") };
    (net, out)
}

/// The intent batch among `outs`, decoded.
fn intents(outs: &[Out]) -> IntentBatch {
    outs.iter()
        .find_map(|o| match o {
            Out::Intents(b) => Some(decode(b).expect("intents")),
            _ => None,
        })
        .expect("an intent batch")
}

#[test]
fn a_host_whose_percept_never_comes_idles_at_the_percept_deadline_and_counts_it() {
    let (mut net, out) = one_host(true);
    // Deliver the tick only: process 0 knows its agents are live, no percept comes.
    let tick: Released = out.into_iter().filter(|(k, _)| *k == keys::tick(RUN)).collect();
    let (t, bytes) = &tick[0];
    assert_eq!(t, &keys::tick(RUN));
    let now = net.now;
    let host = &mut net.procs[0].host;
    host.absorb(Input::Tick(bytes), now);
    assert!(matches!(host.next(now), HostNext::Act(_) | HostNext::Wait(None)));
    assert!(matches!(host.next(now), HostNext::Wait(None)), "no deadline before any percept of the step");
    // A percept shows one own agent and nobody else: the step is being collected, the
    // other own agent is missing (and no cell-mate of another process is expected).
    let percepts = net.server.world().percepts();
    let geom = net.server.world().geometry();
    let p = percepts.iter().find(|p| p.agents.iter().any(|a| a.id == 0)).unwrap().clone();
    let mut only0 = p.clone();
    only0.agents.retain(|a| a.id == 0);
    host.absorb(Input::Percept { cell: only0.cell, bytes: &encode(&only0).unwrap() }, now);
    // The same again (a duplicate) and one from a cell topic that is not its cell.
    host.absorb(Input::Percept { cell: only0.cell, bytes: &encode(&only0).unwrap() }, now);
    host.absorb(
        Input::Percept { cell: (only0.cell + 1) % geom.cell_count() as u32, bytes: &encode(&only0).unwrap() },
        now,
    );
    let deadline = match host.next(now) {
        HostNext::Wait(Some(d)) => d,
        other => panic!("expected a wait for the missing percept, got {other:?}"),
    };
    // The 100 ms percept deadline, longer on a process's first step.
    let first = 100 * u64::from(geese_proto::net::FIRST_STEP_FACTOR);
    assert_eq!(deadline, now + Duration::from_millis(first));
    let HostNext::Act(outs) = host.next(deadline) else { panic!("nothing at the percept deadline") };
    let b = intents(&outs);
    assert_eq!(b.step, 1);
    assert_eq!(b.idle, vec![1]);
    assert_eq!(b.intents.len(), 1);
    assert_eq!((b.counters.percepts_missing, b.counters.hostile, b.counters.deadline_hits), (1, 1, 1));
    // A stale percept of step 1 after it is done changes nothing.
    host.absorb(Input::Percept { cell: p.cell, bytes: &encode(&p).unwrap() }, deadline);
    assert!(matches!(host.next(deadline), HostNext::Wait(None)));
    assert_eq!(host.done(), 1);
}

#[test]
fn hostile_input_to_a_host_is_counted_and_changes_nothing() {
    let (mut net, out) = one_host(false);
    let now = net.now;
    let host = &mut net.procs[0].host;
    host.absorb(Input::Tick(b"\x09\x01\x02"), now);
    host.absorb(Input::Tick(&encode(&geese_proto::net::Tick { step: 1, cells: vec![0] }).unwrap()), now);
    host.absorb(Input::HostPercepts(b"junk"), now);
    host.absorb(Input::HostGenes(b""), now);
    host.absorb(Input::Hostile, now);
    host.absorb(Input::Presence { alive: true, key: "geese/mem/presence/agents/zz" }, now);
    // Then the world's real messages for it: the step goes on as usual.
    for (k, b) in &out {
        if *k == keys::tick(RUN) {
            host.absorb(Input::Tick(b), now);
        } else if *k == keys::host_percepts(RUN, AgentRange::new(0, 2).unwrap()) {
            host.absorb(Input::HostPercepts(b), now);
        }
    }
    let mut outs = Vec::new();
    while let HostNext::Act(o) = host.next(now) {
        outs.extend(o);
        if outs.iter().any(|o| matches!(o, Out::Intents(_))) {
            break;
        }
        // Genes of a shared cell: the other process's come through the world.
    }
    if !outs.iter().any(|o| matches!(o, Out::Intents(_))) {
        // Waiting for cell-mates of process 1: they never come; the gene deadline ends it.
        let HostNext::Wait(Some(d)) = host.next(now) else { panic!("expected the gene wait") };
        let HostNext::Act(o) = host.next(d) else { panic!("nothing at the gene deadline") };
        outs.extend(o);
        assert!(intents(&outs).counters.genes_late > 0);
    }
    let b = intents(&outs);
    assert_eq!(b.counters.hostile, 5);
    assert_eq!(b.intents.len(), 2);
}

#[test]
fn only_the_world_ends_a_gene_wait_for_cell_mates_that_left_and_the_world_leaving_stops_the_host() {
    let (mut net, out) = one_host(false);
    let now = net.now;
    let (r0, r1) = (net.procs[0].range, net.procs[1].range);
    for (k, b) in &out {
        if *k == keys::tick(RUN) {
            net.procs[0].host.absorb(Input::Tick(b), now);
        } else if *k == keys::host_percepts(RUN, r0) {
            net.procs[0].host.absorb(Input::HostPercepts(b), now);
        }
    }
    // Paper layout: all four agents at the hub, in one cell; step 1 sends no genes
    // ahead, so process 0 publishes its genes and waits for process 1's, which never
    // speaks (it is killed before it does).
    net.procs[1].gone = true;
    let HostNext::Act(first) = net.procs[0].host.next(now) else { panic!("step 1 did not begin") };
    assert!(!first.iter().any(|o| matches!(o, Out::Intents(_))));
    let genes = first.iter().find_map(|o| if let Out::Genes(b) = o { Some(b) } else { None }).expect("genes");
    let mut released = net.server.on_gene_bundle(&keys::agents_genes(RUN, r0), genes);
    net.server.flush_genes(&mut released);
    net.route(released);
    assert!(matches!(net.procs[0].host.next(now), HostNext::Wait(Some(_))));
    // Process 0's own view of the tokens does not end the wait: across routers it can
    // lag behind the world's (a token not yet seen, or seen going before it came back),
    // and only the world says who is in a step.
    let gone = keys::agents_presence(RUN, r1);
    net.procs[0].host.absorb(Input::Presence { alive: false, key: &gone }, now);
    assert!(matches!(net.procs[0].host.next(now), HostNext::Wait(Some(_))), "a token alone ended the wait");
    // The world forgets process 1 and releases the cell: the wait ends, nothing late.
    net.leave(1);
    let HostNext::Act(outs) = net.procs[0].host.next(now) else { panic!("the world's release did not end the wait") };
    let b = intents(&outs);
    assert_eq!((b.counters.genes_late, b.counters.deadline_hits), (0, 0));
    let host = &mut net.procs[0].host;
    host.absorb(Input::Presence { alive: false, key: &keys::world_presence(RUN) }, now);
    assert!(matches!(host.next(now), HostNext::Stopped));
    assert!(host.stopped());
}
