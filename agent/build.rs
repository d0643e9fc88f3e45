//! Links `geese-agent` for a small resident set (issue 29): a thousand agent processes
//! on one machine each map the binary's code, and plain RSS counts every page a process
//! touched plus the 16 the kernel maps around each page fault.
//!
//! - `--symbol-ordering-file=geese-agent.order`: the ~3,000 functions an agent process
//!   executes (listed by `scripts/agent-link-order.sh`) placed together at the start of
//!   the text, so the ~2.5 MiB they take are all the code a process maps, instead of
//!   ~8.5 MiB of pages they were scattered over. Symbols the binary no longer has are
//!   skipped (`--no-warn-symbol-ordering`); the test
//!   `footprint::agent_link_order_is_current_and_clusters_the_agents_code` fails when
//!   too many are gone.
//! - `-z pack-relative-relocs` (RELR, glibc ≥ 2.36): the position-independent binary's
//!   ~31,000 relative relocations take 9 KiB instead of 730 KiB that the loader reads
//!   at every start.
//!
//! The order file is linked from a copy in `OUT_DIR`: cargo reuses a build script's
//! output while the files it watches are older than its last run, also when the last
//! run was another checkout's sharing the target directory (as CI's clones do), and a
//! path into that checkout would then be gone.
//!
//! Both are options of LLD, the linker Rust uses by default on x86_64 Linux (GNU); on
//! other targets the binary is linked as cargo does by default. `GEESE_PLAIN_LINK=1`
//! turns them off, for a toolchain configured to link with another linker.
use std::env;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=geese-agent.order");
    println!("cargo:rerun-if-env-changed=GEESE_PLAIN_LINK");
    let cfg = |k: &str| env::var(k).unwrap_or_default();
    let lld_default = cfg("CARGO_CFG_TARGET_OS") == "linux"
        && cfg("CARGO_CFG_TARGET_ARCH") == "x86_64"
        && cfg("CARGO_CFG_TARGET_ENV") == "gnu";
    if !lld_default || env::var_os("GEESE_PLAIN_LINK").is_some_and(|v| v == "1") {
        return;
    }
    let source = std::path::Path::new(&cfg("CARGO_MANIFEST_DIR")).join("geese-agent.order");
    let order = std::path::Path::new(&cfg("OUT_DIR")).join("geese-agent.order");
    if let Err(e) = std::fs::copy(&source, &order) {
        panic!("cannot copy the link order {} to {}: {e}", source.display(), order.display());
    }
    println!("cargo:rustc-link-arg-bin=geese-agent=-Wl,--symbol-ordering-file={}", order.display());
    println!("cargo:rustc-link-arg-bin=geese-agent=-Wl,--no-warn-symbol-ordering");
    println!("cargo:rustc-link-arg-bin=geese-agent=-Wl,-z,pack-relative-relocs");
}
