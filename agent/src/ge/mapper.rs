//! The linear genome → phenotype mapper of PonyGE2 (`map_ind_from_genome`,
//! REFERENCE.md §5.4).
//!
//! Why this exists: every offspring of every genetic step is mapped (twice: after
//! crossover for its used-codon count and depth, after mutation for its phenotype), so the
//! mapper must be exact *and* cheap. [`Mapper`] keeps its symbol stack between calls and
//! can either skip the phenotype ([`Mapper::map_stats`]) or write it into a caller-owned
//! buffer ([`Mapper::map_into`]); [`map_genome`] is the convenient allocating form.
//!
//! The PonyGE2 deque (pop front, push children onto the front in order) is a stack with
//! the children pushed in reverse; wrapping and the depth cut-off are reproduced
//! literally, including their quirks (the wrap counter is advanced on every iteration
//! in which `used` is a positive multiple of the genome length while a non-terminal is
//! pending, and a symbol deeper than the limit only invalidates the individual if further
//! symbols remain).

use super::compiled::{Compiled, NoOutput, RunSink, TextAndScore, TextOutput};
use super::diversity::{diversity, DiversityScan};
use super::grammar::{fast_mod, pack_symbol, Grammar, Symbol, PACKED_NT};

/// Limits of one mapping (PonyGE2 `MAX_TREE_DEPTH`, `MAX_WRAPS`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapLimits {
    /// Derivation-tree depth limit; 0 = no limit (PonyGE2 semantics).
    pub max_tree_depth: usize,
    /// Number of genome wraps allowed; 0 = none.
    pub max_wraps: usize,
}

impl MapLimits {
    /// The depth limit as a bound (no limit = `usize::MAX`).
    pub(crate) fn depth_cap(&self) -> usize {
        if self.max_tree_depth == 0 {
            usize::MAX
        } else {
            self.max_tree_depth
        }
    }
}

/// What an empty genome maps to (PonyGE2 would divide by zero).
pub(crate) const EMPTY_GENOME: MapStats = MapStats { valid: false, used_codons: 0, depth: 1 };

impl Default for MapLimits {
    fn default() -> Self {
        MapLimits { max_tree_depth: 10, max_wraps: 0 }
    }
}

/// Outcome of a mapping without the phenotype string.
///
/// For an invalid mapping `used_codons` and `depth` are the values at the point mapping
/// stopped (PonyGE2 reports them as undefined); they are diagnostic only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MapStats {
    pub valid: bool,
    pub used_codons: usize,
    pub depth: usize,
}

/// Outcome of a mapping with the phenotype (`None` when invalid).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mapping {
    pub valid: bool,
    pub used_codons: usize,
    pub depth: usize,
    pub phenotype: Option<String>,
}

/// Reusable mapper state (the symbol stack), so repeated mappings do not allocate.
#[derive(Debug, Clone, Default)]
pub struct Mapper {
    stack: Vec<u64>,
    scan: DiversityScan,
    text: String,
}

impl Mapper {
    pub fn new() -> Mapper {
        Mapper { stack: Vec::with_capacity(64), scan: DiversityScan::default(), text: String::new() }
    }

    /// The stack holding only the start rule at depth 1. Entries: the packed symbol in
    /// the low 32 bits (rule id with [`PACKED_NT`], or a terminal / run id), the depth in
    /// the high 32 bits.
    fn start_stack(&mut self, start: u32) -> &mut Vec<u64> {
        self.stack.clear();
        self.stack.push(pack_symbol(Symbol::NonTerminal(start)) | (1 << 32));
        &mut self.stack
    }

    /// Map without building the phenotype.
    pub fn map_stats(&mut self, grammar: &Grammar, genome: &[u32], limits: MapLimits) -> MapStats {
        if limits.max_wraps == 0 {
            return self.run_runs(grammar.compiled(), grammar.start(), genome, limits, &mut NoOutput);
        }
        self.run::<false>(grammar, genome, limits, &mut String::new())
    }

