//! The Zenoh transport: how every GEESE process opens its session (DESIGN.md §3).
//!
//! Embedded default: the world's session is a **router** listening on
//! `tcp/127.0.0.1:0` (an ephemeral port; the world prints the real locator), and every
//! other process is a **client** that connects to it explicitly. With `--router
//! ENDPOINT` every process, the world included, is a client of that external `zenohd`.
//! Multicast and gossip scouting are always switched off (a `--cfg` pair can switch
//! them back on; nothing in GEESE does).
//!
//! Every binary flattens the same [`CommonArgs`] into its command line, in the style of
//! Zenoh's examples: `--zenoh-config FILE`, `--mode`, `-e/--connect`, `-l/--listen`,
//! `--router`, `--cfg KEY:VALUE`.
use crate::security;
use std::path::PathBuf;
use zenoh::qos::CongestionControl;
use zenoh::{Config, Session};

/// Why a Zenoh session could not be configured or used.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error("zenoh configuration: {0}")]
    Config(String),
    #[error("--cfg {0:?}: expected KEY:VALUE with VALUE in JSON5")]
    CfgPair(String),
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error(transparent)]
    Security(#[from] security::SecurityError),
}

/// Session mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Mode {
    Router,
    Peer,
    Client,
}

impl Mode {
    fn name(self) -> &'static str {
        match self {
            Mode::Router => "router",
            Mode::Peer => "peer",
            Mode::Client => "client",
        }
    }
}

/// Which process a session belongs to (decides the default mode).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// The world server: a router unless `--router` names an external one.
    World,
    /// Agent processes, the orchestrator, tools: clients.
    Client,
}

/// The Zenoh arguments every GEESE binary shares.
#[derive(clap::Args, Clone, Debug, Default, PartialEq)]
pub struct CommonArgs {
    /// Zenoh configuration file (JSON5, see deploy/); the flags below override it.
    #[arg(long = "zenoh-config", value_name = "FILE")]
    pub zenoh_config: Option<PathBuf>,
    /// Session mode [default: router for the world server, client for everything else].
    #[arg(long, value_enum)]
    pub mode: Option<Mode>,
    /// Endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[arg(short = 'e', long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Endpoint to listen on (repeatable) [default for the world server: tcp/127.0.0.1:0,
    /// an ephemeral port].
    #[arg(short = 'l', long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Use the external zenohd router at ENDPOINT: every process, the world server
    /// included, connects to it as a client.
    #[arg(long, value_name = "ENDPOINT")]
    pub router: Option<String>,
    /// Any other Zenoh setting as KEY:VALUE, VALUE in JSON5 (repeatable), e.g.
    /// --cfg transport/unicast/max_sessions:4000
    #[arg(long = "cfg", value_name = "KEY:VALUE")]
    pub cfg: Vec<String>,
    /// Log in with the credential in FILE (one line `user:password`, made by `geese
    /// secure init` or by `geese run` for its own processes).
    #[arg(long, value_name = "FILE")]
    pub credentials: Option<PathBuf>,
    /// Accept only logins listed in FILE (`user:password` per line): for a session that
    /// others connect to (the world's router, `geese router`).
    #[arg(long, value_name = "FILE")]
    pub users: Option<PathBuf>,
    /// Enforce the access-control list in FILE (JSON5, Zenoh's `access_control`
    /// section; `geese secure init` writes one) on the processes connected here.
    #[arg(long, value_name = "FILE")]
    pub acl: Option<PathBuf>,
}

