//! REFERENCE §6.1–6.5: the learner's per-step order, the stagnation rule, the IP "more
//! than one survivor" rule and the R/fitness update.
//!
//! Each learner here evolves a one-phenotype grammar (`<root>` has a single
//! alternative), so its behaviour tree — and hence B — is known exactly and stays the
//! same through genetic steps. The tests drive it through the public sans-IO API: a
//! hand-made percept per step places the agent (and so fixes the cells it visits, E),
//! sets the lateral-transfer regime, and lists the cell-mates whose genes arrive.
use super::{geom, HUB, ME, SEED};
use crate::ge::{self, GeParams, Grammar};
use crate::grammars;
use crate::learner::{FitnessCell, FitnessVariant, GeneCache, Learner, LearnerConfig, SharedGene, Triggers};
use crate::program::{self, FitnessTerms, GeneDict, Role, StoredGene};
use geese_proto::seed::{derive, Owner, Purpose};
use geese_proto::{
    AgentId, AgentPublic, GeneMapping, GeneMsg, GeneticTrigger, Intent, ObjectInfo, ObjectKind, Percept, Pos, Regime,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

/// Selector[PostCnd DummyNode]: B = 1 every tick; no motion.
const ONE_SELECTOR: &str = "[Selector][PostCnd]DummyNode[/PostCnd][/Selector]";
/// Sequence[Selector[IsVisitedBefore_Hub], Selector[DummyNode]]: B = 2 for an agent that
/// knows the hub; no motion.
const TWO_SELECTORS: &str =
    "[Sequence][Selector][PostCnd]IsVisitedBefore_Hub[/PostCnd][/Selector][Selector][PostCnd]DummyNode[/PostCnd][/Selector][/Sequence]";

/// A grammar whose only phenotype is `phenotype`.
fn grammar_of(phenotype: &str) -> Arc<Grammar> {
    let text = format!("<s> ::= [?xml version=%1.0% encoding=%UTF-8%?]<root>\n<root> ::= {phenotype}\n");
    Arc::new(Grammar::parse(&text).expect("one-phenotype grammar"))
}

/// Cells of the 100 × 100 arena, GS 10 (all away from the hub).
fn cell(k: i32) -> Pos {
    [Pos::new(35, 35), Pos::new(45, 35), Pos::new(35, 45), Pos::new(45, 45), Pos::new(-35, -35), Pos::new(-45, -35)]
        [k as usize]
}

/// What the world shows the learner in one step.
#[derive(Clone)]
struct Step {
    pos: Pos,
    carrying: Vec<ObjectInfo>,
    regime: Regime,
    mates: Vec<AgentId>,
}

impl Step {
    /// Alone at `pos` with lateral transfer off.
    fn at(pos: Pos) -> Step {
        Step {
            pos,
            carrying: Vec::new(),
            regime: Regime { lateral_transfer: false, ip: 1.0, gene_loss: 0.0 },
            mates: vec![],
        }
    }
    /// Lateral transfer on with interaction probability `ip`, these cell-mates present.
    fn lt(mut self, ip: f64, mates: &[AgentId]) -> Step {
        self.regime.lateral_transfer = true;
        self.regime.ip = ip;
        self.mates = mates.to_vec();
        self
    }
    fn carrying(mut self, o: ObjectInfo) -> Step {
        self.carrying.push(o);
        self
    }
}

struct Rig {
    learner: Learner,
    cache: GeneCache,
    /// The genome every cell-mate offers, and its mapping.
    mate_genome: Arc<[u32]>,
    mate_mapping: GeneMapping,
    t: u64,
    /// The gene the learner offered its cell-mates in the last step.
    offered: Option<GeneMsg>,
}

impl Rig {
    fn new(phenotype: &str, cfg: LearnerConfig) -> Rig {
        Rig::with_role(phenotype, cfg, Role::BetrGeese)
    }

    fn with_role(phenotype: &str, cfg: LearnerConfig, role: Role) -> Rig {
        cfg.validate().expect("valid learner config");
        let grammar = grammar_of(phenotype);
        let mate = ge::evaluate(&grammar, vec![3u32, 4], &cfg.ge);
        assert!(mate.valid());
        let mate_mapping = GeneMapping { valid: true, used_codons: mate.used_codons as u32, depth: mate.depth as u32 };
        let learner = Learner::with_role(ME, Arc::new(cfg), grammar, geom(), HUB, SEED, role).expect("tree builds");
        Rig { learner, cache: GeneCache::new(), mate_genome: mate.genome, mate_mapping, t: 0, offered: None }
    }

    /// One step: percept, genes of the cell-mates, intent.
    fn step(&mut self, s: &Step) -> Intent {
        self.begin(s);
        let genes: Vec<GeneMsg> = s.mates.iter().map(|&from| self.mate_gene(from, self.mate_genome.clone())).collect();
        self.learner.finish_step(&genes, &mut self.cache)
    }

    /// The gene cell-mate `from` offers in this step: `genome`, fitness 1.
    fn mate_gene(&self, from: AgentId, genome: Arc<[u32]>) -> GeneMsg {
        GeneMsg { step: self.t, from, genome, fitness: 1.0, mapping: self.mate_mapping }
    }

    /// A step's first half: the next step's percept of `s`, read by the learner.
    fn begin(&mut self, s: &Step) {
        self.t += 1;
        let g = geom();
        let me =
            AgentPublic { id: ME, pos: s.pos, heading: 0.0, carrying: s.carrying.clone(), live: true, learning: true };
        let mut agents: Vec<AgentPublic> =
            s.mates.iter().map(|&id| AgentPublic { id, carrying: Vec::new(), ..me.clone() }).collect();
        agents.push(me);
        agents.sort_by_key(|a| a.id);
        let objects = if g.cell_of(s.pos) == g.cell_of(HUB.pos) { vec![HUB] } else { vec![] };
        let percept = Percept {
            step: self.t,
            cell: g.cell_of(s.pos),
            regime: s.regime,
            objects,
            nearby_impassable: vec![],
            reach: 0,
            area: vec![],
            agents,
        };
        self.offered = self.learner.begin_step(&percept);
        assert_eq!(self.offered.is_some(), s.regime.lateral_transfer && !self.learner.is_fixed());
    }

    /// Run `s` `n` times; the steps (1-based, of this rig) at which a genetic step ran,
    /// with its trigger.
    fn run(&mut self, n: usize, s: &Step) -> Vec<(u64, GeneticTrigger)> {
        (0..n)
            .filter_map(|_| {
                let i = self.step(s);
                (i.stats.genetic != GeneticTrigger::None).then_some((self.t, i.stats.genetic))
            })
            .collect()
    }
}

fn cfg() -> LearnerConfig {
    LearnerConfig::default()
}
fn cfg_st(st: usize) -> LearnerConfig {
    LearnerConfig { st: Some(st), ..LearnerConfig::default() }
}
fn approx(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-9
}

// ---------------------------------------------------------------------------------------
// §6.1, §6.5: the fitness A = 0.1·R + E + B
// ---------------------------------------------------------------------------------------

/// §6.1 + §6.5 (CODE): the first gene's fitness is 0 at start and R = 0, so the fitness
/// is E + B; E = distinct grid cells visited since the gene was adopted, minus 1
/// (cumulative); B = 2 for a tree with two succeeding selectors.
#[test]
fn fitness_is_distinct_cells_minus_one_plus_selectors() {
    let mut r = Rig::new(TWO_SELECTORS, cfg());
    assert_eq!(r.learner.offer(0).fitness, 0.0, "the first gene's fitness is set to 0");
    let steps = [(cell(0), 2.0), (cell(1), 3.0), (cell(0), 3.0), (Pos::new(36, 36), 3.0), (cell(4), 4.0)];
    for (pos, want) in steps {
        let i = r.step(&Step::at(pos));
        assert_eq!(i.stats.fitness, want, "at {pos:?}");
        assert_eq!(r.learner.fitness(), want);
    }
}

/// §1.5 + §2.3 IsVisitedBefore: a learning agent is born knowing the hub, so
/// IsVisitedBefore_Hub succeeds far from it on the very first tick (B = 1).
#[test]
fn a_learner_is_born_knowing_the_hub() {
    let mut r = Rig::new("[Selector][PostCnd]IsVisitedBefore_Hub[/PostCnd][/Selector]", cfg());
    assert_eq!(r.step(&Step::at(cell(4))).stats.fitness, 1.0);
}

/// §2.1 + §6.5: B reads the statuses after the tick, stale ones included. With
/// Selector[IsCarrying_Food, Selector[Dummy]], once the agent carries food the inner
/// selector is no longer ticked but keeps its SUCCESS: B stays 2 (not 1).
#[test]
fn stale_selector_statuses_count_in_the_fitness() {
    let p = "[Selector][PostCnd]IsCarrying_Food[/PostCnd][Selector][PostCnd]DummyNode[/PostCnd][/Selector][/Selector]";
    let mut r = Rig::new(p, cfg());
    assert_eq!(r.step(&Step::at(cell(0))).stats.fitness, 2.0);
    let food = super::object(10, ObjectKind::Food, 35, 35);
    assert_eq!(r.step(&Step::at(cell(0)).carrying(food)).stats.fitness, 2.0);
}

/// §6.2 step 3: the cell added to `visited` is the one the agent is in *after* its
/// tick's own moves. MoveTowards_Hub takes the agent from (10,4) into the hub cell at
/// step 1, where it stays at step 2: one cell visited, E = 0 (B = 0 for this tree).
#[test]
fn the_visited_cell_is_the_one_after_the_ticks_moves() {
    let mut r = Rig::new("[Sequence][Sequence][Act]MoveTowards_Hub_Normal[/Act][/Sequence][/Sequence]", cfg());
    let i = r.step(&Step::at(Pos::new(10, 4)));
    assert!(matches!(i.ops[..], [geese_proto::Op::Move { to: Pos { x: 8, y: 3 }, .. }]), "{:?}", i.ops);
    assert_eq!(i.stats.fitness, 0.0);
    let i = r.step(&Step::at(Pos::new(8, 3)));
    assert!(i.ops.is_empty(), "already at the hub");
    assert_eq!(i.stats.fitness, 0.0, "the start cell (10,4) was never visited");
}

/// §6.2 steps 4, 7, 8 and §6.5 (CODE): the fitness is updated before the genetic step,
/// so R — the fitness the old gene had when it was replaced — includes that step's E;
/// the adopted gene starts at fitness 0, `visited` is cleared, and R stays constant for
/// the gene's lifetime (no recursion on A(t−1)).
#[test]
fn carry_over_is_the_replaced_genes_last_fitness() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    for (k, want) in [(0, 1.0), (1, 2.0), (2, 3.0)] {
        assert_eq!(r.step(&Step::at(cell(k))).stats.fitness, want);
    }
    // Step 4: E = 3, fitness 4, then four IP survivors fill the pool to ST.
    let i = r.step(&Step::at(cell(3)).lt(1.0, &[1, 2, 3]));
    assert_eq!(i.stats.genetic, GeneticTrigger::Storage);
    assert_eq!(i.stats.fitness, 0.0, "the adopted gene's fitness is reset to 0");
    assert_eq!(r.learner.offer(5).fitness, 0.0);
    // R = 4: 0.1·4 + E + 1, E counted afresh from the new gene's adoption.
    assert!(approx(r.step(&Step::at(cell(3))).stats.fitness, 1.4), "visited cleared, R = 4");
    assert!(approx(r.step(&Step::at(cell(4))).stats.fitness, 2.4), "R constant: not 0.1·1.4 + 2");
    assert!(approx(r.step(&Step::at(cell(4))).stats.fitness, 2.4));
    // Second replacement at fitness 2.4 → R = 2.4.
    assert_eq!(r.step(&Step::at(cell(4)).lt(1.0, &[1, 2, 3])).stats.genetic, GeneticTrigger::Storage);
    assert!(approx(r.step(&Step::at(cell(4))).stats.fitness, 1.24));
}

