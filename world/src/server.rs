//! The world server's protocol, sans IO: presence, the control plane and the sequencing
//! of every step (DESIGN.md §2), around the [`World`], the intent [`Gather`] and the
//! [`GeneHub`].
//!
//! The `geese-world` binary is a shell around a [`Server`]: it hands it what arrives
//! (presence changes, control commands, intent batches, gene batches and bundles, a
//! signal) with the `on_*` methods, publishes what they return, and drives the steps
//! with [`Server::next`], passing the time now. `next` answers with messages to publish
//! ([`Next::Publish`]), the instant until which nothing can happen unless a message
//! arrives ([`Next::Wait`]), or the end of the run ([`Next::Finished`]). Every wait has
//! a deadline: the join deadline before step 1, the intent deadline in each step. A step
//! that reaches its deadline says so in the log and in its [`NetCounters::intents_late`].
//!
//! Step t, as `next` runs it:
//! 1. between steps: revive the agents of processes that came back, take the
//!    perturbations the control plane scheduled; open the gathering and the gene hub;
//! 2. publish the tick (when the live set changed), the percepts of every occupied cell
//!    (per cell while some process reads cells one by one; one message per hosting
//!    process otherwise, with the genes sent ahead when every process sent them);
//! 3. wait until every expected agent answered, or the intent deadline;
//! 4. drop intents by the injected loss, resolve the step, publish the report.
use crate::gather::Gather;
use crate::hub::{shared_cells, CellMap, GeneHub, Released};
use crate::pace::Pace;
use crate::{ConfigError, World, WorldConfig};
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{
    loss_draw, nest, nested_size, HostPercepts, NetCounters, NetReport, NetRunSpec, Raw, ReportMsg, RunInfo, Tick,
    LOSS_SALT_INTENT, NO_CELL,
};
use geese_proto::seed::{derive, Owner, Purpose};
use geese_proto::{decode, encode, encode_sized, CodecError, Control, Perturbation, StepReport};
use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

