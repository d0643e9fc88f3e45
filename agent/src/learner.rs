//! The BeTr-GEESE learner: one agent's per-step sense–act–update loop (REFERENCE.md §6).
//!
//! The learner is sans-IO. A step is two calls:
//! 1. [`Learner::begin_step`] with the percept of the agent's cell returns the gene to
//!    offer to cell-mates (lateral transfer, DESIGN.md §2 step 2);
//! 2. [`Learner::finish_step`] with the genes that arrived ticks the tree, updates the
//!    fitness, runs the IP filter and the genetic step, and returns the intent.
//!
//! The order inside `finish_step` is the reference code's (§6.2): tick, visited cells,
//! fitness, lateral transfer into the pool, genetic operators, update. Genes are copied,
//! not shared (§6.6), and the blackboard is per agent (§2.2), as DESIGN.md §2 requires:
//! codons are immutable, so holding the sender's is as good as a copy (docs/research/core-speed.md,
//! "Shared genomes"), and a pool that reaches ST within the step only borrows them for that
//! step's genetic step. The learners of one process share a
//! [`GeneCache`]: scratch buffers, and the trees of adopted phenotypes.
//!
//! An in-process trial can instead reproduce the reference code's shared gene objects
//! ([`Learner::share_genes`], REFERENCE §6.6): then a gene's fitness lives in a
//! [`FitnessCell`] that every agent holding the gene reads and writes.
use crate::bt::{Bt, BuildError, Status};
use crate::ge::{self, Candidate, GeParams, Grammar, Individual, Member};
use crate::program::{FitnessTerms, GeneDict, Role, StoredGene};
use crate::view::View;
use geese_proto::seed::{derive, Fnv64, Owner, Purpose};
use geese_proto::{
    AgentId, AgentStats, BehaviourClass, CellIdx, GeneMapping, GeneMsg, GeneticTrigger, Geometry, Intent, ObjectInfo,
    Percept, Regime,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Which fitness formula (REFERENCE §6.5).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum FitnessVariant {
    /// 0.1·R + E + B, B = successful selectors (the reference code).
    #[default]
    Code,
    /// 0.1·A(t−1) + E + B, A(0) = D, B = +1 post-condition / −2 constraint / +1 root.
    Paper,
}

/// How a Multi-GEESE combine phase learns its wirings (issue 30.1; research record
/// `docs/research/fusion-takeoff.md`). The faithful port is the default; every other
/// variant changes only what a combine agent does (collect agents and the other
/// algorithms are untouched), and only through the agent's own experience: no variant
/// tells an agent where the hub, the site or an item is.
///
/// The combine phase is bimodal under every semantics of the reference code (NOTES.md,
/// issue 16): its genes live about four steps, its fitness E + B ranks explorers first,
/// and the wirings that delivered are lost late in a run. The variants test the
/// hypotheses that the fitness, or the loss of delivering wirings, decides it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Fusion {
    /// The reference code's combine phase (fitness 0.1·R + E + B, the storage trigger).
    #[default]
    Faithful,
    /// The combine fitness adds a delivery term, [`DELIVERY_WEIGHT`] per unit of weight
    /// the agent dropped into a drop zone under its current wiring: a task term, so a
    /// wiring that delivers outranks an explorer in its cell-mates' pools.
    Delivery,
    /// Elitism by experience: a combine agent whose current wiring has delivered keeps
    /// it (no genetic step, incoming genes ignored) while still offering it to its
    /// cell-mates, so a delivering wiring is never lost to churn.
    KeepDeliverers,
    /// Both: the delivery term and keeping the wirings that delivered.
    DeliveryKeep,
    /// Patience: a combine agent takes part in a genetic step only once its wiring is
    /// [`PATIENCE`] steps old (its pool keeps the first ST genes it meets meanwhile).
    /// Faithfully a wiring lives about four steps, so its fitness is a handful of cells
    /// and the genetic step's winner is mostly an offspring ranked by its D: selection
    /// barely sees what a wiring does.
    Patient,
    /// Patience and the delivery term: a wiring is judged over at least [`PATIENCE`]
    /// steps, by what it explored and what it delivered.
    PatientDelivery,
}

/// Age a combine wiring must reach before a genetic step may replace it under
/// [`Fusion::Patient`] and [`Fusion::PatientDelivery`]: long enough to go from the
/// site to the hub and back (site at distance 30, a few cells a tick), half the
/// reference GEESE-BT learner's 200.
pub const PATIENCE: u32 = 100;

/// Fitness a combine agent gains per unit of weight it delivers under [`Fusion::Delivery`]
/// (a food item weighs 5): one delivery (+50) outweighs the cells an explorer covers in a
/// gene's life of a few steps (E ≤ 100 cells in the 10 × 10 grid), which is the point.
pub const DELIVERY_WEIGHT: f64 = 10.0;

impl Fusion {
    pub const ALL: [Fusion; 6] = [
        Fusion::Faithful,
        Fusion::Delivery,
        Fusion::KeepDeliverers,
        Fusion::DeliveryKeep,
        Fusion::Patient,
        Fusion::PatientDelivery,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Fusion::Faithful => "faithful",
            Fusion::Delivery => "delivery",
            Fusion::KeepDeliverers => "keep-deliverers",
            Fusion::DeliveryKeep => "delivery-keep",
            Fusion::Patient => "patient",
            Fusion::PatientDelivery => "patient-delivery",
        }
    }

    /// Does the combine fitness reward delivered weight?
    pub fn rewards_delivery(self) -> bool {
        matches!(self, Fusion::Delivery | Fusion::DeliveryKeep | Fusion::PatientDelivery)
    }

    /// Must a combine wiring reach [`PATIENCE`] steps before a genetic step?
    pub fn is_patient(self) -> bool {
        matches!(self, Fusion::Patient | Fusion::PatientDelivery)
    }

    /// Does a combine agent keep a wiring that delivered?
    pub fn keeps_deliverers(self) -> bool {
        matches!(self, Fusion::KeepDeliverers | Fusion::DeliveryKeep)
    }

    fn is_faithful(&self) -> bool {
        *self == Fusion::Faithful
    }
}

impl std::fmt::Display for Fusion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Fusion {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Fusion::ALL.into_iter().find(|v| v.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Fusion::ALL.iter().map(|v| v.name()).collect();
            format!("unknown fusion variant '{s}' (expected one of: {})", names.join(", "))
        })
    }
}

/// Learner parameters; defaults are the paper's Sec.-5 settings (REFERENCE §5.1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearnerConfig {
    /// Storage threshold ST; `None` = the algorithm's own ([`default_st`]: 7, the paper's,
    /// for BeTr-GEESE and GEESE-BT; 10, the reference code's, for both Multi-GEESE phases).
    pub st: Option<usize>,
    /// Stagnation age (`gstep`): steps without a gene change before the rule may fire.
    pub stagnation_age: u32,
    /// Stagnation exploration floor (`expp`); 0 disables the rule.
    pub stagnation_explore: u32,
    /// Fresh individuals injected by the stagnation rule.
    pub stagnation_individuals: usize,
    /// Individuals created at start-up (the first one is used).
    pub initial_individuals: usize,
    /// Carry-over factor (1 − β).
    pub carry_over: f64,
    pub fitness: FitnessVariant,
    /// Terms of the running fitness; `None` = the algorithm's own (E+B for BeTr-GEESE
    /// and Multi-GEESE, E+C+F for GEESE-BT).
    pub terms: Option<FitnessTerms>,
    /// When the genetic operators run; `None` = the algorithm's own.
    pub triggers: Option<Triggers>,
    pub ge: GeParams,
    /// GE parameters of the Multi-GEESE combine phase (`test_new.txt`: genomes up to
    /// 500 codons, crossover probability 0.1; REFERENCE §5.1).
    pub combine_ge: GeParams,
    /// How the Multi-GEESE combine phase learns ([`Fusion`]); the faithful port unless set.
    #[serde(skip_serializing_if = "Fusion::is_faithful")]
    pub fusion: Fusion,
    /// One-phase fusion ([`crate::program::Phase::One`]): an agent starts wiring once its
    /// GeneDict holds every controller class and no entry has changed for this many
    /// steps (its collection has settled).
    #[serde(skip_serializing_if = "is_default_settle")]
    pub one_phase_settle: u32,
    /// How an agent's mutation probability moves (issue 30.3): `fixed` (the paper's,
    /// GE's `mutation_prob` always) or `stress` ([`StressMutation`]).
    pub mutation: MutationRule,
    /// The constants of the `stress` rule.
    pub stress: StressMutation,
}

