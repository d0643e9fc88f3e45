//! Running inputs through a target with panics caught: the seed corpus, kept crash
//! inputs, an engine's queue or crashes.
//!
//! Panics are caught with `catch_unwind`. The panic hook stays installed for every other
//! thread (tests running beside still print their panics) and only records the message
//! of a panic inside [`run_quiet`] instead of printing it. What is not caught: a stack
//! overflow or an allocation failure aborts the process (Rust does not unwind them); the
//! engine reports those as crashes.
use crate::targets::{by_name, Target};
use std::cell::{Cell, RefCell};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::Once;
use std::time::{Duration, Instant};

thread_local! {
    /// Set while [`run_quiet`] runs: panics are recorded, not printed.
    static QUIET: Cell<bool> = const { Cell::new(false) };
    static LAST_PANIC: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Install (once) the hook that silences panics under [`run_quiet`] and keeps their message.
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

/// How an input that passed ran.
#[derive(Clone, Copy, Debug)]
pub struct Ran {
    pub took: Duration,
    /// The outermost decoder or parser accepted it.
    pub accepted: bool,
}

/// Run one input of `target`; `Err` if it panics or takes longer than `hang_limit`.
pub fn replay_one(target: &Target, input: &[u8], hang_limit: Duration) -> Result<Ran, String> {
    let start = Instant::now();
    let mut accepted = false;
    run_quiet(|| accepted = (target.run)(input))?;
    let took = start.elapsed();
    if took > hang_limit {
        return Err(format!("took {:.3} s (limit {:.3} s)", took.as_secs_f64(), hang_limit.as_secs_f64()));
    }
    Ok(Ran { took, accepted })
}

/// Result of replaying one input file.
#[derive(Debug)]
pub struct Replay {
    pub path: PathBuf,
    pub target: String,
    /// `Err`: the panic message, the time it took, or why it could not run.
    pub outcome: Result<Ran, String>,
}

/// The files of a directory (not recursive), in name order.
fn files_of(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|f| f.is_file()).collect();
    files.sort();
    Ok(files)
}

/// Replay files through `target`: each path a file, or a directory whose files (not
/// recursively: an AFL queue's `.state` is skipped) are inputs.
pub fn replay_paths(target: &Target, paths: &[PathBuf], hang_limit: Duration) -> std::io::Result<Vec<Replay>> {
    let mut out = Vec::new();
    for p in paths {
        let files = if p.is_dir() { files_of(p)? } else { vec![p.clone()] };
        for path in files {
            let outcome = match std::fs::read(&path) {
                Ok(input) => replay_one(target, &input, hang_limit),
                Err(e) => Err(format!("cannot read: {e}")),
            };
            out.push(Replay { path, target: target.name.into(), outcome });
        }
    }
    Ok(out)
}

/// Replay every kept input under `dir` (`<dir>/<target>/<anything>`): each must return
/// within `hang_limit` without panicking. A directory that names no target is an error.
pub fn replay_regressions(dir: &Path, hang_limit: Duration) -> std::io::Result<Vec<Replay>> {
    let mut out = Vec::new();
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    dirs.sort();
    for d in dirs.into_iter().filter(|d| d.is_dir()) {
        let name = d.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        match by_name(&name) {
            Some(t) => out.extend(replay_paths(t, &[d], hang_limit)?),
            None => out.extend(files_of(&d)?.into_iter().map(|path| Replay {
                path,
                target: name.clone(),
                outcome: Err(format!("no target named {name:?}")),
            })),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::corpus::Seeds;

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

    static PANICKY: Target =
        Target { name: "panicky", about: "", run: panics_on_ff, seeds: || Seeds::binary(vec![vec![1]]) };
    static SLOW: Target = Target { name: "slow", about: "", run: sleeps_on_ee, seeds: || Seeds::binary(vec![vec![1]]) };

    #[test]
    fn panics_and_slow_inputs_fail_with_their_reason() {
        let limit = Duration::from_millis(10);
        assert!(replay_one(&PANICKY, &[1, 2], limit).is_ok());
        let e = replay_one(&PANICKY, &[1, 0xff], limit).expect_err("panics");
        assert!(e.contains("found 0xff"), "{e}");
        assert!(replay_one(&SLOW, &[1], limit).is_ok());
        let e = replay_one(&SLOW, &[0xee], limit).expect_err("slow");
        assert!(e.starts_with("took"), "{e}");
    }

    #[test]
    fn kept_inputs_are_replayed_by_the_target_their_directory_names() {
        let dir = std::env::temp_dir().join(format!("geese-fuzz-replay-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        for (sub, file, bytes) in [("bnf", "a.bin", &b"<a> ::= b"[..]), ("bnf", "b.bin", b""), ("nope", "c.bin", b"x")]
        {
            std::fs::create_dir_all(dir.join(sub)).expect("temp dir");
            std::fs::write(dir.join(sub).join(file), bytes).expect("temp file");
        }
        let r = replay_regressions(&dir, Duration::from_secs(5)).expect("readable");
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(r.len(), 3);
        assert!(r[0].outcome.is_ok() && r[1].outcome.is_ok(), "{r:?}");
        assert_eq!(r[2].target, "nope");
        assert!(r[2].outcome.as_ref().is_err_and(|e| e.contains("no target")), "{r:?}");
    }
}
