//! The world's gene hub (DESIGN.md §2 step 2), sans IO: per-cell gene aggregation and
//! the forwarding of agent processes' gene packs.
//!
//! Fed what arrives on the gene keys (key and bytes, as received), it returns the
//! messages to publish ([`Released`]); [`GeneHub::flush`] adds what the hosting
//! processes have still to be sent. Hostile input (undecodable, dishonest, foreign
//! cell, future step) is dropped and counted, never trusted.
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{
    nested_size, pack, unpack, GeneBatch, GeneBatchCell, GeneBatchHead, HostGenes, Raw, AHEAD_CELL,
};
use geese_proto::rules::{for_each_gene_cell, genes_spread};
use geese_proto::{decode, encode, encode_sized, Geometry, Pos};
use std::collections::HashMap;

/// Maps keyed by cell, hashed with foldhash: the world fills and reads them for every
/// shared cell and every batch between two steps, when every agent process waits on it.
pub type CellMap<V> = HashMap<u32, V, foldhash::fast::FixedState>;

/// Messages (key, bytes) to publish, in order.
pub type Released = Vec<(String, Vec<u8>)>;

/// The processes of one cell's gene exchange at a step.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CellPeers {
    /// The processes that send the cell a batch, and whose batches complete it: those
    /// with a live agent whose gene must reach the cell
    /// ([`for_each_gene_cell`]), when an agent of another process reads it.
    pub writers: Vec<AgentRange>,
    /// The processes with a live agent centred in the cell: they read its percept, and
    /// get its genes.
    pub readers: Vec<AgentRange>,
}

/// The cells whose genes go through the hub at a step, given the live agents (their
/// process and centre): the cells where a process reads genes of another's agents.
///
/// An agent's gene must reach every cell it is registered in where a live agent has its
/// centre ([`for_each_gene_cell`], the rule agent processes send by). At GS ≥ 3 that is
/// the cell of its centre only: the writers of a cell are its readers, and a cell is
/// shared when agents of more than one process have their centres in it. At GS 2 an
/// agent is registered in a 3×3 block: a process also writes to the cells next to its
/// agents' that another process reads.
pub fn shared_cells(geom: &Geometry, live: &[(AgentRange, Pos)]) -> CellMap<CellPeers> {
    let add = |m: &mut CellMap<Vec<AgentRange>>, c: u32, r: AgentRange| {
        let v = m.entry(c).or_default();
        if !v.contains(&r) {
            v.push(r);
        }
    };
    let mut readers: CellMap<Vec<AgentRange>> = CellMap::default();
    for &(r, p) in live {
        add(&mut readers, geom.cell_of(p), r);
    }
    if !genes_spread(geom) {
        return readers
            .into_iter()
            .filter(|(_, v)| v.len() > 1)
            .map(|(c, v)| (c, CellPeers { writers: v.clone(), readers: v }))
            .collect();
    }
    let mut writers: CellMap<Vec<AgentRange>> = CellMap::default();
    for &(r, p) in live {
        for_each_gene_cell(geom, p, |c| readers.contains_key(&c), |c| add(&mut writers, c, r));
    }
    writers
        .into_iter()
        .filter_map(|(c, w)| {
            let readers = readers.get(&c)?;
            // A process sends a cell its genes only for readers of another process.
            let writers: Vec<AgentRange> = w.into_iter().filter(|x| readers.iter().any(|y| y != x)).collect();
            (!writers.is_empty()).then(|| (c, CellPeers { writers, readers: readers.clone() }))
        })
        .collect()
}

