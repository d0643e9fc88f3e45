//! Messages of the lock-step protocol (DESIGN.md §2).
//!
//! One step: the world publishes a [`Percept`] per occupied cell; each agent publishes a
//! [`GeneMsg`] to its cell; each agent publishes an [`Intent`]; the world resolves the
//! intents and publishes a [`StepReport`]. [`Control`] commands come from the
//! orchestrator. Everything is plain data with `serde` derives; the codec wraps it.
use crate::geometry::{CellIdx, Pos};
use serde::{Deserialize, Serialize};

pub type AgentId = u32;
pub type ObjectId = u32;

/// Object types of REFERENCE §1.3 (names as the grammars spell them).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, PartialOrd, Ord)]
pub enum ObjectKind {
    Hub,
    Sites,
    Food,
    Debris,
    Obstacles,
    Boundary,
    Traps,
}

impl ObjectKind {
    pub const ALL: [ObjectKind; 7] = [
        ObjectKind::Hub,
        ObjectKind::Sites,
        ObjectKind::Food,
        ObjectKind::Debris,
        ObjectKind::Obstacles,
        ObjectKind::Boundary,
        ObjectKind::Traps,
    ];

    /// Parse the grammar's spelling of an object type.
    pub fn from_name(s: &str) -> Option<Self> {
        Some(match s {
            "Hub" => ObjectKind::Hub,
            "Sites" => ObjectKind::Sites,
            "Food" => ObjectKind::Food,
            "Debris" => ObjectKind::Debris,
            "Obstacles" => ObjectKind::Obstacles,
            "Boundary" => ObjectKind::Boundary,
            "Traps" => ObjectKind::Traps,
            _ => return None,
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            ObjectKind::Hub => "Hub",
            ObjectKind::Sites => "Sites",
            ObjectKind::Food => "Food",
            ObjectKind::Debris => "Debris",
            ObjectKind::Obstacles => "Obstacles",
            ObjectKind::Boundary => "Boundary",
            ObjectKind::Traps => "Traps",
        }
    }

    /// Only obstacles and traps block movement.
    pub fn passable(self) -> bool {
        !matches!(self, ObjectKind::Obstacles | ObjectKind::Traps)
    }

    /// Things an agent can pick up.
    pub fn carryable(self) -> bool {
        matches!(self, ObjectKind::Food | ObjectKind::Debris)
    }

    /// Kinds that go to an agent's static memory instead of its blackboard.
    pub fn memorised(self) -> bool {
        matches!(self, ObjectKind::Hub | ObjectKind::Sites | ObjectKind::Boundary)
    }
}

/// A non-agent object as the world shows it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectInfo {
    pub id: ObjectId,
    pub kind: ObjectKind,
    pub pos: Pos,
    pub radius: i32,
    /// Weight (0 for objects that have none).
    pub weight: i32,
    /// Carrying capacity it takes up when carried.
    pub capacity: i32,
}

/// What everyone can see of an agent.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AgentPublic {
    pub id: AgentId,
    pub pos: Pos,
    pub heading: f64,
    pub carrying: Vec<ObjectInfo>,
    /// False once the agent's process is gone; its body idles.
    pub live: bool,
    /// Learning agents take part in lateral transfer.
    pub learning: bool,
}

/// Run-wide switches that change at scheduled steps; carried in every percept so that
/// all agents apply them at exactly the same step on every transport.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Regime {
    pub lateral_transfer: bool,
    pub ip: f64,
    pub gene_loss: f64,
}

impl Default for Regime {
    fn default() -> Self {
        Regime { lateral_transfer: true, ip: 0.85, gene_loss: 0.0 }
    }
}

