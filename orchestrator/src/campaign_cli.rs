//! The `geese campaign`, `geese merge`, `geese report`, `geese slopes` and `geese export` subcommands (binary only):
//! argument parsing and printing around the library's campaign, store and report.
use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use geese_orchestrator::analysis::metrics::{EfficiencyVariant, PowerVariant};
use geese_orchestrator::analysis::report::{self, EfficiencyChoice, ReportOptions};
use geese_orchestrator::campaigns::campaign::{
    Campaign, CampaignError, CampaignFile, InProcess, RunOptions, TrialRunner,
};
use geese_orchestrator::campaigns::merge;
use geese_orchestrator::campaigns::shard::{self, Shard};
use geese_orchestrator::campaigns::store::Store;
use geese_orchestrator::distributed::launch::{NetOptions, OverZenoh};
use geese_proto::zenoh_bus::CommonArgs;
use std::path::PathBuf;

#[derive(Args)]
pub struct CampaignArgs {
    /// Campaign file (TOML; see campaigns/ and the README).
    pub file: PathBuf,
    /// Results database (default results/<campaign name>.sqlite, with --shard
    /// results/<campaign name>.shard-I-of-N.sqlite). An existing database of the same
    /// campaign (and shard) is resumed: finished trials are not run again.
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// Run only shard I of N: a deterministic, cost-balanced 1/N of the trials (every
    /// shard computes the same split from the campaign alone). I counts from 1, as
    /// $SLURM_ARRAY_TASK_ID does with --array=1-N. Combine the shards' databases with
    /// `geese merge`.
    #[arg(long, value_name = "I/N")]
    pub shard: Option<Shard>,
    /// Trials run at once (default: one per core).
    #[arg(long, short = 'j')]
    pub jobs: Option<usize>,
    /// Run trials that failed in an earlier invocation again.
    #[arg(long)]
    pub retry_failed: bool,
    /// Override the file's number of seeds.
    #[arg(long)]
    pub seeds: Option<u32>,
    /// Override the base number of steps.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Override the base number of agents.
    #[arg(long)]
    pub agents: Option<u32>,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
    /// Run every trial distributed: its own world server and N agent processes on this
    /// machine, over Zenoh (trials then run one at a time unless --jobs says otherwise).
    #[arg(long, value_name = "N")]
    pub processes: Option<u32>,
    /// Agents hosted per agent process [default: the agents split evenly over N].
    #[arg(long, value_name = "K", requires = "processes")]
    pub agents_per_process: Option<u32>,
    /// Directory of geese-world and geese-agent [default: next to geese].
    #[arg(long, requires = "processes")]
    pub bin_dir: Option<PathBuf>,
    #[command(flatten)]
    pub zenoh: CommonArgs,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum EfficiencyArg {
    /// (T − t80)/T · 100 (the paper).
    Paper,
    /// The reference-code variant the campaign file names (code_efficiency).
    Code,
    /// Reference code, Sec. 5 ablation (t_min = 5200).
    Sec5Ablation,
    /// Reference code, Sec. 5 addition/distortion/shift (t_min = 2756, absolute).
    Sec5,
    /// Reference code, Sec. 7 (t_min = fastest trial of the condition).
    Sec7,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum PowerArg {
    /// Maximum success probability before T (the paper).
    Paper,
    /// Task % after the last step (the reference code).
    Code,
}

#[derive(Args)]
pub struct ReportArgs {
    /// Results database written by `geese campaign`.
    pub db: PathBuf,
    /// Directory for the figures and metric CSVs (default: <db without extension>-report).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub metrics: MetricArgs,
    /// Tables only, no figures.
    #[arg(long)]
    pub no_plots: bool,
}

#[derive(Args)]
pub struct SlopesArgs {
    /// Results databases written by `geese campaign` (e.g. an ablation and an addition
    /// campaign run with `series = "mutation"`).
    #[arg(required = true)]
    pub dbs: Vec<PathBuf>,
    /// Figure to write, without extension (PNG and SVG): one row per task, a power and
    /// an efficiency panel per campaign, one fitted line per series level.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub metrics: MetricArgs,
}

/// How `geese report` and `geese slopes` compute power and efficiency.
#[derive(Args, Clone, Copy)]
pub struct MetricArgs {
    #[arg(long, value_enum, default_value = "paper")]
    pub efficiency: EfficiencyArg,
    #[arg(long, value_enum, default_value = "paper")]
    pub power: PowerArg,
    /// Use at most the first N trials per (task, x level), as the reference plots (40).
    #[arg(long)]
    pub cap: Option<usize>,
}

#[derive(Args)]
pub struct MergeArgs {
    /// Results database to merge into (created if needed; one that already holds some
    /// of the campaign's trials is completed).
    pub out: PathBuf,
    /// Databases of the campaign's shards (`geese campaign --shard I/N`), in any order.
    #[arg(required = true)]
    pub shards: Vec<PathBuf>,
}

#[derive(Args)]
pub struct ExportArgs {
    /// Results database written by `geese campaign`.
    pub db: PathBuf,
    /// Directory for trials.csv, steps.csv, sessions.csv and manifest.json.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn campaign_cmd(a: CampaignArgs) -> Result<()> {
    let text =
        std::fs::read_to_string(&a.file).with_context(|| format!("cannot read campaign {}", a.file.display()))?;
    let mut file: CampaignFile =
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("campaign {}: {e}", a.file.display()))?;
    if let Some(v) = a.seeds {
        file.seeds = v;
    }
    if let Some(v) = a.steps {
        file.base.steps = v;
    }
    if let Some(v) = a.agents {
        file.base.world.agents = v;
    }
    let stem = a.file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "campaign".into());
    let campaign = Campaign::new_in(file, text, &stem, a.file.parent())
        .with_context(|| format!("campaign {}", a.file.display()))?;
    let db = a.db.clone().unwrap_or_else(|| match a.shard {
        Some(s) => PathBuf::from(format!("results/{}.{}.sqlite", campaign.name, s.file_tag())),
        None => PathBuf::from(format!("results/{}.sqlite", campaign.name)),
    });
    let mut store = Store::create(&db)?;
    // The transport is chosen here; both runners report the same steps for a seed.
    let over_zenoh = a.processes.map(|processes| OverZenoh {
        opts: NetOptions {
            processes,
            agents_per_process: a.agents_per_process,
            zenoh: a.zenoh.clone(),
            bin_dir: a.bin_dir.clone(),
            quiet_children: true,
            ..NetOptions::default()
        },
    });
    let runner: &dyn TrialRunner = match &over_zenoh {
        Some(z) => z,
        None => &InProcess,
    };
    let plan = campaign.plan();
    let part = a.shard.map(|s| (s, shard::plan(&campaign, s).len()));
    // A distributed trial already spreads over the cores: one at a time by default.
    let jobs = a.jobs.unwrap_or(if over_zenoh.is_some() { 1 } else { 0 });
    let threads = if jobs == 0 { std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1) } else { jobs };
    let of_them = part.map(|(s, n)| format!(", shard {s}: {n} of them")).unwrap_or_default();
    eprintln!(
        "geese campaign {}: {} conditions × {} task(s) × {} seeds = {} trials{of_them}, {} at a time ({}), results in {}",
        campaign.name,
        campaign.conditions.len(),
        campaign.file.tasks.len(),
        campaign.file.seeds,
        plan.len(),
        threads,
        runner.transport(),
        db.display()
    );
    let opts = RunOptions { jobs, retry_failed: a.retry_failed, quiet: a.quiet, shard: a.shard };
    let out = match geese_orchestrator::campaigns::campaign::run_campaign(&campaign, &mut store, runner, &opts) {
        Err(e @ CampaignError::Interrupted { .. }) => {
            eprintln!("{e}");
            std::process::exit(130)
        }
        r => r?,
    };
    println!(
        "{} trials planned: {} already stored, {} run now ({} done, {} failed)",
        out.planned,
        out.skipped,
        out.done + out.failed,
        out.done,
        out.failed
    );
    println!("wall time: {:.1} s", out.wall_seconds);
    let (sessions, total) = store.campaign_wall()?;
    if sessions > 1 {
        println!("campaign wall time over {sessions} invocations: {total:.1} s");
    }
    match a.shard {
        Some(s) => println!("results of shard {s}: {}  (geese merge OUT.sqlite <the N shard databases>)", db.display()),
        None => println!("results: {}  (geese report {})", db.display(), db.display()),
    }
    Ok(())
}