/// §6.5 [switch] `Fidelity::Paper`: A(t) = 0.1·A(t−1) + E + B with A(0) = D, and B =
/// +1 per successful post-condition, +1 for a succeeding root selector. Here D = 2/9·25
/// = 5.5556 (IsCarrying and IsVisitedBefore, §5.5) and B = 2.
#[test]
fn paper_fitness_recursion_starts_from_d() {
    let p = "[Selector][PostCnd]IsCarrying_Food[/PostCnd][PostCnd]IsVisitedBefore_Hub[/PostCnd][/Selector]";
    let d = 5.5556;
    let mut r = Rig::new(p, LearnerConfig { fitness: FitnessVariant::Paper, ..cfg_st(4) });
    assert_eq!(r.learner.offer(0).fitness, d, "A(0) = D");
    let a1 = 0.1 * d + 2.0;
    assert!(approx(r.step(&Step::at(cell(0))).stats.fitness, a1));
    let a2 = 0.1 * a1 + 1.0 + 2.0;
    assert!(approx(r.step(&Step::at(cell(1))).stats.fitness, a2));
    // A gene adopted by a genetic step starts again from its D.
    let i = r.step(&Step::at(cell(1)).lt(1.0, &[1, 2, 3]));
    assert_eq!(i.stats.genetic, GeneticTrigger::Storage);
    assert_eq!(i.stats.fitness, d);
    assert!(approx(r.step(&Step::at(cell(1))).stats.fitness, a1));
    // The same tree under the CODE formula: 0.1·0 + 0 + 1 selector.
    let mut r = Rig::new(p, cfg());
    assert_eq!(r.step(&Step::at(cell(0))).stats.fitness, 1.0);
}