/// One cell's view at the start of step `step`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Percept {
    pub step: u64,
    pub cell: CellIdx,
    pub regime: Regime,
    /// Non-agent objects registered in this cell, in registration order.
    pub objects: Vec<ObjectInfo>,
    /// Impassable objects registered in nearby cells (close enough for a move or an
    /// obstacle probe from this cell to reach them), excluding those in `objects`.
    pub nearby_impassable: Vec<ObjectInfo>,
    /// Agents registered in this cell, in id order.
    pub agents: Vec<AgentPublic>,
    /// Cells around this one whose objects the percept also carries (`area`): 0 for
    /// runs whose trees act once a tick, more where an agent may move and then sense,
    /// pick up or drop in the same tick (several actions in one tree).
    pub reach: u8,
    /// Non-agent objects registered in the cells within `reach` of this one and not in
    /// it (each once, cell by cell in row-major order, registration order within).
    pub area: Vec<ObjectInfo>,
}

/// An agent's current gene, offered to its cell-mates for lateral transfer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeneMsg {
    pub step: u64,
    pub from: AgentId,
    /// Shared, not copied: in one process every cell-mate (and the sender's own
    /// individual) holds the same codons. On the wire it is one byte string (a width
    /// byte, then the codons); an agent process decodes the genomes it receives into one
    /// buffer instead ([`genome_codons_into`]).
    #[serde(serialize_with = "codons::serialize", deserialize_with = "codons::deserialize")]
    pub genome: std::sync::Arc<[u32]>,
    pub fitness: f64,
    /// The sender's mapping of the genome. Every learner of a run maps with the run's
    /// grammar and limits, so receivers take it instead of mapping every arriving gene
    /// again (an agent process hosting many agents received about 900 changed genes per
    /// step with 1,000 agents, and ten processes mapped each of them); a receiver maps a
    /// gene itself only when the claim is implausible. Like the fitness, it is the
    /// sender's word: a false one can mislead evolution but not break a receiver.
    pub mapping: GeneMapping,
}

/// How a genome maps (see [`GeneMsg::mapping`]); used codons and depth are 0 when it
/// is invalid.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct GeneMapping {
    pub valid: bool,
    pub used_codons: u32,
    pub depth: u32,
}

/// A genome on the wire: one byte string, a width byte (2 or 4) then every codon in
/// little-endian of that width. An agent process hosting many agents decodes every
/// cell-mate's gene every step; as a sequence of varints through serde's visitor that
/// was a fifth of the process's time, as a byte string it is a copy and one allocation.
/// Whether `bytes` are a well-formed genome on the wire (see [`GeneMsg::genome`]): what
/// the world checks of the genes it relays without decoding them.
pub fn genome_bytes_ok(bytes: &[u8]) -> bool {
    codons::well_formed(bytes)
}

/// Append the codons of a genome on the wire (see [`GeneMsg::genome`]) to `out`: what
/// a receiver that keeps many genomes in one buffer decodes with. False, with `out`
/// untouched, when the bytes are not a well-formed genome.
pub fn genome_codons_into(bytes: &[u8], out: &mut Vec<u32>) -> bool {
    match bytes.split_first() {
        _ if !codons::well_formed(bytes) => return false,
        Some((2, rest)) => out.extend(rest.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]]) as u32)),
        _ => out.extend(bytes[1..].chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))),
    }
    true
}

mod codons {
    use serde::de::{Deserializer, Error, Visitor};
    use serde::Serializer;
    use std::sync::Arc;

    /// Genomes up to this many bytes on the wire are encoded on the stack (every agent
    /// publishes its gene every step; the default longest genome is 100 codons).
    const ON_STACK: usize = 1 + 2 * 256;

    pub(super) fn serialize<S: Serializer>(genome: &Arc<[u32]>, s: S) -> Result<S::Ok, S::Error> {
        let wide = genome.iter().any(|&c| c > u16::MAX as u32);
        let width = if wide { 4 } else { 2 };
        let len = 1 + width * genome.len();
        let mut stack = [0u8; ON_STACK];
        let mut heap = Vec::new();
        let out: &mut [u8] = if len <= ON_STACK {
            &mut stack[..len]
        } else {
            heap.resize(len, 0);
            &mut heap
        };
        out[0] = width as u8;
        if wide {
            for (o, &c) in out[1..].chunks_exact_mut(4).zip(genome.iter()) {
                o.copy_from_slice(&c.to_le_bytes());
            }
        } else {
            for (o, &c) in out[1..].chunks_exact_mut(2).zip(genome.iter()) {
                o.copy_from_slice(&(c as u16).to_le_bytes());
            }
        }
        s.serialize_bytes(out)
    }

