//! `geese`: run GEESE trials, inspect grammars, benchmark the core.
// Doc comments of clap arguments are also `--help` text, where `<run>` or `<db>` reads
// as a placeholder; rustdoc would take them for HTML tags.
#![allow(rustdoc::invalid_html_tags)]
use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use geese_agent::bt::{Bt, TreeFormat};
use geese_agent::ge::{self, GeParams};
use geese_agent::FitnessVariant;
use geese_agent::Program;
use geese_orchestrator::campaigns::campaign::{run_stages, TrialError, TrialRunner};
use geese_orchestrator::run::config::{load_grammar, read_population, FollowUp, RunConfig};
use geese_orchestrator::run::output::{write_locality, write_manifest, StepCsv};
use geese_orchestrator::run::trial::Ran;
use geese_orchestrator::{run::bench, Trial};
use geese_proto::StepReport;
use geese_world::{Layout, Task};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

mod campaign_cli;
use campaign_cli::{CampaignArgs, ExportArgs, MergeArgs, ReportArgs, SlopesArgs};

#[derive(Parser)]
#[command(name = "geese", version, about = "Online evolution of resilient swarm behaviours (BeTr-GEESE)")]
struct Cli {
    /// Check the command line and exit 0 without running anything: the flags, values and
    /// subcommands as clap parses them, not the files they name. Hidden; the test of
    /// docs/REPRODUCTION.md checks every command there with it (`geese --check-args …`).
    #[arg(long, hide = true)]
    check_args: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run one trial (defaults: the paper's foraging setting).
    Run(RunArgs),
    /// Inspect grammars: map a genome, print the behaviour tree, list built-ins, the
    /// Table 2 metrics.
    Grammar {
        #[command(subcommand)]
        cmd: GrammarCmd,
    },
    /// Benchmark the simulation core: learning agent-steps per second on one thread.
    Bench(BenchArgs),
    /// Benchmark the distributed runtime: lock-step rate over Zenoh, bare and learning.
    BenchNet(geese_orchestrator::distributed::bench_net::BenchNetArgs),
    /// Run a plain Zenoh router (default tcp/127.0.0.1:7447) for --router set-ups.
    Router(geese_orchestrator::distributed::launch::RouterArgs),
    /// Run a campaign file (conditions × tasks × seeds) into a results database;
    /// re-running it resumes where it stopped.
    Campaign(CampaignArgs),
    /// Combine the databases of a campaign's shards (geese campaign --shard I/N) into
    /// one results database, read by report and export as if run unsharded.
    Merge(MergeArgs),
    /// Print metric tables and draw figures from a results database.
    Report(ReportArgs),
    /// Power and efficiency slopes of several campaigns, one line per series level (e.g.
    /// fixed vs stress mutation), in one table and one figure.
    Slopes(SlopesArgs),
    /// Export a results database to CSV files.
    Export(ExportArgs),
    /// Draw a run's locality map (Fig. 5, from `geese run --locality`): one panel per
    /// behaviour class, PNG and SVG.
    Locality(LocalityArgs),
    /// Send a perturbation or stop to a running distributed world (control plane).
    Control(geese_orchestrator::live::control::ControlArgs),
    /// Make the credentials and access-control list of a run whose processes are
    /// started by hand or on several hosts (`geese run --processes N` makes its own).
    Secure {
        #[command(subcommand)]
        cmd: geese_orchestrator::distributed::secure::SecureCmd,
    },
    /// Watch a running distributed run in the browser (a read-only client of its bus;
    /// its controls go through the control plane).
    View(geese_orchestrator::live::view::ViewArgs),
}

#[derive(Clone, Copy, ValueEnum)]
enum TaskArg {
    Foraging,
    Nest,
}

#[derive(Clone, Copy, ValueEnum)]
enum LayoutArg {
    Reference,
    Paper,
}

#[derive(Clone, Copy, ValueEnum)]
enum FitnessArg {
    Code,
    Paper,
}

/// Run options; each overrides the same setting of `--config`.
#[derive(Args)]
struct RunArgs {
    /// TOML config file (see README); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    #[arg(long, value_enum)]
    task: Option<TaskArg>,
    /// Number of agents N.
    #[arg(long)]
    agents: Option<u32>,
    #[arg(long)]
    steps: Option<u64>,
    #[arg(long)]
    seed: Option<u64>,
    /// Interaction probability IP in [0, 1].
    #[arg(long)]
    ip: Option<f64>,
    /// Storage threshold ST (≥ 4) [default: 7; multi-geese 10, the reference code's]
    #[arg(long)]
    st: Option<usize>,
    /// Grid size GS (must divide half the arena).
    #[arg(long)]
    gs: Option<i32>,
    /// Built-in grammar name or .bnf file (default: the algorithm's, for the task).
    #[arg(long)]
    grammar: Option<String>,
    /// Learning algorithm: betr-geese, geese-bt or multi-geese.
    #[arg(long)]
    algorithm: Option<geese_agent::Algorithm>,
    /// Mutation rule: fixed (GE's mutation_prob; the default) or stress (rises while an
    /// agent's fitness stalls or falls; constants under [learner.stress]).
    #[arg(long)]
    mutation: Option<String>,
    /// Multi-GEESE: run one phase alone (collect, or combine with --collect-population).
    #[arg(long)]
    phase: Option<geese_agent::Phase>,
    /// The collect population.json a combine phase starts from.
    #[arg(long)]
    collect_population: Option<PathBuf>,
    /// Run this fixed population (population.json) instead of learning.
    #[arg(long)]
    population: Option<PathBuf>,
    /// Fraction of the population's best members to run (fixed runs; with no
    /// --population, learn first and then test the learned population).
    #[arg(long)]
    sample: Option<f64>,
    /// How a fixed population is handed out: parallel or top-agents.
    #[arg(long)]
    strategy: Option<geese_agent::Strategy>,
    /// Fitness terms summed by the learners, e.g. E+B or D+E+C+F (default: the
    /// algorithm's own).
    #[arg(long)]
    terms: Option<geese_agent::FitnessTerms>,
    /// How the Multi-GEESE combine phase learns: faithful (the reference code's, the
    /// default), delivery, keep-deliverers, delivery-keep, patient or patient-delivery (issue 30.1,
    /// docs/research/fusion-takeoff.md).
    #[arg(long)]
    fusion: Option<geese_agent::learner::Fusion>,
    /// World layout (default reference; a fixed --population without --config runs
    /// in the paper's fixed-agent world).
    #[arg(long, value_enum)]
    layout: Option<LayoutArg>,
    #[arg(long, value_enum)]
    fitness: Option<FitnessArg>,
    /// Switch lateral transfer off for the whole run.
    #[arg(long)]
    no_lateral_transfer: bool,
    /// Step schedule: simultaneous (DESIGN §2) or sequential (the reference code's
    /// turns in id order; in one process only).
    #[arg(long, value_enum)]
    schedule: Option<geese_orchestrator::run::config::Schedule>,
    /// Blackboard scope: per-agent (DESIGN §2) or global (the reference code's one
    /// shared map; in one process only).
    #[arg(long, value_enum)]
    blackboard: Option<geese_orchestrator::run::config::Blackboard>,
    /// Genes a cell-mate passes on: copied (DESIGN §2) or shared (the reference code's
    /// gene objects, one fitness field for all holders; in one process only).
    #[arg(long, value_enum)]
    genes: Option<geese_orchestrator::run::config::Genes>,
    /// Count the locality map (Fig. 5) over steps FROM to TO, both included (step 1 is
    /// the first step) into locality.csv; draw it with `geese locality`.
    #[arg(long, value_name = "FROM:TO")]
    locality: Option<String>,
    /// Threads stepping an in-process trial [default: the machine's cores, at most one
    /// per 200 agents; 1 with --schedule, --blackboard or --genes]. The results are the
    /// same for every value.
    #[arg(long)]
    threads: Option<u32>,
    /// Output directory (default results/<task>-seed<seed>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
    /// Serve a live view of the run on http://127.0.0.1:PORT (printed at start).
    #[arg(long)]
    view: bool,
    /// The viewer's port (0: any free one).
    #[arg(long, default_value_t = 0, requires = "view")]
    view_port: u16,
    /// With --view: make at most this many steps per second from the start (the page
    /// can change it; 0 = no limit) [default: 20, so that the first look is watchable:
    /// unpaced, a default trial ends in seconds].
    #[arg(long, requires = "view")]
    step_rate: Option<f64>,
    /// Distributed mode (issue 3): --processes N and its options.
    #[command(flatten)]
    net: Box<geese_orchestrator::distributed::launch::NetArgs>,
}

impl RunArgs {
    fn resolve(&self) -> Result<RunConfig> {
        let mut c = match &self.config {
            Some(p) => RunConfig::from_file(p)?,
            None => RunConfig::default(),
        };
        if let Some(t) = self.task {
            c.world.task = match t {
                TaskArg::Foraging => Task::Foraging,
                TaskArg::Nest => Task::Nest,
            };
        }
        if let Some(v) = self.agents {
            c.world.agents = v;
        }
        if let Some(v) = self.steps {
            c.steps = v;
        }
        if let Some(v) = self.seed {
            c.seed = v;
        }
        if let Some(v) = self.ip {
            c.ip = v;
        }
        if let Some(v) = self.st {
            c.learner.st = Some(v);
        }
        if let Some(v) = self.gs {
            c.world.grid = v;
        }
        if let Some(v) = &self.grammar {
            c.grammar = Some(v.clone());
        }
        if let Some(v) = self.algorithm {
            c.algorithm = v;
        }
        if let Some(v) = &self.mutation {
            c.learner.mutation = v.parse().map_err(|e: String| anyhow::anyhow!("--mutation: {e}"))?;
        }
        if let Some(v) = self.phase {
            c.phase = Some(v);
        }
        if let Some(v) = &self.collect_population {
            c.collect_population = Some(v.clone());
        }
        if let Some(v) = &self.population {
            c.population = Some(v.clone());
            if self.config.is_none() && self.layout.is_none() {
                // The fixed-agent world of REFERENCE §1.4 (agents start at the hub).
                c.world.layout = Layout::Paper;
            }
        }
        if let Some(v) = self.sample {
            c.sample = Some(v);
        }
        if let Some(v) = self.strategy {
            c.strategy = Some(v);
        }
        if let Some(v) = self.terms {
            c.learner.terms = Some(v);
        }
        if let Some(v) = self.fusion {
            c.learner.fusion = v;
        }
        if let Some(l) = self.layout {
            c.world.layout = match l {
                LayoutArg::Reference => Layout::Reference,
                LayoutArg::Paper => Layout::Paper,
            };
        }
        if let Some(f) = self.fitness {
            c.learner.fitness = match f {
                FitnessArg::Code => FitnessVariant::Code,
                FitnessArg::Paper => FitnessVariant::Paper,
            };
        }
        if self.no_lateral_transfer {
            c.lateral_transfer = false;
        }
        if let Some(v) = self.schedule {
            c.fidelity.schedule = v;
        }
        if let Some(v) = self.blackboard {
            c.fidelity.blackboard = v;
        }
        if let Some(v) = self.genes {
            c.fidelity.genes = v;
        }
        if let Some(w) = &self.locality {
            c.locality = Some(w.clone());
        }
        if let Some(n) = self.threads {
            c.threads = Some(n);
        }
        Ok(c)
    }
}

#[derive(Args)]
struct LocalityArgs {
    /// A run's output directory (its locality.csv and manifest.json) or a locality.csv.
    path: PathBuf,
    /// Write <PREFIX>.png and <PREFIX>.svg [default: locality beside the CSV].
    #[arg(long, value_name = "PREFIX")]
    out: Option<PathBuf>,
}

fn locality_cmd(a: LocalityArgs) -> Result<()> {
    let map = geese_orchestrator::analysis::locality::load(&a.path)?;
    if map.manifest.is_none() {
        eprintln!(
            "no manifest with a locality section beside {}: arena from the data, no landmarks",
            map.csv.display()
        );
    }
    let stem = a.out.unwrap_or_else(|| map.csv.with_file_name("locality"));
    if let Some(d) = stem.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).with_context(|| format!("cannot create {}", d.display()))?;
    }
    let t = map.totals();
    println!(
        "agent-steps by class: none {}, Explore {}, CompositeSingleCarry {}, CompositeDrop {}, MoveTowards {}, MoveAway {}",
        t[0], t[1], t[2], t[3], t[4], t[5]
    );
    for p in map.draw(&stem)? {
        println!("wrote {}", p.display());
    }
    Ok(())
}

