//! What the agents of a run run: a learning algorithm (BeTr-GEESE, GEESE-BT, a
//! Multi-GEESE phase) or a fixed, non-evolving population (REFERENCE.md §6.7, §6.8, §7).
//!
//! A [`Program`] is plain data: the orchestrator makes it from the run's settings and a
//! population file, the in-process trial and every agent process turn it into each
//! agent's [`Role`] the same way ([`Program::prepare`], [`Prepared::role`]), so that a
//! fixed population or a combine phase behaves identically in one process and over
//! Zenoh. Populations are files ([`Population`]): every learning run writes one, and a
//! researcher may write one by hand.
use crate::bt::Bt;
use crate::ge::{self, PNode};
use geese_proto::seed::{derive, Owner, Purpose};
use geese_proto::{AgentId, ObjectKind};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// The learning algorithm of a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Algorithm {
    /// PPA behaviour trees with BT feedback (the paper's main algorithm, §6).
    #[default]
    BetrGeese,
    /// The non-PPA baseline with ad-hoc motivators (§6.7).
    GeeseBt,
    /// Behaviour fusion: a collect phase, then a combine phase (§7).
    MultiGeese,
}

impl Algorithm {
    pub const ALL: [Algorithm; 3] = [Algorithm::BetrGeese, Algorithm::GeeseBt, Algorithm::MultiGeese];

    pub fn name(self) -> &'static str {
        match self {
            Algorithm::BetrGeese => "betr-geese",
            Algorithm::GeeseBt => "geese-bt",
            Algorithm::MultiGeese => "multi-geese",
        }
    }

    /// The built-in grammar of this algorithm (and phase) for a task (`foraging` or
    /// `nest`), REFERENCE §3.6.
    pub fn grammar(self, phase: Option<Phase>, task: &str) -> String {
        match (self, phase) {
            (Algorithm::BetrGeese, _) => format!("betr-{task}-avoid"),
            (Algorithm::GeeseBt, _) => format!("geese-bt-{task}"),
            (Algorithm::MultiGeese, Some(Phase::Combine)) => format!("multi-combine-{task}"),
            (Algorithm::MultiGeese, _) => format!("multi-collect-{task}"),
        }
    }

    /// The fitness terms this algorithm sums by default.
    pub fn default_terms(self) -> FitnessTerms {
        match self {
            Algorithm::GeeseBt => FitnessTerms::GEESE_BT,
            _ => FitnessTerms::BETR,
        }
    }

    /// The strategy a fixed population of this algorithm uses by default (§8.5).
    /// The storage threshold ST of this algorithm's learners when the run sets none:
    /// 10 for Multi-GEESE (the reference code's, REFERENCE §7.1–7.2), 7 otherwise.
    pub fn default_st(self) -> usize {
        crate::learner::default_st(self == Algorithm::MultiGeese)
    }

    pub fn default_strategy(self) -> Strategy {
        match self {
            Algorithm::BetrGeese => Strategy::Parallel,
            _ => Strategy::TopAgents,
        }
    }
}

impl std::fmt::Display for Algorithm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Algorithm {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Algorithm::ALL
            .into_iter()
            .find(|a| a.name() == s)
            .ok_or_else(|| format!("unknown algorithm '{s}' (expected betr-geese, geese-bt or multi-geese)"))
    }
}

/// A Multi-GEESE phase.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    /// BeTr-GEESE with a GeneDict per agent (§7.1).
    Collect,
    /// AAR wiring of the GeneDict's controllers (§7.2).
    Combine,
    /// One-phase fusion (issue 30.2, the paper's Section 8): every agent collects as in
    /// the collect phase and, once its own GeneDict is complete and has settled
    /// ([`crate::LearnerConfig::one_phase_settle`]), evolves wirings of it as in the
    /// combine phase, in the same run: no hand-over.
    One,
}

impl std::str::FromStr for Phase {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "collect" => Ok(Phase::Collect),
            "combine" => Ok(Phase::Combine),
            "one" => Ok(Phase::One),
            other => Err(format!("unknown phase '{other}' (expected collect, combine or one)")),
        }
    }
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Phase::Collect => "collect",
            Phase::Combine => "combine",
            Phase::One => "one",
        })
    }
}

