//! The distributed mode of `geese run`: launch the world server and N agent processes
//! on this machine, gather their per-step reports over Zenoh, and write the same
//! `steps.csv` and manifest as an in-process run (plus `net.csv`).
//!
//! The launcher owns its children: they are spawned with `kill_on_drop`, killed by PID
//! when the run ends or fails, and on Ctrl-C it asks the world to stop (the world's
//! departure makes every agent process exit) before killing whatever is left. If the
//! launcher itself dies, the world notices the orchestrator's liveliness token vanish
//! and stops, and the agents follow the world: no orphans either way.
use crate::run::config::RunSpec;
use crate::run::output::{write_locality, write_manifest, StepCsv};
use crate::run::trial::TrialSummary;
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{Deadlines, LossRates, NetReport, NetRunSpec, ReportMsg};
use geese_proto::security::{self, Layout, Secrets};
use geese_proto::zenoh_bus::{self, CommonArgs, Role};
use geese_proto::{decode, encode, Control};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tokio::sync::mpsc::unbounded_channel;
use zenoh::sample::SampleKind;

/// Why a distributed run failed.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error("{0}")]
    Bus(#[from] zenoh_bus::BusError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("{what}: {source}")]
    Io { what: String, source: std::io::Error },
    #[error("cannot find {bin} in {dir} (build the binaries: cargo build --release --bins)")]
    MissingBinary { bin: String, dir: PathBuf },
    #[error("the world server did not start: {0}")]
    WorldStart(String),
    #[error("the world server exited or disappeared before the run finished (after step {0})")]
    WorldGone(u64),
    #[error("no report for {0:?}; giving up")]
    Stalled(Duration),
    #[error("interrupted")]
    Interrupted,
    #[error("invalid: {0}")]
    Invalid(String),
    #[error("{0}")]
    Codec(#[from] geese_proto::CodecError),
}

fn io(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> LaunchError {
    let what = what.into();
    move |source| LaunchError::Io { what, source }
}

fn zerr(e: zenoh::Error) -> LaunchError {
    LaunchError::Zenoh(e.to_string())
}

/// SIGKILL `count` agent processes right after step `at` is reported.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KillPlan {
    pub at: u64,
    pub count: u32,
}

/// How to run a trial as separate processes.
#[derive(Clone, Debug)]
pub struct NetOptions {
    /// Agent processes to launch on this machine (0: the agents come from elsewhere).
    pub processes: u32,
    /// Agents hosted per process (default: the agents split evenly over `processes`).
    pub agents_per_process: Option<u32>,
    pub loss: LossRates,
    pub deadlines: Deadlines,
    pub zenoh: CommonArgs,
    /// Where `geese-world` and `geese-agent` are (default: next to this executable).
    pub bin_dir: Option<PathBuf>,
    /// Run name (default: unique per launch).
    pub run: Option<String>,
    /// Bare lock-step benchmark: no simulation, ticks out and empty replies back.
    pub bare: bool,
    /// `--subscribe` of the agent processes (`auto`, `cells`, `all`); a comma-separated
    /// list is cycled over the processes.
    pub subscribe: Option<String>,
    /// Failure injection: kill agent processes after given steps.
    pub kill: Vec<KillPlan>,
    /// Restart every killed agent process after these steps (same ids: they rejoin).
    pub restart_at: Vec<u64>,
    /// Give up if no report arrives for this long once the run has started.
    pub stall: Duration,
    /// Discard the children's stderr.
    pub quiet_children: bool,
    /// Serve the live viewer on 127.0.0.1 at this port (0: any free one).
    pub view: Option<u16>,
    /// A step-rate limit asked of the world from the start (the viewer's control).
    pub step_rate: Option<f64>,
    /// Logins and access control (DESIGN.md §7).
    pub security: Security,
}

/// How a distributed run is secured.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum Security {
    /// Fresh credentials and an access-control list for this run only, in a private
    /// temporary directory removed when the run ends (the default).
    #[default]
    PerRun,
    /// Credentials and list made beforehand by `geese secure init` (multi-host runs).
    Dir(PathBuf),
    /// No logins, no access control (`--insecure`, for benchmarks).
    Off,
}

impl Security {
    /// What the manifest and the benchmarks say of it.
    pub fn describe(&self) -> &'static str {
        match self {
            Security::PerRun => "usrpwd+acl (per-run credentials)",
            Security::Dir(_) => "usrpwd+acl (geese secure init)",
            Security::Off => "none (--insecure)",
        }
    }
}

impl Default for NetOptions {
    fn default() -> Self {
        NetOptions {
            processes: 1,
            agents_per_process: None,
            loss: LossRates::default(),
            deadlines: Deadlines::default(),
            zenoh: CommonArgs::default(),
            bin_dir: None,
            run: None,
            bare: false,
            subscribe: None,
            kill: Vec::new(),
            restart_at: Vec::new(),
            stall: Duration::from_secs(60),
            quiet_children: false,
            view: None,
            step_rate: None,
            security: Security::PerRun,
        }
    }
}

/// One launched agent process.
pub struct AgentProc {
    pub first: u32,
    pub count: u32,
    pub child: Option<Child>,
    pub pid: Option<u32>,
    pub killed: bool,
}

/// The launched processes, as the observer of a run sees them.
pub struct Swarm {
    bin_dir: PathBuf,
    run: String,
    client: CommonArgs,
    /// The run's credentials (none when it runs `--insecure`).
    secrets: Option<std::sync::Arc<Secrets>>,
    subscribe: Option<String>,
    quiet: bool,
    pub world_pid: Option<u32>,
    world: Option<Child>,
    pub agents: Vec<AgentProc>,
    /// Every PID spawned, in order (world first).
    spawned: Vec<u32>,
    /// Where agent process i writes its agents' population at the end.
    population_files: Vec<PathBuf>,
}

