//! Shared helpers for the integration tests.
use std::path::PathBuf;
use std::process::Command;

/// The workspace root: the parent of the test's manifest dir. Taken from the
/// environment cargo gives the running test, not baked in at compile time: a build
/// cache shared between checkouts (CI reuses one target dir) may hold this crate
/// compiled in another checkout, whose path can be gone or hold other sources.
pub fn repo_root() -> PathBuf {
    std::env::var_os("CARGO_MANIFEST_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")))
        .join("..")
}

/// Path of a workspace binary built in the same profile as this test, building it first
/// if needed (`cargo test` only builds a package's binaries for that package's own
/// integration tests).
pub fn bin_path(package: &str, bin: &str) -> PathBuf {
    // The test executable lives in <target>/<profile>/deps/.
    let exe = std::env::current_exe().expect("test executable path");
    let profile_dir = exe.parent().and_then(|d| d.parent()).expect("target profile dir").to_path_buf();
    let path = profile_dir.join(bin);
    let release = profile_dir.file_name().is_some_and(|n| n == "release");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.args(["build", "-q", "-p", package, "--bin", bin]);
    if release {
        cmd.arg("--release");
    }
    cmd.current_dir(repo_root());
    // Not the variables cargo sets for running this test: some build scripts (ring's)
    // track e.g. CARGO_MANIFEST_DIR, and a value different from the outer build's makes
    // them, and everything above them, rebuild every time.
    for (k, _) in std::env::vars_os() {
        let k = k.to_string_lossy();
        let test_only = ["CARGO_PKG_", "CARGO_MANIFEST_", "CARGO_CRATE_", "CARGO_BIN_"]
            .iter()
            .any(|p| k.starts_with(p))
            || ["CARGO_PRIMARY_PACKAGE", "CARGO_TARGET_TMPDIR", "CARGO_RUSTC_CURRENT_DIR", "OUT_DIR"].contains(&&*k);
        if test_only {
            cmd.env_remove(&*k);
        }
    }
    let status = cmd.status().expect("run cargo build");
    assert!(status.success(), "building {bin} failed");
    path
}