/// How a fixed population is handed to the agents.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Strategy {
    /// Every agent gets every selected phenotype, in its own shuffled order, under one
    /// Parallel root (§6.8).
    Parallel,
    /// Agent i gets selected member i mod k (§7.3).
    TopAgents,
}

impl std::str::FromStr for Strategy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "parallel" => Ok(Strategy::Parallel),
            "top-agents" => Ok(Strategy::TopAgents),
            other => Err(format!("unknown strategy '{other}' (expected parallel or top-agents)")),
        }
    }
}

/// Which terms the running fitness sums (REFERENCE §6.5, §6.7; the paper's Fig. 3
/// combinations): D diversity of the current phenotype (type I), E cells explored (II),
/// C carried weight (III, prospective), F weight delivered to a drop zone under the
/// current gene (IV, task-specific), B behaviour-tree feedback (V). The carry-over term
/// is always there. Offspring are always ranked by D inside the genetic step (PonyGE2's
/// fitness at creation), whatever the mask.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct FitnessTerms {
    pub d: bool,
    pub e: bool,
    pub b: bool,
    pub c: bool,
    pub f: bool,
}

impl FitnessTerms {
    /// BeTr-GEESE and Multi-GEESE: E + B.
    pub const BETR: FitnessTerms = FitnessTerms { d: false, e: true, b: true, c: false, f: false };
    /// GEESE-BT as the reference learner computes it: E + C + F.
    pub const GEESE_BT: FitnessTerms = FitnessTerms { d: false, e: true, b: false, c: true, f: true };

    /// Parse `E+B`, `D+E+C+F`, … (letters D, E, B, C, F joined by `+`).
    pub fn parse(s: &str) -> Result<FitnessTerms, String> {
        let mut t = FitnessTerms { d: false, e: false, b: false, c: false, f: false };
        for part in s.split('+') {
            let slot = match part.trim() {
                "D" | "d" => &mut t.d,
                "E" | "e" => &mut t.e,
                "B" | "b" => &mut t.b,
                "C" | "c" => &mut t.c,
                "F" | "f" => &mut t.f,
                other => {
                    return Err(format!(
                        "fitness terms '{s}': unknown term '{other}' (expected D, E, B, C or F joined by '+')"
                    ))
                }
            };
            if *slot {
                return Err(format!("fitness terms '{s}': '{}' appears twice", part.trim()));
            }
            *slot = true;
        }
        Ok(t)
    }
}

impl std::fmt::Display for FitnessTerms {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names = [(self.d, "D"), (self.e, "E"), (self.b, "B"), (self.c, "C"), (self.f, "F")];
        let on: Vec<&str> = names.iter().filter(|(on, _)| *on).map(|(_, n)| *n).collect();
        f.write_str(&on.join("+"))
    }
}

impl std::str::FromStr for FitnessTerms {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        FitnessTerms::parse(s)
    }
}

impl Serialize for FitnessTerms {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

impl<'de> Deserialize<'de> for FitnessTerms {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        FitnessTerms::parse(&s).map_err(serde::de::Error::custom)
    }
}

/// A gene kept in a GeneDict.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StoredGene {
    pub phenotype: Arc<str>,
    #[serde(default, skip_serializing_if = "<[u32]>::is_empty")]
    pub genome: Arc<[u32]>,
    #[serde(default)]
    pub fitness: f64,
}

/// Basic-action class → the best gene seen executing it (REFERENCE §7.1).
pub type GeneDict = BTreeMap<String, StoredGene>;

/// The keys a GeneDict may hold: the basic-action class names.
pub const ACTION_CLASSES: [&str; 8] = [
    "ExploreNormal",
    "MoveTowardsNormal",
    "MoveAwayNormal",
    "CompositeSingleCarry",
    "CompositeDrop",
    "Explore",
    "MoveTowards",
    "MoveAway",
];

/// The controller slots of the combine grammar (§3.5 productions 18–22).
const CONTROLLER_SLOTS: [&str; 5] =
    ["ExploreNormal", "MoveTowardsNormal", "MoveAwayNormal", "CompositeSingleCarry", "CompositeDrop"];

/// Does a GeneDict hold a gene for every controller slot of the combine grammar? (A
/// one-phase agent wires only then: an empty slot is an always-FAILURE leaf.)
pub fn is_complete(dict: &GeneDict) -> bool {
    CONTROLLER_SLOTS.iter().all(|k| dict.contains_key(*k))
}

