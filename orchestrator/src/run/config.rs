//! Run configuration: a raw TOML/CLI form, validated into a typed [`RunSpec`].
//!
//! Every field defaults to the paper's setting (REFERENCE.md §5.1): 100 agents, 12,000
//! steps, IP 0.85, ST 7, GS 10. Unknown keys are errors that name the key (serde's
//! `deny_unknown_fields`); out-of-range values are errors that name the field.
use geese_agent::ge::Grammar;
use geese_agent::program::{Algorithm, Phase, Population, Program, Strategy};
use geese_agent::{grammars, LearnerConfig};
use geese_proto::limits::{check_max, MAX_SCHEDULED, MAX_STEPS};
use geese_proto::{Perturbation, Regime};
use geese_world::locality::Window;
use geese_world::{Task, WorldConfig};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Most threads one trial may ask for.
pub const MAX_THREADS: u32 = 1024;

/// Fewest agents per thread `geese run` starts by itself: a step of 100 agents takes
/// about 0.3 ms, and handing it to a second thread and back costs more than it saves
/// (the default trial: 3,195 steps/s on 1 thread, 2,432 on 2; 400 agents: 502 and
/// 619; 1,000 agents: 154 and 239, on 2 cores).
pub const AGENTS_PER_AUTO_THREAD: u32 = 200;

/// A perturbation at a given step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scheduled {
    /// Applied right after this step is resolved (the reference code's hook timing).
    pub at: u64,
    pub change: Perturbation,
}

/// The raw configuration, as written in a TOML file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    pub steps: u64,
    pub seed: u64,
    /// The learning algorithm: betr-geese, geese-bt or multi-geese (REFERENCE §6–7).
    pub algorithm: Algorithm,
    /// Multi-GEESE: run this phase alone; unset runs collect, then combine (each for
    /// `steps` steps).
    pub phase: Option<Phase>,
    /// A combine phase run alone starts from this collect population (its GeneDicts).
    pub collect_population: Option<PathBuf>,
    /// Run this fixed population (no evolution, no lateral transfer).
    pub population: Option<PathBuf>,
    /// Fraction of the population's best members a fixed run uses. Without
    /// `population`, the run learns and then tests its own population so sampled, in
    /// the fixed-agent world (paper layout, agents at the hub), for `steps` steps.
    pub sample: Option<f64>,
    /// How a fixed population is handed out (parallel or top-agents); default: the
    /// file's, else parallel for BeTr-GEESE and top-agents otherwise (REFERENCE §8.5).
    pub strategy: Option<Strategy>,
    /// Built-in grammar name or path to a `.bnf` file; default by algorithm, phase and
    /// task (`betr-foraging-avoid`, `geese-bt-nest`, `multi-combine-foraging`, …).
    pub grammar: Option<String>,
    /// Interaction probability IP.
    pub ip: f64,
    pub lateral_transfer: bool,
    /// Receiver-side probability of losing a gene delivery.
    pub gene_loss: f64,
    /// Task % counted as success.
    pub threshold: f64,
    pub world: WorldConfig,
    pub learner: LearnerConfig,
    pub perturbations: Vec<Scheduled>,
    /// Where a trial follows the reference code instead of DESIGN §2 (in one process
    /// only): the step schedule and the blackboard's scope.
    pub fidelity: Fidelity,
    /// Count the locality map (Fig. 5) over steps `FROM:TO`, both included, step 1
    /// being the first ([`geese_world::locality`]); written to `locality.csv`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub locality: Option<String>,
    /// Threads that step one in-process trial ([`crate::run::trial`]); the trajectory is the
    /// same for every value. Unset: one (a campaign runs one trial per core); `geese run`
    /// chooses ([`RunConfig::auto_threads`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub threads: Option<u32>,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            steps: 12_000,
            seed: 1,
            algorithm: Algorithm::BetrGeese,
            phase: None,
            collect_population: None,
            population: None,
            sample: None,
            strategy: None,
            grammar: None,
            ip: 0.85,
            lateral_transfer: true,
            gene_loss: 0.0,
            threshold: 80.0,
            world: WorldConfig::default(),
            learner: LearnerConfig::default(),
            perturbations: Vec::new(),
            fidelity: Fidelity::default(),
            locality: None,
            threads: None,
        }
    }
}

