//! `geese-world`: the world server of a distributed GEESE run (DESIGN.md §2–4).
//!
//! A thin async shell around the synchronous [`World`]: it publishes the percepts of a
//! step on their cell topics followed by a [`Tick`], gathers the [`IntentBatch`]es of
//! the agent processes until every live agent has answered (or the intent deadline
//! passes), resolves the step exactly as the in-process driver does, and publishes the
//! report. Presence is by liveliness tokens: the run starts when every agent id is
//! covered by a present agent process (and the orchestrator is present, if expected);
//! an agent process that disappears has its agents killed (`World::kill`), one that
//! comes back has them revived (`World::revive`) at the next step.
//!
//! Normally started by `geese run --processes N`, which writes the `--spec` file.
use anyhow::{bail, Context, Result};
use clap::Parser;
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{
    loss_draw, nest, nested_size, pack, unpack, GeneBatch, GeneBatchCell, GeneBatchHead, HostGenes, HostPercepts,
    IntentBatch, NetCounters, NetReport, NetRunSpec, Raw, ReportMsg, RunInfo, Tick, AHEAD_CELL, LOSS_SALT_INTENT,
    NO_CELL,
};
use geese_proto::seed::{derive, Owner, Purpose};
use geese_proto::zenoh_bus::{self, CommonArgs};
use geese_proto::{decode, encode, encode_sized, Control, Intent};
use geese_world::{World, WorldConfig};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};
use tokio::sync::Notify;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;
use zenoh::{Session, Wait};

/// Maps keyed by cell, hashed with foldhash: the world fills and reads them for every
/// shared cell and every batch between two steps, when every agent process waits on it.
type CellMap<V> = HashMap<u32, V, foldhash::fast::FixedState>;

#[derive(Parser)]
#[command(name = "geese-world", version, about = "GEESE world server (Zenoh)")]
struct Args {
    #[command(flatten)]
    zenoh: CommonArgs,
    /// Run specification (JSON), as written by `geese run --processes`.
    #[arg(long)]
    spec: PathBuf,
    /// Tokio worker threads of the server loop.
    #[arg(long, default_value_t = 1)]
    threads: usize,
}

enum Event {
    Presence { alive: bool, key: String },
    Ctl(Vec<u8>),
    Signal,
}

/// mimalloc: the step loop allocates many small, short-lived buffers.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let text = std::fs::read_to_string(&args.spec).with_context(|| format!("cannot read {}", args.spec.display()))?;
    let spec: NetRunSpec =
        serde_json::from_str(&text).with_context(|| format!("{} is not a run specification", args.spec.display()))?;
    if !keys::valid_run_name(&spec.run) {
        bail!("run name {:?} must be one key chunk of letters, digits, '_', '-', '.'", spec.run);
    }
    let rt = zenoh_bus::runtime(args.threads)?;
    rt.block_on(serve(args.zenoh, spec))
}

/// What the `ctl/info` queryable answers with.
struct InfoState {
    next_step: u64,
    cells: Vec<u32>,
}