/// One member of a population file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Member {
    /// The phenotype in the grammar's bracket form.
    pub phenotype: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub genome: Option<Vec<u32>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fitness: Option<f64>,
    /// The agent that held it when the population was written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent: Option<AgentId>,
    /// Multi-GEESE: the agent's GeneDict (controller slots are filled from it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gene_dict: Option<GeneDict>,
}

/// A population file (`population.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Population {
    /// The grammar the phenotypes belong to (built-in name or file).
    pub grammar: String,
    /// How a fixed run hands the members out; default by algorithm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strategy: Option<Strategy>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub algorithm: Option<Algorithm>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<Phase>,
    /// `foraging` or `nest`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task: Option<String>,
    /// Best first.
    pub members: Vec<Member>,
}

/// Why a program or population cannot run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProgramError {
    #[error("population member {index}: {reason}")]
    Member { index: usize, reason: String },
    #[error("population has no members")]
    NoMembers,
    #[error("population has no member {index}: it has {members} (numbered from 0, best first)")]
    NoSuchMember { index: usize, members: usize },
    #[error("sample {sample} of {members} members selects none (it must select at least one)")]
    EmptySample { sample: f64, members: usize },
    #[error("sample {0} is not in (0, 1]")]
    BadSample(f64),
    #[error("GeneDict key '{key}' is not a basic-action class ({})", ACTION_CLASSES.join(", "))]
    BadKey { key: String },
    #[error("agent {agent}: {reason}")]
    Agent { agent: AgentId, reason: String },
}

/// Check that every key of a GeneDict names a basic-action class.
pub fn check_gene_dict(dict: &GeneDict) -> Result<(), ProgramError> {
    match dict.keys().find(|k| !ACTION_CLASSES.contains(&k.as_str())) {
        Some(k) => Err(ProgramError::BadKey { key: k.clone() }),
        None => Ok(()),
    }
}

/// The behaviour tree of a phenotype. With a GeneDict, every combine-grammar controller
/// slot (`[Act]ExploreNormal[/Act]`, …) is replaced by the tree of the gene stored
/// under that key (§4.6); a key the GeneDict lacks becomes an always-FAILURE leaf
/// (§9.4). Errors name what does not parse or build — never an empty tree.
pub fn build_tree(phenotype: &str, dict: Option<&GeneDict>) -> Result<Bt, String> {
    let mut root = ge::parse_phenotype(phenotype).map_err(|e| format!("phenotype does not parse: {e}"))?;
    if let Some(dict) = dict {
        substitute(&mut root, dict)?;
    }
    Bt::from_pnode(&root).map_err(|e| e.to_string())
}

fn substitute(node: &mut PNode, dict: &GeneDict) -> Result<(), String> {
    match node {
        PNode::Composite { children, .. } => children.iter_mut().try_for_each(|c| substitute(c, dict)),
        PNode::Leaf { text, tag } if tag == "Act" && CONTROLLER_SLOTS.contains(&text.trim()) => {
            *node = match dict.get(text.trim()) {
                Some(g) => ge::parse_phenotype(&g.phenotype)
                    .map_err(|e| format!("GeneDict gene '{}' does not parse: {e}", text.trim()))?,
                None => PNode::Leaf { text: "AbsentAction".into(), tag: "Act".into() },
            };
            Ok(())
        }
        PNode::Leaf { .. } => Ok(()),
    }
}

/// Object types a task's world has no use for: a phenotype naming one belongs to the
/// other task. `union` is a run whose task changes (`SwitchTask`, issue 30.4): both
/// tasks' objects belong to it.
pub fn foreign_objects(task: &str) -> &'static [ObjectKind] {
    match task {
        "union" => &[],
        "nest" => &[ObjectKind::Food, ObjectKind::Sites],
        _ => &[ObjectKind::Debris, ObjectKind::Boundary],
    }
}

/// A selected member of a fixed population.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FixedMember {
    pub phenotype: String,
    pub gene_dict: Option<GeneDict>,
}

