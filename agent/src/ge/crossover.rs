//! Variable one-point crossover pairs, drawn from the accepted ones directly.
//!
//! Why this exists: PonyGE2 draws a pair of parent positions, a cut point in each and
//! whether to cross, and throws the pair away when a child would be longer than
//! `max_genome_length`. Once genes have grown to that length (they do, within a few
//! hundred steps), a crossed pair survives only when its two cut points are equal, so
//! a genetic step made about 80 attempts (some 400 random numbers) for its 12 pairs.
//! The attempts are independent, so the pairs that survive are independent draws from
//! the attempt's distribution *conditioned on surviving*; [`PairSampler`] draws from
//! that conditional distribution directly. For each ordered pair of parent positions
//! it counts, in closed form, the cut-point pairs that give acceptable children, and
//! then draws (pair, crossed or not, cut points) with exactly the probabilities the
//! rejection loop accepts them with. The random stream differs; the law of the
//! offspring does not.
//!
//! Lengths: a crossed pair with cut points a, b of parents of lengths L0, L1 gives
//! children of lengths a + L1 − b and b + L0 − a; with d = a − b both lie in
//! [1, max] iff d ∈ [max(1 − L1, L0 − max), min(max − L1, L0 − 1)].

use rand::Rng;

/// One ordered pair of parent positions and what it can produce.
#[derive(Debug, Clone, Copy)]
struct Pair {
    i: usize,
    j: usize,
    /// Probability that an attempt on this pair survives.
    weight: f64,
    /// Probability that an attempt on this pair is crossed and survives.
    crossed: f64,
    /// Cut-point spans of the two parents (a ∈ [1, u0], b ∈ [1, u1]).
    u0: i64,
    u1: i64,
    /// Band of a − b that gives acceptable children, and the number of (a, b) in it.
    dlo: i64,
    dhi: i64,
    count: i64,
}

/// A drawn crossover attempt that survives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) struct Draw {
    pub(crate) i: usize,
    pub(crate) j: usize,
    /// Cut points when crossed; `None` for plain copies.
    pub(crate) cut: Option<(usize, usize)>,
}

/// The surviving crossover attempts of one genetic step's parents.
#[derive(Debug, Default)]
pub(crate) struct PairSampler {
    /// (length, cut-point span) of each parent.
    lens: Vec<(i64, i64)>,
    parents: usize,
    max_len: usize,
    crossover_prob: f64,
    /// Some attempt can survive.
    viable: bool,
    /// Attempts drawn since [`PairSampler::plan`].
    drawn: usize,
    /// Every viable ordered pair, once weighed (see [`TABLE_AFTER`]).
    pairs: Vec<Pair>,
    /// Whether `pairs` is filled, and their total weight.
    table: bool,
    total: f64,
}

/// Up to this many parents, all ordered pairs are weighed (ST = 7 gives 3, the pools
/// of a typical run up to about 15) ...
const TABLE_PARENTS: usize = 16;
/// ... once this many attempts were drawn: a genetic step usually stops after one or
/// two pairs (`ge::ceiling`), and weighing up to 240 ordered pairs for them costs more
/// than drawing them by rejection.
const TABLE_AFTER: usize = 2;

/// Pairs drawn in a row without one surviving before [`PairSampler::draw`] gives up.
const MAX_PAIR_DRAWS: usize = 1_000_000;

/// A uniform position in `0..n`: `rng.random_range(0..n)`, drawn from a `u32` range
/// when `n` fits in one. rand samples a `usize` range that fits in 32 bits with the
/// same `u32` sampler (same words, same value), but the `u32` entry point inlines where
/// the `usize` one, with its 64-bit branch, was a call of ~50 instructions, twice per
/// attempt of the rejection loop (1.6 % of a run's instructions).
#[inline]
fn position<R: Rng + ?Sized>(rng: &mut R, n: usize) -> usize {
    match u32::try_from(n) {
        Ok(n) => rng.random_range(0..n) as usize,
        Err(_) => rng.random_range(0..n),
    }
}

/// #{(a, b) ∈ [1, u0] × [1, u1] : a − b ≤ d}.
fn at_most(u0: i64, u1: i64, d: i64) -> i64 {
    // For each a the b ≥ a − d count clamp(u1 + 1 − t, 0, u1) with t = a − d; sum over
    // t ∈ [1 − d, u0 − d] in the two pieces where it is not 0.
    let (lo, hi) = (1 - d, u0 - d);
    let mut n = 0;
    // t ≤ 1: all u1 values of b.
    let full = hi.min(1) - lo + 1;
    if full > 0 {
        n += full * u1;
    }
    // 2 ≤ t ≤ u1: u1 + 1 − t values, an arithmetic series.
    let (s, e) = (lo.max(2), hi.min(u1));
    if e >= s {
        n += (e - s + 1) * ((u1 + 1 - s) + (u1 + 1 - e)) / 2;
    }
    n
}

