//! Experimental conditions: the named knobs a campaign grid varies, and how one condition
//! turns a base [`RunConfig`] into the configuration of a trial.
//!
//! A knob is either a world-build setting (arena size, grid size, sites, agents, initial
//! obstacles), an initial regime setting (IP, gene loss, grammar, ST) or a perturbation
//! scheduled at a step (obstacles added, IP changed, lateral transfer off for Δ steps,
//! agents killed). Perturbations become entries of [`RunConfig::perturbations`], which the
//! trial hands to `World::schedule` — the same call on every transport, so a condition
//! means the same thing in-process and over Zenoh (DESIGN.md §2 step 4).
//!
//! Knob values are checked here, by knob name, so that a bad campaign file is reported
//! as `grid[1].ip: 1.5 is outside [0, 1]` rather than as a failed trial.
use crate::run::config::{RunConfig, Scheduled};
use geese_proto::Perturbation;
use geese_world::{Layout, Task};
use serde::{Deserialize, Serialize};
use std::fmt;

/// Reference code's lateral-transfer pause after an object addition (REFERENCE §1.8).
pub const DEFAULT_STOP_INTERVAL: u64 = 1000;

/// One value of a knob.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Level {
    Int(i64),
    Float(f64),
    Text(String),
}

impl Level {
    /// Numeric value, if the level is a number.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Level::Int(v) => Some(*v as f64),
            Level::Float(v) => Some(*v),
            Level::Text(_) => None,
        }
    }
}

impl fmt::Display for Level {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Level::Int(v) => write!(f, "{v}"),
            Level::Float(v) => write!(f, "{v}"),
            Level::Text(s) => f.write_str(s),
        }
    }
}

/// What a knob's values look like.
#[derive(Clone, Copy, Debug)]
enum Kind {
    /// Integer in [min, max].
    Int(i64, i64),
    /// Real number in [min, max].
    Float(f64, f64),
    Text,
}