/// What every agent of a run runs (travels to agent processes with the run).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Program {
    Learn {
        algorithm: Algorithm,
        phase: Option<Phase>,
        /// Combine phase: agent i's GeneDict is `gene_dicts[i]`.
        gene_dicts: Vec<GeneDict>,
    },
    Fixed {
        strategy: Strategy,
        /// The selected members, best first.
        members: Vec<FixedMember>,
    },
}

impl Default for Program {
    fn default() -> Self {
        Program::Learn { algorithm: Algorithm::BetrGeese, phase: None, gene_dicts: Vec::new() }
    }
}

impl Program {
    /// A learning program.
    pub fn learn(algorithm: Algorithm, phase: Option<Phase>) -> Program {
        Program::Learn { algorithm, phase, gene_dicts: Vec::new() }
    }

    pub fn is_fixed(&self) -> bool {
        matches!(self, Program::Fixed { .. })
    }

    /// Build what the agents need once (the fixed members' trees, the GeneDicts),
    /// checking every member and GeneDict against a task (`foraging` or `nest`).
    pub fn prepare(&self, task: &str) -> Result<Prepared, ProgramError> {
        let foreign = foreign_objects(task);
        let check = |bt: &Bt| -> Result<(), String> {
            match bt.leaves().find_map(|l| l.object().filter(|k| foreign.contains(k))) {
                Some(k) => Err(format!("names {}, which the {task} task does not have", k.name())),
                None => Ok(()),
            }
        };
        match self {
            Program::Learn { algorithm, phase, gene_dicts } => {
                let combine = *algorithm == Algorithm::MultiGeese && *phase == Some(Phase::Combine);
                if combine && gene_dicts.is_empty() {
                    return Err(ProgramError::Agent {
                        agent: 0,
                        reason: "the combine phase needs each agent's GeneDict (from a collect population)".into(),
                    });
                }
                let mut dicts = Vec::with_capacity(gene_dicts.len());
                for (i, d) in gene_dicts.iter().enumerate() {
                    check_gene_dict(d)?;
                    for (k, g) in d {
                        build_tree(&g.phenotype, None).and_then(|bt| check(&bt)).map_err(|r| ProgramError::Agent {
                            agent: i as AgentId,
                            reason: format!("GeneDict {k}: {r}"),
                        })?;
                    }
                    dicts.push(Arc::new(d.clone()));
                }
                let combine = match (*algorithm, *phase) {
                    (Algorithm::MultiGeese, Some(Phase::One)) => {
                        let name = Algorithm::MultiGeese.grammar(Some(Phase::Combine), task);
                        let text = crate::grammars::builtin(&name).ok_or_else(|| ProgramError::Agent {
                            agent: 0,
                            reason: format!("one-phase fusion needs the built-in grammar {name}"),
                        })?;
                        let g = ge::Grammar::parse(text)
                            .map_err(|e| ProgramError::Agent { agent: 0, reason: format!("grammar {name}: {e}") })?;
                        Some(Arc::new(g))
                    }
                    _ => None,
                };
                Ok(Prepared::Learn { algorithm: *algorithm, phase: *phase, dicts, combine })
            }
            Program::Fixed { strategy, members } => {
                if members.is_empty() {
                    return Err(ProgramError::NoMembers);
                }
                let mut trees = Vec::with_capacity(members.len());
                for (index, m) in members.iter().enumerate() {
                    if let Some(d) = &m.gene_dict {
                        check_gene_dict(d).map_err(|e| ProgramError::Member { index, reason: e.to_string() })?;
                    }
                    let bt = build_tree(&m.phenotype, m.gene_dict.as_ref())
                        .map_err(|reason| ProgramError::Member { index, reason })?;
                    check(&bt).map_err(|reason| ProgramError::Member { index, reason })?;
                    trees.push(bt);
                }
                Ok(Prepared::Fixed { strategy: *strategy, trees })
            }
        }
    }
}

/// A [`Program`] made ready: trees built, GeneDicts shared.
pub enum Prepared {
    /// `combine`: one-phase fusion's combine grammar, which its agents switch to.
    Learn {
        algorithm: Algorithm,
        phase: Option<Phase>,
        dicts: Vec<Arc<GeneDict>>,
        combine: Option<Arc<ge::Grammar>>,
    },
    Fixed {
        strategy: Strategy,
        trees: Vec<Bt>,
    },
}

