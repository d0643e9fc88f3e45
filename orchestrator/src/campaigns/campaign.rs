//! Campaigns: a grid of conditions × tasks × seeds, run in parallel and stored as each
//! trial finishes, so that an interrupted campaign resumes where it stopped.
//!
//! A campaign file (TOML) holds a base run configuration (`[base]`, the same keys as a
//! `geese run` config file), one or more `[[grid]]` tables whose keys are
//! [`Knob`]s with arrays of levels (each table is a Cartesian product; the campaign's
//! conditions are the union of the tables, duplicates removed), the tasks and the seeds.
//! Every value is checked before anything runs; errors name the key.
//!
//! Running a trial goes through the [`TrialRunner`] trait: [`InProcess`] runs it on the
//! in-memory transport; a distributed runner (one trial over Zenoh) plugs in there.
use crate::analysis::metrics::{self, EfficiencyVariant};
use crate::campaigns::condition::{Condition, Coupling, Knob, Level, DEFAULT_STOP_INTERVAL};
use crate::campaigns::shard::{self, Shard};
use crate::campaigns::store::{Store, StoreError, TrialRecord, TrialResult};
use crate::run::config::{RunConfig, RunSpec};
use crate::run::output::text_digest;
use crate::run::trial::{run_trial, Ran};
use geese_proto::seed::Fnv64;
use geese_proto::StepReport;
use geese_world::Task;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// The campaign file as written.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CampaignFile {
    /// Short name (default: the file stem); also the default database name.
    pub name: Option<String>,
    #[serde(default)]
    pub description: String,
    /// Tasks every condition runs on.
    pub tasks: Vec<Task>,
    /// Seeds per (condition, task): `first_seed`, `first_seed + 1`, …
    pub seeds: u32,
    #[serde(default = "one")]
    pub first_seed: u64,
    /// Knob on the x axis of the plots and of the fitted line (required when several
    /// knobs vary); `"condition"` puts each condition at its own position.
    pub x: Option<String>,
    /// Optional second knob: learning curves are drawn per level of it, box plots
    /// grouped by it (Fig. 4b: x = "ip", series = "st").
    pub series: Option<String>,
    /// An obstacle addition also pauses lateral transfer (reference coupling, §1.8).
    #[serde(default)]
    pub lt_pause_on_obstacles: bool,
    #[serde(default = "default_stop_interval")]
    pub stop_interval: u64,
    /// Which reference-code efficiency `geese report --efficiency code` uses.
    #[serde(default)]
    pub code_efficiency: Option<EfficiencyVariant>,
    /// Store every k-th step row (the last step is always stored); metrics are computed
    /// from every step before thinning.
    #[serde(default = "one")]
    pub step_stride: u64,
    #[serde(default)]
    pub base: RunConfig,
    #[serde(default)]
    pub grid: Vec<toml::Table>,
}

/// Most seeds per (condition, task).
pub const MAX_SEEDS: u32 = 10_000;
/// Most conditions a campaign may have (each `[[grid]]` product, and their union).
pub const MAX_CONDITIONS: usize = 10_000;
/// Most trials a campaign may plan (conditions × tasks × seeds).
pub const MAX_TRIALS: u64 = 1_000_000;

fn one() -> u64 {
    1
}
fn default_stop_interval() -> u64 {
    DEFAULT_STOP_INTERVAL
}

#[derive(Debug, thiserror::Error)]
pub enum CampaignError {
    #[error("cannot read campaign {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("campaign {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("campaign: {key}: {reason}")]
    Invalid { key: String, reason: String },
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("the thread pool could not start: {0}")]
    Pool(String),
    #[error("interrupted after {done} finished trial(s); they are stored: run the campaign again to resume")]
    Interrupted { done: usize },
}

fn invalid(key: impl Into<String>, reason: impl Into<String>) -> CampaignError {
    CampaignError::Invalid { key: key.into(), reason: reason.into() }
}

/// One planned trial.
#[derive(Clone, Debug)]
pub struct PlannedTrial {
    /// Index into [`Campaign::conditions`].
    pub condition: usize,
    pub task: Task,
    pub seed: u64,
}

/// A validated campaign: conditions expanded, every configuration checked.
#[derive(Clone, Debug)]
pub struct Campaign {
    pub name: String,
    pub file: CampaignFile,
    /// The file's text, for the manifest.
    pub text: String,
    pub conditions: Vec<Condition>,
    pub x: Option<Knob>,
    /// `x = "condition"`: conditions are the x levels, in grid order.
    pub x_by_condition: bool,
    pub series: Option<Knob>,
    pub coupling: Coupling,
    /// Validated run spec per (condition, task), seed not yet set.
    specs: Vec<Vec<Arc<RunSpec>>>,
}