impl PairSampler {
    /// Prepare for parents given as (genome length, cut-point span) — parent k's cut
    /// point is drawn from `1..=span`. Pairs are drawn uniformly and kept with their
    /// survival probability — the rejection loop with the cut-point and crossover draws
    /// folded into one test — except that with few parents, from the
    /// [`TABLE_AFTER`]-th draw on, every ordered pair is weighed once and drawn by
    /// weight (with many, as crowded cells give pools of hundreds, that would be
    /// quadratic). Both draw from the same law.
    pub(crate) fn plan(
        &mut self,
        parents: impl IntoIterator<Item = (usize, usize)>,
        max_len: usize,
        crossover_prob: f64,
    ) {
        self.pairs.clear();
        self.table = false;
        self.total = 0.0;
        self.drawn = 0;
        self.max_len = max_len;
        self.crossover_prob = crossover_prob;
        self.lens.clear();
        self.lens.extend(parents.into_iter().map(|(l, u)| (l as i64, u as i64)));
        self.parents = self.lens.len();
        self.viable = self.any_viable();
    }

    /// Weigh every ordered pair.
    fn weigh_all(&mut self) {
        self.table = true;
        for i in 0..self.parents {
            for j in 0..self.parents {
                if i != j {
                    let p = self.weigh(i, j);
                    if p.weight > 0.0 {
                        self.total += p.weight;
                        self.pairs.push(p);
                    }
                }
            }
        }
    }

    /// Whether some ordered pair of distinct parents has a surviving attempt: two
    /// parents whose copies fit, or else a pair with an acceptable crossover.
    fn any_viable(&self) -> bool {
        if self.parents < 2 {
            return false;
        }
        let max = self.max_len as i64;
        let fitting = self.lens.iter().filter(|&&(l, _)| (1..=max).contains(&l)).count();
        if fitting >= 2 && self.crossover_prob < 1.0 {
            return true;
        }
        // Crossover only: quadratic, but only reached when copies cannot survive.
        (0..self.parents).any(|i| (0..self.parents).any(|j| i != j && self.weigh(i, j).crossed > 0.0))
    }

    /// The ordered pair (i, j) and its survival probabilities.
    ///
    /// `#[inline]`: the rejection loop of [`PairSampler::draw`] weighs ~5 pairs per
    /// draw and reads only the weight of all but the last; called out of line, the whole
    /// `Pair` went through memory every time.
    #[inline]
    fn weigh(&self, i: usize, j: usize) -> Pair {
        let max = self.max_len as i64;
        let ((l0, u0), (l1, u1)) = (self.lens[i], self.lens[j]);
        let copies_fit = l0 >= 1 && l1 >= 1 && l0 <= max && l1 <= max;
        let (dlo, dhi) = ((1 - l1).max(l0 - max), (max - l1).min(l0 - 1));
        let count = if dhi < dlo || u0 < 1 || u1 < 1 {
            0
        } else if dlo == 0 && dhi == 0 {
            // Both parents at the length limit (the usual case once genes have grown):
            // only equal cut points fit.
            u0.min(u1)
        } else {
            at_most(u0, u1, dhi) - at_most(u0, u1, dlo - 1)
        };
        let crossed = if count > 0 { self.crossover_prob * count as f64 / (u0 * u1) as f64 } else { 0.0 };
        let weight = crossed + if copies_fit { 1.0 - self.crossover_prob } else { 0.0 };
        Pair { i, j, weight, crossed, u0, u1, dlo, dhi, count }
    }

    /// Whether any attempt can survive.
    pub(crate) fn viable(&self) -> bool {
        self.viable
    }

