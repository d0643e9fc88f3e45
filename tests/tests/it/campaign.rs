//! Campaigns end to end: the `geese campaign` binary killed mid-way and resumed, failed
//! trials, perturbation knobs in the trajectory, reports, figures and CSV export.
use geese_orchestrator::campaign::{
    run_campaign, Campaign, CampaignError, InProcess, Interrupted, RunOptions, TrialError, TrialRunner,
};
use geese_orchestrator::config::RunSpec;
use geese_orchestrator::report::{self, ReportOptions};
use geese_orchestrator::store::Store;
use geese_orchestrator::trial::Ran;
use geese_proto::StepReport;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// 2 tasks × 4 conditions × 4 seeds = 32 trials of 30 agents × 400 steps.
const KILLABLE: &str = r#"
name = "killable"
tasks = ["foraging", "nest"]
seeds = 4
x = "obstacles"
step_stride = 7
[base]
steps = 400
[base.world]
agents = 30
[[grid]]
obstacles = [1, 2]
obstacles_at = [100, 300]
"#;

pub(crate) fn quiet() -> RunOptions {
    RunOptions { jobs: 2, retry_failed: false, quiet: true }
}

type Key = (String, String, u64);

fn by_key(store: &Store) -> BTreeMap<Key, (i64, i64, Option<f64>)> {
    store
        .trials()
        .expect("read trials")
        .into_iter()
        .map(|t| ((t.condition, t.task, t.seed), (t.id, t.session, t.outcome.map(|o| o.final_pct))))
        .collect()
}

#[test]
fn killed_campaign_resumes_without_losing_or_repeating_a_trial() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("killable.toml");
    std::fs::write(&file, KILLABLE).expect("write campaign");
    let db = dir.path().join("killable.sqlite");
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    let mut child = Command::new(&bin)
        .args(["campaign", "-q", "--jobs", "2", "--db"])
        .arg(&db)
        .arg(&file)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn geese campaign");
    // Kill it (SIGKILL, by PID) as soon as a few trials are stored.
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        std::thread::sleep(Duration::from_millis(10));
        let stored =
            if db.exists() { Store::open(&db).and_then(|s| s.trials()).map(|t| t.len()).unwrap_or(0) } else { 0 };
        if stored >= 3 {
            break;
        }
        assert!(child.try_wait().expect("poll child").is_none(), "the campaign ended before it could be killed");
        assert!(Instant::now() < deadline, "no trial stored within 120 s");
    }
    child.kill().expect("kill geese campaign");
    child.wait().expect("reap");

    let store = Store::open(&db).expect("open db after kill");
    let before = by_key(&store);
    let total = 32;
    assert!(before.len() >= 3 && before.len() < total, "{} trials stored at the kill", before.len());
    // Only whole trials: each stored trial has all its step rows (every 7th and the last).
    for (id, _, _) in before.values() {
        assert_eq!(store.step_count(*id).expect("count"), 400 / 7 + 1);
    }
    let sessions = store.sessions().expect("sessions");
    assert_eq!(sessions.len(), 1);
    assert!(!sessions[0].finished, "the killed session must not look finished");
    drop(store);

    // Resume with the binary.
    let out = Command::new(&bin).args(["campaign", "-q", "--db"]).arg(&db).arg(&file).output().expect("resume");
    assert!(out.status.success(), "resume failed: {}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains(&format!("{} already stored", before.len())), "{stdout}");

    let store = Store::open(&db).expect("open db after resume");
    let after = by_key(&store);
    assert_eq!(after.len(), total, "every planned trial is stored exactly once");
    for (k, v) in &before {
        assert_eq!(after.get(k), Some(v), "trial {k:?} was run again or changed by the resume");
    }
    assert!(after.iter().filter(|(k, _)| !before.contains_key(*k)).all(|(_, (_, session, _))| *session == 2));
    assert!(after.values().all(|(_, _, pct)| pct.is_some()), "a trial failed");
    let sessions = store.sessions().expect("sessions");
    assert_eq!(
        (sessions[1].skipped, sessions[1].done, sessions[1].finished),
        (before.len(), total - before.len(), true)
    );

    // The interrupted-and-resumed results equal an uninterrupted run (same seeds).
    let campaign = Campaign::from_toml(KILLABLE, "killable").expect("campaign");
    let mut clean = Store::create(&dir.path().join("clean.sqlite")).expect("clean db");
    let o = run_campaign(&campaign, &mut clean, &InProcess, &quiet()).expect("clean run");
    assert_eq!((o.done, o.failed, o.skipped), (total, 0, 0));
    let clean: BTreeMap<Key, Option<f64>> = by_key(&clean).into_iter().map(|(k, v)| (k, v.2)).collect();
    let resumed: BTreeMap<Key, Option<f64>> = after.into_iter().map(|(k, v)| (k, v.2)).collect();
    assert_eq!(clean, resumed);
}

