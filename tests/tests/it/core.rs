//! The in-process simulation core end to end: determinism, learning, CLI contract.
use geese_orchestrator::run::config::RunConfig;
use geese_orchestrator::Trial;
use geese_proto::StepReport;
use geese_world::Task;
use std::process::Command;

fn small(task: Task, seed: u64, agents: u32, steps: u64) -> RunConfig {
    let mut c = RunConfig { steps, seed, ..Default::default() };
    c.world.task = task;
    c.world.agents = agents;
    c
}

fn reports(cfg: RunConfig) -> Vec<StepReport> {
    let steps = cfg.steps;
    let spec = cfg.validate().expect("valid config");
    let mut t = Trial::new(&spec).expect("world builds");
    (0..steps).map(|_| t.step()).collect()
}

#[test]
fn same_seed_same_trajectory_other_seed_other_trajectory() {
    let a = reports(small(Task::Foraging, 11, 30, 300));
    let b = reports(small(Task::Foraging, 11, 30, 300));
    let c = reports(small(Task::Foraging, 12, 30, 300));
    assert_eq!(a, b);
    assert_ne!(a.iter().map(|r| r.digest).collect::<Vec<_>>(), c.iter().map(|r| r.digest).collect::<Vec<_>>());
}

/// Issue 29: one trial on several threads steps exactly as on one, for every
/// algorithm, a fixed population, and a crowded arena where every agent runs a genetic
/// step every step (the work is then spread most unevenly over the threads).
#[test]
fn a_trial_steps_the_same_on_1_2_and_4_threads() {
    use geese_agent::program::{Algorithm, Phase};
    let on = |mut c: RunConfig, threads: u32| {
        c.threads = Some(threads);
        reports(c)
    };
    let mut cases = vec![small(Task::Foraging, 5, 100, 300), small(Task::Nest, 6, 60, 200)];
    let mut crowd = small(Task::Foraging, 7, 1500, 12);
    crowd.world.width = 80;
    crowd.world.height = 80;
    cases.push(crowd);
    for algorithm in [Algorithm::GeeseBt, Algorithm::MultiGeese] {
        let mut c = small(Task::Foraging, 8, 40, 250);
        c.algorithm = algorithm;
        if algorithm == Algorithm::MultiGeese {
            c.phase = Some(Phase::Collect);
        }
        cases.push(c);
    }
    let mut lossy = small(Task::Foraging, 9, 50, 200);
    lossy.gene_loss = 0.3;
    lossy.perturbations = vec![geese_orchestrator::run::config::Scheduled {
        at: 100,
        change: geese_proto::Perturbation::KillFraction(0.3),
    }];
    cases.push(lossy);
    for c in cases {
        let one = on(c.clone(), 1);
        assert!(one.iter().any(|r| r.genetic_steps > 0), "no genetic step: the case checks nothing");
        for threads in [2, 4] {
            let many = on(c.clone(), threads);
            let first = one.iter().zip(&many).position(|(a, b)| a != b);
            assert!(first.is_none(), "{threads} threads differ from 1 at step {:?} ({:?})", first.map(|i| i + 1), c);
            assert_eq!(one.len(), many.len());
        }
    }
}

/// Issue 30.4: a trial whose task changes twice (foraging → nest → foraging, union
/// grammar) steps the same on 1, 2 and 4 threads, and the task % follows the switch:
/// it drops to 0 right after it, and items of the new task get delivered.
#[test]
fn a_trial_with_task_switches_steps_the_same_on_1_2_and_4_threads() {
    use geese_orchestrator::run::config::Scheduled;
    use geese_proto::Perturbation::SwitchTask;
    // Seed 4 delivers in both tasks in time (seeds 1-8 checked; most deliver in only one).
    let mut c = small(Task::Foraging, 4, 100, 2100);
    c.perturbations = vec![
        Scheduled { at: 1200, change: SwitchTask(Task::Nest) },
        Scheduled { at: 2000, change: SwitchTask(Task::Foraging) },
    ];
    let on = |threads: u32| {
        let mut c = c.clone();
        c.threads = Some(threads);
        reports(c)
    };
    let one = on(1);
    assert!(one.iter().any(|r| r.genetic_steps > 0), "no genetic step: the case checks nothing");
    assert!(one[1199].task_pct > 0.0, "nothing delivered before the switch: the drop checks nothing");
    assert_eq!((one[1200].step, one[1200].task_pct), (1201, 0.0), "the nest task starts from 0 after step 1200");
    assert!(one[1999].task_pct > 0.0, "no debris delivered after the switch to nest");
    assert_eq!(one[2000].task_pct, 0.0, "foraging again starts from 0");
    for threads in [2, 4] {
        assert_eq!(one, on(threads), "{threads} threads differ from 1");
    }
}

