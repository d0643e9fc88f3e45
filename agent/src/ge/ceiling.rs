//! The highest diversity D a valid individual of a grammar can score under the
//! derivation-tree depth limit.
//!
//! Why this exists: in a genetic step an offspring can only become the agent's gene by
//! scoring strictly more than the stored elite and every offspring made before it
//! (§5.6: a stable sort, the elite first). Once an offspring scores the ceiling no later
//! one can, and once the elite's running fitness reaches it no offspring can: the rest
//! of the step cannot change the winner. With the swarm's grammars the depth limit keeps
//! D far below 25 (13.8889 for the foraging grammar: five behaviour names in at most
//! nine elements), and almost every genetic step meets an offspring at the ceiling
//! among its first few, so the step stops there (`ge::operators`).
//!
//! How: an exhaustive search over derivations, with every symbol at depth ≤ the limit
//! except possibly the very last one popped (the mapper's rule, §5.4). The diversity scan
//! decides nothing from its counts, so its state with each behaviour count capped at 1
//! and the total at 10 ([`DiversityScan::abstracted`]) is enough to bound D, and the
//! search is memoised per (rule, depth, abstract state). Lengths are not bounded, which
//! can only raise the ceiling: it stays an upper bound of every valid individual's D.
//! A grammar whose search grows beyond [`MAX_STATES`] gets no ceiling (steps then
//! make every offspring, as before).

use std::collections::{HashMap, HashSet};
use std::rc::Rc;
use std::sync::{Mutex, OnceLock};

use foldhash::fast::FixedState;

use super::compiled::Compiled;
use super::diversity::DiversityScan;
use super::grammar::PACKED_NT;

/// Memoised (rule, depth, state) entries before the search gives up.
const MAX_STATES: usize = 200_000;

/// What the search finds for one depth limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Bound {
    /// The ceiling of D, when there is one to find.
    pub(crate) d: Option<f64>,
    /// Whether an individual can be valid yet deeper than the limit (its very last
    /// symbol one level too deep); `true` when the search could not tell.
    pub(crate) deep_last: bool,
}

/// The ceiling of D over valid individuals whose derivation from `start` respects the
/// depth limit `max_tree_depth` (≥ 1); `d` is `None` when there is none to find (no
/// valid individual, a grammar not scored from its runs) or the search is too large.
pub(crate) fn bound(c: &Compiled, start: u32, max_tree_depth: usize) -> Bound {
    let unknown = Bound { d: None, deep_last: true };
    let Ok(limit) = u32::try_from(max_tree_depth) else { return unknown };
    if !c.scored_from_runs || limit == 0 {
        return unknown;
    }
    let mut search = Search { c, limit, memo: HashMap::default(), too_big: false };
    let origin = DiversityScan::default();
    let (within, deep_last) = (search.rule(start, 1, origin, false), search.rule(start, 1, origin, true));
    if search.too_big {
        return unknown;
    }
    Bound {
        d: within.iter().chain(deep_last.iter()).filter_map(|s| s.ceiling_of()).reduce(f64::max),
        deep_last: !deep_last.is_empty(),
    }
}

/// The ceilings of one grammar, per depth limit, computed when first asked for (a run
/// uses one limit; the search takes milliseconds). The first limit asked for is read
/// without a lock: every genetic step asks, and a Mutex there cost ~1 % of a run.
#[derive(Debug, Default)]
pub(crate) struct Ceilings {
    first: OnceLock<(usize, Bound)>,
    more: Mutex<Vec<(usize, Bound)>>,
}

impl Ceilings {
    pub(crate) fn get(&self, c: &Compiled, start: u32, max_tree_depth: usize) -> Bound {
        let &(depth, v) = self.first.get_or_init(|| (max_tree_depth, bound(c, start, max_tree_depth)));
        if depth == max_tree_depth {
            return v;
        }
        // A panic elsewhere cannot leave the list half-written: entries are pushed whole.
        let mut known = self.more.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(&(_, v)) = known.iter().find(|(d, _)| *d == max_tree_depth) {
            return v;
        }
        let v = bound(c, start, max_tree_depth);
        known.push((max_tree_depth, v));
        v
    }
}

impl Clone for Ceilings {
    fn clone(&self) -> Ceilings {
        Ceilings {
            first: self.first.clone(),
            more: Mutex::new(self.more.lock().unwrap_or_else(|e| e.into_inner()).clone()),
        }
    }
}