/// The rule of an agent's mutation probability (PAPER §8: stress-induced mutation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum MutationRule {
    /// GE's `mutation_prob`, at every genetic step (the paper; the default).
    #[default]
    Fixed,
    /// Rises while the agent's fitness stalls or falls, relaxes when it recovers.
    Stress,
}

impl std::str::FromStr for MutationRule {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "fixed" => Ok(MutationRule::Fixed),
            "stress" => Ok(MutationRule::Stress),
            other => Err(format!("unknown mutation rule '{other}' (expected fixed or stress)")),
        }
    }
}

/// Stress-induced mutation (issue 30.3; docs/research/stress-induced-mutation.md).
///
/// Why: an agent whose gene stops paying keeps proposing offspring one codon flip
/// (10 %) away from a pool that no longer fits the world; bacteria under stress raise
/// their mutation rate to search further, and relax it once they fit again.
///
/// Rule. Each agent keeps a stress level `s` in [0, 1], 0 at start; its mutation
/// probability at a genetic step is `p = base + s·(max − base)`, `base` being GE's
/// `mutation_prob` (the phase's). At every genetic step the agent compares the fitness
/// its outgoing gene reached (the running fitness at that step) with the one the gene
/// before reached at the previous genetic step: not higher (stalled or fallen) →
/// `s ← s + rise·(1 − s)`; higher (recovered) → `s ← relax·s`. The first genetic step
/// has nothing to compare with and leaves `s` at 0. No random draw: the rule changes
/// nothing of a run's random streams but the mutation draws themselves.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StressMutation {
    /// Share of the way to 1 the stress level moves at a stalled genetic step.
    pub rise: f64,
    /// Share of the stress level kept at an improving genetic step.
    pub relax: f64,
    /// The mutation probability at full stress (at least GE's `mutation_prob`).
    pub max: f64,
}

impl Default for StressMutation {
    fn default() -> Self {
        StressMutation { rise: 0.5, relax: 0.5, max: 0.5 }
    }
}

impl StressMutation {
    /// The stress level after a genetic step whose outgoing gene reached `now`, the one
    /// before having reached `before` (None at the first genetic step).
    pub fn next(&self, stress: f64, before: Option<f64>, now: f64) -> f64 {
        match before {
            None => stress,
            Some(b) if now <= b => stress + self.rise * (1.0 - stress),
            Some(_) => self.relax * stress,
        }
    }

    /// The mutation probability at stress level `stress` over base rate `base`.
    pub fn rate(&self, base: f64, stress: f64) -> f64 {
        (base + stress * (self.max - base)).clamp(0.0, 1.0)
    }
}

/// When the genetic operators run (REFERENCE §6.2 step 7, §6.7).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Triggers {
    /// The pool reached ST; or the stagnation rule (age > `stagnation_age` and fewer than
    /// `stagnation_explore` cells explored).
    Storage,
    /// The reference GEESE-BT learner: the pool reached ST while fitness ≥ 0, age >
    /// `stagnation_age` and F ≤ 0 (an agent that delivers keeps its gene); stagnation
    /// (fresh individuals) when fitness ≤ 0 and age > 100.
    GeeseBt,
}

/// The storage threshold of the paper (Sec. 3–5 command lines, REFERENCE §5.1).
pub const PAPER_ST: usize = 7;
/// The storage threshold the reference code's Multi-GEESE collect and combine phases ran
/// with (the `mgene` script default, REFERENCE §7.1–7.2, §10.2).
pub const MULTI_GEESE_ST: usize = 10;

/// The storage threshold a learner uses when the run sets none: 10 for the Multi-GEESE
/// phases (the reference code's), 7 otherwise (the paper's).
pub fn default_st(multi_geese: bool) -> usize {
    if multi_geese {
        MULTI_GEESE_ST
    } else {
        PAPER_ST
    }
}

/// Steps a complete GeneDict must stay unchanged before a one-phase agent starts wiring
/// ([`LearnerConfig::one_phase_settle`]). A GeneDict completes within the first hundred
/// steps or so, with whatever genes first succeeded; later entries replace an earlier one
/// only when fitter, ever more rarely, so a pause of this length says the collection
/// has levelled off (issue 30.2, `docs/research/one-phase-fusion.md`).
pub const ONE_PHASE_SETTLE: u32 = 500;

fn is_default_settle(v: &u32) -> bool {
    *v == ONE_PHASE_SETTLE
}

/// Age after which a GEESE-BT agent with no positive fitness takes fresh individuals.
pub const GEESE_BT_STAGNATION_AGE: u32 = 100;

