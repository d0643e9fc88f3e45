//! Mappings that keep the mapper's state at the first codon a mutation changes, so that
//! the mutated child is mapped from there instead of from its first codon.
//!
//! Why this exists: a genetic step maps every offspring twice — before mutation, for
//! its used codons (they bound the mutation, §5.6), and after, for its D — and these
//! mappings are most of the cost of a learning agent. Yet a mutated child derives
//! exactly like the child before mutation until the first mutated codon whose new value
//! picks another alternative (`old % n != new % n`; with the swarm's parameters more
//! than a third of the children have no such codon at all and keep their mapping and D).
//! So the first mapping asks a hook at every codon it reads — the genetic step draws the
//! mutations there, in order — and keeps the mapper's whole state at the first codon
//! the hook reports as changed: the symbol stack (a persistent linked list, so the state
//! is one index into it), the deepest depth so far, the codons the pending
//! non-terminals still need, and the diversity scan. The second mapping starts from it.
//!
//! Exactness: the loop is `Mapper`'s compiled loop (`run_runs`) on a linked stack, with
//! the same checks in the same order, so a resumed mapping has the validity, used
//! codons, depth and D of a mapping from the start (a property test checks this on
//! every shipped grammar). Codons the first mapping did not read cannot change what it
//! read: an invalid child stays invalid at the same codon whatever its unread codons.
//! As everywhere in the mapper, used codons and depth of an *invalid* mapping are
//! diagnostic only.
//!
//! A tape lives for one genetic step: [`Tape::clear`] forgets everything.

use super::compiled::Compiled;
use super::diversity::DiversityScan;
use super::grammar::{fast_mod, pack_symbol, Symbol, PACKED_NT};
use super::mapper::{MapLimits, MapStats, EMPTY_GENOME};

/// End of the linked stack.
const NIL: u32 = u32::MAX;

/// A cell of the persistent symbol stack: a packed entry (symbol in the low 32 bits,
/// depth in the high 32, as in `Mapper`) and the cell below it.
#[derive(Debug, Clone, Copy)]
struct Cell {
    entry: u64,
    below: u32,
}

/// The mapper's state at the top of the loop iteration that reads a codon: resuming
/// from it replays that iteration (the same pops and checks) and then reads the codon
/// from the new genome.
#[derive(Debug, Clone, Copy)]
struct Snap {
    /// Top of the stack: the non-terminal about to read the codon.
    head: u32,
    /// The runs of terminals written so far (see [`Tape::runs`]): the mapping's own
    /// from `runs_at`, `runs_len` of them (snapshots are taken in mappings from the
    /// start only).
    runs_at: u32,
    runs_len: u32,
    max_depth: u32,
    need: u32,
    scan: DiversityScan,
}

/// A kept state: the mapping stood at codon `at`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Mark {
    at: u32,
    snap: u32,
}

/// What a mapping on the tape found.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Mapped {
    pub(crate) stats: MapStats,
    /// D (NaN when invalid).
    pub(crate) d: f64,
    /// The state at the first codon the hook reported as changed.
    pub(crate) mark: Option<Mark>,
    /// The runs of terminals the mapping wrote ([`Tape::phenotype_runs`]).
    pub(crate) runs: Runs,
}

/// The runs of terminals a mapping wrote, as two spans of [`Tape::runs`]: those of the
/// mapping it resumed from, up to the kept state, then its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Runs {
    before: (u32, u32),
    own: (u32, u32),
}

/// Where a mapping starts: from scratch, or from a kept state (of a genome that agrees
/// with this one on the codons read before it, modulo the alternatives read them).
#[derive(Debug, Clone, Copy)]
pub(crate) enum Origin {
    Start,
    Mark(Mark),
}

/// The stack cells and kept states of the mappings of one genetic step.
#[derive(Debug, Default)]
pub(crate) struct Tape {
    cells: Vec<Cell>,
    snaps: Vec<Snap>,
    /// The runs of terminals (ids of `Compiled::runs`) the mappings wrote, each
    /// mapping's in one span ([`Runs`]): a mapping's phenotype is the text of its runs
    /// in order, so the winner's phenotype is known without mapping it again.
    runs: Vec<u32>,
}

/// A hook that never reports a change (for mappings that keep nothing).
pub(crate) fn no_change(_: usize, _: u32, _: u32, _: u64) -> bool {
    false
}

impl Tape {
    /// Forget every mapping (their marks become meaningless).
    pub(crate) fn clear(&mut self) {
        self.cells.clear();
        self.snaps.clear();
        self.runs.clear();
    }

