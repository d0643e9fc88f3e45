//! Running a target: panics caught, hangs watched, failing inputs saved.
//!
//! A target runs on a worker thread; the calling thread is its watchdog. The worker
//! times every input: one that returns after more than the hang limit is run again,
//! twice at most, and is a hang only if it is never under the limit. Why: the machines
//! that run this are shared, and a build beside the fuzzer stalled a 1.4 ms campaign
//! input for 1.2 s; a real hang is slow every time. An input saved from a stall is
//! counted (`stalls`) but is not a failure. One that never returns cannot be interrupted (a thread cannot be killed), so
//! the watchdog, after three hang limits without a return, makes the input again from
//! its index ([`crate::mutate::input`]), saves it, and gives up on the target with the
//! report so far; the CLI then exits non-zero (the worker is left spinning).
//!
//! Panics are caught with `catch_unwind`. The panic hook stays installed for every other
//! thread (tests running beside the fuzzer still print their panics) and only records
//! the message of a worker's panic instead of printing it.
//!
//! What is not caught: a stack overflow or an allocation failure aborts the process (the
//! Rust runtime does not unwind them). The worker runs on a 2 MiB stack, the default of
//! the Tokio worker threads the binaries decode on, so that deep recursion shows up here
//! rather than only in production; the last index reported by `--progress` brackets
//! the input, and `--first` with `--iterations` replays a range.
use crate::mutate::{self, fnv1a, Material};
use crate::targets::Target;
use std::cell::{Cell, RefCell};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Once};
use std::time::{Duration, Instant};

/// Stack of the worker thread (Tokio's default for its workers).
pub const WORKER_STACK: usize = 2 << 20;

/// How a target is run.
#[derive(Clone, Debug)]
pub struct Options {
    /// Inputs to run.
    pub iterations: u64,
    /// Index of the first input (inputs `first..first + iterations` run).
    pub first: u64,
    pub seed: u64,
    /// An input that takes longer than this is a hang.
    pub hang_limit: Duration,
    /// Where failing inputs are saved (`<dir>/<target>/<hash>.bin`); nowhere if `None`.
    pub crash_dir: Option<PathBuf>,
    /// Failures kept in the report with their inputs (all are counted).
    pub keep: usize,
    /// Print the index reached every this many inputs (0: never), to stderr.
    pub progress: u64,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            iterations: 10_000,
            first: 0,
            seed: 0,
            hang_limit: Duration::from_secs(1),
            crash_dir: None,
            keep: 8,
            progress: 0,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailureKind {
    Panic,
    /// Returned, but after more than the hang limit.
    Slow,
    /// Never returned (the watchdog gave up on the worker).
    Stuck,
}

/// One failing input.
#[derive(Clone, Debug)]
pub struct Failure {
    pub kind: FailureKind,
    pub index: u64,
    pub input: Vec<u8>,
    /// The panic message and location, or how long the input took.
    pub message: String,
    /// Where the input was saved.
    pub saved: Option<PathBuf>,
}

/// What running one target gave.
#[derive(Clone, Debug)]
pub struct Report {
    pub target: &'static str,
    /// Inputs that ran to the end (returned or panicked).
    pub inputs: u64,
    /// Inputs the outermost decoder or parser accepted.
    pub accepted: u64,
    pub panics: u64,
    /// Slow inputs, plus one if the worker got stuck.
    pub hangs: u64,
    /// Inputs over the hang limit once but under it when run again (the machine
    /// stalled, not the input).
    pub stalls: u64,
    pub elapsed: Duration,
    /// The slowest input that returned (its fastest run, for an input run again).
    pub slowest: Duration,
    /// The worker never returned from an input: the run stopped there.
    pub stuck: bool,
    pub failures: Vec<Failure>,
}

impl Report {
    pub fn ok(&self) -> bool {
        self.panics == 0 && self.hangs == 0 && !self.stuck
    }

    /// One line: target, inputs, panics, hangs, stalls, seconds, rate, slowest input,
    /// share of inputs accepted.
    pub fn line(&self) -> String {
        let secs = self.elapsed.as_secs_f64();
        format!(
            "{:<14} {:>10} {:>7} {:>6} {:>7} {:>9.1} {:>10.0} {:>9.1} {:>8.1}",
            self.target,
            self.inputs,
            self.panics,
            self.hangs,
            self.stalls,
            secs,
            self.inputs as f64 / secs.max(1e-9),
            self.slowest.as_secs_f64() * 1e3,
            100.0 * self.accepted as f64 / self.inputs.max(1) as f64
        )
    }