/// Issue 30: a switch beyond the run, a switch to the running task, a learner grammar
/// that cannot express the new task and an unknown mutation rule are refused with
/// messages naming the value; a fixed population whose trees name only the old task's
/// objects is accepted, with a note.
#[test]
fn bad_switches_and_mutation_rules_are_refused_by_name() {
    use geese_orchestrator::run::config::Scheduled;
    use geese_proto::Perturbation::SwitchTask;
    let refused = |c: RunConfig| c.validate().map(|_| ()).unwrap_err().to_string();
    let with = |at: u64, to: Task| {
        let mut c = small(Task::Foraging, 1, 10, 1000);
        c.perturbations = vec![Scheduled { at, change: SwitchTask(to) }];
        c
    };
    let e = refused(with(1000, Task::Nest));
    assert!(e.starts_with("perturbations[0].at: SwitchTask at step 1000 is beyond the run"), "{e}");
    let e = refused(with(200, Task::Foraging));
    assert_eq!(
        e,
        "perturbations[0].change: SwitchTask to foraging at step 200: the world already runs the foraging task then"
    );
    let mut twice = with(200, Task::Nest);
    twice.perturbations.push(Scheduled { at: 100, change: SwitchTask(Task::Nest) });
    let e = refused(twice);
    assert!(e.starts_with("perturbations[0].change: SwitchTask to nest at step 200"), "{e}");
    let mut narrow = with(200, Task::Nest);
    narrow.grammar = Some("betr-foraging-avoid".into());
    let e = refused(narrow);
    assert!(
        e.contains("grammar betr-foraging-avoid cannot express the nest task (it lacks Boundary and Debris)"),
        "{e}"
    );
    assert_eq!(with(200, Task::Nest).validate().expect("valid").grammar_name, "betr-union-avoid");
    let e = RunConfig::from_toml("[[perturbations]]\nat = 5\nchange = { SwitchTask = \"garden\" }\n").unwrap_err();
    assert!(e.contains("garden"), "{e}");
    let e = RunConfig::from_toml("[learner]\nmutation = \"heat\"\n").unwrap_err();
    assert!(e.contains("heat"), "{e}");
    let mut fixed = with(200, Task::Nest);
    fixed.population =
        Some(format!("{}/../populations/foraging-five-behaviours.json", env!("CARGO_MANIFEST_DIR")).into());
    let spec = fixed.validate().expect("a fixed population meets the new task as it is");
    assert!(
        spec.notes.iter().any(|n| n.contains("SwitchTask to nest") && n.contains("Boundary, Debris")),
        "{:?}",
        spec.notes
    );
    // The geese CLI names a bad --mutation and a bad task in a config file.
    let geese = geese_tests::bin_path("geese-orchestrator", "geese");
    let out = Command::new(&geese).args(["run", "--steps", "5", "-q", "--mutation", "heat"]).output().expect("runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--mutation: unknown mutation rule 'heat'"));
}

/// Issue 30.3: the stress mutation rule leaves the default trajectory alone when not
/// chosen, and changes it when chosen (the mutation draws differ once an agent's
/// fitness has stalled), the same on 1 and 2 threads.
#[test]
fn stress_mutation_changes_the_trajectory_only_when_chosen() {
    let base = small(Task::Foraging, 4, 60, 600);
    let fixed = reports(base.clone());
    let mut named = base.clone();
    named.learner.mutation = geese_agent::MutationRule::Fixed;
    assert_eq!(fixed, reports(named));
    let mut stress = base.clone();
    stress.learner.mutation = geese_agent::MutationRule::Stress;
    let one = reports(stress.clone());
    assert_ne!(fixed, one, "the stress rule changed nothing");
    stress.threads = Some(2);
    assert_eq!(one, reports(stress));
}

