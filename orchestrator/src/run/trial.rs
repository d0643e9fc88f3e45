//! One trial in one process: a world and N learners over the in-memory transport.
//!
//! This is the lock-step loop of DESIGN.md §2 in memory: percepts go to the cell of each
//! live agent, genes to every cell their sender is registered in whose percept is read
//! (at GS 2 an agent is registered in a 3×3 block; [`Mates`]), intents to the world,
//! which resolves them in agent-id order. The distributed runtime drives the
//! very same [`World`] and [`Learner`] code, which is why the two agree step for step.
//!
//! A trial can instead follow the reference code where DESIGN §2 departs from it
//! ([`Fidelity`]): agents taking their turns one after another on the world of the
//! moment, one blackboard for all, and genes shared as objects rather than copied. Only
//! this loop can; a distributed run refuses it.
//!
//! The decide phase of a lock step — every agent's [`Learner::begin_step`] and
//! [`Learner::finish_step`] — runs on [`Workers`] when the trial has more than one
//! thread (`threads`, DESIGN §11): each agent decides from the frozen start-of-step
//! percepts and genes with its own random streams, the genes offered are gathered by
//! cell in agent-id order once every agent has offered, each worker thread keeps its own
//! [`GeneCache`] (scratch buffers and a memo, so which thread ran an agent changes
//! nothing) and mostly steps the same range of agents, and the world applies the
//! intents in agent-id order as before. The trajectory is therefore the same for every
//! thread count.
//!
//! [`Fidelity`]: crate::run::config::Fidelity
use crate::run::config::{Blackboard, Genes, RunSpec, Schedule};
use geese_agent::program::Member;
use geese_agent::view::KindMap;
use geese_agent::{FitnessCell, GeneCache, GeneRef, Learner, SharedGene};
use geese_proto::{CellIdx, GeneMsg, Intent, Percept, StepReport};
use geese_world::world::MoveHint;
use geese_world::World;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};

/// What a finished trial amounts to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrialSummary {
    pub seed: u64,
    pub steps: u64,
    pub final_task_pct: f64,
    pub max_task_pct: f64,
    /// First step whose task % reached the threshold.
    pub first_step_at_threshold: Option<u64>,
    /// Task % exceeded the threshold at some step.
    pub success: bool,
    pub genetic_steps: u64,
    pub stagnation_steps: u64,
    pub wall_seconds: f64,
    /// The step after which the run's first `SwitchTask` applied (issue 30.4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub switched_after: Option<u64>,
    /// Steps from that switch until the new task first reached the threshold: the
    /// recovery time of a change of task (None: not reached, or no switch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps_to_threshold_after_switch: Option<u64>,
}

impl TrialSummary {
    /// An empty summary for a trial of run seed `seed`.
    pub fn new(seed: u64) -> Self {
        TrialSummary {
            seed,
            steps: 0,
            final_task_pct: 0.0,
            max_task_pct: 0.0,
            first_step_at_threshold: None,
            success: false,
            genetic_steps: 0,
            stagnation_steps: 0,
            wall_seconds: 0.0,
            switched_after: None,
            steps_to_threshold_after_switch: None,
        }
    }

    /// A summary that also measures the recovery from the first task switch of
    /// `perturbations` (the metric of issue 30.4), on every transport alike.
    pub fn for_run(seed: u64, perturbations: &[crate::run::config::Scheduled]) -> Self {
        let switched_after = perturbations
            .iter()
            .filter(|p| matches!(p.change, geese_proto::Perturbation::SwitchTask(_)))
            .map(|p| p.at)
            .min();
        TrialSummary { switched_after, ..TrialSummary::new(seed) }
    }

    /// Fold one step report in; every driver (in-process, Zenoh) keeps it this way.
    pub fn record(&mut self, threshold: f64, rep: &StepReport) {
        self.steps = rep.step;
        self.final_task_pct = rep.task_pct;
        self.max_task_pct = self.max_task_pct.max(rep.task_pct);
        if self.first_step_at_threshold.is_none() && rep.task_pct >= threshold {
            self.first_step_at_threshold = Some(rep.step);
        }
        if let Some(at) = self.switched_after {
            if self.steps_to_threshold_after_switch.is_none() && rep.step > at && rep.task_pct >= threshold {
                self.steps_to_threshold_after_switch = Some(rep.step - at);
            }
        }
        self.success |= rep.task_pct > threshold;
        self.genetic_steps += rep.genetic_steps as u64;
        self.stagnation_steps += rep.stagnation_steps as u64;
    }
}