#[derive(Subcommand)]
enum GrammarCmd {
    /// Map a genome; prints {"valid","used_codons","depth","phenotype","diversity"}.
    Map(MapArgs),
    /// Print the behaviour tree a genome or a population member builds, as text, a
    /// Graphviz digraph or an SVG picture.
    Tree(TreeArgs),
    /// List the built-in grammars.
    List,
    /// Print a grammar's modularity metrics (the paper's Table 2, REFERENCE §8.3).
    Metrics(MetricsArgs),
}

#[derive(Args)]
struct MetricsArgs {
    /// Built-in grammar name or .bnf file.
    #[arg(long)]
    grammar: String,
    /// One JSON object instead of the table.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct MapArgs {
    /// Built-in grammar name or .bnf file.
    #[arg(long)]
    grammar: String,
    /// Comma-separated codons, e.g. 1213,1114,267
    #[arg(long)]
    genome: String,
    #[command(flatten)]
    limits: MapLimitArgs,
}

/// The GE parameters a genome is mapped with.
#[derive(Args)]
struct MapLimitArgs {
    #[arg(long, default_value_t = 2000)]
    codon_size: u32,
    #[arg(long, default_value_t = 10)]
    max_depth: usize,
    #[arg(long, default_value_t = 0)]
    max_wraps: usize,
}

