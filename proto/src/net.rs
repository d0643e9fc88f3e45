//! Messages of the distributed runtime (DESIGN.md §2–4 over Zenoh).
//!
//! The simulation messages ([`Percept`](crate::Percept), [`GeneMsg`], [`Intent`],
//! [`StepReport`]) travel unchanged; this
//! module adds what only a multi-process run needs:
//!
//! - [`NetRunSpec`]: everything the world server needs to run a trial (the launcher
//!   writes it as JSON), and [`RunInfo`]: what an agent process learns from the world
//!   when it joins (so agents on other hosts need no configuration file).
//! - [`Tick`]: published by the world after the percepts of a step. It says which cell
//!   each agent's centre is in (`NO_CELL` for dead agents), so every agent knows which
//!   percept to read and which cell-mates will publish genes, without subscribing to
//!   every cell. Percepts and the tick come from the same session in order, so when the
//!   tick arrives the percepts an agent is subscribed to are already there.
//! - [`GeneBatch`]: the genes one agent process offers in one cell for one step (plus the
//!   ids of its agents there that lost their percept and so offer nothing, so that
//!   mates need not wait for them), published on `cell/<cx>/<cy>/genes/<ids>` only when
//!   agents of more than one process share the cell. The world (which is the router)
//!   gathers the batches of a cell and republishes them as one batch on
//!   `cell/<cx>/<cy>/genes` as soon as every process there has spoken: each process then
//!   receives one message per shared cell instead of one per cell-mate (2N deliveries
//!   for N processes in a cell rather than N²).
//! - [`GeneBundle`]: an agent process's batches of all its shared cells in one message,
//!   each nested ([`Raw`]) and all of them LZ4-packed ([`pack`]); the world unpacks the
//!   bundle, checks each batch ([`GeneBatchHead`], genomes left encoded) and files it as
//!   above. A process hosting many agents (`--subscribe all`) reads no cell topic: the
//!   world sends it, on keys of its own, [`HostPercepts`] (the percepts of its agents'
//!   cells, each encoded once by the world) and [`HostGenes`] (the packs of the other
//!   processes it shares a cell with, as they sent them and as they arrive, then which
//!   of its shared cells are complete).
//! - Genes sent ahead ([`AHEAD_CELL`]): a hosting process's genes for the next step,
//!   as one packed batch carried by its [`IntentBatch`] (`ahead`). While every process
//!   is a hosting one and each sent them, the world puts the other processes' packs
//!   into the next step's [`HostPercepts`], and no gene travels during the step.
//! - [`IntentBatch`]: the intents of one agent process for one step, with the ids of
//!   agents that idle on purpose, the process's drop counters and its genes sent ahead.
//! - [`NetReport`]: the world's step report plus the network counters.
//!
//! Identity: an agent process publishes genes and intents on keys that carry the id
//! range it speaks for ([`keys::AgentRange`](crate::keys::AgentRange)); a payload that
//! names an agent outside that range is dropped and counted, never applied.
use crate::geometry::Geometry;
use crate::message::{AgentId, GeneMsg, Intent, ObjectInfo, Perturbation, Regime, StepReport};
use crate::seed::mix64;
use serde::{Deserialize, Serialize};

/// Cell of a dead agent in a [`Tick`].
pub const NO_CELL: u32 = u32::MAX;

/// Injected message loss (DESIGN.md §2; genes are lost through
/// [`Regime::gene_loss`], applied by the receiving learner).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct LossRates {
    /// World side: probability that an arrived intent is dropped.
    pub intent: f64,
    /// Agent side: probability that an agent's percept is dropped (the agent idles).
    pub percept: f64,
}

/// Deadlines that bound every wait of the distributed runtime.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Deadlines {
    /// World: how long to wait for the intents of a step once its percepts are out.
    pub intent_ms: u32,
    /// Agent: how long to wait for cell-mates' genes.
    pub gene_ms: u32,
    /// Agent: how long to wait for a percept after the tick that announced it.
    pub percept_ms: u32,
    /// World: how long to wait for every expected process to be present.
    pub join_ms: u32,
}

impl Default for Deadlines {
    fn default() -> Self {
        Deadlines { intent_ms: 5_000, gene_ms: 3_000, percept_ms: 1_000, join_ms: 120_000 }
    }
}