/// Why a trial cannot start.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error(transparent)]
    World(#[from] geese_world::ConfigError),
    #[error("agents: {0}")]
    Agents(String),
    #[error("threads: {0}")]
    Threads(String),
}

/// A finished stage of a run: its summary and the population its agents ended with.
#[derive(Clone, Debug)]
pub struct Ran {
    pub summary: TrialSummary,
    /// One member per agent, in agent order.
    pub members: Vec<Member>,
}

/// A world and its learners, stepped in lock-step.
pub struct Trial {
    pub world: World,
    pub agents: Vec<Learner>,
    /// The gene each agent offers this step, by agent id. Kept from step to step, so
    /// that last step's offers are dropped by the thread that made them, as it writes
    /// this step's.
    offered: Vec<Option<GeneMsg>>,
    intents: Vec<Option<Intent>>,
    gene_cache: GeneCache,
    threshold: f64,
    summary: TrialSummary,
    schedule: Schedule,
    /// The swarm's one blackboard, if it has one (`fidelity.blackboard = global`),
    /// swapped into each agent for its tick ([`with_board`]).
    board: Option<KindMap>,
    /// Scratch: the genes a sequential turn's cell-mates offer, with their fitness
    /// fields when genes are shared objects.
    offers: Vec<SharedGene>,
    /// Genes are shared objects (`fidelity.genes = shared`, [`Learner::share_genes`]).
    shared_genes: bool,
    /// The decide phase's threads, when there is more than one.
    workers: Option<Workers>,
    /// Which percept each cell's agents read this step.
    reading: Reading,
}

/// The percepts of one step by cell: a slot per cell of the arena holding the index of
/// its percept among the step's (ascending by cell), kept from step to step and
/// emptied after each. Finding the percept of every agent, and every cell a gene is
/// published to, was a binary search over the step's percepts: with 10,000 sparse
/// agents on 2 threads 4 % of the wall time, on the one thread that runs between the
/// parallel phases.
#[derive(Debug, Default)]
struct Reading {
    slot: Vec<u32>,
    /// The cells with a percept, ascending.
    cells: Vec<CellIdx>,
    /// Scratch for finding them ([`World::occupied_cells_into`]).
    seen: Vec<bool>,
}

impl Reading {
    const NONE: u32 = u32::MAX;

    /// Read the percepts of the cells of the live agents of `world` (`of_body`, the cell
    /// of each body, [`World::body_cell`]): their cells, ascending, each once.
    fn start(&mut self, world: &World, of_body: &[Option<CellIdx>]) -> &[CellIdx] {
        self.end();
        let cell_count = world.geometry().cell_count();
        if self.slot.len() != cell_count {
            self.slot = vec![Self::NONE; cell_count];
        }
        world.occupied_cells_into(of_body.iter().copied(), &mut self.seen, &mut self.cells);
        for (i, &c) in self.cells.iter().enumerate() {
            self.slot[c as usize] = i as u32;
        }
        &self.cells
    }

    /// The index of the percept of `cell`, if it has one this step.
    fn percept(&self, cell: CellIdx) -> Option<usize> {
        self.slot.get(cell as usize).filter(|&&i| i != Self::NONE).map(|&i| i as usize)
    }

    /// The index of the percept a body in `cell` reads (`None` for a dead agent): one
    /// rule for the one-thread and the parallel step.
    fn percept_of_body(&self, cell: Option<CellIdx>) -> Option<usize> {
        cell.and_then(|c| self.percept(c))
    }

    /// Forget the step's percepts.
    fn end(&mut self) {
        for &c in &self.cells {
            self.slot[c as usize] = Self::NONE;
        }
        self.cells.clear();
    }
}

