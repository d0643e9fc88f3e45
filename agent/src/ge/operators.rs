//! GE parameters, individuals and one genetic step ("exchange", REFERENCE.md §5.1, §5.6).
//!
//! Why this exists: this is the only place where genomes change. The step reproduces the
//! PonyGE2 pipeline the swarm code runs on an agent's storage pool — truncation
//! selection, variable one-point crossover within the used codons, per-codon int-flip
//! mutation within the used codons, evaluation with the diversity D, generational
//! replacement with elitism — and it runs for every agent every few world steps, so it
//! is written to be cheap while keeping PonyGE2's law: crossover pairs are drawn from
//! the attempts that survive the length check (`ge::crossover`), mutated codons by the
//! gaps between them, drawn while the child is mapped, a mutated child is mapped from
//! its first changed codon (`ge::tape`), the step stops making offspring once one
//! scores the grammar's ceiling of D, which no later one can beat (`ge::ceiling`),
//! offspring genomes live in one arena, buffers are reused, and only the winner's
//! phenotype becomes an `Arc<str>`.
//!
//! The pool is discarded after the step, so replacement is computed directly: the winner
//! is the first maximum (NaN smallest, stable) of the list "best `elite_size` pool members
//! inserted one by one at the front of the sorted offspring, cut to `population_size`".
//! For the defaults this is "the best pool member unless an offspring's D is strictly
//! larger".

use std::cmp::Ordering;
use std::sync::Arc;

use rand::Rng;
use serde::{Deserialize, Serialize};

use super::crossover::{Draw, PairSampler};
use super::derivations::{self, Derivation, Derivations};
use super::diversity::diversity;
use super::grammar::{fast_mod, Grammar};
use super::init::uniform_tree;
use super::mapper::{MapLimits, MapStats, Mapper};
use super::tape::{no_change, Mapped, Origin, Runs, Tape};

/// GE parameters (§5.1 defaults: the BeTr-GEESE / collect-phase values).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GeParams {
    /// Codons are integers in [0, codon_size].
    pub codon_size: u32,
    /// Offspring longer than this are discarded (crossover).
    pub max_genome_length: usize,
    /// Derivation-tree depth limit (mapping and initialisation).
    pub max_tree_depth: usize,
    /// Genome wraps allowed while mapping.
    pub max_wraps: usize,
    /// Probability that a selected pair is actually crossed over.
    pub crossover_prob: f64,
    /// Per-codon int-flip probability (within the used codons).
    pub mutation_prob: f64,
    /// Truncation-selection proportion.
    pub truncation: f64,
    /// Size of the replacement population (only bounds the candidates for the winner).
    pub population_size: usize,
    /// Best pool members carried into replacement.
    pub elite_size: usize,
    /// Offspring produced per genetic step.
    pub generation_size: usize,
}

impl Default for GeParams {
    fn default() -> Self {
        GeParams {
            codon_size: 2000,
            max_genome_length: 100,
            max_tree_depth: 10,
            max_wraps: 0,
            crossover_prob: 0.9,
            mutation_prob: 0.1,
            truncation: 0.5,
            population_size: 25,
            elite_size: 1,
            generation_size: 24,
        }
    }
}

/// A parameter value that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("GE parameter `{field}` {problem}")]
pub struct ParamsError {
    pub field: &'static str,
    pub problem: String,
}

impl GeParams {
    /// Check every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ParamsError> {
        let bad = |field: &'static str, problem: String| Err(ParamsError { field, problem });
        if self.codon_size < 2 {
            return bad("codon_size", format!("must be at least 2, got {}", self.codon_size));
        }
        if self.max_genome_length == 0 {
            return bad("max_genome_length", "must be at least 1, got 0".into());
        }
        if self.max_tree_depth == 0 {
            return bad("max_tree_depth", "must be at least 1, got 0".into());
        }
        for (field, p) in [("crossover_prob", self.crossover_prob), ("mutation_prob", self.mutation_prob)] {
            if !(0.0..=1.0).contains(&p) {
                return bad(field, format!("must be a probability in [0, 1], got {p}"));
            }
        }
        if !(self.truncation > 0.0 && self.truncation <= 1.0) {
            return bad("truncation", format!("must be in (0, 1], got {}", self.truncation));
        }
        if self.population_size == 0 {
            return bad("population_size", "must be at least 1, got 0".into());
        }
        if self.elite_size > self.population_size {
            return bad(
                "elite_size",
                format!("({}) must not exceed population_size ({})", self.elite_size, self.population_size),
            );
        }
        if self.generation_size == 0 {
            return bad("generation_size", "must be at least 1, got 0".into());
        }
        Ok(())
    }

    /// [`GeParams::validate`] plus the grammar-dependent check that `codon_size` exceeds
    /// the largest number of alternatives (needed by the initialiser's codon draw).
    pub fn validate_for(&self, grammar: &Grammar) -> Result<(), ParamsError> {
        self.validate()?;
        let n = grammar.max_alternatives();
        if (self.codon_size as usize) <= n {
            return Err(ParamsError {
                field: "codon_size",
                problem: format!(
                    "({}) must exceed the largest number of alternatives of a rule ({n})",
                    self.codon_size
                ),
            });
        }
        Ok(())
    }

    /// The mapper limits these parameters imply.
    pub fn map_limits(&self) -> MapLimits {
        MapLimits { max_tree_depth: self.max_tree_depth, max_wraps: self.max_wraps }
    }
}

impl From<&GeParams> for MapLimits {
    fn from(p: &GeParams) -> Self {
        p.map_limits()
    }
}

/// A GE individual.
#[derive(Debug, Clone)]
pub struct Individual {
    /// Shared: pool copies, gene messages and the gene cache hold the same codons.
    pub genome: Arc<[u32]>,
    /// Whether the genome maps to a phenotype.
    pub valid: bool,
    /// The phenotype string: `None` for an invalid individual, and for a valid one made
    /// by [`evaluate_stats_with`] until [`Individual::materialize`] writes it.
    pub phenotype: Option<Arc<str>>,
    /// Codons used by the mapping (0 when invalid).
    pub used_codons: usize,
    /// Derivation-tree depth (0 when invalid).
    pub depth: usize,
    /// Fitness; NaN for an invalid individual. Larger is better.
    pub fitness: f64,
}

impl Individual {
    /// Whether the genome mapped to a phenotype.
    pub fn valid(&self) -> bool {
        self.valid
    }

    /// Write the phenotype of a valid individual if it is not there yet (see
    /// [`evaluate_stats_with`]); returns it (`None` when invalid).
    pub fn materialize(&mut self, grammar: &Grammar, params: &GeParams) -> Option<&Arc<str>> {
        if self.valid && self.phenotype.is_none() {
            let mut text = String::with_capacity(256);
            let st = Mapper::new().map_into(grammar, &self.genome, params.map_limits(), &mut text);
            if st.valid {
                self.phenotype = Some(Arc::from(text));
            }
        }
        self.phenotype.as_ref()
    }
}

impl Default for Individual {
    /// An empty, invalid individual.
    fn default() -> Self {
        Individual { genome: Arc::from([]), valid: false, phenotype: None, used_codons: 0, depth: 0, fitness: f64::NAN }
    }
}

/// Map `genome` and give the individual its diversity D (NaN when invalid).
pub fn evaluate(grammar: &Grammar, genome: impl Into<Arc<[u32]>>, params: &GeParams) -> Individual {
    let genome = genome.into();
    let mut buf = String::with_capacity(256);
    let (st, fitness) = Mapper::new().map_into_scored(grammar, &genome, params.map_limits(), &mut buf);
    if st.valid {
        Individual {
            genome,
            valid: true,
            phenotype: Some(Arc::from(buf)),
            used_codons: st.used_codons,
            depth: st.depth,
            fitness,
        }
    } else {
        Individual { genome, ..Individual::default() }
    }
}

