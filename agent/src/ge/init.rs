//! PonyGE2's `uniform_tree` initialisation (REFERENCE.md §5.3).
//!
//! Why this exists: agents start from, and stagnating agents are refreshed with, random
//! individuals, and their shape statistics (depth 9–10, one action, 16–37 codons for
//! `forge.bnf`) come from this exact procedure: a depth-first random derivation whose
//! choices are restricted by the remaining depth (with PonyGE2's quirk that a remaining
//! depth of exactly 0 allows every alternative), a codon per expansion drawn so that
//! `codon % n` selects the chosen alternative, and a random unexpressed tail of
//! ⌊used/2⌋ codons.

use rand::Rng;

use super::grammar::{Grammar, Symbol};

/// A derived individual: its genome (used codons + tail) and what the derivation produced.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Derivation {
    pub genome: Vec<u32>,
    /// Codons consumed by the derivation (the genome's first `used_codons` entries).
    pub used_codons: usize,
    /// Derivation-tree depth (start symbol = 1, terminals counted).
    pub depth: usize,
    /// Concatenated terminals.
    pub phenotype: String,
}

/// Derive one random individual.
///
/// `max_tree_depth` is the depth limit L (PonyGE2 uses MAX_TREE_DEPTH here, not
/// MAX_INIT_TREE_DEPTH); 0 is treated as 1 so the derivation always terminates.
/// `codon_size` should exceed [`Grammar::max_alternatives`]; for a rule with at least
/// `codon_size` alternatives (where Python's `randrange` would fail) the codon is the bare
/// alternative index.
pub fn uniform_tree<R: Rng + ?Sized>(
    grammar: &Grammar,
    codon_size: u32,
    max_tree_depth: usize,
    rng: &mut R,
) -> Derivation {
    let limit = max_tree_depth.max(1) as i64;
    let max_arity = i64::from(grammar.max_arity());
    let mut genome: Vec<u32> = Vec::with_capacity(64);
    let mut phenotype = String::with_capacity(256);
    let mut stack: Vec<(Symbol, u32)> = vec![(Symbol::NonTerminal(grammar.start()), 1)];
    let mut allowed: Vec<u32> = Vec::with_capacity(8);
    let mut max_depth = 0usize;

    while let Some((sym, d)) = stack.pop() {
        max_depth = max_depth.max(d as usize);
        let r = match sym {
            Symbol::Terminal(t) => {
                phenotype.push_str(grammar.terminal(t));
                continue;
            }
            Symbol::NonTerminal(r) => grammar.rule(r),
        };
        let alts = r.alternatives();
        let remaining = limit - i64::from(d);
        allowed.clear();
        if remaining == 0 || remaining > max_arity + 1 {
            allowed.extend(0..alts.len() as u32);
        } else if remaining < 0 {
            allowed.extend_from_slice(r.min_path());
        } else {
            allowed.extend((0..alts.len() as u32).filter(|&i| i64::from(alts[i as usize].max_path()) < remaining));
            if allowed.is_empty() {
                allowed.extend_from_slice(r.min_path());
            }
        }
        let index = allowed[rng.random_range(0..allowed.len())];
        let n = alts.len() as u32;
        // randrange(n, CODON_SIZE, n) + index: a random multiple of n in [n, CODON_SIZE).
        let multiples = codon_size.saturating_sub(1) / n;
        let codon = if multiples >= 1 { rng.random_range(1..=multiples) * n + index } else { index };
        genome.push(codon);
        let child_depth = d + 1;
        stack.extend(alts[index as usize].symbols().iter().rev().map(|&s| (s, child_depth)));
    }

    let used_codons = genome.len();
    for _ in 0..used_codons / 2 {
        genome.push(rng.random_range(0..=codon_size));
    }
    Derivation { genome, used_codons, depth: max_depth, phenotype }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::mapper::tests::grammar;
    use crate::ge::mapper::{map_genome, MapLimits};
    use crate::ge::testdata::{FORGE, SF, TEST_NEW};
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn count(hay: &str, needle: &str) -> usize {
        hay.matches(needle).count()
    }

    #[test]
    fn forge_statistics() {
        let g = grammar(FORGE);
        let mut rng = ChaCha8Rng::seed_from_u64(2024);
        let n = 500;
        let mut total_len = 0usize;
        let mut depths = [0usize; 16];
        let mut dummy = 0usize;
        let (mut min_len, mut max_len) = (usize::MAX, 0usize);
        for _ in 0..n {
            let d = uniform_tree(&g, 2000, 10, &mut rng);
            assert!(d.depth == 9 || d.depth == 10, "depth {} for {}", d.depth, d.phenotype);
            assert!((16..=37).contains(&d.genome.len()), "length {}", d.genome.len());
            assert_eq!(d.genome.len(), d.used_codons + d.used_codons / 2);
            assert_eq!(count(&d.phenotype, "[Act]"), 1, "{}", d.phenotype);
            // Derivation codons: k·n + index with k ≥ 1, below CODON_SIZE + n; tail ≤ CODON_SIZE.
            assert!(d.genome[..d.used_codons].iter().all(|&c| (1..2000 + 6).contains(&c)));
            assert!(d.genome[d.used_codons..].iter().all(|&c| c <= 2000));
            total_len += d.genome.len();
            depths[d.depth] += 1;
            min_len = min_len.min(d.genome.len());
            max_len = max_len.max(d.genome.len());
            if d.phenotype.contains("DummyNode") {
                dummy += 1;
            }
        }
        let mean = total_len as f64 / n as f64;
        assert!((22.5..=26.5).contains(&mean), "mean genome length {mean}");
        assert!(depths[9] > 0 && depths[10] > 0, "{depths:?}");
        assert!(min_len <= 19 && max_len >= 31, "{min_len}..{max_len}");
        // "About half use <SuccessNode> as post-condition."
        let frac = dummy as f64 / n as f64;
        assert!((0.35..=0.65).contains(&frac), "DummyNode fraction {frac}");
    }

    #[test]
    fn sf_action_counts() {
        let g = grammar(SF);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let n = 1000;
        let mut by_actions = [0usize; 8];
        for _ in 0..n {
            let d = uniform_tree(&g, 2000, 10, &mut rng);
            by_actions[count(&d.phenotype, "[act]").min(7)] += 1;
        }
        // Reference: 34 % / 45 % / 21 % with 1 / 2 / 3 actions.
        let f = |k: usize| by_actions[k] as f64 / n as f64;
        assert!((0.26..=0.42).contains(&f(1)), "{by_actions:?}");
        assert!((0.37..=0.53).contains(&f(2)), "{by_actions:?}");
        assert!((0.14..=0.28).contains(&f(3)), "{by_actions:?}");
        assert_eq!(by_actions[0] + by_actions[4..].iter().sum::<usize>(), 0, "{by_actions:?}");
    }

    #[test]
    fn test_new_statistics() {
        let g = grammar(TEST_NEW);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let n = 300;
        let mut used_total = 0usize;
        for _ in 0..n {
            let d = uniform_tree(&g, 2000, 10, &mut rng);
            assert_eq!(d.depth, 10);
            assert!((85..=133).contains(&d.genome.len()), "length {}", d.genome.len());
            assert_eq!(count(&d.phenotype, "[Act]"), 5);
            used_total += d.used_codons;
        }
        let mean_used = used_total as f64 / n as f64;
        assert!((66.0..=74.0).contains(&mean_used), "mean used {mean_used}");
    }

    #[test]
    fn zero_remaining_depth_allows_every_alternative() {
        // L = 2: <a> at depth 1 has r = 1 → max_path ≤ 0 → only "x"… unless none; <a> at
        // depth 2 would have r = 0 → anything. Use L = 1 so the start rule sees r = 0.
        let g = grammar("<a> ::= <a><a> | x\n");
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut saw_recursion = false;
        for _ in 0..200 {
            let d = uniform_tree(&g, 100, 1, &mut rng);
            // Below the start the remaining depth is negative → min_path ("x") only.
            assert!(d.phenotype == "x" || d.phenotype == "xx", "{}", d.phenotype);
            saw_recursion |= d.phenotype == "xx";
            let limits = MapLimits { max_tree_depth: 0, max_wraps: 0 };
            assert_eq!(map_genome(&g, &d.genome, limits).phenotype.as_deref(), Some(d.phenotype.as_str()));
        }
        assert!(saw_recursion, "r = 0 must allow the recursive alternative");
        // With L = 2 the start rule (r = 1) may only take alternatives with max_path ≤ 0.
        for _ in 0..50 {
            assert_eq!(uniform_tree(&g, 100, 2, &mut rng).phenotype, "x");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        #[test]
        fn init_individuals_are_valid_and_remap_identically(seed in any::<u64>(), which in 0usize..3) {
            let g = grammar([FORGE, SF, TEST_NEW][which]);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let d = uniform_tree(&g, 2000, 10, &mut rng);
            let m = map_genome(&g, &d.genome, MapLimits::default());
            prop_assert!(m.valid);
            prop_assert_eq!(m.used_codons, d.used_codons);
            prop_assert_eq!(m.depth, d.depth);
            prop_assert_eq!(m.phenotype.as_deref(), Some(d.phenotype.as_str()));
        }
    }
}
