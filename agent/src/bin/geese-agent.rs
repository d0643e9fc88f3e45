//! `geese-agent`: one agent, or `--agents K` agents hosted on one shared session, in one
//! process of a distributed GEESE run (DESIGN.md §2–4).
//!
//! A thin async shell around the synchronous [`Learner`]s. Per step, after the world's
//! [`Tick`] (which says which cell every agent's centre is in):
//! 1. read each own agent's cell percept (subscribed in advance, see below);
//! 2. `begin_step`, then publish the process's genes of each cell — only of cells where
//!    an agent of another process is (own cell-mates get them in memory) — as one
//!    [`GeneBundle`] of per-cell [`GeneBatch`](geese_proto::net::GeneBatch)es, LZ4-packed, on `agent/<ids>/genes`, and wait, up to
//!    the gene deadline, for the world's batches of the cells with expected cell-mates
//!    of other processes;
//! 3. `finish_step` with the genes of the cell (the learner sorts candidates by id), and
//!    publish all intents as one [`IntentBatch`] on `agent/<ids>/action`. Received
//!    genes wait in an [`Inbox`] (one buffer for every genome of the step), which lends
//!    them to the learners cell by cell ([`CellGenes`]).
//!
//! A hosting process (below) also publishes, just before its intents, the genes its
//! agents will offer at the next step: one [`AHEAD_CELL`] batch, packed, on
//! `agent/<ids>/genes` (an agent's gene of step t+1 is the one it holds when step t
//! ends). When every process did, the world says so in the next step's
//! [`HostPercepts`] and puts the other processes' packs in it; step 2 is then skipped:
//! the process files each received gene under the cell its sender's centre is in by
//! the percepts, and neither publishes nor waits for genes during the step.
//!
//! Before publishing its intents the process subscribes to the percept and gene topics
//! of every cell its agents may be in next step (the current cell and the cells of their
//! move destinations); Zenoh delivers a session's declarations before its later
//! publications, and the world publishes the next percepts only after every intent, so
//! those subscriptions are in place in time. A process hosting many agents reads no cell
//! topic (`--subscribe all`, the default when it hosts at least a quarter as many agents
//! as there are cells): the world sends it messages on keys of its own — the percepts of
//! its agents' cells ([`HostPercepts`]), and the packs of the other processes it shares
//! cells with as they arrive, then which cells are complete ([`HostGenes`]) — rather than a message
//! per cell (with 1,000 agents in 10 processes, Zenoh's cost per message bounded the step
//! rate) or every cell's (decoding all of them was most of the remaining overhead).
//!
//! The process learns everything else (configuration, grammar, seed, where its agents
//! are) from the world's `ctl/info` queryable, so agents on another host need nothing
//! but `--run` and a way to reach the router. It exits when the world's liveliness
//! token disappears, on the control plane's stop, or on SIGINT/SIGTERM.
use anyhow::{bail, Context, Result};
use clap::{Parser, ValueEnum};
use foldhash::fast::FixedState;
use geese_agent::ge::Grammar;
use geese_agent::inbox::{CellGenes, Inbox};
use geese_agent::{GeneCache, GeneRef, Learner, LearnerConfig};
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{
    loss_draw, nest_sized, pack, unpack, GeneBatchCell, GeneBatchHead, GeneBatchRef, GeneBundle, HostCounters,
    HostGenes, HostPercepts, IntentBatch, Raw, RunInfo, Tick, AHEAD_CELL, LOSS_SALT_PERCEPT, NO_CELL,
};
use geese_proto::seed::{derive, Owner, Purpose};
use geese_proto::zenoh_bus::{self, CommonArgs, Role};
use geese_proto::{decode, encode, encode_sized, AgentId, Control, GeneMsg, Geometry, Intent, Op, Percept};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};
use zenoh::bytes::ZBytes;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;
use zenoh::Session;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum SubscribeArg {
    /// `all` when hosting at least a quarter as many agents as there are cells, else `cells`.
    Auto,
    /// Only the cells the process's agents are in or may move into.
    Cells,
    /// No cell topic: the world sends the process its cells' percepts and genes.
    All,
}

