//! The live viewer end to end: a real run serves its page, headless Chromium (driven by
//! playwright-core, tests/browser/view.mjs) opens it and checks that the step counter
//! advances, the canvas shows agents, clicking an agent shows its tree, pause stops the
//! counter and resume restarts it, and an obstacle added by a click is in the world's
//! next frame. In-process, and over Zenoh with two agent processes.
//!
//! Needs Chromium (`/usr/bin/chromium`, or `$CHROMIUM`) and `tests/browser/node_modules`
//! (`npm ci --prefix tests/browser`); `tests/setup` installs both, and the README's test
//! command runs it first. Without them this test fails and says so: a browser test that
//! skips itself would pass on a machine where nothing was checked.
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn repo() -> PathBuf {
    let manifest = std::env::var_os("CARGO_MANIFEST_DIR").map(PathBuf::from).expect("CARGO_MANIFEST_DIR");
    manifest.join("..")
}

/// Ends the run we started (by its PID) whatever happens in the test: an interrupt
/// first, so a distributed run's launcher takes its world and agent processes down with
/// it; a kill if it has not gone within 15 s.
struct Run(Child);

impl Drop for Run {
    fn drop(&mut self) {
        let _ = Command::new("kill").args(["-INT", &self.0.id().to_string()]).status();
        let deadline = Instant::now() + Duration::from_secs(15);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Start `geese run --view` with `extra` flags; returns it and the page's URL.
fn start(extra: &[&str], out: &std::path::Path) -> (Run, String) {
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    if extra.contains(&"--processes") {
        geese_tests::bin_path("geese-world", "geese-world");
        geese_tests::bin_path("geese-agent", "geese-agent");
    }
    let mut child = Command::new(bin)
        .args(["run", "--view", "--step-rate", "20", "--steps", "100000", "--agents", "40", "--quiet", "--out"])
        .arg(out)
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start geese run --view");
    let stdout = child.stdout.take().expect("stdout");
    let run = Run(child);
    // The URL line comes within seconds; a reader thread keeps the wait bounded.
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(url) = line.strip_prefix("view: ") {
                let _ = tx.send(url.split_whitespace().next().unwrap_or_default().to_string());
            }
        }
    });
    let url = rx.recv_timeout(Duration::from_secs(60)).expect("geese run --view printed its URL within 60 s");
    (run, url)
}

/// Run the browser checks against `url`; returns what the browser saw (JSON).
fn browse(url: &str, screenshot: &std::path::Path) -> serde_json::Value {
    let browser = repo().join("tests/browser");
    assert!(
        browser.join("node_modules/playwright-core").exists(),
        "tests/browser/node_modules is missing: run `bash tests/setup` (the README's test command does)"
    );
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        std::path::Path::new(&chromium).exists(),
        "no Chromium at {chromium}: run `bash tests/setup` (or set CHROMIUM)"
    );
    let mut node = Command::new("node")
        .arg(browser.join("view.mjs"))
        .arg(url)
        .arg(screenshot)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("node (Node.js) is needed for the browser test: run `bash tests/setup`");
    // Bounded: the script's own waits are 15 s each; two minutes is far past them.
    let started = Instant::now();
    while node.try_wait().expect("poll node").is_none() {
        if started.elapsed() > Duration::from_secs(120) {
            let _ = node.kill();
            panic!("the browser test did not finish within 120 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let out = node.wait_with_output().expect("node output");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "browser checks failed: {}{}", stdout, String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(stdout.trim()).expect("the browser test prints one JSON line")
}

fn check(seen: &serde_json::Value, screenshot: &std::path::Path) {
    let pair = |k: &str| (seen[k][0].as_u64().expect(k), seen[k][1].as_u64().expect(k));
    let (a, b) = pair("advance");
    assert!(b > a, "counter advanced: {seen}");
    let (p, q) = pair("paused");
    assert_eq!(p, q, "pause held the counter: {seen}");
    let (r, s) = pair("resumed");
    assert!(s > r, "resume restarted the counter: {seen}");
    assert_eq!(seen["canvas"]["agents"], 40);
    assert!(seen["agent"]["nodes"].as_u64().unwrap_or(0) >= 2, "a tree was drawn: {seen}");
    assert_eq!(seen["obstacle"]["after"].as_u64(), seen["obstacle"]["before"].as_u64().map(|n| n + 1));
    let events = seen["obstacle"]["events"].as_array().expect("events");
    assert!(events.iter().any(|e| e[1].as_str().is_some_and(|w| w.starts_with("AddObstacleAt"))), "{seen}");
    let png = std::fs::read(screenshot).expect("screenshot saved");
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000, "a real screenshot");
}

#[test]
fn the_live_viewer_works_in_a_browser_in_process_and_over_zenoh() {
    let dir = std::env::temp_dir().join(format!("geese-view-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    {
        let (_run, url) = start(&[], &dir.join("in-process"));
        let shot = dir.join("in-process.png");
        let seen = browse(&url, &shot);
        check(&seen, &shot);
        eprintln!("in-process viewer: {seen}");
    }
    {
        // Multi-process runs take the suite's lock (one at a time on 2 cores).
        let _one = crate::distributed::serial();
        let (_run, url) = start(&["--processes", "2"], &dir.join("zenoh"));
        let shot = dir.join("zenoh.png");
        let seen = browse(&url, &shot);
        check(&seen, &shot);
        eprintln!("viewer over Zenoh: {seen}; screenshots in {}", dir.display());
    }
}