    /// Map and write the phenotype into `out` (cleared first). After an invalid mapping
    /// `out` holds the partial output; ignore it.
    pub fn map_into(&mut self, grammar: &Grammar, genome: &[u32], limits: MapLimits, out: &mut String) -> MapStats {
        out.clear();
        if limits.max_wraps == 0 {
            return self.run_runs(grammar.compiled(), grammar.start(), genome, limits, &mut TextOutput(out));
        }
        self.run::<true>(grammar, genome, limits, out)
    }

    /// Map and score: the statistics and the diversity D of the phenotype (NaN when the
    /// mapping is invalid), without building the phenotype string when the grammar
    /// allows it (runs of terminals pre-scanned when the grammar is compiled). Equal,
    /// bit for bit, to [`super::diversity()`] of [`Mapper::map_into`]'s output.
    pub fn map_scored(&mut self, grammar: &Grammar, genome: &[u32], limits: MapLimits) -> (MapStats, f64) {
        self.scored(grammar, genome, limits, None)
    }

    /// Map, write the phenotype into `out` (cleared first) and score it, in one pass
    /// where the grammar allows it; D is NaN when the mapping is invalid.
    pub fn map_into_scored(
        &mut self,
        grammar: &Grammar,
        genome: &[u32],
        limits: MapLimits,
        out: &mut String,
    ) -> (MapStats, f64) {
        out.clear();
        self.scored(grammar, genome, limits, Some(out))
    }

    /// Score from the runs when the grammar allows it (writing the phenotype too if
    /// `out` is given), else from the phenotype string (the caller's or a scratch one).
    fn scored(
        &mut self,
        grammar: &Grammar,
        genome: &[u32],
        limits: MapLimits,
        out: Option<&mut String>,
    ) -> (MapStats, f64) {
        let c = grammar.compiled();
        if limits.max_wraps == 0 && c.scored_from_runs {
            let mut scan = std::mem::take(&mut self.scan);
            scan.reset();
            let st = match out {
                Some(out) => self.run_runs(c, grammar.start(), genome, limits, &mut TextAndScore(out, &mut scan)),
                None => self.run_runs(c, grammar.start(), genome, limits, &mut scan),
            };
            let d = if st.valid { scan.finish() } else { f64::NAN };
            self.scan = scan;
            return (st, d);
        }
        let mut scratch = std::mem::take(&mut self.text);
        let text = out.unwrap_or(&mut scratch);
        let st = self.map_into(grammar, genome, limits, text);
        let d = if st.valid { diversity(text) } else { f64::NAN };
        self.text = scratch;
        (st, d)
    }

    /// Map and return an owned [`Mapping`].
    pub fn map(&mut self, grammar: &Grammar, genome: &[u32], limits: MapLimits) -> Mapping {
        let mut out = String::new();
        let st = self.map_into(grammar, genome, limits, &mut out);
        Mapping { valid: st.valid, used_codons: st.used_codons, depth: st.depth, phenotype: st.valid.then_some(out) }
    }

    /// The literal loop, for tests that check the fast path against it.
    #[cfg(test)]
    pub(crate) fn map_literal(
        &mut self,
        grammar: &Grammar,
        genome: &[u32],
        limits: MapLimits,
        out: &mut String,
    ) -> MapStats {
        out.clear();
        self.run::<true>(grammar, genome, limits, out)
    }