#[test]
fn learning_happens_and_lateral_transfer_switch_works() {
    let on = reports(small(Task::Foraging, 3, 100, 400));
    let genetic: u32 = on.iter().map(|r| r.genetic_steps).sum();
    assert!(genetic > 0, "no storage-triggered genetic step in 400 steps");
    assert!(on.iter().any(|r| r.lt_mean > 0.0));
    let mut cfg = small(Task::Foraging, 3, 100, 400);
    cfg.lateral_transfer = false;
    let off = reports(cfg);
    assert_eq!(off.iter().map(|r| r.genetic_steps).sum::<u32>(), 0);
    assert!(off.iter().all(|r| r.lt_mean == 0.0));
}

#[test]
fn bad_parameters_are_named() {
    let mut c = RunConfig { ip: 1.5, ..Default::default() };
    assert!(c.clone().validate().unwrap_err().to_string().contains("ip"));
    c.ip = 0.5;
    c.learner.st = Some(3);
    assert!(c.clone().validate().unwrap_err().to_string().contains("st"));
    c.learner.st = Some(7);
    c.world.grid = 7;
    assert!(c.clone().validate().unwrap_err().to_string().contains("grid"));
    c.world.grid = 10;
    c.world.agents = 0;
    assert!(c.clone().validate().unwrap_err().to_string().contains("agents"));
}

/// Issue 31: with `RUST_BACKTRACE=1` (common on developers' machines) a user error is
/// still just its message.
#[test]
fn a_user_error_prints_no_backtrace_even_with_rust_backtrace_set() {
    let bin = geese_tests::bin_path("geese-orchestrator", "geese");
    for args in [&["run", "--ip", "2", "--steps", "1", "-q"][..], &["run", "--config", "/nonexistent.toml"]] {
        let out = Command::new(&bin).args(args).env("RUST_BACKTRACE", "1").output().expect("run geese");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(err.starts_with("Error: ") && !err.contains("backtrace") && err.lines().count() == 1, "{err}");
    }
}

/// Issue 31: `geese run --view` without `--step-rate` starts paced (20 steps/s), so a
/// first look shows the run, not its last frame: 30 steps take at least 1.45 s.
#[test]
fn a_viewed_run_starts_paced() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("r");
    let t = std::time::Instant::now();
    let (ok, stdout, err) =
        geese(&["run", "--view", "--agents", "5", "--steps", "30", "-q", "--out", out.to_str().expect("utf8")]);
    let took = t.elapsed();
    assert!(ok, "{err}");
    assert!(stdout.contains("pace: 20 steps/s"), "{stdout}");
    assert!(took >= std::time::Duration::from_millis(1400), "30 steps took {took:?}: not paced");
}