// ---------------------------------------------------------------------------------------
// §6.2 step 6: lateral transfer, the IP filter and "more than one survivor"
// ---------------------------------------------------------------------------------------

/// §6.3: lateral transfer sends the genome with its fitness — the gene as it stands,
/// with the fitness of the agent's last update.
#[test]
fn the_offered_gene_carries_its_current_fitness() {
    let mut r = Rig::new(TWO_SELECTORS, cfg());
    assert_eq!(r.step(&Step::at(cell(0))).stats.fitness, 2.0);
    assert_eq!(r.step(&Step::at(cell(1))).stats.fitness, 3.0);
    r.step(&Step::at(cell(1)).lt(0.0, &[7]));
    let g = r.offered.clone().expect("offered while lateral transfer is on");
    assert_eq!((g.from, g.step, g.fitness), (ME, 3, 3.0));
    assert_eq!(g.genome, r.learner.gene().genome);
}

/// §6.2 step 6: an agent alone in its cell is its own only candidate; one survivor is
/// not "more than one", so nothing joins the pool and ST is never reached.
#[test]
fn a_lone_survivor_adds_nothing_to_the_pool() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    for _ in 0..30 {
        let i = r.step(&Step::at(cell(0)).lt(1.0, &[]));
        assert_eq!(i.stats.lt_rate, 1, "the agent itself survives");
        assert_eq!(i.stats.genetic, GeneticTrigger::None);
    }
}