impl Default for LearnerConfig {
    fn default() -> Self {
        LearnerConfig {
            st: None,
            stagnation_age: 200,
            stagnation_explore: 2,
            stagnation_individuals: 10,
            initial_individuals: 3,
            carry_over: 0.1,
            fitness: FitnessVariant::Code,
            terms: None,
            triggers: None,
            ge: GeParams::default(),
            combine_ge: GeParams { max_genome_length: 500, crossover_prob: 0.1, ..GeParams::default() },
            mutation: MutationRule::Fixed,
            stress: StressMutation::default(),
            fusion: Fusion::Faithful,
            one_phase_settle: ONE_PHASE_SETTLE,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LearnerConfigError {
    #[error("learner.{field}: {reason}")]
    Invalid { field: &'static str, reason: String },
}

impl LearnerConfig {
    pub fn validate(&self) -> Result<(), LearnerConfigError> {
        let bad = |field, reason: &str| Err(LearnerConfigError::Invalid { field, reason: reason.into() });
        if self.st.is_some_and(|st| st < 4) {
            return bad("st", "the storage threshold must be at least 4 (a genetic step needs two parents)");
        }
        if self.initial_individuals == 0 {
            return bad("initial_individuals", "must be at least 1");
        }
        if !(0.0..=1.0).contains(&self.carry_over) {
            return bad("carry_over", "must lie in [0, 1]");
        }
        if self.stagnation_explore > 0 && self.stagnation_individuals < 4 {
            return bad("stagnation_individuals", "must be at least 4 when the stagnation rule is on");
        }
        for (field, v) in
            [("stress.rise", self.stress.rise), ("stress.relax", self.stress.relax), ("stress.max", self.stress.max)]
        {
            if !(0.0..=1.0).contains(&v) {
                return Err(LearnerConfigError::Invalid { field, reason: format!("{v} is not in [0, 1]") });
            }
        }
        if self.mutation == MutationRule::Stress {
            for (field, base) in [("ge", self.ge.mutation_prob), ("combine_ge", self.combine_ge.mutation_prob)] {
                if self.stress.max < base {
                    return Err(LearnerConfigError::Invalid {
                        field: "stress.max",
                        reason: format!(
                            "{} is below learner.{field}.mutation_prob = {base} (stress would lower the rate)",
                            self.stress.max
                        ),
                    });
                }
            }
        }
        self.ge.validate().map_err(|e| LearnerConfigError::Invalid { field: "ge", reason: e.to_string() })?;
        self.combine_ge
            .validate()
            .map_err(|e| LearnerConfigError::Invalid { field: "combine_ge", reason: e.to_string() })
    }
}

/// Set of visited cells (a bitset with a count). The last cell inserted is kept
/// beside it: an agent stays in its cell for many steps, and with 10,000 agents each
/// bitset word it read at every step was a likely cache miss (`CellSet::insert` was 3 %
/// of the samples of a sparse 10,000-agent run).
#[derive(Clone, Debug)]
struct CellSet {
    bits: Vec<u64>,
    set: Vec<u32>,
    last: u32,
}

impl CellSet {
    fn new(cells: usize) -> Self {
        CellSet { bits: vec![0; cells.div_ceil(64)], set: Vec::new(), last: u32::MAX }
    }
    fn insert(&mut self, c: u32) {
        if c == self.last {
            return;
        }
        self.last = c;
        let (w, b) = ((c / 64) as usize, c % 64);
        if let Some(word) = self.bits.get_mut(w) {
            if *word & (1 << b) == 0 {
                *word |= 1 << b;
                self.set.push(c);
            }
        }
    }
    fn len(&self) -> usize {
        self.set.len()
    }
    fn clear(&mut self) {
        for &c in &self.set {
            self.bits[(c / 64) as usize] = 0;
        }
        self.set.clear();
        self.last = u32::MAX;
    }
}

/// Digest of a genome, for parity checks across transports: FNV-1a over whole codons
/// (one multiply per codon rather than per byte; it is computed at every adoption).
pub fn genome_digest(genome: &[u32]) -> u64 {
    let mut h = Fnv64::default().finish();
    for &c in genome {
        h = (h ^ u64::from(c)).wrapping_mul(0x0000_0100_0000_01B3);
    }
    h
}

/// The tree of a learner's individual: plain, or with the combine phase's GeneDict
/// genes in its controller slots.
fn tree_of(ind: &Individual, kind: &Kind) -> Result<Bt, BuildError> {
    match kind {
        Kind::Combine(dict) => {
            let p = ind.phenotype.as_deref().ok_or(BuildError::Empty)?;
            crate::program::build_tree(p, Some(dict)).map_err(BuildError::Program)
        }
        _ => build_tree(ind),
    }
}

/// The GeneDict update of the collect phase (REFERENCE §7.1): when the tree holds
/// exactly one action and it succeeded this tick, store the gene under the action's
/// class unless a fitter one is stored.
///
/// With shared gene objects (`shared`) a stored gene is compared by its fitness as it
/// stands now, and the entry takes the current gene's fitness field.
///
/// Returns whether the GeneDict changed (one-phase fusion waits for it to settle).
fn store_action(dict: &mut GeneDict, shared: Option<&mut SharedGenes>, tree: &Bt, gene: &Individual) -> bool {
    let mut acts = tree.actions();
    let (Some((leaf, Status::Success)), None) = (acts.next(), acts.next()) else { return false };
    let Some(key) = leaf.class_key() else { return false };
    let field = shared.as_ref().and_then(|sh| sh.dict.get(key));
    let better = dict.get(key).is_none_or(|s| field.map_or(s.fitness, |c| c.get()) < gene.fitness);
    if better {
        if let Some(p) = &gene.phenotype {
            let stored = StoredGene { phenotype: p.clone(), genome: gene.genome.clone(), fitness: gene.fitness };
            dict.insert(key.to_string(), stored);
            if let Some(sh) = shared {
                sh.dict.insert(key.to_string(), sh.cell.clone());
            }
            return true;
        }
    }
    false
}

/// Build the behaviour tree of a valid individual.
pub fn build_tree(ind: &Individual) -> Result<Bt, BuildError> {
    match &ind.phenotype {
        Some(p) => {
            let root = ge::parse_phenotype(p).map_err(|e| BuildError::Parse(e.to_string()))?;
            Bt::from_pnode(&root)
        }
        None => Err(BuildError::Empty),
    }
}

/// What a learner does beyond the BeTr-GEESE loop.
enum Kind {
    BetrGeese,
    GeeseBt,
    /// Multi-GEESE collect: fills its GeneDict every step (§7.1).
    Collect(GeneDict),
    /// Multi-GEESE combine: controller slots come from this GeneDict (§7.2).
    Combine(Arc<GeneDict>),
    /// Non-evolving: no lateral transfer, no genetic step.
    Fixed,
}

/// The GE parameters a learner of this kind uses.
#[inline(always)]
fn params<'a>(cfg: &'a LearnerConfig, kind: &Kind) -> &'a GeParams {
    match kind {
        Kind::Combine(_) => &cfg.combine_ge,
        _ => &cfg.ge,
    }
}

/// The fitness field of one gene object, when genes are shared objects as in the
/// reference code (REFERENCE §6.6) rather than copies (DESIGN §2).
///
/// In the Python a gene is one object: an agent's pool holds references to its
/// cell-mates' live genes, an adopter of a pool gene holds the donor's very object (and
/// zeroes the donor's fitness when it resets its own), and a GeneDict entry keeps
/// changing while any agent still runs the gene. Only the fitness of a gene is ever
/// written (codons and phenotype are immutable), so sharing that one field reproduces
/// all three. An `f64` in an atomic: learners must stay `Send`, and a trial steps them
/// one at a time, so relaxed ordering suffices.
#[derive(Debug)]
pub struct FitnessCell(AtomicU64);

impl FitnessCell {
    pub fn new(fitness: f64) -> Arc<FitnessCell> {
        Arc::new(FitnessCell(AtomicU64::new(fitness.to_bits())))
    }
    pub fn get(&self) -> f64 {
        f64::from_bits(self.0.load(Ordering::Relaxed))
    }
    pub fn set(&self, fitness: f64) {
        self.0.store(fitness.to_bits(), Ordering::Relaxed);
    }
}

/// A learner's side of shared gene objects ([`Learner::share_genes`]).
struct SharedGenes {
    /// The current gene's fitness field.
    cell: Arc<FitnessCell>,
    /// The fitness field of each pool entry, in pool order (`None`: a sender's gene
    /// that came without one). A stagnation rule's fresh individuals, which no agent
    /// holds, are the pool's last entries and have no field here.
    pool: Vec<Option<Arc<FitnessCell>>>,
    /// The fitness field of each GeneDict entry (collect phase).
    dict: HashMap<String, Arc<FitnessCell>>,
}

/// A pool entry's fitness field, by the address of its codons: one allocation per gene
/// object, as an adopted pool gene holds its donor's.
type HeldField = (*const u32, Arc<FitnessCell>);

/// Out of line and cold: the default run (copied genes) only tests for `shared` on its
/// hot path, and pays nothing else for it.
impl SharedGenes {
    /// The fields of this step's joining survivors, which stay in the pool.
    #[cold]
    #[inline(never)]
    fn keep_fields<G: Gene>(&mut self, genes: &[G], joining: &[Joining]) {
        for &j in joining {
            let cell = self.field_of(genes, j).cloned();
            self.pool.push(cell);
        }
    }

    /// The field of a joining survivor: this agent's own, or its sender's.
    fn field_of<'a, G: Gene>(&'a self, genes: &'a [G], j: Joining) -> Option<&'a Arc<FitnessCell>> {
        match j {
            Joining::Own => Some(&self.cell),
            Joining::Gene(i) | Joining::Mapped(_, i) => genes[i as usize].cell(),
        }
    }

    /// Read every pool entry (the pool, then this step's joining survivors) with its
    /// gene's fitness as it stands now, and keep the entries' fields in case one wins.
    /// Entries no agent holds (a stagnation rule's fresh individuals, pushed after the
    /// last kept field) keep their own fitness.
    #[cold]
    #[inline(never)]
    fn read_fields<G: Gene>(&mut self, genes: &[G], joining: &[Joining], pool: &mut [Candidate]) -> Vec<HeldField> {
        let joined = joining.iter().map(|&j| self.field_of(genes, j));
        let kept = pool.len() - joining.len();
        let fields = self.pool.iter().map(Option::as_ref).chain(std::iter::repeat(None)).take(kept).chain(joined);
        let held = pool
            .iter_mut()
            .zip(fields)
            .filter_map(|(c, cell)| {
                let cell = cell?;
                c.fitness = cell.get();
                Some((c.genome.as_ptr(), cell.clone()))
            })
            .collect();
        self.pool.clear();
        held
    }

    /// The adopted gene's field: a pool gene that won is the donor's object (the reset
    /// to `winner.fitness` zeroes the donor's fitness too); an offspring is a new one.
    #[cold]
    #[inline(never)]
    fn adopt(&mut self, held: &[HeldField], winner: &Individual, from_pool: bool) {
        let donor = held.iter().find(|(codons, _)| *codons == winner.genome.as_ptr());
        let cell = match donor {
            Some((_, cell)) if from_pool => cell.clone(),
            _ => FitnessCell::new(0.0),
        };
        cell.set(winner.fitness);
        self.cell = cell;
    }
}

/// A cell-mate's gene together with its fitness field, as an in-process trial with
/// shared gene objects hands it over ([`Learner::share_genes`]).
#[derive(Clone, Debug)]
pub struct SharedGene {
    pub msg: GeneMsg,
    pub cell: Option<Arc<FitnessCell>>,
}

impl Gene for SharedGene {
    fn step(&self) -> u64 {
        self.msg.step
    }
    fn sender(&self) -> AgentId {
        self.msg.from
    }
    fn genome(&self) -> &[u32] {
        &self.msg.genome
    }
    fn shared(&self) -> Option<&Arc<[u32]>> {
        Some(&self.msg.genome)
    }
    fn fitness(&self) -> f64 {
        self.cell.as_ref().map_or(self.msg.fitness, |c| c.get())
    }
    fn mapping(&self) -> GeneMapping {
        self.msg.mapping
    }
    fn cell(&self) -> Option<&Arc<FitnessCell>> {
        self.cell.as_ref()
    }
}

/// One agent: a BeTr-GEESE, GEESE-BT or Multi-GEESE learner, or a fixed controller.
pub struct Learner {
    id: AgentId,
    kind: Kind,
    terms: FitnessTerms,
    triggers: Triggers,
    /// Storage threshold ST in force (the config's, else the algorithm's own).
    st: usize,
    /// Diversity D of the current phenotype (for the D term).
    gene_d: f64,
    cfg: Arc<LearnerConfig>,
    grammar: Arc<Grammar>,
    view: View,
    gene: Individual,
    gene_digest: u64,
    tree: Bt,
    /// The current tree's behaviour class, kept with the tree (it changes only with it).
    class: BehaviourClass,
    pool: Vec<Individual>,
    /// Carry-over value R: the previous gene's fitness when it was replaced.
    carry: f64,
    age: u32,
    visited: CellSet,
    rng_bt: ChaCha8Rng,
    rng_ge: ChaCha8Rng,
    rng_ip: ChaCha8Rng,
    rng_loss: ChaCha8Rng,
    step: u64,
    regime: Regime,
    expected: Vec<AgentId>,
    have_percept: bool,
    /// Shared gene objects, if the trial asked for them ([`Learner::share_genes`]).
    shared: Option<Box<SharedGenes>>,
    /// Stress level of the `stress` mutation rule ([`StressMutation`]), in [0, 1].
    stress: f64,
    /// The fitness the outgoing gene reached at the last genetic step (`stress` rule).
    reached: Option<f64>,
    /// One-phase fusion, while this agent still collects: when it starts wiring.
    one_phase: Option<Box<OnePhase>>,
    /// One-phase fusion (both modes): map every received gene with this agent's own
    /// grammar. Cell-mates may be collecting or wiring, and a gene's claimed mapping is
    /// its sender's grammar's; read with the receiver's grammar, a codon string of the
    /// other mode is a new individual of the receiver's (GE genomes are plain integers).
    remap: bool,
}

/// A one-phase agent that still collects (issue 30.2): the combine grammar it will wire
/// with, and the step its GeneDict last changed.
struct OnePhase {
    combine: Arc<Grammar>,
    changed_at: u64,
}

/// What the learners of one process (the in-process trial, or one agent process) share.
///
/// The genetic step's scratch buffers: one set stays warm in the CPU caches, where one
/// per learner (tens of kilobytes each) did not. And the behaviour trees of adopted
/// phenotypes (below). Received genes need no cache: a gene message carries the sender's
/// mapping of its genome ([`GeneMsg::mapping`]).
#[derive(Default)]
pub struct GeneCache {
    received: ReceivedGenes,
    lt: LtScratch,
    workspace: ge::Workspace,
    /// The behaviour trees of the phenotypes adopted lately, by phenotype: a run adopts
    /// a few thousand distinct phenotypes over hundreds of thousands of genetic steps
    /// (99 % of adoptions repeat one), and parsing the phenotype and building its tree
    /// was a tenth of a learner's time. Cleared when [`TREES_KEPT`] are held.
    /// Hashed with foldhash: SipHash over a few hundred bytes per adoption cost 3 % of
    /// a run.
    trees: std::collections::HashMap<Arc<str>, Bt, foldhash::fast::FixedState>,
}

/// Most behaviour trees a [`GeneCache`] keeps.
const TREES_KEPT: usize = 8192;

/// Lateral transfer's buffers (indices into the step's genes), kept between learners.
#[derive(Default)]
struct LtScratch {
    by_sender: Vec<u32>,
    arrived: Vec<u32>,
    /// Survivors of the IP filter in id order; `None` is the learner itself.
    survivors: Vec<Option<u32>>,
    /// The survivors that join the pool, in order.
    joining: Vec<Joining>,
    /// Received genes whose claimed mapping was implausible, mapped here.
    mapped: Vec<Individual>,
}

impl LtScratch {
    fn clear(&mut self) {
        self.joining.clear();
        self.mapped.clear();
    }
}

/// A survivor of the IP filter that joins the pool.
#[derive(Clone, Copy)]
enum Joining {
    /// The learner's own gene.
    Own,
    /// A received gene (index into the step's genes) with the sender's mapping.
    Gene(u32),
    /// A received gene mapped here ([`LtScratch::mapped`]), and its index in the step's genes.
    Mapped(usize, u32),
}

/// How a received gene maps.
enum Received {
    /// The sender's claim is plausible and says valid.
    Claimed,
    /// Invalid (by the sender's word or mapped here): the gene is lost.
    Invalid,
    /// The claim was implausible; mapped here, valid (its fitness is the caller's to set).
    Mapped(Individual),
}

/// A gene a cell-mate offered, as a learner reads it: a [`GeneMsg`] (the in-process
/// trial's, and every learner's own), or a [`GeneRef`] into an agent process's inbox of
/// received genes.
pub trait Gene {
    fn step(&self) -> u64;
    fn sender(&self) -> AgentId;
    fn genome(&self) -> &[u32];
    /// The codons' shared allocation, if they have one (a winner then takes a
    /// reference rather than a copy).
    fn shared(&self) -> Option<&Arc<[u32]>>;
    fn fitness(&self) -> f64;
    /// The sender's mapping of the genome ([`GeneMsg::mapping`]).
    fn mapping(&self) -> GeneMapping;
    /// The gene object's fitness field, when genes are shared objects ([`SharedGene`]).
    fn cell(&self) -> Option<&Arc<FitnessCell>> {
        None
    }
}

impl Gene for GeneMsg {
    fn step(&self) -> u64 {
        self.step
    }
    fn sender(&self) -> AgentId {
        self.from
    }
    fn genome(&self) -> &[u32] {
        &self.genome
    }
    fn shared(&self) -> Option<&Arc<[u32]>> {
        Some(&self.genome)
    }
    fn fitness(&self) -> f64 {
        self.fitness
    }
    fn mapping(&self) -> GeneMapping {
        self.mapping
    }
}

/// A gene whose codons are borrowed from wherever its receiver keeps them.
///
/// An agent process hosting 100 of 1,000 agents receives ~700 genes a step. Decoded as
/// [`GeneMsg`]s, each genome was an allocation of its own, written afresh every step in
/// memory nine other processes had just pushed out of the caches; the process now
/// decodes every genome of a step into one reused buffer and lends them out as these.
#[derive(Clone, Copy, Debug)]
pub struct GeneRef<'a> {
    pub step: u64,
    pub from: AgentId,
    pub genome: &'a [u32],
    pub shared: Option<&'a Arc<[u32]>>,
    pub fitness: f64,
    pub mapping: GeneMapping,
}

impl<'a> GeneRef<'a> {
    /// A gene message, borrowed.
    pub fn of(g: &'a GeneMsg) -> GeneRef<'a> {
        GeneRef {
            step: g.step,
            from: g.from,
            genome: &g.genome,
            shared: Some(&g.genome),
            fitness: g.fitness,
            mapping: g.mapping,
        }
    }
}

impl Gene for GeneRef<'_> {
    fn step(&self) -> u64 {
        self.step
    }
    fn sender(&self) -> AgentId {
        self.from
    }
    fn genome(&self) -> &[u32] {
        self.genome
    }
    fn shared(&self) -> Option<&Arc<[u32]>> {
        self.shared
    }
    fn fitness(&self) -> f64 {
        self.fitness
    }
    fn mapping(&self) -> GeneMapping {
        self.mapping
    }
}

/// A received gene as a pool candidate, with the sender's mapping and fitness.
fn candidate<G: Gene>(g: &G) -> Candidate<'_> {
    let m = g.mapping();
    Candidate {
        genome: g.genome(),
        shared: g.shared(),
        phenotype: None,
        valid: m.valid,
        used_codons: if m.valid { m.used_codons as usize } else { 0 },
        depth: if m.valid { m.depth as usize } else { 0 },
        fitness: g.fitness(),
    }
}