/// Runs every trial in-process except those with seed 2, which end as `fail` says
/// (a panic, or an error the runner returns).
struct Seed2Fails {
    transport: &'static str,
    fail: fn() -> TrialError,
}

impl TrialRunner for Seed2Fails {
    fn transport(&self) -> &str {
        self.transport
    }
    fn run(&self, spec: &RunSpec, observe: &mut dyn FnMut(&StepReport)) -> Result<Ran, TrialError> {
        if spec.config.seed == 2 {
            return Err((self.fail)());
        }
        InProcess.run(spec, observe)
    }
}

/// Fails (by panicking) every trial with seed 2.
const FLAKY: Seed2Fails = Seed2Fails { transport: "flaky", fail: || panic!("injected failure") };

/// Interrupted (as by Ctrl-C) in every trial with seed 2.
const INTERRUPTED: Seed2Fails = Seed2Fails { transport: "in-process", fail: || Box::new(Interrupted) };

#[test]
fn failed_trials_are_recorded_and_the_campaign_goes_on() {
    // 100 obstacles of radius 10 do not fit around the hub: the world cannot be built.
    let text = r#"
        tasks = ["foraging"]
        seeds = 3
        x = "initial_obstacles"
        [base]
        steps = 50
        [base.world]
        agents = 5
        [[grid]]
        initial_obstacles = [0, 100]
    "#;
    let c = Campaign::from_toml(text, "failing").expect("valid campaign");
    let dir = tempfile::tempdir().expect("tempdir");
    let db = dir.path().join("f.sqlite");
    let mut store = Store::create(&db).expect("db");
    let o = run_campaign(&c, &mut store, &FLAKY, &quiet()).expect("campaign runs");
    // Seeds 1 and 3 of condition 0 succeed; seed 2 panics; condition 100 never builds.
    assert_eq!((o.done, o.failed), (2, 4));
    let trials = store.trials().expect("trials");
    let err = |cond: &str, seed: u64| {
        trials.iter().find(|t| t.condition == cond && t.seed == seed).and_then(|t| t.error.clone()).unwrap_or_default()
    };
    assert!(err("initial_obstacles=0", 2).contains("panic: injected failure"));
    assert!(err("initial_obstacles=100", 1).contains("obstacle"), "{}", err("initial_obstacles=100", 1));
    // A second invocation skips failed trials unless asked to retry them.
    let o = run_campaign(&c, &mut store, &FLAKY, &quiet()).expect("again");
    assert_eq!((o.skipped, o.done, o.failed), (6, 0, 0));
    let retry = RunOptions { retry_failed: true, ..quiet() };
    let o = run_campaign(&c, &mut store, &InProcess, &retry).expect("retry");
    assert_eq!((o.skipped, o.done, o.failed), (2, 1, 3));
    assert_eq!(store.trials().expect("trials").len(), 6);
}