impl Campaign {
    /// Read and validate a campaign file.
    pub fn from_file(path: &Path) -> Result<Campaign, CampaignError> {
        let text = std::fs::read_to_string(path).map_err(|source| CampaignError::Read { path: path.into(), source })?;
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "campaign".into());
        let file: CampaignFile =
            toml::from_str(&text).map_err(|e| CampaignError::Parse { path: path.into(), message: e.to_string() })?;
        Campaign::new_in(file, text, &stem, path.parent()).map_err(|e| match e {
            CampaignError::Parse { message, .. } => CampaignError::Parse { path: path.into(), message },
            other => other,
        })
    }

    /// Parse and validate campaign text; `default_name` is used when the file has none.
    pub fn from_toml(text: &str, default_name: &str) -> Result<Campaign, CampaignError> {
        let file: CampaignFile = toml::from_str(text)
            .map_err(|e| CampaignError::Parse { path: PathBuf::from("<text>"), message: e.to_string() })?;
        Campaign::new(file, text.to_string(), default_name)
    }

    /// Validate a parsed campaign file; relative population paths are taken from the
    /// current directory.
    pub fn new(file: CampaignFile, text: String, default_name: &str) -> Result<Campaign, CampaignError> {
        Campaign::new_in(file, text, default_name, None)
    }

    /// Validate a parsed campaign file read from directory `dir`: relative paths of
    /// population files in it (`population`, `collect_population`) are relative to that
    /// directory.
    pub fn new_in(
        file: CampaignFile,
        text: String,
        default_name: &str,
        dir: Option<&Path>,
    ) -> Result<Campaign, CampaignError> {
        let name = file.name.clone().unwrap_or_else(|| default_name.to_string());
        if name.trim().is_empty() || name.contains(['/', '\\']) {
            return Err(invalid("name", "must be a non-empty name without path separators"));
        }
        if file.tasks.is_empty() {
            return Err(invalid("tasks", "is empty: name at least one task (\"foraging\", \"nest\")"));
        }
        let mut seen = HashSet::new();
        for t in &file.tasks {
            if !seen.insert(*t) {
                return Err(invalid("tasks", format!("{t} is listed twice")));
            }
        }
        if file.seeds == 0 {
            return Err(invalid("seeds", "must be at least 1"));
        }
        if file.seeds > MAX_SEEDS {
            return Err(invalid("seeds", format!("{} exceeds {MAX_SEEDS}", file.seeds)));
        }
        if file.first_seed.checked_add(file.seeds as u64).is_none() {
            return Err(invalid("first_seed", "too large"));
        }
        if file.stop_interval == 0 {
            return Err(invalid("stop_interval", "must be at least 1"));
        }
        if file.step_stride == 0 {
            return Err(invalid("step_stride", "must be at least 1"));
        }
        if let Some(w) = &file.base.locality {
            // The results database has no place for per-trial maps (NOTES.md).
            return Err(invalid(
                "base.locality",
                format!("{w:?}: a locality map is drawn from one run: use geese run --locality, not a campaign"),
            ));
        }
        let conditions = expand_grid(&file.grid)?;
        let trials = conditions.len() as u64 * file.tasks.len() as u64 * u64::from(file.seeds);
        if trials > MAX_TRIALS {
            return Err(invalid(
                "seeds",
                format!(
                    "{} conditions × {} tasks × {} seeds = {trials} trials exceed {MAX_TRIALS}",
                    conditions.len(),
                    file.tasks.len(),
                    file.seeds
                ),
            ));
        }
        let coupling =
            Coupling { lt_pause_on_obstacles: file.lt_pause_on_obstacles, stop_interval: file.stop_interval };
        let pick = |key: &str, v: &Option<String>| -> Result<Option<Knob>, CampaignError> {
            let Some(name) = v else { return Ok(None) };
            let k = Knob::from_name(name)
                .ok_or_else(|| invalid(key, format!("'{name}' is not a knob (one of: {})", Knob::names())))?;
            if let Some(c) = conditions.iter().find(|c| c.get(k).is_none()) {
                return Err(invalid(key, format!("'{name}' is not set in condition '{}'", c.label())));
            }
            Ok(Some(k))
        };
        let x_by_condition = file.x.as_deref() == Some("condition");
        let mut x = if x_by_condition { None } else { pick("x", &file.x)? };
        let series = pick("series", &file.series)?;
        if x.is_none() && !x_by_condition {
            // The one knob whose level differs between conditions, if it is set in all.
            let varying: Vec<Knob> = Knob::ALL
                .iter()
                .copied()
                .filter(|&k| {
                    let first = conditions[0].get(k);
                    conditions.iter().any(|c| c.get(k) != first)
                })
                .collect();
            match varying.as_slice() {
                [] => {}
                [k] if conditions.iter().all(|c| c.get(*k).is_some()) => x = Some(*k),
                _ => {
                    let names: Vec<_> = varying.iter().map(|k| k.name()).collect();
                    return Err(invalid(
                        "x",
                        format!(
                            "several knobs vary ({}): name the one to plot, or x = \"condition\"",
                            names.join(", ")
                        ),
                    ));
                }
            }
        }
        // Build and validate every (condition, task) configuration once.
        let mut specs = Vec::with_capacity(conditions.len());
        for (ci, c) in conditions.iter().enumerate() {
            let mut per_task = Vec::new();
            for &task in &file.tasks {
                let where_ = format!("grid condition {} ('{}'), task {task}", ci + 1, c.label());
                let mut cfg = c
                    .apply(&file.base, task, file.first_seed, coupling)
                    .map_err(|e| invalid(e.knob, format!("{} ({where_})", e.reason)))?;
                if let Some(dir) = dir {
                    for p in [&mut cfg.population, &mut cfg.collect_population].into_iter().flatten() {
                        if p.is_relative() {
                            *p = dir.join(&*p);
                        }
                    }
                }
                let spec = cfg.validate().map_err(|e| invalid(format!("base or grid ({where_})"), e.to_string()))?;
                per_task.push(Arc::new(spec));
            }
            specs.push(per_task);
        }
        Ok(Campaign { name, file, text, conditions, x, x_by_condition, series, coupling, specs })
    }

    /// Every trial of the campaign, in a fixed order: condition, task, seed.
    pub fn plan(&self) -> Vec<PlannedTrial> {
        let mut v = Vec::new();
        for ci in 0..self.conditions.len() {
            for &task in &self.file.tasks {
                for s in 0..self.file.seeds as u64 {
                    v.push(PlannedTrial { condition: ci, task, seed: self.file.first_seed + s });
                }
            }
        }
        v
    }

    /// The validated run of a planned trial.
    pub fn spec(&self, t: &PlannedTrial) -> RunSpec {
        let ti = self.file.tasks.iter().position(|&x| x == t.task).unwrap_or(0);
        let mut spec = (*self.specs[t.condition][ti]).clone();
        spec.config.seed = t.seed;
        spec
    }

    /// Position of a condition on the x axis: the x knob's numeric level, or for a text
    /// knob the index of its level in order of first appearance.
    pub fn x_of(&self, condition: usize) -> (f64, String) {
        if self.x_by_condition {
            return (condition as f64, self.conditions[condition].label());
        }
        level_position(&self.conditions, self.x, condition)
    }

    /// Label of a condition's series level (empty without a series knob).
    pub fn series_of(&self, condition: usize) -> String {
        self.series.and_then(|k| self.conditions[condition].get(k)).map(|l| l.to_string()).unwrap_or_default()
    }

    /// Build a planned trial's record (key and configuration) for the store.
    pub fn record(&self, t: &PlannedTrial) -> TrialRecord {
        let c = &self.conditions[t.condition];
        let spec = self.spec(t);
        let (x, x_label) = self.x_of(t.condition);
        TrialRecord {
            condition: c.label(),
            condition_json: c.to_json().to_string(),
            condition_index: t.condition as i64,
            x,
            x_label,
            series: self.series_of(t.condition),
            task: t.task.to_string(),
            seed: t.seed,
            config_json: serde_json::to_string(&spec.config).unwrap_or_default(),
            grammar: spec.grammar_name.clone(),
            grammar_digest: text_digest(&spec.grammar_text),
        }
    }

    /// Digest of the campaign's definition (for the manifest).
    pub fn digest(&self) -> String {
        text_digest(&self.text)
    }

    /// Digest of the resolved campaign: its name, the file as resolved (command-line
    /// overrides of seeds, steps and agents included) and every trial's key and
    /// configuration. The shards of one campaign must agree on it before `geese merge`
    /// combines them: unlike [`Campaign::digest`] (of the file's text) it changes when
    /// `--steps` or a grammar file differs between two invocations, and not when only a
    /// comment of the file does.
    pub fn resolved_digest(&self) -> String {
        let mut h = Fnv64::default();
        // Length-prefixed fields: no two different field lists hash the same bytes.
        let mut field = |s: &str| {
            h.write(&(s.len() as u64).to_le_bytes());
            h.write(s.as_bytes());
        };
        field(&self.name);
        field(&serde_json::to_string(&self.file).unwrap_or_default());
        for t in self.plan() {
            let r = self.record(&t);
            for f in [&r.condition, &r.condition_json, &r.x_label, &r.series, &r.task] {
                field(f);
            }
            for f in [&r.config_json, &r.grammar, &r.grammar_digest] {
                field(f);
            }
            field(&format!("{} {} {}", r.seed, r.condition_index, r.x.to_bits()));
        }
        format!("{:016x}", h.finish())
    }
}