/// Makes individuals of received genes.
#[derive(Default)]
struct ReceivedGenes {
    /// For received genes whose claimed mapping is implausible.
    mapper: ge::Mapper,
}

impl ReceivedGenes {
    /// How a received gene maps: the sender's mapping when it is plausible — a valid
    /// genome uses between one codon and all of them and has a depth — and mapped here
    /// otherwise.
    ///
    /// `remap`: map it here whatever the claim (one-phase fusion, whose cell-mates may
    /// map with another grammar).
    fn mapping<G: Gene>(&mut self, grammar: &Grammar, g: &G, params: &ge::GeParams, remap: bool) -> Received {
        let m = g.mapping();
        let plausible = !m.valid || ((1..=g.genome().len()).contains(&(m.used_codons as usize)) && m.depth >= 1);
        if plausible && !remap {
            return if m.valid { Received::Claimed } else { Received::Invalid };
        }
        let genome = g.shared().map_or_else(|| Arc::from(g.genome()), Arc::clone);
        let ind = ge::evaluate_stats_with(&mut self.mapper, grammar, genome, params);
        if ind.valid() {
            Received::Mapped(ind)
        } else {
            Received::Invalid
        }
    }

    /// The individual of a received gene (its fitness is the sender's): what
    /// [`ReceivedGenes::mapping`] says, as an individual of its own.
    #[cfg(test)]
    fn individual(&mut self, grammar: &Grammar, g: &GeneMsg, params: &ge::GeParams) -> Individual {
        match self.mapping(grammar, g, params, false) {
            Received::Claimed => candidate(g).take(),
            Received::Invalid => Individual { genome: g.genome.clone(), ..Individual::default() },
            Received::Mapped(mut ind) => {
                ind.fitness = g.fitness;
                ind
            }
        }
    }
}

