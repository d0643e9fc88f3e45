//! Campaigns end to end: the `geese campaign` binary killed mid-way and resumed, failed
//! trials, perturbation knobs in the trajectory, reports, figures and CSV export.
use geese_orchestrator::analysis::report::{self, ReportOptions};
use geese_orchestrator::campaigns::campaign::{
    run_campaign, Campaign, CampaignError, InProcess, Interrupted, RunOptions, TrialError, TrialRunner,
};
use geese_orchestrator::campaigns::store::Store;
use geese_orchestrator::run::config::RunSpec;
use geese_orchestrator::run::trial::Ran;
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
    RunOptions { jobs: 2, quiet: true, ..RunOptions::default() }
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
    // One fitted line per series level (st): st = 7 spans two ip levels, st = 5 one.
    let fits = csv_rows(&out_dir.join("fits.csv"));
    let slope = |st: &str| {
        let r = fits.iter().find(|r| r["series"] == st && r["metric"] == "power").expect("fit of the series level");
        r["slope_per_position"].clone()
    };
    assert!(slope("7").parse::<f64>().is_ok(), "{fits:?}");
    assert_eq!(slope("5"), "", "one level, no line");
    assert_eq!(fits.iter().filter(|r| r["metric"] == "power").count(), 3, "{fits:?}");
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

    // Several campaigns' slopes on one figure, one line per series level.
    let stem = dir.path().join("slopes/both");
    let fig4 = dir.path().join("smoke-fig4-ip-st.sqlite");
    let out = Command::new(&bin).arg("slopes").arg(&fig4).arg(&db).arg("--out").arg(&stem).output().expect("slopes");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("smoke-fig4-ip-st") && stdout.contains("smoke-ablation"), "{stdout}");
    png_ok(&stem.with_extension("png"));
    let rows = csv_rows(&stem.with_extension("csv"));
    // fig4: 3 st levels × 2 metrics; ablation: no series, 2 tasks × 2 metrics.
    assert_eq!(rows.len(), 6 + 4, "{rows:?}");
    assert!(rows.iter().any(|r| r["campaign"] == "smoke-ablation" && r["x"] == "obstacles" && r["series"].is_empty()));
    let svg = std::fs::read_to_string(stem.with_extension("svg")).expect("svg");
    assert!(svg.contains("st = 7") && svg.contains("smoke-ablation (nest), power"), "legend and panel titles");
    let missing = dir.path().join("nothing-here.sqlite");
    let out = Command::new(&bin).arg("slopes").arg(&missing).arg("--out").arg(&stem).output().expect("slopes");
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("nothing-here.sqlite"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

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

/// Fig. 8-style campaign: two algorithms (listed against alphabetical order), each
/// learning population tested with half and all of its best members.
const ALGORITHMS: &str = r#"
name = "algorithms"
tasks = ["foraging"]
seeds = 2
x = "sample"
series = "algorithm"
[base]
steps = 50
[base.world]
agents = 10
[[grid]]
algorithm = ["geese-bt", "betr-geese"]
sample = [1.0, 0.5]
"#;

/// The SVG's text elements, in drawing order: (x attribute, text).
fn svg_texts(svg: &str) -> Vec<(f64, String)> {
    svg.split("<text ")
        .skip(1)
        .map(|el| {
            let x = el.split("x=\"").nth(1).and_then(|r| r.split('"').next()).expect("x attribute");
            let body = el.split_once('>').and_then(|(_, b)| b.split("</text>").next()).expect("text body");
            (x.parse().expect("number"), body.trim().to_string())
        })
        .collect()
}

/// The `x` attributes of the SVG text elements that read exactly `text`.
fn svg_text_x(svg: &str, text: &str) -> Vec<f64> {
    svg_texts(svg).into_iter().filter(|(_, t)| t == text).map(|(x, _)| x).collect()
}

/// Position of the first SVG text element reading exactly `text`, in drawing order.
fn svg_text_index(svg: &str, text: &str) -> Option<usize> {
    svg_texts(svg).iter().position(|(_, t)| t == text)
}

fn svg(dir: &Path, stem: &str) -> String {
    png_ok(&dir.join(format!("{stem}.png")));
    std::fs::read_to_string(dir.join(format!("{stem}.svg"))).unwrap_or_else(|e| panic!("{stem}.svg: {e}"))
}

/// Width of a PNG file.
fn png_width(path: &Path) -> u32 {
    let b = std::fs::read(path).expect("png");
    u32::from_be_bytes([b[16], b[17], b[18], b[19]])
}

/// Rows of a CSV without quoted fields, as maps from the header's names.
fn csv_rows(path: &Path) -> Vec<BTreeMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("csv");
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().expect("header").split(',').collect();
    lines.map(|l| head.iter().map(|h| h.to_string()).zip(l.split(',').map(str::to_string)).collect()).collect()
}