    /// A width byte of 2 or 4, then whole codons of that width.
    pub(super) fn well_formed(b: &[u8]) -> bool {
        match b.split_first() {
            Some((&w @ (2 | 4), rest)) => rest.len() % w as usize == 0,
            _ => false,
        }
    }

    struct Codons;

    impl<'de> Visitor<'de> for Codons {
        type Value = Arc<[u32]>;

        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a width byte (2 or 4) and the codons in little-endian")
        }

        fn visit_bytes<E: Error>(self, b: &[u8]) -> Result<Arc<[u32]>, E> {
            let mut codons = Vec::with_capacity(b.len() / 2);
            if !super::genome_codons_into(b, &mut codons) {
                return Err(E::custom("malformed genome (width byte 2 or 4, whole codons)"));
            }
            Ok(codons.into())
        }
    }

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Arc<[u32]>, D::Error> {
        d.deserialize_bytes(Codons)
    }
}

/// One primitive change an agent asks the world to make, applied in order.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Op {
    /// Move to `to`, travelling along `heading` (before any border reflection).
    Move { to: Pos, heading: f64 },
    /// Pick up an object registered in the agent's cell.
    Pick { object: ObjectId },
    /// Drop a carried object where the agent stands.
    Drop { object: ObjectId },
}

/// Why a genetic step ran.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum GeneticTrigger {
    #[default]
    None,
    /// The storage pool reached the threshold ST.
    Storage,
    /// The stagnation rule injected fresh individuals.
    Stagnation,
}

/// Per-agent numbers the world aggregates into the step report.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct AgentStats {
    /// Lateral-transfer rate: genes kept by the IP filter this step (0 if fewer than 2).
    pub lt_rate: u32,
    pub genetic: GeneticTrigger,
    pub fitness: f64,
    /// Digest of the agent's current genome, for cross-transport parity checks.
    pub gene_digest: u64,
    /// Gene messages this agent expected but did not get (lost or late).
    pub genes_lost: u32,
    /// The behaviour class of the agent's current tree (REFERENCE §8.3), for the
    /// locality map and the live view: the world cannot derive it, it never sees trees.
    pub class: BehaviourClass,
}

/// What an agent's current behaviour tree mostly does, as REFERENCE §8.3 classifies it
/// for the locality map (Fig. 5): the first of Explore, CompositeSingleCarry,
/// CompositeDrop, MoveTowards, MoveAway its leaves contain, else `None`. The numbers are
/// the reference's class numbers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[repr(u8)]
pub enum BehaviourClass {
    #[default]
    None = 0,
    Explore = 1,
    CompositeSingleCarry = 2,
    CompositeDrop = 3,
    MoveTowards = 4,
    MoveAway = 5,
}

impl BehaviourClass {
    /// Every class, in the reference's number order.
    pub const ALL: [BehaviourClass; 6] = [
        BehaviourClass::None,
        BehaviourClass::Explore,
        BehaviourClass::CompositeSingleCarry,
        BehaviourClass::CompositeDrop,
        BehaviourClass::MoveTowards,
        BehaviourClass::MoveAway,
    ];

    /// The reference's class number (0–5).
    pub fn number(self) -> u8 {
        self as u8
    }

    pub fn name(self) -> &'static str {
        match self {
            BehaviourClass::None => "None",
            BehaviourClass::Explore => "Explore",
            BehaviourClass::CompositeSingleCarry => "CompositeSingleCarry",
            BehaviourClass::CompositeDrop => "CompositeDrop",
            BehaviourClass::MoveTowards => "MoveTowards",
            BehaviourClass::MoveAway => "MoveAway",
        }
    }
}

/// What an agent decided for step `step`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intent {
    pub step: u64,
    pub agent: AgentId,
    /// Heading at the end of the tick (turns without a move change only this).
    pub heading: f64,
    pub ops: Vec<Op>,
    pub stats: AgentStats,
}