impl CommonArgs {
    /// The same arguments as a command line, to hand on to a child process.
    pub fn to_args(&self) -> Vec<String> {
        let mut v = Vec::new();
        if let Some(p) = &self.zenoh_config {
            v.push("--zenoh-config".into());
            v.push(p.display().to_string());
        }
        if let Some(m) = self.mode {
            v.push("--mode".into());
            v.push(m.name().into());
        }
        for e in &self.connect {
            v.push("--connect".into());
            v.push(e.clone());
        }
        for e in &self.listen {
            v.push("--listen".into());
            v.push(e.clone());
        }
        if let Some(r) = &self.router {
            v.push("--router".into());
            v.push(r.clone());
        }
        for c in &self.cfg {
            v.push("--cfg".into());
            v.push(c.clone());
        }
        for (flag, p) in [("--credentials", &self.credentials), ("--users", &self.users), ("--acl", &self.acl)] {
            if let Some(p) = p {
                v.push(flag.into());
                v.push(p.display().to_string());
            }
        }
        v
    }

    /// Does this session log in or check logins?
    pub fn secured(&self) -> bool {
        self.credentials.is_some() || self.users.is_some() || self.acl.is_some()
    }

    /// The Zenoh configuration of a session of `role`.
    pub fn config(&self, role: Role) -> Result<Config, BusError> {
        self.config_listening(role, &self.default_listen(role))
    }

    fn own_router(&self, role: Role) -> bool {
        role == Role::World && self.router.is_none()
    }

    fn mode(&self, role: Role) -> Option<Mode> {
        match (self.mode, &self.zenoh_config) {
            (Some(m), _) => Some(m),
            (None, None) => Some(if self.own_router(role) { Mode::Router } else { Mode::Client }),
            // A configuration file decides the mode unless a flag does.
            (None, Some(_)) => None,
        }
    }

    fn default_listen(&self, role: Role) -> Vec<String> {
        if !self.listen.is_empty() {
            self.listen.clone()
        } else if self.mode(role) == Some(Mode::Router) && self.zenoh_config.is_none() {
            vec!["tcp/127.0.0.1:0".into()]
        } else {
            Vec::new()
        }
    }

    fn config_listening(&self, role: Role, listen: &[String]) -> Result<Config, BusError> {
        let mut c = match &self.zenoh_config {
            Some(p) => Config::from_file(p).map_err(|e| BusError::Config(format!("{}: {e}", p.display())))?,
            None => Config::default(),
        };
        let mode = self.mode(role);
        if let Some(m) = mode {
            set(&mut c, "mode", &format!("\"{}\"", m.name()))?;
        }
        // Everything connects explicitly: no multicast, no gossip.
        set(&mut c, "scouting/multicast/enabled", "false")?;
        set(&mut c, "scouting/gossip/enabled", "false")?;
        let mut connect = self.connect.clone();
        if let Some(r) = &self.router {
            connect.push(r.clone());
        }
        if !connect.is_empty() {
            set(&mut c, "connect/endpoints", &json_list(&connect))?;
            // Keep trying for a while rather than failing at once if the router is late.
            set(&mut c, "connect/timeout_ms", "15000")?;
        }
        if !listen.is_empty() {
            set(&mut c, "listen/endpoints", &json_list(listen))?;
        }
        if mode == Some(Mode::Router) && self.zenoh_config.is_none() {
            // One transport per agent process: raise the session limits.
            set(&mut c, "transport/unicast/max_sessions", "10000")?;
            set(&mut c, "transport/unicast/accept_pending", "10000")?;
        }
        for pair in &self.cfg {
            let (k, v) = pair.split_once(':').ok_or_else(|| BusError::CfgPair(pair.clone()))?;
            c.insert_json5(k, v).map_err(|e| BusError::Config(format!("--cfg {pair}: {e}")))?;
        }
        refuse_tls_endpoints(&c)?;
        if let Some(p) = &self.credentials {
            security::Credential::read(p)?.apply(&mut c)?;
        }
        if let Some(p) = &self.users {
            security::apply_dictionary(&mut c, p)?;
        }
        if let Some(p) = &self.acl {
            security::apply_acl(&mut c, p)?;
        }
        Ok(c)
    }
}