/// §6.2 step 6: with two survivors (the agent and one cell-mate) *both* genes go to the
/// pool, which keeps growing over steps (duplicates allowed) until it reaches ST.
#[test]
fn two_survivors_both_join_the_pool() {
    for mate in [1, 7] {
        let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
        let s = Step::at(cell(0)).lt(1.0, &[mate]);
        let i = r.step(&s);
        assert_eq!((i.stats.lt_rate, i.stats.genetic), (2, GeneticTrigger::None), "mate {mate}");
        let i = r.step(&s);
        assert_eq!((i.stats.lt_rate, i.stats.genetic), (2, GeneticTrigger::Storage), "mate {mate}: 2 + 2 = ST");
    }
}

/// §6.2 step 6: the agent itself is a candidate — with three cell-mates and IP = 1 four
/// genes join at once and reach ST = 4 in the first step.
#[test]
fn the_agent_itself_is_a_candidate() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    let i = r.step(&Step::at(cell(0)).lt(1.0, &[1, 2, 9]));
    assert_eq!((i.stats.lt_rate, i.stats.genetic), (4, GeneticTrigger::Storage));
}

/// §6.2 step 6: with IP = 0 nobody survives, so no gene is ever stored.
#[test]
fn ip_zero_keeps_nobody() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    for _ in 0..20 {
        let i = r.step(&Step::at(cell(0)).lt(0.0, &[1, 2, 9]));
        assert_eq!((i.stats.lt_rate, i.stats.genetic), (0, GeneticTrigger::None));
    }
}

/// §6.2 step 6: each candidate (the agent and each cell-mate) is kept independently with
/// probability IP — with 4 candidates and IP = 0.5 the number of survivors is
/// Binomial(4, 0.5).
#[test]
fn each_candidate_is_kept_independently_with_probability_ip() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(1_000_000));
    let n = 2000;
    let mut hist = [0usize; 5];
    for _ in 0..n {
        let i = r.step(&Step::at(cell(0)).lt(0.5, &[1, 2, 9]));
        hist[i.stats.lt_rate as usize] += 1;
    }
    for (k, p) in [1.0, 4.0, 6.0, 4.0, 1.0].iter().map(|c| c / 16.0).enumerate() {
        let f = hist[k] as f64 / n as f64;
        assert!((f - p).abs() < 0.04, "P({k} survivors) = {f}, Binomial(4, ½) says {p}; {hist:?}");
    }
}

/// §6.3: while lateral transfer is off the pool does not grow (and the agent reports no
/// survivors); it resumes growing from where it was.
#[test]
fn lateral_transfer_off_freezes_the_pool() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    let on = Step::at(cell(0)).lt(1.0, &[7]);
    let mut off = on.clone();
    off.regime.lateral_transfer = false;
    assert_eq!(r.step(&on).stats.genetic, GeneticTrigger::None);
    for _ in 0..3 {
        let i = r.step(&off);
        assert_eq!((i.stats.lt_rate, i.stats.genetic), (0, GeneticTrigger::None));
    }
    assert_eq!(r.step(&on).stats.genetic, GeneticTrigger::Storage, "2 + 2 = ST");
}