    /// The PonyGE2 loop for `max_wraps = 0` over runs of terminals (`ge::compiled`):
    /// same validity, used codons, depth and output as [`Mapper::run`] symbol by symbol.
    ///
    /// How the literal loop's rules carry over: a run is popped in one go because the
    /// literal loop's checks cannot change between its terminals (no codon is read), except
    /// the depth cut-off, which stops after the first terminal of a run deeper than the
    /// limit. With no wraps allowed, the first iteration that finds every codon used while
    /// a non-terminal is pending is the last: it processes one symbol and, since no
    /// alternative is empty, leaves the stack non-empty, so the mapping is invalid.
    ///
    /// Two checks stop a mapping as soon as it is certain to be invalid, instead of
    /// running to the end of a long genome (a third of the offspring are invalid, and
    /// they used to cost several valid ones each): the pending non-terminals need more
    /// codons than are left, or a non-terminal is popped whose every derivation reaches
    /// below the depth limit while other symbols still wait (the literal loop stops at
    /// the first symbol deeper than the limit that is not the last one). Used codons and
    /// depth of an invalid mapping are diagnostic only, so they may differ from the
    /// literal loop's; validity and everything about a valid mapping are identical.
    fn run_runs<S: RunSink>(
        &mut self,
        c: &Compiled,
        start: u32,
        genome: &[u32],
        limits: MapLimits,
        sink: &mut S,
    ) -> MapStats {
        let n = genome.len();
        if n == 0 {
            return EMPTY_GENOME;
        }
        let stack = self.start_stack(start);
        let depth_limit = limits.depth_cap();
        let mut pending_nts = 1usize;
        let mut used = 0usize;
        let mut max_depth = 1usize;
        // Codons the pending non-terminals need at least.
        let mut need = c.rules[start as usize].min_codons as usize;
        while let Some(&entry) = stack.last() {
            if max_depth > depth_limit {
                break;
            }
            let d = (entry >> 32) as usize;
            let code = entry as u32;
            // The literal loop's wrap iteration (every codon used while a non-terminal is
            // pending) cannot come: `need` stops the mapping first.
            debug_assert!(!(used == n && pending_nts > 0));
            stack.pop();
            if d > max_depth {
                max_depth = d;
            }
            if u64::from(code) & PACKED_NT == 0 {
                if d > depth_limit && c.runs[code as usize].terminals > 1 {
                    // The literal loop stops after this run's first terminal.
                    stack.push(entry);
                    break;
                }
                if S::WANTS_RUNS {
                    sink.run(&c.runs[code as usize]);
                }
                continue;
            }
            pending_nts -= 1;
            let rule = &c.rules[(u64::from(code) & !PACKED_NT) as usize];
            if d + rule.min_steps as usize > depth_limit && !stack.is_empty() {
                stack.push(entry);
                break;
            }
            let alt = &rule.alts[fast_mod(genome[used], rule.magic, rule.alts.len() as u32) as usize];
            used += 1;
            need = need - rule.min_codons as usize + alt.child_codons as usize;
            if need > n - used {
                stack.push(entry);
                break;
            }
            let child_depth = ((d + 1) as u64) << 32;
            if let Some(lead) = alt.lead {
                // The literal loop pushes the alternative and pops its leading run next,
                // with the checks of a loop iteration; the rest of the alternative is
                // still on the stack then.
                let not_last = !stack.is_empty() || !alt.items_rev.is_empty();
                let run = &c.runs[lead as usize];
                if max_depth > depth_limit || (d + 1 > depth_limit && (run.terminals > 1 || not_last)) {
                    stack.push(u64::from(lead) | child_depth);
                    break;
                }
                max_depth = max_depth.max(d + 1);
                sink.run(run);
            }
            stack.extend(alt.items_rev.iter().map(|&x| x | child_depth));
            pending_nts += alt.nt_count as usize;
        }
        MapStats { valid: stack.is_empty(), used_codons: used, depth: max_depth }
    }