/// Zenoh says only "Unicast not supported for tls protocol" for a `tls/` endpoint of this
/// build; say why and what to use instead. Checked on the finished configuration, so an
/// endpoint from a config file or a `--cfg` pair is caught as well as one from a flag.
fn refuse_tls_endpoints(c: &Config) -> Result<(), BusError> {
    for key in ["connect/endpoints", "listen/endpoints"] {
        let json = c.get_json(key).unwrap_or_default();
        if let Some(at) = json.find("\"tls/") {
            let e = json[at + 1..].split('"').next().unwrap_or("tls/");
            return Err(BusError::Config(format!(
                "{key}: {e}: GEESE is built without Zenoh's tls/ links (1.10 reads and writes one TLS \
                 stream from two tasks at once, eclipse-zenoh/zenoh#2557); use quic/ with the same \
                 transport/link/tls settings (deploy/MULTI-HOST.md)"
            )));
        }
    }
    Ok(())
}

/// A publisher on `key` that publishes reliably, as [`put`] does. Declared once, a key
/// has its routes (and, at a router, its access-list answer) resolved once, not on every
/// message.
pub async fn publisher(session: &Session, key: String) -> Result<zenoh::pubsub::Publisher<'static>, BusError> {
    session
        .declare_publisher(key.clone())
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| BusError::Zenoh(format!("declare publisher {key}: {e}")))
}

fn set(c: &mut Config, key: &str, value: &str) -> Result<(), BusError> {
    c.insert_json5(key, value).map_err(|e| BusError::Config(format!("{key}: {e}")))
}

fn json_list(v: &[String]) -> String {
    let items: Vec<String> =
        v.iter().map(|s| format!("\"{}\"", s.replace('\\', "\\\\").replace('"', "\\\""))).collect();
    format!("[{}]", items.join(","))
}

/// Open a session of `role` configured by `args`.
pub async fn open(args: &CommonArgs, role: Role) -> Result<Session, BusError> {
    let cfg = args.config(role)?;
    zenoh::open(cfg).await.map_err(|e| open_error(args, e))
}

/// Why a session did not open, with the likely cause when it logs in: a router refuses
/// a wrong or missing password by closing the link, which Zenoh reports as a failure
/// to connect.
fn open_error(args: &CommonArgs, e: zenoh::Error) -> BusError {
    match &args.credentials {
        Some(p) => BusError::Open(format!(
            "{e} (logging in as the user of {}: a wrong password or a router that does not know the user is refused like an unreachable one)",
            p.display()
        )),
        None => BusError::Open(e.to_string()),
    }
}

/// The `RUST_LOG` directive every GEESE binary adds last: Zenoh prints a session's whole
/// configuration, login password included, at debug level as the session opens.
pub const HIDE_SECRETS_DIRECTIVE: &str = "zenoh::api::session=info";

/// Open the world server's session and return it with the locators others must
/// connect to. A TCP listen endpoint with port 0 gets a free port of this host picked
/// here (retried if another process takes it first), so the real locator is known.
pub async fn open_world(args: &CommonArgs) -> Result<(Session, Vec<String>), BusError> {
    let wanted = args.default_listen(Role::World);
    let mut last = String::new();
    for _ in 0..8 {
        let listen: Vec<String> = wanted
            .iter()
            .map(|e| match e.strip_suffix(":0").and_then(|h| h.strip_prefix("tcp/")) {
                Some(host) => free_port(host).map(|p| format!("tcp/{host}:{p}")).unwrap_or_else(|| e.clone()),
                None => e.clone(),
            })
            .collect();
        let cfg = args.config_listening(Role::World, &listen)?;
        match zenoh::open(cfg).await {
            Ok(s) => {
                let mut locators = listen;
                if locators.is_empty() {
                    if let Some(r) = &args.router {
                        locators.push(r.clone());
                    }
                    locators.extend(args.connect.iter().cloned());
                }
                return Ok((s, locators));
            }
            Err(e) => last = open_error(args, e).to_string(),
        }
    }
    Err(BusError::Open(last))
}