impl GeneCache {
    pub fn new() -> GeneCache {
        GeneCache::default()
    }

    /// The behaviour tree of a valid individual, fresh (as [`build_tree`] makes it).
    fn tree(&mut self, ind: &Individual) -> Result<Bt, BuildError> {
        let Some(p) = &ind.phenotype else { return Err(BuildError::Empty) };
        if let Some(t) = self.trees.get(p) {
            return Ok(t.fresh());
        }
        let t = build_tree(ind)?;
        if self.trees.len() >= TREES_KEPT {
            self.trees.clear();
        }
        self.trees.insert(p.clone(), t.fresh());
        Ok(t)
    }
}

impl Learner {
    /// A fresh BeTr-GEESE learner that knows the hub, with its first random gene.
    pub fn new(
        id: AgentId,
        cfg: Arc<LearnerConfig>,
        grammar: Arc<Grammar>,
        geom: Geometry,
        hub: ObjectInfo,
        run_seed: u64,
    ) -> Result<Learner, BuildError> {
        Learner::with_role(id, cfg, grammar, geom, hub, run_seed, Role::BetrGeese)
    }

    /// A fresh agent of `role` that knows the hub. A learner starts with its first
    /// random gene; its tree must build (an error, never an empty tree).
    pub fn with_role(
        id: AgentId,
        cfg: Arc<LearnerConfig>,
        grammar: Arc<Grammar>,
        geom: Geometry,
        hub: ObjectInfo,
        run_seed: u64,
        role: Role,
    ) -> Result<Learner, BuildError> {
        let rng = |p| ChaCha8Rng::seed_from_u64(derive(run_seed, Owner::Agent(id), p));
        let mut rng_ge = rng(Purpose::Evolution);
        let mut view = View::new(geom, id);
        view.memory.insert(hub);
        let mut one_phase = None;
        let (kind, fixed_tree) = match role {
            Role::BetrGeese => (Kind::BetrGeese, None),
            Role::GeeseBt => (Kind::GeeseBt, None),
            Role::Collect => (Kind::Collect(GeneDict::new()), None),
            Role::OnePhase(combine) => {
                one_phase = Some(Box::new(OnePhase { combine, changed_at: 0 }));
                (Kind::Collect(GeneDict::new()), None)
            }
            Role::Combine(d) => (Kind::Combine(d), None),
            Role::Fixed(t) => (Kind::Fixed, Some(t)),
        };
        let (gene, tree) = match fixed_tree {
            Some(t) => (Individual { valid: true, fitness: 0.0, ..Individual::default() }, t),
            None => {
                // Three individuals are created (consuming their draws); the first is used.
                let p = params(&cfg, &kind);
                let mut first = None;
                for _ in 0..cfg.initial_individuals.max(1) {
                    let ind = ge::random_individual(&grammar, p, &mut rng_ge);
                    first.get_or_insert(ind);
                }
                let gene = match first {
                    Some(g) => g,
                    None => ge::random_individual(&grammar, p, &mut rng_ge),
                };
                let tree = tree_of(&gene, &kind)?;
                (gene, tree)
            }
        };
        let terms = cfg.terms.unwrap_or(match kind {
            Kind::GeeseBt => FitnessTerms::GEESE_BT,
            _ => FitnessTerms::BETR,
        });
        let triggers = cfg.triggers.unwrap_or(match kind {
            Kind::GeeseBt => Triggers::GeeseBt,
            _ => Triggers::Storage,
        });
        let st = cfg.st.unwrap_or_else(|| default_st(matches!(kind, Kind::Collect(_) | Kind::Combine(_))));
        let mut gene = gene;
        // A random individual's fitness is its D (fixed agents have none).
        let gene_d = if gene.fitness.is_finite() { gene.fitness } else { 0.0 };
        gene.fitness = match cfg.fitness {
            FitnessVariant::Code => 0.0,
            FitnessVariant::Paper => gene_d,
        };
        Ok(Learner {
            id,
            kind,
            terms,
            triggers,
            st,
            gene_d,
            gene_digest: genome_digest(&gene.genome),
            gene,
            class: tree.behaviour_class(),
            tree,
            pool: Vec::new(),
            carry: 0.0,
            age: 0,
            visited: CellSet::new(geom.cell_count()),
            rng_bt: rng(Purpose::Behaviour),
            rng_ge,
            rng_ip: rng(Purpose::Interaction),
            rng_loss: rng(Purpose::Loss),
            step: 0,
            regime: Regime::default(),
            expected: Vec::new(),
            have_percept: false,
            shared: None,
            stress: 0.0,
            reached: None,
            remap: one_phase.is_some(),
            one_phase,
            view,
            cfg,
            grammar,
        })
    }

    /// Hold genes as shared objects from now on, as the reference code does (REFERENCE
    /// §6.6; `fidelity.genes = shared`): the fitness of a gene lives in one
    /// [`FitnessCell`] that every agent holding the gene reads and writes. Pool entries
    /// are read with their holders' current fitness at the genetic step, an adopted pool
    /// gene is the donor's own (the adopter's reset zeroes it for both), and a GeneDict
    /// entry follows its gene's fitness. Only a trial that steps all learners in one
    /// process can offer it: cell-mates' genes must come as [`SharedGene`]s, with the
    /// fields of [`Learner::gene_cell`]. A fixed agent holds no gene, and is unchanged.
    pub fn share_genes(&mut self) {
        if self.is_fixed() || self.shared.is_some() {
            return;
        }
        let dict = match &self.kind {
            Kind::Collect(d) => d.iter().map(|(k, g)| (k.clone(), FitnessCell::new(g.fitness))).collect(),
            _ => HashMap::new(),
        };
        let pool = self.pool.iter().map(|g| Some(FitnessCell::new(g.fitness))).collect();
        self.shared = Some(Box::new(SharedGenes { cell: FitnessCell::new(self.gene.fitness), pool, dict }));
    }