/// A thread pool for the decide phase, with one [`GeneCache`] per pool thread.
///
/// Each pool thread steps the same contiguous range of agents in every phase
/// ([`Workers::share`]), so what one phase writes of an agent the next reads from the
/// same core's caches (handing agents to whichever thread was free made 10,000 sparse
/// agents 2–5 % slower). A thread that has finished its range then takes runs of
/// [`AGENTS_PER_TASK`] agents from the end of the others': an agent's step costs a
/// genetic step or not, and with fixed halves the slower half of 10,000 sparse agents
/// took 4.6 % longer every step while the other thread waited.
struct Workers {
    pool: rayon::ThreadPool,
    /// By pool thread index; a thread locks only its own.
    caches: Vec<Mutex<GeneCache>>,
}

/// Agents stepped as one task of the decide phase: enough to make a task's overhead
/// small, few enough that the threads finish the phase together.
const AGENTS_PER_TASK: usize = 64;

impl Workers {
    fn new(threads: usize) -> Result<Workers, SetupError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("geese-trial-{i}"))
            .build()
            .map_err(|e| SetupError::Threads(format!("cannot start {threads} threads: {e}")))?;
        Ok(Workers { pool, caches: (0..threads).map(|_| Mutex::new(GeneCache::new())).collect() })
    }

    fn threads(&self) -> usize {
        self.caches.len()
    }

    /// Run `f` on every task of `tasks` once, on the pool threads, with the
    /// [`GeneCache`] of the thread that runs it. The tasks are split into one
    /// contiguous block per thread; a thread runs its own block from the front, then
    /// takes the tasks left in the other blocks from their ends.
    fn share<T: Send>(&self, tasks: impl IntoIterator<Item = T>, f: impl Fn(T, &mut GeneCache) + Sync) {
        let slots: Vec<Mutex<Option<T>>> = tasks.into_iter().map(|t| Mutex::new(Some(t))).collect();
        let block = slots.len().div_ceil(self.threads()).max(1);
        let blocks: Vec<&[Mutex<Option<T>>]> = slots.chunks(block).collect();
        let take = |s: &Mutex<Option<T>>| s.lock().unwrap_or_else(|e| e.into_inner()).take();
        self.pool.broadcast(|ctx| {
            let me = ctx.index();
            let mut cache = self.caches[me % self.caches.len()].lock().unwrap_or_else(|e| e.into_inner());
            let own = blocks.get(me).copied().unwrap_or_default();
            for s in own {
                if let Some(t) = take(s) {
                    f(t, &mut cache);
                }
            }
            for (k, other) in blocks.iter().enumerate() {
                if k != me {
                    for s in other.iter().rev() {
                        match take(s) {
                            Some(t) => f(t, &mut cache),
                            // Its owner has reached it: the rest of the block is done.
                            None => break,
                        }
                    }
                }
            }
        });
    }

    /// Run `f` once on every pool thread, thread `i` with `parts[i]` (a part per thread
    /// at most; a thread without one does nothing).
    fn each<T: Send>(pool: &rayon::ThreadPool, parts: impl IntoIterator<Item = T>, f: impl Fn(T) + Sync) {
        let slots: Vec<Mutex<Option<T>>> = parts.into_iter().map(|p| Mutex::new(Some(p))).collect();
        pool.broadcast(|ctx| {
            let part = slots.get(ctx.index()).and_then(|s| s.lock().unwrap_or_else(|e| e.into_inner()).take());
            if let Some(part) = part {
                f(part);
            }
        });
    }
}

impl Trial {
    /// Build the world and agents of `spec`.
    pub fn new(spec: &RunSpec) -> Result<Trial, SetupError> {
        let cfg = &spec.config;
        let mut world = World::new(cfg.world.clone(), cfg.seed)?;
        world.set_regime(cfg.regime());
        for p in &cfg.perturbations {
            world.schedule(p.at, p.change.clone());
        }
        if let Some(w) = spec.locality {
            world.record_locality(w);
        }
        let geom = world.geometry();
        let hub = world.hub();
        let prepared = spec.program.prepare(cfg.program_task()).map_err(|e| SetupError::Agents(e.to_string()))?;
        let shared_genes = cfg.fidelity.genes == Genes::Shared;
        let agents = (0..cfg.world.agents)
            .map(|id| {
                let role = prepared.role(id, cfg.seed);
                let mut a =
                    Learner::with_role(id, spec.learner.clone(), spec.grammar.clone(), geom, hub, cfg.seed, role)
                        .map_err(|e| SetupError::Agents(format!("agent {id}: {e}")))?;
                if shared_genes {
                    a.share_genes();
                }
                Ok(a)
            })
            .collect::<Result<_, SetupError>>()?;
        // A follow-up stage may have fewer agents than the run's threads.
        let threads = cfg.threads.unwrap_or(1).clamp(1, cfg.world.agents.max(1)) as usize;
        let workers = if threads > 1 { Some(Workers::new(threads)?) } else { None };
        Ok(Trial {
            offered: vec![None; cfg.world.agents as usize],
            intents: vec![None; cfg.world.agents as usize],
            gene_cache: GeneCache::new(),
            threshold: cfg.threshold,
            summary: TrialSummary::for_run(cfg.seed, &cfg.perturbations),
            schedule: cfg.fidelity.schedule,
            board: (cfg.fidelity.blackboard == Blackboard::Global).then(KindMap::default),
            offers: Vec::new(),
            shared_genes,
            workers,
            reading: Reading::default(),
            world,
            agents,
        })
    }