/// A tree from a genome (`--grammar` and `--genome`) or from a population file
/// (`--population` and `--member`).
#[derive(Args)]
#[command(group(clap::ArgGroup::new("source").required(true).args(["grammar", "population"])))]
struct TreeArgs {
    /// Built-in grammar name or .bnf file (with --genome).
    #[arg(long, requires = "genome")]
    grammar: Option<String>,
    /// Comma-separated codons, e.g. 1213,1114,267 (with --grammar).
    #[arg(long, requires = "grammar")]
    genome: Option<String>,
    #[command(flatten)]
    limits: MapLimitArgs,
    /// A population file (population.json); draw its member --member.
    #[arg(long, requires = "member")]
    population: Option<PathBuf>,
    /// 0-based index of the member, best first (as a fixed run ranks them).
    #[arg(long, value_name = "K", requires = "population")]
    member: Option<usize>,
    /// text (indented listing), dot (Graphviz) or svg (a picture).
    #[arg(long, default_value = "text")]
    format: TreeFormat,
    /// Write to this file instead of standard output.
    #[arg(long)]
    output: Option<PathBuf>,
}

#[derive(Args)]
struct BenchArgs {
    #[arg(long, default_value_t = 100)]
    agents: u32,
    #[arg(long, default_value_t = 12_000)]
    steps: u64,
    #[arg(long, value_enum, default_value = "foraging")]
    task: TaskArg,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Repetitions (different seeds from --seed on).
    #[arg(long, default_value_t = 1)]
    repeat: u32,
    /// Instead of the trial, time one genetic step and one mapping (forge.bnf).
    #[arg(long)]
    micro: bool,
    /// Count the locality map over steps FROM:TO, as `geese run --locality` (to time its
    /// cost).
    #[arg(long, value_name = "FROM:TO")]
    locality: Option<String>,
    /// Threads stepping the trial (its results do not depend on them).
    #[arg(long, default_value_t = 1)]
    threads: u32,
    /// Arena width (default 100; 1000 keeps 10,000 agents at the default density).
    #[arg(long)]
    width: Option<i32>,
    /// Arena height (default: the width).
    #[arg(long)]
    height: Option<i32>,
}

