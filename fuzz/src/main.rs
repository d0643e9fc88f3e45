//! `geese-fuzz`: the seed corpus and the replays of the fuzz targets.
//!
//! The fuzzing itself is done by AFL++ through the harness in `fuzz/afl` (fuzz/README.md):
//! `geese-fuzz seeds DIR` writes the seed inputs and dictionaries it starts from,
//! `geese-fuzz replay TARGET PATH...` runs what it found (a crash, a queue) through a
//! target with panics and timings printed, and `geese-fuzz regressions` replays every
//! kept crash input, as the test suite does.
use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use geese_fuzz::replay::{replay_paths, replay_regressions, Replay};
use geese_fuzz::{by_name, Target, TARGETS};
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(Parser, Debug)]
#[command(name = "geese-fuzz", about = "Seed corpus and replays of GEESE's fuzz targets (the engine: fuzz/afl)")]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// List the targets.
    List,
    /// Write every target's seed inputs (`DIR/<target>/seed-NNN.bin`) and dictionary
    /// (`DIR/<target>.dict`, AFL's format).
    Seeds { dir: PathBuf },
    /// Run files, or every file of directories (an AFL queue, its crashes), through one target.
    Replay {
        target: String,
        #[arg(required = true)]
        paths: Vec<PathBuf>,
        /// An input that takes longer than this many milliseconds fails.
        #[arg(long, default_value_t = 1_000)]
        hang_ms: u64,
    },
    /// Replay every kept crash input (`DIR/<target>/*`).
    Regressions {
        #[arg(default_value_os_t = Path::new(env!("CARGO_MANIFEST_DIR")).join("regressions"))]
        dir: PathBuf,
        #[arg(long, default_value_t = 1_000)]
        hang_ms: u64,
    },
}

fn target(name: &str) -> Result<&'static Target> {
    by_name(name).with_context(|| {
        format!("no target {name:?} (one of: {})", TARGETS.iter().map(|t| t.name).collect::<Vec<_>>().join(", "))
    })
}

/// Print each replay and fail if any failed.
fn report(replays: &[Replay]) -> Result<()> {
    let mut bad = 0;
    for r in replays {
        match &r.outcome {
            Ok(ran) => {
                let what = if ran.accepted { "accepted" } else { "rejected" };
                println!("ok    {} {} ({what}, {:.2} ms)", r.target, r.path.display(), ran.took.as_secs_f64() * 1e3);
            }
            Err(e) => {
                bad += 1;
                println!("FAIL  {} {}: {e}", r.target, r.path.display());
            }
        }
    }
    println!("{} inputs, {bad} failing", replays.len());
    if bad > 0 {
        bail!("{bad} input(s) fail");
    }
    Ok(())
}

fn main() -> Result<()> {
    match Args::parse().command {
        Command::List => {
            for t in TARGETS {
                println!("{:<14} {}", t.name, t.about);
            }
            Ok(())
        }
        Command::Seeds { dir } => {
            for e in geese_fuzz::corpus::export(&dir).with_context(|| format!("writing {}", dir.display()))? {
                println!("{:<14} {:>4} seeds {:>5} tokens", e.target, e.seeds, e.tokens);
            }
            Ok(())
        }
        Command::Replay { target: name, paths, hang_ms } => {
            let t = target(&name)?;
            let replays = replay_paths(t, &paths, Duration::from_millis(hang_ms)).context("reading the inputs")?;
            report(&replays)
        }
        Command::Regressions { dir, hang_ms } => {
            let replays = replay_regressions(&dir, Duration::from_millis(hang_ms))
                .with_context(|| format!("reading {}", dir.display()))?;
            report(&replays)
        }
    }
}