/// Per-cell gene aggregation (DESIGN.md §2 step 2). Agent processes publish their
/// batches of the shared cells of a step as one packed bundle on `agent/<ids>/genes`;
/// once every process expected in a cell has spoken (or left) — every process with a
/// live agent registered in it ([`CellPeers::writers`], [`shared_cells`]) — the cell is
/// complete. Then a process that reads cells one by one gets the cell's genes as one
/// batch on `cell/<cx>/<cy>/genes`. A hosting process gets the packs of the other
/// processes that write to a cell it reads as they arrive, and then which cells are complete,
/// in [`HostGenes`] messages on `agent/<ids>/in/genes` (built by [`GeneHub::flush`],
/// which the shell's publisher calls each time it wakes).
///
/// A hosting process also sends, with its intents, its genes of the next step
/// ([`AHEAD_CELL`]); the hub checks and keeps them, and when every hosting process sent
/// them the server puts them into the next step's
/// [`HostPercepts`](geese_proto::net::HostPercepts) instead of opening the hub's cells
/// for that step. The Zenoh shell files into it from the subscriber callback, like
/// [`Gather`](crate::gather::Gather).
pub struct GeneHub {
    run: String,
    geom: Geometry,
    step: u64,
    cells: CellMap<CellAgg>,
    /// What each hosting process sharing a cell this step has still to be sent.
    hosts: HashMap<AgentRange, HostOut>,
    hostile: u32,
    /// Whether to publish each cell's aggregate on its own topic (some process reads
    /// cells one by one).
    per_cell: bool,
    /// This step's packs for hosting processes ([`HostOut::packs`]): as their senders
    /// sent them, or packed again without the batches the checks dropped.
    packs: Vec<Vec<u8>>,
    /// Where bundles are unpacked (kept between bundles).
    unpacked: Vec<u8>,
    /// The step last begun (0 before the first).
    begun: u64,
    /// Each hosting process's pack sent ahead ([`AHEAD_CELL`]) for the step after the
    /// one begun, with that step.
    ahead: HashMap<AgentRange, (u64, Vec<u8>)>,
}

struct CellAgg {
    /// The processes whose batches complete the cell ([`CellPeers::writers`]).
    expect: Vec<AgentRange>,
    /// Each process's batch, nested as it sent it (checked, never decoded here unless
    /// some process reads this cell's topic; only then are its bytes kept).
    got: Vec<(AgentRange, Vec<u8>)>,
    sent: bool,
    /// The hosting processes that read the cell.
    hosting: Vec<AgentRange>,
}

/// What a hosting process has still to be sent this step: other processes' packs
/// (indices in [`GeneHub::packs`]) and the cells that became complete.
#[derive(Default)]
struct HostOut {
    packs: Vec<usize>,
    complete: Vec<u32>,
}

impl GeneHub {
    /// A hub for run `run` on an arena of geometry `geom`; no step open.
    pub fn new(run: impl Into<String>, geom: Geometry) -> Self {
        GeneHub {
            run: run.into(),
            geom,
            step: 0,
            cells: CellMap::default(),
            hosts: HashMap::new(),
            hostile: 0,
            per_cell: true,
            packs: Vec::new(),
            unpacked: Vec::new(),
            begun: 0,
            ahead: HashMap::new(),
        }
    }

    /// Close the step being filed (later batches of it are stale); returns how many
    /// hostile messages it dropped since the step began.
    pub fn close(&mut self) -> u32 {
        self.step = 0;
        std::mem::take(&mut self.hostile)
    }

    /// Open step `step`: `cells` are the shared cells with the processes that write and
    /// read each ([`shared_cells`]); `hosting` the processes served with [`HostGenes`].
    /// The hostile count is not reset here ([`GeneHub::close`] took the last step's):
    /// what came between the two steps counts in this one.
    pub fn begin(&mut self, step: u64, cells: CellMap<CellPeers>, per_cell: bool, hosting: &[AgentRange]) {
        self.step = step;
        self.begun = step;
        self.per_cell = per_cell;
        self.hosts.clear();
        self.packs.clear();
        self.cells = cells
            .into_iter()
            .map(|(c, peers)| {
                let hosting: Vec<AgentRange> = peers.readers.iter().filter(|r| hosting.contains(r)).copied().collect();
                for r in &hosting {
                    self.hosts.entry(*r).or_default();
                }
                (c, CellAgg { expect: peers.writers, got: Vec::new(), sent: false, hosting })
            })
            .collect();
    }

    /// Say which processes each incomplete cell still waits for (`geese::flow` trace).
    pub fn trace_incomplete(&self) {
        if !tracing::enabled!(target: "geese::flow", tracing::Level::TRACE) {
            return;
        }
        for (c, a) in self.cells.iter().filter(|(_, a)| !a.sent) {
            let got: Vec<AgentRange> = a.got.iter().map(|(r, _)| *r).collect();
            tracing::trace!(target: "geese::flow", "step {}: cell {c} expects {:?}, got {:?}", self.step, a.expect, got);
        }
    }