fn level_position(conditions: &[Condition], knob: Option<Knob>, condition: usize) -> (f64, String) {
    let Some(k) = knob else {
        return (0.0, String::new());
    };
    let Some(level) = conditions[condition].get(k) else {
        return (0.0, String::new());
    };
    match level.as_f64() {
        Some(v) => (v, level.to_string()),
        None => {
            let mut order: Vec<String> = Vec::new();
            for c in conditions {
                if let Some(l) = c.get(k) {
                    let s = l.to_string();
                    if !order.contains(&s) {
                        order.push(s);
                    }
                }
            }
            let s = level.to_string();
            (order.iter().position(|o| *o == s).unwrap_or(0) as f64, s)
        }
    }
}

/// Expand the `[[grid]]` tables into conditions (union of Cartesian products). Each
/// product and the union have at most [`MAX_CONDITIONS`] conditions; a product's size
/// is checked before it is built.
pub fn expand_grid(grid: &[toml::Table]) -> Result<Vec<Condition>, CampaignError> {
    if grid.is_empty() {
        return Err(invalid("grid", "no conditions: add a [[grid]] table with at least one knob"));
    }
    let mut out: Vec<Condition> = Vec::new();
    let mut labels = HashSet::new();
    for (gi, table) in grid.iter().enumerate() {
        if table.is_empty() {
            return Err(invalid(format!("grid[{gi}]"), "is empty: give at least one knob"));
        }
        let mut axes: Vec<(Knob, Vec<Level>)> = Vec::new();
        for (key, value) in table {
            let path = format!("grid[{gi}].{key}");
            let knob = Knob::from_name(key)
                .ok_or_else(|| invalid(&path, format!("unknown knob (known: {})", Knob::names())))?;
            let values: Vec<&toml::Value> = match value {
                toml::Value::Array(a) => a.iter().collect(),
                scalar => vec![scalar],
            };
            if values.is_empty() {
                return Err(invalid(&path, "is an empty list"));
            }
            let mut levels = Vec::new();
            for (i, v) in values.iter().enumerate() {
                let l = knob.level(v).map_err(|r| invalid(format!("{path}[{i}]"), r))?;
                if levels.contains(&l) {
                    return Err(invalid(format!("{path}[{i}]"), format!("{l} is listed twice")));
                }
                levels.push(l);
            }
            axes.push((knob, levels));
        }
        axes.sort_by_key(|(k, _)| *k);
        let size = axes.iter().try_fold(1usize, |n, (_, levels)| n.checked_mul(levels.len()));
        if size.is_none_or(|n| n > MAX_CONDITIONS) {
            let sizes: Vec<String> = axes.iter().map(|(k, l)| format!("{} {k}", l.len())).collect();
            return Err(invalid(
                format!("grid[{gi}]"),
                format!("{} levels make more than {MAX_CONDITIONS} conditions", sizes.join(" × ")),
            ));
        }
        // Cartesian product, first axis slowest.
        let mut conds = vec![Condition::default()];
        for (k, levels) in &axes {
            let mut next = Vec::with_capacity(conds.len() * levels.len());
            for c in &conds {
                for l in levels {
                    let mut c = c.clone();
                    c.levels.push((*k, l.clone()));
                    next.push(c);
                }
            }
            conds = next;
        }
        for c in conds {
            if labels.insert(c.label()) {
                out.push(c);
            }
        }
        if out.len() > MAX_CONDITIONS {
            return Err(invalid("grid", format!("{} conditions exceed {MAX_CONDITIONS}", out.len())));
        }
    }
    Ok(out)
}