/// §6.2 step 8: a genetic step empties the pool, so the next one needs ST genes again.
#[test]
fn a_genetic_step_empties_the_pool() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    let s = Step::at(cell(0)).lt(1.0, &[7]);
    assert_eq!(r.run(8, &s), [2, 4, 6, 8].map(|t| (t, GeneticTrigger::Storage)));
}

// ---------------------------------------------------------------------------------------
// §6.2 step 7, §6.3: the stagnation ("ageing") rule
// ---------------------------------------------------------------------------------------

/// §6.2 step 7: with age > gstep (200) and E < expp (2) the agent injects fresh
/// individuals and runs a genetic step — at step 201, not 200 — and again 201 steps
/// after that (age restarts at 0). It runs while lateral transfer is off (§6.3). R is
/// the replaced gene's fitness (B = 1, E = 0).
#[test]
fn stagnation_fires_when_age_exceeds_gstep_and_e_is_below_expp() {
    let mut r = Rig::new(ONE_SELECTOR, cfg());
    let stay = Step::at(cell(0));
    assert_eq!(r.run(200, &stay), []);
    let i = r.step(&stay);
    assert_eq!((i.stats.genetic, i.stats.fitness), (GeneticTrigger::Stagnation, 0.0), "step 201");
    assert!(approx(r.step(&stay).stats.fitness, 1.1), "R = 1");
    assert_eq!(r.run(199, &stay), []);
    assert_eq!(r.step(&stay).stats.genetic, GeneticTrigger::Stagnation, "step 402");
}

/// §6.2 step 7: E = 1 (two cells) is still below expp = 2, so the rule fires at 201.
#[test]
fn stagnation_fires_with_one_extra_cell() {
    let mut r = Rig::new(ONE_SELECTOR, cfg());
    let mut fired = Vec::new();
    for t in 1..=300u64 {
        let i = r.step(&Step::at(cell((t % 2) as i32)));
        if i.stats.genetic != GeneticTrigger::None {
            fired.push((t, i.stats.genetic));
        }
    }
    assert_eq!(fired, [(201, GeneticTrigger::Stagnation)]);
}

/// §6.2 step 7: an agent that has visited three cells (E = 2, not below expp) does not
/// stagnate, however old its gene.
#[test]
fn no_stagnation_once_e_reaches_expp() {
    let mut r = Rig::new(ONE_SELECTOR, cfg());
    r.step(&Step::at(cell(0)));
    r.step(&Step::at(cell(1)));
    assert_eq!(r.run(500, &Step::at(cell(2))), []);
}

/// §1.4/§5.1: expp = 0 disables the rule (the locality run).
#[test]
fn expp_zero_disables_stagnation() {
    let mut r = Rig::new(ONE_SELECTOR, LearnerConfig { stagnation_explore: 0, ..cfg() });
    assert_eq!(r.run(500, &Step::at(cell(0))), []);
}

/// §6.2 step 8: any genetic step resets the age, so after a storage-triggered step at
/// step 50 the stagnation rule next fires 201 steps later (step 251), not at 201.
#[test]
fn a_genetic_step_restarts_the_age() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    let stay = Step::at(cell(0));
    assert_eq!(r.run(49, &stay), []);
    assert_eq!(r.step(&stay.clone().lt(1.0, &[1, 2, 3])).stats.genetic, GeneticTrigger::Storage);
    assert_eq!(r.run(250, &stay), [(251, GeneticTrigger::Stagnation)]);
}

/// §6.2 step 7: the storage trigger is "pool ≥ ST", checked before the stagnation rule
/// (an old, stagnating agent whose pool fills runs one storage-triggered step).
#[test]
fn storage_trigger_comes_before_stagnation() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    let stay = Step::at(cell(0));
    assert_eq!(r.run(200, &stay), []);
    let i = r.step(&stay.clone().lt(1.0, &[1, 2, 3]));
    assert_eq!(i.stats.genetic, GeneticTrigger::Storage);
    assert_eq!(r.run(200, &stay), [], "age restarted at step 201");
}

// ---------------------------------------------------------------------------------------
// §6.1: start-up
// ---------------------------------------------------------------------------------------

/// §6.1: at start-up each agent initialises 3 individuals (D-evaluated) from its
/// evolution stream and uses the *first* one, not the best; its fitness is set to 0.
#[test]
fn start_up_uses_the_first_of_three_individuals() {
    let grammar = Arc::new(
        Grammar::parse(grammars::builtin("betr-foraging-avoid").expect("built-in")).expect("reference grammar"),
    );
    let cfg = Arc::new(cfg());
    let mut first_not_best = 0;
    for id in 0..40 {
        let mut rng = ChaCha8Rng::seed_from_u64(derive(SEED, Owner::Agent(id), Purpose::Evolution));
        let three: Vec<_> = (0..3).map(|_| ge::random_individual(&grammar, &GeParams::default(), &mut rng)).collect();
        let l = Learner::new(id, cfg.clone(), grammar.clone(), geom(), HUB, SEED).expect("tree builds");
        assert_eq!(l.gene().genome, three[0].genome, "agent {id}");
        assert_eq!(l.fitness(), 0.0);
        if three[1..].iter().any(|o| o.fitness > three[0].fitness) {
            first_not_best += 1;
        }
    }
    assert!(first_not_best > 0, "some agent's first individual is not its best");
}