fn parse_genome(s: &str) -> Result<Vec<u32>> {
    let mut g = Vec::new();
    for (i, tok) in s.split(',').enumerate() {
        let tok = tok.trim();
        if tok.is_empty() {
            bail!("genome: codon {} is empty (expected comma-separated non-negative integers)", i + 1);
        }
        let v: u32 =
            tok.parse().with_context(|| format!("genome: codon {} ('{tok}') is not a non-negative integer", i + 1))?;
        g.push(v);
    }
    Ok(g)
}

fn ge_params(a: &MapLimitArgs) -> Result<GeParams> {
    let p = GeParams {
        codon_size: a.codon_size,
        max_tree_depth: a.max_depth,
        max_wraps: a.max_wraps,
        ..GeParams::default()
    };
    p.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(p)
}

fn grammar_cmd(cmd: GrammarCmd) -> Result<()> {
    match cmd {
        GrammarCmd::List => {
            for n in geese_agent::grammars::names() {
                println!("{n}");
            }
        }
        GrammarCmd::Metrics(a) => {
            let (g, text) = load_grammar(&a.grammar)?;
            let m = ge::GrammarMetrics::compute(&g, &text);
            if a.json {
                /// The grammar's name first, then the metrics in Table 2's order.
                #[derive(serde::Serialize)]
                struct Named<'a> {
                    grammar: &'a str,
                    #[serde(flatten)]
                    metrics: &'a ge::GrammarMetrics,
                }
                println!("{}", serde_json::to_string(&Named { grammar: &a.grammar, metrics: &m })?);
            } else {
                println!("grammar {}", a.grammar);
                print!("{m}");
            }
        }
        GrammarCmd::Map(a) => {
            let (g, _) = load_grammar(&a.grammar)?;
            let genome = parse_genome(&a.genome)?;
            let p = ge_params(&a.limits)?;
            let ind = ge::evaluate(&g, genome, &p);
            let v = match &ind.phenotype {
                Some(ph) => serde_json::json!({
                    "valid": true,
                    "used_codons": ind.used_codons,
                    "depth": ind.depth,
                    "phenotype": ph.as_ref(),
                    "diversity": ind.fitness,
                }),
                None => serde_json::json!({ "valid": false }),
            };
            println!("{v}");
        }
        GrammarCmd::Tree(a) => {
            let picture = tree_of(&a)?.draw(a.format);
            match &a.output {
                Some(path) => {
                    std::fs::write(path, picture).with_context(|| format!("cannot write {}", path.display()))?
                }
                None => print!("{picture}"),
            }
        }
    }
    Ok(())
}