#[test]
fn algorithm_comparison_figures_and_wall_time_per_step() {
    let c = Campaign::from_toml(ALGORITHMS, "algorithms").expect("campaign");
    let dir = tempfile::tempdir().expect("tempdir");
    let mut store = Store::create(&dir.path().join("a.sqlite")).expect("db");
    let o = run_campaign(&c, &mut store, &InProcess, &quiet()).expect("campaign");
    assert_eq!((o.done, o.failed), (8, 0));

    // Every trial has the wall time of its fixed test, and the learning run it tested:
    // the two sampling sizes of one (algorithm, seed) tested the same learned population.
    let trials = store.trials().expect("trials");
    for t in &trials {
        let wall = t.stage_wall_seconds.expect("stage wall time stored");
        assert!(wall > 0.0 && wall <= t.wall_seconds, "{wall} vs {}", t.wall_seconds);
        assert_eq!(t.ms_per_step(), Some(wall * 1000.0 / 50.0));
    }
    let mut learning: BTreeMap<i64, Vec<(u64, f64)>> = BTreeMap::new();
    store.for_each_learning_pct(|id, step, v| learning.entry(id).or_default().push((step, v))).expect("rows");
    assert_eq!(learning.len(), 8);
    for t in &trials {
        let rows = &learning[&t.id];
        assert_eq!(rows.iter().map(|r| r.0).collect::<Vec<_>>(), (1..=50).collect::<Vec<u64>>());
        let twin = trials.iter().find(|u| u.series == t.series && u.seed == t.seed && u.id != t.id).expect("twin");
        assert_ne!(twin.x, t.x);
        assert_eq!(&learning[&twin.id], rows, "both sampling sizes tested the same learning run");
    }

    let r = report::build(&store, &ReportOptions::default()).expect("report");
    // Text series levels in order of first appearance, not alphabetical.
    assert_eq!(r.series_levels, ["geese-bt", "betr-geese"]);
    for row in &r.conditions {
        let ms: Vec<f64> = trials.iter().filter(|t| t.condition == row.label).filter_map(|t| t.ms_per_step()).collect();
        assert_eq!(ms.len(), 2, "{}", row.label);
        let s = row.ms_per_step.expect("ms per step");
        assert!((s.median - (ms[0] + ms[1]) / 2.0).abs() < 1e-9, "{} vs {ms:?}", s.median);
    }
    let out = dir.path().join("report");
    let mut files = r.write_csv(&out).expect("csv");
    files.extend(r.plot(&store, &out).expect("plots"));
    let mut names: Vec<String> =
        files.iter().map(|f| f.file_name().expect("name").to_string_lossy().into_owned()).collect();
    names.sort();
    let mut expected: Vec<String> = [
        "curves-foraging-algorithm-betr-geese",
        "curves-foraging-algorithm-geese-bt",
        "final-foraging",
        "learning-foraging",
        "resilience-foraging",
        "walltime-foraging",
    ]
    .iter()
    .flat_map(|s| [format!("{s}.png"), format!("{s}.svg")])
    .chain(["conditions.csv", "fits.csv", "points.csv", "pooled.csv"].map(String::from))
    .collect();
    expected.sort();
    assert_eq!(names, expected);

    // Fig. 8a: one figure, one curve per algorithm, legend in campaign order.
    let learn = svg(&out, "learning-foraging");
    let (bt, betr) = (svg_text_index(&learn, "algorithm = geese-bt"), svg_text_index(&learn, "algorithm = betr-geese"));
    assert!(bt.is_some() && betr.is_some() && bt < betr, "legend of learning-foraging");
    // Fig. 8b: sampling sizes on x (by value), boxes of both algorithms.
    let fin = svg(&out, "final-foraging");
    let (half, all) = (svg_text_x(&fin, "0.5"), svg_text_x(&fin, "1"));
    assert!(half.len() == 1 && all.len() == 1 && half[0] < all[0], "{half:?} {all:?}");
    let legend = |svg: &str| {
        (svg_text_index(svg, "algorithm = geese-bt").is_some(), svg_text_index(svg, "algorithm = betr-geese").is_some())
    };
    assert_eq!(legend(&fin), (true, true));
    // Fig. 9b: wall time per step.
    let wall = svg(&out, "walltime-foraging");
    assert!(svg_text_index(&wall, "wall ms per step").is_some());
    assert_eq!(legend(&wall), (true, true));

    // The wall-time columns of the tables.
    let rows = csv_rows(&out.join("conditions.csv"));
    assert_eq!(rows.len(), 4);
    for (row, csv) in r.conditions.iter().zip(&rows) {
        let median: f64 = csv["ms_per_step_median"].parse().expect("ms_per_step_median");
        assert_eq!(Some(median), row.ms_per_step.map(|s| s.median));
    }
    let pooled = csv_rows(&out.join("pooled.csv"));
    assert_eq!(pooled.iter().map(|r| r["label"].as_str()).collect::<Vec<_>>(), ["0.5", "1"]);
    assert!(pooled.iter().all(|r| r["ms_per_step_q3"].parse::<f64>().is_ok_and(|v| v > 0.0)));
    let points = csv_rows(&out.join("points.csv"));
    assert_eq!(points.len(), 8);
    for p in &points {
        let t = trials
            .iter()
            .find(|t| t.condition == p["condition"].replace('"', "") && t.seed.to_string() == p["seed"])
            .expect("trial of the point");
        assert_eq!(p["ms_per_step"].parse::<f64>().ok(), t.ms_per_step());
    }
    let mut text = Vec::new();
    r.print(&mut text).expect("print");
    assert!(String::from_utf8_lossy(&text).contains("ms/step"));
}