async fn serve(common: CommonArgs, spec: NetRunSpec) -> Result<()> {
    let wcfg: WorldConfig = serde_json::from_str(&spec.world_json).context("world configuration")?;
    if wcfg.agents != spec.agents {
        bail!("spec: {} agents but the world configuration has {}", spec.agents, wcfg.agents);
    }
    let mut world = World::new(wcfg, spec.seed).map_err(|e| anyhow::anyhow!("world: {e}"))?;
    // Exactly the in-process driver's set-up order (orchestrator/src/trial.rs).
    world.set_regime(spec.regime);
    for (at, change) in &spec.perturbations {
        world.schedule(*at, change.clone());
    }
    let run = spec.run.clone();
    let (session, locators) = zenoh_bus::open_world(&common).await?;
    let (tx, mut rx) = unbounded_channel::<Event>();

    let info = Arc::new(Mutex::new(InfoState { next_step: world.step(), cells: body_cells(&world) }));
    let fixed = (spec.clone(), world.geometry(), world.hub());
    let info_q = info.clone();
    let _queryable = session
        .declare_queryable(keys::info(&run))
        .callback(move |q| {
            let (next_step, cells) = match info_q.lock() {
                Ok(s) => (s.next_step, s.cells.clone()),
                Err(_) => return,
            };
            let ri = RunInfo { spec: fixed.0.clone(), geometry: fixed.1, hub: fixed.2, next_step, cells };
            if let Ok(bytes) = encode(&ri) {
                let _ = q.reply(q.key_expr().clone(), bytes).wait();
            }
        })
        .await
        .map_err(zerr)?;
    let gather = Arc::new(Mutex::new(Gather::new(run.clone(), spec.agents as usize)));
    let gathered = Arc::new(Notify::new());
    let (g, done) = (gather.clone(), gathered.clone());
    let _actions = session
        .declare_subscriber(keys::all_actions(&run))
        .callback(move |s| {
            let bytes = s.payload().to_bytes();
            let mut g = g.lock().unwrap_or_else(|e| e.into_inner());
            if g.on_action(s.key_expr().as_str(), &bytes) {
                done.notify_one();
            }
        })
        .await
        .map_err(zerr)?;
    let (publish, released) = unbounded_channel::<Released>();
    let genes = Arc::new(Mutex::new(GeneHub {
        run: run.clone(),
        geom: world.geometry(),
        step: 0,
        cells: CellMap::default(),
        hosts: HashMap::new(),
        hostile: 0,
        per_cell: true,
        publish,
        packs: Vec::new(),
        unpacked: Vec::new(),
        begun: 0,
        ahead: HashMap::new(),
    }));
    spawn_publisher(&session, released, genes.clone());
    // Per-cell batches (processes of earlier versions, tests) and bundles.
    let _genes = gene_subscriber(&session, keys::all_gene_batches(&run), &genes, GeneHub::on_batch).await?;
    let _gene_bundles = gene_subscriber(&session, keys::all_agents_genes(&run), &genes, GeneHub::on_bundle).await?;
    let t = tx.clone();
    let _ctl = session
        .declare_subscriber(keys::all_ctl(&run))
        .callback(move |s| {
            let _ = t.send(Event::Ctl(s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(zerr)?;
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
    let token = session.liveliness().declare_token(keys::world_presence(&run)).await.map_err(zerr)?;
    spawn_signal_watch(tx.clone());

    // Tell the launcher (or the user) where to connect.
    {
        let mut out = std::io::stdout().lock();
        for l in &locators {
            writeln!(out, "locator={l}")?;
        }
        writeln!(out, "ready run={run}")?;
        out.flush()?;
    }
    eprintln!("geese-world: run {run} listening on {}", locators.join(", "));

    let mut server = Server::new(&session, spec, world, info, gather, gathered, genes);
    let outcome = server.run(&mut rx).await;
    // Whatever happened, say so and let everyone go.
    let (steps, completed) = match &outcome {
        Ok(c) => (server.steps_done, *c),
        Err(_) => (server.steps_done, false),
    };
    let done = ReportMsg::Done { steps, completed, requested: server.stop_requested };
    if let Ok(b) = encode(&done) {
        let _ = zenoh_bus::put(&session, &keys::report(&run), b).await;
    }
    if let Ok(b) = encode(&Control::Stop) {
        let _ = zenoh_bus::put(&session, &keys::ctl(&run, "stop"), b).await;
    }
    drop(server);
    let _ = token.undeclare().await;
    // Give the last messages a moment to leave before the router goes away.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let _ = session.close().await;
    outcome.map(|_| ())
}

fn zerr(e: zenoh::Error) -> anyhow::Error {
    anyhow::Error::new(geese_proto::zenoh_bus::zerr(e))
}

fn spawn_signal_watch(tx: UnboundedSender<Event>) {
    tokio::spawn(async move {
        geese_proto::zenoh_bus::shutdown_signal().await;
        let _ = tx.send(Event::Signal);
    });
}

/// Centre cell of every agent's body, dead or alive.
fn body_cells(world: &World) -> Vec<u32> {
    let g = world.geometry();
    world.bodies().iter().map(|b| g.cell_of(b.pos)).collect()
}

/// Centre cell of every agent (`NO_CELL` when dead).
fn cells_of(world: &World) -> Vec<u32> {
    let g = world.geometry();
    world.bodies().iter().map(|b| if b.live { g.cell_of(b.pos) } else { NO_CELL }).collect()
}

/// The intents of the step being gathered. Filled by the subscriber callback on Zenoh's
/// receive thread, so the server loop wakes once per step (when the last expected
/// intent is in), not once per message.
struct Gather {
    run: String,
    n: usize,
    /// The step whose intents are awaited (0: none).
    step: u64,
    expected: Vec<bool>,
    answered: Vec<bool>,
    intents: Vec<Option<Intent>>,
    pending: usize,
    counters: NetCounters,
}

impl Gather {
    fn new(run: String, n: usize) -> Self {
        Gather {
            run,
            n,
            step: 0,
            expected: vec![false; n],
            answered: vec![false; n],
            intents: vec![None; n],
            pending: 0,
            counters: NetCounters::default(),
        }
    }

    fn begin(&mut self, step: u64, expected: impl Fn(usize) -> bool) {
        self.step = step;
        self.pending = 0;
        self.counters = NetCounters::default();
        for i in 0..self.n {
            self.intents[i] = None;
            self.answered[i] = false;
            self.expected[i] = expected(i);
            self.pending += self.expected[i] as usize;
        }
    }

    /// Agent `id` is no longer awaited (its process left).
    fn forget(&mut self, id: usize) {
        if id < self.n && self.expected[id] {
            self.expected[id] = false;
            if !self.answered[id] {
                self.pending -= 1;
            }
        }
    }

    fn answer(&mut self, id: usize) -> bool {
        if self.answered[id] {
            return false;
        }
        self.answered[id] = true;
        if self.expected[id] {
            self.pending -= 1;
        }
        true
    }

    /// File one intent batch; true when nothing is pending any more.
    fn on_action(&mut self, key: &str, bytes: &[u8]) -> bool {
        let Parsed::Action { from } = keys::parse(&self.run, key) else {
            self.counters.hostile += 1;
            return false;
        };
        let batch: IntentBatch = match decode(bytes) {
            Ok(b) => b,
            Err(e) => {
                tracing::debug!("dropped intent batch on {key}: {e}");
                self.counters.hostile += 1;
                return false;
            }
        };
        let step = self.step;
        tracing::trace!(target: "geese::flow", "intents of step {} from {from} (awaiting {step})", batch.step);
        if batch.step != step || step == 0 {
            // A straggler of an earlier step (after its deadline), or nonsense.
            if batch.step > step {
                self.counters.hostile += 1;
            }
            return false;
        }
        let c = batch.counters;
        self.counters.percepts_lost += c.percepts_lost;
        self.counters.percepts_missing += c.percepts_missing;
        self.counters.genes_late += c.genes_late;
        self.counters.hostile += c.hostile;
        for id in batch.idle {
            if !from.contains(id) || id as usize >= self.n {
                self.counters.hostile += 1;
                continue;
            }
            self.answer(id as usize);
        }
        for intent in batch.intents {
            let id = intent.agent;
            if !from.contains(id) || id as usize >= self.n || intent.step != step {
                // Claims an agent this process does not speak for.
                self.counters.hostile += 1;
                continue;
            }
            let i = id as usize;
            if self.answer(i) && self.expected[i] {
                self.intents[i] = Some(intent);
            }
        }
        self.pending == 0
    }
}

/// Files what arrives on `key` into the hub with `file` (in the subscriber callback,
/// like [`Gather`]) and hands what that releases to the publisher.
async fn gene_subscriber(
    session: &Session,
    key: String,
    hub: &Arc<Mutex<GeneHub>>,
    file: fn(&mut GeneHub, &str, &[u8]) -> Released,
) -> Result<zenoh::pubsub::Subscriber<()>> {
    let h = hub.clone();
    session
        .declare_subscriber(key)
        .callback(move |s| {
            let bytes = s.payload().to_bytes();
            let mut hub = h.lock().unwrap_or_else(|e| e.into_inner());
            let out = file(&mut hub, s.key_expr().as_str(), &bytes);
            hub.release(out);
        })
        .await
        .map_err(zerr)
}

/// Per-cell gene aggregation (DESIGN.md §2 step 2). Agent processes publish their
/// batches of the shared cells of a step as one packed bundle on `agent/<ids>/genes`;
/// once every process with an agent centred in a cell has spoken (or left), the cell is
/// complete. Then a process that reads cells one by one gets the cell's genes as one
/// batch on `cell/<cx>/<cy>/genes`. A hosting process gets the packs of the other
/// processes it shares a cell with as they arrive, and then which cells are complete,
/// in [`HostGenes`] messages on `agent/<ids>/in/genes` (built by the publisher when it
/// wakes: [`spawn_publisher`]).
///
/// A hosting process also sends, with its intents, its genes of the next step
/// ([`AHEAD_CELL`]); the hub checks and keeps them, and when every hosting process sent
/// them the server puts them into the next step's [`HostPercepts`] instead of opening
/// the hub's cells for that step.
/// Runs in the subscriber callback, like [`Gather`].
struct GeneHub {
    run: String,
    geom: geese_proto::Geometry,
    step: u64,
    cells: CellMap<CellAgg>,
    /// What each hosting process sharing a cell this step has still to be sent.
    hosts: HashMap<AgentRange, HostOut>,
    hostile: u32,
    /// Whether to publish each cell's aggregate on its own topic (some process reads
    /// cells one by one).
    per_cell: bool,
    /// Where what the hub releases goes out ([`spawn_publisher`]).
    publish: UnboundedSender<Released>,
    /// This step's packs for hosting processes ([`HostOut::packs`]): as their senders
    /// sent them, or packed again without the batches the checks dropped.
    packs: Vec<Vec<u8>>,
    /// Where bundles are unpacked (kept between bundles).
    unpacked: Vec<u8>,
    /// The step last begun (0 before the first).
    begun: u64,
    /// Each hosting process's pack sent ahead ([`AHEAD_CELL`]) for the step after the
    /// one begun, with that step.
    ahead: HashMap<AgentRange, (u64, Vec<u8>)>,
}

/// What filing gene batches releases: messages (key, bytes) to publish, in order.
type Released = Vec<(String, Vec<u8>)>;

/// Publishes what the hub releases, in order, from a task of its own. Zenoh callbacks
/// must not wait: a put that blocks (congestion control) inside the callback that
/// receives gene batches would stall the thread receiving every process's messages.
///
/// Each time it wakes it also sends the hosting processes what the hub holds for them
/// ([`GeneHub::flush`]): bundles filed while it was busy go out together, one message
/// per process, rather than one message per process and bundle.
fn spawn_publisher(session: &Session, mut rx: UnboundedReceiver<Released>, hub: Arc<Mutex<GeneHub>>) {
    let session = session.clone();
    tokio::spawn(async move {
        while let Some(first) = rx.recv().await {
            let mut out = first;
            while let Ok(more) = rx.try_recv() {
                out.extend(more);
            }
            hub.lock().unwrap_or_else(|e| e.into_inner()).flush(&mut out);
            for (key, bytes) in out {
                let _ = zenoh_bus::put(&session, &key, bytes).await;
            }
        }
    });
}

struct CellAgg {
    expect: Vec<AgentRange>,
    /// Each process's batch, nested as it sent it (checked, never decoded here unless
    /// some process reads this cell's topic; only then are its bytes kept).
    got: Vec<(AgentRange, Vec<u8>)>,
    sent: bool,
    /// The hosting processes sharing the cell.
    hosting: Vec<AgentRange>,
}

/// What a hosting process has still to be sent this step: other processes' packs
/// (indices in [`GeneHub::packs`]) and the cells that became complete.
#[derive(Default)]
struct HostOut {
    packs: Vec<usize>,
    complete: Vec<u32>,
}

impl GeneHub {
    /// Open step `step`: `cells` are the shared cells with the processes centred in
    /// each; `hosting` the processes served with [`HostGenes`].
    fn begin(&mut self, step: u64, cells: CellMap<Vec<AgentRange>>, per_cell: bool, hosting: &[AgentRange]) {
        self.step = step;
        self.begun = step;
        self.per_cell = per_cell;
        self.hostile = 0;
        self.hosts.clear();
        self.packs.clear();
        self.cells = cells
            .into_iter()
            .map(|(c, expect)| {
                let hosting: Vec<AgentRange> = expect.iter().filter(|r| hosting.contains(r)).copied().collect();
                for r in &hosting {
                    self.hosts.entry(*r).or_default();
                }
                (c, CellAgg { expect, got: Vec::new(), sent: false, hosting })
            })
            .collect();
    }

    /// Say which processes each incomplete cell still waits for (`geese::flow` trace).
    fn trace_incomplete(&self) {
        if !tracing::enabled!(target: "geese::flow", tracing::Level::TRACE) {
            return;
        }
        for (c, a) in self.cells.iter().filter(|(_, a)| !a.sent) {
            let got: Vec<AgentRange> = a.got.iter().map(|(r, _)| *r).collect();
            tracing::trace!(target: "geese::flow", "step {}: cell {c} expects {:?}, got {:?}", self.step, a.expect, got);
        }
    }

    /// Hand what filing released to the publisher, and wake it to send the hosting
    /// processes what the hub holds for them.
    fn release(&self, r: Released) {
        let _ = self.publish.send(r);
    }

    /// File one batch published on its cell's key.
    fn on_batch(&mut self, key: &str, bytes: &[u8]) -> Released {
        let Parsed::Genes { cx, cy, from: Some(from) } = keys::parse(&self.run, key) else {
            self.hostile += 1;
            return Released::default();
        };
        let Ok(batch) = decode::<GeneBatchHead>(bytes) else {
            self.hostile += 1;
            return Released::default();
        };
        let cell_ok =
            cx < self.geom.cols() && cy < self.geom.rows() && batch.cell == (cy * self.geom.cols() + cx) as u32;
        if !cell_ok {
            self.hostile += 1;
            return Released::default();
        }
        let mut out = Released::default();
        // The body after the version byte is the batch's nested encoding.
        let nested = Raw(&bytes[1..]);
        if self.file(from, &batch, nested.0, &mut out) {
            self.forward(from, &[(batch.cell, nested)], None);
        }
        out
    }

    /// File the batches of one process's bundle.
    fn on_bundle(&mut self, key: &str, bytes: &[u8]) -> Released {
        let (Parsed::GeneBundle { from }, Ok(bundle)) =
            (keys::parse(&self.run, key), decode::<geese_proto::net::GeneBundle>(bytes))
        else {
            self.hostile += 1;
            return Released::default();
        };
        let mut out = Released::default();
        let mut scratch = std::mem::take(&mut self.unpacked);
        match unpack(bundle.packed.0, &mut scratch) {
            Ok(nested)
                if nested.len() == 1 && nested[0].open::<GeneBatchCell>().is_ok_and(|h| h.cell == AHEAD_CELL) =>
            {
                self.file_ahead(from, bundle.step, nested[0], bundle.packed.0);
            }
            Ok(nested) => {
                let mut kept: Vec<(u32, Raw)> = Vec::with_capacity(nested.len());
                for raw in &nested {
                    let Ok(batch) = raw.open::<GeneBatchHead>() else {
                        self.hostile += 1;
                        continue;
                    };
                    if batch.step != bundle.step || batch.cell as usize >= self.geom.cell_count() {
                        self.hostile += 1;
                        continue;
                    }
                    if self.file(from, &batch, raw.0, &mut out) {
                        kept.push((batch.cell, *raw));
                    }
                }
                // Forwarded as it came when every batch passed (the usual case).
                let whole = kept.len() == nested.len();
                self.forward(from, &kept, whole.then_some(bundle.packed.0));
            }
            Err(_) => self.hostile += 1,
        }
        self.unpacked = scratch;
        out
    }

    /// Keep a pack sent ahead (`packed`, holding `nested`) of the process speaking for
    /// `from`, once checked: honest, for the step after the one begun (the only one a
    /// process sends genes ahead for), and the first of that step (as for a cell's
    /// batches). One for a later step is hostile; one for an earlier step is stale.
    fn file_ahead(&mut self, from: AgentRange, step: u64, nested: Raw, packed: &[u8]) {
        let Ok(batch) = nested.open::<GeneBatchHead>() else {
            self.hostile += 1;
            return;
        };
        if batch.step != step || !batch.honest(from) || step > self.begun + 1 {
            self.hostile += 1;
            return;
        }
        if step <= self.begun || self.ahead.get(&from).is_some_and(|(s, _)| *s == step) {
            return;
        }
        self.ahead.insert(from, (step, packed.to_vec()));
    }

    /// The packs sent ahead for step `step`, by sender; all others are dropped.
    fn take_ahead(&mut self, step: u64) -> Vec<(AgentRange, Vec<u8>)> {
        self.ahead.drain().filter(|(_, (s, _))| *s == step).map(|(from, (_, p))| (from, p)).collect()
    }

    /// File one batch (`nested`: its encoding) of the process speaking for `from`; what
    /// completes goes to `out`. Returns whether the batch was taken (checked, of this
    /// step, of a shared cell the sender is expected in, and its first there).
    fn file(&mut self, from: AgentRange, batch: &GeneBatchHead, nested: &[u8], out: &mut Released) -> bool {
        if !batch.honest(from) {
            // Genes of agents the sender does not speak for, or a malformed genome.
            self.hostile += 1;
            return false;
        }
        if batch.step != self.step {
            if batch.step > self.step {
                self.hostile += 1;
            }
            return false;
        }
        let Some(agg) = self.cells.get_mut(&batch.cell) else { return false };
        if agg.sent || !agg.expect.contains(&from) || agg.got.iter().any(|(r, _)| *r == from) {
            return false;
        }
        let kept = if self.per_cell { nested.to_vec() } else { Vec::new() };
        agg.got.push((from, kept));
        self.complete(batch.cell, out);
        true
    }

    /// Queue the taken batches of `from` (cell, encoding) for the hosting processes that
    /// share one of their cells, at once rather than when the cells are complete: as
    /// `packed`, the pack they came in, when given, else packed here.
    fn forward(&mut self, from: AgentRange, kept: &[(u32, Raw)], packed: Option<&[u8]>) {
        let mut to: Vec<AgentRange> = Vec::new();
        for (cell, _) in kept {
            for h in self.cells.get(cell).into_iter().flat_map(|a| &a.hosting) {
                if *h != from && !to.contains(h) {
                    to.push(*h);
                }
            }
        }
        if to.is_empty() {
            return;
        }
        let bytes = match packed {
            Some(p) => p.to_vec(),
            None => {
                let raws: Vec<Raw> = kept.iter().map(|(_, r)| *r).collect();
                match pack(&raws) {
                    Ok(p) => p,
                    Err(_) => return,
                }
            }
        };
        self.packs.push(bytes);
        let at = self.packs.len() - 1;
        for h in to {
            if let Some(o) = self.hosts.get_mut(&h) {
                o.packs.push(at);
            }
        }
    }

    /// A process left: stop waiting for it.
    fn forget(&mut self, gone: AgentRange) -> Released {
        self.hosts.remove(&gone);
        self.ahead.remove(&gone);
        let cells: Vec<u32> = self.cells.keys().copied().collect();
        let mut out = Released::default();
        for c in cells {
            if let Some(agg) = self.cells.get_mut(&c) {
                agg.expect.retain(|r| *r != gone);
            }
            self.complete(c, &mut out);
        }
        out
    }

    /// Send every hosting process what it has still to be sent: one [`HostGenes`] with
    /// the other processes' packs filed since, and the cells complete since.
    ///
    /// Packs go out as they arrive rather than once a process's cells are complete:
    /// with 1,000 agents in 10 processes every process shares cells with every other,
    /// so all cells completed at the last bundle, and the world then relayed ~130 kB to
    /// each of ten processes in turn while the first served were already computing.
    /// Streamed, most of it goes out while the processes wait at the barrier anyway.
    fn flush(&mut self, out: &mut Released) {
        for (to, o) in self.hosts.iter_mut() {
            if o.packs.is_empty() && o.complete.is_empty() {
                continue;
            }
            let packs: Vec<Raw> = o.packs.iter().filter_map(|&i| self.packs.get(i).map(|b| Raw(b))).collect();
            let cells = std::mem::take(&mut o.complete);
            let size = nested_size(&packs, 5 * cells.len());
            if let Ok(bytes) = encode_sized(&HostGenes { step: self.step, cells, packs }, size) {
                out.push((keys::host_genes(&self.run, *to), bytes));
            }
            o.packs.clear();
        }
    }

    /// If every process expected in `cell` has spoken: its aggregate for per-cell
    /// readers, and the cell noted as complete for the hosting processes sharing it.
    fn complete(&mut self, cell: u32, out: &mut Released) {
        let Some(agg) = self.cells.get_mut(&cell) else { return };
        if agg.sent || agg.got.is_empty() || !agg.expect.iter().all(|r| agg.got.iter().any(|(g, _)| g == r)) {
            return;
        }
        agg.sent = true;
        if self.per_cell {
            let mut all = GeneBatch { step: self.step, cell, genes: Vec::new(), absent: Vec::new() };
            for (_, nested) in &agg.got {
                // Checked when filed; a genome's codons are only decoded here.
                let Ok(b) = Raw(nested).open::<GeneBatch>() else { continue };
                all.genes.extend(b.genes);
                all.absent.extend(b.absent);
            }
            all.genes.sort_by_key(|g| g.from);
            all.absent.sort_unstable();
            let (cx, cy) = self.geom.cell_col_row(cell);
            if let Ok(bytes) = encode(&all) {
                out.push((keys::cell_genes(&self.run, cx, cy), bytes));
            }
        }
        // The hosting processes here hear that the cell is complete (all its batches
        // went, or go, to them before that: [`GeneHub::flush`]).
        for to in &agg.hosting {
            if let Some(o) = self.hosts.get_mut(to) {
                o.complete.push(cell);
            }
        }
    }
}

struct Server<'a> {
    session: &'a Session,
    spec: NetRunSpec,
    world: World,
    info: Arc<Mutex<InfoState>>,
    gather: Arc<Mutex<Gather>>,
    gathered: Arc<Notify>,
    genes: Arc<Mutex<GeneHub>>,
    run: String,
    n: usize,
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
}

impl<'a> Server<'a> {
    fn new(
        session: &'a Session,
        spec: NetRunSpec,
        world: World,
        info: Arc<Mutex<InfoState>>,
        gather: Arc<Mutex<Gather>>,
        gathered: Arc<Notify>,
        genes: Arc<Mutex<GeneHub>>,
    ) -> Self {
        let n = spec.agents as usize;
        let loss_stream = derive(spec.seed, Owner::World, Purpose::Loss) ^ LOSS_SALT_INTENT;
        Server {
            session,
            run: spec.run.clone(),
            spec,
            world,
            info,
            gather,
            gathered,
            genes,
            n,
            hosts: BTreeMap::new(),
            narrow: BTreeMap::new(),
            orchestrator: false,
            revive: Vec::new(),
            scheduled: Vec::new(),
            stop: false,
            stop_requested: false,
            announced: None,
            percept_keys: HashMap::new(),
            loss_stream,
            steps_done: 0,
            counters: NetCounters::default(),
        }
    }

    fn covered(&self) -> bool {
        let mut c = vec![false; self.n];
        for r in self.hosts.keys() {
            for id in r.ids() {
                if let Some(x) = c.get_mut(id as usize) {
                    *x = true;
                }
            }
        }
        c.iter().all(|&x| x)
    }

    fn ready(&self) -> bool {
        self.covered() && (self.orchestrator || !self.spec.expect_orchestrator)
    }

    /// Present agent processes that read no cell topic (hosting processes): they get
    /// their percepts and genes on keys of their own.
    fn hosting(&self) -> Vec<AgentRange> {
        self.hosts.keys().filter(|r| !self.narrow.contains_key(r)).copied().collect()
    }

    fn gather(&self) -> std::sync::MutexGuard<'_, Gather> {
        // A poisoned lock only means a callback panicked; the data is still usable.
        self.gather.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Returns whether the run completed all its steps.
    async fn run(&mut self, rx: &mut UnboundedReceiver<Event>) -> Result<bool> {
        // Join: wait for every expected process.
        let join_deadline = Instant::now() + Duration::from_millis(self.spec.deadlines.join_ms as u64);
        while !self.ready() {
            let left = join_deadline.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, rx.recv()).await {
                Ok(Some(ev)) => self.handle(ev, 0),
                Ok(None) => bail!("event channel closed"),
                Err(_) => bail!(
                    "join deadline ({} ms): agent processes cover {} of {} agents{}",
                    self.spec.deadlines.join_ms,
                    self.hosts.keys().map(|r| r.len()).sum::<u32>(),
                    self.n,
                    if self.spec.expect_orchestrator && !self.orchestrator { ", orchestrator absent" } else { "" }
                ),
            }
            if self.stop {
                return Ok(false);
            }
        }
        self.revive.clear();
        eprintln!("geese-world: {} agent processes present, starting {} steps", self.hosts.len(), self.spec.steps);
        while self.world.step() <= self.spec.steps {
            self.step(rx).await?;
            if self.stop {
                return Ok(false);
            }
        }
        Ok(true)
    }

    async fn step(&mut self, rx: &mut UnboundedReceiver<Event>) -> Result<()> {
        let step = self.world.step();
        // Between steps: revivals and control-plane perturbations.
        for id in std::mem::take(&mut self.revive) {
            if !self.spec.bare && self.world.bodies().get(id as usize).is_some_and(|b| !b.live) {
                self.world.revive(id);
            }
        }
        for (at, change) in std::mem::take(&mut self.scheduled) {
            self.world.schedule(at, change);
        }
        self.counters = NetCounters::default();
        if let Ok(mut s) = self.info.lock() {
            s.next_step = step;
            s.cells = if self.spec.bare { Vec::new() } else { body_cells(&self.world) };
        }
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
        // The hosting processes each process shares a cell with.
        let mut partners: HashMap<AgentRange, Vec<AgentRange>> = HashMap::new();
        let hosts: Vec<AgentRange> = self.hosts.keys().copied().collect();
        // Open the gathering before anything goes out: fast answers must find it open.
        {
            let bare = self.spec.bare;
            let bodies = self.world.bodies();
            let expected = |i: usize| {
                if bare {
                    hosts.iter().any(|r| r.contains(i as u32))
                } else {
                    bodies[i].live
                }
            };
            let mut g = self.gather.lock().unwrap_or_else(|e| e.into_inner());
            g.begin(step, expected);
        }
        if !self.spec.bare {
            // Cells whose centred live agents belong to more than one process: their genes
            // go through the hub (lateral transfer on only).
            let mut shared: CellMap<Vec<AgentRange>> = CellMap::default();
            if self.world.regime().lateral_transfer {
                let g = self.world.geometry();
                // Bodies come in id order and a process speaks for contiguous ids, so a
                // body's process is mostly the previous body's (the first in order that
                // contains its id, either way).
                let mut owner: Option<AgentRange> = None;
                for b in self.world.bodies().iter().filter(|b| b.live) {
                    if !owner.is_some_and(|r| r.contains(b.id)) {
                        owner = hosts.iter().find(|r| r.contains(b.id)).copied();
                    }
                    if let Some(r) = owner {
                        let v = shared.entry(g.cell_of(b.pos)).or_default();
                        if !v.contains(&r) {
                            v.push(r);
                        }
                    }
                }
                shared.retain(|_, v| v.len() > 1);
            }
            let mut hub = self.genes.lock().unwrap_or_else(|e| e.into_inner());
            let packs = hub.take_ahead(step);
            // From every process with a live agent (one without takes no part).
            let bodies = self.world.bodies();
            let takes_part = |h: &AgentRange| h.ids().any(|id| bodies.get(id as usize).is_some_and(|b| b.live));
            ahead &= hosting.iter().filter(|h| takes_part(h)).all(|h| packs.iter().any(|(from, _)| from == h));
            if ahead {
                for ranges in shared.values() {
                    for a in ranges {
                        let p = partners.entry(*a).or_default();
                        for b in ranges {
                            if b != a && !p.contains(b) {
                                p.push(*b);
                            }
                        }
                    }
                }
                ahead_packs = packs;
                shared.clear();
            }
            hub.begin(step, shared, per_cell, &hosting);
        }
        // 1. The tick (bare: every step; otherwise when the live set changed), then the
        //    percepts of every occupied cell.
        if self.spec.bare {
            zenoh_bus::put(self.session, &keys::tick(&self.run), encode(&Tick { step, cells: Vec::new() })?).await?;
        } else {
            let cells = cells_of(&self.world);
            let live: Vec<u32> = cells.iter().map(|&c| if c == NO_CELL { NO_CELL } else { 0 }).collect();
            if self.announced.as_ref() != Some(&live) {
                zenoh_bus::put(self.session, &keys::tick(&self.run), encode(&Tick { step, cells })?).await?;
                self.announced = Some(live);
            }
            let percepts = self.world.percepts();
            tracing::trace!(target: "geese::flow", "step {step}: {} percepts (per cell: {per_cell})", percepts.len());
            // Per-cell topics only while some process reads them.
            if per_cell {
                for p in &percepts {
                    let ke = self.percept_key(p.cell);
                    let bytes = encode(p)?;
                    self.session.put(ke, bytes).congestion_control(CongestionControl::Block).await.map_err(zerr)?;
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
                let g = self.world.geometry();
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
                    zenoh_bus::put(self.session, &keys::host_percepts(&self.run, to), bytes).await?;
                }
            }
        }
        // 2–3 happen in the agent processes. 4. Gather intents.
        let started = Instant::now();
        let deadline =
            tokio::time::Instant::from_std(started + Duration::from_millis(self.spec.deadlines.intent_ms as u64));
        loop {
            let pending = self.gather().pending;
            if pending == 0 || self.stop {
                break;
            }
            tokio::select! {
                _ = self.gathered.notified() => {}
                ev = rx.recv() => match ev {
                    Some(ev) => self.handle(ev, step),
                    None => bail!("event channel closed"),
                },
                _ = tokio::time::sleep_until(deadline) => {
                    // Read again: answers may have come in since the loop last looked.
                    let pending = self.gather().pending;
                    if pending > 0 {
                        self.counters.intents_late = pending as u32;
                        tracing::warn!("step {step}: {pending} intents missing at the deadline");
                        self.genes.lock().unwrap_or_else(|e| e.into_inner()).trace_incomplete();
                    }
                    break;
                }
            }
        }
        self.counters.wait_us = started.elapsed().as_micros().min(u32::MAX as u128) as u32;
        if self.stop {
            return Ok(());
        }
        let (mut intents, answered_live, gc) = {
            let mut g = self.gather();
            g.step = 0;
            let answered_live = (0..self.n).filter(|&i| g.expected[i] && g.answered[i]).count();
            let intents = std::mem::replace(&mut g.intents, vec![None; self.n]);
            (intents, answered_live, g.counters)
        };
        let hub_hostile = {
            let mut h = self.genes.lock().unwrap_or_else(|e| e.into_inner());
            h.step = 0;
            std::mem::take(&mut h.hostile)
        };
        let c = &mut self.counters;
        c.hostile += hub_hostile;
        c.percepts_lost += gc.percepts_lost;
        c.percepts_missing += gc.percepts_missing;
        c.genes_late += gc.genes_late;
        c.hostile += gc.hostile;
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
            report.missing_intents = (live - answered_live.min(live)) as u32;
        }
        self.counters.processes = self.hosts.len() as u32;
        let msg = ReportMsg::Step(NetReport { report, net: self.counters });
        zenoh_bus::put(self.session, &keys::report(&self.run), encode(&msg)?).await?;
        self.steps_done = step;
        Ok(())
    }

    /// The percept key of a cell (plain key expressions: a key declared by this session
    /// would not be known to clients that connect later, e.g. a restarted agent).
    fn percept_key(&mut self, cell: u32) -> String {
        let (cx, cy) = self.world.geometry().cell_col_row(cell);
        let run = &self.run;
        self.percept_keys.entry(cell).or_insert_with(|| keys::cell_percept(run, cx, cy)).clone()
    }

    fn handle(&mut self, ev: Event, step: u64) {
        match ev {
            Event::Presence { alive, key } => match keys::parse(&self.run, &key) {
                Parsed::AgentsPresence { agents } => {
                    keys::tally(&mut self.hosts, agents, alive);
                    if alive {
                        self.revive.extend(agents.ids().filter(|&id| (id as usize) < self.n));
                    } else {
                        let mut hub = self.genes.lock().unwrap_or_else(|e| e.into_inner());
                        let ready = hub.forget(agents);
                        hub.release(ready);
                        drop(hub);
                        // Its agents stop here: bodies idle, carried items dropped.
                        for id in agents.ids().filter(|&id| (id as usize) < self.n) {
                            if !self.hosts.keys().any(|r| r.contains(id)) {
                                self.world.kill(id);
                                self.gather().forget(id as usize);
                                self.revive.retain(|&r| r != id);
                            }
                        }
                        eprintln!("geese-world: agent process {agents} left at step {step}");
                    }
                }
                Parsed::CellsPresence { agents } => keys::tally(&mut self.narrow, agents, alive),
                Parsed::OrchestratorPresence => {
                    if alive {
                        self.orchestrator = true;
                    } else if self.spec.expect_orchestrator {
                        eprintln!("geese-world: the orchestrator left; stopping");
                        self.stop = true;
                    }
                }
                _ => {}
            },
            Event::Ctl(bytes) => match decode::<Control>(&bytes) {
                Ok(Control::Stop) => {
                    self.stop = true;
                    self.stop_requested = true;
                }
                Ok(Control::Schedule { at_step, change }) => self.scheduled.push((at_step, change)),
                Ok(Control::Start) => {}
                Err(_) => self.counters.hostile += 1,
            },
            Event::Signal => {
                eprintln!("geese-world: signal received; stopping");
                self.stop = true;
            }
        }
    }
}