#[derive(Parser)]
#[command(name = "geese-agent", version, about = "GEESE agent process (Zenoh): one or many agents")]
struct Args {
    #[command(flatten)]
    zenoh: CommonArgs,
    /// Run name (the `<run>` of every key).
    #[arg(long, default_value = "geese")]
    run: String,
    /// Id of the (first) agent of this process.
    #[arg(long, default_value_t = 0)]
    id: u32,
    /// Number of agents hosted by this process (ids id..id+K).
    #[arg(long, default_value_t = 1)]
    agents: u32,
    /// How to subscribe to cell topics.
    #[arg(long, value_enum, default_value = "auto")]
    subscribe: SubscribeArg,
    /// Give up if the world has not answered within this many milliseconds.
    #[arg(long, default_value_t = 60_000)]
    join_timeout_ms: u64,
    /// Tokio worker threads.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Run the agents on a runtime of their own rather than on Zenoh's (diagnosis).
    #[arg(long)]
    separate_runtime: bool,
}

enum Event {
    Tick(Vec<u8>),
    Percept {
        cell: u32,
        bytes: Vec<u8>,
    },
    /// The world's batch of all genes of a cell.
    Genes {
        cell: u32,
        bytes: Vec<u8>,
    },
    /// The percepts of the cells of our agents ([`HostPercepts`]), as received (not
    /// copied: these are the large messages).
    Percepts(ZBytes),
    /// The other processes' batches of our shared cells ([`HostGenes`]).
    HostGenes(ZBytes),
    Hostile,
    Presence {
        alive: bool,
        key: String,
    },
    Stop,
}

/// mimalloc: the step loop allocates many small, short-lived buffers.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> Result<()> {
    // Without RUST_LOG: warnings, but not Zenoh's report of data that arrives for a cell
    // subscription just undeclared (harmless: the cell is no longer needed).
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn,zenoh::api::session=off"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    let args = Args::parse();
    if !keys::valid_run_name(&args.run) {
        bail!("--run {:?}: one key chunk of letters, digits, '_', '-', '.'", args.run);
    }
    let Some(range) = AgentRange::new(args.id, args.agents) else {
        bail!("--agents must be at least 1 and the ids must fit in 32 bits");
    };
    // Before any thread exists: size Zenoh's internal pools for many processes.
    zenoh_bus::lean_runtime_unless_set();
    let rt = zenoh_bus::runtime(args.threads)?;
    rt.block_on(host_main(args, range))
}