    /// The current gene's fitness field, if genes are shared objects.
    pub fn gene_cell(&self) -> Option<&Arc<FitnessCell>> {
        self.shared.as_ref().map(|s| &s.cell)
    }

    /// Is this a fixed (non-evolving) agent?
    pub fn is_fixed(&self) -> bool {
        matches!(self.kind, Kind::Fixed)
    }

    /// This agent as a population member: its phenotype, genome, fitness and (for
    /// Multi-GEESE) GeneDict.
    pub fn member(&self) -> crate::program::Member {
        let mut dict = match &self.kind {
            Kind::Collect(d) => Some(d.clone()),
            Kind::Combine(d) => Some((**d).clone()),
            _ => None,
        };
        // Shared gene objects: the fitness fields as they stand now.
        if let (Some(d), Some(sh)) = (&mut dict, &self.shared) {
            for (k, g) in d.iter_mut() {
                if let Some(c) = sh.dict.get(k) {
                    g.fitness = c.get();
                }
            }
        }
        crate::program::Member {
            phenotype: self.gene.phenotype.as_deref().unwrap_or_default().to_string(),
            genome: Some(self.gene.genome.to_vec()),
            fitness: Some(self.fitness()),
            agent: Some(self.id),
            gene_dict: dict,
        }
    }

    /// The GeneDict (Multi-GEESE learners).
    /// What the live viewer shows of this agent when clicked.
    pub fn detail(&self) -> geese_proto::view::AgentDetail {
        geese_proto::view::AgentDetail {
            id: self.id,
            phenotype: self.gene.phenotype.as_deref().unwrap_or_default().to_string(),
            fitness: self.gene.fitness,
            class: self.class,
            tree: self.tree.render(),
            controllers: self
                .gene_dict()
                .map(|d| d.iter().map(|(k, g)| (k.clone(), g.phenotype.to_string())).collect())
                .unwrap_or_default(),
        }
    }

    pub fn gene_dict(&self) -> Option<&GeneDict> {
        match &self.kind {
            Kind::Collect(d) => Some(d),
            Kind::Combine(d) => Some(d),
            _ => None,
        }
    }

    pub fn id(&self) -> AgentId {
        self.id
    }
    pub fn gene(&self) -> &Individual {
        &self.gene
    }
    pub fn tree(&self) -> &Bt {
        &self.tree
    }
    pub fn fitness(&self) -> f64 {
        self.shared.as_ref().map_or(self.gene.fitness, |s| s.cell.get())
    }

    /// Phase 1: read the percept of the agent's cell; return the gene to publish to the
    /// cell (none while lateral transfer is off or the agent is not in the percept).
    pub fn begin_step(&mut self, percept: &Percept) -> Option<GeneMsg> {
        self.step = percept.step;
        self.regime = percept.regime;
        self.have_percept = self.view.load(percept);
        self.expected.clear();
        if !self.have_percept || !self.regime.lateral_transfer || self.is_fixed() {
            return None;
        }
        self.expected.extend(percept.agents.iter().filter(|a| a.id != self.id && a.live && a.learning).map(|a| a.id));
        // The world lists them in id order; lateral transfer relies on it.
        if !self.expected.is_sorted() {
            self.expected.sort_unstable();
        }
        Some(self.offer(self.step))
    }

    /// The gene this agent offers its cell-mates at `step`, if it takes part in it: its
    /// gene as it stands. Nothing in a step's percept changes it, so a process can send
    /// it ahead, as soon as the step before has finished.
    pub fn offer(&self, step: u64) -> GeneMsg {
        let g = &self.gene;
        let mapping = GeneMapping { valid: g.valid(), used_codons: g.used_codons as u32, depth: g.depth as u32 };
        GeneMsg { step, from: self.id, genome: g.genome.clone(), fitness: g.fitness, mapping }
    }

    /// Exchange this agent's blackboard with `board`. An in-process trial that gives
    /// every agent one blackboard (the reference code's single global `neighbourobj`
    /// map, REFERENCE §2.2) swaps the shared one in before the agent's step and out after
    /// it; agents in separate processes cannot share one (DESIGN §2).
    pub fn swap_blackboard(&mut self, board: &mut crate::view::KindMap) {
        std::mem::swap(&mut self.view.blackboard, board);
    }

    /// Hand back an intent this learner made and the world has applied (if any), so
    /// that its ops buffer serves the next intent: the view's buffer goes out with
    /// every intent, and an in-process trial that drops it allocates a new one per
    /// agent per step (~130,000 of the 200,000 agent-steps of `geese bench --steps
    /// 2000`).
    pub fn reuse_ops(&mut self, applied: Option<Intent>) {
        if let Some(Intent { mut ops, .. }) = applied {
            if self.view.ops.capacity() == 0 {
                ops.clear();
                self.view.ops = ops;
            }
        }
    }

    /// Cell-mates whose genes this step should bring (sorted by id).
    pub fn expected_mates(&self) -> &[AgentId] {
        &self.expected
    }

    /// Phase 2: act, learn, and return the intent. `genes` are the gene messages that
    /// arrived from the cell (any order; foreign, stale, duplicate and own messages are
    /// ignored). Without a percept the agent idles: an empty intent.
    ///
    /// `cache` holds the mapped genes of senders, shared by the learners of a process.
    #[inline]
    pub fn finish_step<G: Gene>(&mut self, genes: &[G], cache: &mut GeneCache) -> Intent {
        self.finish_step_with(cache, |_, _| genes)
    }

    /// [`Learner::finish_step`] whose cell-mates are chosen after the agent has acted:
    /// `mates(expected, cell)` gets the cell the tick's own moves took the agent to, may
    /// replace the expected cell-mates (sorted by id) and returns their genes. This is
    /// the reference code's order (REFERENCE §6.2 step 6: the genes of the agents in the
    /// cell the agent is in *after* acting), which only a trial whose agents take turns
    /// can offer; the lock-step protocol exchanges genes on the start-of-step cell.
    pub fn finish_step_with<'g, G: Gene + 'g>(
        &mut self,
        cache: &mut GeneCache,
        mates: impl FnOnce(&mut Vec<AgentId>, CellIdx) -> &'g [G],
    ) -> Intent {
        let mut stats = AgentStats::default();
        if !self.have_percept {
            return Intent { step: self.step, agent: self.id, heading: self.view.heading, ops: Vec::new(), stats };
        }
        // A shared gene's fitness may have been written by another holder since.
        if self.shared.is_some() {
            self.gene.fitness = self.fitness();
        }
        // 1–2. age, act.
        self.age += 1;
        self.tree.tick(&mut self.view, &mut self.rng_bt);
        // 3. visited cells (the cell after this tick's own moves), E.
        self.visited.insert(self.view.cell());
        let explore = self.visited.len().saturating_sub(1) as f64;
        // 4. fitness.
        self.gene.fitness = self.fitness_now(explore);
        if self.is_fixed() {
            return self.intent(stats);
        }
        if let Some(sh) = &self.shared {
            sh.cell.set(self.gene.fitness);
        }
        // 5. Multi-GEESE collect: the GeneDict update.
        if let Kind::Collect(dict) = &mut self.kind {
            let changed = store_action(dict, self.shared.as_deref_mut(), &self.tree, &self.gene);
            if let Some(op) = &mut self.one_phase {
                if changed {
                    op.changed_at = self.step;
                } else if self.step.saturating_sub(op.changed_at) >= u64::from(self.cfg.one_phase_settle)
                    && crate::program::is_complete(dict)
                {
                    self.start_wiring();
                    return self.intent(stats);
                }
            }
        }
        // Fusion variants that keep a wiring which delivered: no genetic step, and the
        // genes that arrive are not stored (the pool would only grow).
        if self.cfg.fusion.keeps_deliverers() && self.view.delivered > 0 && matches!(self.kind, Kind::Combine(_)) {
            return self.intent(stats);
        }
        // 6. sense: lateral transfer through the IP filter; its survivors join the pool
        //    (`cache.lt.joining`).
        let genes = mates(&mut self.expected, self.view.cell());
        cache.lt.clear();
        if self.regime.lateral_transfer {
            stats.lt_rate = self.lateral_transfer(genes, &mut stats.genes_lost, cache);
        }
        // 7–8. genetic operators and update. A pool that reaches ST is used and emptied
        // at once, so the survivors join it only as candidates borrowing their genomes.
        let storage_ready = match self.triggers {
            Triggers::Storage if self.cfg.fusion.is_patient() && matches!(self.kind, Kind::Combine(_)) => {
                if self.age < PATIENCE {
                    // Not yet: keep the first ST genes met (the pool would only grow).
                    if self.pool.len() < self.st {
                        self.keep_joining(genes, cache);
                    }
                    return self.intent(stats);
                }
                true
            }
            Triggers::Storage => true,
            Triggers::GeeseBt => {
                self.gene.fitness >= 0.0 && self.age > self.cfg.stagnation_age && self.view.delivered <= 0
            }
        };
        if storage_ready && self.pool.len() + cache.lt.joining.len() >= self.st {
            self.evolve(genes, cache);
            stats.genetic = GeneticTrigger::Storage;
            return self.intent(stats);
        }
        self.keep_joining(genes, cache);
        let stagnant = match self.triggers {
            Triggers::Storage => {
                self.cfg.stagnation_explore > 0
                    && self.age > self.cfg.stagnation_age
                    && (explore as u32) < self.cfg.stagnation_explore
            }
            Triggers::GeeseBt => self.gene.fitness <= 0.0 && self.age > GEESE_BT_STAGNATION_AGE,
        };
        if stagnant {
            for _ in 0..self.cfg.stagnation_individuals {
                let ind = ge::random_individual(&self.grammar, params(&self.cfg, &self.kind), &mut self.rng_ge);
                self.pool.push(ind);
            }
            self.evolve(genes, cache);
            stats.genetic = GeneticTrigger::Stagnation;
        }
        self.intent(stats)
    }