macro_rules! knobs {
    ($($(#[doc = $doc:literal])* $variant:ident = $name:literal : $kind:expr,)*) => {
        /// A setting a campaign grid may vary. The declaration order is the canonical
        /// order of a condition's label.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        pub enum Knob { $($(#[doc = $doc])* $variant,)* }

        impl Knob {
            pub const ALL: &'static [Knob] = &[$(Knob::$variant,)*];

            /// The key as written in a campaign file.
            pub fn name(self) -> &'static str {
                match self { $(Knob::$variant => $name,)* }
            }

            fn kind(self) -> Kind {
                match self { $(Knob::$variant => $kind,)* }
            }
        }
    };
}

const STEP_MAX: i64 = 100_000_000;

knobs! {
    /// Learning algorithm: betr-geese, geese-bt or multi-geese (Figs. 3, 8, 9).
    Algorithm = "algorithm": Kind::Text,
    /// Fitness terms of the learners, e.g. `E+B`, `D+E+C+F` (Fig. 3).
    Terms = "terms": Kind::Text,
    /// How the Multi-GEESE combine phase learns: faithful, delivery, keep-deliverers,
    /// delivery-keep, patient, patient-delivery (issue 30.1).
    Fusion = "fusion": Kind::Text,
    /// Multi-GEESE phase: unset runs collect then combine; `one` is one-phase fusion
    /// (issue 30.2); `collect` runs the collect phase alone.
    Phase = "phase": Kind::Text,
    /// Fixed-population test: this fraction of the best members (of `population`, or
    /// of the population the trial's own learning run ended with; Figs. 8b, 9).
    Sample = "sample": Kind::Float(0.0, 1.0),
    /// A fixed population file to run (`{task}` stands for the task; Fig. 10).
    Population = "population": Kind::Text,
    /// How a fixed population is handed out: parallel or top-agents.
    Strategy = "strategy": Kind::Text,
    /// Grammar name or file; `{task}` is replaced by `foraging`/`nest`
    /// (e.g. `betr-{task}-addition`, the Normal|Avoid grammar of Sec. 5 addition).
    Grammar = "grammar": Kind::Text,
    /// Interaction probability IP (from the start, or from `ip_at` on).
    Ip = "ip": Kind::Float(0.0, 1.0),
    /// Step after which `ip` replaces the base IP.
    IpAt = "ip_at": Kind::Int(0, STEP_MAX),
    /// Storage threshold ST.
    St = "st": Kind::Int(4, 10_000),
    /// Number of agents N.
    Agents = "agents": Kind::Int(1, 1_000_000),
    /// Receiver-side gene message loss rate (from the start, or from `gene_loss_at` on).
    GeneLoss = "gene_loss": Kind::Float(0.0, 1.0),
    GeneLossAt = "gene_loss_at": Kind::Int(0, STEP_MAX),
    /// Lateral transfer switched off after this step ...
    LtOffAt = "lt_off_at": Kind::Int(0, STEP_MAX),
    /// ... for this many steps (the shift experiment's Δ).
    LtOffFor = "lt_off_for": Kind::Int(1, STEP_MAX),
    /// Obstacles added at run time by the obstacle rule (they stay).
    Obstacles = "obstacles": Kind::Int(0, 100),
    /// Step after which the obstacles are added.
    ObstaclesAt = "obstacles_at": Kind::Int(0, STEP_MAX),
    /// Radius of added and initial obstacles.
    ObstacleRadius = "obstacle_radius": Kind::Int(1, 1000),
    /// Lateral-transfer pause after an obstacle addition (only with
    /// `lt_pause_on_obstacles = true`; the reference's `stop_interval`).
    StopInterval = "stop_interval": Kind::Int(1, STEP_MAX),
    /// Obstacles placed by the obstacle rule when the world is built (Sec. 7 ablation).
    InitialObstacles = "initial_obstacles": Kind::Int(0, 100),
    /// Arena width = height (Sec. 7 addition II).
    Size = "size": Kind::Int(2, 100_000),
    /// Grid-cell size GS (Sec. 7 distortion II).
    Grid = "grid": Kind::Int(1, 100_000),
    /// Number of sites, food split among them at random (Sec. 7 shift II; paper layout).
    Sites = "sites": Kind::Int(1, 36),
    /// Step schedule: simultaneous (DESIGN §2) or sequential (the reference code's turns;
    /// in-process campaigns only).
    Schedule = "schedule": Kind::Text,
    /// Blackboard scope: per-agent (DESIGN §2) or global (the reference code's; in-process
    /// campaigns only).
    Blackboard = "blackboard": Kind::Text,
    /// Genes: copied (DESIGN §2) or shared (the reference code's gene objects; in-process
    /// campaigns only).
    Genes = "genes": Kind::Text,
    /// Fraction of the live agents killed ...
    Kill = "kill": Kind::Float(0.0, 1.0),
    /// ... after this step.
    KillAt = "kill_at": Kind::Int(0, STEP_MAX),
    /// The world turns to the other task right after this step (`SwitchTask`, issue
    /// 30.4): a foraging trial ends as a nest trial and the other way round.
    SwitchAt = "switch_at": Kind::Int(0, STEP_MAX),
    /// The learners' mutation rule: fixed or stress (issue 30.3).
    Mutation = "mutation": Kind::Text,
}

impl Knob {
    pub fn from_name(name: &str) -> Option<Knob> {
        Knob::ALL.iter().copied().find(|k| k.name() == name)
    }

    /// All knob names, for error messages.
    pub fn names() -> String {
        Knob::ALL.iter().map(|k| k.name()).collect::<Vec<_>>().join(", ")
    }

    /// Check one value read from a campaign file and turn it into a level.
    pub fn level(self, v: &toml::Value) -> Result<Level, String> {
        match (self.kind(), v) {
            (Kind::Int(lo, hi), toml::Value::Integer(i)) => {
                if *i < lo || *i > hi {
                    Err(format!("{i} is outside [{lo}, {hi}]"))
                } else {
                    Ok(Level::Int(*i))
                }
            }
            (Kind::Float(lo, hi), toml::Value::Integer(_) | toml::Value::Float(_)) => {
                let x = match v {
                    toml::Value::Integer(i) => *i as f64,
                    toml::Value::Float(f) => *f,
                    _ => unreachable!("matched above"),
                };
                if !x.is_finite() || x < lo || x > hi {
                    Err(format!("{x} is outside [{lo}, {hi}]"))
                } else {
                    Ok(Level::Float(x))
                }
            }
            (Kind::Text, toml::Value::String(s)) => {
                if s.trim().is_empty() {
                    Err("must not be empty".into())
                } else {
                    Ok(Level::Text(s.clone()))
                }
            }
            (Kind::Int(..), other) => Err(format!("expected an integer, found {}", other.type_str())),
            (Kind::Float(..), other) => Err(format!("expected a number, found {}", other.type_str())),
            (Kind::Text, other) => Err(format!("expected a string, found {}", other.type_str())),
        }
    }
}

impl fmt::Display for Knob {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A condition: one level for each knob it sets, in canonical knob order.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Condition {
    pub levels: Vec<(Knob, Level)>,
}

/// Couplings between knobs that are campaign-wide options, not grid axes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Coupling {
    /// An obstacle addition also switches lateral transfer off for `stop_interval`
    /// steps (the reference code's hook, REFERENCE §1.8, §8.4).
    pub lt_pause_on_obstacles: bool,
    pub stop_interval: u64,
}

impl Default for Coupling {
    fn default() -> Self {
        Coupling { lt_pause_on_obstacles: false, stop_interval: DEFAULT_STOP_INTERVAL }
    }
}

/// A knob misused in one condition; `knob` is the key to blame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{knob}: {reason}")]
pub struct KnobError {
    pub knob: String,
    pub reason: String,
}

fn knob_err(knob: Knob, reason: impl Into<String>) -> KnobError {
    KnobError { knob: knob.name().into(), reason: reason.into() }
}

/// A value of one of the `[fidelity]` enums, spelt as in a config file.
fn value_enum<E: clap::ValueEnum>(s: &str) -> Result<E, String> {
    E::from_str(s, false).map_err(|_| {
        let known: Vec<String> = E::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value())
            .map(|p| p.get_name().to_string())
            .collect();
        format!("'{s}' is not one of: {}", known.join(", "))
    })
}