/// Map `genome` for its validity, used codons and depth only: no phenotype (see
/// [`Individual::materialize`]) and no D (fitness NaN, the caller's to set). This is
/// what a gene received by lateral transfer needs: in the pool it is ranked by the
/// sender's fitness, and its phenotype is needed only in the rare case that it wins.
/// `mapper` is the caller's, reused between calls.
pub fn evaluate_stats_with(
    mapper: &mut Mapper,
    grammar: &Grammar,
    genome: Arc<[u32]>,
    params: &GeParams,
) -> Individual {
    let st = mapper.map_stats(grammar, &genome, params.map_limits());
    Individual {
        genome,
        valid: st.valid,
        phenotype: None,
        used_codons: if st.valid { st.used_codons } else { 0 },
        depth: if st.valid { st.depth } else { 0 },
        fitness: f64::NAN,
    }
}

/// A new random individual (`uniform_tree`, §5.3) with fitness D.
pub fn random_individual<R: Rng + ?Sized>(grammar: &Grammar, params: &GeParams, rng: &mut R) -> Individual {
    let d = uniform_tree(grammar, params.codon_size, params.max_tree_depth, rng);
    let fitness = diversity(&d.phenotype);
    Individual {
        genome: d.genome.into(),
        valid: true,
        phenotype: Some(Arc::from(d.phenotype)),
        used_codons: d.used_codons,
        depth: d.depth,
        fitness,
    }
}

/// Total order on fitness values: larger is better, NaN is smaller than every number
/// (all NaNs equal), `-0.0 == 0.0`.
pub fn fitness_cmp(a: f64, b: f64) -> Ordering {
    match (a.is_nan(), b.is_nan()) {
        (true, true) => Ordering::Equal,
        (true, false) => Ordering::Less,
        (false, true) => Ordering::Greater,
        (false, false) => a.partial_cmp(&b).unwrap_or(Ordering::Equal),
    }
}

/// Sort best first (stable: equal fitness keeps its order).
pub fn sort_by_fitness_desc<M: Member>(pop: &mut [M]) {
    pop.sort_by(|a, b| fitness_cmp(b.fitness(), a.fitness()));
}

/// What a genetic step reads of a pool member: an [`Individual`], or a [`Candidate`]
/// that borrows one's parts.
pub trait Member {
    fn genome(&self) -> &[u32];
    fn fitness(&self) -> f64;
    /// Whether the genome maps, with its used codons and depth (0 when invalid).
    fn mapping(&self) -> (bool, usize, usize);
    /// Its phenotype, when known (a received gene's is not: it is mapped if it wins).
    fn phenotype(&self) -> Option<&Arc<str>>;
    /// The codons' shared allocation, if they have one (`ge::derivations` keys by it).
    fn shared(&self) -> Option<&Arc<[u32]>>;
    /// The member as an individual of its own (it may be left empty).
    fn take(&mut self) -> Individual;
}

impl Member for Individual {
    fn genome(&self) -> &[u32] {
        &self.genome
    }
    fn fitness(&self) -> f64 {
        self.fitness
    }
    fn mapping(&self) -> (bool, usize, usize) {
        (self.valid, self.used_codons, self.depth)
    }
    fn phenotype(&self) -> Option<&Arc<str>> {
        self.phenotype.as_ref()
    }
    fn shared(&self) -> Option<&Arc<[u32]>> {
        Some(&self.genome)
    }
    fn take(&mut self) -> Individual {
        std::mem::take(self)
    }
}

/// A pool member that borrows the genome (and phenotype) of an individual or a
/// received gene, with a fitness of its own.
///
/// A learner with ~100 cell-mates puts ~50 received genes in its pool every step and
/// empties it again in the same step's genetic step. As individuals, each one took and
/// gave back a reference to the sender's codons: two atomic operations on a cache line
/// of another agent's genome, per gene and receiver, though only the few parents that
/// cross are ever read. A candidate touches a genome only when it is read, and becomes an
/// individual only if it wins ([`Member::take`]).
#[derive(Clone, Copy, Debug)]
pub struct Candidate<'a> {
    pub genome: &'a [u32],
    /// The codons' shared allocation, when they have one: a winner takes a reference to
    /// it rather than a copy. Genes an agent process received are read from its inbox
    /// (`geese-agent`), and copied only if one wins.
    pub shared: Option<&'a Arc<[u32]>>,
    pub phenotype: Option<&'a Arc<str>>,
    pub valid: bool,
    pub used_codons: usize,
    pub depth: usize,
    pub fitness: f64,
}

impl<'a> Candidate<'a> {
    /// `ind` as a candidate, with its own fitness.
    pub fn of(ind: &'a Individual) -> Candidate<'a> {
        Candidate {
            genome: &ind.genome,
            shared: Some(&ind.genome),
            phenotype: ind.phenotype.as_ref(),
            valid: ind.valid,
            used_codons: ind.used_codons,
            depth: ind.depth,
            fitness: ind.fitness,
        }
    }
}

impl Member for Candidate<'_> {
    fn genome(&self) -> &[u32] {
        self.genome
    }
    fn fitness(&self) -> f64 {
        self.fitness
    }
    fn mapping(&self) -> (bool, usize, usize) {
        (self.valid, self.used_codons, self.depth)
    }
    fn phenotype(&self) -> Option<&Arc<str>> {
        self.phenotype
    }
    fn shared(&self) -> Option<&Arc<[u32]>> {
        self.shared
    }
    fn take(&mut self) -> Individual {
        Individual {
            genome: self.shared.map_or_else(|| Arc::from(self.genome), Arc::clone),
            valid: self.valid,
            phenotype: self.phenotype.cloned(),
            used_codons: self.used_codons,
            depth: self.depth,
            fitness: self.fitness,
        }
    }
}

/// Why a genetic step could not run. The pool is emptied regardless.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeError {
    #[error(
        "genetic step needs at least 2 parents, but truncation ({truncation}) of a pool of {pool} leaves {parents}"
    )]
    TooFewParents { pool: usize, parents: usize, truncation: f64 },
    #[error("parent {index} has an empty genome")]
    EmptyParent { index: usize },
    #[error("crossover produced only {produced} of {wanted} acceptable offspring in {attempts} attempts (parents too long for max_genome_length {max_genome_length}?)")]
    NoViableOffspring { produced: usize, wanted: usize, attempts: usize, max_genome_length: usize },
    #[error(transparent)]
    Params(#[from] ParamsError),
}

/// What happened inside one genetic step (for logging and tests).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepStats {
    /// Parents after truncation.
    pub parents: usize,
    /// Offspring made: `generation_size` or one more (pairs are never split), fewer
    /// once the winner is settled (`ge::ceiling`; [`Workspace::every_offspring`] makes
    /// them all).
    pub offspring: usize,
    /// Offspring invalid after mutation.
    pub invalid_offspring: usize,
    /// Crossover pairs discarded because a child mapped valid but too deep (pairs with
    /// a child too long or empty are never drawn, `ge::crossover`).
    pub discarded_pairs: usize,
    /// Whether the winner is a pool member rather than an offspring.
    pub winner_from_pool: bool,
    /// Whether the winning offspring took its parent's phenotype, deriving exactly like
    /// it (uncrossed, no mutation picking another alternative), instead of being mapped.
    pub winner_phenotype_inherited: bool,
}

/// Pairs drawn per wanted offspring before giving up (only children that map valid
/// but too deep make a drawn pair fail).
const ATTEMPTS_PER_OFFSPRING: usize = 1000;
/// Re-mutations of one offspring that mapped valid but too deep before it is kept as is.
const MAX_REMUTATIONS: usize = 1000;

/// An offspring inside the arena.
#[derive(Debug, Clone, Copy)]
struct Kid {
    start: usize,
    len: usize,
}

/// An offspring mapped before mutation.
#[derive(Debug, Clone, Copy)]
struct Crossed {
    kid: Kid,
    stats: MapStats,
    /// On the tape (when the grammar allows tapes); the mutations are drawn.
    taped: Option<Taped>,
}