impl Swarm {
    fn agent_command(&self, i: usize, first: u32, count: u32) -> Command {
        let mut c = Command::new(self.bin_dir.join("geese-agent"));
        let mut client = self.client.clone();
        if let (Some(s), Some(r)) = (&self.secrets, AgentRange::new(first, count)) {
            client.credentials = Some(s.credential(&security::agents_user(r)));
        }
        c.args(client.to_args()).args(["--run", &self.run, "--id", &first.to_string(), "--agents", &count.to_string()]);
        if let Some(s) = &self.subscribe {
            let modes: Vec<&str> = s.split(',').collect();
            c.args(["--subscribe", modes[i % modes.len()]]);
        }
        if let Some(p) = self.population_files.get(i) {
            c.arg("--population-out").arg(p);
        }
        c.stdin(Stdio::null()).stdout(Stdio::null());
        c.stderr(if self.quiet { Stdio::null() } else { Stdio::inherit() });
        c.kill_on_drop(true);
        c
    }

    fn spawn_agent(&mut self, i: usize) -> Result<(), LaunchError> {
        let (first, count) = (self.agents[i].first, self.agents[i].count);
        let child = self.agent_command(i, first, count).spawn().map_err(io("cannot start geese-agent"))?;
        self.spawned.extend(child.id());
        let a = &mut self.agents[i];
        a.pid = child.id();
        a.child = Some(child);
        a.killed = false;
        Ok(())
    }

    /// SIGKILL agent process `i` (by its PID).
    pub fn kill_agent(&mut self, i: usize) {
        if let Some(a) = self.agents.get_mut(i) {
            if let Some(c) = a.child.as_mut() {
                let _ = c.start_kill();
            }
            a.killed = true;
        }
    }

    /// Start agent process `i` again (same ids: its agents rejoin with fresh genes).
    pub fn restart_agent(&mut self, i: usize) -> Result<(), LaunchError> {
        if let Some(mut c) = self.agents.get_mut(i).and_then(|a| a.child.take()) {
            let _ = c.start_kill();
            let _ = c.try_wait();
        }
        self.spawn_agent(i)
    }

    /// The run name (the `<run>` of every key).
    pub fn run_name(&self) -> &str {
        &self.run
    }

    /// Zenoh arguments a client of this run connects with (no login).
    pub fn client_args(&self) -> &CommonArgs {
        &self.client
    }

    /// The credential file of `user` in this run (none when it runs `--insecure`).
    pub fn credential(&self, user: &str) -> Option<PathBuf> {
        self.secrets.as_ref().map(|s| s.credential(user))
    }

    /// Zenoh arguments of a client logging in as `user` (as [`Swarm::client_args`] when
    /// the run is not secured).
    pub fn client_args_as(&self, user: &str) -> CommonArgs {
        CommonArgs { credentials: self.credential(user), ..self.client.clone() }
    }

    /// PIDs of every process launched so far (world and agents, killed ones included).
    pub fn all_pids(&self) -> Vec<u32> {
        self.spawned.clone()
    }

    /// PIDs of the agent processes that are running.
    pub fn agent_pids(&self) -> Vec<u32> {
        self.agents.iter().filter(|a| !a.killed).filter_map(|a| a.pid).collect()
    }

    /// Resident set size (KiB) of each running agent process, from /proc.
    pub fn agent_rss_kib(&self) -> Vec<u64> {
        self.agent_pids().into_iter().filter_map(rss_kib).collect()
    }

    /// The private part of it (`RssAnon`, KiB): what each further process costs, as
    /// its code's pages are resident once for all of them.
    pub fn agent_private_kib(&self) -> Vec<u64> {
        self.agent_pids()
            .into_iter()
            .filter_map(|pid| proc_number(&format!("/proc/{pid}/status"), "RssAnon:"))
            .collect()
    }

    pub fn world_rss_kib(&self) -> Option<u64> {
        self.world_pid.and_then(rss_kib)
    }

    /// Read (and remove) the population files the agent processes wrote at their end.
    fn take_population(&mut self) -> Vec<geese_agent::program::Member> {
        let mut members = Vec::new();
        for p in std::mem::take(&mut self.population_files) {
            match std::fs::read(&p).map_err(|e| e.to_string()).and_then(|b| {
                serde_json::from_slice::<Vec<geese_agent::program::Member>>(&b).map_err(|e| e.to_string())
            }) {
                Ok(m) => members.extend(m),
                Err(e) => tracing::warn!("agent process population {}: {e}", p.display()),
            }
            let _ = std::fs::remove_file(&p);
        }
        members.sort_by_key(|m| m.agent);
        members
    }

    async fn shutdown(&mut self, grace: Duration) {
        let deadline = Instant::now() + grace;
        let mut all: Vec<&mut Child> =
            self.agents.iter_mut().filter_map(|a| a.child.as_mut()).chain(self.world.as_mut()).collect();
        for c in all.iter_mut() {
            let left = deadline.saturating_duration_since(Instant::now());
            if tokio::time::timeout(left, c.wait()).await.is_err() {
                // Still there after the grace period: end it by PID.
                let _ = c.start_kill();
                let _ = tokio::time::timeout(Duration::from_secs(5), c.wait()).await;
            }
        }
    }
}

/// VmRSS of a process in KiB (Linux).
pub fn rss_kib(pid: u32) -> Option<u64> {
    proc_number(&format!("/proc/{pid}/status"), "VmRSS:")
}

/// The first number after `key` on the line of a `/proc` file that starts with it
/// (`VmRSS:  1234 kB`, `MemAvailable: …`, `Max open files  1024  4096  files`).
pub fn proc_number(file: &str, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(file).ok()?;
    let line = text.lines().find_map(|l| l.strip_prefix(key))?;
    line.split_whitespace().next()?.parse().ok()
}

/// What a distributed run amounts to.
#[derive(Clone, Debug)]
pub struct NetOutcome {
    pub summary: TrialSummary,
    /// All steps ran (false: stopped early).
    pub completed: bool,
    /// Steps reported.
    pub reports: u64,
    /// From the first report to the last (the run proper, start-up excluded).
    pub run_seconds: f64,
    /// From launch to the end, start-up and shutdown included.
    pub wall_seconds: f64,
    /// RSS of each agent process near the end of the run (KiB).
    pub agent_rss_kib: Vec<u64>,
    /// Its private (anonymous) part (KiB).
    pub agent_private_kib: Vec<u64>,
    pub world_rss_kib: Option<u64>,
    pub processes: u32,
    pub agents_per_process: u32,
    /// Perturbations sent on the control plane during the run (`geese control`), in
    /// arrival order, for the manifest.
    pub control_log: Vec<Control>,
    /// The population the agents ended with (one member per agent whose process wrote
    /// it), in agent order.
    pub members: Vec<geese_agent::program::Member>,
    /// The locality map the world counted, if the run asked for one.
    pub locality: Option<Vec<geese_world::locality::Count>>,
}