/// The world's summary of one resolved step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct StepReport {
    pub step: u64,
    /// Task percentage (foraging or maintenance), rounded to 2 decimals.
    pub task_pct: f64,
    /// Mean and standard deviation of the LT rate over agents with a positive rate.
    pub lt_mean: f64,
    pub lt_std: f64,
    /// Agents whose storage pool triggered a genetic step this step.
    pub genetic_steps: u32,
    /// Agents whose stagnation rule triggered a genetic step this step.
    pub stagnation_steps: u32,
    pub live_agents: u32,
    /// Live agents whose intent did not arrive (they idled).
    pub missing_intents: u32,
    /// Intents or ops the world refused as invalid.
    pub rejected: u32,
    /// Gene deliveries lost (receiver side) this step.
    pub genes_lost: u32,
    /// Digest of all agent positions, headings, carried objects and genes.
    pub digest: u64,
}

/// Orchestrator → world/agents commands. They cross a trust boundary: a receiver checks
/// one with [`Control::validate`] (limits in [`crate::limits`]) before acting on it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Control {
    Start,
    Stop,
    /// Apply at the start of `at_step` (world side; propagated in percepts).
    Schedule {
        at_step: u64,
        change: Perturbation,
    },
    // New variants go last: postcard encodes a variant by its index.
    /// Hold the run between two steps until `Resume` (the live viewer's pause).
    Pause,
    Resume,
    /// Make at most this many steps per second (0 = as fast as possible), to watch a
    /// run at human speed.
    StepRate(f64),
}

/// A run-time change of the world or the swarm (REFERENCE §8.4, §8.6). Checked by
/// [`Perturbation::validate`] wherever one comes from (configuration, `geese control`,
/// the control plane).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Perturbation {
    /// Add `count` obstacles of `radius` by the obstacle placement rule; they stay.
    AddObstacles {
        count: u32,
        radius: i32,
    },
    SetIp(f64),
    SetLateralTransfer(bool),
    SetGeneLoss(f64),
    /// Kill this fraction of the live agents (lowest-drawn ids, seeded).
    KillFraction(f64),
    // New variants go last: postcard encodes a variant by its index.
    /// Add one obstacle of `radius` centred at (x, y) (the live viewer's click); it is
    /// not placed where it would cover the hub or another object.
    AddObstacleAt {
        x: i32,
        y: i32,
        radius: i32,
    },
    /// Turn the world to this task (PAPER §8, issue 30.4): the old task's items and
    /// places go (carried ones too), the new task's come, laid out as a world built for
    /// it would have them, and the task % counts the new task from 0. Why a
    /// perturbation: a change of task is the hardest change of environment a swarm can
    /// meet, and scheduling it like the others lets every transport apply it at the same
    /// step.
    SwitchTask(Task),
}

/// Which task the world is laid out for (REFERENCE §1.4). Here, not in the world crate,
/// because a [`Perturbation::SwitchTask`] names one on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Task {
    #[default]
    Foraging,
    Nest,
}

impl Task {
    /// Both tasks.
    pub const ALL: [Task; 2] = [Task::Foraging, Task::Nest];

    /// The object kinds a swarm must sense and act on to do this task besides the hub
    /// (which both tasks have): where items are found or taken, and the items. A
    /// grammar or a phenotype lacking one cannot do the task. Written once: the world
    /// lays these out, the configuration checks grammars against them.
    pub fn objects(self) -> [ObjectKind; 2] {
        match self {
            Task::Foraging => [ObjectKind::Sites, ObjectKind::Food],
            Task::Nest => [ObjectKind::Boundary, ObjectKind::Debris],
        }
    }

    /// The other task.
    pub fn other(self) -> Task {
        match self {
            Task::Foraging => Task::Nest,
            Task::Nest => Task::Foraging,
        }
    }

    /// `foraging` or `nest`.
    pub fn name(self) -> &'static str {
        match self {
            Task::Foraging => "foraging",
            Task::Nest => "nest",
        }
    }
}

impl std::str::FromStr for Task {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "foraging" => Ok(Task::Foraging),
            "nest" => Ok(Task::Nest),
            other => Err(format!("unknown task '{other}' (expected foraging or nest)")),
        }
    }
}

impl std::fmt::Display for Task {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