/// The two departures of DESIGN §2 from the reference code that a trial in one process
/// can undo (REFERENCE §9.2): agents separate processes cannot see one another's moves
/// within a step nor share a blackboard, so the defaults are what every transport can
/// do, and a distributed run refuses anything else ([`Fidelity::check_distributed`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Fidelity {
    pub schedule: Schedule,
    pub blackboard: Blackboard,
    pub genes: Genes,
}

/// When an agent decides (REFERENCE §1.8, §9.3).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Schedule {
    /// Every agent decides on the step's snapshot; the world applies the intents in
    /// agent-id order (DESIGN §2).
    #[default]
    Simultaneous,
    /// Agents decide one after another in id order, each on the world as the agents
    /// before it left it (its percept taken when its turn comes, the genes of the agents
    /// in the cell its move took it to as they stand then, intents applied at once): the
    /// reference code.
    Sequential,
}

/// Whose blackboard a leaf reads and writes (REFERENCE §2.2).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Blackboard {
    /// One per agent (DESIGN §2).
    #[default]
    PerAgent,
    /// One for the whole swarm, as py_trees' global `neighbourobj` key in the
    /// reference code: what one agent sensed, the next one ticked reads.
    Global,
}

/// What an agent holds of a cell-mate's gene (REFERENCE §6.6).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Genes {
    /// A copy, fitness included, as it was sent (DESIGN §2).
    #[default]
    Copied,
    /// The reference code's shared objects: one fitness field per gene for every agent
    /// holding it, read as it stands at the genetic step, zeroed for the donor too when
    /// an adopter resets it, and followed by the GeneDict entries that hold it.
    Shared,
}

impl Fidelity {
    /// A distributed run can only run the defaults.
    pub fn check_distributed(&self) -> Result<(), String> {
        let mut bad = Vec::new();
        if self.schedule != Schedule::Simultaneous {
            bad.push("fidelity.schedule = \"sequential\" (an agent would have to see the moves of agents in other processes within a step)");
        }
        if self.blackboard != Blackboard::PerAgent {
            bad.push("fidelity.blackboard = \"global\" (agents in separate processes share no memory)");
        }
        if self.genes != Genes::Copied {
            bad.push("fidelity.genes = \"shared\" (a gene object cannot be shared across processes)");
        }
        if bad.is_empty() {
            Ok(())
        } else {
            Err(format!("{} runs in one process only: drop --processes, or use the defaults", bad.join(" and ")))
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("config {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{field}: {reason}")]
    Invalid { field: String, reason: String },
    #[error("grammar {name}: {message}")]
    Grammar { name: String, message: String },
    #[error("population {path}: {message}")]
    Population { path: String, message: String },
}

/// What runs after a stage of a run (a Multi-GEESE combine phase, or the fixed test of
/// the population a learning run ended with).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FollowUp {
    None,
    Combine,
    FixedTest,
}

fn invalid(field: &str, reason: impl Into<String>) -> ConfigError {
    ConfigError::Invalid { field: field.into(), reason: reason.into() }
}

/// A validated run: everything a trial needs, grammar parsed.
#[derive(Clone, Debug)]
pub struct RunSpec {
    pub config: RunConfig,
    /// Name (built-in) or path the grammar came from.
    pub grammar_name: String,
    /// The grammar's text, for the manifest digest.
    pub grammar_text: Arc<str>,
    pub grammar: Arc<Grammar>,
    pub learner: Arc<LearnerConfig>,
    /// What the agents run in this stage.
    pub program: Arc<Program>,
    /// What runs after this stage.
    pub follow_up: FollowUp,
    /// Which stage this is: `collect`, `combine`, `learn` or `fixed`.
    pub stage: &'static str,
    /// The steps whose locality map the stage counts (`locality`).
    pub locality: Option<Window>,
    /// The percept reach was the run's choice (`world.percept_reach` unset), so the next
    /// stage chooses again for its own trees.
    reach_by_run: bool,
    /// What the run should know before it starts but is not an error (a fixed
    /// population meeting a task its trees do not name); printed and kept in the
    /// manifest.
    pub notes: Vec<String>,
}