/// Error of one trial, as recorded in the store.
pub type TrialError = Box<dyn std::error::Error + Send + Sync>;

/// What a runner returns when the user interrupts it (Ctrl-C): the campaign records no
/// failure for the trial, starts no further trial and ends with
/// [`CampaignError::Interrupted`]; finished trials are already committed.
#[derive(Debug, thiserror::Error)]
#[error("interrupted")]
pub struct Interrupted;

/// Runs one trial: the hook where the transport is chosen. The in-process runner is
/// [`InProcess`]; a runner that starts a world and agent processes over Zenoh implements
/// the same trait and is handed to [`run_campaign`].
pub trait TrialRunner: Sync {
    /// Transport name recorded with every trial ("in-process", "zenoh", …).
    fn transport(&self) -> &str;
    /// Run one stage `spec` to the end, calling `observe` after every step, in step
    /// order; returns its summary and the population its agents ended with.
    fn run(&self, spec: &RunSpec, observe: &mut dyn FnMut(&StepReport)) -> Result<Ran, TrialError>;
}

/// Run `spec` and the stages that follow it ([`crate::run::config::FollowUp`]: a Multi-GEESE
/// combine phase after its collect phase, the fixed test of a learned population);
/// `observe` sees the last stage's steps, `stage_done` every stage with the population
/// it ended with, and `learned` the task % per step, `(step, task %)`, of the learning
/// stage whose population a fixed test runs (Fig. 8a's curves; with a cache, also when
/// the stage was run by another trial). Returns the last stage.
pub fn run_stages(
    runner: &dyn TrialRunner,
    spec: &RunSpec,
    observe: &mut dyn FnMut(&StepReport),
    stage_done: &mut dyn FnMut(&RunSpec, &Ran, &geese_agent::Population),
    learned: &mut dyn FnMut(&[StepPct]),
    cache: Option<&StageCache>,
) -> Result<Ran, TrialError> {
    let mut cur = spec.clone();
    loop {
        if cur.follow_up == crate::run::config::FollowUp::None {
            let ran = runner.run(&cur, observe)?;
            let pop = cur.population(ran.members.clone());
            stage_done(&cur, &ran, &pop);
            return Ok(ran);
        }
        let key = cache.map(|_| StageCache::key(&cur));
        let cached = cache.zip(key.as_ref()).and_then(|(c, k)| c.get(k));
        let stage = match cached {
            Some(stage) => stage,
            None => {
                let tested = cur.follow_up == crate::run::config::FollowUp::FixedTest;
                let mut curve = Vec::new();
                let ran = runner.run(&cur, &mut |r| {
                    if tested {
                        curve.push((r.step, r.task_pct));
                    }
                })?;
                let pop = cur.population(ran.members.clone());
                stage_done(&cur, &ran, &pop);
                let stage = CachedStage { pop, curve: Arc::new(curve) };
                if let (Some(c), Some(k)) = (cache, key) {
                    c.put(k, stage.clone());
                }
                stage
            }
        };
        if cur.follow_up == crate::run::config::FollowUp::FixedTest {
            learned(&stage.curve);
        }
        match cur.next_stage(&stage.pop)? {
            Some(next) => cur = next,
            None => return Err("a stage with a follow-up had none".into()),
        }
    }
}