/// Where the binaries are: `bin_dir`, else `$GEESE_BIN_DIR`, else next to this
/// executable (its parent when it is a test executable in `deps/`).
pub fn find_bin_dir(bin_dir: Option<&Path>) -> Result<PathBuf, LaunchError> {
    let dir = match (bin_dir, std::env::var_os("GEESE_BIN_DIR")) {
        (Some(d), _) => d.to_path_buf(),
        (None, Some(d)) => PathBuf::from(d),
        (None, None) => {
            let exe = std::env::current_exe().map_err(io("cannot locate this executable"))?;
            let mut d = exe.parent().map(Path::to_path_buf).unwrap_or_default();
            if d.file_name().is_some_and(|n| n == "deps") {
                d.pop();
            }
            d
        }
    };
    for bin in ["geese-world", "geese-agent"] {
        if !dir.join(bin).exists() {
            return Err(LaunchError::MissingBinary { bin: bin.into(), dir });
        }
    }
    Ok(dir)
}

/// A run name unique to this launch (also between launches of one process running
/// trials in parallel: a counter joins the PID and the clock).
pub fn unique_run_name() -> String {
    static LAUNCHES: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let k = LAUNCHES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    format!("r{}-{:x}-{k}", std::process::id(), nanos & 0xffff_ffff)
}

/// Campaign trials over Zenoh (`geese campaign --processes N`): every trial launches its
/// own world server and agent processes with a unique run name, so trials running in
/// parallel never hear each other.
pub struct OverZenoh {
    pub opts: NetOptions,
}

impl crate::campaigns::campaign::TrialRunner for OverZenoh {
    fn transport(&self) -> &str {
        "zenoh"
    }

    fn run(
        &self,
        spec: &RunSpec,
        observe: &mut dyn FnMut(&geese_proto::StepReport),
    ) -> Result<crate::run::trial::Ran, crate::campaigns::campaign::TrialError> {
        let opts = NetOptions { run: None, ..self.opts.clone() };
        match run_net(spec, &opts, |r, _| observe(&r.report)) {
            Ok(out) if out.completed => Ok(crate::run::trial::Ran { summary: out.summary, members: out.members }),
            Ok(out) => Err(format!("the world stopped after {} of {} steps", out.reports, spec.config.steps).into()),
            // Ctrl-C ends the campaign; it is no failure of the trial (the children are
            // gone by now).
            Err(LaunchError::Interrupted) => Err(Box::new(crate::campaigns::campaign::Interrupted)),
            Err(e) => Err(e.into()),
        }
    }
}

/// The credentials of a run of `agents` agents in processes of `per` under `opts`: made
/// fresh, opened from `geese secure init`'s directory, or none.
fn run_secrets(
    opts: &NetOptions,
    run: &str,
    local: &[AgentRange],
    opened: Option<Secrets>,
) -> Result<Option<Secrets>, LaunchError> {
    let sec = |e: security::SecurityError| LaunchError::Invalid(e.to_string());
    match (&opts.security, opened) {
        (Security::Off, _) => Ok(None),
        (Security::PerRun, _) if opts.processes == 0 => Err(LaunchError::Invalid(
            "--processes 0: agent processes started elsewhere need credentials; make them with `geese secure init` and pass --secrets DIR (or run --insecure)".into(),
        )),
        (Security::PerRun, _) if opts.zenoh.router.is_some() => Err(LaunchError::Invalid(
            "--router: an external router checks logins against its own files; make them with `geese secure init` and pass --secrets DIR to both (or run --insecure)".into(),
        )),
        (Security::PerRun, _) => {
            let layout = Layout { run: run.into(), agents: local.to_vec(), routers: Vec::new() };
            Secrets::temporary(&layout).map(Some).map_err(sec)
        }
        (Security::Dir(dir), opened) => {
            let s = match opened {
                Some(s) => s,
                None => Secrets::open(dir).map_err(sec)?,
            };
            if s.layout().run != run {
                return Err(LaunchError::Invalid(format!(
                    "--secrets {}: made for run {:?}, not {run:?} (pass --run-name {0:?}, or make new ones)",
                    dir.display(),
                    s.layout().run
                )));
            }
            if let Some(r) = local.iter().find(|r| !s.layout().agents.contains(r)) {
                return Err(LaunchError::Invalid(format!(
                    "--secrets {}: no credential for an agent process of agents {r} (it was made for {})",
                    dir.display(),
                    s.layout().agents.iter().map(|r| r.to_string()).collect::<Vec<_>>().join(", ")
                )));
            }
            Ok(Some(s))
        }
    }
}

/// The world server's specification of `spec` under `opts`.
pub fn net_spec(spec: &RunSpec, opts: &NetOptions, run: &str) -> Result<NetRunSpec, LaunchError> {
    let c = &spec.config;
    let json = |v: Result<String, serde_json::Error>| v.map_err(|e| LaunchError::Invalid(e.to_string()));
    for (name, p) in [("--intent-loss", opts.loss.intent), ("--percept-loss", opts.loss.percept)] {
        if !(0.0..=1.0).contains(&p) {
            return Err(LaunchError::Invalid(format!("{name} {p} is outside [0, 1]")));
        }
    }
    Ok(NetRunSpec {
        run: run.into(),
        seed: c.seed,
        steps: c.steps,
        agents: c.world.agents,
        world_json: json(serde_json::to_string(&c.world))?,
        learner_json: json(serde_json::to_string(&*spec.learner))?,
        program_json: json(serde_json::to_string(&*spec.program))?,
        grammar_name: spec.grammar_name.clone(),
        grammar_text: spec.grammar_text.to_string(),
        regime: c.regime(),
        perturbations: c.perturbations.iter().map(|p| (p.at, p.change.clone())).collect(),
        loss: opts.loss,
        deadlines: opts.deadlines,
        bare: opts.bare,
        expect_orchestrator: true,
    })
}