impl RunConfig {
    /// Parse a TOML file.
    pub fn from_file(path: &Path) -> Result<RunConfig, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.into(), source })?;
        Self::from_toml(&text).map_err(|message| ConfigError::Parse { path: path.into(), message })
    }

    pub fn from_toml(text: &str) -> Result<RunConfig, String> {
        toml::from_str(text).map_err(|e| e.to_string())
    }

    /// The grammar name this run uses.
    pub fn grammar_name(&self) -> String {
        let phase = match (self.algorithm, self.phase) {
            (Algorithm::MultiGeese, None) => Some(Phase::Collect),
            (_, p) => p,
        };
        // A run whose task changes learns in the union grammar of both tasks (issue 30.4).
        self.grammar.clone().unwrap_or_else(|| self.algorithm.grammar(phase, self.program_task()))
    }

    /// The task the agents' program is checked against
    /// ([`geese_agent::program::Program::prepare`]): `union` when the task changes
    /// during the run (both tasks' objects belong), else the task.
    pub fn program_task(&self) -> &'static str {
        if self.switches().is_empty() {
            task_name(self.world.task)
        } else {
            "union"
        }
    }

    /// The scheduled task switches, in the order they apply: (index in `perturbations`,
    /// step, new task).
    pub fn switches(&self) -> Vec<(usize, u64, Task)> {
        let mut v: Vec<(usize, u64, Task)> = self
            .perturbations
            .iter()
            .enumerate()
            .filter_map(|(i, p)| match p.change {
                Perturbation::SwitchTask(t) => Some((i, p.at, t)),
                _ => None,
            })
            .collect();
        v.sort_by_key(|&(i, at, _)| (at, i));
        v
    }

    /// Check the task switches: each applies before the last step, and each changes
    /// the task (a switch to the task already running is a mistake worth naming).
    fn check_switches(&self) -> Result<(), ConfigError> {
        let mut task = self.world.task;
        for (i, at, to) in self.switches() {
            if at >= self.steps {
                return Err(invalid(
                    &format!("perturbations[{i}].at"),
                    format!(
                        "SwitchTask at step {at} is beyond the run: it applies after step {at}, and the run \
                         ends at step {} (steps = {})",
                        self.steps, self.steps
                    ),
                ));
            }
            if to == task {
                return Err(invalid(
                    &format!("perturbations[{i}].change"),
                    format!("SwitchTask to {to} at step {at}: the world already runs the {to} task then"),
                ));
            }
            task = to;
        }
        Ok(())
    }

    /// The locality window, checked: `FROM:TO` with 1 ≤ FROM ≤ TO ≤ `steps`.
    pub fn locality_window(&self) -> Result<Option<Window>, ConfigError> {
        let Some(text) = &self.locality else { return Ok(None) };
        let w: Window =
            text.parse().map_err(|e: geese_world::locality::LocalityError| invalid("locality", e.to_string()))?;
        if w.to > self.steps {
            return Err(invalid(
                "locality",
                format!("{text:?} ends after the run's last step (steps = {})", self.steps),
            ));
        }
        Ok(Some(w))
    }

    /// The initial regime (IP, lateral transfer, loss).
    pub fn regime(&self) -> Regime {
        Regime { lateral_transfer: self.lateral_transfer, ip: self.ip, gene_loss: self.gene_loss }
    }

    /// `threads` must be at least 1, at most the agents (a thread with no agent has
    /// nothing to decide) and at most [`MAX_THREADS`]; more than one needs DESIGN §2's
    /// defaults, since the reference-code modes of [`Fidelity`] let one agent's step
    /// see another's within the step.
    fn check_threads(&self) -> Result<(), ConfigError> {
        let Some(n) = self.threads else { return Ok(()) };
        if n == 0 {
            return Err(invalid("threads", "0: a trial needs at least 1 thread"));
        }
        if n > MAX_THREADS {
            return Err(invalid("threads", format!("{n} exceeds the limit of {MAX_THREADS}")));
        }
        if n > self.world.agents.max(1) {
            return Err(invalid(
                "threads",
                format!("{n} is more than the {} agents (each thread needs at least one agent)", self.world.agents),
            ));
        }
        if n > 1 && self.fidelity != Fidelity::default() {
            return Err(invalid(
                "threads",
                format!(
                    "{n}: the reference-code fidelity modes (schedule, blackboard, genes) run on 1 thread, \
                     since each agent's step there reads what the agents before it did"
                ),
            ));
        }
        Ok(())
    }

    /// The threads `geese run` uses when none are asked for: the machine's cores, at
    /// most one per [`AGENTS_PER_AUTO_THREAD`] agents, and 1 for the reference-code
    /// fidelity modes.
    pub fn auto_threads(&self) -> u32 {
        if self.fidelity != Fidelity::default() {
            return 1;
        }
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as u32;
        cores.clamp(1, MAX_THREADS).min(self.world.agents / AGENTS_PER_AUTO_THREAD).max(1)
    }

    /// Check every value and load the grammar. Sizes have upper limits
    /// ([`geese_proto::limits`]): at most 10,000,000 steps and 10,000 scheduled
    /// perturbations, each checked as a control command would be
    /// ([`geese_proto::Perturbation::validate`]); the world's limits are
    /// [`WorldConfig::validate`]'s.
    pub fn validate(self) -> Result<RunSpec, ConfigError> {
        if self.steps == 0 {
            return Err(invalid("steps", "must be at least 1"));
        }
        if self.steps > MAX_STEPS {
            return Err(invalid("steps", format!("{} exceeds {MAX_STEPS}", self.steps)));
        }
        if !(0.0..=1.0).contains(&self.ip) {
            return Err(invalid("ip", format!("interaction probability {} is outside [0, 1]", self.ip)));
        }
        if !(0.0..=1.0).contains(&self.gene_loss) {
            return Err(invalid("gene_loss", format!("{} is outside [0, 1]", self.gene_loss)));
        }
        if !(0.0..=100.0).contains(&self.threshold) {
            return Err(invalid("threshold", "must lie in [0, 100]"));
        }
        self.locality_window()?;
        self.check_threads()?;
        let geom = self.world.validate().map_err(|geese_world::ConfigError::Invalid { field, reason }| {
            invalid(&format!("world.{field}"), reason)
        })?;
        self.learner.validate().map_err(|e| invalid("learner", e.to_string()))?;
        if self.perturbations.len() > MAX_SCHEDULED {
            return Err(invalid(
                "perturbations",
                format!("{} scheduled changes exceed {MAX_SCHEDULED}", self.perturbations.len()),
            ));
        }
        for (i, p) in self.perturbations.iter().enumerate() {
            check_max("at", p.at, MAX_STEPS).map_err(|e| invalid(&format!("perturbations[{i}].at"), e.to_string()))?;
            p.change.validate(&geom).map_err(|e| invalid(&format!("perturbations[{i}].change"), e.to_string()))?;
        }
        self.check_switches()?;
        if let Some(s) = self.sample {
            if !(s > 0.0 && s <= 1.0) {
                return Err(invalid("sample", format!("{s} is not in (0, 1]")));
            }
        }
        if self.phase.is_some() && self.algorithm != Algorithm::MultiGeese {
            return Err(invalid("phase", format!("phases belong to multi-geese, not {}", self.algorithm)));
        }
        if self.collect_population.is_some() && self.phase != Some(Phase::Combine) {
            return Err(invalid("collect_population", "is read only by phase = \"combine\""));
        }
        if self.population.is_some() && self.phase.is_some() {
            return Err(invalid("population", "a fixed population has no phase: leave `phase` unset"));
        }
        if let Some(path) = self.population.clone() {
            let pop = read_population(&path)?;
            return self.fixed(&pop, &path.display().to_string());
        }
        let program = match (self.algorithm, self.phase) {
            (Algorithm::MultiGeese, Some(Phase::Combine)) => {
                let Some(path) = self.collect_population.clone() else {
                    return Err(invalid(
                        "collect_population",
                        "phase = \"combine\" starts from a collect population: give its population.json",
                    ));
                };
                let pop = read_population(&path)?;
                let dicts = pop.gene_dicts(self.world.agents).map_err(|e| ConfigError::Population {
                    path: path.display().to_string(),
                    message: e.to_string(),
                })?;
                Program::Learn { algorithm: Algorithm::MultiGeese, phase: Some(Phase::Combine), gene_dicts: dicts }
            }
            (Algorithm::MultiGeese, None) => Program::learn(Algorithm::MultiGeese, Some(Phase::Collect)),
            (a, p) => Program::learn(a, p),
        };
        let follow_up = match (self.algorithm, self.phase, self.sample) {
            (Algorithm::MultiGeese, None, _) => FollowUp::Combine,
            (_, _, Some(_)) => FollowUp::FixedTest,
            _ => FollowUp::None,
        };
        let stage = match (self.algorithm, self.phase) {
            (Algorithm::MultiGeese, Some(Phase::Combine)) => "combine",
            (Algorithm::MultiGeese, Some(Phase::One)) => "one-phase",
            (Algorithm::MultiGeese, _) => "collect",
            _ => "learn",
        };
        let source = format!("of the {} run", self.algorithm);
        self.finish(program, follow_up, stage, &source)
    }

    /// The spec of a validated config running `program`; a member or GeneDict that does
    /// not build is reported as coming from `source`.
    fn finish(
        mut self,
        program: Program,
        follow_up: FollowUp,
        stage: &'static str,
        source: &str,
    ) -> Result<RunSpec, ConfigError> {
        if self.learner.st.is_none() {
            // The algorithm's own ST (Multi-GEESE: the reference code's 10), written
            // into the config so that the manifest shows what ran.
            self.learner.st = Some(self.algorithm.default_st());
        }
        let reach_by_run = self.world.percept_reach.is_none();
        if reach_by_run {
            // Trees that may move and then sense, pick up or drop within one tick need
            // the cells around the agent's (BeTr-GEESE trees hold one action).
            let several_actions = match &program {
                Program::Fixed { .. } => true,
                Program::Learn { algorithm, phase, .. } => {
                    *algorithm == Algorithm::GeeseBt || matches!(phase, Some(Phase::Combine | Phase::One))
                }
            };
            self.world.percept_reach = Some(u32::from(several_actions));
        }
        let locality = self.locality_window()?;
        let name = self.grammar_name();
        let (grammar, text) = load_grammar(&name)?;
        let mut notes = Vec::new();
        for (i, at, to) in self.switches() {
            let lacks: Vec<&str> = to.objects().iter().map(|k| k.name()).filter(|k| !names_object(&text, k)).collect();
            match &program {
                Program::Learn { .. } if !lacks.is_empty() => {
                    return Err(invalid(
                        &format!("perturbations[{i}].change"),
                        format!(
                            "SwitchTask to {to}: grammar {name} cannot express the {to} task (it lacks {}); \
                             learn in a union grammar (leave `grammar` unset, or betr-union-avoid, \
                             geese-bt-union, multi-collect-union, multi-combine-union)",
                            lacks.join(" and ")
                        ),
                    ));
                }
                Program::Fixed { members, .. } => {
                    // An experiment, not an error: the fixed swarm meets a task its
                    // trees may not name (issue 30, "Bad input").
                    let blind = members
                        .iter()
                        .filter(|m| to.objects().iter().any(|k| !names_object(&m.phenotype, k.name())))
                        .count();
                    if blind > 0 {
                        notes.push(format!(
                            "SwitchTask to {to} at step {at}: {blind} of the {} fixed members do not name both of \
                             the {to} task's objects ({}); they meet it with the trees they have",
                            members.len(),
                            to.objects().iter().map(|k| k.name()).collect::<Vec<_>>().join(", ")
                        ));
                    }
                }
                _ => {}
            }
        }
        program
            .prepare(self.program_task())
            .map_err(|e| ConfigError::Population { path: source.into(), message: e.to_string() })?;
        let learner = Arc::new(self.learner.clone());
        Ok(RunSpec {
            config: self,
            grammar_name: name,
            grammar_text: text.into(),
            grammar: Arc::new(grammar),
            learner,
            program: Arc::new(program),
            follow_up,
            stage,
            locality,
            reach_by_run,
            notes,
        })
    }

    /// The fixed run of population `pop` (read from `path`) under this config.
    fn fixed(mut self, pop: &Population, path: &str) -> Result<RunSpec, ConfigError> {
        let perr = |message: String| ConfigError::Population { path: path.into(), message };
        if self.grammar.is_none() {
            self.grammar = Some(pop.grammar.clone());
        }
        let name = self.grammar_name();
        let (_, text) = load_grammar(&name)?;
        pop.check_against(&name, &text, task_name(self.world.task)).map_err(perr)?;
        if let Some(i) =
            self.perturbations.iter().position(|p| p.change == geese_proto::Perturbation::SetLateralTransfer(true))
        {
            return Err(invalid(
                &format!("perturbations[{i}]"),
                "a fixed population has no lateral transfer to switch on",
            ));
        }
        let algorithm = pop.algorithm.unwrap_or(self.algorithm);
        let strategy = self.strategy.or(pop.strategy).unwrap_or(algorithm.default_strategy());
        let members = pop.select(self.sample.unwrap_or(1.0), strategy).map_err(|e| perr(e.to_string()))?;
        self.lateral_transfer = false;
        self.finish(Program::Fixed { strategy, members }, FollowUp::None, "fixed", path)
    }
}