/// The tree `geese grammar tree` draws: a genome's under its grammar, or a population
/// member's as a run builds it.
fn tree_of(a: &TreeArgs) -> Result<Bt> {
    if let (Some(path), Some(k)) = (&a.population, a.member) {
        let pop = read_population(path)?;
        return pop.member_tree(k).with_context(|| format!("population {}, --member {k}", path.display()));
    }
    let (Some(grammar), Some(genome)) = (&a.grammar, &a.genome) else {
        bail!("give --grammar and --genome, or --population and --member");
    };
    let (g, _) = load_grammar(grammar)?;
    let genome = parse_genome(genome)?;
    let p = ge_params(&a.limits)?;
    let ind = ge::evaluate(&g, genome, &p);
    let Some(ph) = &ind.phenotype else {
        bail!("the genome is invalid under this grammar (its derivation does not finish)");
    };
    let root = ge::parse_phenotype(ph).map_err(|e| anyhow::anyhow!("phenotype: {e}"))?;
    Bt::from_pnode(&root).map_err(|e| anyhow::anyhow!("behaviour tree: {e}"))
}

/// The pace of a viewed run when none is asked for: a default trial unpaced ends in
/// seconds, and the page would show only its last frame.
const VIEW_STEP_RATE: f64 = 20.0;

/// The step-rate limit a run starts with: `--step-rate`, or [`VIEW_STEP_RATE`] with
/// `--view`.
fn view_step_rate(a: &RunArgs) -> Option<f64> {
    a.step_rate.or(a.view.then_some(VIEW_STEP_RATE))
}

fn run_cmd(a: RunArgs) -> Result<()> {
    let mut cfg = a.net.apply(a.resolve()?);
    let mut net = a.net.options()?;
    match (&net, cfg.threads) {
        (Some(_), Some(n)) => bail!(
            "--threads {n}: threads step an in-process trial; with --processes every agent process \
             steps its own agents (drop --threads or --processes)"
        ),
        (None, None) => cfg.threads = Some(cfg.auto_threads()),
        _ => {}
    }
    if let Some(n) = net.as_mut() {
        n.view = a.view.then_some(a.view_port);
        n.step_rate = view_step_rate(&a);
    }
    let spec = cfg.validate()?;
    let c = &spec.config;
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from(format!("results/{}-seed{}", c.world.task, c.seed)));
    // Stage by stage (run_stages): a Multi-GEESE collect phase before its combine
    // phase, a learning run before the fixed test of its population. The last stage
    // writes into `out`, earlier ones into `out/<stage>`.
    let watch = match (a.view, &net) {
        (false, _) => None,
        (true, Some(_)) => None,
        (true, None) => {
            let w = geese_orchestrator::live::watch::Watch::start(a.view_port, view_step_rate(&a))?;
            println!("view: {}", w.url());
            if a.step_rate.is_none() {
                println!("pace: {VIEW_STEP_RATE} steps/s while viewed (change it on the page, or --step-rate N; 0 = no limit)");
            }
            Some(w)
        }
    };
    let runner = CliRunner { out, net, quiet: a.quiet, watch: std::sync::Mutex::new(watch) };
    let mut written: Result<()> = Ok(());
    let mut write_population = |s: &geese_orchestrator::RunSpec, _: &Ran, pop: &geese_agent::Population| {
        if s.program.is_fixed() || written.is_err() {
            return;
        }
        let path = runner.dir(s).join("population.json");
        written = std::fs::write(&path, pop.to_json()).with_context(|| format!("cannot write {}", path.display()));
        println!("population: {} ({} members)", path.display(), pop.members.len());
    };
    run_stages(&runner, &spec, &mut |_| {}, &mut write_population, &mut |_| {}, None)
        .map_err(|e| anyhow::anyhow!(e))?;
    written
}