/// Private memory of one agent process hosting one agent, MiB: its heap, stacks and
/// the kernel's share (page tables, socket buffers). Measured 1.8 MiB of anonymous
/// memory a process at 300×1 and 1000×1 (issue 29: the agent uses the system
/// allocator), doubled for what `/proc` does not show.
pub const AGENT_PROCESS_MIB: f64 = 4.0;
/// Code and read-only data of `geese-agent`, resident once however many processes map
/// them (11.8–13.1 MiB of each process's RSS is these shared pages), MiB.
pub const AGENT_SHARED_MIB: f64 = 16.0;
/// Memory each further hosted agent adds, MiB (10×100: 20.6 MiB a process, 13 MiB of
/// it shared code; rounded up).
pub const HOSTED_AGENT_MIB: f64 = 0.17;
/// The world server's resident memory, MiB, plus what it adds per agent process
/// (145 MiB with 300 processes).
pub const WORLD_MIB: f64 = 64.0;
pub const WORLD_MIB_PER_PROCESS: f64 = 0.5;
/// Share of the available memory a launch may plan to use: the rest is left to the
/// machine (and to the estimate's error).
pub const MEMORY_SHARE: f64 = 0.75;
/// Open files the launcher's side needs besides its processes': the world server holds
/// a socket per agent process (and the launcher a few descriptors per child).
pub const FILES_PER_PROCESS: u64 = 4;
pub const FILES_BASE: u64 = 256;

/// What this machine can hold, read before a launch starts anything: the memory the
/// kernel says is available and the open-files limit the world server inherits. A
/// launch that would not fit is refused with the figures, never tried: hundreds of
/// processes that exhaust the memory take the whole machine down with them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Capacity {
    /// `MemAvailable`, KiB (`None`: unknown, not checked).
    pub mem_available_kib: Option<u64>,
    /// The soft `Max open files` limit (`None`: unknown, not checked).
    pub open_files: Option<u64>,
}

impl Capacity {
    /// Read from `/proc` (Linux); what cannot be read is not checked.
    pub fn of_this_machine() -> Capacity {
        Capacity {
            mem_available_kib: proc_number("/proc/meminfo", "MemAvailable:"),
            open_files: proc_number("/proc/self/limits", "Max open files"),
        }
    }

    /// Estimated memory of `processes` agent processes hosting `per` agents each, and
    /// of the world server, MiB: what the machine loses to them, so the agents' shared
    /// code counts once.
    pub fn needed_mib(processes: u32, per: u32) -> f64 {
        Self::fixed_mib() + f64::from(processes) * Self::each_mib(per)
    }

    /// What a launch costs whatever its size: the world server and the agents' code.
    fn fixed_mib() -> f64 {
        WORLD_MIB + AGENT_SHARED_MIB
    }

    /// What each agent process of `per` agents adds, the world's share included.
    fn each_mib(per: u32) -> f64 {
        AGENT_PROCESS_MIB + HOSTED_AGENT_MIB * f64::from(per.saturating_sub(1)) + WORLD_MIB_PER_PROCESS
    }

    /// Whether `processes` agent processes of `per` agents fit; the error names the
    /// value, what it needs and the limit.
    pub fn check(&self, processes: u32, per: u32) -> Result<(), String> {
        if let Some(avail) = self.mem_available_kib {
            let usable = avail as f64 / 1024.0 * MEMORY_SHARE;
            let needed = Self::needed_mib(processes, per);
            if needed > usable {
                let each = Self::each_mib(per);
                let fit = ((usable - Self::fixed_mib()) / each).floor().max(0.0) as u64;
                return Err(format!(
                    "--processes {processes}: {processes} agent processes of {per} agent(s) need about {:.1} GiB \
                     ({each:.1} MiB each and the world server), more than {:.0} % of the {:.1} GiB this machine \
                     has available; at most {fit} fit (host more agents per process with --agents-per-process)",
                    needed / 1024.0,
                    MEMORY_SHARE * 100.0,
                    avail as f64 / 1024.0 / 1024.0,
                ));
            }
        }
        if let Some(limit) = self.open_files {
            let needed = FILES_BASE + FILES_PER_PROCESS * u64::from(processes);
            if needed > limit {
                return Err(format!(
                    "--processes {processes}: the world server would need about {needed} open files, more than \
                     the limit of {limit} (raise it with `ulimit -n`, or use fewer processes)"
                ));
            }
        }
        Ok(())
    }
}

/// Run `spec` as separate processes; `observe` sees every step report (and may kill or
/// restart agent processes through the [`Swarm`]).
pub fn run_net(
    spec: &RunSpec,
    opts: &NetOptions,
    observe: impl FnMut(&NetReport, &mut Swarm),
) -> Result<NetOutcome, LaunchError> {
    let rt = zenoh_bus::runtime(2).map_err(io("cannot start the async runtime"))?;
    rt.block_on(run_net_async(spec, opts, observe))
}

/// The pace the viewer last asked of the world, as the launcher saw it go by.
struct PaceSeen {
    paused: bool,
    rate: f64,
    /// When it last changed.
    at: Instant,
}

enum Ev {
    Report(Vec<u8>),
    WorldGone,
}