    /// Run one step and return its report.
    pub fn step(&mut self) -> StepReport {
        let rep = match self.schedule {
            Schedule::Simultaneous => self.lock_step(),
            Schedule::Sequential => self.turns(),
        };
        self.record(&rep);
        rep
    }

    /// One lock-step step (DESIGN §2), with one blackboard for all agents if `fidelity`
    /// asks for it.
    fn lock_step(&mut self) -> StepReport {
        if self.workers.is_some() {
            return self.parallel_lock_step();
        }
        let world = &self.world;
        let of_body: Vec<Option<CellIdx>> = world.bodies().iter().map(|b| world.body_cell(b)).collect();
        let percepts: Vec<Percept> = self.reading.start(world, &of_body).iter().map(|&c| world.percept(c)).collect();
        let cells = percept_of_each(&self.reading, &of_body);
        for ((agent, cell), offer) in self.agents.iter_mut().zip(&cells).zip(self.offered.iter_mut()) {
            *offer = cell.and_then(|pi| agent.begin_step(&percepts[pi]));
        }
        let mates = Mates::gather(&percepts, &self.offered);
        // Shared gene objects: each offered gene's fitness field as its sender held it
        // when it offered it.
        let fields: Option<Vec<_>> =
            self.shared_genes.then(|| self.agents.iter().map(|a| a.gene_cell().cloned()).collect());
        for ((agent, cell), slot) in self.agents.iter_mut().zip(&cells).zip(self.intents.iter_mut()) {
            agent.reuse_ops(slot.take());
            *slot = cell.map(|pi| {
                let genes = mates.of(pi);
                with_board(&mut self.board, agent, |a| match &fields {
                    None => a.finish_step(genes, &mut self.gene_cache),
                    Some(fields) => finish_holding(a, genes, &self.offered, fields, &mut self.gene_cache),
                })
            });
        }
        drop(mates);
        self.world.resolve(&self.intents)
    }

