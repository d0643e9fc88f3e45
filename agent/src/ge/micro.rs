//! Micro-benchmarks of the two hot loops of grammatical evolution, printed by
//! `geese bench --micro`: one genetic step, and one mapping of a genome.
//!
//! These functions only measure; they assert nothing (speed targets belong in
//! benchmarks that print figures, not in timed tests). Their inputs are fixed: the
//! built-in `betr-foraging-avoid` grammar (`forge.bnf`), random individuals drawn with a
//! [`ChaCha8Rng`] seeded with [`SEED`], and the valid `forge.bnf` golden genomes of
//! REFERENCE.md §5.8 ([`FORGE_GOLDEN_GENOMES`]).
//!
//! Each figure is the best over several batches, so that other load on the machine
//! inflates it as little as possible.

use std::hint::black_box;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::grammar::Grammar;
use super::mapper::{MapLimits, Mapper};
use super::operators::{genetic_step, random_individual, GeParams, Individual};

/// Seed of the [`ChaCha8Rng`] that draws the pools and drives the genetic steps.
pub const SEED: u64 = 1;

/// Individuals in each pool given to [`genetic_step_us`].
pub const POOL_SIZE: usize = 7;

/// Distinct pools [`genetic_step_us`] cycles through.
pub const POOLS: usize = 64;

/// Codons every golden genome is padded to (with codon 7) before [`mapping_ns`] maps it.
pub const PADDED_LENGTH: usize = 100;

/// Genomes of the valid `forge.bnf` golden vectors of REFERENCE.md §5.8 (the same as the
/// mapper's unit tests use; a test checks they agree).
pub const FORGE_GOLDEN_GENOMES: [&[u32]; 3] = [
    &[
        1213, 1114, 267, 757, 1875, 1236, 970, 1281, 1189, 134, 1240, 26, 1861, 1715, 960, 531, 1128, 479, 392, 1468,
        963, 1107,
    ],
    &[
        1027, 25, 1038, 773, 1037, 793, 953, 372, 1146, 1579, 473, 816, 219, 562, 786, 606, 897, 1539, 1964, 164, 1807,
        896,
    ],
    &[
        780, 1228, 708, 273, 774, 1088, 1658, 1922, 411, 782, 1685, 1765, 312, 1355, 1743, 256, 961, 1037, 552, 1142,
        15, 870, 417, 742, 1911, 1094, 165, 946,
    ],
];

/// Time of one genetic step, from [`genetic_step_us`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepTiming {
    /// Microseconds per genetic step, the pool clone excluded.
    pub step_us: f64,
    /// Microseconds per clone of a pool (timed separately and subtracted).
    pub clone_us: f64,
}

/// Time of mapping one golden genome, from [`mapping_ns`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MappingTiming {
    /// Codons the mapping uses (identifies the genome).
    pub used_codons: usize,
    /// Nanoseconds per [`Mapper::map_stats`].
    pub map_stats_ns: f64,
    /// Nanoseconds per [`Mapper::map_scored`].
    pub map_scored_ns: f64,
}

/// The built-in `forge.bnf` grammar, parsed.
///
/// # Panics
/// Only if the embedded grammar text were broken, which the unit tests rule out.
pub fn forge_grammar() -> Grammar {
    let text = crate::grammars::builtin("betr-foraging-avoid").expect("betr-foraging-avoid is built in");
    Grammar::parse(text).expect("the built-in forge.bnf parses")
}