/// A cache: equal grammars have equal ceilings.
impl PartialEq for Ceilings {
    fn eq(&self, _: &Ceilings) -> bool {
        true
    }
}
impl Eq for Ceilings {}

type Ends = Rc<Vec<DiversityScan>>;

struct Search<'c> {
    c: &'c Compiled,
    limit: u32,
    /// (rule, depth, last-is-deep, abstract state on entry) → abstract states on exit.
    /// Hashed with foldhash: with SipHash the search of the foraging grammar was 3 % of
    /// a 2,000-step default run's instructions (it runs once per process and grammar).
    memo: HashMap<(u32, u32, bool, DiversityScan), Ends, FixedState>,
    too_big: bool,
}

impl Search<'_> {
    /// Exit states of the derivations of `rule` at depth `d` entered in state `s`: with
    /// every popped symbol at depth ≤ the limit (`deep_last` false), or with exactly the
    /// last popped one deeper (`deep_last` true; the mapper accepts such an individual).
    fn rule(&mut self, rule: u32, d: u32, s: DiversityScan, deep_last: bool) -> Ends {
        let key = (rule, d, deep_last, s);
        if let Some(e) = self.memo.get(&key) {
            return e.clone();
        }
        if self.memo.len() >= MAX_STATES {
            self.too_big = true;
            return Rc::default();
        }
        let c = self.c;
        let r = &c.rules[rule as usize];
        let mut out: HashSet<DiversityScan, FixedState> = HashSet::default();
        if d > self.limit {
            // Only the last symbol may be this deep: it is popped and expanded, and any
            // symbol it expands to would come after it.
            if deep_last {
                out.extend(r.alts.iter().filter(|a| a.lead.is_none() && a.items_rev.is_empty()).map(|_| s));
            }
        } else if deep_last || d + r.min_steps <= self.limit {
            for alt in r.alts.iter() {
                // The alternative's items left to right, each at depth d + 1.
                let items: Vec<u64> =
                    alt.lead.map(u64::from).into_iter().chain(alt.items_rev.iter().rev().copied()).collect();
                let Some((&last, init)) = items.split_last() else {
                    // An empty alternative: this symbol was the last one, at depth ≤ limit.
                    if !deep_last {
                        out.insert(s);
                    }
                    continue;
                };
                let mut states = vec![s];
                for &item in init {
                    states = self.item_all(item, d + 1, &states, false);
                    if states.is_empty() {
                        break;
                    }
                }
                if !states.is_empty() {
                    out.extend(self.item_all(last, d + 1, &states, deep_last));
                }
            }
        }
        let ends: Ends = Rc::new(out.into_iter().collect());
        self.memo.insert(key, ends.clone());
        ends
    }

    /// Exit states of one item (a run or a rule) at depth `d` from each of `states`.
    fn item_all(&mut self, item: u64, d: u32, states: &[DiversityScan], deep_last: bool) -> Vec<DiversityScan> {
        let mut out: HashSet<DiversityScan, FixedState> = HashSet::default();
        if item & PACKED_NT != 0 {
            let rule = (item & !PACKED_NT) as u32;
            for &s in states {
                out.extend(self.rule(rule, d, s, deep_last).iter().copied());
            }
        } else {
            let run = &self.c.runs[item as usize];
            // Within the limit, or (last only) one terminal beyond it: the mapper stops
            // after the first terminal of a longer run.
            let fits = if deep_last { d > self.limit && run.terminals == 1 } else { d <= self.limit };
            if fits {
                for &s in states {
                    let mut t = s;
                    t.feed_run(&run.toks, run.effect.as_ref());
                    out.insert(t.abstracted());
                }
            }
        }
        out.into_iter().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::testdata::{FORGE, SF, TEST_NEW};
    use crate::ge::{diversity, map_genome, uniform_tree, Grammar, MapLimits};
    use crate::grammars::BUILTIN;
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use std::sync::OnceLock;

    fn ceiling(text: &str, depth: usize) -> Option<f64> {
        let g = Grammar::parse(text).expect("grammar");
        bound(g.compiled(), g.start(), depth).d
    }

    /// Every built-in grammar with its ceiling at the swarm's depth limit 10.
    fn builtins() -> &'static [(Grammar, f64)] {
        static ALL: OnceLock<Vec<(Grammar, f64)>> = OnceLock::new();
        ALL.get_or_init(|| {
            BUILTIN
                .iter()
                .map(|(name, text)| {
                    let g = Grammar::parse(text).expect("grammar");
                    let c = g.d_ceiling(10).unwrap_or_else(|| panic!("{name}: no ceiling"));
                    (g, c)
                })
                .collect()
        })
    }

    #[test]
    fn reference_grammar_ceilings() {
        // forge.bnf: 25 · 5 / 9, what 10⁷ offspring of a 12,000-step trial never exceeded.
        assert_eq!(ceiling(FORGE, 10), Some(13.8889));
        assert_eq!(ceiling(SF, 10), Some(16.6667));
        assert_eq!(ceiling(TEST_NEW, 10), Some(8.3333));
        assert_eq!(builtins().len(), BUILTIN.len());
    }

    #[test]
    fn ceilings_grow_with_the_depth_limit() {
        for text in [FORGE, SF, TEST_NEW] {
            let mut last = 0.0;
            for depth in 4..=12 {
                if let Some(c) = ceiling(text, depth) {
                    assert!(c >= last, "depth {depth}: {c} < {last}");
                    last = c;
                }
            }
        }
    }

    #[test]
    fn a_hand_made_grammar() {
        // Symbols of <a> sit at depth 3, of <b> at 4, of <c> at 5; no limit = no ceiling.
        let g = "<s> ::= [Sequence]<a>[/Sequence]\n<a> ::= [Act]Explore[/Act] | [Act]Explore[/Act]<b>\n<b> ::= [Act]MoveAway[/Act] | [Act]MoveAway[/Act]<c>\n<c> ::= [Act]IsDropable[/Act]\n";
        let names = |n: u32| Some(crate::ge::python_round4(25.0 * f64::from(n) / 9.0));
        assert_eq!(ceiling(g, 2), None);
        assert_eq!(ceiling(g, 3), names(1));
        assert_eq!(ceiling(g, 4), names(2));
        assert_eq!(ceiling(g, 5), names(3));
        assert_eq!(ceiling(g, 0), None);
    }

    #[test]
    fn the_last_symbol_may_be_one_level_deeper() {
        // <b>'s last run is the phenotype's last symbol: the mapper accepts it at depth 4
        // under a limit of 3, so its name counts.
        let g = "<s> ::= [Sequence][Act]Explore[/Act]<b>\n<b> ::= [Act]MoveAway[/Act]<c>\n<c> ::= [Act]IsDropable[/Act][/Sequence]\n";
        let limits = MapLimits { max_tree_depth: 3, max_wraps: 0 };
        let grammar = Grammar::parse(g).expect("grammar");
        let m = map_genome(&grammar, &[0, 0, 0], limits);
        let d = diversity(m.phenotype.as_deref().expect("valid"));
        assert_eq!(m.depth, 4);
        assert_eq!(d, crate::ge::python_round4(25.0 * 3.0 / 9.0));
        assert_eq!(grammar.d_ceiling(3), Some(d));
        assert!(grammar.deep_last_possible(3));
        // The reference grammars close their root element last, at depth 3.
        for text in [FORGE, SF, TEST_NEW] {
            assert!(!Grammar::parse(text).expect("grammar").deep_last_possible(10));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        /// No valid genome scores above the ceiling, on every built-in grammar: random
        /// genomes, and random derivation trees (all valid) with random codons changed.
        #[test]
        fn no_valid_genome_exceeds_the_ceiling(
            which in 0usize..BUILTIN.len(),
            genome in proptest::collection::vec(0u32..=2000, 1..120),
            seed in any::<u64>(),
            flips in proptest::collection::vec((any::<prop::sample::Index>(), 0u32..=2000), 0..4),
        ) {
            let (g, c) = &builtins()[which];
            let limits = MapLimits { max_tree_depth: 10, max_wraps: 0 };
            let mut tree = uniform_tree(g, 2000, 10, &mut ChaCha8Rng::seed_from_u64(seed)).genome;
            for (at, v) in flips {
                let i = at.index(tree.len());
                tree[i] = v;
            }
            for genome in [&genome, &tree] {
                if let Some(p) = map_genome(g, genome, limits).phenotype {
                    let d = diversity(&p);
                    prop_assert!(d <= *c, "{}: D {d} above the ceiling {c}", BUILTIN[which].0);
                }
            }
        }
    }
}
