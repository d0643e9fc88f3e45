//! Three "hosts" on one machine (issue 18, DESIGN.md §9): three network namespaces
//! joined by veth links. Hosts 1 and 2 each run a router, linked by QUIC with mutual TLS
//! (Zenoh's `tls/` links read and write one rustls stream concurrently,
//! eclipse-zenoh/zenoh#2557, and broke here under load); host 3 has no router: its agent
//! process logs in to host 1's router over QUIC. The world is on host 1; everything is
//! logged in and under the generated access-control list. Checks that the run equals
//! the in-process run step for step while a rogue with host 2's agent credentials tries
//! to forge everything else, that cutting host 3's link leaves the world stepping with
//! host 2's agents (and how long it takes to notice), and that host 3's process joins
//! again when the link comes back.
//!
//! Needs root (CI runs as root) and `ip`; without root it says so and checks nothing.
//! Every namespace, link and process it makes is removed when it ends, also when it
//! fails ([`Hosts`]'s `Drop`).
use super::distributed::{bin_dir, serial};
use super::security::attack;
use geese_proto::keys::AgentRange;
use geese_proto::zenoh_bus::CommonArgs;
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

const RUN: &str = "mh";
/// The run both the three-host and the in-process runs make (same config and seed).
const RUN_ARGS: [&str; 8] = ["run", "--agents", "8", "--seed", "3", "--layout", "paper", "-q"];
/// Lease of every link: a silent peer is given up after this long.
const LEASE_MS: u32 = 2000;

fn is_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("Uid:")).map(|l| l.split_whitespace().nth(1) == Some("0")))
        .unwrap_or(false)
}

fn ip(args: &[&str]) {
    let st = Command::new("ip").args(args).status().expect("run ip");
    assert!(st.success(), "ip {args:?} failed");
}

/// The namespaces, links and processes of the test; all removed on drop.
struct Hosts {
    ns: [String; 3],
    /// Root-namespace end of the link to host 2 (the rogue's way in).
    root_link: String,
    children: Vec<Child>,
}

impl Hosts {
    /// h1 — h2 (10.231.12.0/24), h1 — h3 (10.231.13.0/24), root — h2 (10.231.20.0/24).
    fn new() -> Hosts {
        let p = format!("g{}", std::process::id() % 100_000);
        let hosts = Hosts {
            ns: [format!("{p}h1"), format!("{p}h2"), format!("{p}h3")],
            root_link: format!("{p}r"),
            children: Vec::new(),
        };
        for n in &hosts.ns {
            ip(&["netns", "add", n]);
            ip(&["-n", n, "link", "set", "lo", "up"]);
        }
        let [h1, h2, h3] = &hosts.ns;
        for (a, b, na, nb, aa, ab) in [
            (format!("{p}a12"), format!("{p}b12"), h1, h2, "10.231.12.1/24", "10.231.12.2/24"),
            (format!("{p}a13"), format!("{p}b13"), h1, h3, "10.231.13.1/24", "10.231.13.3/24"),
        ] {
            ip(&["link", "add", &a, "type", "veth", "peer", "name", &b]);
            ip(&["link", "set", &a, "netns", na]);
            ip(&["link", "set", &b, "netns", nb]);
            ip(&["-n", na, "addr", "add", aa, "dev", &a]);
            ip(&["-n", nb, "addr", "add", ab, "dev", &b]);
            ip(&["-n", na, "link", "set", &a, "up"]);
            ip(&["-n", nb, "link", "set", &b, "up"]);
        }
        let s = format!("{p}s");
        ip(&["link", "add", &hosts.root_link, "type", "veth", "peer", "name", &s]);
        ip(&["link", "set", &s, "netns", h2]);
        ip(&["addr", "add", "10.231.20.1/24", "dev", &hosts.root_link]);
        ip(&["-n", h2, "addr", "add", "10.231.20.2/24", "dev", &s]);
        ip(&["link", "set", &hosts.root_link, "up"]);
        ip(&["-n", h2, "link", "set", &s, "up"]);
        hosts
    }