    /// File one batch published on its cell's key.
    pub fn on_batch(&mut self, key: &str, bytes: &[u8]) -> Released {
        let Parsed::Genes { cx, cy, from: Some(from) } = keys::parse(&self.run, key) else {
            self.hostile += 1;
            return Released::default();
        };
        let Ok(batch) = decode::<GeneBatchHead>(bytes) else {
            self.hostile += 1;
            return Released::default();
        };
        let cell_ok =
            cx < self.geom.cols() && cy < self.geom.rows() && batch.cell == (cy * self.geom.cols() + cx) as u32;
        if !cell_ok {
            self.hostile += 1;
            return Released::default();
        }
        let mut out = Released::default();
        // The body after the version byte is the batch's nested encoding.
        let nested = Raw(&bytes[1..]);
        if self.file(from, &batch, nested.0, &mut out) {
            self.forward(from, &[(batch.cell, nested)], None);
        }
        out
    }

    /// File the batches of one process's bundle.
    pub fn on_bundle(&mut self, key: &str, bytes: &[u8]) -> Released {
        let (Parsed::GeneBundle { from }, Ok(bundle)) =
            (keys::parse(&self.run, key), decode::<geese_proto::net::GeneBundle>(bytes))
        else {
            self.hostile += 1;
            return Released::default();
        };
        let mut out = Released::default();
        let mut scratch = std::mem::take(&mut self.unpacked);
        match unpack(bundle.packed.0, &mut scratch) {
            Ok(nested)
                if nested.len() == 1 && nested[0].open::<GeneBatchCell>().is_ok_and(|h| h.cell == AHEAD_CELL) =>
            {
                self.file_ahead(from, bundle.step, nested[0], bundle.packed.0);
            }
            Ok(nested) => {
                let mut kept: Vec<(u32, Raw)> = Vec::with_capacity(nested.len());
                for raw in &nested {
                    let Ok(batch) = raw.open::<GeneBatchHead>() else {
                        self.hostile += 1;
                        continue;
                    };
                    if batch.step != bundle.step || batch.cell as usize >= self.geom.cell_count() {
                        self.hostile += 1;
                        continue;
                    }
                    if self.file(from, &batch, raw.0, &mut out) {
                        kept.push((batch.cell, *raw));
                    }
                }
                // Forwarded as it came when every batch passed (the usual case).
                let whole = kept.len() == nested.len();
                self.forward(from, &kept, whole.then_some(bundle.packed.0));
            }
            Err(_) => self.hostile += 1,
        }
        self.unpacked = scratch;
        out
    }

    /// File the genes for step `step` that the process speaking for `from` sent ahead
    /// with its intents ([`IntentBatch::ahead`](geese_proto::net::IntentBatch)): a pack
    /// of one [`AHEAD_CELL`] batch; anything else is hostile.
    pub fn on_ahead(&mut self, from: AgentRange, step: u64, packed: Vec<u8>) {
        let mut scratch = std::mem::take(&mut self.unpacked);
        match unpack(&packed, &mut scratch) {
            Ok(nested)
                if nested.len() == 1 && nested[0].open::<GeneBatchCell>().is_ok_and(|h| h.cell == AHEAD_CELL) =>
            {
                self.file_ahead(from, step, nested[0], packed);
            }
            _ => self.hostile += 1,
        }
        self.unpacked = scratch;
    }

    /// Keep a pack sent ahead (`packed`, holding `nested`) of the process speaking for
    /// `from`, once checked: honest, for the step after the one begun (the only one a
    /// process sends genes ahead for), and the first of that step (as for a cell's
    /// batches). One for a later step is hostile; one for an earlier step is stale.
    fn file_ahead(&mut self, from: AgentRange, step: u64, nested: Raw, packed: impl Into<Vec<u8>>) {
        let Ok(batch) = nested.open::<GeneBatchHead>() else {
            self.hostile += 1;
            return;
        };
        if batch.step != step || !batch.honest(from) || step > self.begun + 1 {
            self.hostile += 1;
            return;
        }
        if step <= self.begun || self.ahead.get(&from).is_some_and(|(s, _)| *s == step) {
            return;
        }
        self.ahead.insert(from, (step, packed.into()));
    }