/// How many times its usual deadline each wait of a first step gets: the run's first
/// step, or the first after a process joined. That step also sets up Zenoh's routes for
/// every key the new processes use (at the router, with access control, a check per
/// key and direction): with 1,000 one-agent processes it took 3.5 s here, against
/// 0.3–0.9 s for the next steps, and 156 agents missed the 3 s gene deadline.
pub const FIRST_STEP_FACTOR: u32 = 10;

impl Deadlines {
    /// The deadlines of a step; `first`: a first step (see [`FIRST_STEP_FACTOR`]).
    /// World and agents use the same rule, so neither gives up on the other early.
    pub fn of_step(self, first: bool) -> Deadlines {
        if !first {
            return self;
        }
        let longer = |ms: u32| ms.saturating_mul(FIRST_STEP_FACTOR);
        Deadlines {
            intent_ms: longer(self.intent_ms),
            gene_ms: longer(self.gene_ms),
            percept_ms: longer(self.percept_ms),
            join_ms: self.join_ms,
        }
    }
}

/// What the world server runs. Crate-specific configurations travel as JSON text
/// (`world_json` is a `geese_world::WorldConfig`, `learner_json` a
/// `geese_agent::LearnerConfig`) so that this contract crate does not depend on them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NetRunSpec {
    /// Run name: the `<run>` of every key expression.
    pub run: String,
    pub seed: u64,
    pub steps: u64,
    pub agents: u32,
    pub world_json: String,
    pub learner_json: String,
    /// What the agents run (`geese_agent::program::Program`, JSON): the algorithm and
    /// phase, a combine phase's GeneDicts, or a fixed population's members.
    pub program_json: String,
    pub grammar_name: String,
    pub grammar_text: String,
    /// The regime in force at step 1 (IP, lateral transfer, gene loss).
    pub regime: Regime,
    /// Scheduled perturbations, in the order they were configured.
    pub perturbations: Vec<(u64, Perturbation)>,
    pub loss: LossRates,
    pub deadlines: Deadlines,
    /// Bare lock-step benchmark: ticks out, empty replies back, no simulation.
    pub bare: bool,
    /// Wait for the orchestrator's presence before step 1 and stop when it goes away.
    pub expect_orchestrator: bool,
}

/// What a joining agent process gets from the world (queryable `ctl/info`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunInfo {
    pub spec: NetRunSpec,
    pub geometry: Geometry,
    pub hub: ObjectInfo,
    /// The step the world will run next.
    pub next_step: u64,
    /// Centre cell of every agent's body now, dead or alive: where a joining (or
    /// rejoining) process subscribes first.
    pub cells: Vec<u32>,
}

/// Published by the world after the percepts of step `step`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tick {
    pub step: u64,
    /// Centre cell of every agent (`NO_CELL` if dead), indexed by agent id.
    pub cells: Vec<u32>,
}

/// Genes one agent process offers in one cell for one step (or, from the world, the
/// genes of every process in the cell).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeneBatch {
    pub step: u64,
    pub cell: u32,
    pub genes: Vec<GeneMsg>,
    /// Agents of this process in this cell that offer no gene this step (percept lost).
    pub absent: Vec<AgentId>,
}

/// The postcard encoding (no envelope: the outer message carries the version) of one
/// message inside another, borrowed from the bytes that arrived. On the wire it is a
/// length and the raw bytes.
///
/// Nesting is what lets the world forward what it does not need to rebuild: it encodes
/// each cell's percept once and copies those bytes into every hosting process's
/// message, and it checks an agent process's gene batch ([`GeneBatchHead`]) and
/// forwards the very bytes the process sent, without decoding a genome. A malformed
/// nested message is counted as hostile by whoever opens it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Raw<'a>(pub &'a [u8]);

impl<'a> Raw<'a> {
    /// Decode the nested message.
    pub fn open<T: Deserialize<'a>>(self) -> Result<T, crate::CodecError> {
        postcard::from_bytes(self.0).map_err(|e| crate::CodecError::Decode(e.to_string()))
    }
}

/// Bytes enough to encode a message holding `nested` (plus `extra` bytes of its own
/// fields), for [`crate::codec::encode_sized`].
pub fn nested_size(nested: &[Raw], extra: usize) -> usize {
    nested.iter().map(|r| r.0.len() + 5).sum::<usize>() + extra + 16
}

