//! The live viewer: a web page on `http://127.0.0.1:PORT` that shows a running swarm
//! (`geese run --view`, `geese view --run NAME`).
//!
//! Why this shape: the page is one embedded HTML file with its own script (no build
//! step, nothing to install), fed by Server-Sent Events. SSE is one HTTP response that
//! stays open, which browsers reconnect by themselves after a reload or a dropped
//! connection; the viewer only ever sends a few commands, which go as plain `POST`s.
//! axum serves it on the Tokio runtime Zenoh already needs.
//!
//! What feeds it is a [`Feed`]: whoever runs the world (the in-process loop, or a
//! Zenoh subscriber to the world server's frames) publishes [`ViewFrame`]s into it, and
//! the page's commands go back through a [`Backend`]: a channel into the in-process
//! loop, or the run's control plane and the agent processes' `detail` queryables.
//! The feed counts the pages connected, so an in-process run builds frames only while
//! one is (the world server does the same with viewers' liveliness tokens).
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use geese_proto::view::{AgentDetail, ViewFrame};
use geese_proto::{AgentId, Control, Perturbation};
use serde::Deserialize;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{oneshot, watch};

/// The page, embedded: the binary serves it with nothing on disk.
const PAGE: &str = include_str!("view.html");

/// Most (step, task %) points the chart keeps; beyond, every other one is dropped.
const HISTORY_POINTS: usize = 2000;

/// Radius of an obstacle added by a click on the arena (the paper's perturbation
/// obstacles are radius 10).
pub const CLICK_OBSTACLE_RADIUS: i32 = 10;

/// How long the page waits for an agent's detail.
const DETAIL_TIMEOUT: Duration = Duration::from_secs(3);

/// The frames of one run, for every page connected.
pub struct Feed {
    /// The latest message every page gets: `{"frame":…,"history":[[step,pct],…]}`.
    latest: watch::Sender<Arc<str>>,
    history: Mutex<Vec<(u64, f64)>>,
    pages: AtomicU32,
}

impl Default for Feed {
    fn default() -> Self {
        Feed::new()
    }
}

impl Feed {
    pub fn new() -> Self {
        let (latest, _) = watch::channel(Arc::from("null"));
        Feed { latest, history: Mutex::new(Vec::new()), pages: AtomicU32::new(0) }
    }

    /// Pages connected now.
    pub fn pages(&self) -> u32 {
        self.pages.load(Ordering::Relaxed)
    }

    /// A new frame: every page shows it at once, with the task % history so far (kept
    /// here, so a page that connects late or reloads draws the whole chart).
    pub fn publish(&self, frame: &ViewFrame) {
        let mut h = self.history.lock().unwrap_or_else(|e| e.into_inner());
        if h.last().is_none_or(|&(s, _)| frame.step > s) {
            h.push((frame.step, frame.task_pct));
            if h.len() > HISTORY_POINTS {
                let kept: Vec<_> = h.iter().step_by(2).copied().collect();
                *h = kept;
            }
        }
        let msg = serde_json::json!({ "frame": frame, "history": &*h });
        drop(h);
        self.latest.send_replace(Arc::from(msg.to_string()));
    }

    /// The latest message (`null` before the first frame).
    pub fn latest(&self) -> Arc<str> {
        self.latest.borrow().clone()
    }
}

/// A page's command, as the in-process loop receives it.
#[derive(Debug)]
pub enum Command {
    Control(Control),
    Detail(AgentId, oneshot::Sender<Option<AgentDetail>>),
}

/// Where a page's commands go.
#[derive(Clone)]
pub enum Backend {
    /// Into the loop of an in-process run, which takes them between two steps.
    InProcess(std::sync::mpsc::Sender<Command>),
    /// The control plane of a distributed run, and its agent processes' queryables.
    /// `control` is false for a viewer without the operator's right to the control plane
    /// (DESIGN.md §7): its page watches only.
    Zenoh { session: zenoh::Session, run: String, control: bool },
}

/// Why a viewer's page may not send commands.
pub const READ_ONLY: &str =
    "read-only: this viewer did not log in with the operator credential (geese view --credentials OPERATOR.cred)";

#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error("the run has ended")]
    RunEnded,
    #[error("no answer for agent {0} (no such agent, or its process did not reply in time)")]
    NoAgent(AgentId),
    #[error("{0}")]
    Invalid(String),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("{READ_ONLY}")]
    ReadOnly,
    #[error("cannot serve the viewer on {addr}: {source}")]
    Bind { addr: SocketAddr, source: std::io::Error },
}

