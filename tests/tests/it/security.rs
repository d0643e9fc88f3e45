//! Logins and access control of distributed runs (issue 18, DESIGN.md §7) on loopback:
//! a process with valid credentials for one agent process tries to speak for another
//! agent process, for the world and for the operator, and nothing it forges reaches
//! anyone; processes without credentials, or with a wrong password, cannot connect.
//!
//! What the router dropped is counted from the outside: a reader logged in as a viewer
//! subscribes to every key of the run, so every message the router lets in reaches it;
//! the forged messages it never sees were dropped at the router. (A receiver's own
//! publications also reach its own subscribers, so the reader is a session of its own.)
use super::distributed::{assert_all_gone, config, in_process, options, serial, step_reports};
use geese_orchestrator::distributed::launch::{run_net, Security};
use geese_proto::keys::{self, AgentRange};
use geese_proto::net::NetReport;
use geese_proto::security::{self, Credential};
use geese_proto::zenoh_bus::{self, CommonArgs, Role};
use geese_proto::{encode, Control};
use geese_world::Layout;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Marks every forged payload, so the reader tells them from the run's own traffic.
const MARK: &[u8] = b"ROGUE-";

/// What the rogue and the reader saw.
#[derive(Debug, Default)]
pub(crate) struct Attack {
    /// Forged messages published (on keys of other processes).
    pub forged: u64,
    /// Forged messages the reader received (must be 0).
    pub forged_seen: u64,
    /// Messages on the rogue's own keys (the control), published and seen.
    pub own: u64,
    pub own_seen: u64,
    /// Forged liveliness tokens the reader found.
    pub tokens_seen: Vec<String>,
    /// Could a session without credentials, or with a wrong password, open?
    pub anonymous_opened: bool,
    pub wrong_password_opened: bool,
}

/// Connect as `args`, trying for up to `patience`; `None` if refused (a router closes a
/// refused login's link at once; the client tries again until its patience runs out).
async fn try_open(args: &CommonArgs, patience: Duration) -> Option<zenoh::Session> {
    let mut a = args.clone();
    a.cfg.push(format!("connect/timeout_ms:{}", patience.as_millis()));
    match tokio::time::timeout(patience + Duration::from_secs(10), zenoh_bus::open(&a, Role::Client)).await {
        Ok(Ok(s)) => Some(s),
        _ => None,
    }
}

