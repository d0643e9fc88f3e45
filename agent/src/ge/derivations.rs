//! The derivations of recent parents, so that an uncrossed child is not mapped again.
//!
//! Why this exists: every child of a genetic step is mapped once before mutation, on
//! the tape (`ge::tape`), to draw its mutations and to learn whether one of them picks
//! another alternative (`old % n != new % n`, where `n` is the number of alternatives of
//! the non-terminal that reads the codon). An uncrossed child is a copy of its parent,
//! so that mapping is its parent's: the same used codons, depth and D, and the same `n`
//! at every codon it reads. Genes are parents many times — in their own learner's
//! steps and in every cell-mate's that receives them — and these first mappings were a
//! third of a learner's instructions. So the first mapping of an uncrossed child of a
//! parent with a shared genome is kept here, by the genome's allocation: the next
//! uncrossed child of that parent draws its mutations from the kept `n`s, with the
//! random draws of a mapping in the same order, and is mapped only if a mutation picks
//! another alternative (then from its first codon, as the resumed mapping would give).
//!
//! Exactness: a kept derivation is used only for the same grammar (its
//! [`Uid`](super::grammar::Uid)) and limits, and only when it was valid, so its codons
//! read are exactly `0..used_codons` and its mapping from the start is the one the tape
//! would make. The genome is held, so no other genome can take its address while the
//! derivation is kept; derivations whose genome only this cache holds are dropped when
//! the cache grows.

use std::collections::HashMap;
use std::sync::Arc;

use super::mapper::{MapLimits, MapStats};

/// Derivations a [`Derivations`] keeps before it drops those of genomes no one else
/// holds any more (they can be no one's parent again); it keeps up to a quarter more
/// than are alive after that, so the bound follows the process's live genes: a few for
/// an agent process hosting one agent, some ten thousand for a crowded trial. (With
/// twice as many, the dead genomes held took 100,000 agents over 2 GiB.)
const FIRST_BOUND: usize = 256;

/// Most derivations kept: past it, after dropping the dead genomes' ones, all are
/// dropped (a trial of 100,000 agents has more live genes than are worth their memory:
/// ~150 bytes each, and it has to fit in 2 GiB).
const MOST: usize = 16_384;

/// The valid mapping of one parent's genome.
#[derive(Debug)]
pub(crate) struct Derivation {
    /// The genome, held so that its address stays its own.
    genome: Arc<[u32]>,
    uid: u64,
    limits: MapLimits,
    pub(crate) stats: MapStats,
    /// D of its phenotype.
    pub(crate) d: f64,
    /// The number of alternatives of the non-terminal that reads each used codon.
    pub(crate) alts: Box<[u8]>,
    /// The runs of terminals its mapping wrote (`Tape::phenotype_runs`): a child that
    /// derives like it and wins has its phenotype written from them (mapping the
    /// winner again for its text was 2 % of a learning run).
    pub(crate) runs: Box<[u32]>,
    /// Its phenotype, once a child that derives like it won.
    pub(crate) phenotype: Option<Arc<str>>,
}

/// Kept derivations by genome allocation.
#[derive(Debug, Default)]
pub(crate) struct Derivations {
    by_genome: HashMap<usize, Derivation, foldhash::fast::FixedState>,
    /// When to drop the derivations of dead genomes ([`FIRST_BOUND`]).
    bound: usize,
    /// The alternatives of the mapping being recorded.
    pub(crate) recording: Vec<u8>,
    /// The runs of terminals of the mapping being kept.
    pub(crate) runs: Vec<u32>,
}

/// The key of a shared genome: its allocation's address.
pub(crate) fn key(genome: &Arc<[u32]>) -> usize {
    Arc::as_ptr(genome).cast::<u32>() as usize
}

impl Derivations {
    /// The kept derivation of `genome` under grammar `uid` and `limits`.
    pub(crate) fn get(&self, genome: &Arc<[u32]>, uid: u64, limits: MapLimits) -> Option<&Derivation> {
        self.by_genome
            .get(&key(genome))
            .filter(|d| Arc::ptr_eq(&d.genome, genome) && d.uid == uid && d.limits == limits)
    }

    /// The kept derivation with key `key`, to give it its phenotype.
    pub(crate) fn by_key(&mut self, key: usize) -> Option<&mut Derivation> {
        self.by_genome.get_mut(&key)
    }

    /// Keep the valid mapping `stats` and D `d` of `genome`, whose alternatives per
    /// codon are in [`Derivations::recording`] and runs of terminals in
    /// [`Derivations::runs`].
    pub(crate) fn keep(&mut self, genome: &Arc<[u32]>, uid: u64, limits: MapLimits, stats: MapStats, d: f64) {
        debug_assert!(stats.valid && self.recording.len() == stats.used_codons);
        if self.by_genome.len() >= self.bound.max(FIRST_BOUND) {
            self.by_genome.retain(|_, d| Arc::strong_count(&d.genome) > 1);
            if self.by_genome.len() > MOST {
                self.by_genome.clear();
            }
            self.bound = self.by_genome.len() + self.by_genome.len() / 4;
        }
        let derivation = Derivation {
            genome: Arc::clone(genome),
            uid,
            limits,
            stats,
            d,
            alts: self.recording.as_slice().into(),
            runs: self.runs.as_slice().into(),
            phenotype: None,
        };
        self.by_genome.insert(key(genome), derivation);
    }

    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.by_genome.len()
    }
}