/// Why a run could not start or go on.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("world configuration: {0}")]
    Config(String),
    #[error("world: {0}")]
    World(#[from] ConfigError),
    #[error("encoding a message: {0}")]
    Codec(#[from] CodecError),
    #[error("join deadline ({ms} ms): agent processes cover {covered} of {agents} agents{orchestrator}")]
    Join { ms: u32, covered: u32, agents: usize, orchestrator: &'static str },
}

/// What the shell does next.
#[derive(Debug)]
pub enum Next {
    /// Publish these messages (key, bytes), in order, then call [`Server::next`] again.
    Publish(Released),
    /// Nothing to do until a message arrives or this instant passes.
    Wait(Instant),
    /// The run is over: publish these last messages (the final report and a stop for
    /// everyone); `outcome` says whether it completed all its steps.
    Finished { messages: Released, outcome: Result<bool, ServerError> },
}

/// How often a paused server looks again (a control message wakes it sooner).
const PAUSED_POLL: Duration = Duration::from_millis(250);

#[derive(Debug, Clone, Copy)]
enum Phase {
    /// Waiting for every expected process, until the join deadline.
    Joining {
        deadline: Instant,
    },
    /// Between two steps.
    Between,
    /// Gathering the intents of the step begun at `started`.
    Gathering {
        started: Instant,
        deadline: Instant,
    },
    Over,
}

/// The world server of one distributed run.
pub struct Server {
    spec: NetRunSpec,
    world: World,
    gather: Gather,
    hub: GeneHub,
    run: String,
    n: usize,
    phase: Phase,
    /// Present agent processes (tokens per id range: a restarted process may briefly
    /// overlap the token of the one it replaces).
    hosts: BTreeMap<AgentRange, u32>,
    /// Present agent processes that read cells one topic per cell (tokens per range).
    narrow: BTreeMap<AgentRange, u32>,
    orchestrator: bool,
    /// Agents whose process came (back) since the last step: revive them.
    revive: Vec<u32>,
    /// Perturbations received on the control plane, applied between steps.
    scheduled: Vec<(u64, geese_proto::Perturbation)>,
    stop: bool,
    /// The stop came from a control-plane `Stop` (a clean early end, not a failure).
    stop_requested: bool,
    /// The live set last announced in a tick.
    announced: Option<Vec<u32>>,
    percept_keys: HashMap<u32, String>,
    loss_stream: u64,
    steps_done: u64,
    counters: NetCounters,
    /// Counted rejections of inputs that arrive between steps (reported with the next).
    rejected_between: u32,
    /// Live viewers present (tokens): frames are built and sent only while one is.
    viewers: u32,
    /// The last step's report (the frame shown while paused).
    last_report: Option<StepReport>,
    /// Pause, step-rate limit and frame-rate bound (the viewer's controls).
    pace: Pace,
}

impl Server {
    /// A server for `spec`, set up exactly as the in-process driver sets up its world
    /// (orchestrator/src/run/trial.rs); joining until `now` + the join deadline.
    pub fn new(spec: NetRunSpec, now: Instant) -> Result<Self, ServerError> {
        let wcfg: WorldConfig =
            serde_json::from_str(&spec.world_json).map_err(|e| ServerError::Config(e.to_string()))?;
        if wcfg.agents != spec.agents {
            return Err(ServerError::Config(format!(
                "spec: {} agents but the world configuration has {}",
                spec.agents, wcfg.agents
            )));
        }
        for (field, p) in [("loss.intent", spec.loss.intent), ("loss.percept", spec.loss.percept)] {
            geese_proto::limits::check_unit(field, p).map_err(|e| ServerError::Config(e.to_string()))?;
        }
        let mut world = World::new(wcfg, spec.seed)?;
        world.set_regime(spec.regime);
        for (at, change) in &spec.perturbations {
            world.schedule(*at, change.clone());
        }
        let n = spec.agents as usize;
        let run = spec.run.clone();
        Ok(Server {
            gather: Gather::new(run.clone(), n),
            hub: GeneHub::new(run.clone(), world.geometry()),
            loss_stream: derive(spec.seed, Owner::World, Purpose::Loss) ^ LOSS_SALT_INTENT,
            phase: Phase::Joining { deadline: now + Duration::from_millis(spec.deadlines.join_ms as u64) },
            run,
            n,
            spec,
            world,
            hosts: BTreeMap::new(),
            narrow: BTreeMap::new(),
            orchestrator: false,
            revive: Vec::new(),
            scheduled: Vec::new(),
            stop: false,
            stop_requested: false,
            announced: None,
            percept_keys: HashMap::new(),
            steps_done: 0,
            counters: NetCounters::default(),
            rejected_between: 0,
            viewers: 0,
            last_report: None,
            pace: Pace::new(),
        })
    }

    /// The world (read only).
    pub fn world(&self) -> &World {
        &self.world
    }

    /// Count the locality map of `window` ([`World::record_locality`]); call before the
    /// run starts, as the in-process driver does.
    pub fn record_locality(&mut self, window: crate::locality::Window) {
        self.world.record_locality(window);
    }

    /// Steps completed so far.
    pub fn steps_done(&self) -> u64 {
        self.steps_done
    }

    /// Present agent processes.
    pub fn processes(&self) -> usize {
        self.hosts.len()
    }

    /// What a joining agent process needs to know (the `ctl/info` queryable).
    pub fn run_info(&self) -> RunInfo {
        let g = self.world.geometry();
        let cells =
            if self.spec.bare { Vec::new() } else { self.world.bodies().iter().map(|b| g.cell_of(b.pos)).collect() };
        RunInfo { spec: self.spec.clone(), geometry: g, hub: self.world.hub(), next_step: self.world.step(), cells }
    }

    fn covered(&self) -> u32 {
        let mut c = vec![false; self.n];
        for r in self.hosts.keys() {
            for id in r.ids() {
                if let Some(x) = c.get_mut(id as usize) {
                    *x = true;
                }
            }
        }
        c.iter().filter(|&&x| x).count() as u32
    }

    fn ready(&self) -> bool {
        self.covered() as usize == self.n && (self.orchestrator || !self.spec.expect_orchestrator)
    }

    /// Present agent processes that read no cell topic (hosting processes): they get
    /// their percepts and genes on keys of their own.
    fn hosting(&self) -> Vec<AgentRange> {
        self.hosts.keys().filter(|r| !self.narrow.contains_key(r)).copied().collect()
    }

    fn count_rejected(&mut self) {
        match self.phase {
            Phase::Gathering { .. } => self.counters.hostile += 1,
            _ => self.rejected_between += 1,
        }
    }

    /// A liveliness token appeared (`alive`) or went on `key`. Returns the gene
    /// messages that a process leaving completes.
    pub fn on_presence(&mut self, alive: bool, key: &str) -> Released {
        if matches!(self.phase, Phase::Over) {
            // The run is over: everyone leaving now is the end, not a failure.
            return Released::default();
        }
        match keys::parse(&self.run, key) {
            p @ (Parsed::AgentsPresence { agents } | Parsed::CellsPresence { agents })
                if !p.within(self.spec.agents) =>
            {
                // A range beyond the run: never iterated, never counted as present.
                tracing::debug!("presence token {key}: agents {agents} outside the run's {} agents; ignored", self.n);
                self.count_rejected();
                Released::default()
            }
            Parsed::AgentsPresence { agents } => {
                keys::tally(&mut self.hosts, agents, alive);
                if alive {
                    self.revive.extend(agents.ids());
                    if !matches!(self.phase, Phase::Joining { .. }) {
                        tracing::info!("agent process {agents} joined at step {}", self.world.step());
                    }
                    return Released::default();
                }
                let out = self.hub.forget(agents);
                // Its agents stop here: bodies idle, carried items dropped.
                for id in agents.ids() {
                    if !self.hosts.keys().any(|r| r.contains(id)) {
                        self.world.kill(id);
                        self.gather.forget(id as usize);
                        self.revive.retain(|&r| r != id);
                    }
                }
                tracing::info!("agent process {agents} left at step {}", self.world.step());
                out
            }
            Parsed::CellsPresence { agents } => {
                keys::tally(&mut self.narrow, agents, alive);
                Released::default()
            }
            Parsed::ViewerPresence => {
                if alive {
                    self.viewers += 1;
                    // A viewer that just came sees the current step at once.
                    self.pace.owe_frame();
                } else {
                    self.viewers = self.viewers.saturating_sub(1);
                }
                tracing::info!("live viewers: {}", self.viewers);
                Released::default()
            }
            Parsed::OrchestratorPresence => {
                if alive {
                    self.orchestrator = true;
                } else if self.spec.expect_orchestrator {
                    tracing::warn!("the orchestrator left; stopping");
                    self.stop = true;
                }
                Released::default()
            }
            _ => Released::default(),
        }
    }

    /// A message on the control plane.
    pub fn on_control(&mut self, bytes: &[u8]) {
        let command = match decode::<Control>(bytes) {
            Ok(c) => c,
            Err(e) => {
                // One line per message at debug; the step's report counts them and
                // says so once (a flood of hostile messages must not flood the log).
                tracing::debug!("control message dropped: {e}");
                self.count_rejected();
                return;
            }
        };
        if let Err(e) = command.validate(&self.world.geometry()) {
            tracing::warn!("control command rejected: {e}");
            self.count_rejected();
            return;
        }
        if self.pace.on_control(&command) {
            tracing::info!("pace: {command:?}");
            return;
        }
        match command {
            Control::Pause | Control::Resume | Control::StepRate(_) => {}
            Control::Stop => {
                self.stop = true;
                self.stop_requested = true;
            }
            Control::Schedule { at_step, change } => self.scheduled.push((at_step, change)),
            Control::Start => {}
        }
    }

    /// SIGINT/SIGTERM: stop after the step in progress.
    pub fn on_signal(&mut self) {
        tracing::warn!("signal received; stopping");
        self.stop = true;
    }

    /// An intent batch; true when the step's gathering is complete (wake the loop). The
    /// genes it carries for the next step are filed first, so they are in before the
    /// loop can begin that step.
    pub fn on_action(&mut self, key: &str, bytes: &[u8]) -> bool {
        let Some((from, mut batch)) = self.gather.open(key, bytes) else { return false };
        if let Some(packed) = batch.ahead.take() {
            self.hub.on_ahead(from, batch.step.saturating_add(1), packed);
        }
        self.gather.file(from, batch)
    }

    /// A gene batch on its cell's key.
    pub fn on_gene_batch(&mut self, key: &str, bytes: &[u8]) -> Released {
        self.hub.on_batch(key, bytes)
    }

    /// A process's gene bundle.
    pub fn on_gene_bundle(&mut self, key: &str, bytes: &[u8]) -> Released {
        self.hub.on_bundle(key, bytes)
    }

    /// What the hub holds for hosting processes, appended to `out` (call each time the
    /// publisher wakes: what was filed meanwhile goes out together).
    pub fn flush_genes(&mut self, out: &mut Released) {
        self.hub.flush(out);
    }

    /// Advance as far as possible at time `now`.
    pub fn next(&mut self, now: Instant) -> Next {
        loop {
            match self.phase {
                Phase::Over => {
                    return Next::Finished { messages: Released::default(), outcome: Ok(false) };
                }
                _ if self.stop => {
                    return self.finish(Ok(false));
                }
                Phase::Joining { deadline } => {
                    if self.ready() {
                        self.revive.clear();
                        tracing::info!(
                            "{} agent processes present, starting {} steps",
                            self.hosts.len(),
                            self.spec.steps
                        );
                        self.phase = Phase::Between;
                        continue;
                    }
                    if now >= deadline {
                        let err = ServerError::Join {
                            ms: self.spec.deadlines.join_ms,
                            covered: self.covered(),
                            agents: self.n,
                            orchestrator: if self.spec.expect_orchestrator && !self.orchestrator {
                                ", orchestrator absent"
                            } else {
                                ""
                            },
                        };
                        return self.finish(Err(err));
                    }
                    return Next::Wait(deadline);
                }
                Phase::Between => {
                    if self.world.step() > self.spec.steps {
                        return self.finish(Ok(true));
                    }
                    // The viewer's pause and step-rate limit hold the next step back;
                    // a control message wakes the shell before the wait ends.
                    match self.pace.step_at(now) {
                        None => {
                            // Paused: what the control plane scheduled applies now, as it
                            // would between two steps, and the viewer sees it at once.
                            if self.hand_over_scheduled() {
                                self.pace.owe_frame();
                            }
                            if let Some(out) = self.frame_if_due(now) {
                                return Next::Publish(out);
                            }
                            return Next::Wait(now + PAUSED_POLL);
                        }
                        Some(at) if at > now => return Next::Wait(at),
                        Some(_) => self.pace.stepped(now),
                    }
                    return match self.begin_step(now) {
                        Ok(out) => Next::Publish(out),
                        Err(e) => self.finish(Err(e)),
                    };
                }
                Phase::Gathering { started, deadline } => {
                    let pending = self.gather.pending();
                    if pending > 0 && now < deadline {
                        return Next::Wait(deadline);
                    }
                    if now >= deadline {
                        // At the deadline: a hit, whether intents are missing or the
                        // wake-up that should have come with the last one never did.
                        self.counters.deadline_hits += 1;
                        self.counters.intents_late = pending as u32;
                        tracing::warn!(
                            "step {}: the intent deadline ({} ms) passed with {pending} intents missing",
                            self.world.step(),
                            deadline.saturating_duration_since(started).as_millis()
                        );
                        self.hub.trace_incomplete();
                    }
                    self.counters.wait_us =
                        now.saturating_duration_since(started).as_micros().min(u32::MAX as u128) as u32;
                    return match self.finish_step(now) {
                        Ok(out) => Next::Publish(out),
                        Err(e) => self.finish(Err(e)),
                    };
                }
            }
        }
    }

    /// The end: the final report and a stop for everyone.
    fn finish(&mut self, outcome: Result<bool, ServerError>) -> Next {
        self.phase = Phase::Over;
        let completed = matches!(outcome, Ok(true));
        let mut messages = Released::default();
        let done = ReportMsg::Done { steps: self.steps_done, completed, requested: self.stop_requested };
        if let Ok(b) = encode(&done) {
            messages.push((keys::report(&self.run), b));
        }
        if let Ok(b) = encode(&Control::Stop) {
            messages.push((keys::ctl(&self.run, "stop"), b));
        }
        Next::Finished { messages, outcome }
    }

    /// Give the world what the control plane scheduled (between two steps: a change
    /// whose step has passed applies at once). True if there was any.
    fn hand_over_scheduled(&mut self) -> bool {
        let any = !self.scheduled.is_empty();
        for (at, change) in std::mem::take(&mut self.scheduled) {
            if let Perturbation::SwitchTask(task) = change {
                // Checked here, in arrival order, against the switches already
                // scheduled: only the world knows which task will be running then.
                if self.world.task_after(at) == task {
                    tracing::warn!("control command rejected: SwitchTask to {task} at step {at}: that task is already running then");
                    self.count_rejected();
                    continue;
                }
            }
            self.world.schedule(at, change);
        }
        any
    }

    /// Steps 1–2: open step `world.step()` and build what goes out.
    fn begin_step(&mut self, now: Instant) -> Result<Released, ServerError> {
        let step = self.world.step();
        let mut out = Released::default();
        let deadlines = self.spec.deadlines.of_step(self.steps_done == 0 || !self.revive.is_empty());
        // Between steps: revivals and control-plane perturbations.
        for id in std::mem::take(&mut self.revive) {
            if !self.spec.bare && self.world.bodies().get(id as usize).is_some_and(|b| !b.live) {
                self.world.revive(id);
            }
        }
        self.hand_over_scheduled();
        self.counters = NetCounters { hostile: std::mem::take(&mut self.rejected_between), ..NetCounters::default() };
        // Who reads what this step: per-cell topics while some process reads cells one by
        // one; a message of their own for every hosting process.
        let per_cell = !self.narrow.is_empty();
        let hosting = self.hosting();
        // Genes sent ahead go out with the percepts while every process is a hosting one,
        // lateral transfer is on and every process sent its genes of the step ahead (see
        // `HostPercepts::genes`; not so at step 1, nor right after a process joined).
        // Otherwise they go through the hub, as processes publish them during the step.
        let mut ahead = !self.spec.bare && !per_cell && !hosting.is_empty() && self.world.regime().lateral_transfer;
        let mut ahead_packs: Vec<(AgentRange, Vec<u8>)> = Vec::new();
        // The hosting processes whose genes each process reads.
        let mut partners: HashMap<AgentRange, Vec<AgentRange>> = HashMap::new();
        let hosts: Vec<AgentRange> = self.hosts.keys().copied().collect();
        // Open the gathering before anything goes out: fast answers must find it open.
        {
            let bare = self.spec.bare;
            let bodies = self.world.bodies();
            self.gather.begin(step, |i| if bare { hosts.iter().any(|r| r.contains(i as u32)) } else { bodies[i].live });
        }
        if !self.spec.bare {
            // Cells where a process reads genes of another process's agents: they go
            // through the hub (lateral transfer on only). At GS ≥ 3 the cells whose
            // centred live agents belong to more than one process; at GS 2 also those
            // next to them ([`shared_cells`]).
            let mut shared = CellMap::default();
            if self.world.regime().lateral_transfer {
                // Bodies come in id order and a process speaks for contiguous ids, so a
                // body's process is mostly the previous body's (the first in order that
                // contains its id, either way).
                let mut owner: Option<AgentRange> = None;
                let mut live: Vec<(AgentRange, geese_proto::Pos)> = Vec::with_capacity(self.n);
                for b in self.world.bodies().iter().filter(|b| b.live) {
                    if !owner.is_some_and(|r| r.contains(b.id)) {
                        owner = hosts.iter().find(|r| r.contains(b.id)).copied();
                    }
                    if let Some(r) = owner {
                        live.push((r, b.pos));
                    }
                }
                shared = shared_cells(&self.world.geometry(), &live);
            }
            let packs = self.hub.take_ahead(step);
            // From every process with a live agent (one without takes no part).
            let bodies = self.world.bodies();
            let takes_part = |h: &AgentRange| h.ids().any(|id| bodies.get(id as usize).is_some_and(|b| b.live));
            ahead &= hosting.iter().filter(|h| takes_part(h)).all(|h| packs.iter().any(|(from, _)| from == h));
            if ahead {
                for peers in shared.values() {
                    for a in &peers.readers {
                        let p = partners.entry(*a).or_default();
                        for b in &peers.writers {
                            if b != a && !p.contains(b) {
                                p.push(*b);
                            }
                        }
                    }
                }
                ahead_packs = packs;
                shared.clear();
            }
            self.hub.begin(step, shared, per_cell, &hosting);
        }
        // The tick (bare: every step; otherwise when the live set changed), then the
        // percepts of every occupied cell.
        if self.spec.bare {
            out.push((keys::tick(&self.run), encode(&Tick { step, cells: Vec::new() })?));
        } else {
            let g = self.world.geometry();
            let cells: Vec<u32> =
                self.world.bodies().iter().map(|b| if b.live { g.cell_of(b.pos) } else { NO_CELL }).collect();
            let live: Vec<u32> = cells.iter().map(|&c| if c == NO_CELL { NO_CELL } else { 0 }).collect();
            if self.announced.as_ref() != Some(&live) {
                out.push((keys::tick(&self.run), encode(&Tick { step, cells })?));
                self.announced = Some(live);
            }
            let percepts = self.world.percepts();
            tracing::trace!(target: "geese::flow", "step {step}: {} percepts (per cell: {per_cell})", percepts.len());
            // Per-cell topics only while some process reads them.
            if per_cell {
                for p in &percepts {
                    let ke = self.percept_key(p.cell);
                    out.push((ke, encode(p)?));
                }
            }
            // Every hosting process: the percepts of its live agents' cells, each cell
            // encoded once.
            if !hosting.is_empty() {
                let mut nested: CellMap<Vec<u8>> =
                    CellMap::with_capacity_and_hasher(percepts.len(), Default::default());
                for p in &percepts {
                    nested.insert(p.cell, nest(p)?);
                }
                for &to in &hosting {
                    let mut cells: Vec<u32> = to
                        .ids()
                        .filter_map(|id| self.world.bodies().get(id as usize))
                        .filter(|b| b.live)
                        .map(|b| g.cell_of(b.pos))
                        .collect();
                    cells.sort_unstable();
                    cells.dedup();
                    let percepts: Vec<Raw> = cells.iter().filter_map(|c| nested.get(c).map(|b| Raw(b))).collect();
                    let genes: Option<Vec<Raw>> = ahead.then(|| {
                        let mates = partners.get(&to).map_or(&[][..], |p| p.as_slice());
                        ahead_packs.iter().filter(|(from, _)| mates.contains(from)).map(|(_, p)| Raw(p)).collect()
                    });
                    self.counters.genes_ahead += genes.is_some() as u32;
                    let size = nested_size(&percepts, 0) + genes.as_deref().map_or(0, |g| nested_size(g, 0));
                    let bytes = encode_sized(&HostPercepts { step, percepts, genes }, size)?;
                    out.push((keys::host_percepts(&self.run, to), bytes));
                }
            }
        }
        let deadline = now + Duration::from_millis(deadlines.intent_ms as u64);
        self.phase = Phase::Gathering { started: now, deadline };
        Ok(out)
    }

    /// Step 4: resolve the gathered step and report it.
    fn finish_step(&mut self, now: Instant) -> Result<Released, ServerError> {
        let step = self.world.step();
        let got = self.gather.close();
        let c = &mut self.counters;
        c.hostile = c.hostile.saturating_add(self.hub.close()).saturating_add(got.counters.hostile);
        c.percepts_lost = c.percepts_lost.saturating_add(got.counters.percepts_lost);
        c.percepts_missing = c.percepts_missing.saturating_add(got.counters.percepts_missing);
        c.genes_late = c.genes_late.saturating_add(got.counters.genes_late);
        c.deadline_hits = c.deadline_hits.saturating_add(got.counters.deadline_hits);
        let mut intents = got.intents;
        // Injected intent loss (world side), one counter-based draw per arrived intent.
        let p = self.spec.loss.intent;
        if p > 0.0 {
            for (id, slot) in intents.iter_mut().enumerate() {
                if slot.is_some() && loss_draw(self.loss_stream, step, id as u64) < p {
                    *slot = None;
                    self.counters.intents_lost += 1;
                }
            }
        }
        let mut report = self.world.resolve(&intents);
        if self.spec.bare {
            // No world to speak of: live = present, missing = not answered.
            let live = (0..self.n).filter(|&i| self.hosts.keys().any(|r| r.contains(i as u32))).count();
            report.live_agents = live as u32;
            report.missing_intents = (live - got.answered_expected.min(live)) as u32;
        }
        self.counters.processes = self.hosts.len() as u32;
        if self.counters.hostile > 0 {
            tracing::warn!(
                "step {step}: {} hostile messages dropped (world and agent processes; RUST_LOG=debug names each)",
                self.counters.hostile
            );
        }
        let msg = ReportMsg::Step(NetReport { report: report.clone(), net: self.counters });
        let mut out = vec![(keys::report(&self.run), encode(&msg)?)];
        self.steps_done = step;
        self.phase = Phase::Between;
        self.last_report = Some(report);
        out.extend(self.frame_if_due(now).unwrap_or_default());
        Ok(out)
    }

    /// The view frame of the last step, when a viewer is present and one is due (the
    /// frame-rate bound, or a pace change or new viewer owed one). Without a viewer
    /// nothing is built: a run nobody watches pays one comparison a step.
    fn frame_if_due(&mut self, now: Instant) -> Option<Released> {
        if self.viewers == 0 || !self.pace.frame_due(now) {
            return None;
        }
        let rep = self.last_report.clone().unwrap_or_else(|| StepReport {
            task_pct: self.world.task_pct(),
            live_agents: self.world.live_agents(),
            ..StepReport::default()
        });
        let f = crate::frame::frame(&self.world, &rep, self.spec.steps, &self.pace);
        match encode(&f) {
            Ok(b) => Some(vec![(keys::view_frame(&self.run), b)]),
            Err(e) => {
                tracing::warn!("view frame not encoded: {e}");
                None
            }
        }
    }

    /// The percept key of a cell (plain key expressions: a key declared by this session
    /// would not be known to clients that connect later, e.g. a restarted agent).
    fn percept_key(&mut self, cell: u32) -> String {
        let (cx, cy) = self.world.geometry().cell_col_row(cell);
        let run = &self.run;
        self.percept_keys.entry(cell).or_insert_with(|| keys::cell_percept(run, cx, cy)).clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geese_proto::net::{Deadlines, HostCounters, IntentBatch, LossRates};
    use geese_proto::{Intent, Regime};

    const RUN: &str = "t";

    fn spec(agents: u32, steps: u64) -> NetRunSpec {
        let world = WorldConfig { agents, ..WorldConfig::default() };
        NetRunSpec {
            run: RUN.into(),
            seed: 7,
            steps,
            agents,
            world_json: serde_json::to_string(&world).unwrap(),
            learner_json: String::new(),
            program_json: String::new(),
            grammar_name: String::new(),
            grammar_text: String::new(),
            regime: Regime::default(),
            perturbations: Vec::new(),
            loss: LossRates::default(),
            deadlines: Deadlines { intent_ms: 100, gene_ms: 100, percept_ms: 100, join_ms: 1_000 },
            bare: false,
            expect_orchestrator: false,
        }
    }

    fn range(first: u32, count: u32) -> AgentRange {
        AgentRange::new(first, count).unwrap()
    }

    fn join(s: &mut Server, r: AgentRange, alive: bool) {
        s.on_presence(alive, &keys::agents_presence(RUN, r));
    }

    /// Every agent of `r` answers step `step` with an empty intent.
    fn answer(s: &mut Server, r: AgentRange, step: u64) -> bool {
        let intents = r
            .ids()
            .filter(|&id| s.world().bodies()[id as usize].live)
            .map(|agent| Intent { agent, step, heading: 0.0, ops: vec![], stats: Default::default() })
            .collect();
        let b = IntentBatch { step, intents, idle: vec![], counters: HostCounters::default(), ahead: None };
        s.on_action(&keys::agents_action(RUN, r), &encode(&b).unwrap())
    }

    fn published(n: &Next) -> Vec<String> {
        match n {
            Next::Publish(out) => out.iter().map(|(k, _)| k.clone()).collect(),
            other => panic!("expected messages to publish, got {other:?}"),
        }
    }

    fn report(n: Next) -> NetReport {
        let Next::Publish(out) = n else { panic!("expected the report, got {n:?}") };
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].0, keys::report(RUN));
        match decode::<ReportMsg>(&out[0].1).unwrap() {
            ReportMsg::Step(r) => r,
            other => panic!("expected a step report, got {other:?}"),
        }
    }

    #[test]
    fn waits_for_every_process_then_times_out_at_the_join_deadline() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(4, 3), t0).unwrap();
        join(&mut s, range(0, 2), true);
        assert!(matches!(s.next(t0), Next::Wait(d) if d == t0 + Duration::from_millis(1_000)));
        match s.next(t0 + Duration::from_millis(1_000)) {
            Next::Finished { outcome: Err(e), messages } => {
                assert!(e.to_string().contains("cover 2 of 4 agents"), "{e}");
                assert_eq!(messages.len(), 2, "a done report and a stop");
            }
            other => panic!("expected the end, got {other:?}"),
        }
    }

    #[test]
    fn a_run_steps_through_when_every_intent_arrives_and_never_waits_a_deadline() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(4, 3), t0).unwrap();
        let (a, b) = (range(0, 2), range(2, 2));
        join(&mut s, a, true);
        join(&mut s, b, true);
        for step in 1..=3 {
            let keys = published(&s.next(t0));
            assert!(keys.contains(&keys::host_percepts(RUN, a)) && keys.contains(&keys::host_percepts(RUN, b)));
            assert_eq!(keys.contains(&keys::tick(RUN)), step == 1, "a tick only when the live set changes");
            assert!(matches!(s.next(t0), Next::Wait(_)));
            assert!(!answer(&mut s, a, step));
            assert!(answer(&mut s, b, step));
            let r = report(s.next(t0));
            assert_eq!(r.report.step, step);
            assert_eq!((r.net.intents_late, r.net.hostile, r.net.deadline_hits, r.net.processes), (0, 0, 0, 2));
            assert_eq!(r.report.missing_intents, 0);
        }
        match s.next(t0) {
            Next::Finished { outcome: Ok(true), .. } => {}
            other => panic!("expected a completed run, got {other:?}"),
        }
        assert_eq!(s.steps_done(), 3);
    }

    #[test]
    fn a_missing_process_costs_one_deadline_and_is_counted_late() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(4, 2), t0).unwrap();
        let (a, b) = (range(0, 2), range(2, 2));
        join(&mut s, a, true);
        join(&mut s, b, true);
        published(&s.next(t0));
        answer(&mut s, a, 1);
        // The first step waits FIRST_STEP_FACTOR times the 100 ms deadline.
        let first = Duration::from_millis(100 * u64::from(geese_proto::net::FIRST_STEP_FACTOR));
        let deadline = t0 + first;
        assert!(matches!(s.next(deadline - Duration::from_millis(1)), Next::Wait(d) if d == deadline));
        let r = report(s.next(deadline));
        assert_eq!((r.net.intents_late, r.net.deadline_hits), (2, 1));
        assert_eq!(r.report.missing_intents, 2);
        assert!(r.net.wait_us as u128 >= first.as_micros());
        // A straggler of step 1 during step 2 is dropped, and not hostile.
        published(&s.next(deadline));
        assert!(!answer(&mut s, b, 1));
        answer(&mut s, a, 2);
        // Later steps have the usual deadline.
        let later = deadline + Duration::from_millis(100);
        assert!(matches!(s.next(deadline + Duration::from_millis(99)), Next::Wait(d) if d == later));
        assert!(answer(&mut s, b, 2));
        let r = report(s.next(deadline));
        assert_eq!((r.net.intents_late, r.net.hostile), (0, 0));
    }

    #[test]
    fn a_process_that_leaves_mid_step_is_not_waited_for_and_rejoins_at_the_next_step() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(4, 3), t0).unwrap();
        let (a, b) = (range(0, 2), range(2, 2));
        join(&mut s, a, true);
        join(&mut s, b, true);
        published(&s.next(t0));
        answer(&mut s, a, 1);
        join(&mut s, b, false);
        let r = report(s.next(t0));
        assert_eq!(r.net.intents_late, 0, "agents of a process that left are not awaited");
        assert_eq!((r.report.live_agents, r.net.processes), (2, 1));
        // It comes back: its agents are revived before the next step, and awaited.
        join(&mut s, b, true);
        // Killed and revived between two ticks: the live set announced stands.
        let keys = published(&s.next(t0));
        assert!(!keys.contains(&keys::tick(RUN)));
        answer(&mut s, a, 2);
        assert!(matches!(s.next(t0), Next::Wait(_)), "the rejoined agents are awaited");
        assert!(answer(&mut s, b, 2));
        let r = report(s.next(t0));
        assert_eq!((r.report.live_agents, r.net.processes), (4, 2));
    }

    #[test]
    fn a_restarted_process_overlapping_its_predecessor_keeps_its_agents_alive() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 2), t0).unwrap();
        let a = range(0, 2);
        join(&mut s, a, true);
        join(&mut s, a, true); // the new token before the old one goes
        join(&mut s, a, false);
        published(&s.next(t0));
        assert!(answer(&mut s, a, 1));
        assert_eq!(report(s.next(t0)).report.live_agents, 2);
    }

    #[test]
    fn presence_ranges_beyond_the_run_are_ignored_and_counted() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 1), t0).unwrap();
        let huge = AgentRange { first: 0, last: u32::MAX };
        join(&mut s, huge, true);
        assert_eq!(s.processes(), 0);
        join(&mut s, range(0, 2), true);
        published(&s.next(t0));
        assert!(answer(&mut s, range(0, 2), 1));
        join(&mut s, huge, false);
        let r = report(s.next(t0));
        assert_eq!(r.net.hostile, 2, "one before step 1, one during it");
        assert_eq!(r.report.live_agents, 2);
    }

    #[test]
    fn stop_on_the_control_plane_ends_the_run_as_requested() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 5), t0).unwrap();
        join(&mut s, range(0, 2), true);
        published(&s.next(t0));
        s.on_control(b"\x00garbage");
        s.on_control(&encode(&Control::Stop).unwrap());
        match s.next(t0) {
            Next::Finished { outcome: Ok(false), messages } => {
                let done = decode::<ReportMsg>(&messages[0].1).unwrap();
                assert_eq!(done, ReportMsg::Done { steps: 0, completed: false, requested: true });
                assert_eq!(messages[1].0, keys::ctl(RUN, "stop"));
            }
            other => panic!("expected the end, got {other:?}"),
        }
    }

    #[test]
    fn out_of_range_control_commands_are_rejected_counted_and_never_applied() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 3), t0).unwrap();
        let a = range(0, 2);
        join(&mut s, a, true);
        published(&s.next(t0));
        use geese_proto::Perturbation::*;
        for change in
            [AddObstacles { count: u32::MAX, radius: 10 }, SetIp(f64::NAN), SetGeneLoss(2.0), KillFraction(-0.5)]
        {
            s.on_control(&encode(&Control::Schedule { at_step: 1, change }).unwrap());
        }
        s.on_control(&encode(&Control::Schedule { at_step: u64::MAX, change: SetIp(0.5) }).unwrap());
        answer(&mut s, a, 1);
        assert_eq!(report(s.next(t0)).net.hostile, 5);
        published(&s.next(t0));
        assert_eq!(s.world().regime(), geese_proto::Regime::default(), "nothing applied");
        // The stop that follows is still obeyed.
        s.on_control(&encode(&Control::Stop).unwrap());
        assert!(matches!(s.next(t0), Next::Finished { outcome: Ok(false), .. }));
    }

    #[test]
    fn processes_leaving_after_the_end_change_nothing() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 1), t0).unwrap();
        let a = range(0, 2);
        join(&mut s, a, true);
        published(&s.next(t0));
        answer(&mut s, a, 1);
        report(s.next(t0));
        assert!(matches!(s.next(t0), Next::Finished { outcome: Ok(true), .. }));
        join(&mut s, a, false);
        assert_eq!(s.processes(), 1, "the last processes leaving are the end, not a departure");
        assert!(s.world().bodies().iter().all(|b| b.live));
    }

    #[test]
    fn scheduled_perturbations_apply_between_steps() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 3), t0).unwrap();
        let a = range(0, 2);
        join(&mut s, a, true);
        published(&s.next(t0));
        // Due right after step 1: taken between steps, in force from step 2.
        let change = geese_proto::Perturbation::SetLateralTransfer(false);
        s.on_control(&encode(&Control::Schedule { at_step: 1, change }).unwrap());
        answer(&mut s, a, 1);
        report(s.next(t0));
        assert!(s.world().regime().lateral_transfer);
        published(&s.next(t0));
        assert!(!s.world().regime().lateral_transfer, "applied at the start of step 2");
    }

    /// Issue 30.5: a control-plane switch to the task running at its step is refused
    /// and counted; one to the other task applies between steps, as in-process.
    #[test]
    fn a_control_plane_task_switch_applies_and_one_to_the_running_task_is_refused() {
        use geese_proto::{Perturbation::SwitchTask, Task};
        let t0 = Instant::now();
        let mut s = Server::new(spec(2, 3), t0).unwrap();
        let a = range(0, 2);
        join(&mut s, a, true);
        published(&s.next(t0));
        s.on_control(&encode(&Control::Schedule { at_step: 1, change: SwitchTask(Task::Foraging) }).unwrap());
        s.on_control(&encode(&Control::Schedule { at_step: 1, change: SwitchTask(Task::Nest) }).unwrap());
        s.on_control(&encode(&Control::Schedule { at_step: 2, change: SwitchTask(Task::Nest) }).unwrap());
        answer(&mut s, a, 1);
        report(s.next(t0));
        assert_eq!(s.world().task(), Task::Foraging);
        published(&s.next(t0));
        assert_eq!(s.world().task(), Task::Nest, "applied at the start of step 2");
        answer(&mut s, a, 2);
        assert_eq!(report(s.next(t0)).net.hostile, 2, "foraging at 1 and nest at 2 refused");
        assert_eq!(s.world().events().len(), 1);
    }

    #[test]
    fn intent_loss_is_seeded_and_counted() {
        let t0 = Instant::now();
        let mut sp = spec(20, 1);
        sp.loss.intent = 0.5;
        let run = |sp: NetRunSpec| {
            let mut s = Server::new(sp, t0).unwrap();
            join(&mut s, range(0, 20), true);
            published(&s.next(t0));
            answer(&mut s, range(0, 20), 1);
            report(s.next(t0)).net.intents_lost
        };
        let lost = run(sp.clone());
        assert!(lost > 0 && lost < 20, "{lost} of 20 lost at p = 0.5");
        assert_eq!(run(sp), lost);
    }

    #[test]
    fn the_locality_map_counts_the_agents_live_after_each_step_of_its_window() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(4, 3), t0).unwrap();
        s.record_locality("2:3".parse().unwrap());
        let (a, b) = (range(0, 2), range(2, 2));
        join(&mut s, a, true);
        join(&mut s, b, true);
        for step in 1..=2 {
            published(&s.next(t0));
            answer(&mut s, a, step);
            answer(&mut s, b, step);
            report(s.next(t0));
        }
        // Process b goes away after step 2: its agents die and count no more.
        join(&mut s, b, false);
        published(&s.next(t0));
        answer(&mut s, a, 3);
        report(s.next(t0));
        let l = s.world().locality().expect("counting");
        assert_eq!((l.steps(), l.agent_steps()), (2, 4 + 2));
        assert_eq!(l.counts().iter().map(|c| c.count).sum::<u64>(), 6);
    }

    #[test]
    fn run_info_tells_a_joining_process_the_next_step_and_every_body_cell() {
        let t0 = Instant::now();
        let mut s = Server::new(spec(3, 2), t0).unwrap();
        let info = s.run_info();
        assert_eq!((info.next_step, info.cells.len()), (1, 3));
        join(&mut s, range(0, 3), true);
        published(&s.next(t0));
        answer(&mut s, range(0, 3), 1);
        report(s.next(t0));
        assert_eq!(s.run_info().next_step, 2);
    }
}
