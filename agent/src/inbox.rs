//! The genes an agent process received from other processes, kept in one buffer.
//!
//! A process hosting 100 of 1,000 agents receives ~700 genes a step from the nine
//! others. Decoded as [`GeneMsg`](geese_proto::GeneMsg)s every genome was an allocation
//! of its own, written afresh each step into memory the other processes had just pushed
//! out of the caches, then moved into its cell's list and freed: about a sixth of the
//! process's time. The [`Inbox`] decodes every genome into one buffer that is reused
//! from step to step, and lends the genes out as [`GeneRef`]s grouped by cell
//! ([`CellGenes`]); a gene is copied out only if a learner keeps it.
use crate::learner::GeneRef;
use geese_proto::net::GeneBatchHead;
use geese_proto::{genome_codons_into, AgentId, GeneMapping};

/// One received gene: its fields, and where its codons are in [`Inbox::codons`].
#[derive(Clone, Copy, Debug)]
struct Slot {
    step: u64,
    cell: u32,
    from: AgentId,
    fitness: f64,
    mapping: GeneMapping,
    start: u32,
    len: u32,
}

impl Slot {
    fn codons(&self) -> std::ops::Range<usize> {
        self.start as usize..(self.start + self.len) as usize
    }
}

/// Received genes of the steps a process has not finished, in arrival order.
#[derive(Default)]
pub struct Inbox {
    codons: Vec<u32>,
    slots: Vec<Slot>,
}

impl Inbox {
    /// File a batch of one cell's genes. False, with nothing filed, when a gene is of
    /// another step than the batch or its genome is malformed (the batch is hostile).
    pub fn file(&mut self, batch: &GeneBatchHead<'_>) -> bool {
        self.file_by_sender(batch, |_| Some(batch.cell))
    }

    /// File a batch whose genes go to the cells `cells_of` names for their senders (a
    /// batch sent ahead, [`geese_proto::net::AHEAD_CELL`]): each gene under every cell
    /// named for its sender (at GS 2 a sender is registered in up to nine cells), its
    /// genome decoded once; the genes of senders it names none for are skipped, their
    /// genomes not decoded. False, with nothing filed, as [`Inbox::file`].
    pub fn file_by_sender<I: IntoIterator<Item = u32>>(
        &mut self,
        batch: &GeneBatchHead<'_>,
        cells_of: impl Fn(AgentId) -> I,
    ) -> bool {
        if batch.genes.iter().any(|g| g.step != batch.step) {
            return false;
        }
        let (codons, slots) = (self.codons.len(), self.slots.len());
        for g in &batch.genes {
            let mut cells = cells_of(g.from).into_iter();
            let Some(cell) = cells.next() else { continue };
            let start = self.codons.len();
            let fits = u32::try_from(start).is_ok();
            if !fits || !genome_codons_into(g.genome.0, &mut self.codons) {
                self.codons.truncate(codons);
                self.slots.truncate(slots);
                return false;
            }
            let slot = Slot {
                step: g.step,
                cell,
                from: g.from,
                fitness: g.fitness,
                mapping: g.mapping,
                start: start as u32,
                len: (self.codons.len() - start) as u32,
            };
            self.slots.push(slot);
            // The same codons under the sender's other cells.
            self.slots.extend(cells.map(|cell| Slot { cell, ..slot }));
        }
        true
    }

    /// Lend the genes of step `step` to `out` with their cells, in arrival order, but not
    /// those of senders `skip` names.
    pub fn lend<'a>(&'a self, step: u64, skip: impl Fn(AgentId) -> bool, out: &mut Vec<(u32, GeneRef<'a>)>) {
        out.extend(self.slots.iter().filter(|s| s.step == step && !skip(s.from)).map(|s| {
            let gene = GeneRef {
                step: s.step,
                from: s.from,
                genome: &self.codons[s.codons()],
                shared: None,
                fitness: s.fitness,
                mapping: s.mapping,
            };
            (s.cell, gene)
        }));
    }

    /// Forget the genes of steps up to `step`; those of later steps are kept.
    pub fn retire(&mut self, step: u64) {
        let Inbox { codons, slots } = self;
        slots.retain(|s| s.step > step);
        if slots.is_empty() {
            codons.clear();
            return;
        }
        // Genes of a later step came before this one ended (rare): move them to the front.
        let mut kept = Vec::with_capacity(slots.iter().map(|s| s.len as usize).sum());
        for s in slots.iter_mut() {
            let start = kept.len() as u32;
            kept.extend_from_slice(&codons[s.codons()]);
            s.start = start;
        }
        *codons = kept;
    }