/// The nested encoding of `msg` (see [`Raw`]).
pub fn nest<T: Serialize + ?Sized>(msg: &T) -> Result<Vec<u8>, crate::CodecError> {
    nest_sized(msg, 64)
}

/// [`nest`] into a buffer of `capacity` bytes to begin with (see
/// [`crate::codec::encode_sized`]).
pub fn nest_sized<T: Serialize + ?Sized>(msg: &T, capacity: usize) -> Result<Vec<u8>, crate::CodecError> {
    postcard::to_extend(msg, Vec::with_capacity(capacity)).map_err(|e| crate::CodecError::Encode(e.to_string()))
}

impl GeneBatchRef<'_> {
    /// About the size of the batch's encoding: each genome at most 4 bytes a codon,
    /// plus a gene's other fields.
    pub fn size_hint(&self) -> usize {
        self.genes.iter().map(|g| 4 * g.genome.len() + 40).sum::<usize>() + 5 * self.absent.len() + 24
    }
}

impl Serialize for Raw<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(self.0)
    }
}

impl<'de: 'a, 'a> Deserialize<'de> for Raw<'a> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Raw<'a>, D::Error> {
        struct Bytes;
        impl<'de> serde::de::Visitor<'de> for Bytes {
            type Value = Raw<'de>;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a byte string borrowed from the message")
            }
            fn visit_borrowed_bytes<E: serde::de::Error>(self, b: &'de [u8]) -> Result<Raw<'de>, E> {
                Ok(Raw(b))
            }
        }
        d.deserialize_bytes(Bytes)
    }
}

/// A [`GeneBatch`] to encode from borrowed parts (the same bytes on the wire): an agent
/// process nests the batch of each shared cell without cloning its genes.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct GeneBatchRef<'a> {
    pub step: u64,
    pub cell: u32,
    pub genes: &'a [GeneMsg],
    pub absent: &'a [AgentId],
}

/// The step and cell of a nested [`GeneBatch`] (its first fields), read without
/// decoding its genes: a pack holds batches of every cell its sender shares, and a
/// receiver decodes only those of cells its agents are in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
pub struct GeneBatchCell {
    pub step: u64,
    pub cell: u32,
}

/// A [`GeneBatch`] as the world checks it: the same wire layout, with every genome left
/// encoded ([`GeneHead`]). The world relays genes it never decodes.
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct GeneBatchHead<'a> {
    pub step: u64,
    pub cell: u32,
    #[serde(borrow)]
    pub genes: Vec<GeneHead<'a>>,
    pub absent: Vec<AgentId>,
}

/// A [`GeneMsg`] with its genome left encoded (see [`GeneBatchHead`]).
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct GeneHead<'a> {
    pub step: u64,
    pub from: AgentId,
    #[serde(borrow)]
    pub genome: Raw<'a>,
    pub fitness: f64,
    pub mapping: crate::message::GeneMapping,
}

impl GeneBatchHead<'_> {
    /// Whether the batch speaks only for agents of `from` and only of its own step, and
    /// every genome is well formed ([`crate::message::genome_bytes_ok`]).
    pub fn honest(&self, from: crate::keys::AgentRange) -> bool {
        self.genes
            .iter()
            .all(|g| from.contains(g.from) && g.step == self.step && crate::message::genome_bytes_ok(g.genome.0))
            && self.absent.iter().all(|&a| from.contains(a))
    }
}

/// What the world hands one agent process that hosts many agents, per step, on
/// `agent/<ids>/in/percepts`: the percepts (each nested, a [`Raw`] of a
/// [`Percept`](crate::Percept)) of the cells its live agents are in, and of no other
/// cell. With 1,000 agents in 10 processes, every process decoding every cell's
/// percepts and genes was a large part of the distributed overhead.
///
/// `genes`, when the world sends it, holds the step's genes of the other hosting
/// processes that share a cell with this one: their packs ([`pack`]) of one
/// [`AHEAD_CELL`] batch each, sent ahead with their intents of the step before. The
/// process then has every gene of the step with its percepts, publishes none and waits
/// for none. The world sends `None` (and the step's genes go through [`HostGenes`]
/// during the step) while some process reads cells one by one, while lateral transfer
/// is off, and when a process with live agents sent no genes ahead (at step 1, and
/// right after it joined).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HostPercepts<'a> {
    pub step: u64,
    #[serde(borrow)]
    pub percepts: Vec<Raw<'a>>,
    #[serde(borrow)]
    pub genes: Option<Vec<Raw<'a>>>,
}