impl Condition {
    pub fn get(&self, k: Knob) -> Option<&Level> {
        self.levels.iter().find(|(x, _)| *x == k).map(|(_, l)| l)
    }

    fn int(&self, k: Knob) -> Option<i64> {
        match self.get(k) {
            Some(Level::Int(v)) => Some(*v),
            _ => None,
        }
    }

    fn float(&self, k: Knob) -> Option<f64> {
        self.get(k).and_then(Level::as_f64)
    }

    /// Canonical label, e.g. `obstacles=2 obstacles_at=3000` (`baseline` if empty).
    pub fn label(&self) -> String {
        if self.levels.is_empty() {
            return "baseline".into();
        }
        self.levels.iter().map(|(k, l)| format!("{k}={l}")).collect::<Vec<_>>().join(" ")
    }

    /// The condition as a JSON object `{knob: value}`.
    pub fn to_json(&self) -> serde_json::Value {
        let mut m = serde_json::Map::new();
        for (k, l) in &self.levels {
            m.insert(k.name().into(), serde_json::to_value(l).unwrap_or(serde_json::Value::Null));
        }
        serde_json::Value::Object(m)
    }

    /// The configuration of this condition for `task` and `seed`, built on `base`.
    pub fn apply(&self, base: &RunConfig, task: Task, seed: u64, coupling: Coupling) -> Result<RunConfig, KnobError> {
        let mut c = base.clone();
        c.seed = seed;
        c.world.task = task;
        let steps = c.steps;
        let time = |k: Knob| -> Result<Option<u64>, KnobError> {
            match self.int(k) {
                None => Ok(None),
                Some(t) if t as u64 >= steps => Err(knob_err(
                    k,
                    format!("step {t} is not before the last step (steps = {steps}), so it would never apply"),
                )),
                Some(t) => Ok(Some(t as u64)),
            }
        };
        let needs = |k: Knob, other: Knob| -> Result<(), KnobError> {
            if self.get(k).is_some() && self.get(other).is_none() {
                Err(knob_err(k, format!("needs `{other}` in the same condition")))
            } else {
                Ok(())
            }
        };
        needs(Knob::IpAt, Knob::Ip)?;
        needs(Knob::GeneLossAt, Knob::GeneLoss)?;
        needs(Knob::LtOffAt, Knob::LtOffFor)?;
        needs(Knob::LtOffFor, Knob::LtOffAt)?;
        needs(Knob::Kill, Knob::KillAt)?;
        needs(Knob::KillAt, Knob::Kill)?;
        needs(Knob::ObstaclesAt, Knob::Obstacles)?;
        if self.int(Knob::Obstacles).unwrap_or(0) > 0 {
            needs(Knob::Obstacles, Knob::ObstaclesAt)?;
        }
        if self.get(Knob::StopInterval).is_some() {
            if !coupling.lt_pause_on_obstacles {
                return Err(knob_err(
                    Knob::StopInterval,
                    "has no effect unless the campaign sets lt_pause_on_obstacles = true",
                ));
            }
            needs(Knob::StopInterval, Knob::Obstacles)?;
        }

        if let Some(Level::Text(g)) = self.get(Knob::Grammar) {
            c.grammar = Some(g.clone());
        }
        if let Some(Level::Text(a)) = self.get(Knob::Algorithm) {
            c.algorithm = a.parse().map_err(|e: String| knob_err(Knob::Algorithm, e))?;
        }
        if let Some(Level::Text(p)) = self.get(Knob::Phase) {
            c.phase = Some(p.parse().map_err(|e: String| knob_err(Knob::Phase, e))?);
        }
        if let Some(Level::Text(f)) = self.get(Knob::Fusion) {
            c.learner.fusion = f.parse().map_err(|e: String| knob_err(Knob::Fusion, e))?;
        }
        if let Some(Level::Text(t)) = self.get(Knob::Terms) {
            c.learner.terms = Some(geese_agent::FitnessTerms::parse(t).map_err(|e| knob_err(Knob::Terms, e))?);
        }
        if let Some(s) = self.float(Knob::Sample) {
            if s <= 0.0 {
                return Err(knob_err(Knob::Sample, "a sample of 0 selects no member"));
            }
            c.sample = Some(s);
        }
        if let Some(Level::Text(p)) = self.get(Knob::Population) {
            c.population = Some(p.into());
        }
        if let Some(Level::Text(s)) = self.get(Knob::Schedule) {
            c.fidelity.schedule = value_enum(s).map_err(|e| knob_err(Knob::Schedule, e))?;
        }
        if let Some(Level::Text(s)) = self.get(Knob::Blackboard) {
            c.fidelity.blackboard = value_enum(s).map_err(|e| knob_err(Knob::Blackboard, e))?;
        }
        if let Some(Level::Text(s)) = self.get(Knob::Genes) {
            c.fidelity.genes = value_enum(s).map_err(|e| knob_err(Knob::Genes, e))?;
        }
        if let Some(Level::Text(s)) = self.get(Knob::Mutation) {
            c.learner.mutation = s.parse().map_err(|e: String| knob_err(Knob::Mutation, e))?;
        }
        if let Some(Level::Text(s)) = self.get(Knob::Strategy) {
            c.strategy = Some(s.parse().map_err(|e: String| knob_err(Knob::Strategy, e))?);
        }
        // `{task}` in a population path (knob or base) stands for the task.
        if let Some(p) = &c.population {
            c.population = Some(p.to_string_lossy().replace("{task}", &task.to_string()).into());
        }
        // `{task}` in a grammar name (knob or base) stands for the task.
        c.grammar = c.grammar.map(|g| g.replace("{task}", &task.to_string()));
        if let Some(v) = self.int(Knob::St) {
            c.learner.st = Some(v as usize);
        }
        if let Some(v) = self.int(Knob::Agents) {
            c.world.agents = v as u32;
        }
        if let Some(v) = self.int(Knob::Size) {
            c.world.width = v as i32;
            c.world.height = v as i32;
        }
        if let Some(v) = self.int(Knob::Grid) {
            c.world.grid = v as i32;
        }
        if let Some(v) = self.int(Knob::Sites) {
            if c.world.layout != Layout::Paper {
                return Err(knob_err(
                    Knob::Sites,
                    "sites are placed only by the paper layout: set layout = \"paper\" in [base.world]",
                ));
            }
            c.world.sites = v as u32;
        }
        if let Some(v) = self.int(Knob::ObstacleRadius) {
            c.world.obstacle_radius = v as i32;
        }
        if let Some(v) = self.int(Knob::InitialObstacles) {
            c.world.obstacles = v as u32;
        }

        let mut sched: Vec<Scheduled> = Vec::new();
        if let Some(ip) = self.float(Knob::Ip) {
            match time(Knob::IpAt)? {
                Some(at) => sched.push(Scheduled { at, change: Perturbation::SetIp(ip) }),
                None => c.ip = ip,
            }
        }
        if let Some(p) = self.float(Knob::GeneLoss) {
            match time(Knob::GeneLossAt)? {
                Some(at) => sched.push(Scheduled { at, change: Perturbation::SetGeneLoss(p) }),
                None => c.gene_loss = p,
            }
        }
        if let Some(at) = time(Knob::SwitchAt)? {
            sched.push(Scheduled { at, change: Perturbation::SwitchTask(task.other()) });
        }
        if let (Some(f), Some(at)) = (self.float(Knob::Kill), time(Knob::KillAt)?) {
            sched.push(Scheduled { at, change: Perturbation::KillFraction(f) });
        }
        // Windows [from, to) during which lateral transfer is off.
        let mut off: Vec<(u64, u64)> = Vec::new();
        if let Some(count) = self.int(Knob::Obstacles).filter(|&n| n > 0) {
            let at = time(Knob::ObstaclesAt)?.unwrap_or(0);
            sched.push(Scheduled {
                at,
                change: Perturbation::AddObstacles { count: count as u32, radius: c.world.obstacle_radius },
            });
            if coupling.lt_pause_on_obstacles {
                let pause = self.int(Knob::StopInterval).map(|v| v as u64).unwrap_or(coupling.stop_interval);
                off.push((at, at.saturating_add(pause)));
            }
        }
        if let (Some(at), Some(d)) = (time(Knob::LtOffAt)?, self.int(Knob::LtOffFor)) {
            off.push((at, at.saturating_add(d as u64)));
        }
        if !off.is_empty() {
            let base_switches = c.perturbations.iter().any(|p| matches!(p.change, Perturbation::SetLateralTransfer(_)));
            if base_switches {
                return Err(KnobError {
                    knob: "base.perturbations".into(),
                    reason: "already switches lateral transfer; do not combine with lt_off_* knobs or \
                             lt_pause_on_obstacles"
                        .into(),
                });
            }
            // With lateral transfer off for the whole run, a window must not switch it on.
            if c.lateral_transfer {
                for (from, to) in merge_windows(off) {
                    sched.push(Scheduled { at: from, change: Perturbation::SetLateralTransfer(false) });
                    if to < steps {
                        sched.push(Scheduled { at: to, change: Perturbation::SetLateralTransfer(true) });
                    }
                }
            }
        }
        sched.sort_by_key(|s| s.at);
        c.perturbations.extend(sched);
        c.perturbations.sort_by_key(|s| s.at);
        Ok(c)
    }
}