impl Backend {
    async fn control(&self, c: Control) -> Result<(), ViewError> {
        match self {
            Backend::InProcess(tx) => tx.send(Command::Control(c)).map_err(|_| ViewError::RunEnded),
            Backend::Zenoh { control: false, .. } => Err(ViewError::ReadOnly),
            Backend::Zenoh { session, run, .. } => {
                let bytes = geese_proto::encode(&c).map_err(|e| ViewError::Invalid(e.to_string()))?;
                geese_proto::zenoh_bus::put(session, &geese_proto::keys::ctl(run, "view"), bytes)
                    .await
                    .map_err(|e| ViewError::Zenoh(e.to_string()))
            }
        }
    }

    async fn detail(&self, id: AgentId) -> Result<AgentDetail, ViewError> {
        match self {
            Backend::InProcess(tx) => {
                let (reply, answer) = oneshot::channel();
                tx.send(Command::Detail(id, reply)).map_err(|_| ViewError::RunEnded)?;
                match tokio::time::timeout(DETAIL_TIMEOUT, answer).await {
                    Ok(Ok(Some(d))) => Ok(d),
                    Ok(Ok(None)) => Err(ViewError::NoAgent(id)),
                    _ => Err(ViewError::RunEnded),
                }
            }
            Backend::Zenoh { session, run, .. } => {
                let replies = session
                    .get(geese_proto::keys::agent_detail(run, id))
                    .timeout(DETAIL_TIMEOUT)
                    .await
                    .map_err(|e| ViewError::Zenoh(e.to_string()))?;
                while let Ok(Ok(r)) = tokio::time::timeout(DETAIL_TIMEOUT, replies.recv_async()).await {
                    let Ok(sample) = r.result() else { continue };
                    if !geese_proto::keys::detail_reply_holds(run, sample.key_expr().as_str(), id) {
                        tracing::warn!("detail reply on {} for agent {id} ignored", sample.key_expr());
                        continue;
                    }
                    // From the network: decoded and checked, never trusted.
                    match geese_proto::decode::<AgentDetail>(&sample.payload().to_bytes()) {
                        Ok(d) if d.id == id => return Ok(d),
                        Ok(d) => tracing::warn!("detail for agent {} answered a query for {id}; ignored", d.id),
                        Err(e) => tracing::warn!("detail of agent {id} dropped: {e}"),
                    }
                }
                Err(ViewError::NoAgent(id))
            }
        }
    }
}

#[derive(Clone)]
struct App {
    feed: Arc<Feed>,
    backend: Backend,
}

/// One page connected: counted while its event stream lives.
struct PageGuard(Arc<Feed>);