    fn link_13(&self) -> String {
        format!("{}b13", self.ns[2].trim_end_matches("h3"))
    }

    /// Start `cmd` on host `h` (0-based).
    fn spawn(&mut self, h: usize, cmd: &[&str], out: Stdio, err: Stdio) -> usize {
        let child = Command::new("ip")
            .args(["netns", "exec", &self.ns[h]])
            .args(cmd)
            .env("GEESE_BIN_DIR", bin_dir())
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err)
            .spawn()
            .expect("spawn in namespace");
        self.children.push(child);
        self.children.len() - 1
    }
}

impl Drop for Hosts {
    fn drop(&mut self) {
        for c in &mut self.children {
            let _ = c.kill();
            let _ = c.wait();
        }
        // Whatever our processes started in the namespaces (the world server).
        for n in &self.ns {
            if let Ok(o) = Command::new("ip").args(["netns", "pids", n]).output() {
                for pid in String::from_utf8_lossy(&o.stdout).split_whitespace() {
                    let _ = Command::new("kill").args(["-9", pid]).status();
                }
            }
        }
        std::thread::sleep(Duration::from_millis(200));
        for n in &self.ns {
            let _ = Command::new("ip").args(["netns", "del", n]).status();
        }
        let _ = Command::new("ip").args(["link", "del", &self.root_link]).stderr(Stdio::null()).status();
    }
}

/// Lines of a child's stream, each with when it arrived.
fn lines(stream: impl std::io::Read + Send + 'static) -> Receiver<(Instant, String)> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for l in std::io::BufReader::new(stream).lines().map_while(Result::ok) {
            if tx.send((Instant::now(), l)).is_err() {
                break;
            }
        }
    });
    rx
}

/// Wait for a line containing `what`; its arrival time and text.
fn wait_line(rx: &Receiver<(Instant, String)>, what: &str, within: Duration) -> (Instant, String) {
    let until = Instant::now() + within;
    loop {
        match rx.recv_timeout(until.saturating_duration_since(Instant::now())) {
            Ok((t, l)) if l.contains(what) => return (t, l),
            Ok((_, l)) => eprintln!("  | {l}"),
            Err(RecvTimeoutError::Timeout) => panic!("no line with {what:?} within {within:?}"),
            Err(RecvTimeoutError::Disconnected) => panic!("stream ended before a line with {what:?}"),
        }
    }
}