async fn run_net_async(
    spec: &RunSpec,
    opts: &NetOptions,
    mut observe: impl FnMut(&NetReport, &mut Swarm),
) -> Result<NetOutcome, LaunchError> {
    let launched = Instant::now();
    spec.config.fidelity.check_distributed().map_err(LaunchError::Invalid)?;
    let n = spec.config.world.agents;
    if n == 0 {
        return Err(LaunchError::Invalid("a run needs at least one agent".into()));
    }
    let per = match opts.agents_per_process {
        Some(0) => return Err(LaunchError::Invalid("--agents-per-process must be at least 1".into())),
        Some(k) => k,
        None => n.div_ceil(opts.processes.max(1)),
    };
    // Before anything starts: whether the processes fit in this machine.
    if opts.processes > 0 {
        Capacity::of_this_machine().check(opts.processes, per).map_err(LaunchError::Invalid)?;
    }
    let bin_dir = find_bin_dir(opts.bin_dir.as_deref())?;
    let opened = match &opts.security {
        Security::Dir(d) => Some(Secrets::open(d).map_err(|e| LaunchError::Invalid(e.to_string()))?),
        _ => None,
    };
    // Secrets made for a run name that run, unless another is asked for.
    let run = match (&opts.run, &opened) {
        (Some(r), _) => r.clone(),
        (None, Some(s)) => s.layout().run.clone(),
        (None, None) => unique_run_name(),
    };
    if !keys::valid_run_name(&run) {
        return Err(LaunchError::Invalid(format!("run name {run:?}")));
    }
    // The id ranges of the agent processes launched here, as the access-control list
    // names them.
    let local = if opts.processes > 0 { Layout::even(&run, n, per).agents } else { Vec::new() };
    let secrets = run_secrets(opts, &run, &local, opened)?.map(std::sync::Arc::new);
    let nspec = net_spec(spec, opts, &run)?;
    let spec_path = std::env::temp_dir().join(format!("geese-{run}.json"));
    std::fs::write(&spec_path, serde_json::to_vec_pretty(&nspec).map_err(|e| LaunchError::Invalid(e.to_string()))?)
        .map_err(io(format!("cannot write {}", spec_path.display())))?;
    let _cleanup = RemoveOnDrop(spec_path.clone());

    // The world first: it tells where to connect.
    let mut world = Command::new(bin_dir.join("geese-world"));
    // Few local agent processes: one Zenoh thread in the world (not for agents started
    // elsewhere, `--processes 0`, whose number is unknown).
    let few = (1..=zenoh_bus::LEAN_WORLD_MAX_PROCESSES).contains(&opts.processes);
    if few && std::env::var_os(zenoh_bus::ZENOH_RUNTIME_ENV).is_none() {
        world.env(zenoh_bus::ZENOH_RUNTIME_ENV, zenoh_bus::LEAN_ZENOH_RUNTIME);
    }
    // The world counts the locality map and writes it here as it exits, as agent
    // processes write their population (`--population-out`).
    let locality_file = spec.locality.map(|_| std::env::temp_dir().join(format!("geese-{run}-locality.csv")));
    let _locality_cleanup = locality_file.clone().map(RemoveOnDrop);
    if let (Some(w), Some(path)) = (spec.locality, &locality_file) {
        world.arg("--locality").arg(w.to_string()).arg("--locality-out").arg(path);
    }
    // The world is the router its clients log in to (it checks their logins and
    // enforces the access-control list) or, with --router, one more client.
    let mut world_zenoh = opts.zenoh.clone();
    if let Some(s) = &secrets {
        if opts.zenoh.router.is_none() {
            world_zenoh.users = Some(s.users());
            world_zenoh.acl = Some(s.acl());
        } else {
            world_zenoh.credentials = Some(s.credential(security::WORLD));
        }
    }
    world
        .args(world_zenoh.to_args())
        .arg("--spec")
        .arg(&spec_path)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(if opts.quiet_children { Stdio::null() } else { Stdio::inherit() })
        .kill_on_drop(true);
    let mut world = world.spawn().map_err(io("cannot start geese-world"))?;
    let world_pid = world.id();
    let stdout = world.stdout.take().ok_or_else(|| LaunchError::WorldStart("no stdout".into()))?;
    let mut lines = BufReader::new(stdout).lines();
    let mut locators = Vec::new();
    let ready = tokio::time::timeout(Duration::from_secs(60), async {
        while let Ok(Some(l)) = lines.next_line().await {
            if let Some(loc) = l.strip_prefix("locator=") {
                locators.push(loc.to_string());
            } else if l.starts_with("ready") {
                return true;
            }
        }
        false
    })
    .await;
    if !matches!(ready, Ok(true)) {
        let _ = world.start_kill();
        return Err(LaunchError::WorldStart("it did not announce its locator".into()));
    }
    // Keep draining the world's stdout so it never blocks on a full pipe.
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });

    // Every other process is a client of the world's router (or of --router).
    let client = CommonArgs {
        zenoh_config: opts.zenoh.zenoh_config.clone(),
        mode: None,
        connect: if opts.zenoh.router.is_some() { opts.zenoh.connect.clone() } else { locators.clone() },
        listen: Vec::new(),
        router: opts.zenoh.router.clone(),
        cfg: opts.zenoh.cfg.clone(),
        credentials: None,
        users: None,
        acl: None,
    };
    // The launcher is the operator: it alone may use the control plane.
    let operator =
        CommonArgs { credentials: secrets.as_ref().map(|s| s.credential(security::OPERATOR)), ..client.clone() };
    let session = zenoh_bus::open(&operator, Role::Client).await?;
    let (tx, mut rx) = unbounded_channel::<Ev>();
    let t = tx.clone();
    let _reports = session
        .declare_subscriber(keys::report(&run))
        .callback(move |s| {
            let _ = t.send(Ev::Report(s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(zerr)?;
    // Record what is scheduled on the control plane while the run goes on, so the
    // manifest says how the run was perturbed.
    // The viewer's pace commands too: a paused run sends no reports, and must not be
    // taken for a stalled one.
    let control_log = std::sync::Arc::new(std::sync::Mutex::new(Vec::<Control>::new()));
    let pace = std::sync::Arc::new(std::sync::Mutex::new(PaceSeen { paused: false, rate: 0.0, at: Instant::now() }));
    let (log, p) = (control_log.clone(), pace.clone());
    let _control = session
        .declare_subscriber(keys::all_ctl(&run))
        .callback(move |s| {
            let Ok(c) = decode::<Control>(&s.payload().to_bytes()) else { return };
            let mut pace = p.lock().unwrap_or_else(|e| e.into_inner());
            match c {
                Control::Schedule { .. } => log.lock().unwrap_or_else(|e| e.into_inner()).push(c),
                Control::Pause => pace.paused = true,
                Control::Resume => pace.paused = false,
                Control::StepRate(r) if geese_proto::limits::check_step_rate(r).is_ok() => pace.rate = r,
                _ => return,
            }
            pace.at = Instant::now();
        })
        .await
        .map_err(zerr)?;
    let view = match opts.view {
        Some(port) => {
            let v = crate::live::view::ZenohView::attach(&session, &run, port, true)
                .await
                .map_err(|e| LaunchError::Invalid(format!("viewer: {e}")))?;
            println!("view: {}", v.url());
            Some(v)
        }
        None => None,
    };
    if let Some(r) = opts.step_rate {
        // The world listens to the control plane before it announces itself: this
        // reaches it before the first step.
        geese_proto::limits::check_step_rate(r).map_err(|e| LaunchError::Invalid(format!("--step-rate: {e}")))?;
        let bytes = encode(&Control::StepRate(r)).map_err(|e| LaunchError::Invalid(e.to_string()))?;
        zenoh_bus::put(&session, &keys::ctl(&run, "view"), bytes).await?;
    }
    let t = tx.clone();
    let run2 = run.clone();
    let _presence = session
        .liveliness()
        .declare_subscriber(keys::world_presence(&run))
        .history(true)
        .callback(move |s| {
            if s.kind() == SampleKind::Delete && keys::parse(&run2, s.key_expr().as_str()) == Parsed::WorldPresence {
                let _ = t.send(Ev::WorldGone);
            }
        })
        .await
        .map_err(zerr)?;
    let token = session.liveliness().declare_token(keys::orchestrator_presence(&run)).await.map_err(zerr)?;

    if let (Some(s), false) = (&secrets, opts.quiet_children) {
        println!(
            "control: geese control --run {run} -e {} --credentials {} (removed when the run ends)",
            locators.first().map(String::as_str).unwrap_or("?"),
            s.credential(security::OPERATOR).display()
        );
    }
    let mut swarm = Swarm {
        bin_dir,
        run: run.clone(),
        client,
        secrets: secrets.clone(),
        subscribe: opts.subscribe.clone(),
        quiet: opts.quiet_children,
        world_pid,
        world: Some(world),
        agents: Vec::new(),
        spawned: world_pid.into_iter().collect(),
        population_files: Vec::new(),
    };
    for (i, r) in local.iter().enumerate() {
        swarm.agents.push(AgentProc { first: r.first, count: r.len(), child: None, pid: None, killed: false });
        if !opts.bare {
            swarm.population_files.push(std::env::temp_dir().join(format!("geese-{run}-population-{i}.json")));
        }
    }
    for i in 0..swarm.agents.len() {
        swarm.spawn_agent(i)?;
    }
    let processes = swarm.agents.len() as u32;

    let c = &spec.config;
    let mut summary = TrialSummary::for_run(c.seed, &c.perturbations);
    let mut first_report: Option<Instant> = None;
    let mut last_report = Instant::now();
    let mut reports = 0u64;
    let mut completed = false;
    let mut agent_rss = Vec::new();
    let mut agent_private = Vec::new();
    let mut world_rss = None;
    let rss_at = (c.steps * 9 / 10).max(1);
    let join_patience = Duration::from_millis(opts.deadlines.join_ms as u64) + Duration::from_secs(10);
    let mut outcome: Result<(), LaunchError> = Ok(());
    // Ctrl-C or SIGTERM: the children go, and so do the run's secrets.
    let ctrl_c = zenoh_bus::shutdown_signal();
    tokio::pin!(ctrl_c);
    // The world's liveliness token travels at a higher priority than its last reports:
    // once it is gone, give the reports a moment to land before concluding.
    let mut world_gone: Option<Instant> = None;
    loop {
        let mut patience = if first_report.is_some() { opts.stall } else { join_patience };
        let (since, held) = {
            // Held by the viewer: no patience runs out while paused (look again each
            // second); otherwise it counts from the last pace change, and a step may take
            // as long as the rate limit says.
            let p = pace.lock().unwrap_or_else(|e| e.into_inner());
            if p.rate > 0.0 {
                patience += Duration::from_secs_f64(1.0 / p.rate);
            }
            if p.paused {
                patience = Duration::from_secs(1);
            }
            (if p.paused { Instant::now() } else { last_report.max(p.at) }, p.paused)
        };
        let mut left = (since + patience).saturating_duration_since(Instant::now());
        if let Some(g) = world_gone {
            left = left.min((g + Duration::from_secs(2)).saturating_duration_since(Instant::now()));
        }
        let ev = tokio::select! {
            ev = rx.recv() => ev,
            _ = tokio::time::sleep(left) => {
                if held && world_gone.is_none() {
                    continue;
                }
                outcome = Err(if world_gone.is_some() {
                    LaunchError::WorldGone(summary.steps)
                } else {
                    LaunchError::Stalled(patience)
                });
                break;
            }
            _ = &mut ctrl_c => {
                outcome = Err(LaunchError::Interrupted);
                break;
            }
        };
        match ev {
            Some(Ev::Report(bytes)) => match decode::<ReportMsg>(&bytes) {
                Ok(ReportMsg::Step(r)) => {
                    let now = Instant::now();
                    first_report.get_or_insert(now);
                    last_report = now;
                    reports += 1;
                    summary.record(c.threshold, &r.report);
                    if r.report.step == rss_at {
                        agent_rss = swarm.agent_rss_kib();
                        agent_private = swarm.agent_private_kib();
                        world_rss = swarm.world_rss_kib();
                    }
                    observe(&r, &mut swarm);
                    let step = r.report.step;
                    for k in opts.kill.iter().filter(|k| k.at == step) {
                        let live: Vec<usize> = (0..swarm.agents.len()).filter(|&i| !swarm.agents[i].killed).collect();
                        for &i in live.iter().rev().take(k.count as usize) {
                            swarm.kill_agent(i);
                        }
                    }
                    if opts.restart_at.contains(&step) {
                        for i in 0..swarm.agents.len() {
                            if swarm.agents[i].killed {
                                swarm.restart_agent(i)?;
                            }
                        }
                    }
                }
                Ok(ReportMsg::Done { steps, completed: done, requested }) => {
                    completed = done && steps == c.steps;
                    if !completed && !requested {
                        outcome = Err(LaunchError::WorldGone(steps));
                    }
                    break;
                }
                Err(e) => tracing::warn!("undecodable report dropped: {e}"),
            },
            Some(Ev::WorldGone) => {
                world_gone.get_or_insert_with(Instant::now);
            }
            None => {
                outcome = Err(LaunchError::WorldGone(summary.steps));
                break;
            }
        }
    }
    let run_seconds = match first_report {
        Some(f) => last_report.duration_since(f).as_secs_f64(),
        None => 0.0,
    };
    if outcome.is_err() {
        // Ask the world to stop; its departure takes the agents with it.
        if let Ok(b) = encode(&Control::Stop) {
            let _ = zenoh_bus::put(&session, &keys::ctl(&run, "stop"), b).await;
        }
    }
    drop(view);
    let _ = token.undeclare().await;
    swarm.shutdown(Duration::from_secs(if outcome.is_ok() { 15 } else { 5 })).await;
    let _ = session.close().await;
    outcome?;
    let members = swarm.take_population();
    let locality = match &locality_file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(io(format!("the world server wrote no locality map {}", path.display())))?;
            let counts = geese_world::locality::parse_csv(&text)
                .map_err(|e| LaunchError::Invalid(format!("locality map {}: {e}", path.display())))?;
            Some(counts)
        }
        None => None,
    };
    summary.wall_seconds = launched.elapsed().as_secs_f64();
    Ok(NetOutcome {
        wall_seconds: summary.wall_seconds,
        summary,
        completed,
        reports,
        run_seconds,
        agent_rss_kib: agent_rss,
        agent_private_kib: agent_private,
        world_rss_kib: world_rss,
        processes,
        agents_per_process: per,
        control_log: control_log.lock().map(|l| l.clone()).unwrap_or_default(),
        members,
        locality,
    })
}

struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// Header of `net.csv`, the per-step network counters of a distributed run.
pub const NET_CSV_HEADER: &str =
    "step,processes,intents_lost,intents_late,percepts_lost,percepts_missing,genes_lost,genes_late,hostile,lt_mean,wait_us,genes_ahead,deadline_hits";

/// `geese run --processes N`: run, write `steps.csv`, `net.csv` and the manifest into
/// `out`, print the same lines as an in-process run.
pub fn run_cli(spec: &RunSpec, opts: &NetOptions, out: &Path, quiet: bool) -> anyhow::Result<NetOutcome> {
    use anyhow::Context;
    let csv_path = out.join("steps.csv");
    let net_path = out.join("net.csv");
    let mut csv = StepCsv::create(&csv_path).with_context(|| format!("cannot write {}", csv_path.display()))?;
    let mut net = std::io::BufWriter::new(
        std::fs::File::create(&net_path).with_context(|| format!("cannot write {}", net_path.display()))?,
    );
    writeln!(net, "{NET_CSV_HEADER}")?;
    let steps = spec.config.steps;
    let bar = if quiet { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(steps) };
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} steps  {msg}  [{elapsed} < {eta}]")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut io_err: Option<std::io::Error> = None;
    let outcome = run_net(spec, opts, |r, _| {
        let rep = &r.report;
        let n = &r.net;
        let res = csv.write(rep).and_then(|_| {
            writeln!(
                net,
                "{},{},{},{},{},{},{},{},{},{},{},{},{}",
                rep.step,
                n.processes,
                n.intents_lost,
                n.intents_late,
                n.percepts_lost,
                n.percepts_missing,
                rep.genes_lost,
                n.genes_late,
                n.hostile,
                rep.lt_mean,
                n.wait_us,
                n.genes_ahead,
                n.deadline_hits
            )
        });
        if let Err(e) = res {
            io_err.get_or_insert(e);
        }
        if rep.step % 50 == 0 {
            bar.set_position(rep.step);
            bar.set_message(format!("task {:.2} %  live {}", rep.task_pct, rep.live_agents));
        }
    });
    bar.finish_and_clear();
    let outcome = outcome?;
    if let Some(e) = io_err {
        return Err(e).context("writing results");
    }
    csv.finish()?;
    net.flush()?;
    if let Some(counts) = &outcome.locality {
        let path = write_locality(out, counts).with_context(|| format!("cannot write {}", out.display()))?;
        let total: u64 = counts.iter().map(|c| c.count).sum();
        println!("locality map: {} ({total} agent-steps)", path.display());
    }
    write_manifest(out, spec, "zenoh", Some(opts.security.describe()), &outcome.summary, &outcome.control_log)?;
    Ok(outcome)
}