/// A child mapped before mutation on the tape, or known from its parent's derivation.
#[derive(Debug, Clone, Copy)]
struct Taped {
    /// D before mutation.
    d: f64,
    /// Where the mutated child is mapped from: `None` when no mutation picks another
    /// alternative (it derives as before mutation), else from the state kept at the
    /// first codon whose mutation does, or from its first codon when its mapping
    /// before mutation was not made (read from its parent's kept derivation).
    resume: Option<Origin>,
    /// The runs of terminals of the mapping, when made on this step's tape.
    runs: Option<Runs>,
    /// The key of the parent's kept derivation ([`Derivations`]) it was read from.
    known: Option<usize>,
}

/// The best offspring of a genetic step so far.
#[derive(Debug, Clone, Copy)]
struct Best {
    /// Where it is in the arena.
    kid: Kid,
    /// Its D (NaN when invalid).
    fitness: f64,
    stats: MapStats,
    /// The parent it derives exactly like (uncrossed, no mutation picking another
    /// alternative), whose phenotype is then its own.
    same_as: Option<usize>,
    /// The runs of terminals of its mapping on the tape.
    runs: Option<Runs>,
    /// With `same_as`: the key of the parent's kept derivation it was read from.
    known: Option<usize>,
}

/// The codons a child's mutations range over (§5.6): its used codons when its mapping
/// is valid, its whole genome otherwise.
fn mutation_span(st: &MapStats, len: usize) -> usize {
    if st.valid {
        len.min(st.used_codons)
    } else {
        len
    }
}

fn too_deep(st: &MapStats, max_tree_depth: usize) -> bool {
    st.valid && max_tree_depth != 0 && st.depth > max_tree_depth
}

/// Upper bound for a crossover cut point / mutation range: the used codons of a valid
/// individual (clamped to its length), the whole genome of an invalid one.
fn used_span<M: Member>(ind: &M) -> usize {
    let len = ind.genome().len();
    match ind.mapping() {
        (true, used, _) if used >= 1 => used.min(len),
        _ => len,
    }
}

/// Independent trials with success probability `p`, visited by sampling the gaps
/// between successes (geometric, by inversion) instead of drawing once per trial: the
/// int-flip mutation tries every used codon of 24 offspring per genetic step, and with
/// p = 0.1 this draws about 3.6 numbers per offspring instead of about 26. The
/// distribution of the mutated positions is the same; the random stream is not.
#[derive(Debug, Clone, Copy)]
struct Bernoulli {
    p: f64,
    /// 1 / ln(1 − p).
    inv_ln_q: f64,
}

impl Bernoulli {
    fn new(p: f64) -> Bernoulli {
        Bernoulli { p, inv_ln_q: 1.0 / (1.0 - p).ln() }
    }

    /// The first successful trial from `i` on (`usize::MAX` if there is none), for
    /// visiting the successes of a range whose end is not known yet: the draws are those
    /// of [`Bernoulli::for_each`] up to its end.
    fn next_from<R: Rng + ?Sized>(&self, rng: &mut R, i: usize) -> usize {
        if self.p <= 0.0 {
            return usize::MAX;
        }
        if self.p >= 1.0 {
            return i;
        }
        let u: f64 = rng.random();
        i.saturating_add(((1.0 - u).ln() * self.inv_ln_q) as usize)
    }

    /// Call `hit` with each successful trial of `0..n`, in increasing order.
    fn for_each<R: Rng + ?Sized>(&self, rng: &mut R, n: usize, mut hit: impl FnMut(&mut R, usize)) {
        if self.p <= 0.0 {
            return;
        }
        if self.p >= 1.0 {
            (0..n).for_each(|i| hit(rng, i));
            return;
        }
        let mut i = 0usize;
        while i < n {
            // 1 − u ∈ (0, 1], so the gap is finite and ≥ 0.
            let u: f64 = rng.random();
            // Finite and ≥ 0, so truncation is the floor (`f64::floor` is a libm call
            // on the baseline x86-64 target).
            let gap = ((1.0 - u).ln() * self.inv_ln_q) as usize;
            if gap >= n - i {
                return;
            }
            i += gap;
            hit(rng, i);
            i += 1;
        }
    }
}

/// Buffers of a genetic step, kept by a caller that runs many (a learner), so that a
/// step allocates nothing but the winner.
#[derive(Debug, Default)]
pub struct Workspace {
    mapper: Mapper,
    arena: Vec<u32>,
    tape: Tape,
    /// The crossover pairs the parents allow.
    pairs: PairSampler,
    /// (position, new value) of the codons the mutations of a pair's children change.
    mutations: [Vec<(u32, u32)>; 2],
    /// Make all offspring even once the winner is settled (for statistics over
    /// offspring; the winner's law is the same).
    every_offspring: bool,
    /// Winners' phenotypes by the runs of terminals that make them.
    phenotypes: Phenotypes,
    /// Recent parents' derivations, for their uncrossed children.
    derivations: Derivations,
}

/// The phenotypes of recent winners, by the runs of terminals (ids of
/// `Compiled::runs`) whose texts make them: a run adopts a few thousand distinct
/// phenotypes over hundreds of thousands of genetic steps, so a winner's phenotype is
/// nearly always one written before, and shared rather than written again. Run ids are
/// a grammar's own, and a process may evolve with several grammars (Multi-GEESE), so
/// the key is the grammar's [`Uid`](super::grammar::Uid) followed by the runs.
#[derive(Debug, Default)]
struct Phenotypes {
    by_runs: std::collections::HashMap<Box<[u32]>, Arc<str>, foldhash::fast::FixedState>,
    key: Vec<u32>,
}

/// Most phenotypes a [`Phenotypes`] keeps (it is emptied when full).
const PHENOTYPES_KEPT: usize = 4096;

impl Phenotypes {
    /// The phenotype written by the runs of `grammar` that `runs` appends to a
    /// buffer, in order.
    fn text(&mut self, grammar: &Grammar, runs: impl FnOnce(&mut Vec<u32>)) -> Arc<str> {
        let uid = grammar.uid().0;
        self.key.clear();
        self.key.extend_from_slice(&[uid as u32, (uid >> 32) as u32]);
        runs(&mut self.key);
        if let Some(p) = self.by_runs.get(self.key.as_slice()) {
            return Arc::clone(p);
        }
        let compiled = grammar.compiled();
        let mut text = String::with_capacity(256);
        for &r in &self.key[2..] {
            text.push_str(&compiled.runs[r as usize].text);
        }
        let text: Arc<str> = Arc::from(text);
        if self.by_runs.len() >= PHENOTYPES_KEPT {
            self.by_runs.clear();
        }
        self.by_runs.insert(self.key.as_slice().into(), Arc::clone(&text));
        text
    }
}

impl Workspace {
    /// Buffers for steps that make every offspring, even after the winner is settled
    /// (`ge::ceiling`), so [`StepStats`] describes a whole generation.
    pub fn every_offspring() -> Workspace {
        Workspace { every_offspring: true, ..Workspace::default() }
    }
}

/// One genetic step on `pool` (§5.6); returns the winner with the fitness it was ranked
/// by (the caller resets it). The pool is emptied.
pub fn genetic_step<R: Rng + ?Sized>(
    grammar: &Grammar,
    pool: &mut Vec<Individual>,
    params: &GeParams,
    rng: &mut R,
) -> Result<Individual, GeError> {
    genetic_step_with_stats(grammar, pool, params, rng).map(|(w, _)| w)
}

/// [`genetic_step`] that also reports what happened.
pub fn genetic_step_with_stats<R: Rng + ?Sized>(
    grammar: &Grammar,
    pool: &mut Vec<Individual>,
    params: &GeParams,
    rng: &mut R,
) -> Result<(Individual, StepStats), GeError> {
    genetic_step_in(&mut Workspace::default(), grammar, pool, params, rng)
}

/// [`genetic_step_with_stats`] with the caller's buffers.
pub fn genetic_step_in<R: Rng + ?Sized>(
    ws: &mut Workspace,
    grammar: &Grammar,
    pool: &mut Vec<Individual>,
    params: &GeParams,
    rng: &mut R,
) -> Result<(Individual, StepStats), GeError> {
    let result = genetic_step_on(ws, grammar, pool, params, rng);
    pool.clear();
    result
}