/// What one agent does.
pub enum Role {
    BetrGeese,
    GeeseBt,
    /// Multi-GEESE collect: BeTr-GEESE filling a GeneDict.
    Collect,
    /// Multi-GEESE combine with the agent's own (fixed) GeneDict.
    Combine(Arc<GeneDict>),
    /// One-phase fusion: collect, then wire with this combine grammar (issue 30.2).
    OnePhase(Arc<ge::Grammar>),
    /// A non-evolving agent ticking this tree.
    Fixed(Bt),
}

impl Prepared {
    /// Agent `id`'s role in a run of seed `seed`. The Parallel strategy's shuffle draws
    /// from the agent's evolution stream (a fixed agent never evolves).
    pub fn role(&self, id: AgentId, seed: u64) -> Role {
        match self {
            Prepared::Learn { algorithm: Algorithm::BetrGeese, .. } => Role::BetrGeese,
            Prepared::Learn { algorithm: Algorithm::GeeseBt, .. } => Role::GeeseBt,
            Prepared::Learn { phase: Some(Phase::Combine), dicts, .. } => {
                // `prepare` checked there is at least one.
                Role::Combine(dicts[id as usize % dicts.len()].clone())
            }
            Prepared::Learn { combine: Some(g), .. } => Role::OnePhase(g.clone()),
            Prepared::Learn { .. } => Role::Collect,
            Prepared::Fixed { strategy: Strategy::TopAgents, trees } => {
                Role::Fixed(trees[id as usize % trees.len()].fresh())
            }
            Prepared::Fixed { strategy: Strategy::Parallel, trees } => {
                let mut rng = ChaCha8Rng::seed_from_u64(derive(seed, Owner::Agent(id), Purpose::Evolution));
                let mut order: Vec<&Bt> = trees.iter().collect();
                order.shuffle(&mut rng);
                let fresh: Vec<Bt> = order.into_iter().map(Bt::fresh).collect();
                Role::Fixed(Bt::parallel(&fresh))
            }
        }
    }
}

impl Population {
    /// Read and parse a population file.
    pub fn from_json(text: &str) -> Result<Population, String> {
        serde_json::from_str(text).map_err(|e| e.to_string())
    }

    /// The file text: the header fields one per line, then one member per line (a
    /// genome is a hundred codons; one codon per line made files of megabytes).
    pub fn to_json(&self) -> String {
        let head = Population {
            grammar: self.grammar.clone(),
            strategy: self.strategy,
            algorithm: self.algorithm,
            phase: self.phase,
            task: self.task.clone(),
            members: Vec::new(),
        };
        let mut out = String::from("{\n");
        if let Ok(serde_json::Value::Object(m)) = serde_json::to_value(&head) {
            for (k, v) in m.iter().filter(|(k, _)| *k != "members") {
                out.push_str(&format!("  {}: {v},\n", serde_json::Value::String(k.clone())));
            }
        }
        out.push_str("  \"members\": [\n");
        let lines: Vec<String> =
            self.members.iter().map(|m| format!("    {}", serde_json::to_string(m).unwrap_or_default())).collect();
        out.push_str(&lines.join(",\n"));
        out.push_str("\n  ]\n}\n");
        out
    }

    /// The members best first: by fitness (descending, stable) when every member has
    /// one, else in file order.
    pub fn sorted_members(&self) -> Vec<&Member> {
        let mut v: Vec<&Member> = self.members.iter().collect();
        if v.iter().all(|m| m.fitness.is_some()) {
            v.sort_by(|a, b| ge::fitness_cmp(b.fitness.unwrap_or(f64::NAN), a.fitness.unwrap_or(f64::NAN)));
        }
        v
    }

    /// The behaviour tree of member `k` of the best-first order ([`Population::sorted_members`])
    /// as a run builds it: a Multi-GEESE member's controller slots hold the trees of its
    /// GeneDict's genes ([`build_tree`]), so the picture is what the agent ticks.
    pub fn member_tree(&self, k: usize) -> Result<Bt, ProgramError> {
        let ranked = self.sorted_members();
        let m = ranked.get(k).ok_or(ProgramError::NoSuchMember { index: k, members: ranked.len() })?;
        if let Some(d) = &m.gene_dict {
            check_gene_dict(d).map_err(|e| ProgramError::Member { index: k, reason: e.to_string() })?;
        }
        build_tree(&m.phenotype, m.gene_dict.as_ref()).map_err(|reason| ProgramError::Member { index: k, reason })
    }