pub fn merge_cmd(a: MergeArgs) -> Result<()> {
    let start = std::time::Instant::now();
    let o = merge::merge(&a.out, &a.shards)?;
    println!(
        "merged {} database(s) into {}: {} trial(s) added, {} already there, {} failed trial(s) replaced by finished ones",
        a.shards.len(),
        a.out.display(),
        o.added,
        o.already,
        o.replaced_failed
    );
    let of = o.planned.map(|p| format!(" of the campaign's {p}")).unwrap_or_default();
    println!("{} now holds {} trial(s){of}: {} done, {} failed", a.out.display(), o.trials, o.done, o.failed);
    if !o.shards.is_empty() {
        println!("shards merged: {}", o.shards.join(" "));
    }
    if !o.missing_shards.is_empty() {
        println!("shards not merged yet: {}", o.missing_shards.join(" "));
    }
    for p in &o.unfinished {
        println!(
            "note: the last invocation of {} did not finish (still running, or stopped): resume it and merge again",
            p.display()
        );
    }
    if o.versions_differ {
        println!("note: the databases were written by different geese versions (see their manifests)");
    }
    println!("merge time: {:.2} s", start.elapsed().as_secs_f64());
    Ok(())
}

fn report_options(m: &MetricArgs) -> Result<ReportOptions> {
    let MetricArgs { efficiency, power, cap } = *m;
    if cap == Some(0) {
        anyhow::bail!("--cap: must be at least 1");
    }
    Ok(ReportOptions {
        efficiency: match efficiency {
            EfficiencyArg::Paper => EfficiencyChoice::Paper,
            EfficiencyArg::Code => EfficiencyChoice::Code,
            EfficiencyArg::Sec5Ablation => EfficiencyChoice::Variant(EfficiencyVariant::Sec5Ablation),
            EfficiencyArg::Sec5 => EfficiencyChoice::Variant(EfficiencyVariant::Sec5),
            EfficiencyArg::Sec7 => EfficiencyChoice::Variant(EfficiencyVariant::Sec7),
        },
        power: match power {
            PowerArg::Paper => PowerVariant::Paper,
            PowerArg::Code => PowerVariant::Code,
        },
        cap,
    })
}