/// Log in as agent process `own`'s user and try to act as process `other`, as the world
/// and as the operator, for `rounds` rounds; a viewer-logged reader counts what arrives.
/// `rogue` and `reader` are the two logins; `anonymous` is `rogue` without credentials.
pub(crate) fn attack(
    run: &str,
    rogue: &CommonArgs,
    reader: &CommonArgs,
    own: AgentRange,
    other: AgentRange,
    rounds: u32,
) -> Attack {
    let rt = zenoh_bus::runtime(1).expect("runtime");
    // Read now: a run's own secrets go when it ends.
    let user = Credential::read(rogue.credentials.as_ref().expect("rogue credentials")).expect("cred").user;
    rt.block_on(async move {
        let mut out = Attack::default();
        let login = Duration::from_secs(20);
        let reader = try_open(reader, login).await.expect("the reader logs in");
        let seen = Arc::new(AtomicU64::new(0));
        let own_seen = Arc::new(AtomicU64::new(0));
        let (s, o) = (seen.clone(), own_seen.clone());
        let _all = reader
            .declare_subscriber(format!("{}/**", keys::run_prefix(run)))
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                if bytes.starts_with(MARK) {
                    if bytes.ends_with(b"own") {
                        o.fetch_add(1, Ordering::Relaxed);
                    } else {
                        s.fetch_add(1, Ordering::Relaxed);
                    }
                }
            })
            .await
            .expect("reader subscribes");
        // No credentials, and a wrong password, while the router is up (the reader is
        // in, and later sees the rogue's own messages).
        let anonymous = CommonArgs { credentials: None, ..rogue.clone() };
        let dir = tempfile::tempdir().expect("tempdir");
        let wrong = dir.path().join("wrong.cred");
        Credential::with_password(&user, "not-the-password").write(&wrong).expect("write");
        let wrong = CommonArgs { credentials: Some(wrong), ..rogue.clone() };
        let refused = Duration::from_secs(3);
        let (a, w) = tokio::join!(try_open(&anonymous, refused), try_open(&wrong, refused));
        out.anonymous_opened = a.is_some();
        out.wrong_password_opened = w.is_some();
        // ...and the router still takes a valid login right after.
        let session = try_open(rogue, login).await.expect("the rogue logs in with valid credentials");
        let stop = encode(&Control::Stop).expect("encode");
        let forged_tokens = [keys::viewer_presence(run, "rogue"), keys::cells_presence(run, other)];
        let mut tokens = Vec::new();
        for k in &forged_tokens {
            // A refused token is dropped at the router; the declaration itself succeeds.
            if let Ok(t) = session.liveliness().declare_token(k.clone()).await {
                tokens.push(t);
            }
        }
        for round in 0..rounds {
            let mark = |what: &str| [MARK, format!("{round}-{what}").as_bytes()].concat();
            let forged: Vec<(String, Vec<u8>)> = vec![
                // As the other agent process: intents, gene bundles, per-cell genes.
                (keys::agents_action(run, other), mark("action")),
                (keys::agents_genes(run, other), mark("genes")),
                (keys::cell_genes_from(run, 5, 5, other), mark("cell-genes")),
                // As the world: ticks, percepts and genes handed to agents, reports,
                // cell percepts, view frames.
                (keys::tick(run), mark("tick")),
                (keys::host_percepts(run, other), mark("percepts")),
                (keys::host_percepts(run, own), mark("own-percepts")),
                (keys::host_genes(run, other), mark("host-genes")),
                (keys::cell_percept(run, 5, 5), mark("cell-percept")),
                (keys::cell_genes(run, 5, 5), mark("world-cell-genes")),
                (keys::report(run), mark("report")),
                (keys::view_frame(run), mark("frame")),
                // As the operator: a well-formed stop, and a schedule.
                (keys::ctl(run, "stop"), [MARK, &stop].concat()),
                (keys::ctl(run, "schedule"), mark("schedule")),
            ];
            for (k, b) in forged {
                if zenoh_bus::put(&session, &k, b).await.is_ok() {
                    out.forged += 1;
                }
            }
            // The stop as the world would decode it, unmarked: counted by its effect (the
            // run would end early).
            if zenoh_bus::put(&session, &keys::ctl(run, "stop"), stop.clone()).await.is_ok() {
                out.forged += 1;
            }
            // The control: its own gene key is open to it.
            if zenoh_bus::put(&session, &keys::agents_genes(run, own), mark("own")).await.is_ok() {
                out.own += 1;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // Let the last messages land.
        tokio::time::sleep(Duration::from_millis(500)).await;
        out.forged_seen = seen.load(Ordering::Relaxed);
        out.own_seen = own_seen.load(Ordering::Relaxed);
        for k in &forged_tokens {
            if let Ok(replies) = reader.liveliness().get(k.clone()).timeout(Duration::from_secs(2)).await {
                while let Ok(Ok(r)) = tokio::time::timeout(Duration::from_secs(3), replies.recv_async()).await {
                    if let Ok(sample) = r.result() {
                        out.tokens_seen.push(sample.key_expr().to_string());
                    }
                }
            }
        }
        drop(tokens);
        let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
        let _ = tokio::time::timeout(Duration::from_secs(5), reader.close()).await;
        out
    })
}

/// Lift the run's step-rate limit as the operator (the run waits for the rogue).
fn release(run: &str, operator: &CommonArgs) {
    let rt = zenoh_bus::runtime(1).expect("runtime");
    rt.block_on(async {
        let session = try_open(operator, Duration::from_secs(20)).await.expect("the operator logs in");
        let bytes = encode(&Control::StepRate(0.0)).expect("encode");
        zenoh_bus::put(&session, &keys::ctl(run, "view"), bytes).await.expect("the operator lifts the step rate");
        let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    });
}