#[test]
fn an_interrupted_trial_stops_the_campaign_and_is_not_recorded() {
    let text = r#"
        tasks = ["foraging"]
        seeds = 3
        x = "obstacles"
        [base]
        steps = 30
        [base.world]
        agents = 5
        [[grid]]
        obstacles = [1]
        obstacles_at = [10]
    "#;
    let c = Campaign::from_toml(text, "interrupted").expect("campaign");
    let dir = tempfile::tempdir().expect("tempdir");
    let mut store = Store::create(&dir.path().join("i.sqlite")).expect("db");
    let one_at_a_time = RunOptions { jobs: 1, ..quiet() };
    let err = run_campaign(&c, &mut store, &INTERRUPTED, &one_at_a_time).expect_err("interrupted");
    assert!(matches!(err, CampaignError::Interrupted { .. }), "{err}");
    let stored = store.trials().expect("trials");
    assert!(stored.iter().all(|t| t.seed != 2 && t.error.is_none()), "no failure recorded for the interruption");
    // The next invocation resumes: everything not stored runs, nothing runs twice.
    let o = run_campaign(&c, &mut store, &InProcess, &quiet()).expect("resumed");
    assert_eq!((o.skipped, o.done, o.failed), (stored.len(), 3 - stored.len(), 0));
}

/// Records every step report of every trial `inner` runs, keyed by its perturbations.
pub(crate) struct Recorder<R> {
    pub inner: R,
    pub runs: Mutex<BTreeMap<String, Vec<StepReport>>>,
}

impl<R> Recorder<R> {
    pub fn new(inner: R) -> Self {
        Recorder { inner, runs: Mutex::default() }
    }
}

impl<R: TrialRunner> TrialRunner for Recorder<R> {
    fn transport(&self) -> &str {
        self.inner.transport()
    }
    fn run(&self, spec: &RunSpec, observe: &mut dyn FnMut(&StepReport)) -> Result<Ran, TrialError> {
        let mut reps = Vec::new();
        let s = self.inner.run(spec, &mut |r| {
            reps.push(r.clone());
            observe(r)
        })?;
        let key = serde_json::to_string(&spec.config.perturbations).unwrap_or_default();
        self.runs.lock().expect("lock").insert(key, reps);
        Ok(s)
    }
}

#[test]
fn perturbation_knobs_act_at_their_step() {
    let text = r#"
        tasks = ["foraging"]
        seeds = 1
        lt_pause_on_obstacles = true
        stop_interval = 30
        x = "condition"
        [base]
        steps = 150
        [base.world]
        agents = 40
        start = "hub"
        [[grid]]
        kill = 0.5
        kill_at = 20
        lt_off_at = 60
        lt_off_for = 20
        [[grid]]
        obstacles = 2
        obstacles_at = 100
    "#;
    let c = Campaign::from_toml(text, "perturb").expect("campaign");
    assert_eq!(c.x_of(1), (1.0, "obstacles=2 obstacles_at=100".to_string()));
    let dir = tempfile::tempdir().expect("tempdir");
    let mut store = Store::create(&dir.path().join("p.sqlite")).expect("db");
    let rec = Recorder::new(InProcess);
    let o = run_campaign(&c, &mut store, &rec, &quiet()).expect("runs");
    assert_eq!(o.done, 2);
    let runs = rec.runs.into_inner().expect("lock");
    let (kill_lt, obstacles): (Vec<_>, Vec<_>) = runs.values().partition(|r| r.iter().any(|s| s.live_agents < 40));
    let r = &kill_lt[0];
    // Killed right after step 20 is resolved; step 20's report is taken after the hooks.
    assert_eq!((r[18].live_agents, r[19].live_agents, r[149].live_agents), (40, 20, 20));
    // Lateral transfer off for steps 61..=80: no gene kept, so the LT rate is 0.
    assert!(r[60..80].iter().all(|s| s.lt_mean == 0.0 && s.genetic_steps == 0));
    assert!(r[..60].iter().any(|s| s.lt_mean > 0.0) && r[80..].iter().any(|s| s.lt_mean > 0.0));
    // Obstacles at 100 pause lateral transfer for 30 steps (reference coupling on).
    let r = &obstacles[0];
    assert!(r[100..130].iter().all(|s| s.lt_mean == 0.0));
    assert!(r[130..].iter().any(|s| s.lt_mean > 0.0));
}

fn png_ok(path: &Path) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 5_000, "{} is not a drawn PNG", path.display());
}

