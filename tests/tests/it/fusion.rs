//! Issue 30.1–30.2: the combine phase's fusion variants and one-phase fusion are
//! selectable by name (flag, config key, campaign knob), deterministic, and change what
//! they say they change — and nothing before it.
use geese_agent::learner::Fusion;
use geese_agent::program::{is_complete, Algorithm, Phase, Population};
use geese_orchestrator::campaigns::campaign::Campaign;
use geese_orchestrator::run::config::RunConfig;
use geese_orchestrator::Trial;
use geese_proto::StepReport;
use std::path::PathBuf;

fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// A 100-agent combine phase of `steps` steps starting from the GeneDicts of the shipped
/// Multi-GEESE foraging population (its wirings start random, its controllers forage).
fn combine(fusion: Fusion, steps: u64) -> RunConfig {
    let mut c = RunConfig { steps, seed: 4, algorithm: Algorithm::MultiGeese, ..Default::default() };
    c.phase = Some(Phase::Combine);
    c.collect_population = Some(repo("populations/fig9-multi-geese-foraging.json"));
    c.learner.fusion = fusion;
    c
}

fn run(cfg: RunConfig) -> (Vec<StepReport>, Trial) {
    let steps = cfg.steps;
    let spec = cfg.validate().expect("valid config");
    let mut t = Trial::new(&spec).expect("world builds");
    let reps = (0..steps).map(|_| t.step()).collect();
    (reps, t)
}

#[test]
fn fusion_variants_are_named_and_unknown_names_list_the_valid_ones() {
    for v in Fusion::ALL {
        assert_eq!(v.name().parse::<Fusion>(), Ok(v));
        let cfg = RunConfig::from_toml(&format!("[learner]\nfusion = \"{}\"\n", v.name())).expect("config key");
        assert_eq!(cfg.learner.fusion, v);
    }
    assert_eq!(RunConfig::default().learner.fusion, Fusion::Faithful, "the faithful port is the default");
    let e = "fast".parse::<Fusion>().unwrap_err();
    assert!(
        e.contains("'fast'")
            && e.contains("faithful, delivery, keep-deliverers, delivery-keep, patient, patient-delivery"),
        "{e}"
    );
    let e = RunConfig::from_toml("[learner]\nfusion = \"fast\"\n").unwrap_err();
    assert!(e.contains("fast") && e.contains("delivery-keep"), "{e}");
    // The campaign knob: levels resolve, an unknown one is named with the valid ones.
    let text = |level: &str| {
        format!(
            "name = \"f\"\ntasks = [\"foraging\"]\nseeds = 1\n[base]\nsteps = 10\n[[grid]]\n\
             algorithm = \"multi-geese\"\nfusion = [\"{level}\", \"faithful\"]\n"
        )
    };
    let c = Campaign::from_toml(&text("keep-deliverers"), "f").expect("campaign");
    let plan = c.plan();
    assert_eq!(c.spec(&plan[0]).config.learner.fusion, Fusion::KeepDeliverers);
    assert_eq!(c.spec(&plan[1]).config.learner.fusion, Fusion::Faithful);
    let e = Campaign::from_toml(&text("fast"), "f").unwrap_err().to_string();
    assert!(e.contains("fusion") && e.contains("'fast'") && e.contains("delivery-keep"), "{e}");
    // The flag.
    let out = std::process::Command::new(geese_tests::bin_path("geese-orchestrator", "geese"))
        .args(["run", "--fusion", "fast", "--steps", "1", "-q"])
        .output()
        .expect("run geese");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("'fast'") && err.contains("keep-deliverers"), "{err}");
}

/// Every variant is deterministic and changes the combine phase. The delivery and keep
/// variants leave it exactly as the faithful port runs it until a combine agent first
/// delivers (they act only on the weight an agent delivered under its wiring); the
/// patient ones let no wiring take part in a genetic step before it is
/// [`geese_agent::learner::PATIENCE`] steps old.
#[test]
fn fusion_variants_are_deterministic_and_act_only_from_the_first_delivery() {
    let steps = 1500;
    let (faithful, _) = run(combine(Fusion::Faithful, steps));
    let first_delivery =
        faithful.iter().position(|r| r.task_pct > 0.0).expect("the faithful combine phase delivers: checks nothing");
    for v in Fusion::ALL.into_iter().filter(|v| *v != Fusion::Faithful) {
        let (a, _) = run(combine(v, steps));
        let (b, _) = run(combine(v, steps));
        assert_eq!(a, b, "{v}: same seed, same trajectory");
        let diverge = faithful.iter().zip(&a).position(|(x, y)| x != y);
        let diverge = diverge.unwrap_or_else(|| panic!("{v}: no different from the faithful port in {steps} steps"));
        if v.is_patient() {
            // A wiring is `age` steps old after its `age`-th step: at step PATIENCE the
            // first ones may take part.
            let young = &a[..geese_agent::learner::PATIENCE as usize - 1];
            assert!(young.iter().all(|r| r.genetic_steps == 0), "{v}: a genetic step before any wiring was old enough");
            assert!(faithful[..young.len()].iter().any(|r| r.genetic_steps > 0), "faithful: checks nothing");
            assert!(a.iter().any(|r| r.genetic_steps > 0), "{v}: no genetic step at all");
        } else {
            assert!(
                diverge >= first_delivery,
                "{v} departs at step {} before the first delivery ({})",
                diverge + 1,
                first_delivery + 1
            );
        }
    }
}

/// One-phase fusion: agents collect, and only an agent whose GeneDict is complete and
/// has settled starts wiring; with a settling time longer than the run none does.
#[test]
fn one_phase_agents_wire_only_once_their_gene_dict_is_complete_and_settled() {
    let one = |settle: u32| {
        let mut c = RunConfig { steps: 900, seed: 2, algorithm: Algorithm::MultiGeese, ..Default::default() };
        c.phase = Some(Phase::One);
        c.world.agents = 60;
        c.learner.one_phase_settle = settle;
        c
    };
    assert_eq!("one".parse::<Phase>(), Ok(Phase::One));
    let wiring = |t: &Trial| {
        t.members()
            .into_iter()
            .filter(|m| {
                m.phenotype.contains("[Act]ExploreNormal[/Act]")
                    || m.phenotype.contains("[Act]CompositeDrop[/Act]")
                    || m.phenotype.contains("[Act]CompositeSingleCarry[/Act]")
                    || m.phenotype.contains("[Act]MoveTowardsNormal[/Act]")
                    || m.phenotype.contains("[Act]MoveAwayNormal[/Act]")
            })
            .collect::<Vec<_>>()
    };
    let (a, ta) = run(one(100));
    let (b, _) = run(one(100));
    assert_eq!(a, b, "deterministic");
    let wired = wiring(&ta);
    assert!(!wired.is_empty(), "no agent started wiring in 900 steps with a settling time of 100");
    for m in &wired {
        assert!(is_complete(m.gene_dict.as_ref().expect("a wiring agent has its GeneDict")), "{m:?}");
    }
    let (_, never) = run(one(10_000));
    assert!(wiring(&never).is_empty(), "a settling time longer than the run: every agent still collects");
    // The run's population round-trips as a file.
    let spec = one(100).validate().expect("valid");
    let pop: Population = spec.population(ta.members());
    assert_eq!(Population::from_json(&pop.to_json()).expect("parses").members.len(), 60);
    assert_eq!(spec.stage, "one-phase");
}