async fn host_main(args: Args, range: AgentRange) -> Result<()> {
    let session = zenoh_bus::open(&args.zenoh, Role::Client).await?;
    let run = args.run.clone();
    let (tx, mut rx) = unbounded_channel::<Event>();
    // Presence first: we must notice the world going away even while joining.
    let t = tx.clone();
    let _presence = session
        .liveliness()
        .declare_subscriber(keys::all_presence(&run))
        .history(true)
        .callback(move |s| {
            let alive = s.kind() == SampleKind::Put;
            let _ = t.send(Event::Presence { alive, key: s.key_expr().as_str().to_owned() });
        })
        .await
        .map_err(zerr)?;
    spawn_signal_watch(tx.clone());
    let (info, zenoh_rt) =
        zenoh_bus::fetch_run_info(&session, &run, Duration::from_millis(args.join_timeout_ms)).await?;
    if range.last >= info.spec.agents {
        bail!("agents {range} outside the run's {} agents", info.spec.agents);
    }
    let t = tx.clone();
    let _tick = session
        .declare_subscriber(keys::tick(&run))
        .callback(move |s| {
            let _ = t.send(Event::Tick(s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(zerr)?;
    let t = tx.clone();
    let _ctl = session
        .declare_subscriber(keys::ctl(&run, "stop"))
        .callback(move |s| match decode::<Control>(&s.payload().to_bytes()) {
            Ok(Control::Stop) => {
                let _ = t.send(Event::Stop);
            }
            _ => {
                let _ = t.send(Event::Hostile);
            }
        })
        .await
        .map_err(zerr)?;
    let wide = match args.subscribe {
        SubscribeArg::All => true,
        SubscribeArg::Cells => false,
        SubscribeArg::Auto => range.len() as usize * 4 >= info.geometry.cell_count(),
    };
    let mut host = Host::new(session.clone(), run.clone(), range, info, tx.clone(), wide)?;
    host.subscribe_initial().await?;
    let intents = session
        .declare_publisher(keys::agents_action(&run, range))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(zerr)?;
    host.intent_pub = Some(intents);
    // Declared after the subscriptions, so the world sees us only once we can hear it
    // (and, reading cells one by one, that it must publish them so before that).
    let cells_token = if wide {
        None
    } else {
        Some(session.liveliness().declare_token(keys::cells_presence(&run, range)).await.map_err(zerr)?)
    };
    let token = session.liveliness().declare_token(keys::agents_presence(&run, range)).await.map_err(zerr)?;
    let work = async move {
        let r = host.run(&mut rx).await;
        host.clock.report(host.range);
        drop(host);
        r
    };
    // Run the agents on Zenoh's own (single-threaded, see LEAN_ZENOH_RUNTIME) runtime:
    // receiving, deciding and sending then happen on one thread, with no hand-off
    // between threads on each message.
    let res = match zenoh_rt {
        Some(h) if !args.separate_runtime => match h.spawn(work).await {
            Ok(r) => r,
            Err(e) => Err(anyhow::anyhow!("agent task: {e}")),
        },
        _ => work.await,
    };
    let _ = token.undeclare().await;
    if let Some(t) = cells_token {
        let _ = t.undeclare().await;
    }
    let _ = session.close().await;
    res
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

/// Maps by cell or agent id looked up for every agent every step, hashed with foldhash
/// (SipHash showed in profiles of 10 x 100 agents).
type FastMap<K, V> = HashMap<K, V, FixedState>;

fn zerr(e: zenoh::Error) -> anyhow::Error {
    anyhow::Error::new(geese_proto::zenoh_bus::zerr(e))
}

fn spawn_signal_watch(tx: UnboundedSender<Event>) {
    tokio::spawn(async move {
        geese_proto::zenoh_bus::shutdown_signal().await;
        let _ = tx.send(Event::Stop);
    });
}

/// Subscriptions of one cell (exact mode).
struct CellSubs {
    _percept: Subscriber<()>,
    _genes: Subscriber<()>,
    /// Last step for which the cell was a candidate.
    wanted: u64,
}

/// Cells stay subscribed this many steps after they were last a candidate (agents
/// often step back and forth across a cell border).
const KEEP_STEPS: u64 = 2;

struct Host {
    session: Session,
    run: String,
    range: AgentRange,
    info: RunInfo,
    geom: Geometry,
    learners: Vec<Learner>,
    /// Mapped genes of senders, shared by this process's learners.
    gene_cache: GeneCache,
    loss_streams: Vec<u64>,
    tx: UnboundedSender<Event>,
    wide: bool,
    wide_subs: Vec<Subscriber<()>>,
    subs: HashMap<u32, CellSubs>,
    intent_pub: Option<Publisher<'static>>,
    /// Last completed step.
    done: u64,
    /// Own agents the world counts as live (from the latest tick), by index.
    live: Vec<bool>,
    /// Centre cell each own agent was last seen in (where to subscribe while unseen).
    last_cell: Vec<u32>,
    /// The step whose percepts are being collected (0: none) and until when.
    collecting: u64,
    collect_deadline: Option<tokio::time::Instant>,
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
    /// Centre cell of each agent of another process in a cell of ours (by agent id,
    /// `NO_CELL` elsewhere), for filing genes sent ahead (kept only for its buffer).
    sender_cell: Vec<u32>,
    present: BTreeMap<AgentRange, u32>,
    counters: HostCounters,
    stop: bool,
    bare_tick: Option<u64>,
    /// A tick came: check that the cells of own agents are subscribed.
    tick_seen: bool,
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
            self.between += now - sent;
        }
        self.first_percept = Some(now);
    }

    /// Time since `from`, added to `phase`; returns now.
    fn lap(phase: &mut Duration, from: Instant) -> Instant {
        let now = Instant::now();
        *phase += now - from;
        now
    }

    fn report(&self, range: AgentRange) {
        let ms = |d: Duration| d.as_secs_f64() * 1e3 / self.steps.max(1) as f64;
        tracing::debug!(
            target: "geese::flow",
            "agents {range}: {} steps; per step {:.3} ms percepts->genes sent, {:.3} ms gene wait, {:.3} ms finish+intents, {:.3} ms intents->next percept",
            self.steps, ms(self.begin), ms(self.gene_wait), ms(self.finish), ms(self.between)
        );
    }
}

impl Host {
    fn new(
        session: Session,
        run: String,
        range: AgentRange,
        info: RunInfo,
        tx: UnboundedSender<Event>,
        wide: bool,
    ) -> Result<Self> {
        let geom = info.geometry;
        let mut learners = Vec::new();
        let mut loss_streams = Vec::new();
        if !info.spec.bare {
            let cfg: LearnerConfig =
                serde_json::from_str(&info.spec.learner_json).context("learner configuration from the world")?;
            cfg.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
            let grammar = Grammar::parse(&info.spec.grammar_text)
                .map_err(|e| anyhow::anyhow!("grammar {}: {e}", info.spec.grammar_name))?;
            let (cfg, grammar) = (Arc::new(cfg), Arc::new(grammar));
            for id in range.ids() {
                learners.push(Learner::new(id, cfg.clone(), grammar.clone(), geom, info.hub, info.spec.seed));
                loss_streams.push(derive(info.spec.seed, Owner::Agent(id), Purpose::Loss) ^ LOSS_SALT_PERCEPT);
            }
        }
        let last_cell = range.ids().map(|id| info.cells.get(id as usize).copied().unwrap_or(NO_CELL)).collect();
        Ok(Host {
            session,
            run,
            range,
            done: info.next_step.saturating_sub(1),
            live: vec![false; range.len() as usize],
            last_cell,
            geom,
            info,
            learners,
            gene_cache: GeneCache::new(),
            loss_streams,
            tx,
            wide,
            wide_subs: Vec::new(),
            subs: HashMap::new(),
            intent_pub: None,
            collecting: 0,
            collect_deadline: None,
            percepts: FastMap::default(),
            found: FastMap::default(),
            inbox: Inbox::default(),
            heard: HashSet::default(),
            unpacked: Vec::new(),
            ahead_step: 0,
            sender_cell: Vec::new(),
            present: BTreeMap::new(),
            counters: HostCounters::default(),
            stop: false,
            bare_tick: None,
            tick_seen: false,
            clock: PhaseClock::default(),
        })
    }

    fn bare(&self) -> bool {
        self.info.spec.bare
    }

    fn idx(&self, id: AgentId) -> usize {
        (id - self.range.first) as usize
    }

    async fn subscribe_initial(&mut self) -> Result<()> {
        if self.bare() {
            return Ok(());
        }
        if self.wide {
            // Our cells' percepts and genes, from the world, one message per step each.
            for key in [keys::host_percepts(&self.run, self.range), keys::host_genes(&self.run, self.range)] {
                let t = self.tx.clone();
                let run = self.run.clone();
                let range = self.range;
                let sub = self
                    .session
                    .declare_subscriber(key)
                    .callback(move |s| {
                        let ev = match keys::parse(&run, s.key_expr().as_str()) {
                            Parsed::HostPercepts { to } if to == range => Event::Percepts(s.payload().clone()),
                            Parsed::HostGenes { to } if to == range => Event::HostGenes(s.payload().clone()),
                            _ => Event::Hostile,
                        };
                        let _ = t.send(ev);
                    })
                    .await
                    .map_err(zerr)?;
                self.wide_subs.push(sub);
            }
            return Ok(());
        }
        self.want_own_cells().await
    }

    /// The cell of every own agent, dead or alive: a restarted agent's body is revived
    /// where it stands, and the percept that shows it live may come before the tick that
    /// says so (a process that dropped the cell then stayed deaf to it for good).
    fn own_cells(&self) -> Vec<u32> {
        self.last_cell.iter().copied().filter(|&c| c != NO_CELL).collect()
    }

    /// Make sure the cell of every own agent is subscribed for the next step.
    async fn want_own_cells(&mut self) -> Result<()> {
        for c in self.own_cells() {
            self.want(c, self.done + 1).await?;
        }
        Ok(())
    }

    /// Make sure cell `cell` is subscribed and keep it for step `step`.
    async fn want(&mut self, cell: u32, step: u64) -> Result<()> {
        if let Some(s) = self.subs.get_mut(&cell) {
            s.wanted = s.wanted.max(step);
            return Ok(());
        }
        let (cx, cy) = self.geom.cell_col_row(cell);
        let t = self.tx.clone();
        let percept = self
            .session
            .declare_subscriber(keys::cell_percept(&self.run, cx, cy))
            .callback(move |s| {
                let _ = t.send(Event::Percept { cell, bytes: s.payload().to_bytes().into_owned() });
            })
            .await
            .map_err(zerr)?;
        let t = self.tx.clone();
        let genes = self
            .session
            .declare_subscriber(keys::cell_genes(&self.run, cx, cy))
            .callback(move |s| {
                let _ = t.send(Event::Genes { cell, bytes: s.payload().to_bytes().into_owned() });
            })
            .await
            .map_err(zerr)?;
        self.subs.insert(cell, CellSubs { _percept: percept, _genes: genes, wanted: step });
        Ok(())
    }

    /// Every own live agent has been seen in a percept of the step being collected.
    fn all_found(&self) -> bool {
        self.range.ids().all(|id| !self.live[self.idx(id)] || self.found.contains_key(&id))
    }

    async fn run(&mut self, rx: &mut UnboundedReceiver<Event>) -> Result<()> {
        loop {
            if self.stop {
                return Ok(());
            }
            if let Some(t) = self.bare_tick.take() {
                self.bare_step(t).await?;
                continue;
            }
            if std::mem::take(&mut self.tick_seen) && !self.wide && !self.bare() {
                // Wherever the world now says our agents are, listen there.
                self.want_own_cells().await?;
            }
            if self.collecting > self.done {
                let expired = self.collect_deadline.is_some_and(|d| tokio::time::Instant::now() >= d);
                if self.all_found() || expired {
                    self.step(self.collecting, rx).await?;
                    continue;
                }
            }
            let deadline = self.collect_deadline;
            tokio::select! {
                ev = rx.recv() => match ev {
                    Some(ev) => self.absorb(ev),
                    None => return Ok(()),
                },
                _ = async {
                    match deadline {
                        Some(d) => tokio::time::sleep_until(d).await,
                        None => std::future::pending::<()>().await,
                    }
                } => {}
            }
        }
    }

    /// File an event.
    fn absorb(&mut self, ev: Event) {
        if tracing::enabled!(target: "geese::flow", tracing::Level::TRACE) {
            let what = match &ev {
                Event::Tick(_) => "tick",
                Event::Percept { .. } => "percept",
                Event::Genes { .. } => "genes",
                Event::Percepts(_) => "percepts",
                Event::HostGenes(_) => "host genes",
                Event::Hostile => "hostile",
                Event::Presence { .. } => "presence",
                Event::Stop => "stop",
            };
            tracing::trace!(target: "geese::flow", "agents {}: {what} (done {}, collecting {})", self.range, self.done, self.collecting);
        }
        match ev {
            Event::Tick(bytes) => match decode::<Tick>(&bytes) {
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
            Event::Percept { cell, bytes } => match decode::<Percept>(&bytes) {
                Ok(p) if p.cell == cell => self.take_percept(p),
                _ => self.counters.hostile += 1,
            },
            Event::Percepts(z) => match decode::<HostPercepts>(&z.to_bytes()) {
                Ok(b) => {
                    let percepts = self.open_each(&b.percepts);
                    self.take_each(percepts, |p| p.step == b.step, Self::take_percept);
                    if let Some(packs) = &b.genes {
                        if b.step == self.collecting && b.step > self.done {
                            self.take_ahead(b.step, packs);
                        }
                    }
                }
                Err(_) => self.counters.hostile += 1,
            },
            Event::Genes { cell, bytes } => match decode::<GeneBatchHead>(&bytes) {
                // A cell's own topic carries its whole aggregate: the cell is complete.
                Ok(b) if b.cell == cell => {
                    if b.step > self.done {
                        self.heard.insert((b.step, cell));
                    }
                    self.take_genes(b)
                }
                _ => self.counters.hostile += 1,
            },
            Event::HostGenes(z) => match decode::<HostGenes>(&z.to_bytes()) {
                Ok(b) => {
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
                    // Packs come as they reach the world, before their cells are complete.
                    // Only batches of cells our agents are in (the cells whose percepts
                    // the step brought, first, from the same session) are decoded.
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
                                self.take_each(batches, |g| g.step == b.step, Self::take_genes);
                            }
                            Err(_) => self.counters.hostile += 1,
                        }
                    }
                    self.unpacked = scratch;
                }
                Err(_) => self.counters.hostile += 1,
            },
            Event::Hostile => self.counters.hostile += 1,
            Event::Presence { alive, key } => match keys::parse(&self.run, &key) {
                Parsed::WorldPresence if !alive => {
                    tracing::info!("agents {}: the world left; exiting", self.range);
                    self.stop = true;
                }
                Parsed::AgentsPresence { agents } => keys::tally(&mut self.present, agents, alive),
                _ => {}
            },
            Event::Stop => self.stop = true,
        }
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

    /// File each cell's item of a bundle that belongs to the bundle's step (`same_step`)
    /// and names a cell of the arena; count the others as hostile.
    fn take_each<T: Cell>(&mut self, items: Vec<T>, same_step: impl Fn(&T) -> bool, take: fn(&mut Self, T)) {
        for item in items {
            if same_step(&item) && (item.cell() as usize) < self.geom.cell_count() {
                take(self, item);
            } else {
                self.counters.hostile += 1;
            }
        }
    }

    /// File the percept of one cell (from its own message or a bundle).
    fn take_percept(&mut self, p: Percept) {
        if p.step <= self.done || p.step < self.collecting {
            return; // stale
        }
        if p.step > self.collecting {
            tracing::trace!(target: "geese::flow", "agents {}: collecting step {}", self.range, p.step);
            let now = Instant::now();
            self.clock.step_begins(now);
            self.collecting = p.step;
            self.percepts.clear();
            self.found.clear();
            self.collect_deadline = Some(
                tokio::time::Instant::from_std(now) + Duration::from_millis(self.info.spec.deadlines.percept_ms as u64),
            );
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
    /// packs, each of one batch sent ahead ([`AHEAD_CELL`]). A gene goes to the cell
    /// its sender's centre is in by this step's percepts, if that is a cell of ours; the
    /// others are skipped unread.
    fn take_ahead(&mut self, step: u64, packs: &[Raw]) {
        self.ahead_step = step;
        self.sender_cell.clear();
        self.sender_cell.resize(self.info.spec.agents as usize, NO_CELL);
        let (range, geom) = (self.range, self.geom);
        for (&c, p) in &self.percepts {
            for a in p.agents.iter().filter(|a| !range.contains(a.id) && geom.cell_of(a.pos) == c) {
                if let Some(x) = self.sender_cell.get_mut(a.id as usize) {
                    *x = c;
                }
            }
        }
        let mut scratch = std::mem::take(&mut self.unpacked);
        for p in packs {
            let Ok(nested) = unpack(p.0, &mut scratch) else {
                self.counters.hostile += 1;
                continue;
            };
            for raw in nested {
                let cells = &self.sender_cell;
                let cell_of = |from: AgentId| cells.get(from as usize).copied().filter(|&c| c != NO_CELL);
                let filed = match raw.open::<GeneBatchHead>() {
                    Ok(b) if b.step == step && b.cell == AHEAD_CELL => self.inbox.file_by_sender(&b, cell_of),
                    _ => false,
                };
                if !filed {
                    self.counters.hostile += 1;
                }
            }
        }
        self.unpacked = scratch;
    }

    /// Publish, ahead, the genes our agents offer at step `step` ([`AHEAD_CELL`]): each
    /// agent's gene as it stands, except those of agents whose percept of that step the
    /// injected loss will drop (they take no part in it). The world files them and
    /// sends them on with the percepts of `step`.
    async fn publish_ahead(&mut self, step: u64) -> Result<()> {
        let p_loss = self.info.spec.loss.percept;
        let genes: Vec<GeneMsg> = (0..self.learners.len())
            .filter(|&k| p_loss <= 0.0 || loss_draw(self.loss_streams[k], step, 0) >= p_loss)
            .map(|k| self.learners[k].offer(step))
            .collect();
        let batch = GeneBatchRef { step, cell: AHEAD_CELL, genes: &genes, absent: &[] };
        let nested = nest_sized(&batch, batch.size_hint())?;
        self.publish_bundle(step, &[Raw(&nested)]).await
    }

    /// Publish gene batches (nested) of step `step` as one packed [`GeneBundle`] on
    /// `agent/<ids>/genes`.
    async fn publish_bundle(&self, step: u64, batches: &[Raw<'_>]) -> Result<()> {
        let packed = pack(batches)?;
        let bytes = encode_sized(&GeneBundle { step, packed: Raw(&packed) }, packed.len() + 16)?;
        self.session
            .put(keys::agents_genes(&self.run, self.range), bytes)
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zerr)
    }

    /// File a batch of genes of one cell (the cell's aggregate, or one process's batch
    /// of it; whether the cell is complete is said apart).
    fn take_genes(&mut self, b: GeneBatchHead) {
        if b.step > self.done && !self.inbox.file(&b) {
            self.counters.hostile += 1;
        }
    }

    /// Wait for events until `done(self)` holds or `deadline` passes; false on timeout.
    async fn wait_until(
        &mut self,
        rx: &mut UnboundedReceiver<Event>,
        deadline: Instant,
        done: impl Fn(&Self) -> bool,
    ) -> bool {
        loop {
            if done(self) {
                return true;
            }
            if self.stop {
                return false;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, rx.recv()).await {
                Ok(Some(ev)) => self.absorb(ev),
                Ok(None) => {
                    self.stop = true;
                    return false;
                }
                Err(_) => return done(self),
            }
        }
    }

    async fn publish_intents(&mut self, batch: IntentBatch) -> Result<()> {
        let bytes = encode(&batch)?;
        if let Some(p) = &self.intent_pub {
            p.put(bytes).await.map_err(zerr)?;
        }
        Ok(())
    }

    async fn bare_step(&mut self, step: u64) -> Result<()> {
        let batch = IntentBatch {
            step,
            intents: Vec::new(),
            idle: self.range.ids().collect(),
            counters: std::mem::take(&mut self.counters),
        };
        self.publish_intents(batch).await?;
        self.done = step;
        Ok(())
    }

    async fn step(&mut self, t: u64, rx: &mut UnboundedReceiver<Event>) -> Result<()> {
        let spec_deadlines = self.info.spec.deadlines;
        let own: Vec<AgentId> = self.range.ids().filter(|&id| self.live[self.idx(id)]).collect();
        // 1–2. Percepts, then begin: genes to offer, agents that idle.
        let p_loss = self.info.spec.loss.percept;
        let mut idle: Vec<AgentId> = Vec::new();
        let mut active: Vec<(AgentId, u32)> = Vec::new();
        // Each cell's own genes.
        let mut local: FastMap<u32, Vec<GeneMsg>> = FastMap::default();
        let mut absent: FastMap<u32, Vec<AgentId>> = FastMap::default();
        for &id in &own {
            let k = self.idx(id);
            let Some(&c) = self.found.get(&id) else {
                // Its percept never came: it idles (its mates do not know it is there).
                self.counters.percepts_missing += 1;
                idle.push(id);
                continue;
            };
            self.last_cell[k] = c;
            if p_loss > 0.0 && loss_draw(self.loss_streams[k], t, 0) < p_loss {
                self.counters.percepts_lost += 1;
                idle.push(id);
                absent.entry(c).or_default().push(id);
                continue;
            }
            let Some(percept) = self.percepts.get(&c) else {
                continue;
            };
            if let Some(g) = self.learners[k].begin_step(percept) {
                local.entry(c).or_default().push(g);
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
            let outsiders = self.percepts.get(&c).is_some_and(|p| {
                p.agents.iter().any(|a| a.live && !self.range.contains(a.id) && self.geom.cell_of(a.pos) == c)
            });
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
            self.publish_bundle(t, &batches).await?;
        }
        let genes_sent = match self.clock.first_percept {
            Some(f) => PhaseClock::lap(&mut self.clock.begin, f),
            None => Instant::now(),
        };
        // Which remote cell-mates each cell waits for: expected mates of another process
        // whose centre is in the cell (others publish elsewhere and count as lost).
        // Every own agent in a cell expects the same remote mates (its list differs from
        // another own agent's only by own ids), so one agent's list per cell will do.
        let mut wait_for: FastMap<u32, Vec<AgentId>> = FastMap::default();
        let (range, geom) = (self.range, self.geom);
        for &(id, c) in active.iter().filter(|_| !ahead) {
            if wait_for.contains_key(&c) {
                continue;
            }
            let Some(p) = self.percepts.get(&c) else {
                continue;
            };
            let mut remote: Vec<AgentId> =
                p.agents.iter().filter(|a| !range.contains(a.id) && geom.cell_of(a.pos) == c).map(|a| a.id).collect();
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
        if !wait_for.is_empty() {
            // One aggregate per shared cell, sent once every process there has spoken.
            let deadline = Instant::now() + Duration::from_millis(spec_deadlines.gene_ms as u64);
            let satisfied = |h: &Self| {
                wait_for.iter().all(|(&c, mates)| h.heard.contains(&(t, c)) || mates.iter().all(|&m| !h.is_present(m)))
            };
            if !self.wait_until(rx, deadline, satisfied).await {
                if self.stop {
                    return Ok(());
                }
                let late = wait_for
                    .iter()
                    .filter(|(&c, _)| !self.heard.contains(&(t, c)))
                    .map(|(_, mates)| mates.len() as u32)
                    .sum::<u32>();
                tracing::trace!(target: "geese::flow", "agents {}: step {t}: genes late, waited for {wait_for:?}", self.range);
                self.counters.genes_late += late;
            }
        }
        let finish_from = PhaseClock::lap(&mut self.clock.gene_wait, genes_sent);
        // 3. Finish: act, learn, intents.
        let mut intents: Vec<Intent> = Vec::with_capacity(active.len());
        // Each cell's genes: our own, then the others' as they arrived, lent from the
        // inbox; in sender order once per cell, so that each learner's own check finds
        // them sorted.
        let range = self.range;
        let mut lent = Vec::with_capacity(self.inbox.len() + own.len());
        for (&c, genes) in &local {
            lent.extend(genes.iter().map(|g| (c, GeneRef::of(g))));
        }
        self.inbox.lend(t, |from| range.contains(from), &mut lent);
        let cell_genes = CellGenes::new(lent);
        for &(id, c) in &active {
            let k = self.idx(id);
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
                self.want(c, t + 1).await?;
            }
            self.subs.retain(|_, s| s.wanted + KEEP_STEPS > t);
        }
        let batch = IntentBatch { step: t, intents, idle, counters: std::mem::take(&mut self.counters) };
        // Our genes for the next step, before the intents that let the world start it
        // (not while lateral transfer is off: if it comes on at the next step, that
        // step's genes go through the world during the step).
        let lateral = self.percepts.values().next().is_some_and(|p| p.regime.lateral_transfer);
        if self.wide && lateral && t < self.info.spec.steps {
            self.publish_ahead(t + 1).await?;
        }
        tracing::trace!(target: "geese::flow", "agents {}: intents of step {t}", self.range);
        self.publish_intents(batch).await?;
        self.clock.intents_sent = Some(PhaseClock::lap(&mut self.clock.finish, finish_from));
        self.clock.steps += 1;
        self.done = t;
        self.collect_deadline = None;
        self.percepts.clear();
        self.found.clear();
        self.inbox.retire(t);
        self.heard.retain(|&(s, _)| s > t);
        Ok(())
    }

    /// Is some process speaking for agent `m` present?
    fn is_present(&self, m: AgentId) -> bool {
        self.present.keys().any(|r| r.contains(m))
    }
}