/// Fig. 3-style campaign: conditions of two text knobs, on the x axis.
const TEXT_CONDITIONS: &str = r#"
name = "fig3-like"
tasks = ["foraging"]
seeds = 3
x = "condition"
[base]
steps = 100
[[grid]]
algorithm = "geese-bt"
terms = ["E+C+F", "E+B"]
[[grid]]
algorithm = "betr-geese"
terms = "D+E+B"
"#;

#[test]
fn text_conditions_are_ordered_as_written_with_readable_labels() {
    use geese_orchestrator::analysis::metrics;
    use geese_orchestrator::campaigns::store::TrialResult;
    use geese_orchestrator::run::trial::TrialSummary;
    let c = Campaign::from_toml(TEXT_CONDITIONS, "fig3-like").expect("campaign");
    let dir = tempfile::tempdir().expect("tempdir");
    let mut store = Store::create(&dir.path().join("t.sqlite")).expect("db");
    let session = store.begin_session(&c).expect("session");
    // Stored results made up so that every number is known: condition i, seed s reaches
    // 10·i + s % and its last stage took (i + 1)·s·0.1 s for 100 steps, (i + 1)·s ms a step.
    for t in c.plan() {
        let (i, s) = (t.condition as f64, t.seed as f64);
        let series: Vec<f64> = (1..=100).map(|k| (10.0 * i + s) * k as f64 / 100.0).collect();
        let rows: Vec<StepReport> = series
            .iter()
            .enumerate()
            .map(|(k, &v)| StepReport { step: k as u64 + 1, task_pct: v, ..Default::default() })
            .collect();
        let summary = TrialSummary { wall_seconds: (i + 1.0) * s * 0.1, ..TrialSummary::new(t.seed) };
        let result = TrialResult {
            outcome: metrics::outcome(&series, 80.0),
            summary: Some(summary),
            rows,
            error: None,
            wall_seconds: 1.0,
            learning_rows: Vec::new(),
        };
        store.insert(&c.record(&t), &result, session, 1.0, "made-up").expect("insert");
    }
    let r = report::build(&store, &ReportOptions::default()).expect("report");
    let labels: Vec<&str> = r.conditions.iter().map(|row| row.label.as_str()).collect();
    assert_eq!(
        labels,
        ["algorithm=geese-bt terms=E+C+F", "algorithm=geese-bt terms=E+B", "algorithm=betr-geese terms=D+E+B"]
    );
    let medians: Vec<f64> = r.conditions.iter().map(|row| row.ms_per_step.expect("ms").median).collect();
    for (m, want) in medians.iter().zip([2.0, 4.0, 6.0]) {
        assert!((m - want).abs() < 1e-9, "{medians:?}");
    }
    let groups: Vec<&str> = r.groups.iter().map(|row| row.label.as_str()).collect();
    assert_eq!(groups, labels, "pooled by condition, in campaign order");

    let out = dir.path().join("report");
    r.write_csv(&out).expect("csv");
    let files = r.plot(&store, &out).expect("plots");
    assert_eq!(files.len(), 2 * 4, "curves, resilience, final, walltime");
    let rows = csv_rows(&out.join("conditions.csv"));
    let csv_medians: Vec<f64> = rows.iter().map(|r| r["ms_per_step_median"].parse().expect("median")).collect();
    assert_eq!(csv_medians, medians);
    for stem in ["final-foraging", "walltime-foraging", "resilience-foraging"] {
        let svg = svg(&out, stem);
        // One knob per line, never the whole label on one line; left to right as written.
        assert!(svg_text_index(&svg, "algorithm=geese-bt terms=E+C+F").is_none(), "{stem}");
        assert_eq!(svg_text_x(&svg, "algorithm=geese-bt").len(), if stem == "resilience-foraging" { 4 } else { 2 });
        let x = |t: &str| svg_text_x(&svg, t)[0];
        assert!(x("terms=E+C+F") < x("terms=E+B") && x("terms=E+B") < x("terms=D+E+B"), "{stem}");
        assert!(x("algorithm=betr-geese") > x("terms=E+B"));
        // Neighbouring labels do not overlap: ~0.62 em per character at 14 px.
        let gap = x("terms=E+B") - x("terms=E+C+F");
        assert!(gap > "algorithm=betr-geese".len() as f64 * 14.0 * 0.62, "{stem}: {gap}");
    }
    assert!(png_width(&out.join("final-foraging.png")) > 700);
    let wall = svg(&out, "walltime-foraging");
    assert!(svg_text_index(&wall, "wall ms per step").is_some());
}

