//! `geese-agent`: one agent, or `--agents K` agents hosted on one shared session, in one
//! process of a distributed GEESE run (DESIGN.md §2–4).
//!
//! A thin async shell around the sans-IO [`Host`] (`geese_agent::host`, where the
//! protocol of a step is described and tested): Zenoh callbacks queue what arrives, the
//! loop hands it to the host and carries out what [`Host::next`] returns — publish the
//! gene bundle or the intents, subscribe to or drop a cell's topics, or wait for the
//! next message until the deadline the host names.
//!
//! The process learns everything else (configuration, grammar, seed, where its agents
//! are) from the world's `ctl/info` queryable, so agents on another host need nothing
//! but `--run` and a way to reach the router. It exits when the world's liveliness
//! token disappears, on the control plane's stop, or on SIGINT/SIGTERM.
//!
//! It uses the system allocator, not mimalloc as `geese` and `geese-world` do: an agent
//! process needs about 1 MiB of heap, and mimalloc kept 10 MiB resident for it (its
//! per-thread, per-size-class pages), against under 2 MiB with glibc's malloc — the
//! difference between a thousand agent processes fitting on one machine or not. Ten
//! processes hosting 100 learners each spent the same CPU time with either (5.5 s of
//! user time for 400 steps, docs/PERFORMANCE.md).
use anyhow::{bail, Context, Result};
use clap::{Parser, ValueEnum};
use geese_agent::host::{Host, Input, Next, Out};
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::zenoh_bus::{self, CommonArgs, Role};
use geese_proto::{decode, Control};
use std::collections::HashMap;
use std::time::{Duration, Instant};
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};
use zenoh::bytes::ZBytes;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::sample::SampleKind;
use zenoh::Session;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum SubscribeArg {
    /// `all`. It used to be `cells` for a process hosting fewer agents than a quarter of
    /// the cells; `all` spares the subscription churn of agents changing cells, lets
    /// genes go ahead with the percepts (one barrier a step instead of two) and has no
    /// first-step race between a process's cell subscriptions and its cell-mates'
    /// genes. 100 one-agent processes learnt at 54–76 steps/s with `all` against 48–61
    /// with `cells`, interleaved (issue 29, docs/PROTOCOL.md).
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
    /// At the end, write this process's agents as population members (JSON) here.
    #[arg(long)]
    population_out: Option<std::path::PathBuf>,
    /// When the world's presence goes (a lost link, a partitioned host), wait up to MS
    /// milliseconds for it to come back and join again with fresh agents, as a restarted
    /// process would [default 0: exit].
    #[arg(long, value_name = "MS", default_value_t = 0)]
    rejoin_ms: u64,
}

/// A task that ends with the membership that started it.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// How one membership of the run ended.
enum Ended {
    /// A stop command, a signal, or the run's end.
    Stopped,
    /// The world's presence token went.
    WorldLeft,
}

/// What the callbacks queue for the loop, as received.
enum Event {
    Tick(Vec<u8>),
    Percept {
        cell: u32,
        bytes: Vec<u8>,
    },
    Genes {
        cell: u32,
        bytes: Vec<u8>,
    },
    /// [`HostPercepts`](geese_proto::net::HostPercepts), not copied: the large messages.
    Percepts(ZBytes),
    HostGenes(ZBytes),
    Hostile,
    /// The live viewer asks for an agent's detail.
    Detail(zenoh::query::Query),
    Presence {
        alive: bool,
        key: String,
    },
    Stop,
}

fn main() -> Result<()> {
    // Without RUST_LOG: warnings, but not Zenoh's report of data that arrives for a cell
    // subscription just undeclared (harmless: the cell is no longer needed).
    // Zenoh logs a session's configuration, password included, at debug level.
    let filter = match tracing_subscriber::EnvFilter::try_from_default_env() {
        Ok(f) => f.add_directive(geese_proto::zenoh_bus::HIDE_SECRETS_DIRECTIVE.parse()?),
        Err(_) => tracing_subscriber::EnvFilter::new("warn,zenoh::api::session=off"),
    };
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
    // A signal ends the process whichever membership it is in.
    let (signalled_tx, signalled) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        zenoh_bus::shutdown_signal().await;
        let _ = signalled_tx.send(true);
    });
    let mut patience = Duration::from_millis(args.join_timeout_ms);
    let mut rejoining = false;
    loop {
        let mut sig = signalled.clone();
        let ended = tokio::select! {
            r = member(&args, range, patience, sig.clone()) => r,
            _ = sig.wait_for(|s| *s) => return Ok(()),
        };
        match ended {
            Ok(Ended::WorldLeft) if args.rejoin_ms > 0 => {
                tracing::warn!("agents {range}: the world left; waiting up to {} ms to join again", args.rejoin_ms);
                patience = Duration::from_millis(args.rejoin_ms);
                rejoining = true;
            }
            Ok(_) => return Ok(()),
            // The world did not come back in time: the run is over for us.
            Err(e) if rejoining => {
                tracing::warn!("agents {range}: not joined again: {e:#}");
                return Ok(());
            }
            Err(e) => return Err(e),
        }
    }
}

