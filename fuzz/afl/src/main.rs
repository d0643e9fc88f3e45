//! `geese-fuzz-afl TARGET`: one geese-fuzz target under AFL++ (persistent mode).
//!
//! `cargo afl fuzz -i SEEDS/TARGET -o OUT -- geese-fuzz-afl TARGET` fuzzes it;
//! `geese-fuzz-afl TARGET --replay PATH...` runs files, or every file of directories
//! (a queue, crashes), through the target in one process, with panics reported: for a
//! crash found, and for `afl-showmap` to count the edges a whole queue covers.
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(name) = args.first() else {
        eprintln!("usage: geese-fuzz-afl TARGET [--replay PATH...]");
        return ExitCode::from(2);
    };
    let Some(target) = geese_fuzz::by_name(name) else {
        let names: Vec<&str> = geese_fuzz::TARGETS.iter().map(|t| t.name).collect();
        eprintln!("no target {name:?} (one of: {})", names.join(", "));
        return ExitCode::from(2);
    };
    match args.get(1).map(String::as_str) {
        None => {
            afl::fuzz(true, |data: &[u8]| {
                (target.run)(data);
            });
            ExitCode::SUCCESS
        }
        Some("--replay") => replay(target, &args[2..]),
        Some(other) => {
            eprintln!("unknown argument {other:?} (expected --replay PATH...)");
            ExitCode::from(2)
        }
    }
}

fn replay(target: &'static geese_fuzz::Target, paths: &[String]) -> ExitCode {
    let paths: Vec<PathBuf> = paths.iter().map(PathBuf::from).collect();
    // No time limit here: afl-fuzz and afl-showmap keep their own.
    match geese_fuzz::replay::replay_paths(target, &paths, Duration::MAX) {
        Ok(replays) => {
            let failing: Vec<_> = replays.iter().filter_map(|r| r.outcome.as_ref().err().map(|e| (r, e))).collect();
            for (r, e) in &failing {
                println!("FAIL {}: {e}", r.path.display());
            }
            println!("{} inputs, {} failing", replays.len(), failing.len());
            if failing.is_empty() {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            }
        }
        Err(e) => {
            eprintln!("cannot read the inputs: {e}");
            ExitCode::from(2)
        }
    }
}