#[test]
fn a_rogue_with_valid_credentials_reaches_no_one_and_changes_nothing() {
    let _one_at_a_time = serial();
    // 12 agents in three processes of four; every process reads all keys (no per-cell
    // tokens of its own), so a forged cells token would be new.
    // The run goes at 200 steps/s until the rogue (started at step 5) is done, then the
    // operator lifts the limit: the rogue never meets a finished run, however slowly it
    // gets its logins on a busy machine. (Without a limit the 30,000 steps took ~7 s,
    // and one CI run in several lost that race: the rogue's valid login came after
    // the router had gone.)
    let cfg = config(12, 30_000, 6, Layout::Paper);
    let expected = in_process(&cfg);
    let spec = cfg.clone().validate().expect("valid config");
    let mut opts = options(3, Some(4));
    opts.subscribe = Some("all".into());
    opts.step_rate = Some(200.0);
    assert_eq!(opts.security, Security::PerRun, "distributed runs are secured by default");
    let own = AgentRange::new(0, 4).expect("range");
    let other = AgentRange::new(4, 4).expect("range");
    let (tx, rx) = std::sync::mpsc::channel::<(String, CommonArgs, CommonArgs, CommonArgs)>();
    let rogue = std::thread::spawn(move || {
        let (run, rogue, reader, operator) = rx.recv_timeout(Duration::from_secs(120)).expect("run started");
        let a = attack(&run, &rogue, &reader, own, other, 20);
        release(&run, &operator);
        a
    });
    let mut sent = false;
    let mut reps: Vec<NetReport> = Vec::new();
    let mut pids = Vec::new();
    let out = run_net(&spec, &opts, |r, swarm| {
        reps.push(r.clone());
        if !sent && r.report.step >= 5 {
            sent = true;
            let rogue = swarm.client_args_as(&security::agents_user(own));
            let reader = swarm.client_args_as(security::VIEWER);
            let operator = swarm.client_args_as(security::OPERATOR);
            let _ = tx.send((swarm.run_name().to_string(), rogue, reader, operator));
        }
        pids = swarm.all_pids();
    })
    .expect("distributed run");
    let a = rogue.join().expect("rogue thread");
    eprintln!("rogue: {a:?}");
    assert!(out.completed, "the forged stop ended the run");
    assert!(a.forged >= 200, "{a:?}");
    assert_eq!(a.forged_seen, 0, "forged messages got through: {a:?}");
    assert!(a.tokens_seen.is_empty(), "forged liveliness tokens got through: {a:?}");
    assert_eq!((a.own, a.own_seen), (20, 20), "the control did not get through: {a:?}");
    assert!(!a.anonymous_opened, "a session without credentials connected");
    assert!(!a.wrong_password_opened, "a session with a wrong password connected");
    // The world counted the control's malformed bundles (at most one a step: two in one
    // step count once), and nothing of the 13 forged kinds a round.
    let hostile: u32 = reps.iter().map(|r| r.net.hostile).sum();
    eprintln!("hostile messages counted at the world: {hostile}");
    assert!((1..=a.own).contains(&(hostile as u64)), "{hostile} hostile messages at the world, {} controls", a.own);
    let got = step_reports(&reps);
    let first_diff = expected.iter().zip(&got).position(|(a, b)| a != b);
    assert!(
        first_diff.is_none() && expected.len() == got.len(),
        "the attacked run left the in-process trajectory at step index {first_diff:?}"
    );
    assert_all_gone(&pids);
}