    /// One-phase fusion: this collect agent's GeneDict is complete and has settled, so
    /// from now on it evolves wirings of it (issue 30.2). Its GeneDict is frozen as the
    /// combine phase's is; it takes a fresh random wiring as its gene (from its own
    /// evolution stream), empties its pool of collect genes, and starts a gene's life
    /// (age, explored cells and delivered weight from zero; the collect gene's fitness
    /// is the carry-over R, as at any gene change).
    #[cold]
    #[inline(never)]
    fn start_wiring(&mut self) {
        let Some(op) = self.one_phase.take() else { return };
        let Kind::Collect(dict) = &self.kind else { return };
        let kind = Kind::Combine(Arc::new(dict.clone()));
        let p = params(&self.cfg, &kind);
        let mut gene = ge::random_individual(&op.combine, p, &mut self.rng_ge);
        let tree = match tree_of(&gene, &kind) {
            Ok(t) => t,
            Err(e) => {
                // Should a wiring not build (the run's combine grammar names a leaf the
                // engine lacks), the agent goes on collecting for good rather than stop.
                tracing::warn!(agent = self.id, "one-phase wiring does not build, the agent keeps collecting: {e}");
                return;
            }
        };
        self.kind = kind;
        self.grammar = op.combine;
        self.carry = self.fitness();
        gene.fitness = match self.cfg.fitness {
            FitnessVariant::Code => 0.0,
            FitnessVariant::Paper => gene.fitness,
        };
        if let Some(sh) = &mut self.shared {
            sh.cell = FitnessCell::new(gene.fitness);
            sh.pool.clear();
            sh.dict.clear();
        }
        self.pool.clear();
        self.view.delivered = 0;
        self.gene_digest = genome_digest(&gene.genome);
        self.gene = gene;
        self.class = tree.behaviour_class();
        self.tree = tree;
        self.visited.clear();
        self.age = 0;
    }

    /// Is this agent wiring (a combine agent, or a one-phase agent that has switched)?
    pub fn is_wiring(&self) -> bool {
        matches!(self.kind, Kind::Combine(_))
    }

    /// The running fitness after this tick (REFERENCE §6.5, §6.7): carry-over plus the
    /// terms in force.
    #[inline]
    fn fitness_now(&self, explore: f64) -> f64 {
        let t = self.terms;
        let mut a = match self.cfg.fitness {
            FitnessVariant::Code => self.cfg.carry_over * self.carry,
            FitnessVariant::Paper => self.cfg.carry_over * self.gene.fitness,
        };
        if t.e {
            a += explore;
        }
        if t.b {
            a += match self.cfg.fitness {
                FitnessVariant::Code => self.tree.successful_selectors() as f64,
                FitnessVariant::Paper => self.tree.paper_feedback(),
            };
        }
        if t.d {
            a += self.gene_d;
        }
        if t.c {
            a += self.view.carried_weight() as f64;
        }
        if t.f {
            a += self.view.delivered as f64;
        }
        if self.cfg.fusion.rewards_delivery() && matches!(self.kind, Kind::Combine(_)) {
            a += DELIVERY_WEIGHT * self.view.delivered as f64;
        }
        a
    }

    /// The step's intent: the tree's operations, heading and the agent's numbers.
    fn intent(&mut self, mut stats: AgentStats) -> Intent {
        stats.fitness = self.gene.fitness;
        stats.gene_digest = self.gene_digest;
        stats.class = self.class;
        Intent {
            step: self.step,
            agent: self.id,
            heading: self.view.heading,
            ops: std::mem::take(&mut self.view.ops),
            stats,
        }
    }

    /// Candidates = this agent plus the cell-mates whose genes arrived, in id order; each
    /// kept with probability IP; if more than one survives all survivors' genes go to the
    /// pool. Returns the number of survivors.
    ///
    /// Works on indices into `genes` in the process's shared scratch buffers: a learner
    /// with ~100 cell-mates allocating and growing three vectors per step was a tenth of
    /// its allocations.
    fn lateral_transfer<G: Gene>(&mut self, genes: &[G], lost: &mut u32, cache: &mut GeneCache) -> u32 {
        let LtScratch { by_sender, arrived, survivors, joining, mapped } = &mut cache.lt;
        // This step's messages by sender (a stable sort keeps the first of duplicates
        // first; the transports hand them over sorted, which it checks in one pass), then
        // one merge walk with the expected mates (sorted by id): k per agent, not k².
        by_sender.clear();
        by_sender.extend((0..genes.len() as u32).filter(|&i| genes[i as usize].step() == self.step));
        if !by_sender.is_sorted_by_key(|&i| genes[i as usize].sender()) {
            by_sender.sort_by_key(|&i| genes[i as usize].sender());
        }
        arrived.clear();
        let mut next = 0;
        for &mate in &self.expected {
            while by_sender.get(next).is_some_and(|&i| genes[i as usize].sender() < mate) {
                next += 1;
            }
            let msg = by_sender.get(next).copied().filter(|&i| genes[i as usize].sender() == mate);
            match msg.map(|i| (i, &genes[i as usize])) {
                Some((i, g))
                    if g.genome().len() <= params(&self.cfg, &self.kind).max_genome_length
                        && g.fitness().is_finite() =>
                {
                    // Injected receiver-side loss.
                    if self.regime.gene_loss > 0.0 && self.rng_loss.random::<f64>() < self.regime.gene_loss {
                        *lost += 1;
                    } else {
                        arrived.push(i);
                    }
                }
                Some(_) | None => *lost += 1,
            }
        }
        // Candidates in id order, self included (`None`).
        survivors.clear();
        let mut self_done = false;
        let ip = self.regime.ip;
        for &i in arrived.iter() {
            if !self_done && self.id < genes[i as usize].sender() {
                self_done = true;
                if self.rng_ip.random::<f64>() < ip {
                    survivors.push(None);
                }
            }
            if self.rng_ip.random::<f64>() < ip {
                survivors.push(Some(i));
            }
        }
        if !self_done && self.rng_ip.random::<f64>() < ip {
            survivors.push(None);
        }
        let kept = survivors.len() as u32;
        if survivors.len() > 1 {
            for s in survivors.iter() {
                let join = match *s {
                    None => Joining::Own,
                    Some(i) => {
                        let g = &genes[i as usize];
                        match cache.received.mapping(&self.grammar, g, params(&self.cfg, &self.kind), self.remap) {
                            Received::Invalid => {
                                *lost += 1;
                                continue;
                            }
                            Received::Claimed => Joining::Gene(i),
                            Received::Mapped(mut ind) => {
                                ind.fitness = g.fitness();
                                mapped.push(ind);
                                Joining::Mapped(mapped.len() - 1, i)
                            }
                        }
                    }
                };
                joining.push(join);
            }
        }
        kept
    }