    /// Genes held.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }
}

/// A step's genes grouped by cell, each cell's sorted by sender; stable, so that what
/// came first of one sender (a learner's own gene, then as they arrived) stays first.
pub struct CellGenes<'a> {
    genes: Vec<GeneRef<'a>>,
    /// (cell, start, end) in `genes`, by cell.
    spans: Vec<(u32, usize, usize)>,
}

impl<'a> CellGenes<'a> {
    pub fn new(lent: Vec<(u32, GeneRef<'a>)>) -> CellGenes<'a> {
        // Sorting (cell, sender, arrival) keys rather than the genes themselves: a tenth
        // of the bytes to move.
        let mut order: Vec<(u64, u32)> =
            lent.iter().enumerate().map(|(i, (c, g))| ((u64::from(*c) << 32) | u64::from(g.from), i as u32)).collect();
        order.sort_unstable();
        let mut genes = Vec::with_capacity(lent.len());
        let mut spans: Vec<(u32, usize, usize)> = Vec::new();
        for (key, i) in order {
            let cell = (key >> 32) as u32;
            match spans.last_mut() {
                Some(s) if s.0 == cell => s.2 += 1,
                _ => spans.push((cell, genes.len(), genes.len() + 1)),
            }
            genes.push(lent[i as usize].1);
        }
        CellGenes { genes, spans }
    }

    /// The genes of `cell` (none if it has none).
    pub fn of(&self, cell: u32) -> &[GeneRef<'a>] {
        match self.spans.binary_search_by_key(&cell, |s| s.0) {
            Ok(k) => &self.genes[self.spans[k].1..self.spans[k].2],
            Err(_) => &[],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geese_proto::net::{nest_sized, GeneBatchRef};
    use geese_proto::GeneMsg;
    use std::sync::Arc;

    fn gene(step: u64, from: AgentId, genome: &[u32]) -> GeneMsg {
        GeneMsg {
            step,
            from,
            genome: Arc::from(genome),
            fitness: from as f64,
            mapping: GeneMapping { valid: true, used_codons: 1, depth: 1 },
        }
    }

    /// The bytes of a batch as a process sends it.
    fn batch_bytes(step: u64, cell: u32, genes: &[GeneMsg]) -> Vec<u8> {
        let b = GeneBatchRef { step, cell, genes, absent: &[] };
        nest_sized(&b, b.size_hint()).expect("encodes")
    }

    fn head(bytes: &[u8]) -> GeneBatchHead<'_> {
        geese_proto::net::Raw(bytes).open().expect("decodes")
    }

    #[test]
    fn lends_what_it_filed_by_cell_and_sender_and_keeps_later_steps() {
        let mut inbox = Inbox::default();
        let wide = [70_000, 3];
        let a = batch_bytes(5, 2, &[gene(5, 9, &[1, 2, 3]), gene(5, 4, &wide)]);
        let b = batch_bytes(5, 1, &[gene(5, 7, &[8])]);
        let later = batch_bytes(6, 1, &[gene(6, 7, &[5, 5])]);
        // A second gene of one sender in one cell stays behind the first.
        let again = batch_bytes(5, 1, &[gene(5, 7, &[9]), gene(5, 6, &[6])]);
        for bytes in [&a, &b, &later, &again] {
            assert!(inbox.file(&head(bytes)));
        }
        assert_eq!(inbox.len(), 6);
        let own = gene(5, 3, &[42]);
        let mut lent = vec![(2, GeneRef::of(&own))];
        inbox.lend(5, |from| from == 9, &mut lent);
        let cells = CellGenes::new(lent);
        let of = |c| cells.of(c).iter().map(|g| (g.from, g.genome.to_vec())).collect::<Vec<_>>();
        assert_eq!(of(2), vec![(3, vec![42]), (4, wide.to_vec())]);
        assert_eq!(of(1), vec![(6, vec![6]), (7, vec![8]), (7, vec![9])]);
        assert!(of(3).is_empty());
        assert!(cells.of(2)[0].shared.is_some() && cells.of(2)[1].shared.is_none());
        drop(cells);
        inbox.retire(5);
        assert_eq!(inbox.len(), 1);
        let mut lent = Vec::new();
        inbox.lend(6, |_| false, &mut lent);
        assert_eq!(lent.len(), 1);
        assert_eq!((lent[0].0, lent[0].1.genome), (1, &[5, 5][..]));
    }

    #[test]
    fn a_batch_sent_ahead_is_filed_by_its_senders_cells_and_the_others_skipped() {
        let mut inbox = Inbox::default();
        let ahead = geese_proto::net::AHEAD_CELL;
        let genes = [gene(5, 1, &[1]), gene(5, 2, &[2, 2]), gene(5, 3, &[3])];
        let bytes = batch_bytes(5, ahead, &genes);
        // Sender 2 is in no cell of ours: skipped, and its genome (however bad) unread.
        let mut bad = bytes.clone();
        let at = bad.windows(5).position(|w| w == [2, 2, 0, 2, 0]).expect("genome of sender 2");
        bad[at] = 3;
        let cell_of = |from: AgentId| match from {
            1 => Some(7),
            3 => Some(8),
            _ => None,
        };
        assert!(inbox.file_by_sender(&head(&bad), cell_of));
        let mut lent = Vec::new();
        inbox.lend(5, |_| false, &mut lent);
        let got: Vec<(u32, AgentId, Vec<u32>)> = lent.iter().map(|(c, g)| (*c, g.from, g.genome.to_vec())).collect();
        assert_eq!(got, vec![(7, 1, vec![1]), (8, 3, vec![3])]);
        // A bad genome of a sender it needs files nothing.
        assert!(!inbox.file_by_sender(&head(&bad), |_| Some(7)));
        assert_eq!(inbox.len(), 2);
    }

    #[test]
    fn a_gene_sent_ahead_is_filed_under_every_cell_of_its_sender_and_decoded_once() {
        let mut inbox = Inbox::default();
        let genes = [gene(5, 1, &[1, 1]), gene(5, 2, &[2]), gene(5, 3, &[3])];
        let bytes = batch_bytes(5, geese_proto::net::AHEAD_CELL, &genes);
        let cells_of = |from: AgentId| match from {
            1 => &[7u32, 8, 9][..],
            3 => &[8][..],
            _ => &[][..],
        };
        assert!(inbox.file_by_sender(&head(&bytes), |from| cells_of(from).iter().copied()));
        assert_eq!((inbox.len(), inbox.codons.len()), (4, 3), "sender 1's codons once");
        let mut lent = Vec::new();
        inbox.lend(5, |_| false, &mut lent);
        let cells = CellGenes::new(lent);
        let of = |c| cells.of(c).iter().map(|g| (g.from, g.genome.to_vec())).collect::<Vec<_>>();
        assert_eq!(of(7), vec![(1, vec![1, 1])]);
        assert_eq!(of(8), vec![(1, vec![1, 1]), (3, vec![3])]);
        assert_eq!(of(9), vec![(1, vec![1, 1])]);
        drop(cells);
        // Kept past a retire that keeps a later step: each slot its own codons.
        let later = batch_bytes(6, geese_proto::net::AHEAD_CELL, &[gene(6, 1, &[4, 4])]);
        assert!(inbox.file_by_sender(&head(&later), |from| cells_of(from).iter().copied()));
        inbox.retire(5);
        let mut lent = Vec::new();
        inbox.lend(6, |_| false, &mut lent);
        let got: Vec<(u32, Vec<u32>)> = lent.iter().map(|(c, g)| (*c, g.genome.to_vec())).collect();
        assert_eq!(got, vec![(7, vec![4, 4]), (8, vec![4, 4]), (9, vec![4, 4])]);
    }

    #[test]
    fn a_batch_with_a_bad_gene_files_nothing() {
        let mut inbox = Inbox::default();
        assert!(inbox.file(&head(&batch_bytes(5, 2, &[gene(5, 9, &[1])]))));
        // A gene of another step than its batch.
        assert!(!inbox.file(&head(&batch_bytes(5, 2, &[gene(5, 1, &[1]), gene(4, 2, &[2])]))));
        // A malformed genome (width byte 3) after a good one: the good one is taken back.
        let g = gene(5, 1, &[0x1111, 0x2222]);
        let mut bytes = batch_bytes(5, 2, &[g.clone(), g]);
        let wire = [2, 0x11, 0x11, 0x22, 0x22];
        let at = bytes.windows(wire.len()).rposition(|w| w == wire).expect("the second genome");
        bytes[at] = 3;
        assert!(!inbox.file(&head(&bytes)));
        assert_eq!(inbox.len(), 1);
        let mut lent = Vec::new();
        inbox.lend(5, |_| false, &mut lent);
        assert_eq!(lent[0].1.genome, &[1][..]);
    }
}