/// A TCP port of `host` that is free now.
fn free_port(host: &str) -> Option<u16> {
    let l = std::net::TcpListener::bind((host.trim_start_matches('[').trim_end_matches(']'), 0)).ok()?;
    l.local_addr().ok().map(|a| a.port())
}

/// Publish `bytes` on `key`, reliably: the lock-step protocol cannot afford a message
/// dropped by congestion control (a dead receiver's link closes at lease expiry, which
/// bounds the wait).
pub async fn put(session: &Session, key: &str, bytes: Vec<u8>) -> Result<(), BusError> {
    session
        .put(key, bytes)
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| BusError::Zenoh(format!("put {key}: {e}")))
}

/// Ask the world of `run` for its [`crate::net::RunInfo`] (queryable `ctl/info`),
/// retrying until `patience` runs out. Also returns the handle of the runtime Zenoh
/// delivers messages on (seen from the reply callback), which agent processes reuse.
pub async fn fetch_run_info(
    session: &Session,
    run: &str,
    patience: std::time::Duration,
) -> Result<(crate::net::RunInfo, Option<tokio::runtime::Handle>), BusError> {
    use std::time::{Duration, Instant};
    let deadline = Instant::now() + patience;
    loop {
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
        session
            .get(crate::keys::info(run))
            .timeout(Duration::from_secs(2))
            .callback(move |reply| {
                if let Ok(sample) = reply.result() {
                    let handle = tokio::runtime::Handle::try_current().ok();
                    let _ = tx.send((sample.payload().to_bytes().into_owned(), handle));
                }
            })
            .await
            .map_err(|e| BusError::Zenoh(format!("query {}: {e}", crate::keys::info(run))))?;
        if let Ok(Some((bytes, handle))) = tokio::time::timeout(Duration::from_millis(2500), rx.recv()).await {
            match crate::decode::<crate::net::RunInfo>(&bytes) {
                Ok(i) if i.spec.run == run => return Ok((i, handle)),
                Ok(_) => tracing::warn!("run info of another run ignored"),
                Err(e) => tracing::warn!("undecodable run info ignored: {e}"),
            }
        }
        if Instant::now() >= deadline {
            return Err(BusError::Zenoh(format!(
                "no world answered on {} within {} ms",
                crate::keys::info(run),
                patience.as_millis()
            )));
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The environment variable Zenoh reads its internal runtime sizes from.
pub const ZENOH_RUNTIME_ENV: &str = "ZENOH_RUNTIME";

/// Internal Zenoh thread pools sized for a machine running hundreds of GEESE processes
/// on a few cores: one thread for everything (every pool handed over to the
/// application one), which saves thread hand-offs on each message. Agent processes use
/// it unless `ZENOH_RUNTIME` is set; `geese run` gives it to the world server too when
/// it launches few agent processes ([`LEAN_WORLD_MAX_PROCESSES`]).
pub const LEAN_ZENOH_RUNTIME: &str =
    "(app: (worker_threads: 1), acc: (handover: app), net: (handover: app), tx: (handover: app), rx: (handover: app))";

/// Most agent processes for which a launched world server runs Zenoh on one thread
/// ([`LEAN_ZENOH_RUNTIME`]). With ten processes hosting 100 agents each, the world's
/// receive, send and publisher threads competed with the busy agents for two cores, and
/// one thread was faster in 8 of 10 interleaved pairs (about +5 %). With 100 processes
/// of one agent, where the world routes for 100 links, it was 10 % slower (2,000 steps:
/// 64.0 and 66.6 against 74.5 and 72.8 steps/s).
pub const LEAN_WORLD_MAX_PROCESSES: u32 = 32;

/// Use [`LEAN_ZENOH_RUNTIME`] unless `ZENOH_RUNTIME` is set. Call it first thing in
/// `main`, before any thread exists (it sets an environment variable).
pub fn lean_runtime_unless_set() {
    if std::env::var_os(ZENOH_RUNTIME_ENV).is_none() {
        std::env::set_var(ZENOH_RUNTIME_ENV, LEAN_ZENOH_RUNTIME);
    }
}

/// A Tokio multi-thread runtime (Zenoh requires one) with `workers` worker threads.
pub fn runtime(workers: usize) -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(workers.max(1)).enable_all().build()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_loopback_router_and_clients_without_scouting() {
        let a = CommonArgs::default();
        let w = a.config(Role::World).unwrap();
        assert_eq!(w.get_json("mode").unwrap(), "\"router\"");
        assert!(w.get_json("listen/endpoints").unwrap().contains("tcp/127.0.0.1:0"));
        assert_eq!(w.get_json("scouting/multicast/enabled").unwrap(), "false");
        assert_eq!(w.get_json("scouting/gossip/enabled").unwrap(), "false");
        let c = CommonArgs { connect: vec!["tcp/127.0.0.1:7447".into()], ..Default::default() }
            .config(Role::Client)
            .unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"client\"");
        assert!(c.get_json("connect/endpoints").unwrap().contains("tcp/127.0.0.1:7447"));
        let r = CommonArgs { router: Some("tcp/127.0.0.1:7447".into()), ..Default::default() };
        assert_eq!(r.config(Role::World).unwrap().get_json("mode").unwrap(), "\"client\"");
    }

    #[test]
    fn tls_endpoints_are_refused_with_the_way_out() {
        for a in [
            CommonArgs { connect: vec!["tls/10.0.0.1:7448".into()], ..Default::default() },
            CommonArgs { listen: vec!["tls/10.0.0.1:7448".into()], ..Default::default() },
        ] {
            let e = a.config(Role::Client).unwrap_err().to_string();
            assert!(e.contains("tls/10.0.0.1:7448") && e.contains("use quic/"), "{e}");
        }
        let c = CommonArgs { cfg: vec![r#"connect/endpoints:["tls/10.0.0.1:7448"]"#.into()], ..Default::default() };
        assert!(c.config(Role::Client).unwrap_err().to_string().contains("use quic/"));
        let q = CommonArgs { connect: vec!["quic/10.0.0.1:7448".into()], ..Default::default() };
        assert!(q.config(Role::Client).is_ok());
    }

    #[test]
    fn cfg_pairs_apply_last_and_bad_pairs_are_errors() {
        let a = CommonArgs { cfg: vec!["transport/unicast/max_sessions:42".into()], ..Default::default() };
        assert_eq!(a.config(Role::World).unwrap().get_json("transport/unicast/max_sessions").unwrap(), "42");
        let bad = CommonArgs { cfg: vec!["nocolon".into()], ..Default::default() };
        assert!(matches!(bad.config(Role::Client), Err(BusError::CfgPair(_))));
        let round = CommonArgs {
            connect: vec!["tcp/127.0.0.1:1".into()],
            router: Some("tcp/127.0.0.1:2".into()),
            cfg: vec!["a:1".into()],
            ..Default::default()
        };
        assert_eq!(round.to_args().len(), 6);
    }
}

/// Wait for SIGTERM or SIGINT (Ctrl-C elsewhere): the graceful-shutdown future every
/// GEESE process passes to its main loop.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let (Ok(mut term), Ok(mut int)) = (signal(SignalKind::terminate()), signal(SignalKind::interrupt())) else {
            // Without signal handlers the process is still ended by the launcher's kill.
            return std::future::pending().await;
        };
        tokio::select! {
            _ = term.recv() => {}
            _ = int.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// A Zenoh error as a plain `std::error::Error`, so binaries can use `?` into `anyhow`.
#[derive(Debug, thiserror::Error)]
#[error("zenoh: {0}")]
pub struct ZenohError(pub String);

/// Wrap a Zenoh error for a binary's error chain.
pub fn zerr(e: zenoh::Error) -> ZenohError {
    ZenohError(e.to_string())
}
