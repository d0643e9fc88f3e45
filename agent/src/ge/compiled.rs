//! A grammar compiled for the mapper's hot path.
//!
//! Why this exists: a genetic step maps every offspring twice and scores it with the
//! diversity D, tens of thousands of times per second per core. Mapping symbol by symbol
//! spends most of its time pushing and popping terminals, and scoring a phenotype string
//! means building it and scanning it byte by byte. Here every alternative is stored as
//! *items*: non-terminals and maximal runs of adjacent terminals. A run is one stack
//! entry, carries its concatenated text (for the phenotype) and its tokens pre-scanned
//! for the diversity state machine ([`DiversityScan`]), so an offspring is scored from
//! its runs without a string. The mapper that uses this reproduces the literal PonyGE2
//! loop exactly (the tests compare them on random genomes of every shipped grammar).
use super::diversity::{tokenize_run, DiversityScan, RunEffect, Tok};
use super::grammar::{Grammar, Symbol, PACKED_NT};

/// One run of adjacent terminals.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Run {
    /// Number of terminals in the run (the literal loop pops them one by one).
    pub(crate) terminals: u32,
    /// The run's text (its terminals concatenated).
    pub(crate) text: Box<str>,
    /// The text pre-scanned for [`DiversityScan`] (empty when the grammar has no plan).
    pub(crate) toks: Box<[Tok]>,
    /// The tokens' effect, for runs inside the root element.
    pub(crate) effect: Option<RunEffect>,
}

/// One alternative as stack items, right to left: a rule id with [`PACKED_NT`] set, or a
/// run id; the mapper ORs the depth into the high 32 bits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct CAlt {
    /// The items after the leading run (all items if the alternative starts with a
    /// non-terminal), right to left.
    pub(crate) items_rev: Box<[u64]>,
    /// The run the alternative starts with, if any: the mapper handles it on expansion,
    /// without pushing it (it would be popped right away).
    pub(crate) lead: Option<u32>,
    pub(crate) nt_count: u32,
    /// Codons the alternative's non-terminals need at least (sum of their `min_codons`).
    pub(crate) child_codons: u32,
}

/// One rule: its alternatives and the [`super::grammar::fast_mod`] multiplier.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct CRule {
    pub(crate) alts: Box<[CAlt]>,
    pub(crate) magic: u64,
    /// §5.2 `min_steps`: every derivation of the rule at depth d holds a symbol at depth
    /// d + `min_steps` or deeper.
    pub(crate) min_steps: u32,
    /// Fewest codons any derivation of the rule consumes (itself included).
    pub(crate) min_codons: u32,
}

/// The compiled form of a [`Grammar`].
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub(crate) struct Compiled {
    pub(crate) rules: Box<[CRule]>,
    pub(crate) runs: Box<[Run]>,
    /// Every run tokenises on its own (no tag spans two runs), so D can be computed from
    /// the runs' tokens; otherwise callers score the phenotype string.
    pub(crate) scored_from_runs: bool,
}