/// Fig. 9-style campaign: each algorithm's population tested at its own sampling size,
/// algorithms on the x axis (no series knob).
const BEST_POPULATIONS: &str = r#"
name = "best"
tasks = ["foraging"]
seeds = 2
x = "algorithm"
[base]
steps = 50
[base.world]
agents = 10
[[grid]]
algorithm = "geese-bt"
sample = 0.5
[[grid]]
algorithm = "betr-geese"
sample = 1.0
"#;

#[test]
fn algorithms_on_x_get_one_curve_and_one_box_each() {
    let c = Campaign::from_toml(BEST_POPULATIONS, "best").expect("campaign");
    let dir = tempfile::tempdir().expect("tempdir");
    let mut store = Store::create(&dir.path().join("b.sqlite")).expect("db");
    let o = run_campaign(&c, &mut store, &InProcess, &quiet()).expect("campaign");
    assert_eq!((o.done, o.failed), (4, 0));
    let r = report::build(&store, &ReportOptions::default()).expect("report");
    let out = dir.path().join("report");
    let files = r.plot(&store, &out).expect("plots");
    let mut stems: Vec<String> =
        files.iter().map(|f| f.file_stem().expect("stem").to_string_lossy().into_owned()).collect();
    stems.dedup();
    assert_eq!(
        stems,
        ["curves-foraging", "learning-foraging", "resilience-foraging", "final-foraging", "walltime-foraging"]
    );
    for stem in ["curves-foraging", "learning-foraging"] {
        let svg = svg(&out, stem);
        let (bt, betr) = (svg_text_index(&svg, "algorithm = geese-bt"), svg_text_index(&svg, "algorithm = betr-geese"));
        assert!(bt.is_some() && betr.is_some() && bt < betr, "{stem}: one curve per algorithm, in campaign order");
    }
    for stem in ["final-foraging", "walltime-foraging"] {
        let svg = svg(&out, stem);
        let (bt, betr) = (svg_text_x(&svg, "geese-bt"), svg_text_x(&svg, "betr-geese"));
        assert!(bt.len() == 1 && betr.len() == 1 && bt[0] < betr[0], "{stem}: {bt:?} {betr:?}");
    }
    let ms: Vec<f64> = r.groups.iter().map(|g| g.ms_per_step.expect("ms per step").median).collect();
    assert!(ms.len() == 2 && ms.iter().all(|&v| v > 0.0), "{ms:?}");
}

