//! An in-process run with the live viewer attached (`geese run --view`): serves the
//! page, and between two steps takes the page's commands — pause, step-rate limit, an
//! obstacle, an agent's detail — then publishes a frame when one is due.
//!
//! The run's loop stays synchronous: the web server runs on a Tokio runtime of its own
//! and talks to the loop through a channel; the loop never waits on the server.
use crate::live::view::{self, Backend, Command, Feed};
use crate::run::trial::Trial;
use geese_proto::{Control, StepReport};
use geese_world::pace::Pace;
use std::net::SocketAddr;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Longest a paused loop sleeps before looking again (commands wake it sooner).
const PAUSED_POLL: Duration = Duration::from_millis(200);

/// The viewer of an in-process run.
pub struct Watch {
    feed: Arc<Feed>,
    commands: Receiver<Command>,
    pace: Pace,
    url: String,
    stop: bool,
    /// A frame has been published (the page server holds one for a page that comes).
    shown: bool,
    _shutdown: tokio::sync::oneshot::Sender<()>,
    // Last: dropping the runtime ends the server after the shutdown signal.
    _rt: tokio::runtime::Runtime,
}

impl Watch {
    /// Serve the viewer on 127.0.0.1:`port` (0: an ephemeral port); `step_rate`: the
    /// step-rate limit to start with.
    pub fn start(port: u16, step_rate: Option<f64>) -> anyhow::Result<Watch> {
        let mut pace = Pace::new();
        if let Some(r) = step_rate {
            geese_proto::limits::check_step_rate(r).map_err(|e| anyhow::anyhow!("--step-rate: {e}"))?;
            pace.on_control(&Control::StepRate(r));
        }
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
        let feed = Arc::new(Feed::new());
        let (tx, commands) = std::sync::mpsc::channel();
        let (shutdown, done) = tokio::sync::oneshot::channel::<()>();
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        let (bound, _task) = rt.block_on(view::serve(addr, feed.clone(), Backend::InProcess(tx), async {
            let _ = done.await;
        }))?;
        Ok(Watch {
            feed,
            commands,
            pace,
            url: format!("http://{bound}/"),
            stop: false,
            shown: false,
            _shutdown: shutdown,
            _rt: rt,
        })
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// Between two steps: take the page's commands, and hold the run while it is paused
    /// or ahead of its step-rate limit. False when the page asked the run to stop.
    pub fn before_step(&mut self, trial: &mut Trial, last: Option<&StepReport>, steps: u64) -> bool {
        loop {
            while let Ok(c) = self.commands.try_recv() {
                self.take(c, trial);
            }
            if self.stop {
                return false;
            }
            let now = Instant::now();
            if let Some(rep) = last {
                self.frame(trial, rep, steps, now);
            }
            let wait = match self.pace.step_at(now) {
                Some(at) if at <= now => break,
                Some(at) => (at - now).min(PAUSED_POLL),
                None => PAUSED_POLL,
            };
            match self.commands.recv_timeout(wait) {
                Ok(c) => self.take(c, trial),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        self.pace.stepped(Instant::now());
        true
    }

    /// After a step: a frame, when a page is connected and one is due.
    pub fn after_step(&mut self, trial: &Trial, rep: &StepReport, steps: u64) {
        self.frame(trial, rep, steps, Instant::now());
    }

    /// The run is over: the last frame, whatever the rate bound.
    pub fn finish(&mut self, trial: &Trial, rep: &StepReport, steps: u64) {
        self.pace.owe_frame();
        self.frame(trial, rep, steps, Instant::now());
    }

    fn frame(&mut self, trial: &Trial, rep: &StepReport, steps: u64, now: Instant) {
        if self.feed.pages() == 0 && self.shown {
            // Nobody watches: no frame is built (a page that connects gets the last one,
            // and the next within a frame interval).
            self.pace.owe_frame();
            return;
        }
        if self.pace.frame_due(now) {
            self.feed.publish(&geese_world::frame::frame(&trial.world, rep, steps, &self.pace));
            self.shown = true;
        }
    }

    fn take(&mut self, c: Command, trial: &mut Trial) {
        match c {
            Command::Detail(id, reply) => {
                let _ = reply.send(trial.agents.get(id as usize).map(|a| a.detail()));
            }
            Command::Control(c) => {
                if self.pace.on_control(&c) {
                    return;
                }
                match c {
                    // Applied now, between two steps: in the next percepts.
                    Control::Schedule { change, .. } => {
                        trial.world.perturb(change);
                        self.pace.owe_frame();
                    }
                    Control::Stop => self.stop = true,
                    _ => {}
                }
            }
        }
    }
}