    /// The packs sent ahead for step `step`, by sender; all others are dropped.
    pub fn take_ahead(&mut self, step: u64) -> Vec<(AgentRange, Vec<u8>)> {
        self.ahead.drain().filter(|(_, (s, _))| *s == step).map(|(from, (_, p))| (from, p)).collect()
    }

    /// File one batch (`nested`: its encoding) of the process speaking for `from`; what
    /// completes goes to `out`. Returns whether the batch was taken (checked, of this
    /// step, of a shared cell the sender is expected in, and its first there).
    fn file(&mut self, from: AgentRange, batch: &GeneBatchHead, nested: &[u8], out: &mut Released) -> bool {
        if !batch.honest(from) {
            // Genes of agents the sender does not speak for, or a malformed genome.
            self.hostile += 1;
            return false;
        }
        if batch.step != self.step {
            if batch.step > self.step {
                self.hostile += 1;
            }
            return false;
        }
        let Some(agg) = self.cells.get_mut(&batch.cell) else { return false };
        if agg.sent || !agg.expect.contains(&from) || agg.got.iter().any(|(r, _)| *r == from) {
            return false;
        }
        let kept = if self.per_cell { nested.to_vec() } else { Vec::new() };
        agg.got.push((from, kept));
        self.complete(batch.cell, out);
        true
    }

    /// Queue the taken batches of `from` (cell, encoding) for the hosting processes that
    /// read one of their cells, at once rather than when the cells are complete: as
    /// `packed`, the pack they came in, when given, else packed here.
    fn forward(&mut self, from: AgentRange, kept: &[(u32, Raw)], packed: Option<&[u8]>) {
        let mut to: Vec<AgentRange> = Vec::new();
        for (cell, _) in kept {
            for h in self.cells.get(cell).into_iter().flat_map(|a| &a.hosting) {
                if *h != from && !to.contains(h) {
                    to.push(*h);
                }
            }
        }
        if to.is_empty() {
            return;
        }
        let bytes = match packed {
            Some(p) => p.to_vec(),
            None => {
                let raws: Vec<Raw> = kept.iter().map(|(_, r)| *r).collect();
                match pack(&raws) {
                    Ok(p) => p,
                    Err(_) => return,
                }
            }
        };
        self.packs.push(bytes);
        let at = self.packs.len() - 1;
        for h in to {
            if let Some(o) = self.hosts.get_mut(&h) {
                o.packs.push(at);
            }
        }
    }

    /// A process left: stop waiting for it.
    pub fn forget(&mut self, gone: AgentRange) -> Released {
        self.hosts.remove(&gone);
        self.ahead.remove(&gone);
        let cells: Vec<u32> = self.cells.keys().copied().collect();
        let mut out = Released::default();
        for c in cells {
            if let Some(agg) = self.cells.get_mut(&c) {
                agg.expect.retain(|r| *r != gone);
            }
            self.complete(c, &mut out);
        }
        out
    }

    /// Send every hosting process what it has still to be sent: one [`HostGenes`] with
    /// the other processes' packs filed since, and the cells complete since.
    ///
    /// Packs go out as they arrive rather than once a process's cells are complete:
    /// with 1,000 agents in 10 processes every process shares cells with every other,
    /// so all cells completed at the last bundle, and the world then relayed ~130 kB to
    /// each of ten processes in turn while the first served were already computing.
    /// Streamed, most of it goes out while the processes wait at the barrier anyway.
    pub fn flush(&mut self, out: &mut Released) {
        for (to, o) in self.hosts.iter_mut() {
            if o.packs.is_empty() && o.complete.is_empty() {
                continue;
            }
            let packs: Vec<Raw> = o.packs.iter().filter_map(|&i| self.packs.get(i).map(|b| Raw(b))).collect();
            let cells = std::mem::take(&mut o.complete);
            let size = nested_size(&packs, 5 * cells.len());
            if let Ok(bytes) = encode_sized(&HostGenes { step: self.step, cells, packs }, size) {
                out.push((keys::host_genes(&self.run, *to), bytes));
            }
            o.packs.clear();
        }
    }