impl RunSpec {
    /// The population this stage's agents ended with (`members` as the runner returned
    /// them), best first.
    pub fn population(&self, mut members: Vec<geese_agent::program::Member>) -> Population {
        members
            .sort_by(|a, b| geese_agent::ge::fitness_cmp(b.fitness.unwrap_or(f64::NAN), a.fitness.unwrap_or(f64::NAN)));
        let c = &self.config;
        let phase = match &*self.program {
            Program::Learn { phase, .. } => *phase,
            Program::Fixed { .. } => None,
        };
        Population {
            grammar: self.grammar_name.clone(),
            strategy: Some(c.strategy.unwrap_or(c.algorithm.default_strategy())),
            algorithm: Some(c.algorithm),
            phase,
            task: Some(task_name(c.world.task).into()),
            members,
        }
    }

    /// The stage after this one, given the population this one ended with.
    pub fn next_stage(&self, pop: &Population) -> Result<Option<RunSpec>, ConfigError> {
        let mut c = self.config.clone();
        if self.reach_by_run {
            // The collect phase's reach (0: one action a tick) must not carry over to a
            // combine phase or a fixed test, whose trees act several times a tick.
            c.world.percept_reach = None;
        }
        match self.follow_up {
            FollowUp::None => Ok(None),
            FollowUp::Combine => {
                c.phase = Some(Phase::Combine);
                c.grammar = None;
                let dicts = pop.gene_dicts(c.world.agents).map_err(|e| ConfigError::Population {
                    path: "of the collect phase".into(),
                    message: e.to_string(),
                })?;
                let follow_up = if c.sample.is_some() { FollowUp::FixedTest } else { FollowUp::None };
                let program =
                    Program::Learn { algorithm: Algorithm::MultiGeese, phase: Some(Phase::Combine), gene_dicts: dicts };
                c.finish(program, follow_up, "combine", "of the collect phase").map(Some)
            }
            FollowUp::FixedTest => {
                // The fixed-agent world of REFERENCE §1.4: paper layout, agents at the hub.
                c.world.layout = geese_world::Layout::Paper;
                c.world.start = None;
                c.phase = None;
                c.grammar = Some(self.grammar_name.clone());
                let from = format!("learned by the {} run", c.algorithm);
                c.fixed(pop, &from).map(Some)
            }
        }
    }
}