/// Time one genetic step with default [`GeParams`] on a pool of [`POOL_SIZE`] random
/// `forge.bnf` individuals (fitnesses 0, 0.5, 1, …), cycling through [`POOLS`] pools.
///
/// Each of `batches` batches clones `batch` pools, then clones and steps `batch` pools;
/// the best per-clone and per-step times over the batches are kept, and the clone time is
/// subtracted from the step time. `geese bench --micro` uses 30 batches of 2,000.
/// Deterministic in its inputs ([`SEED`]); only the times vary.
pub fn genetic_step_us(batches: usize, batch: usize) -> StepTiming {
    let g = forge_grammar();
    let p = GeParams::default();
    let mut rng = ChaCha8Rng::seed_from_u64(SEED);
    let pools: Vec<Vec<Individual>> = (0..POOLS)
        .map(|_| {
            let mut pool: Vec<Individual> = (0..POOL_SIZE).map(|_| random_individual(&g, &p, &mut rng)).collect();
            pool.iter_mut().enumerate().for_each(|(k, i)| i.fitness = k as f64 * 0.5);
            pool
        })
        .collect();
    let batch = batch.max(1);
    let mut best_step = f64::MAX;
    let mut best_clone = f64::MAX;
    for _ in 0..batches.max(1) {
        let t = Instant::now();
        for k in 0..batch {
            black_box(pools[k % POOLS].clone());
        }
        best_clone = best_clone.min(t.elapsed().as_secs_f64() / batch as f64);
        let t = Instant::now();
        for k in 0..batch {
            let mut pool = pools[k % POOLS].clone();
            black_box(genetic_step(&g, &mut pool, &p, &mut rng).map(|w| w.genome.len()).unwrap_or(0));
        }
        best_step = best_step.min(t.elapsed().as_secs_f64() / batch as f64);
    }
    StepTiming { step_us: (best_step - best_clone) * 1e6, clone_us: best_clone * 1e6 }
}

/// Time [`Mapper::map_stats`] and [`Mapper::map_scored`] (default [`MapLimits`]) on each
/// of [`FORGE_GOLDEN_GENOMES`] padded to [`PADDED_LENGTH`] codons, `iterations` calls of
/// each per genome. `geese bench --micro` uses 200,000.
pub fn mapping_ns(iterations: usize) -> Vec<MappingTiming> {
    let g = forge_grammar();
    let mut m = Mapper::new();
    let limits = MapLimits::default();
    let n = iterations.max(1);
    FORGE_GOLDEN_GENOMES
        .iter()
        .map(|genome| {
            let mut genome = genome.to_vec();
            genome.resize(PADDED_LENGTH, 7);
            let used_codons = m.map_stats(&g, &genome, limits).used_codons;
            let t = Instant::now();
            for _ in 0..n {
                black_box(m.map_stats(&g, black_box(&genome), limits).used_codons);
            }
            let map_stats_ns = t.elapsed().as_secs_f64() / n as f64 * 1e9;
            let t = Instant::now();
            for _ in 0..n {
                black_box(m.map_scored(&g, black_box(&genome), limits).0.used_codons);
            }
            let map_scored_ns = t.elapsed().as_secs_f64() / n as f64 * 1e9;
            MappingTiming { used_codons, map_stats_ns, map_scored_ns }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_genomes_match_the_mapper_tests() {
        let golden: Vec<Vec<u32>> = crate::ge::mapper::tests::forge_golden().into_iter().map(|v| v.0).collect();
        let here: Vec<Vec<u32>> = FORGE_GOLDEN_GENOMES.iter().map(|g| g.to_vec()).collect();
        assert_eq!(here, golden);
        assert_eq!(forge_grammar(), crate::ge::mapper::tests::grammar(crate::ge::testdata::FORGE));
    }

    /// Not a timing test: the benchmark functions run on tiny batches and report
    /// figures that can be printed (no bound on their values).
    #[test]
    fn micro_benchmarks_run_and_report_finite_figures() {
        let s = genetic_step_us(1, 3);
        assert!(s.clone_us.is_finite() && s.clone_us >= 0.0, "{s:?}");
        assert!(s.step_us.is_finite() && s.step_us > 0.0, "{s:?}");
        let m = mapping_ns(2);
        let used: Vec<usize> = m.iter().map(|t| t.used_codons).collect();
        let golden: Vec<usize> = crate::ge::mapper::tests::forge_golden().into_iter().map(|v| v.1).collect();
        assert_eq!(used, golden);
        for t in &m {
            assert!(t.map_stats_ns.is_finite() && t.map_stats_ns > 0.0, "{t:?}");
            assert!(t.map_scored_ns.is_finite() && t.map_scored_ns > 0.0, "{t:?}");
        }
    }
}