impl Drop for PageGuard {
    fn drop(&mut self) {
        self.0.pages.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A page's command, as JSON: `{"cmd":"pause"}`, `{"cmd":"resume"}`,
/// `{"cmd":"rate","rate":5}` (steps per second, 0 = no limit), `{"cmd":"obstacle",
/// "x":10,"y":-20}`.
#[derive(Debug, Deserialize, PartialEq)]
#[serde(tag = "cmd", rename_all = "lowercase")]
pub enum PageCommand {
    Pause,
    Resume,
    Rate { rate: f64 },
    Obstacle { x: f64, y: f64 },
}

impl PageCommand {
    /// The control-plane command it stands for, checked as the world checks it (for the
    /// arena of the latest frame, if any).
    pub fn control(&self, frame: Option<&ViewFrame>) -> Result<Control, ViewError> {
        let c = match *self {
            PageCommand::Pause => Control::Pause,
            PageCommand::Resume => Control::Resume,
            PageCommand::Rate { rate } => Control::StepRate(rate),
            PageCommand::Obstacle { x, y } => {
                if !(x.is_finite() && y.is_finite()) {
                    return Err(ViewError::Invalid(format!("obstacle at ({x}, {y}): not a position")));
                }
                let change = Perturbation::AddObstacleAt {
                    x: x.round().clamp(i32::MIN as f64, i32::MAX as f64) as i32,
                    y: y.round().clamp(i32::MIN as f64, i32::MAX as f64) as i32,
                    radius: CLICK_OBSTACLE_RADIUS,
                };
                // Step 0 has passed: the world applies it at once, between two steps.
                Control::Schedule { at_step: 0, change }
            }
        };
        if let Some(f) = frame {
            let geom = geese_proto::Geometry::new(f.width, f.height, f.grid)
                .map_err(|e| ViewError::Invalid(format!("frame arena: {e}")))?;
            c.validate(&geom).map_err(|e| ViewError::Invalid(e.to_string()))?;
        }
        Ok(c)
    }
}

fn error(status: StatusCode, e: impl std::fmt::Display) -> Response {
    (status, Json(serde_json::json!({ "error": e.to_string() }))).into_response()
}

async fn page() -> Html<&'static str> {
    Html(PAGE)
}

async fn state(State(app): State<App>) -> Response {
    ([("content-type", "application/json")], app.feed.latest().to_string()).into_response()
}

async fn events(
    State(app): State<App>,
) -> Sse<impl futures_util::Stream<Item = Result<Event, std::convert::Infallible>>> {
    app.feed.pages.fetch_add(1, Ordering::Relaxed);
    let guard = PageGuard(app.feed.clone());
    let mut rx = app.feed.latest.subscribe();
    // The current frame first (a late page starts at the current step), then each new one.
    rx.mark_changed();
    let stream = futures_util::stream::unfold((rx, guard), |(mut rx, guard)| async move {
        rx.changed().await.ok()?;
        let msg = rx.borrow_and_update().clone();
        Some((Ok(Event::default().data(&*msg)), (rx, guard)))
    });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

async fn rights(State(app): State<App>) -> Response {
    let control = !matches!(app.backend, Backend::Zenoh { control: false, .. });
    Json(serde_json::json!({ "control": control, "why": if control { "" } else { READ_ONLY } })).into_response()
}

async fn agent(State(app): State<App>, Path(id): Path<AgentId>) -> Response {
    match app.backend.detail(id).await {
        Ok(d) => Json(d).into_response(),
        Err(e @ ViewError::NoAgent(_)) => error(StatusCode::NOT_FOUND, e),
        Err(e) => error(StatusCode::SERVICE_UNAVAILABLE, e),
    }
}

async fn control(State(app): State<App>, Json(cmd): Json<PageCommand>) -> Response {
    let latest = app.feed.latest();
    let frame = serde_json::from_str::<serde_json::Value>(&latest)
        .ok()
        .and_then(|v| serde_json::from_value::<ViewFrame>(v.get("frame")?.clone()).ok());
    let c = match cmd.control(frame.as_ref()) {
        Ok(c) => c,
        Err(e) => return error(StatusCode::BAD_REQUEST, e),
    };
    match app.backend.control(c.clone()).await {
        Ok(()) => Json(serde_json::json!({ "sent": format!("{c:?}") })).into_response(),
        Err(e @ ViewError::ReadOnly) => error(StatusCode::FORBIDDEN, e),
        Err(e) => error(StatusCode::SERVICE_UNAVAILABLE, e),
    }
}

/// Serve the viewer on `addr` (port 0: an ephemeral one) until `shutdown` completes;
/// returns the address bound and the server's task.
pub async fn serve(
    addr: SocketAddr,
    feed: Arc<Feed>,
    backend: Backend,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(SocketAddr, tokio::task::JoinHandle<()>), ViewError> {
    let app = Router::new()
        .route("/", get(page))
        .route("/state", get(state))
        .route("/events", get(events))
        .route("/agent/{id}", get(agent))
        .route("/control", post(control))
        .route("/rights", get(rights))
        .with_state(App { feed, backend });
    let listener = tokio::net::TcpListener::bind(addr).await.map_err(|source| ViewError::Bind { addr, source })?;
    let bound = listener.local_addr().map_err(|source| ViewError::Bind { addr, source })?;
    let task = tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).with_graceful_shutdown(shutdown).await {
            tracing::warn!("viewer server: {e}");
        }
    });
    Ok((bound, task))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn page_commands_become_checked_control_commands() {
        let frame = ViewFrame { width: 100, height: 100, grid: 10, ..ViewFrame::default() };
        let parse = |s: &str| serde_json::from_str::<PageCommand>(s).expect(s);
        assert_eq!(parse(r#"{"cmd":"pause"}"#).control(Some(&frame)).unwrap(), Control::Pause);
        assert_eq!(parse(r#"{"cmd":"rate","rate":5}"#).control(Some(&frame)).unwrap(), Control::StepRate(5.0));
        assert_eq!(
            parse(r#"{"cmd":"obstacle","x":20.4,"y":-30.6}"#).control(Some(&frame)).unwrap(),
            Control::Schedule { at_step: 0, change: Perturbation::AddObstacleAt { x: 20, y: -31, radius: 10 } }
        );
        let e = parse(r#"{"cmd":"obstacle","x":80,"y":0}"#).control(Some(&frame)).unwrap_err();
        assert!(e.to_string().contains("outside the 100x100 arena"), "{e}");
        let e = parse(r#"{"cmd":"rate","rate":-1}"#).control(Some(&frame)).unwrap_err();
        assert!(e.to_string().starts_with("StepRate -1"), "{e}");
        assert!(serde_json::from_str::<PageCommand>(r#"{"cmd":"explode"}"#).is_err());
    }

    #[test]
    fn the_feed_keeps_a_bounded_history_and_the_latest_frame() {
        let feed = Feed::new();
        assert_eq!(&*feed.latest(), "null");
        for step in 0..(HISTORY_POINTS as u64 + 10) {
            feed.publish(&ViewFrame { step, task_pct: step as f64, ..ViewFrame::default() });
        }
        let v: serde_json::Value = serde_json::from_str(&feed.latest()).unwrap();
        assert_eq!(v["frame"]["step"], HISTORY_POINTS as u64 + 9);
        let h = v["history"].as_array().unwrap();
        assert!(h.len() <= HISTORY_POINTS && h.len() > HISTORY_POINTS / 2, "{}", h.len());
        assert_eq!(h[0][0], 0);
    }
}

/// A viewer of a distributed run: the page server, fed by the world server's frames.
/// Its liveliness token tells the world a viewer is present; dropping it (or the
/// process ending) tells it none is, and the world stops building frames.
pub struct ZenohView {
    url: String,
    _token: zenoh::liveliness::LivelinessToken,
    _frames: zenoh::pubsub::Subscriber<()>,
    _server: tokio::task::JoinHandle<()>,
    _shutdown: oneshot::Sender<()>,
}

impl ZenohView {
    /// Serve the viewer of run `run` on 127.0.0.1:`port` (0: any free port) through
    /// `session`.
    /// `control`: may the page send commands (the session logged in as the operator, or
    /// the run is not secured)?
    pub async fn attach(session: &zenoh::Session, run: &str, port: u16, control: bool) -> Result<ZenohView, ViewError> {
        let zerr = |e: zenoh::Error| ViewError::Zenoh(e.to_string());
        let feed = Arc::new(Feed::new());
        let f = feed.clone();
        let frames = session
            .declare_subscriber(geese_proto::keys::view_frame(run))
            .callback(move |s| match geese_proto::decode::<ViewFrame>(&s.payload().to_bytes()) {
                Ok(frame) => f.publish(&frame),
                // From the network: counted in the log, never shown.
                Err(e) => tracing::warn!("view frame dropped: {e}"),
            })
            .await
            .map_err(zerr)?;
        let (shutdown, done) = oneshot::channel::<()>();
        let backend = Backend::Zenoh { session: session.clone(), run: run.to_string(), control };
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        let (bound, server) = serve(addr, feed, backend, async {
            let _ = done.await;
        })
        .await?;
        // Declared last: the world sends frames once we can receive them.
        let name = format!("{}-{}", std::process::id(), bound.port());
        let token =
            session.liveliness().declare_token(geese_proto::keys::viewer_presence(run, &name)).await.map_err(zerr)?;
        Ok(ZenohView {
            url: format!("http://{bound}/"),
            _token: token,
            _frames: frames,
            _server: server,
            _shutdown: shutdown,
        })
    }

    pub fn url(&self) -> &str {
        &self.url
    }
}

/// `geese view`: watch a running distributed run.
#[derive(clap::Args, Debug)]
pub struct ViewArgs {
    /// Name of the run (`geese run --run-name`, or the launcher's generated name).
    #[arg(long)]
    pub run: String,
    /// The page's port on 127.0.0.1 (0: any free one).
    #[arg(long, default_value_t = 0)]
    pub port: u16,
    #[command(flatten)]
    pub zenoh: geese_proto::zenoh_bus::CommonArgs,
}

/// Serve the page of run `args.run` until the world goes away or Ctrl-C.
pub fn view_cmd(args: ViewArgs) -> anyhow::Result<()> {
    use geese_proto::keys;
    use geese_proto::zenoh_bus::{self, Role};
    if !keys::valid_run_name(&args.run) {
        anyhow::bail!("--run {:?}: one key chunk of letters, digits, '_', '-', '.'", args.run);
    }
    let rt = zenoh_bus::runtime(2)?;
    rt.block_on(async move {
        let session = zenoh_bus::open(&args.zenoh, Role::Client).await?;
        let (gone_tx, mut gone) = tokio::sync::mpsc::unbounded_channel::<()>();
        let run = args.run.clone();
        let _world = session
            .liveliness()
            .declare_subscriber(keys::world_presence(&run))
            .history(true)
            .callback(move |s| {
                if s.kind() == zenoh::sample::SampleKind::Delete {
                    let _ = gone_tx.send(());
                }
            })
            .await
            .map_err(|e| anyhow::anyhow!("zenoh: {e}"))?;
        // The router decides what gets through; the page offers controls only to the
        // operator (or on a run without logins).
        let control = match &args.zenoh.credentials {
            None => true,
            Some(p) => geese_proto::security::Credential::read(p)?.user == geese_proto::security::OPERATOR,
        };
        let view = ZenohView::attach(&session, &args.run, args.port, control).await?;
        println!("view: {} (run {}; Ctrl-C to leave)", view.url(), args.run);
        tokio::select! {
            _ = gone.recv() => println!("the run's world has gone"),
            _ = tokio::signal::ctrl_c() => {}
        }
        drop(view);
        let _ = session.close().await;
        anyhow::Ok(())
    })
}