    /// If every process expected in `cell` has spoken: its aggregate for per-cell
    /// readers, and the cell noted as complete for the hosting processes sharing it.
    fn complete(&mut self, cell: u32, out: &mut Released) {
        let Some(agg) = self.cells.get_mut(&cell) else { return };
        if agg.sent || agg.got.is_empty() || !agg.expect.iter().all(|r| agg.got.iter().any(|(g, _)| g == r)) {
            return;
        }
        agg.sent = true;
        if self.per_cell {
            let mut all = GeneBatch { step: self.step, cell, genes: Vec::new(), absent: Vec::new() };
            for (_, nested) in &agg.got {
                // Checked when filed; a genome's codons are only decoded here.
                let Ok(b) = Raw(nested).open::<GeneBatch>() else { continue };
                all.genes.extend(b.genes);
                all.absent.extend(b.absent);
            }
            all.genes.sort_by_key(|g| g.from);
            all.absent.sort_unstable();
            let (cx, cy) = self.geom.cell_col_row(cell);
            if let Ok(bytes) = encode(&all) {
                out.push((keys::cell_genes(&self.run, cx, cy), bytes));
            }
        }
        // The hosting processes here hear that the cell is complete (all its batches
        // went, or go, to them before that: [`GeneHub::flush`]).
        for to in &agg.hosting {
            if let Some(o) = self.hosts.get_mut(to) {
                o.complete.push(cell);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geese_proto::net::{nest, GeneBatchRef, GeneBundle};
    use geese_proto::{GeneMapping, GeneMsg};
    use std::sync::Arc;

    const RUN: &str = "t";

    fn geom() -> Geometry {
        Geometry::new(100, 100, 10).unwrap()
    }

    fn r(first: u32, count: u32) -> AgentRange {
        AgentRange::new(first, count).unwrap()
    }

    fn gene(from: u32, step: u64) -> GeneMsg {
        GeneMsg { step, from, genome: Arc::from(vec![1u32, 2, 3]), fitness: 0.5, mapping: GeneMapping::default() }
    }

    /// A bundle of `from` for `step` holding one batch per (cell, genes).
    fn bundle(step: u64, batches: &[(u32, Vec<GeneMsg>)]) -> Vec<u8> {
        let nested: Vec<Vec<u8>> = batches
            .iter()
            .map(|(cell, genes)| nest(&GeneBatchRef { step, cell: *cell, genes, absent: &[] }).unwrap())
            .collect();
        let raws: Vec<Raw> = nested.iter().map(|b| Raw(b)).collect();
        let packed = pack(&raws).unwrap();
        encode(&GeneBundle { step, packed: Raw(&packed) }).unwrap()
    }

    fn key(from: AgentRange) -> String {
        keys::agents_genes(RUN, from)
    }

    /// Both write and read.
    fn peers(v: Vec<AgentRange>) -> CellPeers {
        CellPeers { writers: v.clone(), readers: v }
    }

    /// Step `step` with cell 5 shared by processes a and b, both hosting.
    fn open(hub: &mut GeneHub, step: u64, a: AgentRange, b: AgentRange) {
        let mut cells = CellMap::default();
        cells.insert(5, peers(vec![a, b]));
        hub.begin(step, cells, false, &[a, b]);
    }

    /// The HostGenes messages in `out` for `to`: (cells complete, packs).
    fn host_genes(out: &Released, to: AgentRange) -> Vec<(Vec<u32>, usize)> {
        out.iter()
            .filter(|(k, _)| *k == keys::host_genes(RUN, to))
            .map(|(_, b)| {
                let h: HostGenes = decode(b).unwrap();
                (h.cells, h.packs.len())
            })
            .collect()
    }

    #[test]
    fn a_shared_cell_completes_once_every_process_spoke_and_packs_are_forwarded() {
        let (a, b) = (r(0, 2), r(2, 2));
        let mut hub = GeneHub::new(RUN, geom());
        open(&mut hub, 3, a, b);
        let mut out = hub.on_bundle(&key(a), &bundle(3, &[(5, vec![gene(0, 3)])]));
        hub.flush(&mut out);
        assert_eq!(host_genes(&out, b), vec![(vec![], 1)], "a's pack goes to b at once");
        assert!(host_genes(&out, a).is_empty(), "nothing of its own goes back to a");
        let mut out = hub.on_bundle(&key(b), &bundle(3, &[(5, vec![gene(2, 3)])]));
        hub.flush(&mut out);
        assert_eq!(host_genes(&out, a), vec![(vec![5], 1)]);
        assert_eq!(host_genes(&out, b), vec![(vec![5], 0)]);
        assert_eq!(hub.close(), 0);
    }

    #[test]
    fn duplicates_stale_and_foreign_cells_are_dropped_future_and_dishonest_ones_counted() {
        let (a, b) = (r(0, 2), r(2, 2));
        let mut hub = GeneHub::new(RUN, geom());
        open(&mut hub, 3, a, b);
        hub.on_bundle(&key(a), &bundle(3, &[(5, vec![gene(0, 3)])]));
        // The same process again: the first batch stands, nothing forwarded.
        let mut out = hub.on_bundle(&key(a), &bundle(3, &[(5, vec![gene(1, 3)])]));
        hub.flush(&mut out);
        assert_eq!(host_genes(&out, b), vec![(vec![], 1)], "only the first pack");
        // A stale step and a cell nobody shares: dropped, not hostile.
        let mut out = hub.on_bundle(&key(a), &bundle(2, &[(5, vec![gene(0, 2)])]));
        out.extend(hub.on_bundle(&key(a), &bundle(3, &[(7, vec![gene(0, 3)])])));
        hub.flush(&mut out);
        assert!(out.is_empty());
        assert_eq!(hub.hostile, 0);
        // A future step, genes of another process's agent, a cell beyond the arena,
        // garbage, a key naming nobody: hostile.
        hub.on_bundle(&key(b), &bundle(4, &[(5, vec![gene(2, 4)])]));
        hub.on_bundle(&key(b), &bundle(3, &[(5, vec![gene(0, 3)])]));
        hub.on_bundle(&key(b), &bundle(3, &[(100_000, vec![gene(2, 3)])]));
        hub.on_bundle(&key(b), b"\x08junk");
        hub.on_bundle("geese/t/agent/zz/genes", &bundle(3, &[(5, vec![gene(2, 3)])]));
        assert_eq!(hub.close(), 5);
    }

    /// A hostile bundle between two steps (a paced run waits there) counts in the next
    /// step's report.
    #[test]
    fn hostile_bundles_between_steps_count_in_the_next() {
        let (a, b) = (r(0, 2), r(2, 2));
        let mut hub = GeneHub::new(RUN, geom());
        open(&mut hub, 3, a, b);
        assert_eq!(hub.close(), 0);
        hub.on_bundle(&key(b), b"\x08junk");
        open(&mut hub, 4, a, b);
        assert_eq!(hub.close(), 1);
    }

    #[test]
    fn a_process_leaving_completes_the_cells_that_waited_for_it() {
        let (a, b) = (r(0, 2), r(2, 2));
        let mut hub = GeneHub::new(RUN, geom());
        open(&mut hub, 1, a, b);
        hub.on_bundle(&key(a), &bundle(1, &[(5, vec![gene(0, 1)])]));
        let mut out = hub.forget(b);
        hub.flush(&mut out);
        assert_eq!(host_genes(&out, a), vec![(vec![5], 0)]);
        assert!(host_genes(&out, b).is_empty(), "nothing goes to a process that left");
    }

    #[test]
    fn per_cell_readers_get_the_cell_aggregate_sorted_by_sender() {
        let (a, b) = (r(0, 2), r(2, 2));
        let mut hub = GeneHub::new(RUN, geom());
        let mut cells = CellMap::default();
        cells.insert(5, peers(vec![b, a]));
        hub.begin(1, cells, true, &[]);
        hub.on_bundle(&key(b), &bundle(1, &[(5, vec![gene(3, 1), gene(2, 1)])]));
        let out = hub.on_bundle(&key(a), &bundle(1, &[(5, vec![gene(1, 1)])]));
        let (cx, cy) = geom().cell_col_row(5);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].0, keys::cell_genes(RUN, cx, cy));
        let all: GeneBatch = decode(&out[0].1).unwrap();
        assert_eq!(all.genes.iter().map(|g| g.from).collect::<Vec<_>>(), vec![1, 2, 3]);
    }

    #[test]
    fn shared_cells_are_those_of_centres_at_gs_10_and_of_blocks_at_gs_2() {
        let (a, b, c) = (r(0, 2), r(2, 2), r(4, 2));
        // GS 10: two processes centred in one cell share it; a neighbour does not count.
        let g = geom();
        let live = [(a, Pos::new(1, 1)), (b, Pos::new(8, 8)), (c, Pos::new(11, 1)), (a, Pos::new(12, 1))];
        let cells = shared_cells(&g, &live);
        let (here, next) = (g.cell_of(Pos::new(1, 1)), g.cell_of(Pos::new(11, 1)));
        assert_eq!(cells.len(), 2);
        assert_eq!(cells[&here], peers(vec![a, b]));
        assert_eq!(cells[&next], peers(vec![c, a]));
        // GS 2: a at (0,0), b centred in the next cell, c two cells further (in the
        // block of b's agent, not of a's), and a's second agent far away.
        let g = Geometry::new(100, 100, 2).unwrap();
        let live = [(a, Pos::new(0, 0)), (b, Pos::new(2, 0)), (c, Pos::new(4, 0)), (a, Pos::new(-20, 0))];
        let cells = shared_cells(&g, &live);
        let at = |x| g.cell_of(Pos::new(x, 0));
        // A process writes to a cell only for readers of another process.
        let peers_at = |x| cells[&at(x)].clone().sorted();
        assert_eq!(peers_at(0), CellPeers { writers: vec![b], readers: vec![a] });
        assert_eq!(peers_at(2), CellPeers { writers: vec![a, c], readers: vec![b] });
        assert_eq!(peers_at(4), CellPeers { writers: vec![b], readers: vec![c] });
        assert_eq!(cells.len(), 3, "the cell of a's far agent has nobody else");
    }

    impl CellPeers {
        fn sorted(mut self) -> Self {
            self.writers.sort();
            self.readers.sort();
            self
        }
    }

    #[test]
    fn at_gs_2_a_process_writes_to_a_cell_it_does_not_read_and_completes_it() {
        let (a, b) = (r(0, 2), r(2, 2));
        let g = Geometry::new(100, 100, 2).unwrap();
        let (pa, pb) = (Pos::new(0, 0), Pos::new(2, 0));
        let (ca, cb) = (g.cell_of(pa), g.cell_of(pb));
        let mut hub = GeneHub::new(RUN, g);
        hub.begin(3, shared_cells(&g, &[(a, pa), (b, pb)]), false, &[a, b]);
        // b's gene goes to a's cell (and its own, which only b reads: no batch there).
        let mut out = hub.on_bundle(&key(b), &bundle(3, &[(ca, vec![gene(2, 3)])]));
        hub.flush(&mut out);
        assert_eq!(host_genes(&out, a), vec![(vec![ca], 1)], "a's cell is complete with b's batch");
        assert!(host_genes(&out, b).is_empty(), "b reads no cell that a pack came for");
        let mut out = hub.on_bundle(&key(a), &bundle(3, &[(cb, vec![gene(0, 3)])]));
        hub.flush(&mut out);
        assert_eq!(host_genes(&out, b), vec![(vec![cb], 1)]);
        assert_eq!(hub.close(), 0);
    }

    #[test]
    fn genes_sent_ahead_keep_the_first_pack_of_the_next_step_only() {
        let a = r(0, 2);
        let mut hub = GeneHub::new(RUN, geom());
        hub.begin(4, CellMap::default(), false, &[a]);
        hub.on_bundle(&key(a), &bundle(5, &[(AHEAD_CELL, vec![gene(0, 5)])]));
        hub.on_bundle(&key(a), &bundle(5, &[(AHEAD_CELL, vec![gene(1, 5)])])); // second: ignored
        hub.on_bundle(&key(a), &bundle(4, &[(AHEAD_CELL, vec![gene(0, 4)])])); // stale
        assert_eq!(hub.hostile, 0);
        hub.on_bundle(&key(a), &bundle(6, &[(AHEAD_CELL, vec![gene(0, 6)])])); // too far ahead
        hub.on_bundle(&key(a), &bundle(5, &[(AHEAD_CELL, vec![gene(9, 5)])])); // not its agent
        assert_eq!(hub.hostile, 2);
        let packs = hub.take_ahead(5);
        assert_eq!(packs.len(), 1);
        let mut scratch = Vec::new();
        let nested = unpack(&packs[0].1, &mut scratch).unwrap();
        let b: GeneBatch = nested[0].open().unwrap();
        assert_eq!(b.genes[0].from, 0, "the first pack of the step is kept");
        assert!(hub.take_ahead(5).is_empty(), "taken once");
    }
}