    /// Draw a surviving attempt; `None` when none is viable or [`MAX_PAIR_DRAWS`]
    /// pairs in a row did not survive.
    pub(crate) fn draw<R: Rng + ?Sized>(&mut self, rng: &mut R) -> Option<Draw> {
        if !self.viable {
            return None;
        }
        self.drawn += 1;
        if self.drawn > TABLE_AFTER && self.parents <= TABLE_PARENTS && !self.table {
            self.weigh_all();
        }
        let p = if !self.table {
            let mut tries = 0;
            loop {
                tries += 1;
                if tries > MAX_PAIR_DRAWS {
                    return None;
                }
                // random.sample(parents, 2): two distinct positions.
                let i = position(rng, self.parents);
                let mut j = position(rng, self.parents - 1);
                if j >= i {
                    j += 1;
                }
                let p = self.weigh(i, j);
                if rng.random::<f64>() < p.weight {
                    break p;
                }
            }
        } else {
            let mut x = rng.random::<f64>() * self.total;
            let mut pick = self.pairs[self.pairs.len() - 1];
            for p in &self.pairs {
                if x < p.weight {
                    pick = *p;
                    break;
                }
                x -= p.weight;
            }
            pick
        };
        if rng.random::<f64>() * p.weight >= p.crossed {
            return Some(Draw { i: p.i, j: p.j, cut: None });
        }
        // A uniform (a, b) in the band.
        let (a, b) = p.kth(rng.random_range(0..p.count));
        Some(Draw { i: p.i, j: p.j, cut: Some((a as usize, b as usize)) })
    }
}