// ---------------------------------------------------------------------------------------
// §6.7 GEESE-BT, §7 Multi-GEESE, §6.8/§7.3 fixed agents
// ---------------------------------------------------------------------------------------

/// Drops food at the hub when it carries some; B = 0 (no selector).
const DROP: &str = "[Sequence][Sequence][Act]CompositeDrop_Food[/Act][/Sequence][/Sequence]";

fn geese_bt() -> LearnerConfig {
    LearnerConfig { terms: Some(FitnessTerms::GEESE_BT), triggers: Some(Triggers::GeeseBt), ..cfg_st(4) }
}

/// §6.7: GEESE-BT's fitness is 0.1·R + E + C + F: C the weight carried now (type III),
/// F the weight this gene delivered to the hub (type IV); no BT feedback.
#[test]
fn geese_bt_fitness_counts_carried_and_delivered_weight() {
    let food = super::object(10, ObjectKind::Food, 35, 35);
    let mut r = Rig::with_role(ONE_SELECTOR, geese_bt(), Role::GeeseBt);
    assert_eq!(r.step(&Step::at(cell(0))).stats.fitness, 0.0, "no B, E = 0");
    assert_eq!(r.step(&Step::at(cell(1)).carrying(food)).stats.fitness, 1.0 + 5.0, "E = 1, C = 5");
    let mut r = Rig::with_role(DROP, geese_bt(), Role::GeeseBt);
    let hub_food = super::object(11, ObjectKind::Food, 1, 1);
    let i = r.step(&Step::at(Pos::new(2, 2)).carrying(hub_food));
    assert_eq!(i.ops, [geese_proto::Op::Drop { object: 11 }]);
    assert_eq!(i.stats.fitness, 5.0, "F = 5 once dropped into the hub, C = 0");
    assert_eq!(r.step(&Step::at(Pos::new(2, 2))).stats.fitness, 5.0, "F stays with the gene");
    // The D term adds the phenotype's diversity (DummyNode alone: 0 of the nine names).
    let d = LearnerConfig { terms: Some(FitnessTerms::parse("D+E").unwrap()), ..cfg() };
    let p = "[Selector][PostCnd]IsCarrying_Food[/PostCnd][PostCnd]IsVisitedBefore_Hub[/PostCnd][/Selector]";
    assert!(approx(Rig::new(p, d).step(&Step::at(cell(0))).stats.fitness, 5.5556));
}

/// §6.7 (CODE `resilience_evolution`): GEESE-BT's genetic step waits for an age over
/// `stagnation_age` (200) even with a full pool, and an agent whose gene delivered
/// (F > 0) keeps it; stagnation takes fresh individuals when fitness ≤ 0 and age > 100.
#[test]
fn geese_bt_triggers_wait_for_age_and_spare_deliverers() {
    let mut r = Rig::with_role(ONE_SELECTOR, geese_bt(), Role::GeeseBt);
    // Fitness stays 0 in one cell: stagnation fires at age 101.
    let fired = r.run(101, &Step::at(cell(0)));
    assert_eq!(fired, vec![(101, GeneticTrigger::Stagnation)]);
    // With E > 0 a full pool waits until age 201.
    let mut r = Rig::with_role(ONE_SELECTOR, geese_bt(), Role::GeeseBt);
    r.step(&Step::at(cell(0)));
    let fired = r.run(210, &Step::at(cell(1)).lt(1.0, &[1, 2, 3]));
    assert_eq!(fired.first(), Some(&(201, GeneticTrigger::Storage)), "{fired:?}");
    // A gene that delivered is kept whatever the pool.
    let mut r = Rig::with_role(DROP, geese_bt(), Role::GeeseBt);
    let hub_food = super::object(11, ObjectKind::Food, 1, 1);
    r.step(&Step::at(Pos::new(2, 2)).carrying(hub_food));
    assert!(r.run(300, &Step::at(Pos::new(2, 2)).lt(1.0, &[1, 2, 3])).is_empty());
}