#[test]
fn smoke_campaigns_report_and_export() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../campaigns/smoke");
    let dir = tempfile::tempdir().expect("tempdir");
    let mut names = Vec::new();
    for entry in std::fs::read_dir(&root).expect("campaigns/smoke") {
        let path = entry.expect("entry").path();
        let c = Campaign::from_file(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let db = dir.path().join(format!("{}.sqlite", c.name));
        let mut store = Store::create(&db).expect("db");
        let o = run_campaign(&c, &mut store, &InProcess, &quiet()).expect("smoke campaign");
        assert_eq!((o.done, o.failed), (c.plan().len(), 0), "{}", c.name);
        let r = report::build(&store, &ReportOptions::default()).expect("report");
        assert_eq!(r.points.len(), c.plan().len());
        assert!(r.fits.iter().all(|f| f.n > 0));
        let mut text = Vec::new();
        r.print(&mut text).expect("print");
        assert!(String::from_utf8_lossy(&text).contains("Least-squares slope"));
        names.push(c.name.clone());
    }
    names.sort();
    assert!(names.len() >= 9, "{names:?}");

    // Figures and CSVs through the binary, for a campaign with a series knob.
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    let db = dir.path().join("smoke-fig4-ip-st.sqlite");
    let out_dir = dir.path().join("fig4");
    let out = Command::new(&bin).arg("report").arg(&db).arg("--out").arg(&out_dir).output().expect("report");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("Pooled by ip"), "{stdout}");
    for f in ["curves-foraging-st-7", "resilience-foraging", "final-foraging"] {
        png_ok(&out_dir.join(format!("{f}.png")));
        assert!(std::fs::read_to_string(out_dir.join(format!("{f}.svg"))).expect("svg").contains("<svg"));
    }
    for f in ["conditions.csv", "pooled.csv", "fits.csv", "points.csv"] {
        assert!(out_dir.join(f).exists(), "{f}");
    }
    // Reference-code metrics need the campaign's code_efficiency (fig4 has none).
    let out = Command::new(&bin)
        .arg("report")
        .arg(&db)
        .args(["--efficiency", "code", "--no-plots"])
        .output()
        .expect("report");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("code_efficiency"));
    let db = dir.path().join("smoke-ablation.sqlite");
    let out = Command::new(&bin)
        .arg("report")
        .arg(&db)
        .args(["--efficiency", "code", "--power", "code", "--no-plots", "--out"])
        .arg(dir.path().join("abl"))
        .output()
        .expect("report");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("sec5-ablation"));

    // CSV export: one trials row per trial, step rows of every trial, the manifest.
    let csv = dir.path().join("csv");
    let out = Command::new(&bin).arg("export").arg(&db).arg("--out").arg(&csv).output().expect("export");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let trials = std::fs::read_to_string(csv.join("trials.csv")).expect("trials.csv");
    assert_eq!(trials.lines().count(), 1 + 3 * 2 * 2 * 2);
    let steps = std::fs::read_to_string(csv.join("steps.csv")).expect("steps.csv");
    assert_eq!(steps.lines().count(), 1 + 24 * 200);
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(csv.join("manifest.json")).expect("manifest")).expect("json");
    assert_eq!(manifest["name"], "smoke-ablation");
    assert!(manifest["versions"]["git_revision"].is_string());
    assert!(manifest["campaign_file"].as_str().is_some_and(|s| s.contains("obstacles_at")));
}

#[test]
fn bad_campaign_file_is_an_error_naming_the_key() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    for (text, key) in [
        ("tasks = [\"foraging\"]\nseeds = 2\n[[grid]]\nip = [0.5, 1.2]\n", "grid[0].ip[1]"),
        ("tasks = [\"foraging\"]\nseeds = 2\n[[grid]]\nobstacle = [1]\n", "grid[0].obstacle"),
        ("tasks = [\"foraging\"]\nseeds = 2\nsteps = 5\n[[grid]]\nip = 0.5\n", "steps"),
        ("tasks = [\"foraging\"]\nseeds = 2\n[[grid]]\nst = []\n", "grid[0].st"),
    ] {
        let f = dir.path().join("bad.toml");
        std::fs::write(&f, text).expect("write");
        let out = Command::new(&bin)
            .arg("campaign")
            .arg(&f)
            .arg("--db")
            .arg(dir.path().join("x.sqlite"))
            .output()
            .expect("run");
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(key), "expected '{key}' in: {err}");
    }
}