/// Merge overlapping or touching half-open windows, sorted by start.
pub fn merge_windows(mut w: Vec<(u64, u64)>) -> Vec<(u64, u64)> {
    w.sort();
    let mut out: Vec<(u64, u64)> = Vec::new();
    for (a, b) in w {
        match out.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => out.push((a, b)),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cond(levels: &[(Knob, Level)]) -> Condition {
        let mut levels = levels.to_vec();
        levels.sort_by_key(|(k, _)| *k);
        Condition { levels }
    }

    #[test]
    fn levels_are_range_checked_by_knob() {
        assert_eq!(Knob::Ip.level(&toml::Value::Float(0.9)), Ok(Level::Float(0.9)));
        assert_eq!(Knob::Ip.level(&toml::Value::Integer(1)), Ok(Level::Float(1.0)));
        assert!(Knob::Ip.level(&toml::Value::Float(1.5)).unwrap_err().contains("outside"));
        assert!(Knob::Obstacles.level(&toml::Value::Float(1.0)).unwrap_err().contains("integer"));
        assert!(Knob::St.level(&toml::Value::Integer(3)).is_err());
        assert_eq!(Knob::from_name("lt_off_for"), Some(Knob::LtOffFor));
        assert_eq!(Knob::from_name("bogus"), None);
    }

    /// `schedule`, `blackboard` and `genes` set the trial's `[fidelity]`; a bad value
    /// names the knob and the values it takes.
    #[test]
    fn fidelity_knobs_set_the_schedule_blackboard_and_genes() {
        use crate::run::config::{Blackboard, Genes, Schedule};
        let text = |s: &str| Level::Text(s.into());
        let c = cond(&[
            (Knob::Schedule, text("sequential")),
            (Knob::Blackboard, text("global")),
            (Knob::Genes, text("shared")),
        ]);
        let r = c.apply(&RunConfig::default(), Task::Foraging, 1, Coupling::default()).unwrap();
        let f = r.fidelity;
        assert_eq!((f.schedule, f.blackboard, f.genes), (Schedule::Sequential, Blackboard::Global, Genes::Shared));
        let bad = cond(&[(Knob::Genes, text("aliased"))]);
        let err = bad.apply(&RunConfig::default(), Task::Foraging, 1, Coupling::default()).unwrap_err().to_string();
        assert!(err.contains("genes") && err.contains("copied, shared"), "{err}");
        let bad = cond(&[(Knob::Schedule, text("turns"))]);
        let err = bad.apply(&RunConfig::default(), Task::Foraging, 1, Coupling::default()).unwrap_err().to_string();
        assert!(err.contains("schedule") && err.contains("simultaneous, sequential"), "{err}");
    }

    #[test]
    fn obstacles_schedule_and_optional_lt_pause() {
        let base = RunConfig::default();
        let c = cond(&[(Knob::Obstacles, Level::Int(2)), (Knob::ObstaclesAt, Level::Int(3000))]);
        assert_eq!(c.label(), "obstacles=2 obstacles_at=3000");
        let r = c.apply(&base, Task::Nest, 9, Coupling::default()).unwrap();
        assert_eq!((r.seed, r.world.task), (9, Task::Nest));
        assert_eq!(
            r.perturbations,
            vec![Scheduled { at: 3000, change: Perturbation::AddObstacles { count: 2, radius: 10 } }]
        );
        let coupled = Coupling { lt_pause_on_obstacles: true, stop_interval: 1000 };
        let r = c.apply(&base, Task::Foraging, 1, coupled).unwrap();
        let at: Vec<_> = r.perturbations.iter().map(|p| (p.at, p.change.clone())).collect();
        assert_eq!(
            at,
            vec![
                (3000, Perturbation::AddObstacles { count: 2, radius: 10 }),
                (3000, Perturbation::SetLateralTransfer(false)),
                (4000, Perturbation::SetLateralTransfer(true)),
            ]
        );
    }

    #[test]
    fn overlapping_lt_windows_merge_and_never_switch_on_a_disabled_run() {
        assert_eq!(merge_windows(vec![(5, 10), (1, 3), (3, 4), (8, 20)]), vec![(1, 4), (5, 20)]);
        let c = cond(&[
            (Knob::Obstacles, Level::Int(1)),
            (Knob::ObstaclesAt, Level::Int(1000)),
            (Knob::StopInterval, Level::Int(2500)),
            (Knob::LtOffAt, Level::Int(1000)),
            (Knob::LtOffFor, Level::Int(1000)),
        ]);
        let coupled = Coupling { lt_pause_on_obstacles: true, stop_interval: 1000 };
        let r = c.apply(&RunConfig::default(), Task::Foraging, 1, coupled).unwrap();
        let lt: Vec<_> = r
            .perturbations
            .iter()
            .filter(|p| matches!(p.change, Perturbation::SetLateralTransfer(_)))
            .map(|p| p.at)
            .collect();
        assert_eq!(lt, vec![1000, 3500]);
        let off = RunConfig { lateral_transfer: false, ..RunConfig::default() };
        let r = c.apply(&off, Task::Foraging, 1, coupled).unwrap();
        assert!(r.perturbations.iter().all(|p| !matches!(p.change, Perturbation::SetLateralTransfer(_))));
        // A window running past the end never switches back on.
        let late = cond(&[(Knob::LtOffAt, Level::Int(11_000)), (Knob::LtOffFor, Level::Int(4000))]);
        let r = late.apply(&RunConfig::default(), Task::Foraging, 1, Coupling::default()).unwrap();
        assert_eq!(r.perturbations.len(), 1);
    }

    #[test]
    fn world_and_regime_knobs() {
        let c = cond(&[
            (Knob::Grammar, Level::Text("betr-{task}-addition".into())),
            (Knob::Ip, Level::Float(0.5)),
            (Knob::GeneLoss, Level::Float(0.2)),
            (Knob::GeneLossAt, Level::Int(100)),
            (Knob::Size, Level::Int(300)),
            (Knob::Grid, Level::Int(5)),
            (Knob::Kill, Level::Float(0.25)),
            (Knob::KillAt, Level::Int(50)),
        ]);
        let r = c.apply(&RunConfig::default(), Task::Nest, 1, Coupling::default()).unwrap();
        assert_eq!(r.grammar.as_deref(), Some("betr-nest-addition"));
        assert_eq!((r.ip, r.gene_loss, r.world.width, r.world.height, r.world.grid), (0.5, 0.0, 300, 300, 5));
        assert_eq!(r.perturbations[0], Scheduled { at: 50, change: Perturbation::KillFraction(0.25) });
        assert_eq!(r.perturbations[1], Scheduled { at: 100, change: Perturbation::SetGeneLoss(0.2) });
    }

    #[test]
    fn misuse_names_the_knob() {
        let base = RunConfig::default();
        let e = cond(&[(Knob::Obstacles, Level::Int(2))]).apply(&base, Task::Foraging, 1, Coupling::default());
        assert_eq!(e.unwrap_err().knob, "obstacles");
        let e = cond(&[(Knob::LtOffAt, Level::Int(12_000)), (Knob::LtOffFor, Level::Int(10))]).apply(
            &base,
            Task::Foraging,
            1,
            Coupling::default(),
        );
        assert_eq!(e.unwrap_err().knob, "lt_off_at");
        let e = cond(&[(Knob::Sites, Level::Int(3))]).apply(&base, Task::Foraging, 1, Coupling::default());
        assert_eq!(e.unwrap_err().knob, "sites");
        let e = cond(&[
            (Knob::Obstacles, Level::Int(1)),
            (Knob::ObstaclesAt, Level::Int(5)),
            (Knob::StopInterval, Level::Int(5)),
        ])
        .apply(&base, Task::Foraging, 1, Coupling::default());
        assert_eq!(e.unwrap_err().knob, "stop_interval");
    }
}
