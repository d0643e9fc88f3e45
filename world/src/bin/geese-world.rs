//! `geese-world`: the world server of a distributed GEESE run (DESIGN.md §2–4).
//!
//! A thin async shell around the sans-IO [`Server`] (`geese_world::server`): Zenoh
//! callbacks hand it what arrives (presence, control, intents, genes), a publisher task
//! sends what the gene hub releases, and the loop publishes whatever [`Server::next`]
//! returns, sleeping until the next message or the deadline it names. The protocol
//! itself — the intent gathering, the gene hub, step sequencing and every deadline —
//! lives and is tested in the library.
//!
//! Normally started by `geese run --processes N`, which writes the `--spec` file.
use anyhow::{bail, Context, Result};
use clap::Parser;
use geese_proto::encode;
use geese_proto::keys;
use geese_proto::net::NetRunSpec;
use geese_proto::zenoh_bus::{self, CommonArgs};
use geese_world::hub::Released;
use geese_world::locality::Window;
use geese_world::server::{Next, Server};
use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};
use tokio::sync::Notify;
use zenoh::sample::SampleKind;
use zenoh::Session;

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
    /// Count the locality map (Fig. 5) over steps FROM to TO, both included (step 1 is
    /// the first step).
    #[arg(long, value_name = "FROM:TO", requires = "locality_out")]
    locality: Option<Window>,
    /// Where to write the locality map (CSV: x,y,class,count) when the run ends.
    #[arg(long, value_name = "FILE", requires = "locality")]
    locality_out: Option<PathBuf>,
}

/// mimalloc: the step loop allocates many small, short-lived buffers.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> Result<()> {
    // Without RUST_LOG: warnings, and the server's notes on processes joining and
    // leaving.
    // Zenoh logs a session's configuration, password included, at debug level.
    let filter = match tracing_subscriber::EnvFilter::try_from_default_env() {
        Ok(f) => f.add_directive(zenoh_bus::HIDE_SECRETS_DIRECTIVE.parse()?),
        Err(_) => tracing_subscriber::EnvFilter::new("warn,geese_world=info"),
    };
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    let args = Args::parse();
    let text = std::fs::read_to_string(&args.spec).with_context(|| format!("cannot read {}", args.spec.display()))?;
    let spec: NetRunSpec =
        serde_json::from_str(&text).with_context(|| format!("{} is not a run specification", args.spec.display()))?;
    if !keys::valid_run_name(&spec.run) {
        bail!("run name {:?} must be one key chunk of letters, digits, '_', '-', '.'", spec.run);
    }
    let rt = zenoh_bus::runtime(args.threads)?;
    let locality = args.locality.zip(args.locality_out);
    rt.block_on(serve(args.zenoh, spec, locality))
}

/// The server, shared by the Zenoh callbacks and the loop (never held across an await).
type Shared = Arc<Mutex<Server>>;

fn lock(s: &Shared) -> MutexGuard<'_, Server> {
    // A poisoned lock only means a callback panicked; the state is still usable.
    s.lock().unwrap_or_else(|e| e.into_inner())
}

