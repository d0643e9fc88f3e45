//! Recorded mappings that a genetic step resumes from instead of mapping offspring from
//! their first codon.
//!
//! Why this exists: a genetic step maps every offspring twice (after crossover, for its
//! used codons; after mutation, for its D), and these mappings were most of the cost of
//! a learning agent. Yet an offspring shares most of its derivation with a mapping
//! already done: a crossed child `g0[..p] ++ g1[q..]` derives exactly like its parent
//! `g0` until it reads codon `p`, and a mutated child derives exactly like the child
//! before mutation until the first mutated codon whose new value picks another
//! alternative (`old % n != new % n`; with the swarm's parameters more than a third of
//! the children have no such codon at all and keep their mapping and D). So the tape
//! records, at every codon a mapping reads, the mapper's whole state — the symbol stack
//! (a persistent linked list, so a snapshot is one index), the deepest depth so far, the
//! codons the pending non-terminals still need, and the diversity scan — and a later
//! mapping starts from such a snapshot.
//!
//! Exactness: the loop is `Mapper`'s compiled loop (`run_runs`) on a linked stack, with
//! the same checks in the same order, so a resumed mapping has the validity, used
//! codons, depth and D of a mapping from the start (a property test checks this on
//! every shipped grammar). The one check that depends on the genome's length — the
//! pending non-terminals need more codons than are left — is monotone (what the
//! pending symbols need falls by at most one per codon read, the codons left by exactly
//! one), so a child shorter than the recorded parent that would have failed it before
//! the snapshot fails it right after: it is invalid either way. As everywhere in the
//! mapper, used codons and depth of an *invalid* mapping are diagnostic only.
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
pub(crate) struct Snap {
    /// Top of the stack: the non-terminal about to read the codon.
    head: u32,
    max_depth: u32,
    need: u32,
    /// Number of alternatives of that non-terminal (a new codon value changes the
    /// derivation iff it differs from the old one modulo this), and its `fast_mod`
    /// multiplier.
    alts: u32,
    magic: u64,
    scan: DiversityScan,
}

/// What a mapping on the tape found, and where its snapshots are.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Recorded {
    pub(crate) stats: MapStats,
    /// D (NaN when invalid).
    pub(crate) d: f64,
    /// The snapshots of codons `0..reads`: `cut` of them from an earlier recording
    /// starting at tape index `lower`, the rest at tape index `upper`.
    lower: u32,
    cut: u32,
    upper: u32,
    /// Codons the mapping read (= its snapshots).
    reads: u32,
}

impl Recorded {
    /// Codons the mapping read.
    pub(crate) fn reads(&self) -> usize {
        self.reads as usize
    }
}

/// Where a mapping starts: from scratch, or from the snapshot of codon `at` of a
/// recording.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Origin<'r> {
    Start,
    Snapshot(&'r Recorded, usize),
}

/// Snapshots and stack cells of the mappings of one genetic step.
#[derive(Debug, Default)]
pub(crate) struct Tape {
    cells: Vec<Cell>,
    snaps: Vec<Snap>,
}

impl Tape {
    /// Forget every recording (their [`Recorded`] handles become meaningless).
    pub(crate) fn clear(&mut self) {
        self.cells.clear();
        self.snaps.clear();
    }

    fn snap(&self, r: &Recorded, i: usize) -> &Snap {
        let i = i as u32;
        debug_assert!(i < r.reads);
        if i < r.cut {
            &self.snaps[(r.lower + i) as usize]
        } else {
            &self.snaps[(r.upper + i - r.cut) as usize]
        }
    }

    /// Whether codon `i` of the genome `r` recorded (`i < r.reads()`) picks another
    /// alternative as `new` than as `old`.
    pub(crate) fn changes(&self, r: &Recorded, i: usize, old: u32, new: u32) -> bool {
        let s = self.snap(r, i);
        s.alts > 1 && fast_mod(old, s.magic, s.alts) != fast_mod(new, s.magic, s.alts)
    }