    pub fn header() -> String {
        format!(
            "{:<14} {:>10} {:>7} {:>6} {:>7} {:>9} {:>10} {:>9} {:>8}",
            "target", "inputs", "panics", "hangs", "stalls", "seconds", "inputs/s", "max ms", "valid %"
        )
    }
}

thread_local! {
    /// Set on a worker thread while it runs inputs: its panics are recorded, not printed.
    static QUIET: Cell<bool> = const { Cell::new(false) };
    static LAST_PANIC: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Install (once) the hook that silences workers' panics and keeps their message.
fn install_hook() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if QUIET.with(Cell::get) {
                LAST_PANIC.with(|l| *l.borrow_mut() = Some(info.to_string()));
            } else {
                previous(info);
            }
        }));
    });
}

/// Run `f` with panics caught and silenced; `Err` holds the panic's message.
pub fn run_quiet(f: impl FnOnce()) -> Result<(), String> {
    install_hook();
    let was = QUIET.with(|q| q.replace(true));
    let r = catch_unwind(AssertUnwindSafe(f));
    QUIET.with(|q| q.set(was));
    r.map_err(|_| LAST_PANIC.with(|l| l.borrow_mut().take()).unwrap_or_else(|| "panic".into()))
}

/// Save a failing input as `<dir>/<target>/<fnv1a hex>.bin`.
pub fn save(dir: &Path, target: &str, input: &[u8]) -> std::io::Result<PathBuf> {
    let d = dir.join(target);
    std::fs::create_dir_all(&d)?;
    let p = d.join(format!("{:016x}.bin", fnv1a(input)));
    std::fs::write(&p, input)?;
    Ok(p)
}

/// What the worker shares with the watchdog.
struct Shared {
    /// Index of the input being run.
    index: AtomicU64,
    /// When it started, in µs since the run began; `IDLE` between inputs.
    started_us: AtomicU64,
}

const IDLE: u64 = u64::MAX;

/// Runs again of an input over the hang limit before it counts as a hang.
const RETIMES: usize = 2;

fn failure(kind: FailureKind, index: u64, input: Vec<u8>, message: String, target: &str, opts: &Options) -> Failure {
    let saved = opts.crash_dir.as_ref().and_then(|d| save(d, target, &input).ok());
    Failure { kind, index, input, message, saved }
}

/// The worker's loop over inputs `first..first + iterations`.
fn work(target: &'static Target, material: &Material, opts: &Options, shared: &Shared, t0: Instant) -> Report {
    let mut r = Report {
        target: target.name,
        inputs: 0,
        accepted: 0,
        panics: 0,
        hangs: 0,
        stalls: 0,
        elapsed: Duration::ZERO,
        slowest: Duration::ZERO,
        stuck: false,
        failures: Vec::new(),
    };
    for index in opts.first..opts.first.saturating_add(opts.iterations) {
        let input = mutate::input(opts.seed, target.name, index, material);
        shared.index.store(index, Ordering::Relaxed);
        let start = Instant::now();
        shared.started_us.store((start - t0).as_micros() as u64, Ordering::Release);
        let mut accepted = false;
        let outcome = run_quiet(|| accepted = (target.run)(&input));
        let mut took = start.elapsed();
        shared.started_us.store(IDLE, Ordering::Release);
        if outcome.is_ok() && took > opts.hang_limit {
            for _ in 0..RETIMES {
                let again = Instant::now();
                shared.started_us.store((again - t0).as_micros() as u64, Ordering::Release);
                let _ = run_quiet(|| {
                    (target.run)(&input);
                });
                took = took.min(again.elapsed());
                shared.started_us.store(IDLE, Ordering::Release);
                if took <= opts.hang_limit {
                    r.stalls += 1;
                    break;
                }
            }
        }
        r.inputs += 1;
        r.accepted += u64::from(accepted);
        r.slowest = r.slowest.max(took);
        let fail = match outcome {
            Err(message) => {
                r.panics += 1;
                Some((FailureKind::Panic, message))
            }
            Ok(()) if took > opts.hang_limit => {
                r.hangs += 1;
                Some((FailureKind::Slow, format!("took {:.3} s at best of {} runs", took.as_secs_f64(), RETIMES + 1)))
            }
            Ok(()) => None,
        };
        if let Some((kind, message)) = fail {
            if r.failures.len() < opts.keep {
                r.failures.push(failure(kind, index, input, message, target.name, opts));
            }
        }
        if opts.progress > 0 && (index + 1).is_multiple_of(opts.progress) {
            eprintln!("{}: {} inputs, {:.1} s", target.name, index + 1 - opts.first, t0.elapsed().as_secs_f64());
        }
    }
    r.elapsed = t0.elapsed();
    r
}

