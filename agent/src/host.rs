//! An agent process's host of one or many agents, sans IO (DESIGN.md §2 steps 1–3).
//!
//! The `geese-agent` binary is a shell around a [`Host`]: it hands it what arrives
//! ([`Input`]) and carries out what [`Host::next`] returns ([`Next`]): publish the
//! process's gene bundle or intent batch, subscribe to or drop a cell's topics, or wait
//! for the next message until a deadline. Per step, after the world's [`Tick`] (which
//! says which cell every agent's centre is in):
//! 1. collect each own agent's cell percept, until every live agent is found or the
//!    percept deadline passes;
//! 2. `begin_step`, then publish the process's genes of each cell — every cell each
//!    agent's gene must reach ([`for_each_gene_cell`]: its own at GS ≥ 3, the cells of
//!    its 3×3 block where a live agent has its centre at GS 2), and only cells where
//!    an agent of another process has its centre (own cell-mates get them in memory) —
//!    as one [`GeneBundle`](geese_proto::net::GeneBundle) of per-cell batches,
//!    LZ4-packed, and wait, up to the gene deadline, for the world's batches of the
//!    cells with expected cell-mates of other processes;
//! 3. `finish_step` with the genes of the cell (the learner sorts candidates by id), and
//!    publish all intents as one [`IntentBatch`]. Received genes wait in an [`Inbox`].
//!
//! A hosting process (`wide`: it reads no cell topic, the world sends it its cells'
//! percepts in [`HostPercepts`] and the packs of the processes it shares cells with in
//! [`HostGenes`]) also sends, in its intent batch, the genes its agents will offer at
//! the next step ([`AHEAD_CELL`]); when every process did, the world puts the
//! other processes' packs into the next step's percepts and step 2 is skipped.
//!
//! A process that reads cells one by one subscribes, before publishing its intents, to
//! the cells its agents may be in next step (the current cell and the cells of their
//! move destinations): Zenoh delivers a session's declarations before its later
//! publications, and the world publishes the next percepts only after every intent, so
//! those subscriptions are in place in time. Hence [`Next::Act`] is an ordered list.
use crate::ge::Grammar;
use crate::inbox::{CellGenes, Inbox};
use crate::{GeneCache, GeneRef, Learner, LearnerConfig, Program};
use foldhash::fast::FixedState;
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{
    loss_draw, nest_sized, pack, unpack, GeneBatchCell, GeneBatchHead, GeneBatchRef, GeneBundle, HostCounters,
    HostGenes, HostPercepts, IntentBatch, Raw, RunInfo, Tick, AHEAD_CELL, LOSS_SALT_PERCEPT, NO_CELL,
};
use geese_proto::rules::{for_each_gene_cell, genes_spread};
use geese_proto::seed::{derive, Owner, Purpose};
use geese_proto::{decode, encode, encode_sized, AgentId, CodecError, GeneMsg, Geometry, Intent, Op, Percept};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Maps by cell or agent id looked up for every agent every step, hashed with foldhash
/// (SipHash showed in profiles of 10 x 100 agents).
type FastMap<K, V> = HashMap<K, V, FixedState>;

/// Cells stay subscribed this many steps after they were last a candidate (agents
/// often step back and forth across a cell border).
const KEEP_STEPS: u64 = 2;