    /// Map `genome` and score it, starting from `from` (whose genome must agree with
    /// `genome` on the codons read before the snapshot, modulo the alternatives read
    /// them). With `RECORD` the snapshots of the codons read from there on are kept, so
    /// the result can be resumed from in turn; without it the snapshots are not kept
    /// and the result must not be resumed from.
    pub(crate) fn map<const RECORD: bool>(
        &mut self,
        c: &Compiled,
        start: u32,
        genome: &[u32],
        limits: MapLimits,
        from: Origin<'_>,
    ) -> Recorded {
        let n = genome.len();
        let upper = self.snaps.len() as u32;
        let (state, lower, cut) = match from {
            Origin::Start => {
                self.cells.push(Cell { entry: pack_symbol(Symbol::NonTerminal(start)) | (1 << 32), below: NIL });
                let head = self.cells.len() as u32 - 1;
                ((head, 0, 1, c.rules[start as usize].min_codons as usize, DiversityScan::default()), 0, 0)
            }
            Origin::Snapshot(r, at) => {
                let s = *self.snap(r, at);
                // The new recording's snapshots below `at` are `r`'s: `at` of them in
                // `r`'s lower segment, or in its upper one when that is all `r` has
                // of its own. (A recording resumed from a resumed recording past its
                // cut would need three segments; a genetic step never makes one, and
                // it is recorded from the start instead.)
                let (lower, cut) = if at as u32 <= r.cut {
                    (r.lower, at as u32)
                } else if r.cut == 0 {
                    (r.upper, at as u32)
                } else {
                    return self.map::<RECORD>(c, start, genome, limits, Origin::Start);
                };
                ((s.head, at, s.max_depth as usize, s.need as usize, s.scan), lower, cut)
            }
        };
        let (mut head, mut used, mut max_depth, mut need, mut scan) = state;
        if n == 0 {
            return Recorded { stats: EMPTY_GENOME, d: f64::NAN, lower, cut, upper, reads: 0 };
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
            if RECORD {
                self.snaps.push(Snap {
                    head,
                    max_depth: depth_before as u32,
                    need: need as u32,
                    alts: nalts,
                    magic: rule.magic,
                    scan,
                });
            }
            let alt = &rule.alts[fast_mod(genome[used], rule.magic, nalts) as usize];
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
            }
            for &x in alt.items_rev.iter() {
                self.cells.push(Cell { entry: x | child_depth, below: head });
                head = self.cells.len() as u32 - 1;
            }
        }
        let valid = valid_so_far && head == NIL;
        let stats = MapStats { valid, used_codons: used, depth: max_depth };
        let d = if valid { scan.finish() } else { f64::NAN };
        Recorded { stats, d, lower, cut, upper, reads: if RECORD { used as u32 } else { 0 } }
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

    fn got(r: &Recorded) -> (bool, usize, usize, u64) {
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

    /// Recording from the start, resuming a crossed child from its parent's snapshot,
    /// and resuming a mutated child from its first changed codon give what mapping
    /// from the start gives, on every shipped grammar, for valid and invalid genomes
    /// and with the depth limits that matter (the limit, one below it, and none).
    #[test]
    fn resumed_mappings_equal_mappings_from_the_start() {
        let mut m = Mapper::new();
        let mut tape = Tape::default();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut resumed = 0usize;
        for (name, text) in crate::grammars::BUILTIN {
            let g = grammar(text);
            let c = g.compiled();
            assert!(c.scored_from_runs, "{name}");
            for max_tree_depth in [10, 9, 0] {
                let limits = MapLimits { max_tree_depth, max_wraps: 0 };
                for _ in 0..300 {
                    tape.clear();
                    let g0 = genome(&mut rng, &g, 10);
                    let g1 = genome(&mut rng, &g, 10);
                    let r0 = tape.map::<true>(c, g.start(), &g0, limits, Origin::Start);
                    assert_eq!(got(&r0), expected(&mut m, &g, &g0, limits), "{name}: {g0:?}");

                    // Crossover: the child keeps `keep` codons of g0.
                    let keep = rng.random_range(1..=g0.len());
                    let mut child: Vec<u32> = g0[..keep].to_vec();
                    child.extend_from_slice(&g1[rng.random_range(0..g1.len())..]);
                    let rc = if keep < r0.reads() {
                        resumed += 1;
                        tape.map::<true>(c, g.start(), &child, limits, Origin::Snapshot(&r0, keep))
                    } else {
                        tape.map::<true>(c, g.start(), &child, limits, Origin::Start)
                    };
                    assert_eq!(got(&rc), expected(&mut m, &g, &child, limits), "{name}: {child:?} from {g0:?}");

                    // Mutation: resume from the first codon that picks another alternative.
                    let before = child.clone();
                    let mut mutant = child;
                    mutate(&mut rng, &mut mutant, before.len(), 0.15);
                    let first = (0..rc.reads()).find(|&i| tape.changes(&rc, i, before[i], mutant[i]));
                    let want = expected(&mut m, &g, &mutant, limits);
                    match first {
                        None => assert_eq!(got(&rc), want, "{name}: unchanged derivation {mutant:?}"),
                        Some(at) => {
                            let r = tape.map::<false>(c, g.start(), &mutant, limits, Origin::Snapshot(&rc, at));
                            assert_eq!(got(&r), want, "{name}: {mutant:?} from {before:?} at {at}");
                        }
                    }
                }
            }
        }
        assert!(resumed > 3000, "too few resumed mappings: {resumed}");
    }
}