/// 2 agent counts × 2 tasks × 2 seeds, plus GEESE-BT learning runs tested at two
/// sampling sizes × 2 tasks × 2 seeds: 16 small trials, 4 of the learning runs shared
/// by two trials each.
const SHARDED: &str = r#"
name = "sharded"
tasks = ["foraging", "nest"]
seeds = 2
x = "condition"
step_stride = 3
[base]
steps = 60
[base.world]
agents = 8
[[grid]]
agents = [6, 12]
[[grid]]
algorithm = "geese-bt"
sample = [0.5, 1.0]
"#;

/// Fields of an RFC 4180 CSV text (quoted fields may hold commas, quotes, newlines).
fn parse_csv(text: &str) -> Vec<Vec<String>> {
    let (mut rows, mut row, mut field) = (Vec::new(), Vec::new(), String::new());
    let mut chars = text.chars().peekable();
    let mut quoted = false;
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                field.push('"');
                chars.next();
            }
            (true, '"') => quoted = false,
            (true, c) => field.push(c),
            (false, '"') => quoted = true,
            (false, ',') => row.push(std::mem::take(&mut field)),
            (false, '\n') => {
                row.push(std::mem::take(&mut field));
                rows.push(std::mem::take(&mut row));
            }
            (false, c) => field.push(c),
        }
    }
    rows
}

/// A CSV export's rows without the columns named in `drop`, sorted: comparable between
/// databases whose row ids and wall-clock times differ.
fn csv_without(path: &Path, drop: &[&str]) -> (Vec<String>, Vec<Vec<String>>) {
    let mut rows = parse_csv(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())));
    let head = rows.remove(0);
    let keep: Vec<usize> = (0..head.len()).filter(|&i| !drop.contains(&head[i].as_str())).collect();
    let pick = |r: &Vec<String>| keep.iter().map(|&i| r[i].clone()).collect::<Vec<_>>();
    let mut body: Vec<Vec<String>> = rows.iter().map(pick).collect();
    body.sort();
    (pick(&head), body)
}

/// Run `bin` (the `geese` binary) in `dir`.
fn geese(bin: &Path, dir: &Path, args: &[&str]) -> std::process::Output {
    Command::new(bin).current_dir(dir).args(args).output().expect("run geese")
}