/// A step and the task % after it.
pub type StepPct = (u64, f64);

/// A stage's result as the cache keeps it: the population it ended with and, for a
/// stage a fixed test follows, its task % per step.
#[derive(Clone)]
struct CachedStage {
    pop: geese_agent::Population,
    curve: Arc<Vec<StepPct>>,
}

/// The populations a campaign's learning stages ended with, by stage configuration:
/// trials that differ only in how they test a learned population (Fig. 8b's sampling
/// sizes) learn it once. A learning stage's result depends on its configuration alone.
#[derive(Default)]
pub struct StageCache {
    pops: std::sync::Mutex<std::collections::HashMap<String, CachedStage>>,
}

impl StageCache {
    /// The key of a stage: trials with the same key share the stage (and the shards of
    /// a campaign keep them together, [`crate::campaigns::shard`]).
    pub(crate) fn key(spec: &RunSpec) -> String {
        let mut c = spec.config.clone();
        // Settings read only by the fixed test that follows.
        c.sample = None;
        c.strategy = None;
        let program = serde_json::to_string(&*spec.program).unwrap_or_default();
        format!("{}|{}|{}", spec.stage, serde_json::to_string(&c).unwrap_or_default(), program)
    }
    fn get(&self, key: &str) -> Option<CachedStage> {
        self.pops.lock().ok()?.get(key).cloned()
    }
    fn put(&self, key: String, stage: CachedStage) {
        if let Ok(mut m) = self.pops.lock() {
            m.insert(key, stage);
        }
    }
}