pub fn report_cmd(a: ReportArgs) -> Result<()> {
    let store = Store::open(&a.db)?;
    let opts = report_options(&a.metrics)?;
    let r = report::build(&store, &opts)?;
    r.print(&mut std::io::stdout().lock())?;
    let (sessions, wall) = store.campaign_wall()?;
    println!("\ncampaign wall time: {wall:.1} s over {sessions} invocation(s) of geese campaign");
    let out = a.out.clone().unwrap_or_else(|| {
        let stem = a.db.file_stem().map(|s| s.to_string_lossy().into_owned());
        a.db.with_file_name(format!("{}-report", stem.unwrap_or_else(|| "results".into())))
    });
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut files = r.write_csv(&out)?;
    if !a.no_plots {
        files.extend(r.plot(&store, &out)?);
    }
    println!("\nwrote {} files to {}", files.len(), out.display());
    Ok(())
}

/// The power and efficiency slopes of several campaigns, per series level, in one table
/// and one figure (issue 30.3: the four slopes of ablation and addition, both mutation
/// rules).
pub fn slopes_cmd(a: SlopesArgs) -> Result<()> {
    let opts = report_options(&a.metrics)?;
    let mut reports = Vec::new();
    for db in &a.dbs {
        let store = Store::open(db)?;
        let r = report::build(&store, &opts).with_context(|| format!("report of {}", db.display()))?;
        if r.points.is_empty() {
            anyhow::bail!("{}: no finished trial to fit", db.display());
        }
        reports.push(r);
    }
    let out = std::io::stdout();
    let files = report::slopes(&reports, &a.out, &mut out.lock())?;
    println!("\nwrote {}", files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", "));
    Ok(())
}

pub fn export_cmd(a: ExportArgs) -> Result<()> {
    let store = Store::open(&a.db)?;
    let files = store.export_csv(&a.out)?;
    for f in &files {
        println!("{}", f.display());
    }
    Ok(())
}