/// Why a host could not be built or go on.
#[derive(Debug, thiserror::Error)]
pub enum HostError {
    #[error("agents {range} outside the run's {agents} agents")]
    Range { range: AgentRange, agents: u32 },
    #[error("run information from the world: {0}")]
    Learner(String),
    #[error("grammar {name}: {reason}")]
    Grammar { name: String, reason: String },
    #[error("encoding a message: {0}")]
    Codec(#[from] CodecError),
}

/// What arrives, as received.
#[derive(Debug, Clone, Copy)]
pub enum Input<'a> {
    /// The world's [`Tick`].
    Tick(&'a [u8]),
    /// A percept on the topic of cell `cell`.
    Percept { cell: u32, bytes: &'a [u8] },
    /// The world's batch of all genes of cell `cell`, on its topic.
    CellGenes { cell: u32, bytes: &'a [u8] },
    /// [`HostPercepts`] on this process's own key.
    HostPercepts(&'a [u8]),
    /// [`HostGenes`] on this process's own key.
    HostGenes(&'a [u8]),
    /// Something that was not what its key promised (counted as hostile).
    Hostile,
    /// A liveliness token appeared (`alive`) or went. Only the world's matters: the
    /// host stops when it goes.
    Presence { alive: bool, key: &'a str },
    /// The control plane's stop, or a signal.
    Stop,
}

/// One thing for the shell to do.
#[derive(Debug, Clone, PartialEq)]
pub enum Out {
    /// Publish a [`GeneBundle`] on `agent/<ids>/genes`.
    Genes(Vec<u8>),
    /// Publish an [`IntentBatch`] on `agent/<ids>/action`.
    Intents(Vec<u8>),
    /// Subscribe to the percept and gene topics of a cell.
    Subscribe(u32),
    /// Drop the subscriptions of a cell.
    Unsubscribe(u32),
}

/// What the shell does next.
#[derive(Debug)]
pub enum Next {
    /// Carry these out, in order, then call [`Host::next`] again.
    Act(Vec<Out>),
    /// Nothing to do until an input arrives, or until the instant, if any.
    Wait(Option<Instant>),
    /// The process is done (stop, or the world left).
    Stopped,
}

/// A step between its genes and its intents: what `begin_step` left for `finish_step`.
struct Pending {
    step: u64,
    own: usize,
    idle: Vec<AgentId>,
    active: Vec<(AgentId, u32)>,
    /// Each cell's own genes.
    local: FastMap<u32, Vec<GeneMsg>>,
    /// Which remote cell-mates each cell waits for.
    wait_for: FastMap<u32, Vec<AgentId>>,
    deadline: Instant,
    genes_sent: Instant,
}

/// The agents of one process and the protocol around them.
pub struct Host {
    range: AgentRange,
    info: RunInfo,
    geom: Geometry,
    wide: bool,
    learners: Vec<Learner>,
    /// Mapped genes of senders, shared by this process's learners.
    gene_cache: GeneCache,
    loss_streams: Vec<u64>,
    /// Subscribed cells and the last step for which each was a candidate.
    subs: HashMap<u32, u64>,
    /// Last completed step.
    done: u64,
    /// Own agents the world counts as live (from the latest tick), by index.
    live: Vec<bool>,
    /// Centre cell each own agent was last seen in (where to subscribe while unseen).
    last_cell: Vec<u32>,
    /// The step whose percepts are being collected (0: none) and until when.
    collecting: u64,
    collect_deadline: Option<Instant>,
    percepts: FastMap<u32, Percept>,
    /// Own agent → the cell whose percept shows its centre, this step.
    found: FastMap<AgentId, u32>,
    /// Genes received from other processes, for steps not yet finished.
    inbox: Inbox,
    /// (step, cell) of every gene aggregate received from the world.
    heard: HashSet<(u64, u32), FixedState>,
    /// Where received packs are unpacked (kept between messages).
    unpacked: Vec<u8>,
    /// The last step whose genes came with its percepts (sent ahead).
    ahead_step: u64,
    /// The cells of ours whose percepts list each agent of another process, for filing
    /// genes sent ahead (kept only for its buffers).
    sender_cells: SenderCells,
    counters: HostCounters,
    stop: bool,
    world_left: bool,
    bare_tick: Option<u64>,
    /// A tick came: check that the cells of own agents are subscribed.
    tick_seen: bool,
    pending: Option<Pending>,
    clock: PhaseClock,
}

/// Where a process's steps spend their wall time (reported at exit on the
/// `geese::flow` target at debug level): from the first percept of a step to its genes
/// sent, waiting for cell-mates' genes, deciding and sending intents, and from the
/// intents to the next step's first percept.
#[derive(Default)]
struct PhaseClock {
    first_percept: Option<Instant>,
    intents_sent: Option<Instant>,
    steps: u64,
    begin: Duration,
    gene_wait: Duration,
    finish: Duration,
    between: Duration,
}

impl PhaseClock {
    /// The first percept of a new step arrived.
    fn step_begins(&mut self, now: Instant) {
        if let Some(sent) = self.intents_sent.take() {
            self.between += now.saturating_duration_since(sent);
        }
        self.first_percept = Some(now);
    }
}

impl Host {
    /// The agents `range` of the run described by `info`; `wide`: read no cell topic
    /// (the world sends this process its cells' percepts and genes).
    pub fn new(range: AgentRange, info: RunInfo, wide: bool) -> Result<Self, HostError> {
        if range.last >= info.spec.agents {
            return Err(HostError::Range { range, agents: info.spec.agents });
        }
        geese_proto::limits::check_unit("loss.percept", info.spec.loss.percept)
            .map_err(|e| HostError::Learner(e.to_string()))?;
        if info.cells.len() > info.spec.agents as usize {
            return Err(HostError::Learner(format!(
                "run info lists {} cells for {} agents",
                info.cells.len(),
                info.spec.agents
            )));
        }
        let geom = info.geometry;
        let mut learners = Vec::new();
        let mut loss_streams = Vec::new();
        if !info.spec.bare {
            let cfg: LearnerConfig =
                serde_json::from_str(&info.spec.learner_json).map_err(|e| HostError::Learner(e.to_string()))?;
            cfg.validate().map_err(|e| HostError::Learner(e.to_string()))?;
            let grammar = Grammar::parse(&info.spec.grammar_text)
                .map_err(|e| HostError::Grammar { name: info.spec.grammar_name.clone(), reason: e.to_string() })?;
            let (cfg, grammar) = (Arc::new(cfg), Arc::new(grammar));
            let program: Program = serde_json::from_str(&info.spec.program_json)
                .map_err(|e| HostError::Learner(format!("program: {e}")))?;
            let task = serde_json::from_str::<serde_json::Value>(&info.spec.world_json)
                .ok()
                .and_then(|w| w.get("task").and_then(|t| t.as_str()).map(str::to_string))
                .unwrap_or_else(|| "foraging".into());
            // A run whose task changes holds both tasks' objects (as the orchestrator's
            // `RunConfig::program_task`).
            let switches =
                info.spec.perturbations.iter().any(|(_, p)| matches!(p, geese_proto::Perturbation::SwitchTask(_)));
            let task = if switches { "union".to_string() } else { task };
            let prepared = program.prepare(&task).map_err(|e| HostError::Learner(e.to_string()))?;
            for id in range.ids() {
                let role = prepared.role(id, info.spec.seed);
                let l = Learner::with_role(id, cfg.clone(), grammar.clone(), geom, info.hub, info.spec.seed, role)
                    .map_err(|e| HostError::Learner(format!("agent {id}: {e}")))?;
                learners.push(l);
                loss_streams.push(derive(info.spec.seed, Owner::Agent(id), Purpose::Loss) ^ LOSS_SALT_PERCEPT);
            }
        }
        let last_cell = range.ids().map(|id| info.cells.get(id as usize).copied().unwrap_or(NO_CELL)).collect();
        Ok(Host {
            range,
            done: info.next_step.saturating_sub(1),
            live: vec![false; range.len() as usize],
            last_cell,
            geom,
            wide,
            info,
            learners,
            gene_cache: GeneCache::new(),
            loss_streams,
            subs: HashMap::new(),
            collecting: 0,
            collect_deadline: None,
            percepts: FastMap::default(),
            found: FastMap::default(),
            inbox: Inbox::default(),
            heard: HashSet::default(),
            unpacked: Vec::new(),
            ahead_step: 0,
            sender_cells: SenderCells::default(),
            counters: HostCounters::default(),
            stop: false,
            world_left: false,
            bare_tick: None,
            tick_seen: false,
            pending: None,
            clock: PhaseClock::default(),
        })
    }

    /// This process's agents as population members, in agent order.
    pub fn members(&self) -> Vec<crate::program::Member> {
        self.learners.iter().map(Learner::member).collect()
    }

    /// The live viewer's detail of agent `id`, if this process hosts it.
    pub fn detail(&self, id: AgentId) -> Option<geese_proto::view::AgentDetail> {
        let i = id.checked_sub(self.range.first)? as usize;
        self.learners.get(i).map(Learner::detail)
    }

    /// The agents this process speaks for.
    pub fn range(&self) -> AgentRange {
        self.range
    }

    /// Whether the process reads no cell topic (see [`Host::new`]).
    pub fn wide(&self) -> bool {
        self.wide
    }

    /// The last step this process completed.
    pub fn done(&self) -> u64 {
        self.done
    }

    /// Whether the process stopped.
    pub fn stopped(&self) -> bool {
        self.stop
    }

    /// Did it stop because the world's presence token went (the world ended, or the
    /// link to it was lost), rather than on a stop command or a signal?
    pub fn world_left(&self) -> bool {
        self.world_left
    }

    /// The cells subscribed now (a process reading cells one by one).
    pub fn subscribed(&self) -> Vec<u32> {
        let mut v: Vec<u32> = self.subs.keys().copied().collect();
        v.sort_unstable();
        v
    }

    fn bare(&self) -> bool {
        self.info.spec.bare
    }

    fn idx(&self, id: AgentId) -> usize {
        (id - self.range.first) as usize
    }

    /// This step's deadlines: longer until the process has finished its first step.
    fn deadlines(&self) -> geese_proto::net::Deadlines {
        self.info.spec.deadlines.of_step(self.done == 0)
    }

    /// The subscriptions a process reading cells one by one starts with.
    pub fn start(&mut self) -> Vec<Out> {
        let mut out = Vec::new();
        if !self.wide && !self.bare() {
            self.want_own_cells(&mut out);
        }
        out
    }

    /// The cell of every own agent, dead or alive: a restarted agent's body is revived
    /// where it stands, and the percept that shows it live may come before the tick that
    /// says so (a process that dropped the cell then stayed deaf to it for good).
    fn own_cells(&self) -> Vec<u32> {
        self.last_cell.iter().copied().filter(|&c| c != NO_CELL).collect()
    }

    /// Make sure the cell of every own agent is subscribed for the next step.
    fn want_own_cells(&mut self, out: &mut Vec<Out>) {
        for c in self.own_cells() {
            self.want(c, self.done + 1, out);
        }
    }

    /// Make sure cell `cell` is subscribed and keep it for step `step`.
    fn want(&mut self, cell: u32, step: u64, out: &mut Vec<Out>) {
        match self.subs.get_mut(&cell) {
            Some(w) => *w = (*w).max(step),
            None => {
                self.subs.insert(cell, step);
                out.push(Out::Subscribe(cell));
            }
        }
    }

    /// Every own live agent has been seen in a percept of the step being collected.
    fn all_found(&self) -> bool {
        self.range.ids().all(|id| !self.live[self.idx(id)] || self.found.contains_key(&id))
    }

    /// Advance as far as possible at time `now`.
    pub fn next(&mut self, now: Instant) -> Next {
        if self.stop {
            return Next::Stopped;
        }
        if let Some(t) = self.bare_tick.take() {
            let r = self.bare_step(t);
            return self.result(r);
        }
        if let Some(p) = &self.pending {
            let (step, deadline) = (p.step, p.deadline);
            if self.genes_complete() {
                let r = self.finish(now, Vec::new());
                return self.result(r);
            }
            if now >= deadline {
                self.counters.deadline_hits += 1;
                let late = self.pending.as_ref().map_or(0, |p| {
                    p.wait_for
                        .iter()
                        .filter(|(&c, _)| !self.heard.contains(&(step, c)))
                        .map(|(_, mates)| mates.len() as u32)
                        .sum::<u32>()
                });
                tracing::warn!(
                    "agents {}: step {step}: {late} cell-mates' genes missing at the gene deadline ({} ms)",
                    self.range,
                    self.deadlines().gene_ms
                );
                self.counters.genes_late += late;
                let r = self.finish(now, Vec::new());
                return self.result(r);
            }
            return Next::Wait(Some(deadline));
        }
        let mut out = Vec::new();
        if std::mem::take(&mut self.tick_seen) && !self.wide && !self.bare() {
            // Wherever the world now says our agents are, listen there.
            self.want_own_cells(&mut out);
        }
        if self.collecting > self.done {
            let expired = self.collect_deadline.is_some_and(|d| now >= d);
            if expired {
                self.counters.deadline_hits += 1;
            }
            if expired && !self.all_found() {
                tracing::warn!(
                    "agents {}: step {}: percepts missing at the percept deadline ({} ms)",
                    self.range,
                    self.collecting,
                    self.deadlines().percept_ms
                );
            }
            if self.all_found() || expired {
                let r = self.begin(now, out);
                return self.result(r);
            }
        }
        if out.is_empty() {
            Next::Wait(self.collect_deadline)
        } else {
            Next::Act(out)
        }
    }

    fn result(&mut self, r: Result<Vec<Out>, HostError>) -> Next {
        match r {
            Ok(out) => Next::Act(out),
            Err(e) => {
                // Only our own messages are encoded here; failing to is a bug, not input.
                tracing::error!("agents {}: {e}; stopping", self.range);
                self.stop = true;
                Next::Stopped
            }
        }
    }

    /// File what arrived.
    pub fn absorb(&mut self, input: Input, now: Instant) {
        tracing::trace!(target: "geese::flow", "agents {}: {input:?} (done {}, collecting {})", self.range, self.done, self.collecting);
        match input {
            Input::Tick(bytes) => match decode::<Tick>(bytes) {
                Ok(t) if self.bare() => {
                    if t.step > self.done {
                        self.bare_tick = Some(t.step);
                    }
                }
                Ok(t) if t.cells.len() == self.info.spec.agents as usize => {
                    // The live set from step t on (ticks precede that step's percepts).
                    for id in self.range.ids() {
                        let k = self.idx(id);
                        let c = t.cells[id as usize];
                        self.live[k] = c != NO_CELL;
                        if c != NO_CELL {
                            self.last_cell[k] = c;
                        }
                    }
                    self.tick_seen = true;
                }
                _ => self.counters.hostile += 1,
            },
            Input::Percept { cell, bytes } => match decode::<Percept>(bytes) {
                Ok(p) if p.cell == cell => self.take_percept(p, now),
                _ => self.counters.hostile += 1,
            },
            Input::HostPercepts(bytes) => match decode::<HostPercepts>(bytes) {
                Ok(b) => {
                    let percepts: Vec<Percept> = self.open_each(&b.percepts);
                    for p in self.only_valid(percepts, |p| p.step == b.step) {
                        self.take_percept(p, now);
                    }
                    if let Some(packs) = &b.genes {
                        if b.step == self.collecting && b.step > self.done {
                            self.take_ahead(b.step, packs);
                        }
                    }
                }
                Err(_) => self.counters.hostile += 1,
            },
            Input::CellGenes { cell, bytes } => match decode::<GeneBatchHead>(bytes) {
                // A cell's own topic carries its whole aggregate: the cell is complete.
                Ok(b) if b.cell == cell => {
                    if b.step > self.done {
                        self.heard.insert((b.step, cell));
                    }
                    self.take_genes(b)
                }
                _ => self.counters.hostile += 1,
            },
            Input::HostGenes(bytes) => match decode::<HostGenes>(bytes) {
                Ok(b) => self.take_host_genes(b),
                Err(_) => self.counters.hostile += 1,
            },
            Input::Hostile => self.counters.hostile += 1,
            Input::Presence { alive, key } => match keys::parse(&self.info.spec.run, key) {
                Parsed::WorldPresence if !alive => {
                    tracing::info!("agents {}: the world left", self.range);
                    self.stop = true;
                    self.world_left = true;
                }
                _ => {}
            },
            Input::Stop => self.stop = true,
        }
    }

    fn take_host_genes(&mut self, b: HostGenes) {
        // The cells listed are complete, whether or not a batch came with them.
        if b.step > self.done {
            for &c in &b.cells {
                if (c as usize) < self.geom.cell_count() {
                    self.heard.insert((b.step, c));
                } else {
                    self.counters.hostile += 1;
                }
            }
        }
        // Packs come as they reach the world, before their cells are complete. Only
        // batches of cells our agents are in (the cells whose percepts the step brought,
        // first, from the same session) are decoded.
        let filter = self.collecting == b.step;
        let mut scratch = std::mem::take(&mut self.unpacked);
        for p in &b.packs {
            match unpack(p.0, &mut scratch) {
                Ok(mut nested) => {
                    if filter {
                        // Batches that do not peek well are decoded, and counted.
                        nested.retain(|r| {
                            r.open::<GeneBatchCell>()
                                .map_or(true, |h| h.step != b.step || self.percepts.contains_key(&h.cell))
                        });
                    }
                    let batches = self.open_each(&nested);
                    for g in self.only_valid(batches, |g: &GeneBatchHead| g.step == b.step) {
                        self.take_genes(g);
                    }
                }
                Err(_) => self.counters.hostile += 1,
            }
        }
        self.unpacked = scratch;
    }

    /// Open the nested messages of a message from the world; one that does not open is
    /// hostile.
    fn open_each<'a, T: serde::Deserialize<'a>>(&mut self, nested: &[Raw<'a>]) -> Vec<T> {
        let mut out = Vec::with_capacity(nested.len());
        for b in nested {
            match b.open::<T>() {
                Ok(v) => out.push(v),
                Err(_) => self.counters.hostile += 1,
            }
        }
        out
    }

    /// The items of a bundle that belong to the bundle's step (`same_step`) and name a
    /// cell of the arena; the others are counted as hostile.
    fn only_valid<T: Cell>(&mut self, items: Vec<T>, same_step: impl Fn(&T) -> bool) -> Vec<T> {
        let cells = self.geom.cell_count();
        let before = items.len();
        let kept: Vec<T> = items.into_iter().filter(|i| same_step(i) && (i.cell() as usize) < cells).collect();
        self.counters.hostile += (before - kept.len()) as u32;
        kept
    }

    /// File the percept of one cell (from its own message or a bundle).
    fn take_percept(&mut self, p: Percept, now: Instant) {
        if p.step <= self.done || p.step < self.collecting {
            return; // stale
        }
        if self.pending.as_ref().is_some_and(|q| p.step > q.step) {
            // The world went on without our intents (its deadline passed): this step is
            // finished first; its agents idle in the one it skipped to.
            tracing::debug!(
                "agents {}: percept of step {} while finishing step {}",
                self.range,
                p.step,
                self.collecting
            );
            return;
        }
        if p.step > self.collecting {
            tracing::trace!(target: "geese::flow", "agents {}: collecting step {}", self.range, p.step);
            self.clock.step_begins(now);
            self.collecting = p.step;
            self.percepts.clear();
            self.found.clear();
            self.collect_deadline = Some(now + Duration::from_millis(self.deadlines().percept_ms as u64));
        }
        let cell = p.cell;
        for a in &p.agents {
            if self.range.contains(a.id) && a.live && self.geom.cell_of(a.pos) == cell {
                self.found.insert(a.id, cell);
            }
        }
        self.percepts.insert(cell, p);
    }

    /// File the genes of step `step` that came with its percepts: the other processes'
    /// packs, each of one batch sent ahead ([`AHEAD_CELL`]). A gene goes to every cell
    /// of ours whose percept of this step lists its sender: the cells it is registered
    /// in (at GS ≥ 3 the cell of its centre; at GS 2 up to nine), as its mates there
    /// expect it. The others are skipped unread.
    fn take_ahead(&mut self, step: u64, packs: &[Raw]) {
        self.ahead_step = step;
        self.sender_cells.build(self.range, self.info.spec.agents as usize, &self.percepts);
        let mut scratch = std::mem::take(&mut self.unpacked);
        for p in packs {
            let Ok(nested) = unpack(p.0, &mut scratch) else {
                self.counters.hostile += 1;
                continue;
            };
            for raw in nested {
                let cells = &self.sender_cells;
                let cells_of = |from: AgentId| cells.of(from).iter().copied();
                let filed = match raw.open::<GeneBatchHead>() {
                    Ok(b) if b.step == step && b.cell == AHEAD_CELL => self.inbox.file_by_sender(&b, cells_of),
                    _ => false,
                };
                if !filed {
                    self.counters.hostile += 1;
                }
            }
        }
        self.unpacked = scratch;
    }

    /// File a batch of genes of one cell (the cell's aggregate, or one process's batch
    /// of it; whether the cell is complete is said apart).
    fn take_genes(&mut self, b: GeneBatchHead) {
        if b.step > self.done && !self.inbox.file(&b) {
            self.counters.hostile += 1;
        }
    }

    /// The genes of every cell the pending step waits for are in.
    ///
    /// Only the world says a cell is complete, also when a cell-mate's process left
    /// (its hub forgets the process and releases the cell): the world decides who is in
    /// a step, and this process's own view of the liveliness tokens may lag behind it.
    /// Across routers a step-1 percept can arrive before the token of a process the
    /// world already counted; taking that process for gone lost its genes (a
    /// three-host run once differed from the in-process run at step 1 this way).
    fn genes_complete(&self) -> bool {
        let Some(p) = &self.pending else { return true };
        p.wait_for.keys().all(|&c| self.heard.contains(&(p.step, c)))
    }

    /// The cells where a live agent has its centre by this step's percepts, each with
    /// whether an agent of another process is centred there. Exact for every cell near
    /// an own agent: a percept lists every agent registered in its cell, that is every
    /// agent centred in a cell of the block around it (GS 2).
    fn centres(&self) -> FastMap<u32, bool> {
        let mut centres: FastMap<u32, bool> = FastMap::default();
        for p in self.percepts.values() {
            for a in p.agents.iter().filter(|a| a.live) {
                *centres.entry(self.geom.cell_of(a.pos)).or_default() |= !self.range.contains(a.id);
            }
        }
        centres
    }

    /// Publish gene batches (nested) of step `step` as one packed [`GeneBundle`].
    fn bundle(step: u64, batches: &[Raw<'_>]) -> Result<Out, HostError> {
        let packed = pack(batches)?;
        let bytes = encode_sized(&GeneBundle { step, packed: Raw(&packed) }, packed.len() + 16)?;
        Ok(Out::Genes(bytes))
    }

    /// The genes our agents offer at step `step`, packed to go ahead ([`AHEAD_CELL`],
    /// in the intent batch of `step − 1`): each agent's gene as it stands, except those
    /// of agents whose percept of that step the injected loss will drop (they take no
    /// part in it). The world files them and sends them on with the percepts of `step`.
    fn ahead(&self, step: u64) -> Result<Vec<u8>, HostError> {
        let p_loss = self.info.spec.loss.percept;
        let genes: Vec<GeneMsg> = (0..self.learners.len())
            .filter(|&k| p_loss <= 0.0 || loss_draw(self.loss_streams[k], step, 0) >= p_loss)
            .map(|k| self.learners[k].offer(step))
            .collect();
        let batch = GeneBatchRef { step, cell: AHEAD_CELL, genes: &genes, absent: &[] };
        let nested = nest_sized(&batch, batch.size_hint())?;
        Ok(pack(&[Raw(&nested)])?)
    }

    fn bare_step(&mut self, step: u64) -> Result<Vec<Out>, HostError> {
        let batch = IntentBatch {
            step,
            intents: Vec::new(),
            idle: self.range.ids().collect(),
            counters: std::mem::take(&mut self.counters),
            ahead: None,
        };
        self.done = step;
        Ok(vec![Out::Intents(encode(&batch)?)])
    }

    /// Steps 1–2 of the step being collected: begin every agent, publish the genes of
    /// shared cells, and wait for cell-mates' genes — or finish at once when none are
    /// awaited.
    fn begin(&mut self, now: Instant, mut out: Vec<Out>) -> Result<Vec<Out>, HostError> {
        let t = self.collecting;
        let own: Vec<AgentId> = self.range.ids().filter(|&id| self.live[self.idx(id)]).collect();
        let p_loss = self.info.spec.loss.percept;
        let mut idle: Vec<AgentId> = Vec::new();
        let mut active: Vec<(AgentId, u32)> = Vec::new();
        // Each cell's own genes (and own agents that offer none), in every cell each
        // agent's gene must reach (`rules::for_each_gene_cell`): at GS ≥ 3 the cell of
        // its centre; at GS 2 every cell of its 3×3 block where a live agent has its
        // centre, which our percepts tell (`centres`).
        let mut local: FastMap<u32, Vec<GeneMsg>> = FastMap::default();
        let mut absent: FastMap<u32, Vec<AgentId>> = FastMap::default();
        let spread = genes_spread(&self.geom);
        let centres = if spread { self.centres() } else { FastMap::default() };
        let mut to: Vec<u32> = Vec::new();
        for &id in &own {
            let k = self.idx(id);
            let Some(&c) = self.found.get(&id) else {
                // Its percept never came: it idles (its mates do not know it is there).
                self.counters.percepts_missing += 1;
                idle.push(id);
                continue;
            };
            self.last_cell[k] = c;
            let Some(percept) = self.percepts.get(&c) else {
                continue;
            };
            to.clear();
            match percept.agents.binary_search_by_key(&id, |a| a.id) {
                Ok(i) => {
                    for_each_gene_cell(&self.geom, percept.agents[i].pos, |d| centres.contains_key(&d), |d| to.push(d))
                }
                Err(_) => to.push(c),
            }
            if p_loss > 0.0 && loss_draw(self.loss_streams[k], t, 0) < p_loss {
                self.counters.percepts_lost += 1;
                idle.push(id);
                for &d in &to {
                    absent.entry(d).or_default().push(id);
                }
                continue;
            }
            if let Some(g) = self.learners[k].begin_step(percept) {
                if let Some((&last, rest)) = to.split_last() {
                    for &d in rest {
                        local.entry(d).or_default().push(g.clone());
                    }
                    local.entry(last).or_default().push(g);
                }
            } else {
                tracing::trace!(target: "geese::flow", "agents {}: step {t}: agent {id} offers no gene", self.range);
            }
            active.push((id, c));
        }
        // The other processes' genes came with the percepts (sent ahead), and ours went
        // ahead too: nothing to publish or wait for.
        let ahead = self.ahead_step == t;
        // Publish our genes in cells where an agent of another process has its centre.
        let mut out_cells: Vec<u32> =
            if ahead { Vec::new() } else { local.keys().chain(absent.keys()).copied().collect() };
        out_cells.sort_unstable();
        out_cells.dedup();
        let mut nested = Vec::new();
        for c in out_cells {
            let outsiders = if spread {
                centres.get(&c).is_some_and(|&outsider| outsider)
            } else {
                self.percepts.get(&c).is_some_and(|p| {
                    p.agents.iter().any(|a| a.live && !self.range.contains(a.id) && self.geom.cell_of(a.pos) == c)
                })
            };
            if !outsiders {
                continue;
            }
            let batch = GeneBatchRef {
                step: t,
                cell: c,
                genes: local.get(&c).map_or(&[], |v| v.as_slice()),
                absent: absent.get(&c).map_or(&[], |v| v.as_slice()),
            };
            nested.push(nest_sized(&batch, batch.size_hint())?);
        }
        // All of them in one message, packed: the world files each batch as its cell's,
        // and forwards the pack as it is.
        if !nested.is_empty() {
            let batches: Vec<Raw> = nested.iter().map(|b| Raw(b)).collect();
            out.push(Self::bundle(t, &batches)?);
        }
        if let Some(f) = self.clock.first_percept {
            self.clock.begin += now.saturating_duration_since(f);
        }
        // Which remote cell-mates each cell waits for: expected mates of another process
        // (registered in the cell: their processes publish their genes in it, wherever
        // their centres are). Every own agent in a cell expects the same remote mates
        // (its list differs from another own agent's only by own ids), so one agent's
        // list per cell will do.
        let mut wait_for: FastMap<u32, Vec<AgentId>> = FastMap::default();
        let range = self.range;
        for &(id, c) in active.iter().filter(|_| !ahead) {
            if wait_for.contains_key(&c) {
                continue;
            }
            let Some(p) = self.percepts.get(&c) else {
                continue;
            };
            let mut remote: Vec<AgentId> = p.agents.iter().filter(|a| !range.contains(a.id)).map(|a| a.id).collect();
            remote.sort_unstable();
            let mates: Vec<AgentId> = self.learners[self.idx(id)]
                .expected_mates()
                .iter()
                .copied()
                .filter(|m| remote.binary_search(m).is_ok())
                .collect();
            wait_for.insert(c, mates);
        }
        wait_for.retain(|_, mates| !mates.is_empty());
        let deadline = now + Duration::from_millis(self.deadlines().gene_ms as u64);
        self.pending =
            Some(Pending { step: t, own: own.len(), idle, active, local, wait_for, deadline, genes_sent: now });
        if self.genes_complete() {
            return self.finish(now, out);
        }
        Ok(out)
    }

    /// Step 3: finish every active agent with its cell's genes, and publish the intents
    /// (after the subscriptions for the next step) with the genes sent ahead.
    fn finish(&mut self, now: Instant, mut out: Vec<Out>) -> Result<Vec<Out>, HostError> {
        let Some(p) = self.pending.take() else { return Ok(out) };
        let t = p.step;
        self.clock.gene_wait += now.saturating_duration_since(p.genes_sent);
        let mut intents: Vec<Intent> = Vec::with_capacity(p.active.len());
        // Each cell's genes: our own, then the others' as they arrived, lent from the
        // inbox; in sender order once per cell, so that each learner's own check finds
        // them sorted.
        let range = self.range;
        let mut lent = Vec::with_capacity(self.inbox.len() + p.own);
        for (&c, genes) in &p.local {
            lent.extend(genes.iter().map(|g| (c, GeneRef::of(g))));
        }
        self.inbox.lend(t, |from| range.contains(from), &mut lent);
        let cell_genes = CellGenes::new(lent);
        for &(id, c) in &p.active {
            let k = (id - range.first) as usize;
            intents.push(self.learners[k].finish_step(cell_genes.of(c), &mut self.gene_cache));
        }
        drop(cell_genes);
        // Subscriptions for step t+1: where each agent is, and where its moves lead.
        if !self.wide {
            let mut next = self.own_cells();
            for i in &intents {
                for op in &i.ops {
                    if let Op::Move { to, .. } = op {
                        next.push(self.geom.cell_of(*to));
                    }
                }
            }
            next.sort_unstable();
            next.dedup();
            for c in next {
                self.want(c, t + 1, &mut out);
            }
            let mut dropped: Vec<u32> =
                self.subs.iter().filter(|(_, &w)| w + KEEP_STEPS <= t).map(|(&c, _)| c).collect();
            dropped.sort_unstable();
            for c in dropped {
                self.subs.remove(&c);
                out.push(Out::Unsubscribe(c));
            }
        }
        // Our genes for the next step go with the intents that let the world start it
        // (not while lateral transfer is off: if it comes on at the next step, that
        // step's genes go through the world during the step).
        let lateral = self.percepts.values().next().is_some_and(|p| p.regime.lateral_transfer);
        let ahead = if self.wide && lateral && t < self.info.spec.steps { Some(self.ahead(t + 1)?) } else { None };
        let batch = IntentBatch { step: t, intents, idle: p.idle, counters: std::mem::take(&mut self.counters), ahead };
        tracing::trace!(target: "geese::flow", "agents {}: intents of step {t}", self.range);
        out.push(Out::Intents(encode(&batch)?));
        let end = Instant::now();
        self.clock.finish += end.saturating_duration_since(now);
        self.clock.intents_sent = Some(end);
        self.clock.steps += 1;
        self.done = t;
        self.collect_deadline = None;
        self.percepts.clear();
        self.found.clear();
        self.inbox.retire(t);
        self.heard.retain(|&(s, _)| s > t);
        Ok(out)
    }

    /// Say where the steps spent their wall time (`geese::flow` target, debug level).
    pub fn report_phases(&self) {
        let c = &self.clock;
        let ms = |d: Duration| d.as_secs_f64() * 1e3 / c.steps.max(1) as f64;
        tracing::debug!(
            target: "geese::flow",
            "agents {}: {} steps; per step {:.3} ms percepts->genes sent, {:.3} ms gene wait, {:.3} ms finish+intents, {:.3} ms intents->next percept",
            self.range, c.steps, ms(c.begin), ms(c.gene_wait), ms(c.finish), ms(c.between)
        );
    }
}

/// For each agent of another process, the cells of ours whose percepts list it (it is
/// registered there), by agent id: the cells of agent `i` are `cells[at[i]..at[i + 1]]`.
#[derive(Default)]
struct SenderCells {
    at: Vec<u32>,
    cells: Vec<u32>,
}

impl SenderCells {
    /// From this step's percepts, for a run of `agents` agents (ids beyond it are
    /// left out), leaving out `own`.
    fn build(&mut self, own: AgentRange, agents: usize, percepts: &FastMap<u32, Percept>) {
        let listed = || {
            percepts.iter().flat_map(|(&c, p)| {
                p.agents.iter().filter(|a| !own.contains(a.id) && (a.id as usize) < agents).map(move |a| (a.id, c))
            })
        };
        // Counts, then their running sums (`at[i]`: the end of agent i's cells), then
        // filled back to front (`at[i]`: the start).
        self.at.clear();
        self.at.resize(agents + 1, 0);
        for (id, _) in listed() {
            self.at[id as usize] += 1;
        }
        for i in 1..self.at.len() {
            self.at[i] += self.at[i - 1];
        }
        self.cells.clear();
        self.cells.resize(self.at[agents] as usize, NO_CELL);
        for (id, c) in listed() {
            let i = id as usize;
            self.at[i] -= 1;
            self.cells[self.at[i] as usize] = c;
        }
    }

    /// The cells of agent `id` (none if it is listed nowhere).
    fn of(&self, id: AgentId) -> &[u32] {
        let i = id as usize;
        match (self.at.get(i), self.at.get(i + 1)) {
            (Some(&a), Some(&b)) => &self.cells[a as usize..b as usize],
            _ => &[],
        }
    }
}

/// A message about one cell.
trait Cell {
    fn cell(&self) -> u32;
}
impl Cell for Percept {
    fn cell(&self) -> u32 {
        self.cell
    }
}
impl Cell for GeneBatchHead<'_> {
    fn cell(&self) -> u32 {
        self.cell
    }
}