    /// [`Trial::lock_step`] with the decide phase on the [`Workers`]: the same inputs to
    /// every agent and the same order of publication, so the same step.
    fn parallel_lock_step(&mut self) -> StepReport {
        let Trial { world, agents, offered, intents, workers, reading, .. } = self;
        let Some(w) = workers else { unreachable!("parallel_lock_step runs only with workers") };
        let of_body: Vec<Option<CellIdx>> =
            w.pool.install(|| world.bodies().par_iter().map(|b| world.body_cell(b)).collect());
        let occupied = reading.start(world, &of_body);
        let percepts: Vec<Percept> = w.pool.install(|| occupied.par_iter().map(|&c| world.percept(c)).collect());
        let reading = &*reading;
        let cells: Vec<Option<usize>> =
            w.pool.install(|| of_body.par_iter().map(|&c| reading.percept_of_body(c)).collect());
        let n = AGENTS_PER_TASK;
        let percepts = &percepts;
        w.share(
            agents.chunks_mut(n).zip(offered.chunks_mut(n)).zip(cells.chunks(n)),
            |((agents, offers), cells), _| {
                for ((agent, offer), cell) in agents.iter_mut().zip(offers).zip(cells) {
                    *offer = cell.and_then(|pi| agent.begin_step(&percepts[pi]));
                }
            },
        );
        // Each worker gathers the genes of a range of percepts.
        let offered = &*offered;
        let per = percepts.len().div_ceil(w.threads()).max(1);
        let mut mates: Vec<Option<Mates>> = (0..w.threads()).map(|_| None).collect();
        Workers::each(&w.pool, percepts.chunks(per).zip(mates.iter_mut()), |(percepts, out)| {
            *out = Some(Mates::gather(percepts, offered));
        });
        let mates: Vec<Mates> = mates.into_iter().flatten().collect();
        let mates = &mates;
        // Each worker also computes where its agents' first moves go, which the world
        // would otherwise compute on the one thread that applies the intents.
        let mut hints: Vec<Option<MoveHint>> = vec![None; agents.len()];
        let frozen = &*world;
        w.share(
            agents.chunks_mut(n).zip(intents.chunks_mut(n)).zip(hints.chunks_mut(n)).zip(cells.chunks(n)),
            |(((agents, slots), hints), cells), cache| {
                for (((agent, slot), hint), cell) in agents.iter_mut().zip(slots).zip(hints).zip(cells) {
                    agent.reuse_ops(slot.take());
                    *slot = cell.map(|pi| agent.finish_step(mates[pi / per].of(pi % per), cache));
                    *hint = slot.as_ref().and_then(|i| frozen.move_hint(i));
                }
            },
        );
        world.resolve_hinted(intents, &hints)
    }

    /// One step of agents taking turns in id order (REFERENCE §1.8, §9.3), with one
    /// blackboard for all if `fidelity` asks (§2.2). Each agent reads the percept of its
    /// cell when its turn comes, ticks, then takes the genes of the agents registered in
    /// the cell its own moves took it to, as they stand then (agents before it may
    /// already hold this step's new ones, REFERENCE §6.2 step 6); its intent is applied
    /// before the next agent's turn.
    fn turns(&mut self) -> StepReport {
        let Trial { world, agents, gene_cache, board, offers, .. } = self;
        let geom = world.geometry();
        world.resolve_by(|w, id| {
            let me = id as usize;
            let percept = w.percept(geom.cell_of(w.bodies().get(me)?.pos));
            let step = percept.step;
            let (before, rest) = agents.split_at_mut(me);
            let (agent, after) = rest.split_first_mut()?;
            let _ = agent.begin_step(&percept);
            // Cell-mates after the agent's own moves: those registered in that cell as
            // the agents before it left the world (REFERENCE §6.2 step 6).
            let intent = with_board(board, agent, |a| {
                a.finish_step_with(gene_cache, |expected, cell| {
                    expected.clear();
                    expected.extend(w.agents_in(cell).filter(|a| a.id != id && a.live && a.learning).map(|a| a.id));
                    expected.sort_unstable();
                    offers.clear();
                    for &mate in expected.iter() {
                        let m = mate as usize;
                        let other = if m < me { before.get(m) } else { after.get(m - me - 1) };
                        offers.extend(other.map(|a| SharedGene { msg: a.offer(step), cell: a.gene_cell().cloned() }));
                    }
                    &offers[..]
                })
            });
            Some(intent)
        })
    }

    fn record(&mut self, rep: &StepReport) {
        self.summary.record(self.threshold, rep);
    }

    pub fn summary(&self) -> &TrialSummary {
        &self.summary
    }

    /// Every agent as a population member, in agent order.
    pub fn members(&self) -> Vec<Member> {
        self.agents.iter().map(Learner::member).collect()
    }
}

/// Which percept each agent reads, by agent id: the index among the step's percepts
/// of the cell its body is in (`of_body`); `None` for a dead agent.
fn percept_of_each(reading: &Reading, of_body: &[Option<CellIdx>]) -> Vec<Option<usize>> {
    of_body.iter().map(|&c| reading.percept_of_body(c)).collect()
}

