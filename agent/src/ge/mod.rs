//! Grammatical evolution as the swarm code configures PonyGE2 (REFERENCE.md §3–5).
//!
//! The pieces are kept apart because they are used at different rates: the grammar is
//! parsed once per run, the mapper and diversity run for every offspring of every genetic
//! step, and the phenotype tree is only built for the gene an agent adopts.
//!
//! - [`grammar`]: BNF parsing with PonyGE2's conventions and the §5.2 pre-computation.
//! - [`mapper`]: the linear genome → phenotype mapper of §5.4, over the grammar's
//!   compiled form (`compiled`: runs of terminals, pre-scanned for D).
//! - [`init`]: PonyGE2's `uniform_tree` random initialisation (§5.3).
//! - [`phenotype`]: bracket phenotype string → composite tree with the §4.3 quirk.
//! - [`mod@diversity`]: the `bt_diversity` fitness D of §5.5.
//! - [`operators`]: parameters, individuals and one genetic step (§5.1, §5.6).
//! - [`metrics`]: the grammar modularity metrics of the paper's Table 2 (§8.3).
//! - [`micro`]: micro-benchmarks of one genetic step and one mapping (`geese bench --micro`).
//! - `ceiling`: the highest D a grammar's valid individuals can score.
//! - `crossover`: the genetic step's crossover pairs, drawn from the accepted ones.
//! - `tape`: mappings that keep the state at a child's first mutated codon, to resume from.
//! - `derivations`: recent parents' mappings, so that uncrossed children are not mapped
//!   again.

mod ceiling;
mod compiled;
mod crossover;
mod derivations;
pub mod diversity;
pub mod grammar;
pub mod init;
pub mod mapper;
pub mod metrics;
pub mod micro;
pub mod operators;
pub mod phenotype;
mod tape;

pub use diversity::{diversity, python_round4, BEHAVIOURS};
pub use grammar::{Alternative, Grammar, GrammarError, Rule, Symbol};
pub use init::{uniform_tree, Derivation};
pub use mapper::{map_genome, MapLimits, MapStats, Mapper, Mapping};
pub use metrics::GrammarMetrics;
pub use operators::{
    evaluate, evaluate_stats_with, fitness_cmp, genetic_step, genetic_step_in, genetic_step_on,
    genetic_step_with_stats, random_individual, sort_by_fitness_desc, Candidate, GeError, GeParams, Individual, Member,
    ParamsError, StepStats, Workspace,
};
pub use phenotype::{parse_phenotype, CompositeKind, PNode, PhenotypeError};

/// Grammar texts used by the unit tests of this module (byte-for-byte reference files).
#[cfg(test)]
pub(crate) mod testdata {
    /// `forge.bnf`@master.
    pub const FORGE: &str = include_str!("../../grammars/betr-foraging-avoid.bnf");
    /// `sf.bnf` (GEESE-BT).
    pub const SF: &str = include_str!("../../grammars/geese-bt-foraging.bnf");
    /// `test_new.bnf`@mgenes (Multi-GEESE combine phase).
    pub const TEST_NEW: &str = include_str!("../../grammars/multi-combine-foraging.bnf");
    /// The XML header every reference grammar's start rule emits.
    pub const HEADER: &str = "[?xml version=%1.0% encoding=%UTF-8%?]";
}