/// Trials on the in-memory transport, in the calling thread.
pub struct InProcess;

impl TrialRunner for InProcess {
    fn transport(&self) -> &str {
        "in-process"
    }
    fn run(&self, spec: &RunSpec, observe: &mut dyn FnMut(&StepReport)) -> Result<Ran, TrialError> {
        Ok(run_trial(spec, observe)?)
    }
}

/// How to run a campaign.
#[derive(Clone, Debug, Default)]
pub struct RunOptions {
    /// Trials at once (0 = one per core).
    pub jobs: usize,
    /// Run failed trials of an earlier invocation again.
    pub retry_failed: bool,
    /// No progress bar.
    pub quiet: bool,
    /// Run only this shard's trials ([`crate::campaigns::shard`]); the store records the shard.
    pub shard: Option<Shard>,
}

/// What a campaign invocation did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CampaignOutcome {
    pub planned: usize,
    /// Found finished in the store and skipped.
    pub skipped: usize,
    pub done: usize,
    pub failed: usize,
    pub wall_seconds: f64,
}

/// Run every trial of `campaign` not yet in `store`, `jobs` at a time, writing each
/// trial (summary and step rows) in one transaction as soon as it finishes.
pub fn run_campaign(
    campaign: &Campaign,
    store: &mut Store,
    runner: &dyn TrialRunner,
    opts: &RunOptions,
) -> Result<CampaignOutcome, CampaignError> {
    let start = std::time::Instant::now();
    let session = store.begin_session_in(campaign, opts.shard)?;
    let plan = match opts.shard {
        Some(s) => shard::plan(campaign, s),
        None => campaign.plan(),
    };
    let mut pending = Vec::new();
    let mut skipped = 0;
    for t in &plan {
        let rec = campaign.record(t);
        match store.find(&rec)? {
            Some(status) if status == "done" || (status == "failed" && !opts.retry_failed) => skipped += 1,
            Some(_) => {
                store.remove(&rec)?;
                pending.push((t.clone(), rec));
            }
            None => pending.push((t.clone(), rec)),
        }
    }
    let bar = if opts.quiet { ProgressBar::hidden() } else { ProgressBar::new(pending.len() as u64) };
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} trials  [{elapsed_precise} < {eta_precise}]  {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.jobs)
        .thread_name(|i| format!("geese-trial-{i}"))
        .build()
        .map_err(|e| CampaignError::Pool(e.to_string()))?;
    let stop = AtomicBool::new(false);
    let interrupted = AtomicBool::new(false);
    let (tx, rx) = std::sync::mpsc::channel::<(TrialRecord, TrialResult)>();
    let stride = campaign.file.step_stride;
    let cache = &StageCache::default();
    let mut out = CampaignOutcome { planned: plan.len(), skipped, ..Default::default() };
    let mut write_error: Option<StoreError> = None;
    std::thread::scope(|s| {
        let pending = &pending;
        let stop = &stop;
        let interrupted = &interrupted;
        s.spawn(move || {
            pool.install(|| {
                use rayon::prelude::*;
                pending.par_iter().for_each_with(tx, |tx, (t, rec)| {
                    if stop.load(Ordering::Relaxed) {
                        return;
                    }
                    let spec = campaign.spec(t);
                    match run_one(runner, &spec, stride, cache) {
                        Some(result) => {
                            let _ = tx.send((rec.clone(), result));
                        }
                        None => {
                            interrupted.store(true, Ordering::Relaxed);
                            stop.store(true, Ordering::Relaxed);
                        }
                    }
                });
            });
        });
        for (rec, result) in rx {
            if write_error.is_some() {
                continue;
            }
            let ok = result.error.is_none();
            match store.insert(&rec, &result, session, start.elapsed().as_secs_f64(), runner.transport()) {
                Ok(()) => {
                    if ok {
                        out.done += 1;
                    } else {
                        out.failed += 1;
                        bar.println(format!(
                            "trial failed: {} task {} seed {}: {}",
                            rec.condition,
                            rec.task,
                            rec.seed,
                            result.error.as_deref().unwrap_or("")
                        ));
                    }
                    bar.inc(1);
                    bar.set_message(format!("{} done, {} failed", out.done, out.failed));
                }
                Err(e) => {
                    stop.store(true, Ordering::Relaxed);
                    write_error = Some(e);
                }
            }
        }
    });
    bar.finish_and_clear();
    if let Some(e) = write_error {
        return Err(e.into());
    }
    if interrupted.load(Ordering::Relaxed) {
        return Err(CampaignError::Interrupted { done: out.done + out.failed });
    }
    out.wall_seconds = start.elapsed().as_secs_f64();
    store.end_session(session, &out)?;
    Ok(out)
}