/// [`Learner::finish_step`] with the cell-mates' genes as shared gene objects: each
/// offered message (`offered`, by agent id) with its sender's fitness field (`fields`,
/// by agent id). Out of line, so the default lock step (copied genes) keeps its own code.
#[cold]
#[inline(never)]
fn finish_holding(
    agent: &mut Learner,
    genes: &[GeneRef],
    offered: &[Option<GeneMsg>],
    fields: &[Option<Arc<FitnessCell>>],
    cache: &mut GeneCache,
) -> Intent {
    let held: Vec<SharedGene> = genes
        .iter()
        .filter_map(|g| {
            let msg = offered.get(g.from as usize)?.clone()?;
            Some(SharedGene { msg, cell: fields.get(g.from as usize).cloned().flatten() })
        })
        .collect();
    agent.finish_step(&held, cache)
}

/// Run `f` on `agent` with the swarm's one blackboard in place of its own, if the trial
/// has one (REFERENCE §2.2), and give the board back afterwards.
fn with_board<T>(board: &mut Option<KindMap>, agent: &mut Learner, f: impl FnOnce(&mut Learner) -> T) -> T {
    let Some(board) = board else { return f(agent) };
    agent.swap_blackboard(board);
    let out = f(agent);
    agent.swap_blackboard(board);
    out
}

/// The genes the agents of each of a run of percepts receive: the genes offered by the
/// agents registered in the percept's cell ([`Percept::agents`]), in agent-id order.
///
/// That is the lateral-transfer rule the distributed runtime routes by
/// ([`geese_proto::rules::for_each_gene_cell`]: a gene goes to every cell its sender is
/// registered in whose percept is read) seen from the receiving end: both follow the
/// world's registration of agents in the cells of their neighbourhood, and the parity
/// tests hold the two runtimes to the same steps. Reading the senders off the percepts
/// replaces per-cell mailboxes, which the one thread between the parallel phases filled
/// and emptied: 4 % of the wall time of 10,000 sparse agents on 2 threads.
struct Mates<'a> {
    genes: Vec<GeneRef<'a>>,
    /// Where the genes of each percept start in `genes`, and then where the last end.
    starts: Vec<u32>,
}