    /// The members a fixed run of `sample` (a fraction in (0, 1]) uses with `strategy`:
    /// the best ⌊sample · n⌋ of the n members; for the Parallel strategy duplicate
    /// phenotypes collapse first and the best ⌊sample · n⌋ distinct ones are kept (the
    /// reference takes the ratio of the population size, §6.8), for Top Agents every
    /// member counts (§7.3).
    pub fn select(&self, sample: f64, strategy: Strategy) -> Result<Vec<FixedMember>, ProgramError> {
        if !(sample > 0.0 && sample <= 1.0) {
            return Err(ProgramError::BadSample(sample));
        }
        if self.members.is_empty() {
            return Err(ProgramError::NoMembers);
        }
        let mut ranked = self.sorted_members();
        let k = (sample * ranked.len() as f64 + 1e-9).floor() as usize;
        if k == 0 {
            return Err(ProgramError::EmptySample { sample, members: ranked.len() });
        }
        if strategy == Strategy::Parallel {
            let mut seen = std::collections::HashSet::new();
            ranked.retain(|m| seen.insert(m.phenotype.as_str()));
        }
        Ok(ranked[..k.min(ranked.len())]
            .iter()
            .map(|m| FixedMember { phenotype: m.phenotype.clone(), gene_dict: m.gene_dict.clone() })
            .collect())
    }

    /// The GeneDict each of `agents` combine agents starts with: collect agent i's for
    /// agent i (members carry their agent id), round-robin over the members in file
    /// order when the ids do not cover every agent.
    pub fn gene_dicts(&self, agents: u32) -> Result<Vec<GeneDict>, ProgramError> {
        if self.members.is_empty() {
            return Err(ProgramError::NoMembers);
        }
        for (index, m) in self.members.iter().enumerate() {
            match &m.gene_dict {
                None => {
                    return Err(ProgramError::Member {
                        index,
                        reason: "has no gene_dict (a combine phase starts from a collect population)".into(),
                    })
                }
                Some(d) => check_gene_dict(d).map_err(|e| ProgramError::Member { index, reason: e.to_string() })?,
            }
        }
        let by_agent: BTreeMap<AgentId, &GeneDict> =
            self.members.iter().filter_map(|m| Some((m.agent?, m.gene_dict.as_ref()?))).collect();
        Ok((0..agents)
            .map(|i| match by_agent.get(&i) {
                Some(d) => (*d).clone(),
                None => self.members[i as usize % self.members.len()].gene_dict.clone().unwrap_or_default(),
            })
            .collect())
    }

    /// Check the file belongs to `grammar` (its name, or its bracket tags and behaviour
    /// names appear in the grammar text) and to `task`.
    pub fn check_against(&self, grammar_name: &str, grammar_text: &str, task: &str) -> Result<(), String> {
        if let Some(t) = &self.task {
            if t != task {
                return Err(format!("population is for the {t} task, the run is {task}"));
            }
        }
        if self.grammar == grammar_name {
            return Ok(());
        }
        for (index, m) in self.members.iter().enumerate() {
            for tag in tags(&m.phenotype) {
                if !grammar_text.contains(&format!("[{tag}]")) {
                    return Err(format!(
                        "population member {index}: tag [{tag}] does not occur in grammar {grammar_name} \
                         (the file says its grammar is {})",
                        self.grammar
                    ));
                }
            }
        }
        Ok(())
    }
}

