//! The fuzz targets' short, deterministic pass (issue 31, item 3): every target's seed
//! inputs, a property over inputs near them and over random bytes, and every kept
//! crash input, replayed through the target with panics caught.
//!
//! The fuzzing is AFL++'s, outside the suite (fuzz/README.md); this pass keeps the
//! targets honest between engine runs: a seed that stops decoding, a decoder change that
//! panics on what it used to reject, a fixed crash coming back. The property's inputs
//! come from a fixed-seed `proptest` runner, so a failure is the same on every run and
//! shrinks to a small input.
use geese_fuzz::replay::{replay_one, replay_regressions};
use geese_fuzz::{Target, TARGETS};
use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{Config, RngAlgorithm, TestCaseError, TestRng, TestRunner};
use std::path::Path;
use std::time::Duration;

/// Hang limit: far above any target's slowest input (a campaign file validating every
/// condition's run takes a few ms), because this test shares the machine with the rest
/// of the suite.
const HANG: Duration = Duration::from_secs(5);

/// Property cases per target: about 1 s for all targets in release.
const CASES: u32 = 400;

#[test]
fn every_target_runs_its_seeds_and_accepts_some() {
    let mut bad = Vec::new();
    for t in TARGETS {
        let seeds = (t.seeds)();
        assert!(!seeds.inputs.is_empty(), "{} has no seeds", t.name);
        let mut accepted = 0;
        for (i, s) in seeds.inputs.iter().enumerate() {
            match replay_one(t, s, HANG) {
                Ok(ran) => accepted += usize::from(ran.accepted),
                Err(e) => bad.push(format!("{} seed {i}: {e}", t.name)),
            }
        }
        // A target none of whose seeds decode fuzzes nothing but the first checks.
        assert!(accepted > 0, "{}: none of its {} seeds is accepted", t.name, seeds.inputs.len());
    }
    assert!(bad.is_empty(), "seed inputs fail:\n{}", bad.join("\n"));
}

/// Inputs of `t`: a seed with up to four bytes overwritten and maybe cut short (they get
/// past the version byte and the first lengths), or random bytes.
fn near_seeds(t: &Target) -> impl Strategy<Value = Vec<u8>> {
    let seeds = (t.seeds)().inputs;
    let n = seeds.len();
    let edited = (0..n, proptest::collection::vec((any::<Index>(), any::<u8>()), 0..4), any::<Option<Index>>())
        .prop_map(move |(i, edits, cut)| {
            let mut s = seeds[i].clone();
            if !s.is_empty() {
                for (at, b) in edits {
                    let at = at.index(s.len());
                    s[at] = b;
                }
                if let Some(cut) = cut {
                    s.truncate(cut.index(s.len()));
                }
            }
            s
        });
    prop_oneof![4 => edited, 1 => proptest::collection::vec(any::<u8>(), 0..256)]
}

#[test]
fn no_target_panics_or_hangs_near_its_seeds() {
    let mut bad = Vec::new();
    for t in TARGETS {
        let config = Config { cases: CASES, failure_persistence: None, ..Config::default() };
        let mut runner = TestRunner::new_with_rng(config, TestRng::deterministic_rng(RngAlgorithm::ChaCha));
        let outcome =
            runner.run(&near_seeds(t), |input| replay_one(t, &input, HANG).map(drop).map_err(TestCaseError::fail));
        if let Err(e) = outcome {
            bad.push(format!("{}: {e}", t.name));
        }
    }
    assert!(bad.is_empty(), "fuzz targets fail (fixed-seed proptest, same inputs every run):\n{}", bad.join("\n"));
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