/// The Zenoh flags of router `name` (its certificate and key in `tls`).
fn router_args(name: &str, secrets: &Path, tls: &Path) -> Vec<String> {
    let f = |p: PathBuf| format!("\"{}\"", p.display());
    let mut v: Vec<String> = vec![
        "--users".into(),
        secrets.join("users.txt").display().to_string(),
        "--acl".into(),
        secrets.join("acl.json5").display().to_string(),
        "--credentials".into(),
        secrets.join(format!("router-{name}.cred")).display().to_string(),
    ];
    for (k, val) in [
        ("root_ca_certificate", f(tls.join("ca.pem"))),
        ("listen_private_key", f(tls.join(format!("{name}.key")))),
        ("listen_certificate", f(tls.join(format!("{name}.pem")))),
        ("enable_mtls", "true".into()),
        ("connect_private_key", f(tls.join(format!("{name}.key")))),
        ("connect_certificate", f(tls.join(format!("{name}.pem")))),
        ("verify_name_on_connect", "true".into()),
    ] {
        v.push("--cfg".into());
        v.push(format!("transport/link/tls/{k}:{val}"));
    }
    v.push("--cfg".into());
    v.push(format!("transport/link/tx/lease:{LEASE_MS}"));
    v
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

/// `(step, live_agents)` of every row of a steps.csv.
fn live_per_step(csv: &str) -> Vec<(u64, u32)> {
    let mut rows = csv.lines();
    let header: Vec<&str> = rows.next().expect("header").split(',').collect();
    let live = header.iter().position(|h| *h == "live_agents").expect("live_agents column");
    rows.filter_map(|l| {
        let f: Vec<&str> = l.split(',').collect();
        Some((f.first()?.parse().ok()?, f.get(live)?.parse().ok()?))
    })
    .collect()
}

#[test]
fn three_hosts_in_network_namespaces_quic_mtls_acl_attack_link_cut_and_rejoin() {
    if !is_root() {
        eprintln!("three_hosts_in_network_namespaces: needs root (ip netns); nothing checked");
        return;
    }
    let _one_at_a_time = serial();
    let geese = geese_tests::bin_path("geese-orchestrator", "geese");
    let agent = bin_dir().join("geese-agent");
    let dir = tempfile::tempdir().expect("tempdir");
    let secrets = dir.path().join("secrets");
    let tls = dir.path().join("tls");
    let st = Command::new(&geese)
        .args(["secure", "init", "--run", RUN, "--agents", "8", "--per-process", "4", "--routers", "h1,h2", "--out"])
        .arg(&secrets)
        .stdout(Stdio::null())
        .status()
        .expect("geese secure init");
    assert!(st.success());
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/tls/make-test-ca.sh");
    let st = Command::new("bash")
        .arg(&script)
        .arg(&tls)
        .args(["h1=10.231.12.1,10.231.13.1", "h2=10.231.12.2,10.231.20.2"])
        .stdout(Stdio::null())
        .status()
        .expect("make-test-ca.sh");
    assert!(st.success());

    let mut hosts = Hosts::new();
    let g = geese.display().to_string();
    let lease = format!("transport/link/tx/lease:{LEASE_MS}");
    // Routers on hosts 1 and 2, linked by QUIC with mutual TLS; each takes its host's
    // processes on its own loopback (host 2's also on the link the rogue comes in by).
    // Host 1's router also takes router-less clients from host 3 over QUIC (server
    // certificate checked by the client, no client certificate: a client presenting a
    // router's certificate would get that router's rights).
    let mut r1 = vec![g.clone(), "router".into(), "-l".into(), "tcp/127.0.0.1:7447".into()];
    r1.extend(["-l", "quic/10.231.12.1:7448", "-l", "quic/10.231.13.1:7449#enable_mtls=false"].map(String::from));
    r1.extend(router_args("h1", &secrets, &tls));
    let mut r2 = vec![g.clone(), "router".into(), "-l".into(), "tcp/127.0.0.1:7447".into()];
    r2.extend(["-l", "tcp/10.231.20.2:7447", "-e", "quic/10.231.12.1:7448"].map(String::from));
    r2.extend(router_args("h2", &secrets, &tls));
    for (h, r) in [(0, &r1), (1, &r2)] {
        let i = hosts.spawn(h, &strs(r), Stdio::piped(), Stdio::inherit());
        let out = hosts.children[i].stdout.take().expect("router stdout");
        wait_line(&lines(out), "listening", Duration::from_secs(30));
    }
    let cred = |user: &str| secrets.join(format!("{user}.cred")).display().to_string();
    let ca = format!("transport/link/tls/root_ca_certificate:\"{}\"", tls.join("ca.pem").display());
    // Agent processes 0-3 on host 2 (through its router), 4-7 on host 3 (straight to
    // host 1's router over QUIC, logged in like any other client).
    let agents = |hosts: &mut Hosts, rejoin: &str| -> [usize; 2] {
        [(1, 0, "tcp/127.0.0.1:7447"), (2, 4, "quic/10.231.13.1:7449")].map(|(h, id, router)| {
            let range = format!("{}-{}", id, id + 3);
            let cmd = [
                agent.display().to_string(),
                "--router".into(),
                router.into(),
                "--run".into(),
                RUN.into(),
                "--id".into(),
                id.to_string(),
                "--agents".into(),
                "4".into(),
                "--credentials".into(),
                cred(&format!("agents-{range}")),
                "--cfg".into(),
                lease.clone(),
                "--cfg".into(),
                ca.clone(),
                "--rejoin-ms".into(),
                rejoin.into(),
                "--subscribe".into(),
                "all".into(),
            ];
            hosts.spawn(h, &strs(&cmd), Stdio::null(), Stdio::inherit())
        })
    };
    let world_cmd = |steps: &str, out: &Path| -> Vec<String> {
        let mut v: Vec<String> = [g.as_str()].into_iter().chain(RUN_ARGS).map(String::from).collect();
        v.extend(
            [
                "--processes",
                "0",
                "--run-name",
                RUN,
                "--router",
                "tcp/127.0.0.1:7447",
                "--join-timeout-ms",
                "60000",
                "--steps",
                steps,
            ]
            .map(String::from),
        );
        v.extend(["--secrets".into(), secrets.display().to_string(), "--cfg".into(), lease.clone()]);
        v.extend(["--out".into(), out.display().to_string()]);
        v
    };

    // 1. Parity under attack: the run across hosts equals the in-process run while a
    // rogue on host 2's router, logged in with host 2's agent credentials, forges
    // messages of the other agent process, the world and the operator, and tries to log
    // in without credentials and with a wrong password.
    let steps = 20_000;
    let inproc = dir.path().join("inproc");
    let st = Command::new(&geese)
        .args(RUN_ARGS)
        .args(["--steps", &steps.to_string(), "--out"])
        .arg(&inproc)
        .stdout(Stdio::null())
        .status()
        .expect("in-process run");
    assert!(st.success());
    let out_a = dir.path().join("a");
    let w = hosts.spawn(0, &strs(&world_cmd(&steps.to_string(), &out_a)), Stdio::piped(), Stdio::piped());
    let world_err = lines(hosts.children[w].stderr.take().expect("stderr"));
    let world_out = lines(hosts.children[w].stdout.take().expect("stdout"));
    let _a = agents(&mut hosts, "0");
    wait_line(&world_err, "starting", Duration::from_secs(90));
    let client = |user: &str| CommonArgs {
        connect: vec!["tcp/10.231.20.2:7447".into()],
        credentials: Some(PathBuf::from(cred(user))),
        cfg: vec![lease.clone()],
        ..Default::default()
    };
    let own = AgentRange::new(0, 4).expect("range");
    let other = AgentRange::new(4, 4).expect("range");
    let rogue = attack(RUN, &client("agents-0-3"), &client("viewer"), own, other, 20);
    eprintln!("three hosts, rogue on host 2's router: {rogue:?}");
    let during = hosts.children[w].try_wait().expect("status").is_none();
    let (_, wall) = wait_line(&world_out, "wall time", Duration::from_secs(120));
    eprintln!("three hosts, parity run under attack: {wall}");
    let status = hosts.children[w].wait().expect("world host exit");
    while let Ok((_, l)) = world_err.recv_timeout(Duration::from_millis(200)) {
        eprintln!("  | {l}");
    }
    assert!(status.success(), "the run across hosts failed");
    assert!(during, "the run ended before the attack did: make it longer");
    assert!(rogue.forged >= 200, "{rogue:?}");
    assert_eq!(rogue.forged_seen, 0, "forged messages got through: {rogue:?}");
    assert!(rogue.tokens_seen.is_empty(), "forged tokens got through: {rogue:?}");
    assert_eq!((rogue.own, rogue.own_seen), (20, 20), "the control did not get through: {rogue:?}");
    assert!(!rogue.anonymous_opened && !rogue.wrong_password_opened, "{rogue:?}");
    let a = std::fs::read_to_string(inproc.join("steps.csv")).expect("in-process csv");
    let b = std::fs::read_to_string(out_a.join("steps.csv")).expect("three-host csv");
    let diff = a.lines().zip(b.lines()).position(|(x, y)| x != y);
    // The network counters of the step that differs tell a deadline (genes_late,
    // deadline_hits) from genes never waited for or lost on the way (genes_lost).
    let net = std::fs::read_to_string(out_a.join("net.csv")).unwrap_or_default();
    assert!(
        diff.is_none() && a.lines().count() == b.lines().count(),
        "the three-host run differs from the in-process run from line {diff:?}: {:?}; net.csv there: {:?}",
        diff.map(|i| (a.lines().nth(i), b.lines().nth(i))),
        diff.map(|i| (net.lines().next(), net.lines().nth(i)))
    );

    // 2. Cut host 3's link from its own end (host 1 hears nothing: only the lease tells
    // it), then restore it.
    let out_b = dir.path().join("b");
    let w = hosts.spawn(0, &strs(&world_cmd("1000000", &out_b)), Stdio::null(), Stdio::piped());
    let world_err = lines(hosts.children[w].stderr.take().expect("stderr"));
    let [_, h3_agents] = agents(&mut hosts, "60000");
    let h3_pid = hosts.children[h3_agents].id();
    wait_line(&world_err, "starting", Duration::from_secs(90));
    std::thread::sleep(Duration::from_secs(2));
    let cut = Instant::now();
    ip(&["-n", &hosts.ns[2].clone(), "link", "set", &hosts.link_13(), "down"]);
    let (t_left, left) = wait_line(&world_err, "agent process 4-7 left", Duration::from_secs(30));
    let noticed = t_left.duration_since(cut);
    std::thread::sleep(Duration::from_secs(2));
    let restored = Instant::now();
    ip(&["-n", &hosts.ns[2].clone(), "link", "set", &hosts.link_13(), "up"]);
    let (t_joined, joined) = wait_line(&world_err, "agent process 4-7 joined", Duration::from_secs(60));
    let rejoin = t_joined.duration_since(restored);
    eprintln!(
        "three hosts: cut → world dropped host 3 in {noticed:?} ({left}); restored → rejoined in {rejoin:?} ({joined})"
    );
    std::thread::sleep(Duration::from_secs(1));
    assert!(
        hosts.children[h3_agents].try_wait().expect("status").is_none(),
        "host 3's agent process (pid {h3_pid}) exited instead of joining again"
    );
    let stop =
        [g.as_str(), "control", "--run", RUN, "-e", "tcp/127.0.0.1:7447", "--credentials", &cred("operator"), "stop"]
            .map(String::from);
    let c = hosts.spawn(0, &strs(&stop), Stdio::null(), Stdio::inherit());
    assert!(hosts.children[c].wait().expect("control").success(), "geese control stop failed");
    let until = Instant::now() + Duration::from_secs(30);
    while hosts.children[w].try_wait().expect("status").is_none() && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(hosts.children[w].try_wait().expect("status").is_some(), "the world host did not stop");
    let rows = live_per_step(&std::fs::read_to_string(out_b.join("steps.csv")).expect("csv"));
    let first_four = rows.iter().position(|&(_, l)| l == 4).expect("a step with host 3's agents gone");
    let back = rows[first_four..].iter().position(|&(_, l)| l == 8).expect("a step with host 3's agents back");
    assert!(rows[..first_four].iter().all(|&(_, l)| l == 8), "agents missing before the cut");
    assert!(back > 5, "too few steps with host 2 alone ({back})");
    assert!(rows.len() > first_four + back + 5, "too few steps after the rejoin");
    eprintln!(
        "three hosts: {} steps; host 2 alone from step {} for {back} steps; all 8 again from step {}",
        rows.len(),
        rows[first_four].0,
        rows[first_four + back].0
    );
    assert!(noticed < Duration::from_millis(3 * LEASE_MS as u64), "the cut was noticed after {noticed:?}");
}