/// The element tags of a bracket phenotype (without the XML header).
fn tags(phenotype: &str) -> impl Iterator<Item = &str> {
    phenotype.split('[').skip(1).filter_map(|s| {
        let t = s.split(']').next()?;
        (!t.starts_with('/') && !t.starts_with('?')).then_some(t)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const PPA: &str = "[?xml version=%1.0% encoding=%UTF-8%?][Selector][Sequence][PostCnd]IsCarrying_Food[/PostCnd][/Sequence][Sequence][Sequence][PreCnd]NeighbourObjects_Food[/PreCnd][/Sequence][Act]CompositeSingleCarry_Food[/Act][/Sequence][/Selector]";

    fn member(p: &str, f: Option<f64>) -> Member {
        Member { phenotype: p.into(), genome: None, fitness: f, agent: None, gene_dict: None }
    }

    #[test]
    fn terms_parse_and_print() {
        assert_eq!(FitnessTerms::parse("E+B").unwrap(), FitnessTerms::BETR);
        assert_eq!(FitnessTerms::parse("E+C+F").unwrap(), FitnessTerms::GEESE_BT);
        assert_eq!(FitnessTerms::parse("D+E+B+C+F").unwrap().to_string(), "D+E+B+C+F");
        assert!(FitnessTerms::parse("E+X").unwrap_err().contains("'X'"));
        assert!(FitnessTerms::parse("E+E").unwrap_err().contains("twice"));
    }

    #[test]
    fn algorithms_parse_by_name() {
        for a in Algorithm::ALL {
            assert_eq!(a.name().parse::<Algorithm>().unwrap(), a);
        }
        assert!("betr".parse::<Algorithm>().unwrap_err().contains("'betr'"));
    }

    #[test]
    fn samples_select_the_best_and_empty_samples_are_errors() {
        let pop = Population {
            grammar: "betr-foraging-avoid".into(),
            strategy: None,
            algorithm: None,
            phase: None,
            task: None,
            members: (0..10).map(|i| member(&format!("{PPA}{i}"), Some(i as f64))).collect(),
        };
        let s = pop.select(0.3, Strategy::TopAgents).unwrap();
        assert_eq!(s.len(), 3);
        assert!(s[0].phenotype.ends_with('9'));
        assert_eq!(
            pop.select(0.001, Strategy::TopAgents),
            Err(ProgramError::EmptySample { sample: 0.001, members: 10 })
        );
        assert_eq!(pop.select(0.0, Strategy::TopAgents), Err(ProgramError::BadSample(0.0)));
        let dup = Population { members: vec![member(PPA, Some(2.0)), member(PPA, Some(1.0))], ..pop };
        assert_eq!(dup.select(1.0, Strategy::Parallel).unwrap().len(), 1);
        assert_eq!(dup.select(1.0, Strategy::TopAgents).unwrap().len(), 2);
    }

    #[test]
    fn bad_phenotypes_and_foreign_objects_name_the_member() {
        let fixed = |p: &str| Program::Fixed {
            strategy: Strategy::TopAgents,
            members: vec![
                FixedMember { phenotype: PPA.into(), gene_dict: None },
                FixedMember { phenotype: p.into(), gene_dict: None },
            ],
        };
        let err = |p: &str, task| fixed(p).prepare(task).err().unwrap().to_string();
        assert!(fixed(PPA).prepare("foraging").is_ok());
        assert!(err("[Sequence][Act]Fly_Hub[/Act][/Sequence]", "foraging")
            .starts_with("population member 1: unknown behaviour 'Fly'"));
        assert!(err("[Sequence][Act]Explore", "foraging").starts_with("population member 1: phenotype does not parse"));
        assert!(err(PPA, "nest").contains("names Food, which the nest task does not have"));
        // A combine phenotype without a GeneDict cannot be built.
        let combine = "[Sequence][Sequence][Selector][Sequence][PreCnd]IsVisitedBefore_Hub[/PreCnd][/Sequence][Act]CompositeSingleCarry[/Act][/Selector][PostCnd]NeighbourObjects_Hub[/PostCnd][/Sequence][/Sequence]";
        assert!(err(combine, "foraging").contains("needs an object type"));
    }

    #[test]
    fn gene_dict_fills_controller_slots_and_a_missing_key_fails() {
        let combine = "[Sequence][Sequence][Selector][Sequence][PreCnd]IsVisitedBefore_Hub[/PreCnd][/Sequence][Act]CompositeSingleCarry[/Act][/Selector][PostCnd]NeighbourObjects_Hub[/PostCnd][/Sequence][/Sequence]";
        let mut dict = GeneDict::new();
        dict.insert(
            "CompositeSingleCarry".into(),
            StoredGene { phenotype: PPA.into(), genome: Arc::from([]), fitness: 3.0 },
        );
        let bt = build_tree(combine, Some(&dict)).unwrap();
        let text = bt.render();
        assert!(text.contains("CompositeSingleCarry[Food]"), "{text}");
        assert!(text.contains("IsCarrying[Food]"), "{text}");
        let empty = build_tree(combine, Some(&GeneDict::new())).unwrap();
        assert!(empty.render().contains("AbsentAction"), "{}", empty.render());
        dict.insert("Fly".into(), StoredGene { phenotype: PPA.into(), genome: Arc::from([]), fitness: 0.0 });
        assert_eq!(check_gene_dict(&dict), Err(ProgramError::BadKey { key: "Fly".into() }));
    }

    /// Issue 19: any member of the shipped populations can be drawn; a Multi-GEESE
    /// member's controllers appear in place.
    #[test]
    fn members_of_the_shipped_populations_build_as_the_run_builds_them() {
        use crate::bt::TreeFormat;
        let five = Population::from_json(include_str!("../../populations/foraging-five-behaviours.json")).unwrap();
        for k in 0..5 {
            let bt = five.member_tree(k).unwrap();
            assert!(bt.draw(TreeFormat::Dot).starts_with("digraph bt {"));
            assert!(bt.render().contains("(Act)"));
        }
        assert_eq!(five.member_tree(5).unwrap_err(), ProgramError::NoSuchMember { index: 5, members: 5 });
        assert_eq!(
            five.member_tree(5).unwrap_err().to_string(),
            "population has no member 5: it has 5 (numbered from 0, best first)"
        );

        let multi = Population::from_json(include_str!("../../populations/fig9-multi-geese-foraging.json")).unwrap();
        let best = multi.sorted_members()[0];
        let dict = best.gene_dict.as_ref().unwrap();
        let bt = multi.member_tree(0).unwrap();
        let bare = ge::parse_phenotype(&best.phenotype).unwrap();
        assert!(bt.len() > bare.size(), "the GeneDict's trees replace the controller slots");
        let text = bt.render();
        assert!(!text.contains("AbsentAction"), "all five slots are in the GeneDict: {text}");
        // Every controller slot of the combine phenotype became its gene's tree.
        let slots: Vec<&str> =
            bare.leaves().into_iter().filter(|(_, tag)| *tag == "Act").map(|(l, _)| l.trim()).collect();
        assert!(!slots.is_empty());
        for slot in slots {
            let gene = build_tree(&dict[slot].phenotype, None).unwrap().render();
            let action = gene.lines().find(|l| l.ends_with("(Act)")).unwrap().trim();
            assert!(text.contains(action), "{slot}: {action} not in the combined tree");
        }
        let svg = bt.draw(TreeFormat::Svg);
        assert_eq!(svg.matches("<g>").count(), bt.len());
        // A member whose phenotype needs its GeneDict, without it, is named.
        let mut broken = multi.clone();
        broken.members.iter_mut().for_each(|m| m.gene_dict = None);
        let e = broken.member_tree(0).unwrap_err().to_string();
        assert!(e.starts_with("population member 0: "), "{e}");
    }

    #[test]
    fn population_files_of_another_grammar_or_task_are_refused() {
        let pop = Population {
            grammar: "geese-bt-foraging".into(),
            strategy: None,
            algorithm: None,
            phase: None,
            task: Some("foraging".into()),
            members: vec![member("[Selector][cond]IsDropable_Hub[/cond][act]Explore[/act][/Selector]", None)],
        };
        let forge = crate::grammars::builtin("betr-foraging-avoid").unwrap();
        let e = pop.check_against("betr-foraging-avoid", forge, "foraging").unwrap_err();
        assert!(e.contains("tag [cond]"), "{e}");
        assert!(pop.check_against("geese-bt-foraging", "", "nest").unwrap_err().contains("foraging task"));
        let text = r#"{"grammar": "betr-foraging-avoid", "strategy": "parallel", "members": [{"phenotype": "x"}]}"#;
        assert_eq!(Population::from_json(text).unwrap().strategy, Some(Strategy::Parallel));
        assert!(Population::from_json(r#"{"grammar": "g", "members": [], "extra": 1}"#).unwrap_err().contains("extra"));
        let round = Population::from_json(&pop.to_json()).unwrap();
        assert_eq!(round, pop);
        assert_eq!(pop.to_json().lines().count(), 7, "brace, 2 header lines, members line, 1 member, bracket, brace");
    }
}