/// What the offspring of one genetic step are made with.
#[derive(Clone, Copy)]
struct Env<'a> {
    grammar: &'a Grammar,
    compiled: &'a super::compiled::Compiled,
    start_rule: u32,
    limits: MapLimits,
    params: &'a GeParams,
    gaps: Bernoulli,
    /// Whether offspring are mapped on the tape.
    taped: bool,
}

/// Map a child before mutation. On the tape its mutations are drawn (into
/// `mutations`) as its codons are read — the draws of [`Bernoulli::for_each`] over
/// its used codons (its whole genome when invalid) — and the state at the first drawn
/// codon that picks another alternative is kept, for mapping the mutated child from
/// there. Off the tape an uncrossed valid child is a copy of its parent, whose mapping
/// is known.
#[allow(clippy::too_many_arguments)]
fn map_crossed<R: Rng + ?Sized, M: Member>(
    env: &Env<'_>,
    kid: Kid,
    parent: &M,
    cross: bool,
    genome: &[u32],
    tape: &mut Tape,
    mapper: &mut Mapper,
    derivations: &mut Derivations,
    mutations: &mut Vec<(u32, u32)>,
    rng: &mut R,
) -> Crossed {
    if !env.taped {
        let stats = match parent.mapping() {
            (true, used_codons, depth) if !cross => MapStats { valid: true, used_codons, depth },
            _ => mapper.map_stats(env.grammar, genome, env.limits),
        };
        return Crossed { kid, stats, taped: None };
    }
    let (gaps, codon_size) = (env.gaps, env.params.codon_size);
    mutations.clear();
    let mut next = gaps.next_from(rng, 0);
    // An uncrossed child of a parent whose derivation is kept: the mapping's draws,
    // made from the kept alternatives per codon, in the same order.
    let shared = if cross { None } else { parent.shared() };
    if let Some(known) = shared.and_then(|g| derivations.get(g, env.grammar.uid().0, env.limits)) {
        let mut changed = false;
        while next < known.stats.used_codons {
            let i = next;
            let new = rng.random_range(0..=codon_size);
            mutations.push((i as u32, new));
            next = gaps.next_from(rng, i + 1);
            let alts = u32::from(known.alts[i]);
            changed |= alts > 1 && genome[i] % alts != new % alts;
        }
        let eff = mutation_span(&known.stats, genome.len());
        while next < eff {
            mutations.push((next as u32, rng.random_range(0..=codon_size)));
            next = gaps.next_from(rng, next + 1);
        }
        let resume = changed.then_some(Origin::Start);
        let key = shared.map(derivations::key);
        return Crossed { kid, stats: known.stats, taped: Some(Taped { d: known.d, resume, runs: None, known: key }) };
    }
    // Otherwise mapped, and its parent's derivation kept when it has a shared genome.
    let recording = &mut derivations.recording;
    recording.clear();
    let mut fits = true;
    let m: Mapped =
        tape.map(env.compiled, env.start_rule, genome, env.limits, Origin::Start, |i, codon, alts, magic| {
            if shared.is_some() {
                match u8::try_from(alts) {
                    Ok(a) => recording.push(a),
                    Err(_) => fits = false,
                }
            }
            if i != next {
                return false;
            }
            let new = rng.random_range(0..=codon_size);
            mutations.push((i as u32, new));
            next = gaps.next_from(rng, i + 1);
            alts > 1 && fast_mod(codon, magic, alts) != fast_mod(new, magic, alts)
        });
    let eff = mutation_span(&m.stats, genome.len());
    while next < eff {
        mutations.push((next as u32, rng.random_range(0..=codon_size)));
        next = gaps.next_from(rng, next + 1);
    }
    if let (Some(g), true) = (shared, fits && m.stats.valid) {
        derivations.runs.clear();
        tape.phenotype_runs(m.runs, &mut derivations.runs);
        derivations.keep(g, env.grammar.uid().0, env.limits, m.stats, m.d);
    }
    let resume = m.mark.map(Origin::Mark);
    Crossed { kid, stats: m.stats, taped: Some(Taped { d: m.d, resume, runs: Some(m.runs), known: None }) }
}

/// Mutate a child within its used codons (its drawn mutations when on the tape) and
/// map and score the result; a child that maps valid but too deep is mutated again
/// from scratch (at most [`MAX_REMUTATIONS`] times). The flag says that the mutated
/// child derives exactly as before mutation: on the tape, no mutation picked another
/// alternative (and it was not mutated again). The last value is the runs of terminals
/// of the final mapping when it was made on the tape ([`Tape::phenotype_runs`]).
fn mutate_and_score<R: Rng + ?Sized>(
    env: &Env<'_>,
    child: Crossed,
    arena: &mut [u32],
    drawn: &[(u32, u32)],
    tape: &mut Tape,
    mapper: &mut Mapper,
    rng: &mut R,
) -> (MapStats, f64, bool, Option<Runs>) {
    let Env { grammar, params, gaps, .. } = *env;
    let Crossed { kid, stats: before, taped } = child;
    let genome = &mut arena[kid.start..kid.start + kid.len];
    let eff = mutation_span(&before, kid.len);
    let unchanged = matches!(taped, Some(Taped { resume: None, .. }));
    let (mut st, mut fitness, mut runs) = match taped {
        Some(Taped { d, resume, runs, .. }) => {
            for &(i, new) in drawn {
                genome[i as usize] = new;
            }
            match resume {
                None => (before, d, runs),
                Some(from) => {
                    let r = tape.map(env.compiled, env.start_rule, genome, env.limits, from, no_change);
                    (r.stats, r.d, Some(r.runs))
                }
            }
        }
        None => {
            gaps.for_each(rng, eff, |rng, i| genome[i] = rng.random_range(0..=params.codon_size));
            let (st, d) = mapper.map_scored(grammar, genome, env.limits);
            (st, d, None)
        }
    };
    let mut tries = 1;
    while too_deep(&st, params.max_tree_depth) && tries < MAX_REMUTATIONS && eff > 0 {
        gaps.for_each(rng, eff, |rng, i| genome[i] = rng.random_range(0..=params.codon_size));
        (st, fitness) = mapper.map_scored(grammar, genome, env.limits);
        runs = None;
        tries += 1;
    }
    (st, fitness, unchanged && tries == 1, runs)
}