fn geese(args: &[&str]) -> (bool, String, String) {
    // Built (or found up to date) once per test process: each `cargo build` check costs
    // about 0.4 s, and a test may run the binary several times.
    static BIN: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    let bin = BIN.get_or_init(|| geese_tests::bin_path("geese-orchestrator", "geese"));
    let out = Command::new(bin).args(args).output().expect("run geese");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

#[test]
fn cli_grammar_map_matches_golden_vectors() {
    let (ok, out, err) = geese(&[
        "grammar",
        "map",
        "--grammar",
        "betr-foraging-avoid",
        "--genome",
        "1213,1114,267,757,1875,1236,970,1281,1189,134,1240,26,1861,1715,960,531,1128,479,392,1468,963,1107",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect("one JSON object");
    assert_eq!(v["valid"], true);
    assert_eq!(v["used_codons"], 12);
    assert_eq!(v["depth"], 10);
    assert_eq!(v["diversity"], 5.5556);
    assert_eq!(
        v["phenotype"],
        "[?xml version=%1.0% encoding=%UTF-8%?][Sequence][Selector][PostCnd]DummyNode[/PostCnd][Sequence][Sequence][Cnstr]IsDropable_Hub[/Cnstr][/Sequence][Act]Explore_0_Avoid[/Act][/Sequence][/Selector][/Sequence]"
    );
    let (ok, out, _) = geese(&[
        "grammar",
        "map",
        "--grammar",
        "betr-foraging-avoid",
        "--genome",
        "0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0",
    ]);
    assert!(ok);
    assert_eq!(out.trim(), r#"{"valid":false}"#);
    let (ok, out, err) = geese(&[
        "grammar",
        "map",
        "--grammar",
        "geese-bt-foraging",
        "--genome",
        "1774,927,1808,570,1290,194,631,186,1220,1981,1341,1279,1704,169,74,1802,1845,1594,671,1221,1064,1641,602,1023,9,1356,174,936,1341,569,833,1128,1908",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect("json");
    assert_eq!(
        (v["used_codons"].as_u64(), v["depth"].as_u64(), v["diversity"].as_f64()),
        (Some(22), Some(10), Some(13.8889))
    );
}

/// The genome of REFERENCE §4.5's worked tree.
const WORKED_GENOME: &str =
    "1027,25,1038,773,1037,793,953,372,1146,1579,473,816,219,562,786,606,897,1539,1964,164,1807,896";

#[test]
fn cli_grammar_tree_prints_the_worked_tree() {
    let (ok, out, err) = geese(&["grammar", "tree", "--grammar", "betr-foraging-avoid", "--genome", WORKED_GENOME]);
    assert!(ok, "{err}");
    let expected = "Selector\n  Selector\n    Sequence\n      IsCarrying[Food] (PostCnd)\n    Sequence\n      Sequence\n        Inverter\n          IsVisitedBefore[Sites] (PreCnd)\n        MoveAway[Hub] (Act)\n";
    assert_eq!(out, expected);
}

/// Issue 19: `geese grammar metrics` prints Table 2's values (REFERENCE §8.3) as a table
/// and as JSON; a missing file or a grammar that does not parse is named.
#[test]
fn cli_grammar_metrics_prints_table_2() {
    let (ok, out, err) = geese(&["grammar", "metrics", "--grammar", "betr-table2-reference"]);
    assert!(ok, "{err}");
    for line in ["terminals (T)             30", "Halstead effort (HAL)     283.62", "tree impurity (TIMP) %    7.60"] {
        assert!(out.contains(line), "{line:?} not in\n{out}");
    }
    let (ok, out, err) = geese(&["grammar", "metrics", "--grammar", "geese-bt-foraging", "--json"]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect("one JSON object");
    assert_eq!(v["grammar"], "geese-bt-foraging");
    let ints = ["T", "N", "MCC", "NSLEV", "DEP"].map(|k| v[k].as_u64().unwrap_or(u64::MAX));
    assert_eq!(ints, [24, 11, 27, 4, 6]);
    assert_eq!((v["RHS"].as_f64(), v["HAL"].as_f64()), (Some(4.09), Some(132.94)));
    let two = |k: &str| format!("{:.2}", v[k].as_f64().unwrap_or(f64::NAN));
    assert_eq!((two("TIMP"), two("CLEV")), ("15.56".to_string(), "36.36".to_string()));

    let (ok, _, err) = geese(&["grammar", "metrics", "--grammar", "/nonexistent/g.bnf"]);
    assert!(!ok && err.contains("/nonexistent/g.bnf") && !err.contains("panicked"), "{err}");
    let dir = tempfile::tempdir().expect("tmp");
    let bad = dir.path().join("bad.bnf");
    std::fs::write(&bad, "<s> ::= <missing>\n").expect("write");
    let (ok, _, err) = geese(&["grammar", "metrics", "--grammar", bad.to_str().expect("utf8")]);
    assert!(!ok && err.contains("bad.bnf") && err.contains("<missing>"), "{err}");
}

/// Issue 19: `geese grammar tree` draws a genome or a population member as text, DOT or
/// SVG, into a file with --output; a bad member index or format is named.
#[test]
fn cli_grammar_tree_draws_pictures_of_population_members() {
    let pops = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../populations");
    let multi = pops.join("fig9-multi-geese-foraging.json");
    let multi = multi.to_str().expect("utf8");
    let dir = tempfile::tempdir().expect("tmp");
    let svg = dir.path().join("member.svg");
    let args = ["grammar", "tree", "--population", multi, "--member", "0", "--format", "svg", "--output"];
    let (ok, out, err) = geese(&[&args[..], &[svg.to_str().expect("utf8")]].concat());
    assert!(ok && out.is_empty(), "{err}");
    let svg = std::fs::read_to_string(&svg).expect("written");
    assert!(svg.starts_with("<svg ") && svg.trim_end().ends_with("</svg>"));
    // The controllers are in place: the GeneDict's gene trees hold their actions.
    assert!(svg.contains("ExploreNormal (Act)") && svg.contains("CompositeDrop[Food] (Act)"), "{svg}");
    let (ok, text, err) = geese(&["grammar", "tree", "--population", multi, "--member", "0"]);
    assert!(ok, "{err}");
    assert_eq!(svg.matches("<g>").count(), text.lines().count(), "one group per node");

    let (ok, dot, err) =
        geese(&["grammar", "tree", "--grammar", "betr-foraging-avoid", "--genome", WORKED_GENOME, "--format", "dot"]);
    assert!(ok, "{err}");
    assert!(dot.starts_with("digraph bt {") && dot.contains(r#"n8 [label="MoveAway[Hub] (Act)""#), "{dot}");

    let five = pops.join("foraging-five-behaviours.json");
    let five = five.to_str().expect("utf8");
    let (ok, _, err) = geese(&["grammar", "tree", "--population", five, "--member", "5"]);
    assert!(!ok && err.contains("has no member 5: it has 5") && !err.contains("panicked"), "{err}");
    let (ok, _, err) = geese(&["grammar", "tree", "--population", five, "--member", "0", "--format", "png"]);
    assert!(!ok && err.contains("'png'") && err.contains("text, dot or svg"), "{err}");
    let (ok, _, err) = geese(&["grammar", "tree", "--population", five, "--member", "first"]);
    assert!(!ok && err.contains("--member"), "{err}");
}

#[test]
fn cli_rejects_bad_input_with_a_named_error() {
    let (ok, _, err) = geese(&["grammar", "map", "--grammar", "betr-foraging-avoid", "--genome", "1,2,x"]);
    assert!(!ok && err.contains("codon 3"), "{err}");
    let (ok, _, err) = geese(&["grammar", "map", "--grammar", "/nonexistent.bnf", "--genome", "1"]);
    assert!(!ok && err.contains("/nonexistent.bnf"), "{err}");
    let (ok, _, err) = geese(&["run", "--ip", "2", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("ip"), "{err}");
    let (ok, _, err) = geese(&["run", "--st", "2", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("st"), "{err}");
    let (ok, _, err) = geese(&["run", "--gs", "7", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("grid"), "{err}");
    let (ok, _, err) = geese(&["run", "--agents", "0", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("agents"), "{err}");
    let (ok, _, err) = geese(&["run", "--task", "flying", "--steps", "1"]);
    assert!(!ok && err.contains("flying"), "{err}");
    let (ok, _, err) = geese(&["run", "--threads", "0", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("threads: 0"), "{err}");
    let (ok, _, err) = geese(&["run", "--threads", "5", "--agents", "4", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("threads: 5 is more than the 4 agents"), "{err}");
    let (ok, _, err) = geese(&["run", "--threads", "2", "--schedule", "sequential", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("threads: 2") && err.contains("1 thread"), "{err}");
    // Refused before any process starts: 100,000 agent processes fit in no machine here.
    let (ok, _, err) = geese(&["run", "--processes", "100000", "--agents", "100000", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("--processes 100000") && err.contains("available"), "{err}");
    let (ok, _, err) = geese(&["run", "--threads", "2", "--processes", "2", "--steps", "1", "-q"]);
    assert!(!ok && err.contains("--threads 2") && err.contains("--processes"), "{err}");
    let dir = tempfile::tempdir().expect("tmp");
    let cfg = dir.path().join("bad.toml");
    std::fs::write(&cfg, "steps = 3\n[world]\nwidht = 100\n").expect("write");
    let (ok, _, err) = geese(&["run", "--config", cfg.to_str().expect("utf8"), "-q"]);
    assert!(!ok && err.contains("widht"), "{err}");
}

#[test]
fn cli_run_writes_csv_and_manifest() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("r");
    let (ok, stdout, err) =
        geese(&["run", "--agents", "20", "--steps", "50", "--seed", "4", "-q", "--out", out.to_str().expect("utf8")]);
    assert!(ok, "{err}");
    assert!(stdout.contains("final task %"), "{stdout}");
    let csv = std::fs::read_to_string(out.join("steps.csv")).expect("csv");
    assert_eq!(csv.lines().count(), 51);
    assert!(csv.starts_with("step,task_pct"));
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).expect("manifest")).expect("json");
    assert_eq!(m["seed"], 4);
    assert_eq!(m["config"]["world"]["agents"], 20);
    assert!(m["versions"]["git_revision"].is_string());
}

/// Issue 19: `--locality 5:20` counts every live agent once after each of steps 5–20,
/// both included; bad windows are errors naming the value; `geese locality` draws it.
#[test]
fn cli_run_locality_counts_live_agents_times_steps_in_the_window() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("r");
    let o = out.to_str().expect("utf8");
    let (ok, stdout, err) =
        geese(&["run", "--agents", "10", "--steps", "30", "--seed", "4", "--locality", "5:20", "-q", "--out", o]);
    assert!(ok, "{err}");
    assert!(stdout.contains("locality map"), "{stdout}");
    let text = std::fs::read_to_string(out.join("locality.csv")).expect("locality.csv");
    let counts = geese_world::locality::parse_csv(&text).expect("well-formed");
    assert!(text.starts_with("x,y,class,count\n"));
    assert_eq!(counts.iter().map(|c| c.count).sum::<u64>(), 10 * 16);
    assert!(counts.windows(2).all(|w| (w[0].x, w[0].y, w[0].class) < (w[1].x, w[1].y, w[1].class)));
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).expect("manifest")).expect("json");
    let l = &m["locality"];
    assert_eq!((l["window"].as_str(), l["from"].as_u64(), l["to"].as_u64()), (Some("5:20"), Some(5), Some(20)));
    assert_eq!(l["steps_counted"], 16);
    assert_eq!(m["config"]["locality"], "5:20");
    assert!(l["landmarks"].as_array().expect("landmarks").iter().any(|x| x["kind"] == "Hub"));
    // One bad window through the CLI (each `geese` call costs a cargo check of the
    // binary); config::tests names every kind.
    let (ok, _, err) = geese(&["run", "--agents", "2", "--steps", "30", "--locality", "5:3", "-q", "--out", o]);
    assert!(!ok && err.contains("locality: \"5:3\": FROM 5 comes after TO 3"), "{err}");
    let (ok, stdout, err) = geese(&["locality", o]);
    assert!(ok, "{err}");
    assert!(stdout.contains("agent-steps by class"), "{stdout}");
    for ext in ["png", "svg"] {
        assert!(std::fs::metadata(out.join(format!("locality.{ext}"))).expect("figure").len() > 1000);
    }
    let (ok, _, err) = geese(&["locality", dir.path().join("nothing").to_str().expect("utf8")]);
    assert!(!ok && err.contains("nothing"), "{err}");
}

/// The shipped locality world (configs/locality.toml) is the reference's (REFERENCE §1.4).
#[test]
fn the_shipped_locality_config_is_the_reference_locality_world() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/locality.toml");
    let spec = RunConfig::from_file(&path).expect("parses").validate().expect("valid");
    let c = &spec.config;
    assert_eq!((c.world.agents, c.ip, c.learner.st, c.learner.stagnation_explore), (100, 0.85, Some(10), 0));
    assert_eq!(spec.grammar_name, "betr-foraging-avoid");
    assert_eq!(spec.locality.map(|w| (w.from, w.to)), Some((1, 3000)));
    let w = geese_world::World::new(c.world.clone(), c.seed).expect("world");
    let at = |k| w.objects().filter(|o| o.info.kind == k).map(|o| (o.info.pos.x, o.info.pos.y)).collect::<Vec<_>>();
    assert_eq!(at(geese_proto::ObjectKind::Obstacles), [(-30, -30), (30, -30), (30, 30), (-15, 0)]);
    assert_eq!(at(geese_proto::ObjectKind::Sites), [(-30, 30)]);
    assert!(w.bodies().iter().all(|b| (b.pos.x, b.pos.y) == (0, 0)));
}

/// Issue 16, bad input: an unknown algorithm, a population of the wrong grammar or task,
/// an empty sample, a GeneDict key that is no action class, a phenotype that does not
/// build — each a clear error naming the value, never a panic.
#[test]
fn cli_rejects_bad_algorithms_and_populations_by_name() {
    let pops = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../populations");
    let five = pops.join("foraging-five-behaviours.json");
    let five = five.to_str().expect("utf8");
    // Refused with a message, not a panic.
    let refused = |args: &[&str]| {
        let (ok, _, err) = geese(args);
        assert!(!ok && !err.contains("panicked"), "{err}");
        err
    };
    let err = refused(&["run", "--algorithm", "betr", "--steps", "1", "-q"]);
    assert!(err.contains("'betr'") && err.contains("multi-geese"), "{err}");
    let err = refused(&["run", "--population", five, "--sample", "0.001", "--steps", "1", "-q"]);
    assert!(err.contains("sample 0.001 of 5 members selects none"), "{err}");
    let err = refused(&["run", "--population", five, "--task", "nest", "--steps", "1", "-q"]);
    assert!(err.contains("foraging task") && err.contains("nest"), "{err}");
    let err = refused(&["run", "--population", five, "--grammar", "geese-bt-foraging", "--steps", "1", "-q"]);
    assert!(err.contains("[PostCnd]") && err.contains("geese-bt-foraging"), "{err}");
    let err = refused(&["run", "--phase", "combine", "--steps", "1", "-q"]);
    assert!(err.contains("phase"), "{err}");
    let err = refused(&["run", "--terms", "E+Q", "--steps", "1", "-q"]);
    assert!(err.contains("'Q'"), "{err}");
    let dir = tempfile::tempdir().expect("tmp");
    let write = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).expect("write");
        p.to_str().expect("utf8").to_string()
    };
    let bad_key = write(
        "bad-key.json",
        r#"{"grammar": "multi-collect-foraging", "members": [{"phenotype": "x", "agent": 0,
            "gene_dict": {"Fly": {"phenotype": "[Sequence][Sequence][Act]Explore_0_Normal[/Act][/Sequence][/Sequence]"}}}]}"#,
    );
    let err = refused(&[
        "run",
        "--algorithm",
        "multi-geese",
        "--phase",
        "combine",
        "--collect-population",
        &bad_key,
        "--steps",
        "1",
        "-q",
    ]);
    assert!(err.contains("GeneDict key 'Fly'"), "{err}");
    let bad_leaf = write(
        "bad-leaf.json",
        r#"{"grammar": "betr-foraging-avoid", "members": [{"phenotype": "[Sequence][Sequence][Act]Fly_Hub[/Act][/Sequence][/Sequence]"}]}"#,
    );
    let err = refused(&["run", "--population", &bad_leaf, "--steps", "1", "-q"]);
    assert!(err.contains("member 0") && err.contains("'Fly'"), "{err}");
    let err = refused(&["run", "--population", "/nonexistent/pop.json", "--steps", "1", "-q"]);
    assert!(err.contains("/nonexistent/pop.json"), "{err}");
}

/// Issue 16: the shipped five-behaviour populations run in one command, and a learning
/// run writes its population, which runs again as a fixed population.
#[test]
fn cli_populations_round_trip() {
    let pops = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../populations");
    let dir = tempfile::tempdir().expect("tmp");
    for task in ["foraging", "nest"] {
        let five = pops.join(format!("{task}-five-behaviours.json"));
        let out = dir.path().join(task);
        let (ok, stdout, err) = geese(&[
            "run",
            "--task",
            task,
            "--population",
            five.to_str().expect("utf8"),
            "--steps",
            "400",
            "-q",
            "--out",
            out.to_str().expect("utf8"),
        ]);
        assert!(ok, "{err}");
        assert!(stdout.contains("reached 80 % at step"), "{task}: the hand-designed controller works: {stdout}");
        assert!(!out.join("population.json").exists(), "a fixed run writes no population");
    }
    let learn = dir.path().join("learn");
    let (ok, _, err) = geese(&[
        "run",
        "--algorithm",
        "geese-bt",
        "--agents",
        "12",
        "--steps",
        "60",
        "-q",
        "--out",
        learn.to_str().expect("utf8"),
    ]);
    assert!(ok, "{err}");
    let pop = learn.join("population.json");
    let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&pop).expect("population")).expect("json");
    assert_eq!(p["grammar"], "geese-bt-foraging");
    assert_eq!(p["members"].as_array().map(Vec::len), Some(12));
    let (ok, stdout, err) = geese(&[
        "run",
        "--population",
        pop.to_str().expect("utf8"),
        "--steps",
        "20",
        "-q",
        "--out",
        dir.path().join("fixed").to_str().expect("utf8"),
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("final task %"), "{stdout}");
}
