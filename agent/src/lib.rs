//! The agent side of GEESE: grammatical evolution, behaviour trees and learners.
//!
//! # Layout
//! - [`ge`]: BNF grammars, genotype → phenotype mapping, diversity fitness and the
//!   GE operators (PonyGE2 semantics, REFERENCE.md §3–5).
//! - [`grammars`]: the grammar files shipped with GEESE.
//! - [`bt`]: the behaviour-tree engine (py_trees semantics, stale statuses included).
//! - [`leaves`]: conditions, primitive and composite actions.
//! - [`view`]: an agent's local world model, blackboard and static memory for one tick.
//! - [`inbox`]: the genes an agent process received from other processes, decoded into
//!   one reused buffer and lent to its learners by cell.
//! - [`host`]: an agent process's host of many agents — the protocol of a step
//!   (percepts, genes, intents, deadlines) driven by messages in and a clock value,
//!   returning what to publish and subscribe; the `geese-agent` binary is a shell
//!   around it.
//! - [`program`]: what a run's agents run (an algorithm, or a fixed population),
//!   population files, GeneDicts and the Multi-GEESE controller substitution.
//! - [`learner`]: the per-step loop of every algorithm (lateral transfer, genetic step, fitness),
//!   and the per-process [`GeneCache`] of received genes' mappings (which also holds the
//!   genetic step's scratch buffers and the behaviour trees of adopted phenotypes).
pub mod bt;
pub mod ge;
pub mod grammars;
pub mod host;
pub mod inbox;
pub mod learner;
pub mod leaves;
pub mod program;
pub mod view;

pub use learner::{
    FitnessCell, FitnessVariant, Gene, GeneCache, GeneRef, Learner, LearnerConfig, MutationRule, SharedGene,
    StressMutation, Triggers,
};
pub use program::{Algorithm, FitnessTerms, Phase, Population, Program, Role, Strategy};
#[cfg(test)]
mod tests;