/// Run one trial, catching errors and panics, and thin its step rows; `None` when the
/// runner was interrupted ([`Interrupted`]).
fn run_one(runner: &dyn TrialRunner, spec: &RunSpec, stride: u64, cache: &StageCache) -> Option<TrialResult> {
    let steps = spec.config.steps;
    let theta = spec.config.threshold;
    let mut rows: Vec<StepReport> = Vec::new();
    let mut series: Vec<f64> = Vec::with_capacity(steps as usize);
    let mut learning_rows: Vec<StepPct> = Vec::new();
    let started = std::time::Instant::now();
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let keep = |step: u64, last: u64| step.is_multiple_of(stride) || step == last;
        let mut observe = |rep: &StepReport| {
            series.push(rep.task_pct);
            if keep(rep.step, steps) {
                rows.push(rep.clone());
            }
        };
        let mut learned = |curve: &[StepPct]| {
            let last = curve.last().map_or(0, |r| r.0);
            learning_rows = curve.iter().copied().filter(|r| keep(r.0, last)).collect();
        };
        run_stages(runner, spec, &mut observe, &mut |_, _, _| {}, &mut learned, Some(cache)).map(|r| r.summary)
    }));
    let wall = started.elapsed().as_secs_f64();
    let error = match r {
        Ok(Ok(summary)) => {
            if series.len() as u64 != steps {
                Some(format!("the runner reported {} of {steps} steps", series.len()))
            } else {
                return Some(TrialResult {
                    outcome: metrics::outcome(&series, theta),
                    summary: Some(summary),
                    rows,
                    error: None,
                    wall_seconds: wall,
                    learning_rows,
                });
            }
        }
        Ok(Err(e)) if e.is::<Interrupted>() => return None,
        Ok(Err(e)) => Some(e.to_string()),
        Err(panic) => Some(format!(
            "panic: {}",
            panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown".into())
        )),
    };
    Some(TrialResult {
        outcome: metrics::outcome(&series, theta),
        summary: None,
        rows: Vec::new(),
        error,
        wall_seconds: wall,
        learning_rows: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL: &str = r#"
        tasks = ["foraging", "nest"]
        seeds = 2
        x = "obstacles"
        [base]
        steps = 50
        [base.world]
        agents = 5
        [[grid]]
        obstacles = [1, 2]
        obstacles_at = [10, 20]
        [[grid]]
        obstacles = 1
        obstacles_at = 10
    "#;

    #[test]
    fn grid_expands_to_the_union_of_products() {
        let c = Campaign::from_toml(SMALL, "small").unwrap();
        assert_eq!(c.name, "small");
        let labels: Vec<_> = c.conditions.iter().map(|c| c.label()).collect();
        assert_eq!(
            labels,
            [
                "obstacles=1 obstacles_at=10",
                "obstacles=1 obstacles_at=20",
                "obstacles=2 obstacles_at=10",
                "obstacles=2 obstacles_at=20"
            ]
        );
        let plan = c.plan();
        assert_eq!(plan.len(), 4 * 2 * 2);
        assert_eq!(c.spec(&plan[3]).config.seed, 2);
        assert_eq!(c.spec(&plan[3]).config.world.task, Task::Nest);
        assert_eq!(c.x_of(2), (2.0, "2".into()));
    }

    fn err(text: &str) -> String {
        match Campaign::from_toml(text, "t") {
            Ok(_) => panic!("accepted:\n{text}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn bad_campaigns_name_the_key() {
        let head = "tasks = [\"foraging\"]\nseeds = 1\n";
        assert!(err(&format!("{head}bogus = 1\n[[grid]]\nip = [0.9]\n")).contains("bogus"));
        assert!(err(&format!("{head}[base]\nbogus = 1\n[[grid]]\nip = [0.9]\n")).contains("bogus"));
        assert!(err(&format!("{head}[[grid]]\nipp = [0.9]\n")).contains("grid[0].ipp"));
        let e = err(&format!("{head}[base]\nlocality = \"1:100\"\n[[grid]]\nip = [0.9]\n"));
        assert!(e.contains("base.locality: \"1:100\""), "{e}");
        assert!(err(&format!("{head}[[grid]]\nip = []\n")).contains("grid[0].ip: is an empty list"));
        assert!(err(&format!("{head}[[grid]]\nip = [0.5, 1.5]\n")).contains("grid[0].ip[1]"));
        assert!(err(head).contains("grid: no conditions"));
        assert!(err("tasks = []\nseeds = 1\n[[grid]]\nip = 0.9\n").contains("tasks"));
        assert!(err("tasks = [\"foraging\"]\nseeds = 0\n[[grid]]\nip = 0.9\n").contains("seeds"));
        assert!(err("seeds = 1\n[[grid]]\nip = 0.9\n").contains("tasks"));
        assert!(err(&format!("{head}[[grid]]\nip = [0.8, 0.9]\nst = [5, 7]\n")).contains("x: several knobs vary"));
        assert!(err(&format!("{head}x = \"size\"\n[[grid]]\nip = [0.9]\n")).contains("x: 'size' is not set"));
        assert!(err(&format!("{head}[[grid]]\nobstacles = [2]\n")).contains("obstacles: needs `obstacles_at`"));
        assert!(err(&format!("{head}[base]\nsteps = 100\n[[grid]]\nkill = 0.5\nkill_at = 100\n")).contains("kill_at"));
        assert!(err(&format!("{head}[[grid]]\ngrid = [7]\n")).contains("grid"));
        assert!(err(&format!("{head}[[grid]]\ngrammar = \"no-such-grammar\"\n")).contains("no-such-grammar"));
    }

    /// `n` distinct levels of the `ip` knob.
    fn ips(n: usize) -> String {
        let v: Vec<String> = (0..n).map(|i| format!("{}", i as f64 / n as f64)).collect();
        format!("ip = [{}]\n", v.join(", "))
    }

    /// `n` distinct levels of the `st` knob.
    fn sts(n: usize) -> String {
        let v: Vec<String> = (4..4 + n).map(|i| i.to_string()).collect();
        format!("st = [{}]\n", v.join(", "))
    }

    #[test]
    fn campaign_sizes_are_bounded() {
        let seeds = |n: u32| format!("tasks = [\"foraging\"]\nseeds = {n}\n[[grid]]\nip = 0.9\n");
        assert!(Campaign::from_toml(&seeds(MAX_SEEDS), "t").is_ok());
        let e = err(&seeds(MAX_SEEDS + 1));
        assert!(e.contains("seeds: 10001 exceeds 10000"), "{e}");
        assert!(err(&seeds(u32::MAX)).contains("seeds: 4294967295 exceeds"));

        // A product of 101 × 100 levels is refused before it is built.
        let head = "tasks = [\"foraging\"]\nseeds = 1\nx = \"condition\"\n";
        let e = err(&format!("{head}[[grid]]\n{}{}", ips(101), sts(100)));
        assert!(e.contains("grid[0]: 101 ip × 100 st levels make more than 10000 conditions"), "{e}");
        // Two tables of 6,000 each: the union is too large.
        let e = err(&format!("{head}[[grid]]\n{}{}[[grid]]\n{}{}", ips(60), sts(100), ips(61), sts(100)));
        assert!(e.contains("grid: 12000 conditions exceed 10000"), "{e}");
        // Conditions × tasks × seeds.
        let text = format!("tasks = [\"foraging\", \"nest\"]\nseeds = 10000\nx = \"condition\"\n[[grid]]\n{}", ips(51));
        let e = err(&text);
        assert!(e.contains("seeds: 51 conditions × 2 tasks × 10000 seeds = 1020000 trials exceed 1000000"), "{e}");
    }

    #[test]
    fn shipped_campaign_files_are_valid() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../campaigns");
        let mut n = 0;
        for sub in [dir.clone(), dir.join("smoke")] {
            for e in std::fs::read_dir(&sub).unwrap() {
                let p = e.unwrap().path();
                if p.extension().is_some_and(|x| x == "toml") {
                    let c = Campaign::from_file(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
                    assert!(c.x.is_some() || c.x_by_condition, "{}: no x knob", p.display());
                    n += 1;
                }
            }
        }
        assert!(n >= 18, "only {n} campaign files");
    }
}