/// `foraging` or `nest`.
pub fn task_name(t: Task) -> &'static str {
    match t {
        Task::Foraging => "foraging",
        Task::Nest => "nest",
    }
}

/// Whether `text` (a grammar or a phenotype) names object kind `kind` as a word of its
/// own: `Food` in `CompositeDrop_Food` or `<dobjects>::=Food|Debris`, not in `Foods`.
pub fn names_object(text: &str, kind: &str) -> bool {
    text.split(|c: char| !c.is_ascii_alphanumeric()).any(|w| w == kind)
}

/// Read a population file.
pub fn read_population(path: &Path) -> Result<Population, ConfigError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| ConfigError::Population { path: path.display().to_string(), message: e.to_string() })?;
    Population::from_json(&text)
        .map_err(|message| ConfigError::Population { path: path.display().to_string(), message })
}

/// Load a grammar by built-in name or file path; returns it with its text.
pub fn load_grammar(name: &str) -> Result<(Grammar, String), ConfigError> {
    let text = match grammars::builtin(name) {
        Some(t) => t.to_string(),
        None => std::fs::read_to_string(name).map_err(|e| ConfigError::Grammar {
            name: name.into(),
            message: format!(
                "not a built-in grammar ({}) and not a readable file: {e}",
                grammars::names().collect::<Vec<_>>().join(", ")
            ),
        })?,
    };
    let g = Grammar::parse(&text).map_err(|e| ConfigError::Grammar { name: name.into(), message: e.to_string() })?;
    Ok((g, text))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_key_is_named() {
        let e = RunConfig::from_toml("steps = 5\nbogus = 1\n").unwrap_err();
        assert!(e.contains("bogus"), "{e}");
        let e = RunConfig::from_toml("[world]\ngrid_size = 5\n").unwrap_err();
        assert!(e.contains("grid_size"), "{e}");
    }

    fn invalid_of(c: RunConfig) -> (String, String) {
        match c.validate().map(|_| ()).unwrap_err() {
            ConfigError::Invalid { field, reason } => (field, reason),
            other => panic!("not an invalid value: {other}"),
        }
    }

    #[test]
    fn steps_and_schedules_are_bounded() {
        let ok = |c: RunConfig| c.validate().map(|_| ()).map_err(|e| e.to_string());
        assert_eq!(ok(RunConfig { steps: MAX_STEPS, ..Default::default() }), Ok(()));
        let (f, r) = invalid_of(RunConfig { steps: MAX_STEPS + 1, ..Default::default() });
        assert_eq!((f.as_str(), r.as_str()), ("steps", "10000001 exceeds 10000000"));
        let (f, _) = invalid_of(RunConfig { steps: u64::MAX, ..Default::default() });
        assert_eq!(f, "steps");

        let at = |at, change| Scheduled { at, change };
        let one = |s: Scheduled| RunConfig { perturbations: vec![s], ..Default::default() };
        assert_eq!(ok(one(at(MAX_STEPS, Perturbation::AddObstacles { count: 1000, radius: 100 }))), Ok(()));
        let (f, r) = invalid_of(one(at(5, Perturbation::AddObstacles { count: u32::MAX, radius: 10 })));
        assert_eq!((f.as_str(), r.as_str()), ("perturbations[0].change", "AddObstacles.count 4294967295 exceeds 1000"));
        let (f, r) = invalid_of(one(at(5, Perturbation::AddObstacles { count: 1, radius: 101 })));
        assert_eq!(f, "perturbations[0].change");
        assert!(r.starts_with("AddObstacles.radius 101 exceeds 100"), "{r}");
        let (f, r) = invalid_of(one(at(5, Perturbation::SetIp(f64::NAN))));
        assert_eq!((f.as_str(), r.as_str()), ("perturbations[0].change", "SetIp NaN is not in [0, 1]"));
        let (f, _) = invalid_of(one(at(MAX_STEPS + 1, Perturbation::SetIp(0.5))));
        assert_eq!(f, "perturbations[0].at");
        let many = vec![at(5, Perturbation::SetLateralTransfer(true)); MAX_SCHEDULED + 1];
        let (f, _) = invalid_of(RunConfig { perturbations: many.clone(), ..Default::default() });
        assert_eq!(f, "perturbations");
        assert_eq!(ok(RunConfig { perturbations: many[1..].to_vec(), ..Default::default() }), Ok(()));
    }

    #[test]
    fn world_sizes_are_named_by_key() {
        let mut c = RunConfig::default();
        c.world.agents = 2_000_000;
        let (f, r) = invalid_of(c);
        assert_eq!((f.as_str(), r.as_str()), ("world.agents", "2000000 exceeds 1000000"));
        let mut c = RunConfig::default();
        c.world.width = 20_000;
        assert_eq!(invalid_of(c).0, "world.width");
        assert_eq!(invalid_of(RunConfig { ip: f64::NAN, ..Default::default() }).0, "ip");
    }

    #[test]
    fn the_locality_window_is_checked_and_named() {
        let with = |w: &str, steps| RunConfig { locality: Some(w.into()), steps, ..Default::default() };
        let spec = with("5:20", 30).validate().expect("valid");
        assert_eq!(spec.locality, Some(Window { from: 5, to: 20 }));
        assert_eq!(with("1:30", 30).validate().expect("valid").locality, Some(Window { from: 1, to: 30 }));
        assert_eq!(RunConfig { steps: 5, ..Default::default() }.validate().expect("valid").locality, None);
        for (bad, value) in
            [("5:3", "\"5:3\""), ("a:b", "\"a\""), ("10", "\"10\""), ("0:3", "\"0:3\""), ("1:31", "\"1:31\"")]
        {
            let (f, r) = invalid_of(with(bad, 30));
            assert_eq!(f, "locality", "{bad}: {r}");
            assert!(r.contains(value), "{bad}: {r}");
        }
        let c = RunConfig::from_toml("steps = 40\nlocality = \"2:40\"\n").expect("parses");
        assert_eq!(c.locality_window().expect("valid"), Some(Window { from: 2, to: 40 }));
    }

    #[test]
    fn defaults_are_the_paper() {
        let c = RunConfig::default();
        assert_eq!((c.steps, c.ip, c.learner.st, c.world.grid, c.world.agents), (12_000, 0.85, None, 10, 100));
        let spec = c.validate().expect("valid");
        assert_eq!(spec.config.learner.st, Some(7), "the paper's ST for BeTr-GEESE");
    }

    /// Multi-GEESE runs with the reference code's ST 10 unless the config sets one
    /// (REFERENCE §7.1–7.2, §10.2); GEESE-BT keeps the paper's 7.
    #[test]
    fn st_defaults_by_algorithm_and_a_set_st_wins() {
        let st = |text: &str| RunConfig::from_toml(text).expect("parses").validate().expect("valid").config.learner.st;
        assert_eq!(st("algorithm = \"multi-geese\"\n"), Some(10));
        assert_eq!(st("algorithm = \"geese-bt\"\n"), Some(7));
        assert_eq!(st("algorithm = \"multi-geese\"\n[learner]\nst = 7\n"), Some(7));
        assert_eq!(st("[learner]\nst = 12\n"), Some(12));
    }

    /// `[fidelity]` picks the reference code's step schedule, blackboard and gene objects;
    /// a bad value names itself; a distributed run refuses anything but the defaults,
    /// naming it.
    #[test]
    fn fidelity_parses_and_distributed_runs_refuse_it() {
        let text = "[fidelity]\nschedule = \"sequential\"\nblackboard = \"global\"\ngenes = \"shared\"\n";
        let c = RunConfig::from_toml(text).expect("parses");
        let reference =
            Fidelity { schedule: Schedule::Sequential, blackboard: Blackboard::Global, genes: Genes::Shared };
        assert_eq!(c.fidelity, reference);
        let err = c.fidelity.check_distributed().unwrap_err();
        for key in ["fidelity.schedule", "fidelity.blackboard", "fidelity.genes"] {
            assert!(err.contains(key), "{key}: {err}");
        }
        assert!(Fidelity::default().check_distributed().is_ok());
        let only = Fidelity { blackboard: Blackboard::Global, ..Fidelity::default() };
        assert!(!only.check_distributed().unwrap_err().contains("schedule"));
        let err = RunConfig::from_toml("[fidelity]\nschedule = \"turns\"\n").unwrap_err().to_string();
        assert!(err.contains("turns") && err.contains("sequential"), "{err}");
        // A later stage keeps the run's fidelity.
        let c = RunConfig::from_toml("algorithm = \"multi-geese\"\nsteps = 5\n[fidelity]\nschedule = \"sequential\"\n")
            .expect("parses");
        assert_eq!(c.validate().expect("valid").config.fidelity.schedule, Schedule::Sequential);
    }

    /// A combine phase and a fixed test choose their own percept reach (1: their trees act
    /// several times a tick), not the collect phase's 0 (REFERENCE §1.8; NOTES "Local
    /// model after a move").
    #[test]
    fn later_stages_choose_their_own_percept_reach() {
        let c = RunConfig::from_toml("algorithm = \"multi-geese\"\nsample = 0.5\nsteps = 5\n").expect("parses");
        let collect = c.validate().expect("valid");
        assert_eq!(collect.config.world.percept_reach, Some(0));
        let member = |agent: u32| geese_agent::program::Member {
            phenotype: String::new(),
            genome: None,
            fitness: Some(0.0),
            agent: Some(agent),
            gene_dict: Some(Default::default()),
        };
        let pop = collect.population((0..100).map(member).collect());
        let combine = collect.next_stage(&pop).expect("builds").expect("a combine phase follows");
        assert_eq!((combine.stage, combine.config.world.percept_reach), ("combine", Some(1)));
        let set = RunConfig::from_toml("algorithm = \"multi-geese\"\nsteps = 5\n[world]\npercept_reach = 2\n")
            .expect("parses")
            .validate()
            .expect("valid");
        let combine = set.next_stage(&pop).expect("builds").expect("a combine phase follows");
        assert_eq!(combine.config.world.percept_reach, Some(2), "a reach the user set is kept");
    }
}