#[test]
fn four_concurrent_shards_merge_into_the_unsharded_campaign() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    std::fs::write(d.join("sharded.toml"), SHARDED).expect("write campaign");
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    // The whole campaign and its four shards, five processes at once.
    let spawn = |args: &[&str]| {
        Command::new(&bin)
            .current_dir(d)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn geese campaign")
    };
    let mut runs = vec![spawn(&["campaign", "-q", "-j", "1", "--db", "whole.sqlite", "sharded.toml"])];
    for i in 1..=4 {
        runs.push(spawn(&["campaign", "-q", "-j", "1", "--shard", &format!("{i}/4"), "sharded.toml"]));
    }
    for r in runs {
        let out = r.wait_with_output().expect("wait");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    }
    // Default names; every trial in exactly one shard.
    let shards: Vec<String> = (1..=4).map(|i| format!("results/sharded.shard-{i}-of-4.sqlite")).collect();
    let counts: Vec<usize> =
        shards.iter().map(|s| Store::open(&d.join(s)).and_then(|s| s.trials()).expect("shard db").len()).collect();
    assert_eq!(counts.iter().sum::<usize>(), 16, "{counts:?}");
    assert!(counts.iter().all(|&n| n > 0), "{counts:?}");

    // Running a shard again resumes it: nothing to run.
    let out = geese(&bin, d, &["campaign", "-q", "--shard", "2/4", "sharded.toml"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(&format!("{} trials planned: {} already stored, 0 run now", counts[1], counts[1])),
        "{stdout}"
    );

    let mut args = vec!["merge", "merged.sqlite"];
    args.extend(shards.iter().map(String::as_str));
    let out = geese(&bin, d, &args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("16 trial(s) added, 0 already there"), "{stdout}");
    assert!(stdout.contains("merged.sqlite now holds 16 trial(s) of the campaign's 16: 16 done, 0 failed"), "{stdout}");
    assert!(stdout.contains("shards merged: 1/4 2/4 3/4 4/4") && !stdout.contains("not merged yet"), "{stdout}");
    // Merging again (a shard twice, too) changes nothing.
    let out = geese(&bin, d, &["merge", "merged.sqlite", &shards[0], &shards[0], &shards[3]]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("0 trial(s) added"), "{out:?}");

    // Export reads the merged database as the unsharded one: the same trials, step rows
    // and learning-step rows, wall-clock columns and row ids aside.
    for db in ["whole", "merged"] {
        let out = geese(&bin, d, &["export", &format!("{db}.sqlite"), "--out", db]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    }
    let not_results = ["id", "session", "wall_seconds", "stage_wall_seconds", "finished_unix"];
    for (file, drop) in
        [("trials.csv", &not_results[..]), ("steps.csv", &["trial"][..]), ("learning_steps.csv", &["trial"][..])]
    {
        let (whole, merged) =
            (csv_without(&d.join("whole").join(file), drop), csv_without(&d.join("merged").join(file), drop));
        assert!(!whole.1.is_empty(), "{file} is empty");
        assert_eq!(whole, merged, "{file}");
    }
    let (head, trials) = csv_without(&d.join("merged/trials.csv"), &not_results);
    assert_eq!(trials.len(), 16);
    assert!(head.contains(&"final_task_pct".to_string()) && head.contains(&"config".to_string()), "{head:?}");
    let manifest = |db: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(d.join(db).join("manifest.json")).expect("manifest"))
            .expect("json")
    };
    let (whole, merged) = (manifest("whole"), manifest("merged"));
    assert_eq!(merged["name"], "sharded");
    assert_eq!(merged["campaign_resolved_digest"], whole["campaign_resolved_digest"]);
    assert_eq!(merged["merged_shards"], "1/4,2/4,3/4,4/4");
    assert!(merged.get("shard").is_none(), "the merged database is no shard");
    let sessions = std::fs::read_to_string(d.join("merged/sessions.csv")).expect("sessions.csv");
    assert_eq!(sessions.lines().count(), 1 + 5, "four shard invocations and the resumed one");

    // The report reads it too.
    let out = geese(&bin, d, &["report", "merged.sqlite", "--no-plots"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// 1 condition × 1 task × 4 seeds of 5 agents × 30 steps.
const TINY: &str = r#"
name = "tiny"
tasks = ["foraging"]
seeds = 4
[base]
steps = 30
[base.world]
agents = 5
[[grid]]
ip = 0.9
"#;

#[test]
fn merge_refuses_other_campaigns_and_files_and_shard_specs_must_be_i_of_n() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    std::fs::write(d.join("tiny.toml"), TINY).expect("write campaign");
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    let ok = |out: std::process::Output| {
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    };
    let fails = |out: std::process::Output, says: &[&str]| {
        assert!(!out.status.success(), "succeeded: {}", String::from_utf8_lossy(&out.stdout));
        let err = String::from_utf8_lossy(&out.stderr);
        for s in says {
            assert!(err.contains(s), "expected '{s}' in: {err}");
        }
    };
    ok(geese(&bin, d, &["campaign", "-q", "--shard", "1/2", "--db", "s1.sqlite", "tiny.toml"]));
    // Shard 2 of the campaign run with other steps: another resolved campaign.
    ok(geese(&bin, d, &["campaign", "-q", "--shard", "2/2", "--steps", "40", "--db", "s2.sqlite", "tiny.toml"]));
    let digest = |db: &str| Store::open(&d.join(db)).and_then(|s| s.meta("campaign_resolved_digest")).expect("meta");
    let (d1, d2) = (digest("s1.sqlite").expect("digest"), digest("s2.sqlite").expect("digest"));
    assert_ne!(d1, d2);
    fails(
        geese(&bin, d, &["merge", "out.sqlite", "s1.sqlite", "s2.sqlite"]),
        &["s2.sqlite is not of the same campaign", &d2, "s1.sqlite", &d1],
    );
    // A shard database takes no other shard.
    fails(
        geese(&bin, d, &["campaign", "-q", "--shard", "2/2", "--db", "s1.sqlite", "tiny.toml"]),
        &["s1.sqlite holds shard 1/2, not shard 2/2"],
    );

    // Files that are no campaign database.
    let conn = rusqlite::Connection::open(d.join("other.sqlite")).expect("sqlite");
    conn.execute_batch("CREATE TABLE things (x INTEGER); INSERT INTO things VALUES (1);").expect("table");
    drop(conn);
    fails(
        geese(&bin, d, &["merge", "out.sqlite", "s1.sqlite", "other.sqlite"]),
        &["other.sqlite is not a campaign database: it has no `meta` table"],
    );
    std::fs::write(d.join("notes.sqlite"), "these are notes, not a database; long enough for a header .....")
        .expect("write");
    fails(geese(&bin, d, &["merge", "out.sqlite", "notes.sqlite"]), &["notes.sqlite is not a campaign database"]);
    fails(geese(&bin, d, &["merge", "other.sqlite", "s1.sqlite"]), &["other.sqlite is not a campaign database"]);
    fails(geese(&bin, d, &["merge", "out.sqlite"]), &["<SHARDS>"]);
    // Nothing was merged by the refused merges.
    assert!(Store::open(&d.join("out.sqlite")).and_then(|s| s.trials()).map(|t| t.is_empty()).unwrap_or(true));

    for (spec, says) in [
        ("5/4", "I = 5 is greater than N = 4"),
        ("0/0", "N must be at least 1"),
        ("0/4", "I counts from 1"),
        ("a/b", "I 'a' is not a whole number"),
        ("3", "expected I/N"),
    ] {
        let quoted = format!("shard '{spec}'");
        fails(
            geese(&bin, d, &["campaign", "-q", "--shard", spec, "--db", "bad.sqlite", "tiny.toml"]),
            &[&quoted, says],
        );
    }
    assert!(!d.join("bad.sqlite").exists());
    let help = geese(&bin, d, &["campaign", "--help"]);
    assert!(String::from_utf8_lossy(&help.stdout).contains("I counts from 1"), "{help:?}");
}