/// §7.1: the collect phase stores the current gene under the class of its single
/// action when that action succeeded this tick, and replaces it only by a fitter gene;
/// an action that failed stores nothing.
#[test]
fn collect_phase_fills_the_gene_dict_with_successful_actions() {
    let explore = "[Sequence][Sequence][Act]Explore_0_Normal[/Act][/Sequence][/Sequence]";
    let mut r = Rig::with_role(explore, cfg(), Role::Collect);
    r.step(&Step::at(cell(0)));
    let d = r.learner.gene_dict().expect("a collect learner has a GeneDict");
    assert_eq!(d.keys().collect::<Vec<_>>(), ["ExploreNormal"]);
    assert_eq!(d["ExploreNormal"].fitness, r.learner.fitness());
    assert_eq!(&*d["ExploreNormal"].genome, &*r.learner.gene().genome);
    // CompositeDrop fails when not carrying: nothing stored.
    let mut r = Rig::with_role(DROP, cfg(), Role::Collect);
    r.step(&Step::at(cell(0)));
    assert!(r.learner.gene_dict().expect("GeneDict").is_empty());
    // The member written to population.json carries it.
    assert!(r.learner.member().gene_dict.is_some());
}

/// §7.2: a combine learner's tree takes its controllers from its own GeneDict, and a
/// received combine genome is decoded against the receiver's GeneDict.
#[test]
fn combine_phase_trees_are_built_from_the_own_gene_dict() {
    let combine = Arc::new(
        Grammar::parse(grammars::builtin("multi-combine-foraging").expect("built-in")).expect("combine grammar"),
    );
    let explore = "[Sequence][Selector][PostCnd]IsCarrying_Food[/PostCnd][Sequence][Act]Explore_0_Normal[/Act][/Sequence][/Selector][/Sequence]";
    let mut dict = GeneDict::new();
    for k in ["ExploreNormal", "MoveTowardsNormal", "MoveAwayNormal", "CompositeSingleCarry", "CompositeDrop"] {
        dict.insert(k.into(), StoredGene { phenotype: explore.into(), genome: Arc::from([]), fitness: 1.0 });
    }
    let cfg = Arc::new(cfg());
    let l = Learner::with_role(ME, cfg.clone(), combine.clone(), geom(), HUB, SEED, Role::Combine(Arc::new(dict)))
        .expect("every slot filled");
    let text = l.tree().render();
    assert!(!text.contains("AbsentAction") && text.contains("Explore"), "{text}");
    // Without its GeneDict the combine grammar's slots do not build: an error, never
    // an empty tree.
    assert!(Learner::new(ME, cfg, combine, geom(), HUB, SEED).is_err());
}

/// §6.8 / §7.3: a fixed agent ticks its tree every step, offers no gene even while
/// lateral transfer is on, and never runs a genetic step.
#[test]
fn fixed_agents_act_but_neither_share_nor_evolve() {
    let tree = program::build_tree("[Sequence][Sequence][Act]MoveTowards_Hub_Normal[/Act][/Sequence][/Sequence]", None)
        .expect("tree");
    let mut r = Rig::with_role(ONE_SELECTOR, cfg_st(4), Role::Fixed(tree));
    for k in 0..5 {
        let i = r.step(&Step::at(cell(k)).lt(1.0, &[1, 2, 3]));
        assert!(r.offered.is_none());
        assert_eq!(i.stats.genetic, GeneticTrigger::None);
        assert_eq!(i.stats.lt_rate, 0);
        assert!(matches!(i.ops[..], [geese_proto::Op::Move { .. }]), "{:?}", i.ops);
    }
}

/// `finish_step_with` asks for the cell-mates after the tick, with the cell the agent's
/// own move took it to (REFERENCE §6.2 step 6), and takes the genes it returns: an
/// explorer at the east edge of its cell steps into the next one and is handed one mate
/// there, who survives IP 1 with it (LT rate 2).
#[test]
fn finish_step_with_chooses_cell_mates_after_the_move() {
    const EXPLORE: &str = "[Sequence][Act]Explore_0_Normal[/Act][/Sequence]";
    let mut r = Rig::new(EXPLORE, cfg());
    let g = geom();
    let start = Pos::new(39, 35);
    let s = Step::at(start).lt(1.0, &[]);
    let me = AgentPublic { id: ME, pos: start, heading: 0.0, carrying: vec![], live: true, learning: true };
    let percept = Percept {
        step: 1,
        cell: g.cell_of(start),
        regime: s.regime,
        objects: vec![],
        nearby_impassable: vec![],
        reach: 0,
        area: vec![],
        agents: vec![me],
    };
    assert!(r.learner.begin_step(&percept).is_some());
    let mate = GeneMsg { step: 1, from: 7, genome: r.mate_genome.clone(), fitness: 1.0, mapping: r.mate_mapping };
    let genes = [mate];
    let mut asked = None;
    let intent = r.learner.finish_step_with(&mut r.cache, |expected, cell| {
        asked = Some(cell);
        expected.clear();
        expected.push(7);
        &genes[..]
    });
    let moved_to = intent.ops.iter().rev().find_map(|op| match op {
        geese_proto::Op::Move { to, .. } => Some(*to),
        _ => None,
    });
    let to = moved_to.expect("the explorer moves");
    assert_ne!(g.cell_of(to), g.cell_of(start), "the move crosses into the next cell");
    assert_eq!(asked, Some(g.cell_of(to)));
    assert_eq!(intent.stats.lt_rate, 2);
    assert_eq!(intent.stats.genes_lost, 0);
}