/// `geese run`'s stages: each writes its results into its own directory and prints its
/// lines, in this process or over Zenoh.
struct CliRunner {
    out: PathBuf,
    net: Option<geese_orchestrator::distributed::launch::NetOptions>,
    quiet: bool,
    /// The live viewer of an in-process run (`--view`), shared by its stages.
    watch: std::sync::Mutex<Option<geese_orchestrator::live::watch::Watch>>,
}

impl CliRunner {
    fn dir(&self, spec: &geese_orchestrator::RunSpec) -> PathBuf {
        if spec.follow_up == FollowUp::None {
            self.out.clone()
        } else {
            self.out.join(spec.stage)
        }
    }
}

impl TrialRunner for CliRunner {
    fn transport(&self) -> &str {
        if self.net.is_some() {
            "zenoh"
        } else {
            "in-process"
        }
    }

    fn run(&self, spec: &geese_orchestrator::RunSpec, _: &mut dyn FnMut(&StepReport)) -> Result<Ran, TrialError> {
        let dir = self.dir(spec);
        std::fs::create_dir_all(&dir).with_context(|| format!("cannot create output directory {}", dir.display()))?;
        let ran = match &self.net {
            Some(opts) => net_run_cmd(spec, opts, &dir, self.quiet)?,
            None => {
                let mut watch = self.watch.lock().unwrap_or_else(|e| e.into_inner());
                in_process_run(spec, &dir, self.quiet, watch.as_mut())?
            }
        };
        Ok(ran)
    }
}

/// The line every run prints first.
fn describe(spec: &geese_orchestrator::RunSpec, transport: &str) -> String {
    let c = &spec.config;
    let what = match &*spec.program {
        Program::Fixed { strategy, members } => {
            format!("fixed population of {} members ({strategy:?})", members.len())
        }
        Program::Learn { algorithm, phase: Some(p), .. } => format!("{algorithm} ({p} phase)"),
        Program::Learn { algorithm, .. } => algorithm.to_string(),
    };
    let mut line = format!(
        "geese run: {what}, {} agents{transport}, {} steps, task {}, grammar {}, IP {}, ST {}, GS {}, seed {}",
        c.world.agents,
        c.steps,
        c.world.task,
        spec.grammar_name,
        c.ip,
        c.learner.st.unwrap_or_else(|| c.algorithm.default_st()),
        c.world.grid,
        c.seed
    );
    for n in &spec.notes {
        line.push_str(&format!("\nnote: {n}"));
    }
    line
}

/// After a task switch: how long the new task took to reach the threshold.
fn print_recovery(s: &geese_orchestrator::run::trial::TrialSummary, threshold: f64) {
    if let Some(at) = s.switched_after {
        match s.steps_to_threshold_after_switch {
            Some(n) => println!("task switched after step {at}: the new task reached {threshold} % {n} steps later"),
            None => println!("task switched after step {at}: the new task never reached {threshold} %"),
        }
    }
}