    fn run<const OUT: bool>(
        &mut self,
        grammar: &Grammar,
        genome: &[u32],
        limits: MapLimits,
        out: &mut String,
    ) -> MapStats {
        let n = genome.len();
        if n == 0 {
            return EMPTY_GENOME;
        }
        let stack = self.start_stack(grammar.start());
        let mut pending_nts = 1usize;
        let mut used = 0usize;
        // used % n, maintained incrementally (no division in the loop).
        let mut pos = 0usize;
        let mut wraps: i64 = -1;
        let max_wraps = limits.max_wraps as i64;
        let depth_limit = limits.depth_cap();
        let mut max_depth = 1usize;
        let rules = grammar.rules();

        while wraps < max_wraps {
            let Some(&entry) = stack.last() else { break };
            if max_depth > depth_limit {
                break;
            }
            if pos == 0 && used > 0 && pending_nts > 0 {
                wraps += 1;
            }
            stack.pop();
            let d = (entry >> 32) as usize;
            if d > max_depth {
                max_depth = d;
            }
            let code = entry as u32;
            if u64::from(code) & PACKED_NT == 0 {
                if OUT {
                    out.push_str(grammar.terminal(code));
                }
                continue;
            }
            pending_nts -= 1;
            let rule = &rules[(u64::from(code) & !PACKED_NT) as usize];
            let alts = &rule.alternatives;
            let alt = &alts[fast_mod(genome[pos], rule.mod_magic, alts.len() as u32) as usize];
            used += 1;
            pos += 1;
            if pos == n {
                pos = 0;
            }
            let child_depth = ((d + 1) as u64) << 32;
            stack.extend(alt.packed_rev.iter().map(|&c| c | child_depth));
            pending_nts += alt.nt_count as usize;
        }
        MapStats { valid: stack.is_empty(), used_codons: used, depth: max_depth }
    }
}