/// The `cell` of a [`GeneBatch`] sent ahead: a hosting process's genes for step `s`, of
/// every agent it expects to take part in step `s`, packed as the only batch in the
/// `ahead` field of its [`IntentBatch`] of step `s − 1`.
///
/// Why ahead: the gene an agent offers at step `s` is the one it holds when step
/// `s − 1` ends, whatever its percept of step `s` says, so it can travel with the
/// intents. That removes a round trip through the world from every step: with 1,000
/// agents in 10 processes, the gene exchange between percepts and intents cost each
/// process ten more messages and every process a barrier per step. Which agent is in
/// which cell at step `s` only the world knows; a receiver files each gene under every
/// cell of its own whose percept of step `s` lists the sender (the cells the sender is
/// registered in: the cell of its centre at GS ≥ 3, up to nine at GS 2), and skips the
/// others unread.
pub const AHEAD_CELL: u32 = u32::MAX;

/// What the world hands one hosting agent process on `agent/<ids>/in/genes`: the packs
/// ([`pack`]) of the other processes that share a cell with it, as they sent them and as
/// they arrive, and then which of its shared cells are complete. `cells` lists those
/// cells, so that a cell whose other processes all left is known to be complete too; a
/// cell listed has had every pack with a batch of it sent before (or with) the list.
///
/// A pack holds the sender's batches of every cell it shares with anyone, so a process
/// may get batches of cells it has no agent in; it ignores them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HostGenes<'a> {
    pub step: u64,
    pub cells: Vec<u32>,
    #[serde(borrow)]
    pub packs: Vec<Raw<'a>>,
}

/// An agent process's [`GeneBatch`]es of every cell it shares, for one step, in one
/// message (to the world, on `agent/<ids>/genes`), packed ([`pack`]) so that the world
/// can check them and forward the pack as it came.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeneBundle<'a> {
    pub step: u64,
    #[serde(borrow)]
    pub packed: Raw<'a>,
}

/// Most bytes a pack may unpack to (a pack that claims more is hostile): far above the
/// ~25 kB of a process hosting 100 agents.
pub const MAX_UNPACKED: usize = 64 << 20;

/// Pack nested batches: their postcard encoding (a sequence of [`Raw`]), compressed
/// with LZ4 (block format, the unpacked size first).
///
/// Why: the genomes of one process's agents descend from the same few parents, so its
/// batches compress about 3x (1,000 agents, step 500: 195 kB of codons to 51 kB with
/// zlib, 3.1x with LZ4), and every batch goes to up to nine other processes: with
/// 1,000 agents in 10 processes the loopback carried ~2 MB a step, most of it genomes,
/// copied by the world, Zenoh and the kernel on the way. LZ4 packs a process's batches
/// in ~12 µs and a receiver unpacks one in ~3 µs.
pub fn pack(batches: &[Raw]) -> Result<Vec<u8>, crate::CodecError> {
    let plain = postcard::to_extend(batches, Vec::with_capacity(nested_size(batches, 0)))
        .map_err(|e| crate::CodecError::Encode(e.to_string()))?;
    Ok(lz4_flex::block::compress_prepend_size(&plain))
}

/// Unpack a [`pack`] into `scratch` (reused between calls) and return its nested
/// batches, borrowed from `scratch`. Fails, without allocating what it claims, on a
/// pack that claims more than [`MAX_UNPACKED`] bytes or more than LZ4 can expand its
/// input to, that does not decompress to exactly its claimed size, or whose content is
/// not a sequence of nested messages.
pub fn unpack<'s>(packed: &[u8], scratch: &'s mut Vec<u8>) -> Result<Vec<Raw<'s>>, crate::CodecError> {
    let bad = |what: &str| crate::CodecError::Decode(format!("gene pack: {what}"));
    let (size, body) = lz4_flex::block::uncompressed_size(packed).map_err(|e| bad(&e.to_string()))?;
    // LZ4 expands a byte to at most 255.
    if size > MAX_UNPACKED || size > body.len().saturating_mul(255) {
        return Err(bad(&format!("claims {size} bytes from {}", body.len())));
    }
    scratch.clear();
    scratch.resize(size, 0);
    let n = lz4_flex::block::decompress_into(body, scratch).map_err(|e| bad(&e.to_string()))?;
    if n != size {
        return Err(bad(&format!("unpacked {n} bytes, claimed {size}")));
    }
    postcard::from_bytes(scratch).map_err(|e| bad(&e.to_string()))
}