impl<'a> Mates<'a> {
    /// The genes of `percepts`, from the offers by agent id.
    fn gather(percepts: &[Percept], offered: &'a [Option<GeneMsg>]) -> Mates<'a> {
        let mut m = Mates { genes: Vec::with_capacity(percepts.len()), starts: Vec::with_capacity(percepts.len() + 1) };
        for p in percepts {
            m.starts.push(m.genes.len() as u32);
            m.genes.extend(p.agents.iter().filter_map(|a| offered.get(a.id as usize)?.as_ref()).map(GeneRef::of));
        }
        m.starts.push(m.genes.len() as u32);
        m
    }

    /// The genes of the `k`-th percept.
    fn of(&self, k: usize) -> &[GeneRef<'a>] {
        &self.genes[self.starts[k] as usize..self.starts[k + 1] as usize]
    }
}

pub fn run_trial(spec: &RunSpec, mut observe: impl FnMut(&StepReport)) -> Result<Ran, SetupError> {
    let start = std::time::Instant::now();
    let mut t = Trial::new(spec)?;
    for _ in 0..spec.config.steps {
        let rep = t.step();
        observe(&rep);
    }
    let mut summary = t.summary.clone();
    summary.wall_seconds = start.elapsed().as_secs_f64();
    Ok(Ran { summary, members: t.members() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::config::{Fidelity, RunConfig};
    use geese_agent::program::{FixedMember, Program, Strategy};
    use geese_proto::Pos;

    /// Two fixed agents (member i for agent i) in a foraging world with one food item at
    /// the site, agent 0 in the site's cell and agent 1 at `one`.
    fn pair(fidelity: Fidelity, members: [&str; 2], one: Pos) -> Trial {
        let mut cfg = RunConfig { steps: 1, seed: 3, fidelity, ..Default::default() };
        cfg.world.agents = 2;
        cfg.world.items = Some(1);
        let mut spec = cfg.validate().expect("valid");
        let members = members.iter().map(|p| FixedMember { phenotype: (*p).into(), gene_dict: None }).collect();
        spec.program = Arc::new(Program::Fixed { strategy: Strategy::TopAgents, members });
        let mut t = Trial::new(&spec).expect("trial builds");
        let site = spec.config.world.site;
        t.world.place_agent(0, site, 0.0);
        t.world.place_agent(1, one, 0.0);
        t
    }

    const CARRY_THEN_EXPLORE: &str =
        "[Sequence][Act]CompositeSingleCarry_Food[/Act][Act]Explore_0_Normal[/Act][/Sequence]";

    /// Simultaneous steps: both agents see the one item and reach for it; the world gives
    /// it to agent 0, and agent 1's move (at the pace of a carrier it is not) is refused.
    /// Sequential turns: agent 1 looks after agent 0 has taken it, finds nothing, and its
    /// tree stops before exploring (heading unchanged, nothing refused).
    #[test]
    fn sequential_turns_see_the_item_an_earlier_agent_took() {
        let fidelity = |schedule| Fidelity { schedule, ..Fidelity::default() };
        let site = RunConfig::default().world.site;
        for (schedule, refused) in [(Schedule::Simultaneous, 1), (Schedule::Sequential, 0)] {
            let mut t = pair(fidelity(schedule), [CARRY_THEN_EXPLORE; 2], site);
            let rep = t.step();
            let b = t.world.bodies();
            assert_eq!((b[0].carrying.len(), b[1].carrying.len()), (1, 0), "{schedule:?}");
            assert_eq!(rep.rejected, refused, "{schedule:?}");
            assert_eq!(b[1].heading == 0.0, schedule == Schedule::Sequential, "{schedule:?}: agent 1's heading");
        }
    }

    /// One blackboard for all: agent 1, far from any food, reads the food agent 0 sensed
    /// at the site a moment before (IsCarryable reads the blackboard, REFERENCE §2.3) and
    /// explores; with its own blackboard it knows of no food and stays put.
    #[test]
    fn a_global_blackboard_carries_what_one_agent_sensed_to_the_next() {
        let sense = "[Sequence][PostCnd]NeighbourObjects_Food[/PostCnd][/Sequence]";
        let gated = "[Sequence][PreCnd]IsCarryable_Food[/PreCnd][Act]Explore_0_Normal[/Act][/Sequence]";
        let far = Pos::new(-35, -35);
        for schedule in [Schedule::Simultaneous, Schedule::Sequential] {
            for (blackboard, moves) in [(Blackboard::PerAgent, false), (Blackboard::Global, true)] {
                let mut t = pair(Fidelity { schedule, blackboard, ..Fidelity::default() }, [sense, gated], far);
                t.step();
                assert_eq!(t.world.bodies()[1].pos != far, moves, "{schedule:?}, {blackboard:?}");
            }
        }
    }

    /// Shared gene objects (`fidelity.genes = shared`, REFERENCE §6.6): under either
    /// schedule, an agent that adopted a cell-mate's gene from its pool holds the very
    /// fitness field of the donor, so in a 100-agent run two agents come to share one
    /// (seed 5: at step 257 with simultaneous steps, 1,852 with turns, where a mate that
    /// already took its turn offers the gene it just adopted, at fitness 0); with copied
    /// genes (the default) no agent holds a field at all.
    #[test]
    fn shared_genes_end_up_held_by_several_agents() {
        let sharing = |t: &Trial| {
            let cells: Vec<_> = t.agents.iter().filter_map(|a| a.gene_cell()).collect();
            let shared = cells.iter().enumerate().any(|(i, c)| cells[..i].iter().any(|d| Arc::ptr_eq(c, d)));
            (cells.len(), shared)
        };
        for schedule in [Schedule::Simultaneous, Schedule::Sequential] {
            for (genes, steps) in [(Genes::Copied, 50), (Genes::Shared, 2_500)] {
                let cfg = RunConfig {
                    steps,
                    seed: 5,
                    fidelity: Fidelity { schedule, genes, ..Fidelity::default() },
                    ..Default::default()
                };
                let agents = cfg.world.agents as usize;
                let mut t = Trial::new(&cfg.validate().expect("valid")).expect("trial builds");
                let mut seen = (0, false);
                for _ in 0..steps {
                    t.step();
                    seen = sharing(&t);
                    if seen.1 {
                        break;
                    }
                }
                let want = match genes {
                    Genes::Copied => (0, false),
                    Genes::Shared => (agents, true),
                };
                assert_eq!(seen, want, "{schedule:?}, {genes:?}");
                for a in &t.agents {
                    assert_eq!(a.member().fitness, Some(a.fitness()));
                }
            }
        }
    }

    /// The genes read off the percepts ([`Mates`]) are those that publishing each offer
    /// to the cells the distributed runtime routes it to
    /// ([`geese_proto::rules::for_each_gene_cell`]) gives, in the same order, at GS 2
    /// (agents registered in 3×3 blocks) and at GS 10, with agents crowded and spread,
    /// some of them offering nothing, and over percepts split into runs as the workers
    /// split them.
    #[test]
    fn genes_read_off_the_percepts_are_those_routed_to_the_cell() {
        use geese_proto::rules::for_each_gene_cell;
        use geese_proto::GeneMapping;
        let mut checked = 0;
        for (grid, width) in [(2, 80), (10, 100), (10, 400)] {
            let mut cfg = RunConfig { steps: 1, seed: 13, ..Default::default() };
            cfg.world.agents = 300;
            cfg.world.grid = grid;
            (cfg.world.width, cfg.world.height) = (width, width);
            let spec = cfg.validate().expect("valid");
            let mut world = World::new(spec.config.world.clone(), 13).expect("world builds");
            let half = width / 2;
            for id in 0..300u32 {
                let (x, y) = ((id as i32 * 37) % width - half, (id as i32 * 91) % width - half);
                world.place_agent(id, Pos::new(x, y), 0.0);
            }
            let offered: Vec<Option<GeneMsg>> = (0..300u32)
                .map(|id| {
                    (id % 7 != 3).then(|| GeneMsg {
                        step: 0,
                        from: id,
                        genome: Arc::from([id]),
                        fitness: 0.0,
                        mapping: GeneMapping::default(),
                    })
                })
                .collect();
            let percepts = world.percepts();
            let geom = world.geometry();
            let mut routed: std::collections::HashMap<CellIdx, Vec<u32>> = Default::default();
            for (b, g) in world.bodies().iter().zip(&offered) {
                if let (Some(g), true) = (g, b.live) {
                    let read = |c| percepts.iter().any(|p| p.cell == c);
                    for_each_gene_cell(&geom, b.pos, read, |c| routed.entry(c).or_default().push(g.from));
                }
            }
            for per in [1, 7, percepts.len()] {
                for (k, run) in percepts.chunks(per).enumerate() {
                    let mates = Mates::gather(run, &offered);
                    for (i, p) in run.iter().enumerate() {
                        let got: Vec<u32> = mates.of(i).iter().map(|g| g.from).collect();
                        assert_eq!(got, routed.get(&p.cell).cloned().unwrap_or_default(), "GS {grid}, run {k}");
                        checked += got.len();
                    }
                }
            }
        }
        assert!(checked > 1000, "{checked} genes checked");
    }

    /// At GS 2 an agent (radius 3) is registered in a 3×3 block of cells, so a neighbour
    /// centred in the next cell is registered in the agent's own cell and shows in its
    /// percept; lateral transfer takes its gene (REFERENCE §6.2), none is lost.
    #[test]
    fn at_gs_2_a_neighbour_centred_next_door_gives_its_gene() {
        let mut cfg = RunConfig { steps: 1, seed: 11, ip: 1.0, ..Default::default() };
        cfg.world.agents = 3;
        cfg.world.grid = 2;
        let mut t = Trial::new(&cfg.validate().expect("valid")).expect("world builds");
        // 0 and 1 in neighbouring cells; 2 three cells away, registered in neither's.
        let (a, b, far) = (Pos::new(0, 0), Pos::new(2, 0), Pos::new(-6, 0));
        for (id, p) in [(0, a), (1, b), (2, far)] {
            t.world.place_agent(id, p, 0.0);
        }
        let geom = t.world.geometry();
        assert_ne!(geom.cell_of(a), geom.cell_of(b));
        let percepts = t.world.percepts();
        let mates = |c| percepts.iter().find(|p| p.cell == c).map(|p| p.agents.iter().map(|x| x.id).collect());
        assert_eq!(mates(geom.cell_of(a)), Some(vec![0, 1]));
        assert_eq!(mates(geom.cell_of(b)), Some(vec![0, 1]));
        let rep = t.step();
        assert_eq!(rep.genes_lost, 0);
        // IP 1: agents 0 and 1 each keep both genes, agent 2 its own only.
        assert_eq!((rep.lt_mean, rep.lt_std), (1.67, 0.47));
    }
}