/// The distributed-mode flags of `geese run`.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct NetArgs {
    /// Run distributed: the world server and N agent processes on this machine, over
    /// Zenoh (0: start only the world and wait for agent processes started elsewhere).
    #[arg(long, value_name = "N")]
    pub processes: Option<u32>,
    /// Agents hosted per agent process [default: the agents split evenly over N].
    #[arg(long, value_name = "K")]
    pub agents_per_process: Option<u32>,
    /// Receiver-side probability of losing each gene delivery (in-process too).
    #[arg(long, value_name = "P")]
    pub gene_loss: Option<f64>,
    /// World-side probability of dropping each arrived intent (distributed only).
    #[arg(long, value_name = "P")]
    pub intent_loss: Option<f64>,
    /// Agent-side probability of dropping each percept (distributed only).
    #[arg(long, value_name = "P")]
    pub percept_loss: Option<f64>,
    /// World: longest wait for a step's intents [default 5000].
    #[arg(long, value_name = "MS")]
    pub intent_timeout_ms: Option<u32>,
    /// Agents: longest wait for cell-mates' genes [default 3000].
    #[arg(long, value_name = "MS")]
    pub gene_timeout_ms: Option<u32>,
    /// World: longest wait for every agent process to be present [default 120000].
    #[arg(long, value_name = "MS")]
    pub join_timeout_ms: Option<u32>,
    /// SIGKILL COUNT agent processes after step STEP (repeatable).
    #[arg(long, value_name = "STEP:COUNT")]
    pub kill: Vec<String>,
    /// Restart the killed agent processes after step STEP (repeatable).
    #[arg(long, value_name = "STEP")]
    pub restart_at: Vec<u64>,
    /// Run name, the <run> of every key [default: unique per launch].
    #[arg(long)]
    pub run_name: Option<String>,
    /// Directory of geese-world and geese-agent [default: next to geese].
    #[arg(long)]
    pub bin_dir: Option<PathBuf>,
    /// How agent processes read cells: auto, cells or all; a comma-separated list is
    /// cycled over the processes (e.g. `all,cells`: a mixed swarm).
    #[arg(long)]
    pub subscribe: Option<String>,
    /// No logins and no access control (benchmarks; the manifest says so) [default: a
    /// fresh credential per process and an access-control list for the run].
    #[arg(long, conflicts_with = "secrets")]
    pub insecure: bool,
    /// Use the credentials and access-control list `geese secure init` made in DIR
    /// (multi-host runs, external routers).
    #[arg(long, value_name = "DIR")]
    pub secrets: Option<PathBuf>,
    #[command(flatten)]
    pub zenoh: CommonArgs,
}