/// Drop counters of one agent process since its previous intent batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct HostCounters {
    /// Percepts dropped by injected loss.
    pub percepts_lost: u32,
    /// Percepts that never arrived before their deadline.
    pub percepts_missing: u32,
    /// Cell-mates' genes that did not arrive before the gene deadline.
    pub genes_late: u32,
    /// Messages that did not decode, had the wrong version or claimed a foreign id.
    pub hostile: u32,
    /// Waits of this process (for percepts, for cell-mates' genes) that ran to their
    /// deadline, whatever had arrived by then.
    pub deadline_hits: u32,
}

/// The intents of one agent process for one step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IntentBatch {
    pub step: u64,
    pub intents: Vec<Intent>,
    /// Agents that idle this step on purpose (no percept); not waited for.
    pub idle: Vec<AgentId>,
    pub counters: HostCounters,
    /// The process's genes for step `step + 1`, sent ahead: a [`pack`] of one
    /// [`AHEAD_CELL`] batch, as a [`GeneBundle`] of that step would carry it.
    ///
    /// Why here and not in a `GeneBundle` of its own: the genes an agent offers at
    /// `step + 1` are known when its intents of `step` are, and the world must have them
    /// before it begins `step + 1`, which it does only once every intent batch is in. In
    /// one message they cost the process one put instead of two, and the world one
    /// callback, one lock and no publisher wake instead of two callbacks and a wake
    /// that sends nothing (wire version 12).
    #[serde(with = "serde_bytes")]
    pub ahead: Option<Vec<u8>>,
}

/// Network counters of one step, summed over the world and the agent processes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct NetCounters {
    /// Intents dropped by injected loss (world side).
    pub intents_lost: u32,
    /// Live agents whose intent had not arrived at the deadline.
    pub intents_late: u32,
    /// Percepts dropped by injected loss (agent side).
    pub percepts_lost: u32,
    /// Percepts that never arrived (agent side).
    pub percepts_missing: u32,
    /// Genes that missed the gene deadline (agent side).
    pub genes_late: u32,
    /// Messages dropped as hostile (undecodable, wrong version, foreign id), world and
    /// agents together.
    pub hostile: u32,
    /// Agent processes present at the end of the step.
    pub processes: u32,
    /// Microseconds the world waited for intents this step.
    pub wait_us: u32,
    /// Hosting processes that got the step's genes with their percepts (sent ahead,
    /// [`HostPercepts::genes`]).
    pub genes_ahead: u32,
    /// Waits that ran to their deadline this step: the world's for intents, the agent
    /// processes' for percepts and genes. A run that loses nothing has none; a wait that
    /// ends at its deadline with everything in (a wake-up that never came) counts too.
    pub deadline_hits: u32,
}

/// The world's report of one step in a distributed run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NetReport {
    pub report: StepReport,
    pub net: NetCounters,
}

/// Messages on the report plane.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ReportMsg {
    Step(NetReport),
    /// The world finished (`completed` false: stopped early) after `steps` steps;
    /// `requested`: it stopped because a control-plane stop asked it to.
    Done {
        steps: u64,
        completed: bool,
        requested: bool,
    },
}

