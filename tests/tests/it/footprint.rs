//! The agent binary's link order (issue 29, `agent/build.rs`): the functions an agent
//! process executes sit together, so a process maps ~2.5 MiB of code rather than
//! ~8.5 MiB. Symbol names carry hashes that change with dependency versions and large
//! code changes; this fails once the list has gone stale, before anyone notices the
//! memory of a thousand-process run growing again (regenerate it with
//! `scripts/agent-link-order.sh`).
use std::collections::HashMap;
use std::process::Command;

/// (address, size) of every function `nm` lists in `bin`, by mangled name.
fn functions(bin: &std::path::Path) -> HashMap<String, (u64, u64)> {
    let out = Command::new("nm").args(["-S", "--defined-only"]).arg(bin).output().expect("run nm (binutils)");
    assert!(out.status.success(), "nm {} failed", bin.display());
    let mut map = HashMap::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        if let [addr, size, kind, name] = f[..] {
            if matches!(kind, "t" | "T" | "w" | "W") {
                let hex = |s: &str| u64::from_str_radix(s, 16).expect("nm prints hex");
                map.insert(name.to_string(), (hex(addr), hex(size)));
            }
        }
    }
    map
}

#[test]
fn agent_link_order_is_current_and_clusters_the_agents_code() {
    let lld_target = cfg!(all(target_os = "linux", target_arch = "x86_64", target_env = "gnu"));
    if !lld_target || std::env::var_os("GEESE_PLAIN_LINK").is_some_and(|v| v == "1") {
        eprintln!("skipped: geese-agent is linked without an order on this target");
        return;
    }
    let order_file = geese_tests::repo_root().join("agent/geese-agent.order");
    let order = std::fs::read_to_string(&order_file).expect("read agent/geese-agent.order");
    let names: Vec<&str> = order.lines().filter(|l| !l.is_empty()).collect();
    assert!(names.len() > 1000, "{} lists only {} functions", order_file.display(), names.len());
    let bin = geese_tests::bin_path("geese-agent", "geese-agent");
    let syms = functions(&bin);
    let found: Vec<(u64, u64)> = names.iter().filter_map(|n| syms.get(*n).copied()).collect();
    let share = found.len() as f64 / names.len() as f64;
    assert!(
        share >= 0.9,
        "only {} of the {} functions in agent/geese-agent.order are in geese-agent ({:.0} %): the list is stale, \
         run scripts/agent-link-order.sh",
        found.len(),
        names.len(),
        100.0 * share
    );
    // Placed together: the span from the first to the end of the last listed function
    // is little more than their sizes (alignment padding only).
    let lo = found.iter().map(|&(a, _)| a).min().expect("some found");
    let hi = found.iter().map(|&(a, s)| a + s).max().expect("some found");
    let total: u64 = found.iter().map(|&(_, s)| s).sum();
    assert!(
        ((hi - lo) as f64) < 1.3 * total as f64,
        "the listed functions ({} KiB) are spread over {} KiB of geese-agent's text: the link order was not applied",
        total / 1024,
        (hi - lo) / 1024
    );
}