impl Compiled {
    pub(crate) fn build(g: &Grammar) -> Compiled {
        let mut runs: Vec<Run> = Vec::new();
        let mut plan_ok = true;
        let mut rules = Vec::with_capacity(g.rules().len());
        for rule in g.rules() {
            let mut alts = Vec::with_capacity(rule.alternatives().len());
            for alt in rule.alternatives() {
                let mut items: Vec<u64> = Vec::new();
                let mut pending: Vec<u32> = Vec::new();
                let mut flush = |pending: &mut Vec<u32>, items: &mut Vec<u64>, runs: &mut Vec<Run>| {
                    if pending.is_empty() {
                        return;
                    }
                    let text: String = pending.iter().map(|&t| g.terminal(t)).collect();
                    let toks = match tokenize_run(&text) {
                        Some(t) => t,
                        None => {
                            plan_ok = false;
                            Vec::new()
                        }
                    };
                    items.push(runs.len() as u64);
                    let effect = RunEffect::of(&toks);
                    runs.push(Run { terminals: pending.len() as u32, text: text.into(), toks: toks.into(), effect });
                    pending.clear();
                };
                for s in alt.symbols() {
                    match *s {
                        Symbol::Terminal(t) => pending.push(t),
                        Symbol::NonTerminal(r) => {
                            flush(&mut pending, &mut items, &mut runs);
                            items.push(PACKED_NT | u64::from(r));
                        }
                    }
                }
                flush(&mut pending, &mut items, &mut runs);
                let lead = match items.first() {
                    Some(&x) if x & PACKED_NT == 0 => Some(items.remove(0) as u32),
                    _ => None,
                };
                items.reverse();
                alts.push(CAlt { items_rev: items.into(), lead, nt_count: alt.nt_count() as u32, child_codons: 0 });
            }
            alts.shrink_to_fit();
            rules.push(CRule { alts: alts.into(), magic: rule.mod_magic, min_steps: rule.min_steps(), min_codons: 0 });
        }
        // Fewest codons per rule: a fixpoint from "unknown" (every rule terminates, or
        // the grammar would have been rejected, so it converges).
        let mut min_codons = vec![u32::MAX; rules.len()];
        loop {
            let mut changed = false;
            for (r, rule) in g.rules().iter().enumerate() {
                for alt in rule.alternatives() {
                    let mut sum = 1u32;
                    for s in alt.symbols() {
                        if let Symbol::NonTerminal(c) = *s {
                            sum = sum.saturating_add(min_codons[c as usize]);
                        }
                    }
                    if sum < min_codons[r] {
                        min_codons[r] = sum;
                        changed = true;
                    }
                }
            }
            if !changed {
                break;
            }
        }
        for ((crule, rule), &mc) in rules.iter_mut().zip(g.rules()).zip(&min_codons) {
            crule.min_codons = mc;
            for (calt, alt) in crule.alts.iter_mut().zip(rule.alternatives()) {
                calt.child_codons = alt
                    .symbols()
                    .iter()
                    .map(|s| match *s {
                        Symbol::NonTerminal(c) => min_codons[c as usize],
                        Symbol::Terminal(_) => 0,
                    })
                    .fold(0u32, u32::saturating_add);
            }
        }
        if !plan_ok {
            for r in &mut runs {
                r.toks = Box::new([]);
                r.effect = None;
            }
        }
        Compiled { rules: rules.into(), runs: runs.into(), scored_from_runs: plan_ok }
    }
}

/// What the mapper does with each run it pops.
pub(crate) trait RunSink {
    /// Whether [`RunSink::run`] does anything (the mapper skips the run lookup if not).
    const WANTS_RUNS: bool = true;
    fn run(&mut self, run: &Run);
}

/// Statistics only.
pub(crate) struct NoOutput;
impl RunSink for NoOutput {
    const WANTS_RUNS: bool = false;
    #[inline]
    fn run(&mut self, _: &Run) {}
}

/// The phenotype string.
pub(crate) struct TextOutput<'a>(pub(crate) &'a mut String);
impl RunSink for TextOutput<'_> {
    #[inline]
    fn run(&mut self, run: &Run) {
        self.0.push_str(&run.text);
    }
}

impl RunSink for DiversityScan {
    #[inline]
    fn run(&mut self, run: &Run) {
        self.feed_run(&run.toks, run.effect.as_ref());
    }
}

/// The phenotype string and D in one pass.
pub(crate) struct TextAndScore<'a>(pub(crate) &'a mut String, pub(crate) &'a mut DiversityScan);
impl RunSink for TextAndScore<'_> {
    #[inline]
    fn run(&mut self, run: &Run) {
        self.0.push_str(&run.text);
        self.1.feed_run(&run.toks, run.effect.as_ref());
    }
}