/// One stage in this process; returns the population its agents ended with.
fn in_process_run(
    spec: &geese_orchestrator::RunSpec,
    out: &std::path::Path,
    quiet: bool,
    mut watch: Option<&mut geese_orchestrator::live::watch::Watch>,
) -> Result<Ran> {
    let c = &spec.config;
    let csv_path = out.join("steps.csv");
    let mut csv = StepCsv::create(&csv_path).with_context(|| format!("cannot write {}", csv_path.display()))?;
    eprintln!("{}", describe(spec, ""));
    let bar = if quiet { ProgressBar::hidden() } else { ProgressBar::new(c.steps) };
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} steps  task {msg}  [{elapsed} < {eta}]")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let start = std::time::Instant::now();
    let mut trial = Trial::new(spec)?;
    let mut last: Option<StepReport> = None;
    for _ in 0..c.steps {
        if let Some(w) = watch.as_deref_mut() {
            if !w.before_step(&mut trial, last.as_ref(), c.steps) {
                break;
            }
        }
        let rep = trial.step();
        csv.write(&rep)?;
        if rep.step % 50 == 0 {
            bar.set_position(rep.step);
            bar.set_message(format!("{:.2} %", rep.task_pct));
        }
        if let Some(w) = watch.as_deref_mut() {
            w.after_step(&trial, &rep, c.steps);
        }
        last = Some(rep);
    }
    if let (Some(w), Some(rep)) = (watch, &last) {
        w.finish(&trial, rep, c.steps);
    }
    bar.finish_and_clear();
    csv.finish()?;
    let mut summary = trial.summary().clone();
    summary.wall_seconds = start.elapsed().as_secs_f64();
    if let Some(l) = trial.world.locality() {
        let path = write_locality(out, &l.counts()).with_context(|| format!("cannot write {}", out.display()))?;
        println!("locality map: {} ({} agent-steps over {} steps)", path.display(), l.agent_steps(), l.steps());
    }
    write_manifest(out, spec, "in-process", None, &summary, &[])?;
    println!("final task %: {:.2}", summary.final_task_pct);
    match summary.first_step_at_threshold {
        Some(s) => println!("reached {} % at step {s}", c.threshold),
        None => println!("never reached {} % (max {:.2} %)", c.threshold, summary.max_task_pct),
    }
    print_recovery(&summary, c.threshold);
    println!("wall time: {:.2} s", summary.wall_seconds);
    println!("results: {} and {}", csv_path.display(), out.join("manifest.json").display());
    Ok(Ran { summary, members: trial.members() })
}

/// `geese run --processes N`: the same stage as separate processes over Zenoh.
fn net_run_cmd(
    spec: &geese_orchestrator::RunSpec,
    opts: &geese_orchestrator::distributed::launch::NetOptions,
    out: &std::path::Path,
    quiet: bool,
) -> Result<Ran> {
    let c = &spec.config;
    eprintln!("{}", describe(spec, &format!(" in {} agent processes over Zenoh", opts.processes)));
    let o = geese_orchestrator::distributed::launch::run_cli(spec, opts, out, quiet)?;
    let s = &o.summary;
    if !o.completed {
        println!("stopped at step {} of {} by a control-plane stop (geese control)", s.steps, c.steps);
    }
    println!("final task %: {:.2}", s.final_task_pct);
    match s.first_step_at_threshold {
        Some(st) => println!("reached {} % at step {st}", c.threshold),
        None => println!("never reached {} % (max {:.2} %)", c.threshold, s.max_task_pct),
    }
    print_recovery(s, c.threshold);
    println!(
        "wall time: {:.2} s ({:.1} steps/s once all processes were present)",
        s.wall_seconds,
        o.reports as f64 / o.run_seconds.max(1e-9)
    );
    println!(
        "results: {}, {} and {}",
        out.join("steps.csv").display(),
        out.join("net.csv").display(),
        out.join("manifest.json").display()
    );
    Ok(Ran { summary: o.summary.clone(), members: o.members })
}