/// Shared gene objects (REFERENCE §6.6, `Learner::share_genes`): a pool entry is read
/// with its holder's fitness as it stands at the genetic step, not as it was when it
/// joined; the adopted pool gene is the donor's object, so the adopter's reset zeroes
/// the donor's fitness, and the adopter's next fitness is what the donor reads.
///
/// Mate 7's gene joins the pool at step 1 with fitness 1, mate 8's at step 2 with 5;
/// mate 7's holder then reaches 1,000, which outbids 8's and every offspring's D.
#[test]
fn shared_genes_are_read_live_and_an_adopted_one_is_the_donors() {
    let mut r = Rig::new(ONE_SELECTOR, cfg_st(4));
    r.learner.share_genes();
    let own = r.learner.gene_cell().cloned().expect("a shared gene's field");
    let (seven, eight) = (FitnessCell::new(1.0), FitnessCell::new(5.0));
    // Two allocations of one genome: two gene objects.
    let codons = |g: &Arc<[u32]>| Arc::<[u32]>::from(&g[..]);
    let (g7, g8) = (codons(&r.mate_genome), codons(&r.mate_genome));
    let s = Step::at(cell(0)).lt(1.0, &[7]);
    r.begin(&s);
    let genes = [SharedGene { msg: r.mate_gene(7, g7.clone()), cell: Some(seven.clone()) }];
    let first = r.learner.finish_step(&genes, &mut r.cache);
    assert_eq!((first.stats.lt_rate, first.stats.genetic), (2, GeneticTrigger::None), "two in the pool");
    assert!(approx(own.get(), 1.0), "the learner writes its fitness (B = 1) into its field");
    seven.set(1000.0);
    let s = Step::at(cell(0)).lt(1.0, &[8]);
    r.begin(&s);
    let genes = [SharedGene { msg: r.mate_gene(8, g8), cell: Some(eight.clone()) }];
    let second = r.learner.finish_step(&genes, &mut r.cache);
    assert_eq!(second.stats.genetic, GeneticTrigger::Storage);
    let held = r.learner.gene_cell().expect("a shared gene's field");
    assert!(Arc::ptr_eq(held, &seven), "the fittest by its current fitness won: mate 7's object");
    assert_eq!(r.learner.gene().genome.as_ptr(), g7.as_ptr());
    assert!(approx(seven.get(), 0.0), "the adopter's reset zeroed the donor");
    assert!(approx(eight.get(), 5.0));
    // R is the old gene's fitness as it stood at step 2 (E 0, B 1); then E 0, B 1.
    r.step(&Step::at(cell(1)));
    assert!(approx(seven.get(), 0.1 * 1.0 + 1.0), "adopter's 0.1·R + E + B, in the donor's field");
    assert!(approx(r.learner.member().fitness.expect("fitness"), seven.get()));
}

/// Shared gene objects in the collect phase (§6.6, §7.1): a GeneDict entry follows the
/// fitness of the gene it holds, and a rival gene of the same class replaces it only
/// when it outdoes the stored gene's fitness as it stands.
#[test]
fn a_shared_genedict_entry_follows_its_genes_fitness() {
    const EXPLORE: &str = "[Sequence][Act]Explore_0_Normal[/Act][/Sequence]";
    let mut r = Rig::with_role(EXPLORE, cfg(), Role::Collect);
    r.learner.share_genes();
    let field = r.learner.gene_cell().cloned().expect("a shared gene's field");
    for _ in 0..3 {
        r.step(&Step::at(cell(0)));
    }
    let stored = |r: &Rig| r.learner.member().gene_dict.expect("a GeneDict")["ExploreNormal"].fitness;
    assert!(approx(stored(&r), field.get()));
    field.set(42.0);
    assert!(approx(stored(&r), 42.0), "another holder's write shows in the entry");
}