impl Pair {
    /// The `k`-th cut-point pair (a, b) of the band, in order of a, then b (`k` below
    /// `count`). With equal cut points only (both parents at the length limit, the
    /// usual case) that is (k + 1, k + 1); otherwise a walk over a.
    fn kth(&self, mut k: i64) -> (i64, i64) {
        if self.dlo == 0 && self.dhi == 0 {
            return (k + 1, k + 1);
        }
        for a in 1..=self.u0 {
            let (b_lo, b_hi) = ((a - self.dhi).max(1), (a - self.dlo).min(self.u1));
            let n = (b_hi - b_lo + 1).max(0);
            if k < n {
                return (a, b_lo + k);
            }
            k -= n;
        }
        unreachable!("the band holds `count` cut-point pairs")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use std::collections::HashMap;

    /// [`position`] draws `0..n` from a u32 range where the rule is a `usize` range:
    /// rand must give the same value from the same words, or every trajectory would
    /// change. Fails if a rand update makes the two differ.
    #[test]
    fn u32_positions_are_the_usize_draws() {
        let mut a = ChaCha8Rng::seed_from_u64(7);
        let mut b = ChaCha8Rng::seed_from_u64(7);
        for k in 0..200_000u32 {
            // Small pools, and ranges where the biased-sample branch is common.
            let n = if k % 2 == 0 { 2 + k % 300 } else { u32::MAX - k } as usize;
            assert_eq!(a.random_range(0..n), position(&mut b, n), "n {n}");
        }
        let big = u32::MAX as usize + 7;
        assert_eq!(a.random_range(0..big), position(&mut b, big), "beyond 32 bits");
        assert_eq!(a.random::<u64>(), b.random::<u64>(), "both streams read the same words");
    }

    #[test]
    fn equal_cut_points_count_as_the_band_does() {
        for u0 in 1..=30i64 {
            for u1 in 1..=30i64 {
                assert_eq!(u0.min(u1), at_most(u0, u1, 0) - at_most(u0, u1, -1), "u0 {u0} u1 {u1}");
            }
        }
    }

    /// The k-th cut-point pair of a band is the k-th of the band's pairs listed by a,
    /// then b, for bands of equal cut points (the shortcut) and others.
    #[test]
    fn kth_pair_of_a_band_is_the_kth_listed() {
        for u0 in 1..=12i64 {
            for u1 in 1..=12i64 {
                for (dlo, dhi) in [(0, 0), (-2, 1), (-5, -1), (1, 4)] {
                    let listed: Vec<(i64, i64)> = (1..=u0)
                        .flat_map(|a| (1..=u1).map(move |b| (a, b)))
                        .filter(|&(a, b)| (dlo..=dhi).contains(&(a - b)))
                        .collect();
                    let count = listed.len() as i64;
                    let p = Pair { i: 0, j: 1, weight: 1.0, crossed: 1.0, u0, u1, dlo, dhi, count };
                    for (k, &want) in listed.iter().enumerate() {
                        assert_eq!(p.kth(k as i64), want, "u {u0} {u1} band {dlo}..={dhi} k {k}");
                    }
                }
            }
        }
    }

    #[test]
    fn band_counts_match_brute_force() {
        for u0 in 1..=9i64 {
            for u1 in 1..=9i64 {
                for d in -12..=12i64 {
                    let brute = (1..=u0).flat_map(|a| (1..=u1).map(move |b| a - b)).filter(|&x| x <= d).count();
                    assert_eq!(at_most(u0, u1, d), brute as i64, "u0 {u0} u1 {u1} d {d}");
                }
            }
        }
    }

    /// The attempts the rejection loop keeps, counted by outcome.
    fn rejection_loop(
        rng: &mut ChaCha8Rng,
        lens: &[usize],
        spans: &[usize],
        max_len: usize,
        pc: f64,
        n: usize,
    ) -> HashMap<Draw, u32> {
        let c = lens.len();
        let mut kept: HashMap<Draw, u32> = HashMap::new();
        let mut k = 0;
        while k < n {
            let i = rng.random_range(0..c);
            let mut j = rng.random_range(0..c - 1);
            if j >= i {
                j += 1;
            }
            let (a, b) = (rng.random_range(1..=spans[i]), rng.random_range(1..=spans[j]));
            let cross = rng.random::<f64>() < pc;
            let (l0, l1) = if cross { (a + lens[j] - b, b + lens[i] - a) } else { (lens[i], lens[j]) };
            if l0 == 0 || l1 == 0 || l0 > max_len || l1 > max_len {
                continue;
            }
            k += 1;
            *kept.entry(Draw { i, j, cut: cross.then_some((a, b)) }).or_default() += 1;
        }
        kept
    }

    /// The law of the drawn attempts is the law of the attempts the rejection loop
    /// keeps: compare frequencies of every (pair, cut points) outcome, half drawn from a
    /// table of pairs (few parents) and half from pairs drawn and kept by weight (many
    /// parents are only ever drawn so; there the outcomes are compared by pair and
    /// crossed-or-not).
    #[test]
    fn draws_follow_the_rejection_loop() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let few = (vec![9usize, 7, 10, 4], vec![5usize, 7, 3, 4]);
        // Genes at the length limit, as in a run after a few hundred steps.
        let grown = (vec![100usize, 98, 100, 95, 100, 87, 100], vec![20usize, 25, 18, 22, 30, 15, 21]);
        let many: (Vec<usize>, Vec<usize>) = (0..20).map(|k| (4 + k % 7, 1 + k % 5)).unzip();
        for (lens, spans, by_cut, max_len) in
            [(few.0, few.1, true, 10), (grown.0, grown.1, true, 100), (many.0, many.1, false, 10)]
        {
            let (pc, n) = (0.9, 400_000);
            let coarse = |d: Draw| if by_cut { d } else { Draw { cut: d.cut.map(|_| (0, 0)), ..d } };
            let mut want: HashMap<Draw, u32> = HashMap::new();
            for (d, k) in rejection_loop(&mut rng, &lens, &spans, max_len, pc, n) {
                *want.entry(coarse(d)).or_default() += k;
            }
            // Planned once (the table after the first draws, with few parents), and
            // planned before every draw (always by rejection).
            let mut once = PairSampler::default();
            once.plan(lens.iter().copied().zip(spans.iter().copied()), max_len, pc);
            let mut got: HashMap<Draw, u32> = HashMap::new();
            let mut each = PairSampler::default();
            for k in 0..n {
                let d = if k % 2 == 0 {
                    once.draw(&mut rng)
                } else {
                    each.plan(lens.iter().copied().zip(spans.iter().copied()), max_len, pc);
                    each.draw(&mut rng)
                };
                let d = d.expect("viable");
                if let Some((a, b)) = d.cut {
                    let (l0, l1) = (a + lens[d.j] - b, b + lens[d.i] - a);
                    assert!((1..=max_len).contains(&l0) && (1..=max_len).contains(&l1), "{d:?}");
                }
                *got.entry(coarse(d)).or_default() += 1;
            }
            for (k, &w) in &want {
                let g = got.get(k).copied().unwrap_or(0);
                let p = f64::from(w) / n as f64;
                let sd = (p * (1.0 - p) / n as f64).sqrt() * std::f64::consts::SQRT_2;
                let f = f64::from(g) / n as f64;
                assert!((f - p).abs() < 6.0 * sd + 1e-5, "{k:?}: rejection {p}, direct {f}");
            }
            assert!(got.keys().all(|k| want.contains_key(k)), "a draw the rejection loop never keeps");
        }
    }

    #[test]
    fn nothing_viable_when_every_child_is_too_long() {
        let mut s = PairSampler::default();
        s.plan([(40, 40), (40, 40)], 30, 0.9);
        assert!(!s.viable());
        s.plan([(40, 40), (40, 40)], 30, 1.0);
        assert!(!s.viable());
        // Equal cut points keep both lengths.
        s.plan([(30, 30), (30, 30)], 30, 1.0);
        assert!(s.viable());
        // Many parents: the same answers without weighing every pair in advance.
        s.plan([(40, 40); 20], 30, 0.9);
        assert!(!s.viable());
        s.plan([(30, 30); 20], 30, 1.0);
        assert!(s.viable());
    }
}