    /// The run ids of the phenotype of a valid mapping ([`Mapped::runs`]), in order,
    /// appended to `out`. The phenotype is the concatenation of their texts: the mapper
    /// writes exactly the runs the tape feeds to the diversity scan, at the same points.
    pub(crate) fn phenotype_runs(&self, runs: Runs, out: &mut Vec<u32>) {
        for (at, len) in [runs.before, runs.own] {
            out.extend_from_slice(&self.runs[at as usize..(at + len) as usize]);
        }
    }

    /// Map `genome` and score it, starting from `from`. `changed(i, codon, alts,
    /// magic)` is called for every codon `i` the mapping reads, in order, with the
    /// number of alternatives of the non-terminal reading it and their
    /// [`fast_mod`] multiplier; the state at the first codon it returns `true` for is
    /// kept as the result's mark.
    ///
    /// `#[inline]`: its one hot caller is the genetic step's offspring loop; without the
    /// hint, where this lands among the crate's codegen units shifts with unrelated
    /// changes, and called out of line it costs ~0.8 % more instructions a run.
    #[inline]
    pub(crate) fn map(
        &mut self,
        c: &Compiled,
        start: u32,
        genome: &[u32],
        limits: MapLimits,
        from: Origin,
        mut changed: impl FnMut(usize, u32, u32, u64) -> bool,
    ) -> Mapped {
        let n = genome.len();
        let mut mark = None;
        let own = self.runs.len() as u32;
        let (mut head, mut used, mut max_depth, mut need, mut scan, before) = match from {
            Origin::Start => {
                self.cells.push(Cell { entry: pack_symbol(Symbol::NonTerminal(start)) | (1 << 32), below: NIL });
                let head = self.cells.len() as u32 - 1;
                (head, 0, 1, c.rules[start as usize].min_codons as usize, DiversityScan::default(), (own, 0))
            }
            Origin::Mark(m) => {
                let s = self.snaps[m.snap as usize];
                (s.head, m.at as usize, s.max_depth as usize, s.need as usize, s.scan, (s.runs_at, s.runs_len))
            }
        };
        if n == 0 {
            return Mapped { stats: EMPTY_GENOME, d: f64::NAN, mark, runs: Runs { before, own: (own, 0) } };
        }
        let depth_limit = limits.depth_cap();
        // A resumed mapping of a shorter genome may already have too few codons left.
        let mut valid_so_far = need <= n.saturating_sub(used);
        while valid_so_far && head != NIL {
            if max_depth > depth_limit {
                break;
            }
            let Cell { entry, below } = self.cells[head as usize];
            let d = (entry >> 32) as usize;
            let code = entry as u32;
            if u64::from(code) & PACKED_NT == 0 {
                let run = &c.runs[code as usize];
                max_depth = max_depth.max(d);
                if d > depth_limit && run.terminals > 1 {
                    // The literal loop stops after this run's first terminal.
                    break;
                }
                scan.feed_run(&run.toks, run.effect.as_ref());
                self.runs.push(code);
                head = below;
                continue;
            }
            let rule = &c.rules[(u64::from(code) & !PACKED_NT) as usize];
            let depth_before = max_depth;
            max_depth = max_depth.max(d);
            if d + rule.min_steps as usize > depth_limit && below != NIL {
                break;
            }
            let nalts = rule.alts.len() as u32;
            let codon = genome[used];
            if changed(used, codon, nalts, rule.magic) && mark.is_none() {
                let runs_len = self.runs.len() as u32 - own;
                self.snaps.push(Snap {
                    head,
                    runs_at: own,
                    runs_len,
                    max_depth: depth_before as u32,
                    need: need as u32,
                    scan,
                });
                mark = Some(Mark { at: used as u32, snap: self.snaps.len() as u32 - 1 });
            }
            let alt = &rule.alts[fast_mod(codon, rule.magic, nalts) as usize];
            used += 1;
            need = need - rule.min_codons as usize + alt.child_codons as usize;
            if need > n - used {
                break;
            }
            head = below;
            let child_depth = ((d + 1) as u64) << 32;
            if let Some(lead) = alt.lead {
                let not_last = head != NIL || !alt.items_rev.is_empty();
                let run = &c.runs[lead as usize];
                if max_depth > depth_limit || (d + 1 > depth_limit && (run.terminals > 1 || not_last)) {
                    // Stops with the lead run pending: invalid.
                    valid_so_far = false;
                    break;
                }
                max_depth = max_depth.max(d + 1);
                scan.feed_run(&run.toks, run.effect.as_ref());
                self.runs.push(lead);
            }
            for &x in alt.items_rev.iter() {
                self.cells.push(Cell { entry: x | child_depth, below: head });
                head = self.cells.len() as u32 - 1;
            }
        }
        let valid = valid_so_far && head == NIL;
        let stats = MapStats { valid, used_codons: used, depth: max_depth };
        let d = if valid { scan.finish() } else { f64::NAN };
        let runs = Runs { before, own: (own, self.runs.len() as u32 - own) };
        Mapped { stats, d, mark, runs }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::init::uniform_tree;
    use crate::ge::mapper::tests::grammar;
    use crate::ge::mapper::Mapper;
    use crate::ge::Grammar;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// What a mapping from the start gives: validity, and for a valid one used codons,
    /// depth and D (bit for bit).
    fn expected(m: &mut Mapper, g: &Grammar, genome: &[u32], limits: MapLimits) -> (bool, usize, usize, u64) {
        let (st, d) = m.map_scored(g, genome, limits);
        if st.valid {
            (true, st.used_codons, st.depth, d.to_bits())
        } else {
            (false, 0, 0, 0)
        }
    }

    fn got(r: &Mapped) -> (bool, usize, usize, u64) {
        if r.stats.valid {
            (true, r.stats.used_codons, r.stats.depth, r.d.to_bits())
        } else {
            (false, 0, 0, 0)
        }
    }

    fn mutate(rng: &mut ChaCha8Rng, genome: &mut [u32], upto: usize, p: f64) {
        for c in genome[..upto].iter_mut() {
            if rng.random::<f64>() < p {
                *c = rng.random_range(0..=2000);
            }
        }
    }

    /// A random genome of `g`: a derivation with a tail, often mutated, sometimes cut or
    /// grown (so that invalid genomes of every kind occur).
    fn genome(rng: &mut ChaCha8Rng, g: &Grammar, depth: usize) -> Vec<u32> {
        let mut x = uniform_tree(g, 2000, depth, rng).genome;
        match rng.random_range(0..4) {
            0 => {}
            1 => {
                let n = x.len();
                mutate(rng, &mut x, n, 0.1)
            }
            2 => x.truncate(rng.random_range(1..=x.len())),
            _ => x.extend((0..rng.random_range(0..20)).map(|_| rng.random_range(0..=2000))),
        }
        x
    }

    /// Mapping a child with a hook that reports its mutated codons, then resuming the
    /// mutated child from the state kept at the first one that picks another
    /// alternative, gives what mapping from the start gives, on every shipped grammar,
    /// for valid and invalid genomes and with the depth limits that matter (the limit,
    /// one below it, and none).
    #[test]
    fn resumed_mappings_equal_mappings_from_the_start() {
        let mut m = Mapper::new();
        let mut tape = Tape::default();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (mut resumed, mut kept) = (0usize, 0usize);
        for (name, text) in crate::grammars::BUILTIN {
            let g = grammar(text);
            let c = g.compiled();
            assert!(c.scored_from_runs, "{name}");
            for max_tree_depth in [10, 9, 0] {
                let limits = MapLimits { max_tree_depth, max_wraps: 0 };
                for _ in 0..300 {
                    tape.clear();
                    // A crossed child, then its mutant.
                    let (g0, g1) = (genome(&mut rng, &g, 10), genome(&mut rng, &g, 10));
                    let mut child: Vec<u32> = g0[..rng.random_range(1..=g0.len())].to_vec();
                    child.extend_from_slice(&g1[rng.random_range(0..g1.len())..]);
                    let mut mutant = child.clone();
                    mutate(&mut rng, &mut mutant, child.len(), 0.15);
                    let mut reads = 0;
                    let r = tape.map(c, g.start(), &child, limits, Origin::Start, |i, codon, alts, magic| {
                        assert_eq!((i, codon), (reads, child[i]), "codons are reported in order");
                        reads += 1;
                        alts > 1 && fast_mod(codon, magic, alts) != fast_mod(mutant[i], magic, alts)
                    });
                    assert_eq!(got(&r), expected(&mut m, &g, &child, limits), "{name}: {child:?}");
                    let want = expected(&mut m, &g, &mutant, limits);
                    match r.mark {
                        None => {
                            kept += 1;
                            assert_eq!(got(&r), want, "{name}: unchanged derivation {mutant:?}")
                        }
                        Some(mark) => {
                            resumed += 1;
                            let again = tape.map(c, g.start(), &mutant, limits, Origin::Mark(mark), no_change);
                            assert_eq!(got(&again), want, "{name}: {mutant:?} from {child:?} at {mark:?}");
                        }
                    }
                }
            }
        }
        assert!(resumed > 3000 && kept > 1000, "too few of a kind: {resumed} resumed, {kept} kept");
    }
}