/// Where the loss draws of one (stream, step, index) land: a uniform number in [0, 1).
///
/// Counter-based (a hash of the stream seed, step and index) rather than sequential, so
/// the draw for a message does not depend on which other messages arrived, or in which
/// order. `stream` is a `proto::seed::derive(run seed, owner, Purpose::Loss)` seed,
/// salted per use with [`LOSS_SALT_PERCEPT`] or [`LOSS_SALT_INTENT`].
pub fn loss_draw(stream: u64, step: u64, index: u64) -> f64 {
    let h = mix64(mix64(stream ^ mix64(step)) ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Salt of the agent-side percept-loss stream (the learner owns the unsalted
/// `Purpose::Loss` stream of each agent for gene loss).
pub const LOSS_SALT_PERCEPT: u64 = 0x5045_5243_4550_5400;
/// Salt of the world-side intent-loss stream.
pub const LOSS_SALT_INTENT: u64 = 0x494e_5445_4e54_0000;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::{decode, encode};

    #[test]
    fn loss_draws_are_uniform_and_stable() {
        let n = 20_000;
        let below = (0..n).filter(|&i| loss_draw(7, i / 100, i % 100) < 0.25).count();
        assert!((4_500..5_500).contains(&below), "{below}");
        assert_eq!(loss_draw(1, 2, 3), loss_draw(1, 2, 3));
        assert_ne!(loss_draw(1, 2, 3), loss_draw(1, 2, 4));
        assert!((0..1000).all(|i| (0.0..1.0).contains(&loss_draw(i, i, i))));
    }

    #[test]
    fn net_messages_round_trip() {
        let t = Tick { step: 4, cells: vec![1, NO_CELL, 99] };
        assert_eq!(decode::<Tick>(&encode(&t).unwrap()).unwrap(), t);
        let b = IntentBatch { step: 2, intents: vec![], idle: vec![3], counters: HostCounters::default(), ahead: None };
        assert_eq!(decode::<IntentBatch>(&encode(&b).unwrap()).unwrap(), b);
        let b = IntentBatch { ahead: Some(pack(&[Raw(&[7, 8])]).unwrap()), ..b };
        assert_eq!(decode::<IntentBatch>(&encode(&b).unwrap()).unwrap(), b);
        let packed = pack(&[]).unwrap();
        for genes in [None, Some(vec![Raw(&packed)])] {
            let h = HostPercepts { step: 3, percepts: vec![Raw(&[1, 2])], genes };
            assert_eq!(decode::<HostPercepts>(&encode(&h).unwrap()).unwrap(), h);
        }
        let r = ReportMsg::Done { steps: 5, completed: true, requested: false };
        assert_eq!(decode::<ReportMsg>(&encode(&r).unwrap()).unwrap(), r);
    }

    #[test]
    fn nested_messages_carry_messages_and_bad_ones_fail_to_open() {
        let batch = GeneBatch { step: 3, cell: 7, genes: vec![], absent: vec![4, 5] };
        let nested = nest(&batch).unwrap();
        let junk = vec![0xff; 3];
        let packed = pack(&[Raw(&nested), Raw(&junk)]).unwrap();
        let h = HostGenes { step: 3, cells: vec![7], packs: vec![Raw(&packed)] };
        let bytes = encode(&h).unwrap();
        let back = decode::<HostGenes>(&bytes).unwrap();
        assert_eq!(back, h);
        let mut scratch = Vec::new();
        let batches = unpack(back.packs[0].0, &mut scratch).unwrap();
        assert_eq!(batches.len(), 2);
        assert_eq!(batches[0].open::<GeneBatch>().unwrap(), batch);
        assert!(batches[1].open::<GeneBatch>().is_err());
        // A nested message is a length and raw bytes on the wire, not a sequence of varints.
        let big = vec![200; 1000];
        assert!(encode(&Raw(&big)).unwrap().len() <= 1000 + 3);
    }

    #[test]
    fn packs_compress_alike_genomes_and_hostile_packs_fail_without_allocating() {
        use crate::message::{GeneMapping, GeneMsg};
        let mapping = GeneMapping { valid: true, used_codons: 90, depth: 5 };
        // Genomes of one process share their parents' codons.
        let parent: Vec<u32> = (0..100).map(|i| (i * 7919) % 2001).collect();
        let genes: Vec<GeneMsg> = (0..50)
            .map(|k| {
                let mut genome = parent.clone();
                genome[k] = 3;
                GeneMsg { step: 2, from: k as u32, genome: genome.into(), fitness: 1.0, mapping }
            })
            .collect();
        let nested: Vec<Vec<u8>> = genes
            .chunks(5)
            .enumerate()
            .map(|(c, g)| nest(&GeneBatchRef { step: 2, cell: c as u32, genes: g, absent: &[] }).unwrap())
            .collect();
        let raws: Vec<Raw> = nested.iter().map(|b| Raw(b)).collect();
        let packed = pack(&raws).unwrap();
        assert!(packed.len() * 3 < nested_size(&raws, 0), "{} bytes packed", packed.len());
        let mut scratch = Vec::new();
        assert_eq!(unpack(&packed, &mut scratch).unwrap(), raws);
        assert_eq!(unpack(&pack(&[]).unwrap(), &mut scratch).unwrap(), Vec::<Raw>::new());
        // Claims of 4 GB or of more than LZ4 can expand to, truncated and garbage packs.
        let mut huge = packed.clone();
        huge[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        let mut greedy = packed[..12].to_vec();
        greedy[..4].copy_from_slice(&(1u32 << 20).to_le_bytes());
        for bad in [&huge[..], &greedy[..], &packed[..packed.len() / 2], &[1, 2, 3][..], &[][..]] {
            assert!(matches!(unpack(bad, &mut scratch), Err(crate::CodecError::Decode(_))));
            assert!(scratch.capacity() < 1 << 20, "a hostile pack made it allocate {}", scratch.capacity());
        }
    }

    #[test]
    fn corrupted_packs_never_panic() {
        // Every single-byte change and every truncation of a real pack, and random bytes:
        // an error or some batches, never a panic (the LZ4 decoder is the unsafe one,
        // with its bounds checks on).
        let nested: Vec<Vec<u8>> = (0..20)
            .map(|c| nest(&GeneBatch { step: 1, cell: c, genes: vec![], absent: vec![c, c + 1] }).unwrap())
            .collect();
        let packed = pack(&nested.iter().map(|b| Raw(b)).collect::<Vec<_>>()).unwrap();
        let mut scratch = Vec::new();
        for at in 0..packed.len() {
            for byte in [0u8, 1, 0x7f, 0x80, 0xff] {
                let mut bad = packed.clone();
                bad[at] = byte;
                let _ = unpack(&bad, &mut scratch);
            }
            let _ = unpack(&packed[..at], &mut scratch);
        }
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for len in 0..2_000usize {
            let junk: Vec<u8> = (0..len % 300)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            let _ = unpack(&junk, &mut scratch);
        }
    }

    #[test]
    fn gene_batches_encode_alike_from_parts_and_check_without_decoding_genomes() {
        use crate::message::{GeneMapping, GeneMsg};
        let mapping = GeneMapping { valid: true, used_codons: 2, depth: 3 };
        let g = |from, genome: Vec<u32>| GeneMsg { step: 3, from, genome: genome.into(), fitness: 1.5, mapping };
        let batch =
            GeneBatch { step: 3, cell: 7, genes: vec![g(10, vec![1, 2, 3]), g(11, vec![70_000])], absent: vec![12] };
        let by_parts = GeneBatchRef { step: 3, cell: 7, genes: &batch.genes, absent: &batch.absent };
        let nested = nest(&batch).unwrap();
        assert_eq!(nest(&by_parts).unwrap(), nested);
        let head: GeneBatchHead = Raw(&nested).open().unwrap();
        assert_eq!((head.step, head.cell, head.absent.as_slice()), (3, 7, &[12][..]));
        assert_eq!(Raw(&nested).open::<GeneBatchCell>().unwrap(), GeneBatchCell { step: 3, cell: 7 });
        assert_eq!(
            head.genes.iter().map(|g| (g.from, g.fitness, g.mapping)).collect::<Vec<_>>(),
            [(10, 1.5, mapping), (11, 1.5, mapping)]
        );
        let range = |first, n| crate::keys::AgentRange::new(first, n).unwrap();
        assert!(head.honest(range(10, 3)));
        assert!(!head.honest(range(10, 2)), "absent agent 12 is not the sender's");
        assert!(!head.honest(range(11, 2)), "gene of agent 10 is not the sender's");
        // A malformed genome is caught without decoding it.
        let mut bad = batch.clone();
        bad.genes[0].genome = vec![].into();
        let mut bytes = nest(&bad).unwrap();
        // Gene 0: step 3, from 10, then the genome: length 1, width byte 2 (no codons).
        let at = bytes.windows(4).position(|w| w == [3, 10, 1, 2]).unwrap() + 3;
        bytes[at] = 3;
        let head: GeneBatchHead = Raw(&bytes).open().unwrap();
        assert!(!head.honest(range(10, 3)));
    }
}