impl NetArgs {
    /// The security the flags ask for.
    pub fn security(&self) -> Security {
        match (&self.secrets, self.insecure) {
            (Some(d), _) => Security::Dir(d.clone()),
            (None, true) => Security::Off,
            (None, false) => Security::PerRun,
        }
    }
}

impl NetArgs {
    /// Apply the flags that change the run configuration itself.
    pub fn apply(&self, mut c: crate::run::config::RunConfig) -> crate::run::config::RunConfig {
        if let Some(p) = self.gene_loss {
            c.gene_loss = p;
        }
        c
    }

    /// The launcher options, or `None` for an in-process run.
    pub fn options(&self) -> anyhow::Result<Option<NetOptions>> {
        let Some(processes) = self.processes else {
            if self.intent_loss.is_some() || self.percept_loss.is_some() || !self.kill.is_empty() {
                anyhow::bail!("--intent-loss, --percept-loss and --kill need --processes N (a distributed run)");
            }
            return Ok(None);
        };
        let mut kill = Vec::new();
        for k in &self.kill {
            let (at, count) = k
                .split_once(':')
                .and_then(|(a, c)| Some((a.parse().ok()?, c.parse().ok()?)))
                .ok_or_else(|| anyhow::anyhow!("--kill {k:?}: expected STEP:COUNT"))?;
            kill.push(KillPlan { at, count });
        }
        if let Some(s) = &self.subscribe {
            if !s.split(',').all(|m| ["auto", "cells", "all"].contains(&m)) {
                anyhow::bail!("--subscribe {s:?}: expected auto, cells or all, or a comma-separated list of them");
            }
        }
        let mut deadlines = Deadlines::default();
        if let Some(v) = self.intent_timeout_ms {
            deadlines.intent_ms = v;
        }
        if let Some(v) = self.gene_timeout_ms {
            deadlines.gene_ms = v;
        }
        if let Some(v) = self.join_timeout_ms {
            deadlines.join_ms = v;
        }
        Ok(Some(NetOptions {
            processes,
            agents_per_process: self.agents_per_process,
            loss: LossRates { intent: self.intent_loss.unwrap_or(0.0), percept: self.percept_loss.unwrap_or(0.0) },
            deadlines,
            zenoh: self.zenoh.clone(),
            bin_dir: self.bin_dir.clone(),
            run: self.run_name.clone(),
            kill,
            restart_at: self.restart_at.clone(),
            subscribe: self.subscribe.clone(),
            security: self.security(),
            ..NetOptions::default()
        }))
    }
}

