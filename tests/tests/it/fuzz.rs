//! The fuzz targets' short run (issue 17, item 5): every target for a few thousand
//! inputs, 0 panics and 0 hangs, and every kept crash input replayed.
//!
//! The long run is `cargo run --release -p geese-fuzz -- --iterations 1000000`; this one
//! only keeps the targets honest between long runs (a seed input that stops decoding,
//! a decoder change that panics on what used to be rejected). Inputs are fixed by the
//! seed, so a failure here is reproducible with `geese-fuzz --seed` and `--first`.
use geese_fuzz::driver::{replay_regressions, Options};
use geese_fuzz::{run_target, TARGETS};
use std::path::Path;
use std::time::Duration;

/// Inputs per target: about 3 s for all of them in release, most of it the campaign
/// target (each accepted campaign validates every condition's run).
const INPUTS: u64 = 3_000;

/// Hang limit of the short run: above the CLI's 1 s, because this test shares the
/// machine with the rest of the suite.
const HANG: Duration = Duration::from_secs(5);

#[test]
fn every_target_survives_a_short_run() {
    let opts = Options { iterations: INPUTS, seed: 0x6ee5e, hang_limit: HANG, keep: 2, ..Options::default() };
    let mut bad = Vec::new();
    for t in TARGETS {
        let r = run_target(t, &opts);
        assert_eq!(r.inputs, INPUTS, "{}", r.target);
        // Inputs that get past the outermost decoder: without them the target fuzzes
        // nothing but the first checks (the least accepted, run_config, is about 8 %).
        assert!(r.accepted * 50 > r.inputs, "{}: only {} of {} inputs accepted", r.target, r.accepted, r.inputs);
        if !r.ok() {
            for f in &r.failures {
                bad.push(format!("{} input {} ({:?}): {}", r.target, f.index, f.kind, f.message));
            }
        }
    }
    assert!(
        bad.is_empty(),
        "fuzz failures (replay with geese-fuzz --seed {} --first <input>):\n{}",
        opts.seed,
        bad.join("\n")
    );
}

#[test]
fn kept_crash_inputs_stay_fixed() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions");
    let replays = replay_regressions(&dir, HANG).expect("fuzz/regressions is readable");
    assert!(!replays.is_empty(), "no kept inputs under {}", dir.display());
    let bad: Vec<String> =
        replays.iter().filter_map(|r| r.outcome.as_ref().err().map(|e| format!("{}: {e}", r.path.display()))).collect();
    assert!(bad.is_empty(), "kept inputs fail again:\n{}", bad.join("\n"));
}

#[test]
fn kept_wire_inputs_are_of_this_wire_version_and_still_reach_their_bug() {
    // A kept input of an older wire version is rejected at its version byte and tests
    // nothing: after a version bump its first byte is updated (the messages it holds
    // did not change shape) and this test says so.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions/run_info");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).expect("fuzz/regressions/run_info") {
        let bytes = std::fs::read(entry.expect("entry").path()).expect("kept input");
        assert_eq!(bytes.first(), Some(&geese_proto::WIRE_VERSION), "kept input of another wire version");
        geese_proto::decode::<geese_proto::net::RunInfo>(&bytes).expect_err("the grid-0 geometry is rejected");
        // The same bytes with the geometry left unchecked decode: the geometry, and
        // nothing before it, is what is rejected.
        let raw: UncheckedRunInfo = geese_proto::decode(&bytes).expect("decodes with the geometry unchecked");
        assert_eq!(raw.geometry.grid, 0, "the kept input is the grid-0 geometry");
        seen += 1;
    }
    assert!(seen > 0);
}

/// [`geese_proto::net::RunInfo`]'s layout with its geometry's fields left unchecked.
#[derive(serde::Deserialize)]
#[allow(dead_code)]
struct UncheckedRunInfo {
    spec: geese_proto::net::NetRunSpec,
    geometry: UncheckedGeometry,
    hub: geese_proto::ObjectInfo,
    next_step: u64,
    cells: Vec<u32>,
}

#[derive(serde::Deserialize)]
#[allow(dead_code)]
struct UncheckedGeometry {
    width: i32,
    height: i32,
    grid: i32,
}