/// Map `genome` with a fresh [`Mapper`] (allocates; use a [`Mapper`] in loops).
pub fn map_genome(grammar: &Grammar, genome: &[u32], limits: MapLimits) -> Mapping {
    Mapper::new().map(grammar, genome, limits)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::ge::testdata::{FORGE, HEADER, SF, TEST_NEW};
    use proptest::prelude::*;

    pub(crate) fn grammar(text: &str) -> Grammar {
        match Grammar::parse(text) {
            Ok(g) => g,
            Err(e) => panic!("grammar failed to parse: {e}"),
        }
    }

    /// (genome, used, depth, phenotype) of the valid golden vectors of §5.8.
    pub(crate) fn forge_golden() -> Vec<(Vec<u32>, usize, usize, String)> {
        vec![
            (
                vec![
                    1213, 1114, 267, 757, 1875, 1236, 970, 1281, 1189, 134, 1240, 26, 1861, 1715, 960, 531, 1128, 479,
                    392, 1468, 963, 1107,
                ],
                12,
                10,
                format!(
                    "{HEADER}[Sequence][Selector][PostCnd]DummyNode[/PostCnd][Sequence][Sequence][Cnstr]IsDropable_Hub[/Cnstr][/Sequence][Act]Explore_0_Avoid[/Act][/Sequence][/Selector][/Sequence]"
                ),
            ),
            (
                vec![
                    1027, 25, 1038, 773, 1037, 793, 953, 372, 1146, 1579, 473, 816, 219, 562, 786, 606, 897, 1539,
                    1964, 164, 1807, 896,
                ],
                15,
                10,
                format!(
                    "{HEADER}[Selector][Selector][Sequence][PostCnd]IsCarrying_Food[/PostCnd][/Sequence][Sequence][Sequence][PreCnd]IsVisitedBefore_Sites_invert[/PreCnd][/Sequence][Act]MoveAway_Hub_Avoid[/Act][/Sequence][/Selector][/Selector]"
                ),
            ),
            (
                vec![
                    780, 1228, 708, 273, 774, 1088, 1658, 1922, 411, 782, 1685, 1765, 312, 1355, 1743, 256, 961, 1037,
                    552, 1142, 15, 870, 417, 742, 1911, 1094, 165, 946,
                ],
                19,
                10,
                format!(
                    "{HEADER}[Sequence][Selector][PostCnd]DummyNode[/PostCnd][Sequence][Sequence][PreCnd]IsCarrying_Food[/PreCnd][/Sequence][Sequence][Cnstr]CanMove[/Cnstr][Cnstr]IsCarryable_Food[/Cnstr][/Sequence][Act]MoveAway_Hub_Avoid[/Act][/Sequence][/Selector][/Sequence]"
                ),
            ),
        ]
    }

    pub(crate) fn sf_golden() -> Vec<(Vec<u32>, usize, usize, String)> {
        vec![
            (
                vec![1450, 647, 1578, 61, 1154, 825, 1734, 793, 1969, 1736, 550, 1900, 1864, 107, 962, 768, 1451, 813],
                12,
                9,
                format!(
                    "{HEADER}[Selector][cond]IsDropable_Hub[/cond][cond]IsDropable_Hub[/cond][act]MoveTowards_Hub[/act][/Selector]"
                ),
            ),
            (
                sf_second(),
                22,
                10,
                format!(
                    "{HEADER}[Selector][Selector][cond]IsCarrying_Food_invert[/cond][cond]IsVisitedBefore_Sites_invert[/cond][cond]NeighbourObjects[/cond][act]MoveAway_Hub[/act][/Selector] [Sequence][cond]IsVisitedBefore_Hub_invert[/cond][act]Explore[/act][/Sequence][/Selector]"
                ),
            ),
        ]
    }

    pub(crate) fn sf_second() -> Vec<u32> {
        vec![
            1774, 927, 1808, 570, 1290, 194, 631, 186, 1220, 1981, 1341, 1279, 1704, 169, 74, 1802, 1845, 1594, 671,
            1221, 1064, 1641, 602, 1023, 9, 1356, 174, 936, 1341, 569, 833, 1128, 1908,
        ]
    }

    pub(crate) fn test_new_golden() -> (Vec<u32>, usize, usize, String) {
        let genome = vec![
            52, 502, 361, 1386, 1210, 66, 193, 843, 1150, 1467, 453, 1815, 1659, 1945, 1430, 697, 319, 1963, 375, 780,
            736, 1239, 140, 1099, 970, 1131, 1699, 1183, 1445, 168, 1584, 164, 1776, 780, 931, 507, 729, 823, 1248,
            533, 336, 978, 1896, 1403, 1727, 471, 1134, 551, 433, 437, 1541, 1813, 373, 286, 1526, 1530, 1841, 1441,
            450, 1044, 189, 342, 1286, 1624, 1393, 864, 1221, 130, 788, 781, 1220, 958, 1083, 514, 1988, 1133, 1762,
            1930, 23, 1393, 1476, 234, 1396, 1812, 1099, 1537, 546, 1574, 1312, 696, 228, 601, 890, 323, 929, 6,
        ];
        let p = [
            "[Sequence]",
            "[Sequence][Selector][Sequence][PreCnd]IsVisitedBefore_Hub[/PreCnd][/Sequence][Act]MoveTowardsNormal[/Act][/Selector][PostCnd]DidAvoidedObj_Sites[/PostCnd][/Sequence]",
            "[Sequence][Selector][Sequence][PreCnd]IsVisitedBefore_Hub_invert[/PreCnd][/Sequence][Act]ExploreNormal[/Act][/Selector][PostCnd]NeighbourObjects_Food[/PostCnd][/Sequence]",
            "[Sequence][Selector][Sequence][PreCnd]IsDropable_Hub[/PreCnd][/Sequence][Act]ExploreNormal[/Act][/Selector][PostCnd]DidAvoidedObj_Sites[/PostCnd][PostCnd]NeighbourObjects_Hub[/PostCnd][PostCnd]IsVisitedBefore_Hub[/PostCnd][/Sequence]",
            "[Sequence][Selector][Sequence][PreCnd]IsDropable_Sites[/PreCnd][/Sequence][Act]CompositeDrop[/Act][/Selector][PostCnd]IsVisitedBefore_Sites[/PostCnd][/Sequence]",
            "[Sequence][Selector][Sequence][PreCnd]IsCarrying_Food_invert[/PreCnd][/Sequence][Act]CompositeDrop[/Act][/Selector][PostCnd]NeighbourObjects_Hub[/PostCnd][/Sequence]",
            "[/Sequence]",
        ];
        (genome, 64, 10, format!("{HEADER}{}", p.concat()))
    }

    pub(crate) fn forge_invalid() -> Vec<Vec<u32>> {
        vec![
            vec![0; 20],
            vec![1; 20],
            (0..25).collect(),
            vec![
                975, 813, 1308, 1763, 308, 474, 1300, 310, 1777, 1896, 1071, 798, 1518, 31, 1375, 1591, 131, 326, 1552,
                1960, 1210, 87, 616, 1597, 63, 1686, 1772, 551, 968, 1218, 1472, 1884,
            ],
        ]
    }

    fn check_valid(g: &Grammar, genome: &[u32], used: usize, depth: usize, phenotype: &str) {
        let m = map_genome(g, genome, MapLimits::default());
        assert!(m.valid, "expected valid: {genome:?}");
        assert_eq!(m.used_codons, used, "used codons of {genome:?}");
        assert_eq!(m.depth, depth, "depth of {genome:?}");
        assert_eq!(m.phenotype.as_deref(), Some(phenotype));
        // The non-allocating forms agree.
        let mut mapper = Mapper::new();
        let st = mapper.map_stats(g, genome, MapLimits::default());
        assert_eq!(st, MapStats { valid: true, used_codons: used, depth });
        let mut buf = String::from("garbage");
        assert_eq!(mapper.map_into(g, genome, MapLimits::default(), &mut buf), st);
        assert_eq!(buf, phenotype);
    }

    /// Shipped grammars plus small ones whose tags span terminals, contain odd text or
    /// recurse deeply, for the fast-path equivalence tests.
    fn equivalence_grammars() -> Vec<Grammar> {
        let mut v: Vec<Grammar> = crate::grammars::BUILTIN.iter().map(|(_, t)| grammar(t)).collect();
        for text in [
            "<s> ::= [Sequence]<a>[/Sequence]\n<a> ::= [Act]<n>[/Act]<a> | [Act]<n>[/Act] | [Seq<t>\n<t> ::= uence][/Sequence]\n<n> ::= Explore_0 | Move<m> | _x | IsCarrying\n<m> ::= Away_Hub | Towards | Away",
            "<s> ::= <x>\n<x> ::= [Act]Move<y>[/Act] | [Selector]<x><x>[/Selector] | [Act/] | [Selector] <x> [/Selector]\n<y> ::= Away|Towards_Hub|Away_|<y><y>",
            "<e> ::= <e>+<e> | (<e>) | x | y",
        ] {
            v.push(grammar(text));
        }
        v
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(768))]

        /// The runs-based fast path gives exactly the literal loop's validity, used codons,
        /// depth and phenotype, and `map_scored` gives D of that phenotype, bit for bit.
        #[test]
        fn fast_path_equals_literal_loop(
            which in 0usize..14,
            genome in proptest::collection::vec(0u32..2001, 0..120),
            depth in prop_oneof![Just(10usize), Just(0usize), 1usize..14],
        ) {
            let gs = equivalence_grammars();
            let g = &gs[which % gs.len()];
            let limits = MapLimits { max_tree_depth: depth, max_wraps: 0 };
            let mut m = Mapper::new();
            let (mut lit, mut fast) = (String::new(), String::new());
            let a = m.map_literal(g, &genome, limits, &mut lit);
            // Used codons and depth of an invalid mapping are diagnostic only.
            let same = |b: MapStats| if a.valid { b == a } else { !b.valid };
            let b = m.map_into(g, &genome, limits, &mut fast);
            prop_assert!(same(b), "{:?} vs {:?}", b, a);
            if a.valid {
                prop_assert_eq!(&lit, &fast);
            }
            prop_assert!(same(m.map_stats(g, &genome, limits)));
            let (st, d) = m.map_scored(g, &genome, limits);
            prop_assert!(same(st));
            let mut both = String::new();
            let (st2, d2) = m.map_into_scored(g, &genome, limits, &mut both);
            prop_assert!(same(st2));
            prop_assert!(d2.to_bits() == d.to_bits() || (d.is_nan() && d2.is_nan()));
            if a.valid {
                prop_assert_eq!(&both, &lit);
            }
            let want = if a.valid { diversity(&lit) } else { f64::NAN };
            prop_assert!(d.to_bits() == want.to_bits() || (d.is_nan() && want.is_nan()), "D {} vs {}", d, want);
        }
    }

    #[test]
    fn grammars_with_split_tags_are_scored_from_strings() {
        let gs = equivalence_grammars();
        let split = &gs[crate::grammars::BUILTIN.len()];
        assert!(!split.compiled().scored_from_runs);
        for g in &gs[..crate::grammars::BUILTIN.len()] {
            assert!(g.compiled().scored_from_runs, "shipped grammars are scored from runs");
        }
    }

    #[test]
    fn forge_golden_vectors() {
        let g = grammar(FORGE);
        for (genome, used, depth, p) in forge_golden() {
            check_valid(&g, &genome, used, depth, &p);
        }
    }

    #[test]
    fn forge_codon_14_variant() {
        let g = grammar(FORGE);
        let (mut genome, used, depth, p) = forge_golden().swap_remove(1);
        assert_eq!(genome[14], 786);
        genome[14] = 1589;
        let p = p.replace("MoveAway_Hub_Avoid", "MoveAway_Sites_Avoid");
        assert!(p.contains("MoveAway_Sites_Avoid"));
        check_valid(&g, &genome, used, depth, &p);
    }

    #[test]
    fn forge_invalid_vectors() {
        let g = grammar(FORGE);
        for genome in forge_invalid() {
            let m = map_genome(&g, &genome, MapLimits::default());
            assert!(!m.valid, "expected invalid: {genome:?}");
            assert_eq!(m.phenotype, None);
        }
    }

    #[test]
    fn sf_golden_vectors() {
        let g = grammar(SF);
        for (genome, used, depth, p) in sf_golden() {
            check_valid(&g, &genome, used, depth, &p);
        }
        let mut genome = sf_second();
        assert_eq!(genome[16], 1845);
        genome[16] = 1519;
        let m = map_genome(&g, &genome, MapLimits::default());
        assert!(!m.valid);
        assert_eq!(m.phenotype, None);
    }

    #[test]
    fn test_new_golden_vector() {
        let g = grammar(TEST_NEW);
        let (genome, used, depth, p) = test_new_golden();
        assert_eq!(genome.len(), 96);
        check_valid(&g, &genome, used, depth, &p);
    }

    #[test]
    fn genome_end_and_depth_limit() {
        let g = grammar(FORGE);
        let (genome, used, _, _) = forge_golden().swap_remove(0);
        // Exactly the used codons suffice; one fewer does not.
        assert!(map_genome(&g, &genome[..used], MapLimits::default()).valid);
        assert!(!map_genome(&g, &genome[..used - 1], MapLimits::default()).valid);
        // The same genome under a tighter depth limit is invalid, without limit valid.
        assert!(!map_genome(&g, &genome, MapLimits { max_tree_depth: 9, max_wraps: 0 }).valid);
        assert!(map_genome(&g, &genome, MapLimits { max_tree_depth: 0, max_wraps: 0 }).valid);
        // Empty genome: invalid, no panic.
        assert!(!map_genome(&g, &[], MapLimits::default()).valid);
    }

    #[test]
    fn wrapping_follows_ponyge2() {
        let g = grammar("<a> ::= x<b>\n<b> ::= y | z\n");
        // One codon: <a> uses it, then the genome is exhausted with <b> pending.
        let none = MapLimits { max_tree_depth: 10, max_wraps: 0 };
        assert!(!map_genome(&g, &[1], none).valid);
        // PonyGE2 advances the wrap counter on every iteration while used % n == 0 and a
        // non-terminal is pending: one wrap is spent on the "x" iteration, the second on
        // expanding <b>; the terminal that expansion pushes is still unprocessed when the
        // loop stops. So one wrap is not enough, two are.
        assert!(!map_genome(&g, &[1], MapLimits { max_tree_depth: 10, max_wraps: 1 }).valid);
        let m = map_genome(&g, &[1], MapLimits { max_tree_depth: 10, max_wraps: 2 });
        assert!(m.valid);
        assert_eq!(m.phenotype.as_deref(), Some("xz"));
        assert_eq!(m.used_codons, 2);
        // Last symbol beyond the depth limit: still valid (no symbol left to process).
        let deep = grammar("<a> ::= <b>\n<b> ::= <c>\n<c> ::= q\n");
        let m = map_genome(&deep, &[0, 0, 0], MapLimits { max_tree_depth: 3, max_wraps: 0 });
        assert!(m.valid, "{m:?}");
        assert_eq!(m.depth, 4);
        let deep3 = grammar("<a> ::= <b>\n<b> ::= <c><c>\n<c> ::= q\n");
        let m = map_genome(&deep3, &[0, 0, 0, 0], MapLimits { max_tree_depth: 3, max_wraps: 0 });
        assert!(!m.valid, "{m:?}");
    }

    #[test]
    fn fast_mod_edges() {
        use crate::ge::grammar::mod_magic;
        for d in [1u32, 2, 3, 5, 7, 8, 1000, 2001, u32::MAX - 1, u32::MAX] {
            for a in [0u32, 1, 2, d - 1, d, d.wrapping_add(1), 1999, 2000, u32::MAX - 1, u32::MAX] {
                assert_eq!(fast_mod(a, mod_magic(d), d), a % d, "{a} % {d}");
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn mapper_never_panics_and_is_consistent(
            genome in proptest::collection::vec(any::<u32>(), 0..160),
            which in 0usize..3,
            depth in 0usize..14,
            wraps in 0usize..3,
        ) {
            let g = grammar([FORGE, SF, TEST_NEW][which]);
            let limits = MapLimits { max_tree_depth: depth, max_wraps: wraps };
            let m = map_genome(&g, &genome, limits);
            let st = Mapper::new().map_stats(&g, &genome, limits);
            prop_assert_eq!(st.valid, m.valid);
            prop_assert_eq!(st.used_codons, m.used_codons);
            prop_assert_eq!(st.depth, m.depth);
            if m.valid {
                if wraps == 0 {
                    prop_assert!(m.used_codons <= genome.len());
                }
                let p = m.phenotype.as_deref().unwrap_or("");
                prop_assert!(p.starts_with(HEADER));
            } else {
                prop_assert!(m.phenotype.is_none());
            }
        }

        #[test]
        fn fast_mod_is_exact(a in any::<u32>(), d in 1u32..5000) {
            prop_assert_eq!(fast_mod(a, crate::ge::grammar::mod_magic(d), d), a % d);
        }

        #[test]
        fn small_codon_genomes_map_like_their_residues(genome in proptest::collection::vec(0u32..2000, 1..60)) {
            // Adding a common multiple of every alternative count (420 = lcm(1..=7)) to a
            // codon never changes the mapping.
            let g = grammar(FORGE);
            let shifted: Vec<u32> = genome.iter().map(|c| c + 420).collect();
            prop_assert_eq!(
                map_genome(&g, &genome, MapLimits::default()),
                map_genome(&g, &shifted, MapLimits::default())
            );
        }
    }
}