/// Join the run (waiting up to `patience` for the world), take part until it ends for
/// us, and say how it ended.
async fn member(
    args: &Args,
    range: AgentRange,
    patience: Duration,
    mut signalled: tokio::sync::watch::Receiver<bool>,
) -> Result<Ended> {
    let session = zenoh_bus::open(&args.zenoh, Role::Client).await?;
    let run = args.run.clone();
    let (tx, mut rx) = unbounded_channel::<Event>();
    // The world's presence first: we must notice it going away even while joining.
    // (Other processes' tokens are the world's business: it says who is in a step.)
    let t = tx.clone();
    let _presence = session
        .liveliness()
        .declare_subscriber(keys::world_presence(&run))
        .history(true)
        .callback(move |s| {
            let alive = s.kind() == SampleKind::Put;
            let _ = t.send(Event::Presence { alive, key: s.key_expr().as_str().to_owned() });
        })
        .await
        .map_err(zerr)?;
    let t = tx.clone();
    let _signal = AbortOnDrop(tokio::spawn(async move {
        let _ = signalled.wait_for(|s| *s).await;
        let _ = t.send(Event::Stop);
    }));
    let info = zenoh_bus::fetch_run_info(&session, &run, patience).await;
    let (info, zenoh_rt) = match info {
        Ok(i) => i,
        Err(e) => {
            let _ = session.close().await;
            return Err(e.into());
        }
    };
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
        .callback(move |s| {
            let ev = match decode::<Control>(&s.payload().to_bytes()) {
                Ok(Control::Stop) => Event::Stop,
                _ => Event::Hostile,
            };
            let _ = t.send(ev);
        })
        .await
        .map_err(zerr)?;
    let t = tx.clone();
    let _detail = session
        .declare_queryable(keys::agents_detail(&run, range))
        .callback(move |q| {
            let _ = t.send(Event::Detail(q));
        })
        .await
        .map_err(zerr)?;
    let wide = match args.subscribe {
        SubscribeArg::All => true,
        SubscribeArg::Cells => false,
        SubscribeArg::Auto => true,
    };
    let geom = info.geometry;
    let mut host = Host::new(range, info, wide)?;
    let mut shell = Shell {
        session: session.clone(),
        run: run.clone(),
        range,
        geom,
        tx: tx.clone(),
        subs: HashMap::new(),
        wide_subs: Vec::new(),
        intents: zenoh_bus::publisher(&session, keys::agents_action(&run, range)).await?,
        genes_key: keys::agents_genes(&run, range),
    };
    if wide {
        shell.subscribe_host_keys().await?;
    }
    let first = host.start();
    shell.carry_out(first).await?;
    // Declared after the subscriptions, so the world sees us only once we can hear it
    // (and, reading cells one by one, that it must publish them so before that).
    let cells_token = if wide {
        None
    } else {
        Some(session.liveliness().declare_token(keys::cells_presence(&run, range)).await.map_err(zerr)?)
    };
    let token = session.liveliness().declare_token(keys::agents_presence(&run, range)).await.map_err(zerr)?;
    let population_out = args.population_out.clone();
    let work = async move {
        let r = shell.drive(&mut host, &mut rx).await;
        host.report_phases();
        if let Some(path) = population_out {
            let members = host.members();
            let bytes = serde_json::to_vec(&members)?;
            std::fs::write(&path, bytes).with_context(|| format!("cannot write {}", path.display()))?;
        }
        r.map(|_| if host.world_left() { Ended::WorldLeft } else { Ended::Stopped })
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

/// The Zenoh side of a host: its session, publisher and subscriptions.
struct Shell {
    session: Session,
    run: String,
    range: AgentRange,
    geom: geese_proto::Geometry,
    tx: UnboundedSender<Event>,
    /// The percept and gene subscriptions of each cell (reading cells one by one).
    subs: HashMap<u32, (Subscriber<()>, Subscriber<()>)>,
    wide_subs: Vec<Subscriber<()>>,
    intents: Publisher<'static>,
    /// Where this process's gene bundles go (built once, not every step).
    genes_key: String,
}

impl Shell {
    /// Hand the host what arrives and carry out what it asks, until it stops.
    async fn drive(&mut self, host: &mut Host, rx: &mut UnboundedReceiver<Event>) -> Result<()> {
        loop {
            match host.next(Instant::now()) {
                Next::Act(out) => self.carry_out(out).await?,
                Next::Stopped => return Ok(()),
                Next::Wait(deadline) => {
                    let ev = match deadline {
                        Some(d) => match tokio::time::timeout_at(tokio::time::Instant::from_std(d), rx.recv()).await {
                            Ok(ev) => ev,
                            Err(_) => continue,
                        },
                        None => rx.recv().await,
                    };
                    let Some(ev) = ev else { return Ok(()) };
                    absorb(host, &self.run, self.range, ev);
                    // Take whatever else is queued before deciding again.
                    while let Ok(ev) = rx.try_recv() {
                        absorb(host, &self.run, self.range, ev);
                    }
                }
            }
        }
    }

    async fn carry_out(&mut self, out: Vec<Out>) -> Result<()> {
        for o in out {
            match o {
                // Not a declared publisher: with one, the three-host run lost the first
                // step's genes once in four suite runs (NOTES, "Logins and access
                // control"; QUIC's stream per priority is the suspect, not proven).
                Out::Genes(bytes) => zenoh_bus::put(&self.session, &self.genes_key, bytes).await?,
                Out::Intents(bytes) => self.intents.put(bytes).await.map_err(zerr)?,
                Out::Subscribe(cell) => self.subscribe_cell(cell).await?,
                Out::Unsubscribe(cell) => {
                    self.subs.remove(&cell);
                }
            }
        }
        Ok(())
    }

    /// Our cells' percepts and genes, from the world, one message per step each.
    async fn subscribe_host_keys(&mut self) -> Result<()> {
        for key in [keys::host_percepts(&self.run, self.range), keys::host_genes(&self.run, self.range)] {
            let (t, run, range) = (self.tx.clone(), self.run.clone(), self.range);
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
        Ok(())
    }

    async fn subscribe_cell(&mut self, cell: u32) -> Result<()> {
        if self.subs.contains_key(&cell) {
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
        self.subs.insert(cell, (percept, genes));
        Ok(())
    }
}

fn absorb(host: &mut Host, run: &str, range: AgentRange, ev: Event) {
    let now = Instant::now();
    match ev {
        Event::Tick(b) => host.absorb(Input::Tick(&b), now),
        Event::Percept { cell, bytes } => host.absorb(Input::Percept { cell, bytes: &bytes }, now),
        Event::Genes { cell, bytes } => host.absorb(Input::CellGenes { cell, bytes: &bytes }, now),
        Event::Percepts(z) => host.absorb(Input::HostPercepts(&z.to_bytes()), now),
        Event::HostGenes(z) => host.absorb(Input::HostGenes(&z.to_bytes()), now),
        Event::Hostile => host.absorb(Input::Hostile, now),
        Event::Presence { alive, key } => host.absorb(Input::Presence { alive, key: &key }, now),
        Event::Stop => host.absorb(Input::Stop, now),
        Event::Detail(q) => reply_detail(host, run, range, q),
    }
}

/// Answer the live viewer's question about one of our agents (between two decisions,
/// from the host's own loop: the learners are not shared with any other thread). A key
/// that names no agent of ours gets no answer; the process hosting it answers.
fn reply_detail(host: &Host, run: &str, range: AgentRange, q: zenoh::query::Query) {
    use zenoh::Wait;
    let key = q.key_expr().as_str();
    let id = key.rsplit('/').next().and_then(AgentRange::parse).filter(|r| r.len() == 1).map(|r| r.first);
    let Some(detail) = id.and_then(|id| host.detail(id)) else { return };
    match geese_proto::encode(&detail) {
        Ok(bytes) => {
            if let Err(e) = q.reply(keys::agent_detail_reply(run, range, detail.id), bytes).wait() {
                tracing::debug!("detail reply not sent: {e}");
            }
        }
        Err(e) => tracing::warn!("detail of agent {}: {e}", detail.id),
    }
}

fn zerr(e: zenoh::Error) -> anyhow::Error {
    anyhow::Error::new(geese_proto::zenoh_bus::zerr(e))
}