fn bench_cmd(a: BenchArgs) -> Result<()> {
    if a.micro {
        use geese_agent::ge::micro;
        println!(
            "geese bench --micro: forge.bnf, ChaCha8 seed {}, best of {} batches of {} genetic steps",
            micro::SEED,
            bench::MICRO_BATCHES,
            bench::MICRO_BATCH
        );
        let r = bench::bench_micro();
        println!(
            "genetic_step (pool of {}, default parameters): {:.2} µs per step (pool clone {:.2} µs excluded)",
            micro::POOL_SIZE,
            r.step.step_us,
            r.step.clone_us
        );
        for t in &r.mapping {
            println!(
                "golden genome using {} codons, padded to {}: map_stats {:.0} ns, map_scored {:.0} ns",
                t.used_codons,
                micro::PADDED_LENGTH,
                t.map_stats_ns,
                t.map_scored_ns
            );
        }
        return Ok(());
    }
    let counting = a.locality.as_deref().map(|w| format!(", locality map over steps {w}")).unwrap_or_default();
    let width = a.width.unwrap_or(geese_world::WorldConfig::default().width);
    let height = a.height.unwrap_or(width);
    let threads = if a.threads == 1 { "one thread".to_string() } else { format!("{} threads", a.threads) };
    println!(
        "geese bench: {} learning agents, {width}x{height} arena, {} steps, {threads}{counting}",
        a.agents, a.steps
    );
    let mut rates = Vec::new();
    let (mut seconds, mut genetic) = (0.0, 0u64);
    for r in 0..a.repeat {
        let mut cfg = RunConfig::default();
        cfg.world.agents = a.agents;
        cfg.steps = a.steps;
        cfg.seed = a.seed + r as u64;
        cfg.locality = a.locality.clone();
        cfg.threads = Some(a.threads);
        cfg.world.width = width;
        cfg.world.height = height;
        cfg.world.task = match a.task {
            TaskArg::Foraging => Task::Foraging,
            TaskArg::Nest => Task::Nest,
        };
        let b = bench::bench_core(cfg)?;
        println!(
            "seed {}: {:.3} s, {:.0} agent-steps/s, {:.1} steps/s, {} genetic steps ({:.2} µs of wall time each), final task {:.2} %",
            a.seed + r as u64,
            b.seconds,
            b.agent_steps_per_sec,
            b.steps as f64 / b.seconds,
            b.genetic_steps,
            b.seconds * 1e6 / b.genetic_steps.max(1) as f64,
            b.final_task_pct
        );
        rates.push(b.agent_steps_per_sec);
        seconds += b.seconds;
        genetic += b.genetic_steps;
    }
    rates.sort_by(|x, y| x.total_cmp(y));
    let median = rates[rates.len() / 2];
    println!("median: {:.0} agent-steps/s, {:.1} steps/s", median, median / a.agents.max(1) as f64);
    match bench::peak_rss_mib() {
        Some(mib) => println!("peak resident memory: {mib:.1} MiB"),
        None => println!("peak resident memory: unknown (no /proc/self/status)"),
    }
    // How fast a run is depends on how many genetic steps its trajectory makes (pools
    // fill faster when agents crowd), so builds whose random streams differ are best
    // compared by the wall time per genetic step over many seeds.
    if a.repeat > 1 {
        println!(
            "all seeds: {:.0} agent-steps/s, {:.2} µs of wall time per genetic step",
            (a.agents as u64 * a.steps * a.repeat as u64) as f64 / seconds,
            seconds * 1e6 / genetic.max(1) as f64
        );
    }
    Ok(())
}

/// mimalloc: the step loop allocates many small, short-lived buffers.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// A user's mistake (a bad value, a missing file) is a message, not a crash: printed
/// with its causes on one line and no stack backtrace, even with `RUST_BACKTRACE` set
/// (anyhow would print the one it captured). Panics, which are bugs, keep theirs.
fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("Error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Errors only, and none of Zenoh's (its crates log under these targets).
const QUIET_ZENOH: &str = "error,zenoh=off,zenoh_transport=off,zenoh_link=off,zenoh_link_tcp=off,\
    zenoh_link_quic=off,zenoh_runtime=off,zenoh_config=off,zenoh_util=off,zenoh_task=off";

fn run() -> Result<()> {
    // Zenoh logs a session's configuration, password included, at debug level.
    let cli = Cli::parse();
    if cli.check_args {
        return Ok(());
    }
    let filter = match tracing_subscriber::EnvFilter::try_from_default_env() {
        Ok(f) => f.add_directive(geese_proto::zenoh_bus::HIDE_SECRETS_DIRECTIVE.parse()?),
        // `geese control` says itself why it has no session (`control::OPEN_WAIT`):
        // Zenoh's own retries would print five ERROR lines with source paths first.
        Err(_) if matches!(cli.cmd, Cmd::Control(_)) => tracing_subscriber::EnvFilter::new(QUIET_ZENOH),
        Err(_) => tracing_subscriber::EnvFilter::new("error"),
    };
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    match cli.cmd {
        Cmd::Run(a) => run_cmd(a),
        Cmd::Grammar { cmd } => grammar_cmd(cmd),
        Cmd::Bench(a) => bench_cmd(a),
        Cmd::BenchNet(a) => geese_orchestrator::distributed::bench_net::bench_net_cmd(a),
        Cmd::Router(a) => geese_orchestrator::distributed::launch::router_cmd(a),
        Cmd::Campaign(a) => campaign_cli::campaign_cmd(a),
        Cmd::Merge(a) => campaign_cli::merge_cmd(a),
        Cmd::Report(a) => campaign_cli::report_cmd(a),
        Cmd::Slopes(a) => campaign_cli::slopes_cmd(a),
        Cmd::Export(a) => campaign_cli::export_cmd(a),
        Cmd::Locality(a) => locality_cmd(a),
        Cmd::Control(a) => geese_orchestrator::live::control::control_cmd(a),
        Cmd::View(a) => geese_orchestrator::live::view::view_cmd(a),
        Cmd::Secure { cmd } => geese_orchestrator::distributed::secure::secure_cmd(cmd),
    }
}