/// `geese router`: a plain Zenoh router (what `zenohd` would be), for `--router` set-ups
/// and multi-host runs without installing anything.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct RouterArgs {
    #[command(flatten)]
    pub zenoh: CommonArgs,
}

pub fn router_cmd(args: RouterArgs) -> anyhow::Result<()> {
    let mut common = args.zenoh;
    if common.listen.is_empty() && common.zenoh_config.is_none() {
        common.listen.push("tcp/127.0.0.1:7447".into());
    }
    if common.mode.is_none() && common.zenoh_config.is_none() {
        common.mode = Some(zenoh_bus::Mode::Router);
    }
    let rt = zenoh_bus::runtime(1)?;
    rt.block_on(async move {
        let session = zenoh_bus::open(&common, Role::World).await?;
        println!("geese router: listening on {}", common.listen.join(", "));
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            let mut term = signal(SignalKind::terminate())?;
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
        }
        #[cfg(not(unix))]
        tokio::signal::ctrl_c().await?;
        let _ = session.close().await;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_launch_that_does_not_fit_is_refused_with_its_figures() {
        let gib = 1024 * 1024;
        let m = Capacity { mem_available_kib: Some(4 * gib), open_files: Some(20_000) };
        // 1,000 one-agent processes need ~4.5 GiB: more than 75 % of 4 GiB.
        let e = m.check(1000, 1).unwrap_err();
        assert!(e.contains("--processes 1000") && e.contains("4.0 GiB") && e.contains("at most 664 fit"), "{e}");
        assert!(m.check(600, 1).is_ok());
        // Ten processes of 100 agents each fit easily; on 22 GiB, a thousand processes do.
        assert!(m.check(10, 100).is_ok());
        assert!(Capacity { mem_available_kib: Some(22 * gib), ..m }.check(1000, 1).is_ok());
        let files = Capacity { mem_available_kib: None, open_files: Some(1024) };
        let e = files.check(500, 1).unwrap_err();
        assert!(e.contains("--processes 500") && e.contains("limit of 1024"), "{e}");
        assert!(files.check(150, 1).is_ok());
        // What cannot be read is not checked.
        assert!(Capacity { mem_available_kib: None, open_files: None }.check(u32::MAX, 1).is_ok());
    }

    #[test]
    fn this_machine_can_be_read() {
        let c = Capacity::of_this_machine();
        if cfg!(target_os = "linux") {
            assert!(c.mem_available_kib.is_some_and(|k| k > 0) && c.open_files.is_some_and(|n| n > 0), "{c:?}");
        }
    }
}