/// Run `target` for `opts.iterations` inputs.
pub fn run_target(target: &'static Target, opts: &Options) -> Report {
    install_hook();
    let material = Arc::new((target.material)());
    let shared = Arc::new(Shared { index: AtomicU64::new(opts.first), started_us: AtomicU64::new(IDLE) });
    let t0 = Instant::now();
    let (tx, rx) = mpsc::channel();
    let worker = {
        let (material, shared, opts) = (material.clone(), shared.clone(), opts.clone());
        std::thread::Builder::new()
            .name(format!("fuzz-{}", target.name))
            .stack_size(WORKER_STACK)
            .spawn(move || {
                let _ = tx.send(work(target, &material, &opts, &shared, t0));
            })
            .expect("the worker thread starts")
    };
    let stuck_after = opts.hang_limit.saturating_mul(3).max(Duration::from_millis(300));
    loop {
        match rx.recv_timeout(Duration::from_millis(50)) {
            Ok(report) => {
                let _ = worker.join();
                return report;
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                // The worker died without a report: only a panic outside `run_quiet`
                // (in the generator) can do that.
                let index = shared.index.load(Ordering::Relaxed);
                return stuck_report(target, opts, &material, index, t0, "the worker thread died".into());
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {
                let started = shared.started_us.load(Ordering::Acquire);
                if started == IDLE {
                    continue;
                }
                let running = t0.elapsed().saturating_sub(Duration::from_micros(started));
                if running > stuck_after {
                    let index = shared.index.load(Ordering::Relaxed);
                    let msg = format!("no return after {:.1} s", running.as_secs_f64());
                    return stuck_report(target, opts, &material, index, t0, msg);
                }
            }
        }
    }
}

/// The report of a run the watchdog gave up on at input `index` (counts of inputs run
/// before it are lost with the worker; they all passed or were saved).
fn stuck_report(
    target: &'static Target,
    opts: &Options,
    material: &Material,
    index: u64,
    t0: Instant,
    message: String,
) -> Report {
    let input = mutate::input(opts.seed, target.name, index, material);
    Report {
        target: target.name,
        inputs: index - opts.first,
        accepted: 0,
        panics: 0,
        hangs: 1,
        stalls: 0,
        elapsed: t0.elapsed(),
        slowest: Duration::ZERO,
        stuck: true,
        failures: vec![failure(FailureKind::Stuck, index, input, message, target.name, opts)],
    }
}

/// Result of replaying one kept input.
#[derive(Debug)]
pub struct Replay {
    pub path: PathBuf,
    pub target: String,
    /// `Err`: the panic message, the time it took, or why it could not run.
    pub outcome: Result<Duration, String>,
}

/// Replay every kept input under `dir` (`<dir>/<target>/<anything>`): each must return
/// within `hang_limit` without panicking. A directory that names no target is an error.
pub fn replay_regressions(dir: &Path, hang_limit: Duration) -> std::io::Result<Vec<Replay>> {
    let mut out = Vec::new();
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    dirs.sort();
    for d in dirs.into_iter().filter(|d| d.is_dir()) {
        let name = d.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let mut files: Vec<PathBuf> = std::fs::read_dir(&d)?.filter_map(|e| e.ok().map(|e| e.path())).collect();
        files.sort();
        for path in files.into_iter().filter(|f| f.is_file()) {
            let outcome = match crate::targets::by_name(&name) {
                None => Err(format!("no target named {name:?}")),
                Some(t) => {
                    let input = std::fs::read(&path)?;
                    replay_one(t, &input, hang_limit)
                }
            };
            out.push(Replay { path, target: name.clone(), outcome });
        }
    }
    Ok(out)
}

/// Run one input of `target`; `Err` if it panics or takes longer than `hang_limit`.
pub fn replay_one(target: &Target, input: &[u8], hang_limit: Duration) -> Result<Duration, String> {
    let start = Instant::now();
    run_quiet(|| {
        (target.run)(input);
    })?;
    let took = start.elapsed();
    if took > hang_limit {
        return Err(format!("took {:.3} s", took.as_secs_f64()));
    }
    Ok(took)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn panics_on_ff(b: &[u8]) -> bool {
        assert!(!b.contains(&0xff), "found 0xff");
        true
    }

    fn sleeps_on_ee(b: &[u8]) -> bool {
        if b.first() == Some(&0xee) {
            std::thread::sleep(Duration::from_millis(30));
        }
        true
    }

    fn spins_on_ee(b: &[u8]) -> bool {
        if b.first() == Some(&0xee) {
            std::thread::sleep(Duration::from_secs(3));
        }
        true
    }

    static PANICKY: Target =
        Target { name: "panicky", about: "", run: panics_on_ff, material: || Material::binary(vec![vec![1, 2, 3]]) };
    static SLOW: Target =
        Target { name: "slow", about: "", run: sleeps_on_ee, material: || Material::binary(vec![vec![0xee, 0]]) };
    /// Slow on its first run of each input only: the machine stalling, not the input.
    fn slow_once(b: &[u8]) -> bool {
        thread_local!(static SEEN: RefCell<Vec<Vec<u8>>> = const { RefCell::new(Vec::new()) });
        let first = SEEN.with(|s| {
            let mut s = s.borrow_mut();
            let first = !s.iter().any(|x| x == b);
            if first {
                s.push(b.to_vec());
            }
            first
        });
        if first && b.first() == Some(&0xee) {
            std::thread::sleep(Duration::from_millis(30));
        }
        true
    }

    static STALLING: Target =
        Target { name: "stalling", about: "", run: slow_once, material: || Material::binary(vec![vec![0xee, 0]]) };
    static STUCK: Target =
        Target { name: "stuck", about: "", run: spins_on_ee, material: || Material::binary(vec![vec![0xee, 0]]) };

    #[test]
    fn panics_are_counted_silenced_and_saved() {
        let dir = std::env::temp_dir().join(format!("geese-fuzz-test-{}", std::process::id()));
        let opts = Options { iterations: 2_000, crash_dir: Some(dir.clone()), keep: 3, ..Options::default() };
        let r = run_target(&PANICKY, &opts);
        assert_eq!(r.inputs, 2_000);
        assert!(r.panics > 10, "{r:?}");
        assert_eq!(r.failures.len(), 3);
        let f = &r.failures[0];
        assert!(f.message.contains("found 0xff"), "{}", f.message);
        assert_eq!(std::fs::read(f.saved.as_ref().unwrap()).unwrap(), f.input);
        // The saved input is the input of that index.
        let m = (PANICKY.material)();
        assert_eq!(mutate::input(opts.seed, "panicky", f.index, &m), f.input);
        let replays = replay_regressions(&dir, Duration::from_secs(1)).unwrap();
        assert_eq!(replays.len(), 3);
        assert!(replays.iter().all(|r| r.outcome.is_err()));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn slow_and_stuck_inputs_are_hangs() {
        let opts = Options { iterations: 100, hang_limit: Duration::from_millis(10), ..Options::default() };
        let r = run_target(&SLOW, &opts);
        assert!(r.hangs > 0 && r.panics == 0 && !r.stuck, "{r:?}");
        assert!(r.failures.iter().all(|f| f.kind == FailureKind::Slow && f.input[0] == 0xee));
        let r = run_target(&STALLING, &opts);
        assert!(r.hangs == 0 && r.stalls > 0 && r.ok(), "{r:?}");
        let opts = Options { iterations: 1_000, hang_limit: Duration::from_millis(100), ..Options::default() };
        let r = run_target(&STUCK, &opts);
        assert!(r.stuck && r.hangs == 1, "{r:?}");
        assert_eq!(r.failures[0].kind, FailureKind::Stuck);
        assert_eq!(r.failures[0].input[0], 0xee);
    }
}