/// `geese secure init` writes what a multi-host run needs and refuses bad input with a
/// message naming it; `geese control` refuses a login that is not the operator's; bad
/// credential and ACL files are named.
#[test]
fn secure_init_and_bad_security_input() {
    let geese = geese_tests::bin_path("geese-orchestrator", "geese");
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("s");
    let run = |args: &[&str]| std::process::Command::new(&geese).args(args).output().expect("run geese");
    let ok = run(&[
        "secure",
        "init",
        "--run",
        "exp1",
        "--agents",
        "10",
        "--per-process",
        "4",
        "--routers",
        "h1,h2",
        "--out",
        out.to_str().expect("path"),
    ]);
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let printed = String::from_utf8_lossy(&ok.stdout).to_string();
    for f in ["users.txt", "acl.json5", "layout.json", "agents-0-3.cred", "agents-8-9.cred", "router-h2.cred"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let dict = std::fs::read_to_string(out.join("users.txt")).expect("users");
    for line in dict.lines() {
        let password = line.split(':').nth(1).expect("user:password");
        assert!(!printed.contains(password), "a password was printed");
    }
    // A secured run logging everything at debug level, and its manifest, hold no password.
    let logged = dir.path().join("logged");
    let ok = run(&[
        "secure",
        "init",
        "--run",
        "logtest",
        "--agents",
        "4",
        "--per-process",
        "2",
        "--out",
        logged.to_str().expect("p"),
    ]);
    assert!(ok.status.success());
    let res = dir.path().join("logged-run");
    let o = std::process::Command::new(&geese)
        .args(["run", "--agents", "4", "--steps", "20", "--processes", "2", "--run-name", "logtest", "-q", "--secrets"])
        .arg(&logged)
        .arg("--out")
        .arg(&res)
        .env("RUST_LOG", "debug")
        .env("GEESE_BIN_DIR", super::distributed::bin_dir())
        .output()
        .expect("run geese");
    assert!(o.status.success(), "secured run with --secrets failed");
    let everything = [
        String::from_utf8_lossy(&o.stdout).to_string(),
        String::from_utf8_lossy(&o.stderr).to_string(),
        std::fs::read_to_string(res.join("manifest.json")).expect("manifest"),
    ]
    .concat();
    assert!(everything.len() > 10_000, "too little logged to mean anything ({} bytes)", everything.len());
    assert!(everything.contains("usrpwd+acl"), "the manifest does not say the run was secured");
    for line in std::fs::read_to_string(logged.join("users.txt")).expect("users").lines() {
        let password = line.split(':').nth(1).expect("user:password");
        assert!(!everything.contains(password), "the password of {line:.12}… was logged");
    }
    let fails = |args: &[&str], says: &[&str]| {
        let o = run(args);
        let e = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(!o.status.success(), "{args:?} succeeded");
        for s in says {
            assert!(e.contains(s), "{args:?}: {e:?} does not say {s:?}");
        }
    };
    let o = out.to_str().expect("path");
    fails(&["secure", "init", "--run", "x", "--agents", "10", "--ranges", "0-5,5-9", "--out", o], &["overlap", "0-5"]);
    fails(&["secure", "init", "--run", "x", "--agents", "10", "--ranges", "0-10", "--out", o], &["0-10", "outside"]);
    fails(&["secure", "init", "--run", "a/b", "--agents", "10", "--out", o], &["a/b"]);
    let viewer = out.join("viewer.cred");
    let v = viewer.to_str().expect("path");
    fails(
        &["control", "--run", "exp1", "-e", "tcp/127.0.0.1:9", "--credentials", v, "stop"],
        &["viewer", "only the operator"],
    );
    let missing = dir.path().join("nope.cred");
    fails(
        &["control", "--run", "exp1", "-e", "tcp/127.0.0.1:9", "--credentials", missing.to_str().expect("p"), "stop"],
        &["nope.cred"],
    );
    let bad = dir.path().join("bad.cred");
    std::fs::write(&bad, "no-colon-here\n").expect("write");
    fails(
        &["view", "--run", "exp1", "-e", "tcp/127.0.0.1:9", "--credentials", bad.to_str().expect("p")],
        &["bad.cred", "user:password"],
    );
    let acl = dir.path().join("acl.json5");
    std::fs::write(&acl, "{ enabled: true, rules: [ { id: 7 } ] ").expect("write");
    fails(&["router", "-l", "tcp/127.0.0.1:0", "--acl", acl.to_str().expect("p")], &["acl.json5", "access-control"]);
    // A run given secrets made for another run name, or lacking its processes.
    let res = dir.path().join("results");
    let r = res.to_str().expect("path");
    fails(
        &[
            "run",
            "--agents",
            "10",
            "--steps",
            "5",
            "--processes",
            "2",
            "--secrets",
            o,
            "--run-name",
            "other",
            "--out",
            r,
        ],
        &["exp1", "other"],
    );
    fails(
        &["run", "--agents", "10", "--steps", "5", "--processes", "2", "--secrets", o, "--out", r],
        &["no credential", "0-4"],
    );
    fails(
        &["run", "--agents", "10", "--steps", "5", "--processes", "0", "--out", r],
        &["--secrets", "geese secure init"],
    );
}