    /// Put this step's joining survivors in the pool for good (the pool stays below ST).
    fn keep_joining<G: Gene>(&mut self, genes: &[G], cache: &mut GeneCache) {
        let LtScratch { joining, mapped, .. } = &mut cache.lt;
        if let Some(sh) = &mut self.shared {
            sh.keep_fields(genes, joining);
        }
        for j in joining.drain(..) {
            let ind = match j {
                Joining::Own => self.gene.clone(),
                Joining::Gene(i) => candidate(&genes[i as usize]).take(),
                Joining::Mapped(k, _) => std::mem::take(&mut mapped[k]),
            };
            self.pool.push(ind);
        }
    }

    /// Genetic step on the pool and this step's joining survivors, in that order, then
    /// adopt the winner (§5.6, §6.2 step 8).
    fn evolve<G: Gene>(&mut self, genes: &[G], cache: &mut GeneCache) {
        let GeneCache { lt, workspace, .. } = cache;
        let mut pool: Vec<Candidate> = Vec::with_capacity(self.pool.len() + lt.joining.len());
        pool.extend(self.pool.iter().map(Candidate::of));
        pool.extend(lt.joining.iter().map(|j| match *j {
            Joining::Own => Candidate::of(&self.gene),
            Joining::Gene(i) => candidate(&genes[i as usize]),
            Joining::Mapped(k, _) => Candidate::of(&lt.mapped[k]),
        }));
        let held = match self.shared.as_deref_mut() {
            None => Vec::new(),
            Some(sh) => sh.read_fields(genes, &lt.joining, &mut pool),
        };
        let mut p = params(&self.cfg, &self.kind);
        let stressed;
        if self.cfg.mutation == MutationRule::Stress {
            let now = self.fitness();
            self.stress = self.cfg.stress.next(self.stress, self.reached, now);
            self.reached = Some(now);
            stressed = GeParams { mutation_prob: self.cfg.stress.rate(p.mutation_prob, self.stress), ..p.clone() };
            p = &stressed;
        }
        let step = ge::genetic_step_on(workspace, &self.grammar, &mut pool, p, &mut self.rng_ge);
        self.pool.clear();
        let Ok((mut winner, stats)) = step else { return };
        winner.materialize(&self.grammar, p);
        let built = match &self.kind {
            Kind::Combine(_) => tree_of(&winner, &self.kind),
            _ => cache.tree(&winner),
        };
        let Ok(tree) = built else {
            // A phenotype of the run's own grammar whose tree does not build: the
            // grammar names a leaf the engine lacks, which `Learner::new` already
            // refused for the first gene; keep the current gene.
            tracing::warn!(agent = self.id, "adopted phenotype does not build a tree; gene kept");
            return;
        };
        self.carry = self.fitness();
        // D of the adopted phenotype, only where a formula reads it: parsing every
        // adopted phenotype for it cost a fifth of a BeTr-GEESE run's instructions.
        if self.terms.d || self.cfg.fitness == FitnessVariant::Paper {
            self.gene_d = winner.phenotype.as_deref().map(ge::diversity).unwrap_or(0.0);
        }
        winner.fitness = match self.cfg.fitness {
            FitnessVariant::Code => 0.0,
            FitnessVariant::Paper => self.gene_d,
        };
        if let Some(sh) = &mut self.shared {
            sh.adopt(&held, &winner, stats.winner_from_pool);
        }
        self.view.delivered = 0;
        self.gene_digest = genome_digest(&winner.genome);
        self.gene = winner;
        self.class = tree.behaviour_class();
        self.tree = tree;
        self.visited.clear();
        self.age = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grammars;

    /// The stress rule (issue 30.3): a stalled or fallen genetic step moves the stress
    /// level half-way to 1, an improving one halves it; the first changes nothing; the
    /// rate runs from GE's base to `max`. Constants outside [0, 1], and a `max` below
    /// the base rate, are refused naming the key.
    #[test]
    fn stress_rises_while_fitness_stalls_and_relaxes_when_it_recovers() {
        let r = StressMutation::default();
        assert_eq!(r.next(0.0, None, 5.0), 0.0);
        assert_eq!(r.next(0.0, Some(5.0), 5.0), 0.5, "a stall");
        assert_eq!(r.next(0.5, Some(5.0), 3.0), 0.75, "a fall");
        assert_eq!(r.next(0.75, Some(3.0), 4.0), 0.375, "a recovery");
        assert_eq!(r.rate(0.1, 0.0), 0.1);
        assert_eq!(r.rate(0.1, 1.0), 0.5);
        assert!((r.rate(0.1, 0.5) - 0.3).abs() < 1e-12);
        let bad = |stress: StressMutation, mutation| {
            LearnerConfig { stress, mutation, ..LearnerConfig::default() }.validate().unwrap_err().to_string()
        };
        let fixed = MutationRule::Fixed;
        assert_eq!(bad(StressMutation { rise: 1.5, ..r }, fixed), "learner.stress.rise: 1.5 is not in [0, 1]");
        assert_eq!(bad(StressMutation { relax: -0.1, ..r }, fixed), "learner.stress.relax: -0.1 is not in [0, 1]");
        assert_eq!(bad(StressMutation { max: f64::NAN, ..r }, fixed), "learner.stress.max: NaN is not in [0, 1]");
        let e = bad(StressMutation { max: 0.05, ..r }, MutationRule::Stress);
        assert!(e.starts_with("learner.stress.max: 0.05 is below learner.ge.mutation_prob = 0.1"), "{e}");
        assert!(LearnerConfig { stress: StressMutation { max: 0.05, ..r }, ..LearnerConfig::default() }
            .validate()
            .is_ok());
        assert_eq!("stress".parse::<MutationRule>(), Ok(MutationRule::Stress));
        assert_eq!(
            "heat".parse::<MutationRule>().unwrap_err(),
            "unknown mutation rule 'heat' (expected fixed or stress)"
        );
    }

    fn grammar(name: &str) -> Grammar {
        Grammar::parse(grammars::builtin(name).expect("built-in grammar")).expect("parses")
    }

    #[test]
    fn received_genes_take_the_senders_mapping_unless_implausible() {
        let forage = grammar("betr-foraging-avoid");
        let p = ge::GeParams::default();
        let genome: Arc<[u32]> = Arc::from([
            1213, 1114, 267, 757, 1875, 1236, 970, 1281, 1189, 134, 1240, 26, 1861, 1715, 960, 531, 1128, 479, 392,
        ]);
        let fresh = ge::evaluate(&forage, genome.clone(), &p);
        let msg = |mapping| GeneMsg { step: 1, from: 3, genome: genome.clone(), fitness: 2.0, mapping };
        let honest = GeneMapping { valid: true, used_codons: fresh.used_codons as u32, depth: fresh.depth as u32 };
        let mut cache = GeneCache::new();
        let a = cache.received.individual(&forage, &msg(honest), &p);
        assert!(a.valid() && Arc::ptr_eq(&a.genome, &genome));
        assert_eq!((a.used_codons, a.depth), (fresh.used_codons, fresh.depth));
        // Implausible claims are not taken: the gene is mapped here.
        for bad in [
            GeneMapping { valid: true, used_codons: 0, depth: 10 },
            GeneMapping { valid: true, used_codons: 99, depth: 10 },
            GeneMapping { valid: true, used_codons: 12, depth: 0 },
        ] {
            let b = cache.received.individual(&forage, &msg(bad), &p);
            assert_eq!((b.valid(), b.used_codons, b.depth), (true, fresh.used_codons, fresh.depth), "{bad:?}");
        }
        // A gene its sender calls invalid stays invalid (the receiver drops it).
        assert!(!cache.received.individual(&forage, &msg(GeneMapping::default()), &p).valid());
    }
}
