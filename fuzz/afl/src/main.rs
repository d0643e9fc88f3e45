//! `geese-fuzz-afl TARGET`: one geese-fuzz target under AFL++ (persistent mode).
//!
//! `cargo afl fuzz -i SEEDS/TARGET -o OUT -- geese-fuzz-afl TARGET` fuzzes it;
//! `geese-fuzz-afl TARGET --replay PATH...` runs files, or every file of directories
//! (a queue, crashes), through the target in one process, with panics reported: for a
//! crash found, and for `afl-showmap` to count the edges a whole queue covers.
use std::path::{Path, PathBuf};
use std::process::ExitCode;

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
        // Measurement only (removed with the old generator): the old driver's inputs,
        // generated and run in this instrumented binary for N seconds, or only generated.
        Some(mode @ ("--old" | "--old-generate-only")) => {
            let secs: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(240);
            let material = (target.material)();
            let t0 = std::time::Instant::now();
            let mut n = 0u64;
            while t0.elapsed().as_secs() < secs {
                for _ in 0..64 {
                    let input = geese_fuzz::mutate::input(0, target.name, n, &material);
                    if mode == "--old" {
                        let _ = geese_fuzz::driver::run_quiet(|| {
                            (target.run)(&input);
                        });
                    }
                    n += 1;
                }
            }
            let s = t0.elapsed().as_secs_f64();
            eprintln!("old {}: {n} inputs in {s:.1} s, {:.0}/s", target.name, n as f64 / s);
            ExitCode::SUCCESS
        }
        Some(other) => {
            eprintln!("unknown argument {other:?} (expected --replay PATH...)");
            ExitCode::from(2)
        }
    }
}

/// Every file named, or under a directory named (not recursively), in path order.
fn inputs(paths: &[String]) -> std::io::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for p in paths.iter().map(Path::new) {
        if p.is_dir() {
            let mut files: Vec<PathBuf> =
                std::fs::read_dir(p)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|f| f.is_file()).collect();
            files.sort();
            out.extend(files);
        } else {
            out.push(p.to_path_buf());
        }
    }
    Ok(out)
}

fn replay(target: &geese_fuzz::Target, paths: &[String]) -> ExitCode {
    let files = match inputs(paths) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("cannot list the inputs: {e}");
            return ExitCode::from(2);
        }
    };
    let mut failed = 0;
    for f in &files {
        let input = match std::fs::read(f) {
            Ok(b) => b,
            Err(e) => {
                eprintln!("{}: cannot read: {e}", f.display());
                failed += 1;
                continue;
            }
        };
        if let Err(message) = geese_fuzz::driver::run_quiet(|| {
            (target.run)(&input);
        }) {
            println!("PANIC {}: {message}", f.display());
            failed += 1;
        }
    }
    println!("{} inputs, {failed} failing", files.len());
    if failed > 0 {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}