/// [`genetic_step_in`] over a pool of any [`Member`]s (the caller empties it).
pub fn genetic_step_on<R: Rng + ?Sized, M: Member>(
    ws: &mut Workspace,
    grammar: &Grammar,
    pool: &mut [M],
    params: &GeParams,
    rng: &mut R,
) -> Result<(Individual, StepStats), GeError> {
    params.validate()?;
    let mut stats = StepStats::default();

    // 1. Truncation selection.
    sort_by_fitness_desc(pool);
    let cutoff = (pool.len() as f64 * params.truncation) as usize;
    if cutoff < 2 {
        return Err(GeError::TooFewParents { pool: pool.len(), parents: cutoff, truncation: params.truncation });
    }
    let parents = &pool[..cutoff];
    if let Some(index) = parents.iter().position(|p| p.genome().is_empty()) {
        return Err(GeError::EmptyParent { index });
    }
    stats.parents = cutoff;

    let limits = params.map_limits();
    let max_len = params.max_genome_length;
    let wanted = params.generation_size;
    let Workspace { mapper, arena, tape, mutations, pairs, every_offspring, phenotypes, derivations } = ws;
    arena.clear();
    tape.clear();
    // Offspring are mapped on the tape (`ge::tape`) when the grammar is scored from its
    // runs and genomes do not wrap; otherwise with the mapper.
    let compiled = grammar.compiled();
    let taped = limits.max_wraps == 0 && compiled.scored_from_runs;
    let start_rule = grammar.start();

    // The winner is settled, and making further offspring pointless, once one scores
    // the grammar's ceiling of D (`ge::ceiling`): a later offspring would have to score
    // strictly more. Offspring cannot win at all when the elite already has the ceiling,
    // or when the population keeps no offspring.
    let elites = params.elite_size.min(pool.len());
    let bound = grammar.d_bound(params.max_tree_depth);
    let ceiling = if *every_offspring { None } else { bound.d };
    let settled = |f: f64| ceiling.is_some_and(|c| f >= c);
    let offspring_can_win = elites < params.population_size && !(elites > 0 && settled(pool[0].fitness()));
    // Whether a child can map valid but too deep, which discards its whole pair; if
    // not, a pair's second child is only made when the first did not settle the winner.
    let deep_possible = bound.deep_last;
    let env = Env { grammar, compiled, start_rule, limits, params, gaps: Bernoulli::new(params.mutation_prob), taped };

    // 2. Variable one-point crossover until enough offspring exist, drawn from the
    // attempts that produce acceptable lengths (`ge::crossover`); 3–4. each pair's
    // children mutated within their used codons, remapped and scored with D at once,
    // remembering the first best (= first after a stable descending sort). On the tape a
    // child's mutations are drawn while it is mapped before mutation, and the mutated
    // child is mapped from its first codon whose new value picks another alternative
    // (it keeps its mapping and D when there is none). Pairs and mutations are
    // independent draws, so making them pair by pair, child by child, instead of all
    // crossovers first gives every offspring the same law (the random stream differs).
    pairs.plan(parents.iter().map(|p| (p.genome().len(), used_span(p))), max_len, params.crossover_prob);
    let max_attempts = wanted.saturating_mul(ATTEMPTS_PER_OFFSPRING);
    let mut attempts = 0usize;
    // The best offspring so far.
    let mut best: Option<Best> = None;
    let mut made = 0usize;
    if !pairs.viable() {
        return Err(GeError::NoViableOffspring { produced: 0, wanted, attempts: 0, max_genome_length: max_len });
    }
    'pairs: while offspring_can_win && made < wanted {
        let drawn = if attempts < max_attempts { pairs.draw(rng) } else { None };
        let Some(Draw { i, j, cut }) = drawn else {
            return Err(GeError::NoViableOffspring { produced: made, wanted, attempts, max_genome_length: max_len });
        };
        attempts += 1;
        let (p0, p1) = (&parents[i], &parents[j]);
        let (g0, g1) = (p0.genome(), p1.genome());
        let cross = cut.is_some();
        let (pt0, pt1) = cut.unwrap_or((g0.len(), g1.len()));
        let (len0, len1) = (pt0 + g1.len() - pt1, pt1 + g0.len() - pt0);
        let start = arena.len();
        if cross {
            arena.extend_from_slice(&g0[..pt0]);
            arena.extend_from_slice(&g1[pt1..]);
            arena.extend_from_slice(&g1[..pt1]);
            arena.extend_from_slice(&g0[pt0..]);
        } else {
            arena.extend_from_slice(g0);
            arena.extend_from_slice(g1);
        }
        let kids = [Kid { start, len: len0 }, Kid { start: start + len0, len: len1 }];
        let parents_of = [p0, p1];
        let crossed = |k: usize,
                       arena: &[u32],
                       tape: &mut Tape,
                       mapper: &mut Mapper,
                       derivations: &mut Derivations,
                       muts: &mut Vec<(u32, u32)>,
                       rng: &mut R| {
            let kid = kids[k];
            map_crossed(
                &env,
                kid,
                parents_of[k],
                cross,
                &arena[kid.start..kid.start + kid.len],
                tape,
                mapper,
                derivations,
                muts,
                rng,
            )
        };
        let first = crossed(0, arena, tape, mapper, derivations, &mut mutations[0], rng);
        let second = if deep_possible {
            let second = crossed(1, arena, tape, mapper, derivations, &mut mutations[1], rng);
            if too_deep(&first.stats, params.max_tree_depth) || too_deep(&second.stats, params.max_tree_depth) {
                arena.truncate(start);
                stats.discarded_pairs += 1;
                continue;
            }
            Some(second)
        } else {
            None
        };
        for k in 0..2 {
            let child = match (k, second) {
                (0, _) => first,
                (_, Some(c)) => c,
                (_, None) => crossed(1, arena, tape, mapper, derivations, &mut mutations[1], rng),
            };
            let (st, mut fitness, unchanged, runs) =
                mutate_and_score(&env, child, arena, &mutations[k], tape, mapper, rng);
            made += 1;
            if !st.valid {
                stats.invalid_offspring += 1;
                fitness = f64::NAN;
            }
            if best.is_none_or(|b| fitness_cmp(fitness, b.fitness) == Ordering::Greater) {
                let same_as = (unchanged && !cross).then_some([i, j][k]);
                let known = same_as.and(child.taped.and_then(|t| t.known));
                best = Some(Best { kid: child.kid, fitness, stats: st, same_as, runs, known });
            }
            if best.is_some_and(|b| settled(b.fitness)) {
                break 'pairs;
            }
        }
    }
    stats.offspring = made;

    // 5–6. Generational replacement with elites, stable sort, first is the winner.
    enum Cand {
        Pool(usize),
        Kid,
    }
    let candidates = (0..elites).rev().map(Cand::Pool).chain(std::iter::once(Cand::Kid)).take(params.population_size);
    let mut winner: Option<(Cand, f64)> = None;
    for c in candidates {
        let f = match c {
            Cand::Pool(j) => pool[j].fitness(),
            Cand::Kid => match best {
                Some(b) => b.fitness,
                None => continue,
            },
        };
        if winner.as_ref().is_none_or(|(_, wf)| fitness_cmp(f, *wf) == Ordering::Greater) {
            winner = Some((c, f));
        }
    }
    let ind = match (winner, best) {
        (Some((Cand::Pool(j), _)), _) => {
            stats.winner_from_pool = true;
            pool[j].take()
        }
        (Some((Cand::Kid, _)), Some(Best { kid, fitness, stats: st, same_as, runs, known })) => {
            let genome: Arc<[u32]> = Arc::from(&arena[kid.start..kid.start + kid.len]);
            if st.valid {
                // Only the winner's phenotype is ever written out: its parent's when it
                // derives like it (known to the parent, or written from the runs of the
                // parent's kept derivation), else the text of the runs its mapping on
                // the tape wrote (either held already when a winner wrote the same
                // runs), else mapped.
                let kept = known.and_then(|k| derivations.by_key(k));
                let phenotype = match (same_as.and_then(|p| pool[p].phenotype()), runs, kept) {
                    (Some(p), _, _) => {
                        stats.winner_phenotype_inherited = true;
                        Arc::clone(p)
                    }
                    (None, Some(runs), _) => phenotypes.text(grammar, |key| tape.phenotype_runs(runs, key)),
                    (None, None, Some(Derivation { phenotype: Some(p), .. })) => {
                        stats.winner_phenotype_inherited = true;
                        Arc::clone(p)
                    }
                    (None, None, Some(d)) => {
                        stats.winner_phenotype_inherited = true;
                        let text = phenotypes.text(grammar, |key| key.extend_from_slice(&d.runs));
                        d.phenotype = Some(Arc::clone(&text));
                        text
                    }
                    (None, None, None) => {
                        let mut text = String::with_capacity(256);
                        mapper.map_into(grammar, &genome, limits, &mut text);
                        Arc::from(text)
                    }
                };
                Individual {
                    genome,
                    valid: true,
                    phenotype: Some(phenotype),
                    used_codons: st.used_codons,
                    depth: st.depth,
                    fitness,
                }
            } else {
                Individual { genome, ..Individual::default() }
            }
        }
        // Unreachable: population_size ≥ 1 and at least one offspring exist.
        _ => {
            return Err(GeError::Params(ParamsError { field: "population_size", problem: "must be at least 1".into() }))
        }
    };
    Ok((ind, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::mapper::map_genome;
    use crate::ge::mapper::tests::{forge_golden, grammar, sf_golden, test_new_golden};
    use crate::ge::testdata::{FORGE, SF, TEST_NEW};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use serde::de::value::{Error as DeError, MapDeserializer};

    fn pool_of(g: &Grammar, params: &GeParams, rng: &mut ChaCha8Rng, n: usize) -> Vec<Individual> {
        (0..n).map(|_| random_individual(g, params, rng)).collect()
    }

    /// The gap sampler mutates each position independently with probability p: the
    /// per-position frequencies and the mean count match, and p = 0 / p = 1 are exact.
    #[test]
    fn bernoulli_gaps_hit_each_position_with_probability_p() {
        // Both ways of visiting the successes.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (n, trials) = (30usize, 200_000usize);
        for p in [0.1, 0.5] {
            let b = Bernoulli::new(p);
            let mut hits = vec![0u32; n];
            let mut last = None;
            for _ in 0..trials {
                b.for_each(&mut rng, n, |_, i| {
                    assert!(last.is_none_or(|l| i > l), "positions must increase");
                    last = Some(i);
                    hits[i] += 1;
                });
                last = None;
            }
            // Visited without knowing the end in advance, as the genetic step does.
            let mut next_hits = vec![0u32; n];
            for _ in 0..trials {
                let mut i = b.next_from(&mut rng, 0);
                while i < n {
                    next_hits[i] += 1;
                    i = b.next_from(&mut rng, i + 1);
                }
            }
            let sd = (p * (1.0 - p) / trials as f64).sqrt();
            for (i, (&h, &g)) in hits.iter().zip(&next_hits).enumerate() {
                for (how, h) in [("for_each", h), ("next_from", g)] {
                    let f = f64::from(h) / trials as f64;
                    assert!((f - p).abs() < 6.0 * sd, "p {p}, {how}: position {i} hit with frequency {f}");
                }
            }
        }
        assert_eq!(Bernoulli::new(0.0).next_from(&mut rng, 3), usize::MAX);
        assert_eq!(Bernoulli::new(1.0).next_from(&mut rng, 3), 3);
        let mut count = |p: f64| {
            let mut k = 0;
            Bernoulli::new(p).for_each(&mut rng, 17, |_, _| k += 1);
            k
        };
        assert_eq!(count(0.0), 0);
        assert_eq!(count(1.0), 17);
    }

    #[test]
    fn defaults_match_table_1() {
        let p = GeParams::default();
        assert_eq!(p.codon_size, 2000);
        assert_eq!(p.max_genome_length, 100);
        assert_eq!(p.max_tree_depth, 10);
        assert_eq!(p.max_wraps, 0);
        assert_eq!(p.crossover_prob, 0.9);
        assert_eq!(p.mutation_prob, 0.1);
        assert_eq!(p.truncation, 0.5);
        assert_eq!(p.population_size, 25);
        assert_eq!(p.elite_size, 1);
        assert_eq!(p.generation_size, 24);
        assert_eq!(p.validate(), Ok(()));
        assert_eq!(p.validate_for(&grammar(FORGE)), Ok(()));
    }

    #[test]
    fn validate_names_the_bad_field() {
        let cases: Vec<(&str, GeParams)> = vec![
            ("codon_size", GeParams { codon_size: 1, ..Default::default() }),
            ("max_genome_length", GeParams { max_genome_length: 0, ..Default::default() }),
            ("max_tree_depth", GeParams { max_tree_depth: 0, ..Default::default() }),
            ("crossover_prob", GeParams { crossover_prob: 1.5, ..Default::default() }),
            ("mutation_prob", GeParams { mutation_prob: f64::NAN, ..Default::default() }),
            ("truncation", GeParams { truncation: 0.0, ..Default::default() }),
            ("population_size", GeParams { population_size: 0, elite_size: 0, ..Default::default() }),
            ("elite_size", GeParams { elite_size: 26, ..Default::default() }),
            ("generation_size", GeParams { generation_size: 0, ..Default::default() }),
        ];
        for (field, p) in cases {
            let e = p.validate().expect_err(field);
            assert_eq!(e.field, field);
            assert!(e.to_string().contains(field), "{e}");
        }
        let e = GeParams { codon_size: 7, ..Default::default() }.validate_for(&grammar(FORGE)).expect_err("7");
        assert_eq!(e.field, "codon_size");
        assert!(GeParams { codon_size: 8, ..Default::default() }.validate_for(&grammar(FORGE)).is_ok());
    }

    #[test]
    fn serde_defaults_and_unknown_fields() {
        let partial =
            MapDeserializer::<_, DeError>::new(vec![("codon_size", 1000u64), ("max_genome_length", 500)].into_iter());
        let p = GeParams::deserialize(partial).expect("partial params");
        assert_eq!(p, GeParams { codon_size: 1000, max_genome_length: 500, ..Default::default() });
        let unknown = MapDeserializer::<_, DeError>::new(vec![("codon_sise", 1000u64)].into_iter());
        let e = GeParams::deserialize(unknown).expect_err("unknown field accepted");
        assert!(e.to_string().contains("codon_sise"), "{e}");
    }

    #[test]
    fn evaluate_golden_vectors() {
        let p = GeParams::default();
        for (gram, cases) in [(FORGE, forge_golden()), (SF, sf_golden())] {
            let g = grammar(gram);
            for (genome, used, depth, ph) in cases {
                let ind = evaluate(&g, genome, &p);
                assert!(ind.valid());
                assert_eq!(ind.used_codons, used);
                assert_eq!(ind.depth, depth);
                assert_eq!(ind.phenotype.as_deref(), Some(ph.as_str()));
                assert_eq!(ind.fitness, diversity(&ph));
            }
        }
        let ds: Vec<f64> = forge_golden().into_iter().map(|c| evaluate(&grammar(FORGE), c.0, &p).fitness).collect();
        assert_eq!(ds, vec![5.5556, 8.3333, 5.5556]);
        let (genome, _, _, _) = test_new_golden();
        let combine = GeParams { max_genome_length: 500, crossover_prob: 0.1, ..Default::default() };
        assert_eq!(evaluate(&grammar(TEST_NEW), genome, &combine).fitness, 6.9444);
        for genome in crate::ge::mapper::tests::forge_invalid() {
            let ind = evaluate(&grammar(FORGE), genome, &p);
            assert!(!ind.valid());
            assert!(ind.fitness.is_nan());
        }
    }

    #[test]
    fn random_individuals_are_valid_and_scored() {
        let g = grammar(FORGE);
        let p = GeParams::default();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..100 {
            let ind = random_individual(&g, &p, &mut rng);
            assert!(ind.valid());
            let again = evaluate(&g, ind.genome.clone(), &p);
            assert_eq!(again.phenotype, ind.phenotype);
            assert_eq!(again.used_codons, ind.used_codons);
            assert_eq!(again.depth, ind.depth);
            assert_eq!(again.fitness, ind.fitness);
            assert!(ind.fitness > 0.0);
        }
    }

    #[test]
    fn ordering_nan_smallest_and_stable() {
        assert_eq!(fitness_cmp(f64::NAN, -1e300), Ordering::Less);
        assert_eq!(fitness_cmp(0.0, f64::NAN), Ordering::Greater);
        assert_eq!(fitness_cmp(f64::NAN, f64::NAN), Ordering::Equal);
        assert_eq!(fitness_cmp(-0.0, 0.0), Ordering::Equal);
        assert_eq!(fitness_cmp(1.0, 2.0), Ordering::Less);
        let mk = |tag: u32, f: f64| Individual { genome: Arc::from([tag]), fitness: f, ..Individual::default() };
        let mut v = vec![mk(0, f64::NAN), mk(1, 1.0), mk(2, 3.0), mk(3, 1.0), mk(4, f64::NAN), mk(5, 3.0), mk(6, -2.0)];
        sort_by_fitness_desc(&mut v);
        let order: Vec<u32> = v.iter().map(|i| i.genome[0]).collect();
        assert_eq!(order, vec![2, 5, 1, 3, 6, 0, 4]);
    }

    #[test]
    fn too_few_parents_is_an_error_and_clears_the_pool() {
        let g = grammar(FORGE);
        let p = GeParams::default();
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let mut pool = pool_of(&g, &p, &mut rng, 3);
        let e = genetic_step(&g, &mut pool, &p, &mut rng).expect_err("3 individuals give 1 parent");
        assert_eq!(e, GeError::TooFewParents { pool: 3, parents: 1, truncation: 0.5 });
        assert!(pool.is_empty());
        assert!(e.to_string().contains("at least 2 parents"), "{e}");
        let mut pool = pool_of(&g, &p, &mut rng, 4);
        assert!(genetic_step(&g, &mut pool, &p, &mut rng).is_ok());
        assert!(pool.is_empty());
        let bad = GeParams { truncation: 2.0, ..Default::default() };
        let mut pool = pool_of(&g, &p, &mut rng, 8);
        let e = genetic_step(&g, &mut pool, &bad, &mut rng).expect_err("bad params");
        assert!(matches!(e, GeError::Params(ParamsError { field: "truncation", .. })), "{e:?}");
        let mut pool = pool_of(&g, &p, &mut rng, 7);
        pool[0].genome = Arc::from([]);
        pool[0].fitness = 100.0;
        let e = genetic_step(&g, &mut pool, &p, &mut rng).expect_err("empty parent");
        assert_eq!(e, GeError::EmptyParent { index: 0 });
    }

    #[test]
    fn elite_wins_unless_an_offspring_is_strictly_better() {
        let g = grammar(FORGE);
        let p = GeParams::default();
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for round in 0..50 {
            let mut pool = pool_of(&g, &p, &mut rng, 7);
            // Running fitness of stored genes: large for the first, so it is the elite.
            for (k, ind) in pool.iter_mut().enumerate() {
                ind.fitness = if k == 3 { 1000.0 } else { k as f64 };
            }
            let elite_genome = pool[3].genome.clone();
            let (w, st) = genetic_step_with_stats(&g, &mut pool, &p, &mut rng).expect("step");
            assert!(st.winner_from_pool, "round {round}");
            assert_eq!(w.genome, elite_genome);
            assert_eq!(w.fitness, 1000.0);
            assert!(pool.is_empty());
        }
        // With a zero-fitness elite, the best offspring (D > 0) wins; its fields agree with
        // a fresh evaluation of its genome.
        let mut won_by_kid = 0;
        for _ in 0..50 {
            let mut pool = pool_of(&g, &p, &mut rng, 7);
            pool.iter_mut().for_each(|i| i.fitness = 0.0);
            let (w, st) =
                genetic_step_in(&mut Workspace::every_offspring(), &g, &mut pool, &p, &mut rng).expect("step");
            assert_eq!(st.offspring, 24);
            assert!(st.parents == 3);
            if !st.winner_from_pool {
                won_by_kid += 1;
                assert!(w.valid());
                assert!(w.fitness > 0.0);
                assert!(w.genome.len() <= p.max_genome_length);
                let again = evaluate(&g, w.genome.clone(), &p);
                assert_eq!(again.phenotype, w.phenotype);
                assert_eq!(again.used_codons, w.used_codons);
                assert_eq!(again.depth, w.depth);
                assert_eq!(again.fitness, w.fitness);
            }
        }
        assert!(won_by_kid >= 45, "{won_by_kid}");
        // Ties favour the elite: elite fitness equal to the maximum D any forge phenotype
        // can reach (13.8889) can never be beaten strictly, and no offspring is made.
        let mut pool = pool_of(&g, &p, &mut rng, 7);
        pool.iter_mut().for_each(|i| i.fitness = 13.8889);
        let first = pool[0].genome.clone();
        let (w, st) = genetic_step_with_stats(&g, &mut pool, &p, &mut rng).expect("step");
        assert!(st.winner_from_pool);
        assert_eq!(st.offspring, 0);
        assert_eq!(w.genome, first, "stable sort keeps the first of equal pool members");
    }

    #[test]
    fn stopping_at_the_ceiling_keeps_the_winner() {
        // The same pools and random stream, with and without stopping once an offspring
        // scores the ceiling: the same winner, from fewer offspring.
        let (mut made, mut full) = (0usize, 0usize);
        for text in [FORGE, SF, TEST_NEW] {
            let g = grammar(text);
            let p = GeParams { max_genome_length: if text == TEST_NEW { 500 } else { 100 }, ..Default::default() };
            let mut rng = ChaCha8Rng::seed_from_u64(31);
            for round in 0..150 {
                let mut pool = pool_of(&g, &p, &mut rng, 7 + round % 5);
                // Elites below, at and above the ceilings (13.8889, 16.6667, 8.3333).
                let top = [0.0, 5.0, 8.3333, 13.8889, 16.6667, 20.0][round % 6];
                pool.iter_mut().enumerate().for_each(|(k, i)| i.fitness = top - k as f64);
                let mut again = pool.clone();
                let seed: u64 = rng.random();
                let run = |ws: &mut Workspace, pool: &mut Vec<Individual>| {
                    genetic_step_in(ws, &g, pool, &p, &mut ChaCha8Rng::seed_from_u64(seed)).expect("step")
                };
                let (w, st) = run(&mut Workspace::default(), &mut pool);
                let (w_full, st_full) = run(&mut Workspace::every_offspring(), &mut again);
                assert_eq!(w.genome, w_full.genome, "round {round}");
                assert_eq!(w.fitness.to_bits(), w_full.fitness.to_bits());
                assert_eq!(w.phenotype, w_full.phenotype);
                assert_eq!(st.winner_from_pool, st_full.winner_from_pool);
                made += st.offspring;
                full += st_full.offspring;
            }
        }
        assert!(made * 2 < full, "{made} of {full} offspring made");
    }

    #[test]
    fn elite_order_with_several_elites_is_reversed() {
        // PonyGE2 inserts the elites one by one at the front, so with equal fitness the
        // last elite ends up first.
        let g = grammar(FORGE);
        let p = GeParams { elite_size: 3, ..Default::default() };
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        let mut pool = pool_of(&g, &p, &mut rng, 8);
        for (k, ind) in pool.iter_mut().enumerate() {
            ind.fitness = if k < 3 { 500.0 } else { 0.0 };
        }
        let third = pool[2].genome.clone();
        let w = genetic_step(&g, &mut pool, &p, &mut rng).expect("step");
        assert_eq!(w.genome, third);
        // population_size == elite_size: offspring cannot win.
        let p = GeParams { elite_size: 1, population_size: 1, ..Default::default() };
        let mut pool = pool_of(&g, &p, &mut rng, 8);
        pool.iter_mut().for_each(|i| i.fitness = f64::NAN);
        let (w, st) = genetic_step_with_stats(&g, &mut pool, &p, &mut rng).expect("step");
        assert!(st.winner_from_pool);
        assert!(w.fitness.is_nan());
    }

    #[test]
    fn deterministic_for_a_seed() {
        let g = grammar(FORGE);
        let p = GeParams::default();
        let run = |seed: u64| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let mut out = Vec::new();
            for _ in 0..20 {
                let mut pool = pool_of(&g, &p, &mut rng, 7);
                pool.iter_mut().for_each(|i| i.fitness = 0.0);
                let w = genetic_step(&g, &mut pool, &p, &mut rng).expect("step");
                out.push((w.genome, w.fitness.to_bits()));
            }
            out
        };
        assert_eq!(run(42), run(42));
        assert_ne!(run(42), run(43));
    }

    fn invalid_rate(text: &str, max_genome_length: usize) -> f64 {
        let g = grammar(text);
        let p = GeParams { max_genome_length, ..Default::default() };
        let mut rng = ChaCha8Rng::seed_from_u64(99);
        let (mut invalid, mut total) = (0usize, 0usize);
        for _ in 0..400 {
            // Parents drawn without regard to D, as in the reference measurement (selecting
            // the highest-D GEESE-BT parents favours larger trees and raises the rate).
            let mut pool = pool_of(&g, &p, &mut rng, 7);
            pool.iter_mut().for_each(|i| i.fitness = 0.0);
            let (_, st) =
                genetic_step_in(&mut Workspace::every_offspring(), &g, &mut pool, &p, &mut rng).expect("step");
            invalid += st.invalid_offspring;
            total += st.offspring;
        }
        invalid as f64 / total as f64
    }

    #[test]
    fn invalid_offspring_rate_is_about_55_percent() {
        let forge = invalid_rate(FORGE, 100);
        assert!((0.40..=0.70).contains(&forge), "forge invalid rate {forge}");
        let sf = invalid_rate(SF, 50);
        assert!((0.40..=0.70).contains(&sf), "sf invalid rate {sf}");
    }

    #[test]
    fn offspring_respect_max_genome_length() {
        let g = grammar(FORGE);
        let p = GeParams { max_genome_length: 30, ..Default::default() };
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..100 {
            // Parents of at most 25 codons can always produce children within 30 (the
            // uncrossed copies); longer ones may make the limit unreachable.
            let mut pool: Vec<Individual> =
                pool_of(&g, &p, &mut rng, 20).into_iter().filter(|i| i.genome.len() <= 25).take(7).collect();
            assert!(pool.len() >= 4);
            pool.iter_mut().for_each(|i| i.fitness = f64::NAN);
            let (w, st) = genetic_step_with_stats(&g, &mut pool, &p, &mut rng).expect("step");
            if !st.winner_from_pool {
                assert!(w.genome.len() <= 30);
            }
        }
        // Parents that can only produce over-long children: the step gives up cleanly.
        let long: Vec<u32> = forge_golden()[0].0.iter().cycle().take(400).copied().collect();
        let mut pool: Vec<Individual> = (0..6).map(|_| evaluate(&g, long.clone(), &GeParams::default())).collect();
        let p = GeParams { max_genome_length: 50, generation_size: 2, ..Default::default() };
        let e = genetic_step(&g, &mut pool, &p, &mut rng).expect_err("over-long parents");
        assert!(matches!(e, GeError::NoViableOffspring { produced: 0, .. }), "{e:?}");
    }

    /// A winning offspring that derives like its parent takes the parent's phenotype
    /// (no mapping); it is the phenotype its own genome maps to, like every winner's.
    #[test]
    fn a_winner_deriving_like_its_parent_has_its_own_phenotype() {
        let p = GeParams::default();
        let grammars = [("forge", grammar(FORGE)), ("sf", grammar(SF))];
        let mut rng = ChaCha8Rng::seed_from_u64(29);
        let (mut inherited, mut mapped) = ([0; 2], [0; 2]);
        // One workspace for all steps of both grammars, interleaved (as Multi-GEESE's
        // learners share one): a winner's phenotype is written from its runs the first
        // time and taken from the workspace when the same grammar's runs repeat.
        let mut ws = Workspace::default();
        for step in 0..1200 {
            let k = step % 2;
            let (name, g) = &grammars[k];
            let mut pool = pool_of(g, &p, &mut rng, 8);
            pool.iter_mut().for_each(|i| i.fitness = 0.0);
            let Ok((w, st)) = genetic_step_in(&mut ws, g, &mut pool, &p, &mut rng) else {
                continue;
            };
            if st.winner_from_pool || !w.valid() {
                continue;
            }
            if st.winner_phenotype_inherited {
                inherited[k] += 1;
            } else {
                mapped[k] += 1;
            }
            let again = evaluate(g, w.genome.clone(), &p);
            assert_eq!(again.phenotype, w.phenotype, "{name}");
            assert_eq!((again.used_codons, again.depth, again.fitness), (w.used_codons, w.depth, w.fitness));
        }
        for (k, (name, _)) in grammars.iter().enumerate() {
            let (inherited, mapped) = (inherited[k], mapped[k]);
            assert!(inherited >= 10 && mapped >= 10, "{name}: {inherited} inherited, {mapped} mapped");
        }
        let known = ws.phenotypes.by_runs.len();
        let mapped = mapped[0] + mapped[1];
        assert!(known >= 10 && known < mapped, "{known} phenotypes kept for {mapped} mapped winners");
    }

    /// Uncrossed children of parents whose derivations are kept (`ge::derivations`) are
    /// not mapped before mutation, yet every step is the same: same random draws, same
    /// winner, same statistics, as with a workspace that keeps nothing between steps.
    #[test]
    fn kept_derivations_change_no_step() {
        let p = GeParams::default();
        for (name, bnf) in [("forge", FORGE), ("sf", SF)] {
            let g = grammar(bnf);
            let mut setup = ChaCha8Rng::seed_from_u64(7);
            // A few pools whose genomes (shared allocations) come back step after step,
            // with phenotypes unknown, as received genes' are.
            let mut pools: Vec<Vec<Individual>> = (0..4).map(|_| pool_of(&g, &p, &mut setup, 7)).collect();
            pools.iter_mut().flatten().for_each(|i| i.phenotype = None);
            let (mut kept, mut fresh) = (Workspace::default(), Workspace::default());
            let (mut rk, mut rf) = (ChaCha8Rng::seed_from_u64(8), ChaCha8Rng::seed_from_u64(8));
            let mut inherited = 0;
            for step in 0..400 {
                let base = &pools[step % pools.len()];
                let (mut a, mut b) = (base.clone(), base.clone());
                a.iter_mut().chain(b.iter_mut()).for_each(|i| i.fitness = (step % 3) as f64);
                fresh.derivations = Derivations::default();
                let wa = genetic_step_in(&mut kept, &g, &mut a, &p, &mut rk);
                let wb = genetic_step_in(&mut fresh, &g, &mut b, &p, &mut rf);
                let (Ok((wa, mut sa)), Ok((wb, mut sb))) = (wa, wb) else { panic!("{name}: step {step} failed") };
                inherited += usize::from(sa.winner_phenotype_inherited && !sb.winner_phenotype_inherited);
                (sa.winner_phenotype_inherited, sb.winner_phenotype_inherited) = (false, false);
                assert_eq!(sa, sb, "{name}: step {step}");
                assert_eq!(
                    (&wa.genome, &wa.phenotype, wa.valid, wa.used_codons, wa.depth, wa.fitness.to_bits()),
                    (&wb.genome, &wb.phenotype, wb.valid, wb.used_codons, wb.depth, wb.fitness.to_bits()),
                    "{name}: step {step}"
                );
            }
            assert!(kept.derivations.len() >= 4, "{name}: {} derivations kept", kept.derivations.len());
            assert!(inherited > 0, "{name}: no winner took its phenotype from a kept derivation");
        }
    }

    #[test]
    fn phenotypes_of_two_grammars_with_the_same_run_ids_are_kept_apart() {
        let (a, b) = (grammar("<s> ::= left | right\n"), grammar("<s> ::= up | down\n"));
        let mut kept = Phenotypes::default();
        for _ in 0..2 {
            for (g, text) in [(&a, "left"), (&b, "up"), (&a.clone(), "left")] {
                let run = g.compiled().runs.iter().position(|r| &*r.text == text).expect("a run per terminal");
                assert_eq!(&*kept.text(g, |key| key.push(run as u32)), text);
            }
        }
        assert_eq!(kept.by_runs.len(), 2, "a clone of a grammar is the same grammar");
    }

    #[test]
    fn invalid_parents_use_whole_genome() {
        // Pools normally hold valid genes only; invalid ones must not break the step.
        let g = grammar(FORGE);
        let p = GeParams::default();
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mut pool: Vec<Individual> =
            crate::ge::mapper::tests::forge_invalid().into_iter().map(|gn| evaluate(&g, gn, &p)).collect();
        pool.extend(pool_of(&g, &p, &mut rng, 2));
        pool.iter_mut().for_each(|i| i.fitness = f64::NAN);
        let (w, st) = genetic_step_with_stats(&g, &mut pool, &p, &mut rng).expect("step");
        assert_eq!(st.parents, 3);
        assert!(w.genome.len() <= 100);
        let m = map_genome(&g, &w.genome, p.map_limits());
        assert_eq!(m.phenotype.as_deref(), w.phenotype.as_deref());
    }
}
