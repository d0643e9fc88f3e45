//! `geese-fuzz`: run the fuzz targets on stable Rust.
//!
//! `cargo run --release -p geese-fuzz -- --iterations 1000000` runs every target for a
//! million inputs and prints, per target, the inputs run, panics, hangs and seconds; it
//! exits non-zero if any input panicked or hung, and saves those inputs under
//! `fuzz/crashes/<target>/`. Copy one to `fuzz/regressions/<target>/` (once the bug is
//! fixed) and the test suite replays it for good.
use anyhow::{bail, Context, Result};
use clap::Parser;
use geese_fuzz::driver::{replay_one, replay_regressions, Options, Report};
use geese_fuzz::{by_name, run_target, Target, TARGETS};
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(Parser, Debug)]
#[command(name = "geese-fuzz", about = "Fuzz GEESE's decoders and parsers on stable Rust")]
struct Args {
    /// Inputs per target.
    #[arg(long, default_value_t = 100_000)]
    iterations: u64,
    /// Only these targets (repeatable); all by default.
    #[arg(long = "target", short = 't')]
    targets: Vec<String>,
    /// Seed of the input streams (input i of a target is the same for the same seed).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Index of the first input (to replay a range of a run).
    #[arg(long, default_value_t = 0)]
    first: u64,
    /// An input that takes longer than this many milliseconds is a hang.
    #[arg(long, default_value_t = 1_000)]
    hang_ms: u64,
    /// Where failing inputs are saved, per target.
    #[arg(long, default_value_os_t = default_crash_dir())]
    crash_dir: PathBuf,
    /// Targets run at the same time.
    #[arg(long, short = 'j', default_value_t = 1)]
    jobs: usize,
    /// Print progress every this many inputs (0: never).
    #[arg(long, default_value_t = 0)]
    progress: u64,
    /// List the targets and exit.
    #[arg(long)]
    list: bool,
    /// Run these files as inputs of the one `--target` (a saved crash, say), with
    /// panics shown, instead of fuzzing.
    #[arg(long)]
    replay: Vec<PathBuf>,
    /// Replay every kept input under this directory (`<dir>/<target>/*`) and exit.
    #[arg(long)]
    regressions: Option<PathBuf>,
    /// Write every target's seed inputs (and dictionary) under this directory and exit.
    #[arg(long)]
    export_seeds: Option<PathBuf>,
}

fn default_crash_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("crashes")
}

fn selected(names: &[String]) -> Result<Vec<&'static Target>> {
    if names.is_empty() {
        return Ok(TARGETS.iter().collect());
    }
    names
        .iter()
        .map(|n| {
            by_name(n).with_context(|| {
                format!("no target {n:?} (one of: {})", TARGETS.iter().map(|t| t.name).collect::<Vec<_>>().join(", "))
            })
        })
        .collect()
}

fn main() -> Result<()> {
    let args = Args::parse();
    let hang = Duration::from_millis(args.hang_ms);
    if args.list {
        for t in TARGETS {
            println!("{:<14} {}", t.name, t.about);
        }
        return Ok(());
    }
    if let Some(dir) = &args.export_seeds {
        for e in geese_fuzz::corpus::export(dir).with_context(|| format!("writing {}", dir.display()))? {
            println!("{:<14} {:>4} seeds {:>5} tokens", e.target, e.seeds, e.tokens);
        }
        return Ok(());
    }
    if let Some(dir) = &args.regressions {
        let replays = replay_regressions(dir, hang).with_context(|| format!("reading {}", dir.display()))?;
        let bad = replays.iter().filter(|r| r.outcome.is_err()).count();
        for r in &replays {
            match &r.outcome {
                Ok(t) => println!("ok    {} ({:.1} ms)", r.path.display(), t.as_secs_f64() * 1e3),
                Err(e) => println!("FAIL  {}: {e}", r.path.display()),
            }
        }
        println!("{} kept inputs, {bad} failing", replays.len());
        if bad > 0 {
            bail!("{bad} kept input(s) fail");
        }
        return Ok(());
    }
    let targets = selected(&args.targets)?;
    if !args.replay.is_empty() {
        let [t] = targets.as_slice() else { bail!("--replay needs exactly one --target") };
        for p in &args.replay {
            let input = std::fs::read(p).with_context(|| format!("reading {}", p.display()))?;
            // Panics print here: this is for looking at one.
            let start = std::time::Instant::now();
            let accepted = (t.run)(&input);
            let took = start.elapsed();
            let what = if accepted { "accepted" } else { "rejected" };
            println!("{}: {what}, returned in {:.3} ms", p.display(), took.as_secs_f64() * 1e3);
            let _ = replay_one(t, &input, hang).map_err(|e| println!("  but: {e}"));
        }
        return Ok(());
    }
    let opts = Options {
        iterations: args.iterations,
        first: args.first,
        seed: args.seed,
        hang_limit: hang,
        crash_dir: Some(args.crash_dir.clone()),
        keep: 8,
        progress: args.progress,
    };
    println!(
        "seed {}, inputs {}..{}, hang limit {} ms",
        args.seed,
        args.first,
        args.first + args.iterations,
        args.hang_ms
    );
    println!("{}", Report::header());
    let reports = run_all(&targets, &opts, args.jobs.max(1));
    let (mut inputs, mut panics, mut hangs, mut stalls) = (0, 0, 0, 0);
    for r in &reports {
        inputs += r.inputs;
        panics += r.panics;
        hangs += r.hangs;
        stalls += r.stalls;
    }
    let n = reports.len();
    println!("total: {n} targets, {inputs} inputs, {panics} panics, {hangs} hangs ({stalls} stalls of the machine)");
    let failing: Vec<&Report> = reports.iter().filter(|r| !r.ok()).collect();
    for r in &failing {
        for f in &r.failures {
            let at = f.saved.as_ref().map_or_else(|| "not saved".into(), |p| p.display().to_string());
            println!(
                "{} input {} ({:?}): {} -> {at}",
                r.target,
                f.index,
                f.kind,
                f.message.lines().next().unwrap_or("")
            );
        }
    }
    if !failing.is_empty() {
        // A stuck worker cannot be joined: exit rather than return.
        std::process::exit(1);
    }
    Ok(())
}

/// Run the targets, `jobs` at a time; each line is printed as its target finishes.
fn run_all(targets: &[&'static Target], opts: &Options, jobs: usize) -> Vec<Report> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let reports = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..jobs.min(targets.len()) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(t) = targets.get(i) else { break };
                let r = run_target(t, opts);
                println!("{}", r.line());
                reports.lock().unwrap_or_else(|e| e.into_inner()).push((i, r));
            });
        }
    });
    let mut reports = reports.into_inner().unwrap_or_else(|e| e.into_inner());
    reports.sort_by_key(|(i, _)| *i);
    reports.into_iter().map(|(_, r)| r).collect()
}