async fn serve(common: CommonArgs, spec: NetRunSpec, locality: Option<(Window, PathBuf)>) -> Result<()> {
    let run = spec.run.clone();
    let mut s = Server::new(spec, Instant::now())?;
    if let Some((w, _)) = &locality {
        s.record_locality(*w);
    }
    let server: Shared = Arc::new(Mutex::new(s));
    let (session, locators) = zenoh_bus::open_world(&common).await?;
    // Woken whenever an input may let the loop go on (the last intent of a step, a
    // process leaving, a stop).
    let wake = Arc::new(Notify::new());

    let s = server.clone();
    // Replies go out from a task: a run info carrying a combine phase's GeneDicts or a
    // fixed population is hundreds of kilobytes, and a blocking reply from inside the
    // callback stalled Zenoh's single runtime thread that must drain it.
    let rt = tokio::runtime::Handle::current();
    let _queryable = session
        .declare_queryable(keys::info(&run))
        .callback(move |q| {
            let info = lock(&s).run_info();
            if let Ok(bytes) = encode(&info) {
                rt.spawn(async move {
                    let _ = q.reply(q.key_expr().clone(), bytes).await;
                });
            }
        })
        .await
        .map_err(zerr)?;
    let (s, w) = (server.clone(), wake.clone());
    let _actions = session
        .declare_subscriber(keys::all_actions(&run))
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            if lock(&s).on_action(sample.key_expr().as_str(), &bytes) {
                w.notify_one();
            }
        })
        .await
        .map_err(zerr)?;
    let (publish, released) = unbounded_channel::<Released>();
    spawn_publisher(&session, released, server.clone());
    // Per-cell batches (processes of earlier versions, tests) and bundles.
    let _genes =
        gene_subscriber(&session, keys::all_gene_batches(&run), &server, &publish, Server::on_gene_batch).await?;
    let _gene_bundles =
        gene_subscriber(&session, keys::all_agents_genes(&run), &server, &publish, Server::on_gene_bundle).await?;
    let (s, w) = (server.clone(), wake.clone());
    let _ctl = session
        .declare_subscriber(keys::all_ctl(&run))
        .callback(move |sample| {
            lock(&s).on_control(&sample.payload().to_bytes());
            w.notify_one();
        })
        .await
        .map_err(zerr)?;
    let (s, w, p) = (server.clone(), wake.clone(), publish.clone());
    let _presence = session
        .liveliness()
        .declare_subscriber(keys::all_presence(&run))
        .history(true)
        .callback(move |sample| {
            let alive = sample.kind() == SampleKind::Put;
            let out = lock(&s).on_presence(alive, sample.key_expr().as_str());
            let _ = p.send(out);
            w.notify_one();
        })
        .await
        .map_err(zerr)?;
    let token = session.liveliness().declare_token(keys::world_presence(&run)).await.map_err(zerr)?;
    let (s, w) = (server.clone(), wake.clone());
    tokio::spawn(async move {
        zenoh_bus::shutdown_signal().await;
        lock(&s).on_signal();
        w.notify_one();
    });

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

    let outcome = drive(&session, &server, &wake).await;
    // Before leaving: the launcher reads the file once this process has exited.
    let written = match &locality {
        Some((_, path)) => {
            let counts = lock(&server).world().locality().map(|l| l.counts()).unwrap_or_default();
            std::fs::File::create(path)
                .and_then(|f| geese_world::locality::write_csv(&counts, std::io::BufWriter::new(f)))
                .with_context(|| format!("cannot write the locality map {}", path.display()))
        }
        None => Ok(()),
    };
    drop(publish);
    let _ = token.undeclare().await;
    // Give the last messages a moment to leave before the router goes away.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let _ = session.close().await;
    outcome.map(|_| ())?;
    written
}

/// Files what arrives on `key` into the server with `file` (in the subscriber callback)
/// and hands what that releases to the publisher.
async fn gene_subscriber(
    session: &Session,
    key: String,
    server: &Shared,
    publish: &UnboundedSender<Released>,
    file: fn(&mut Server, &str, &[u8]) -> Released,
) -> Result<zenoh::pubsub::Subscriber<()>> {
    let (s, p) = (server.clone(), publish.clone());
    session
        .declare_subscriber(key)
        .callback(move |sample| {
            let out = file(&mut lock(&s), sample.key_expr().as_str(), &sample.payload().to_bytes());
            let _ = p.send(out);
        })
        .await
        .map_err(zerr)
}

/// Drive the server to the end of the run: publish what it returns, wait for what it
/// waits for. Returns whether the run completed all its steps.
async fn drive(session: &Session, server: &Shared, wake: &Notify) -> Result<bool> {
    loop {
        let next = lock(server).next(Instant::now());
        match next {
            Next::Publish(out) => publish_all(session, out).await?,
            Next::Wait(until) => {
                let _ = tokio::time::timeout_at(tokio::time::Instant::from_std(until), wake.notified()).await;
            }
            Next::Finished { messages, outcome } => {
                // Whatever happened, say so and let everyone go.
                let _ = publish_all(session, messages).await;
                return Ok(outcome?);
            }
        }
    }
}

async fn publish_all(session: &Session, out: Released) -> Result<()> {
    for (key, bytes) in out {
        zenoh_bus::put(session, &key, bytes).await?;
    }
    Ok(())
}

/// Publishes what the gene hub releases, in order, from a task of its own. Zenoh
/// callbacks must not wait: a put that blocks (congestion control) inside the callback
/// that receives gene batches would stall the thread receiving every process's
/// messages.
///
/// Each time it wakes it also sends the hosting processes what the hub holds for them
/// ([`Server::flush_genes`]): bundles filed while it was busy go out together, one
/// message per process, rather than one message per process and bundle.
fn spawn_publisher(session: &Session, mut rx: UnboundedReceiver<Released>, server: Shared) {
    let session = session.clone();
    tokio::spawn(async move {
        while let Some(first) = rx.recv().await {
            let mut out = first;
            while let Ok(more) = rx.try_recv() {
                out.extend(more);
            }
            lock(&server).flush_genes(&mut out);
            for (key, bytes) in out {
                let _ = zenoh_bus::put(&session, &key, bytes).await;
            }
        }
    });
}

fn zerr(e: zenoh::Error) -> anyhow::Error {
    anyhow::Error::new(geese_proto::zenoh_bus::zerr(e))
}
