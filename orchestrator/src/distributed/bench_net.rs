//! `geese bench-net`: throughput of the distributed runtime on this machine.
//!
//! For each scenario (P agent processes × K agents each) it runs, in the same
//! invocation, the **bare** lock-step over the same process topology (the world sends a
//! tick, every agent process answers at once with an empty batch: the bus alone) and the
//! **learning** run (the default foraging trial with P·K agents), and prints wall time,
//! steps per second (from the first step report to the last, start-up excluded), the
//! ratio learning/bare, and the resident memory per agent process; with `--repeat N` it
//! runs each learning scenario N times and adds the minimum, median and maximum rate. It
//! prints figures; it asserts nothing.
use crate::distributed::launch::{run_net, NetOptions, NetOutcome, Security};
use crate::run::config::RunConfig;
use anyhow::{bail, Context, Result};
use std::path::PathBuf;

#[derive(clap::Args, Clone, Debug)]
pub struct BenchNetArgs {
    /// Scenarios PxK or PxK:STEPS (P agent processes hosting K agents each, STEPS learning
    /// steps), comma-separated.
    #[arg(long, default_value = "10x1,100x1,300x1,10x100")]
    pub scenarios: String,
    /// Learning steps of a scenario without :STEPS.
    #[arg(long, default_value_t = 12_000)]
    pub steps: u64,
    /// Steps of the bare lock-step measurement.
    #[arg(long, default_value_t = 2_000)]
    pub bare_steps: u64,
    /// Skip the learning runs (bare lock-step only).
    #[arg(long)]
    pub bare_only: bool,
    /// Learning runs per scenario, one after the other, then their minimum, median and
    /// maximum: the machine's speed drifts over minutes, so one run can mislead.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub repeat: u32,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Directory of geese-world and geese-agent [default: next to geese].
    #[arg(long)]
    pub bin_dir: Option<PathBuf>,
    /// How agent processes read cells: auto, cells or all; a comma-separated list is cycled over the processes.
    #[arg(long)]
    pub subscribe: Option<String>,
    /// Logins and access control: on (what `geese run --processes` does), off
    /// (`--insecure`) or both, interleaved run by run.
    #[arg(long, value_enum, default_value = "on")]
    pub security: BenchSecurity,
    #[command(flatten)]
    pub zenoh: geese_proto::zenoh_bus::CommonArgs,
}

/// The security modes a benchmark measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchSecurity {
    On,
    Off,
    Both,
}

impl BenchSecurity {
    fn modes(self) -> Vec<Security> {
        match self {
            BenchSecurity::On => vec![Security::PerRun],
            BenchSecurity::Off => vec![Security::Off],
            BenchSecurity::Both => vec![Security::PerRun, Security::Off],
        }
    }
}

fn mode_name(s: &Security) -> &'static str {
    if *s == Security::Off {
        "security off"
    } else {
        "security on"
    }
}

/// One scenario: processes × agents per process, learning steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Scenario {
    pub processes: u32,
    pub per_process: u32,
    pub steps: u64,
}

/// Parse `PxK[:STEPS],...`.
pub fn parse_scenarios(s: &str, default_steps: u64) -> Result<Vec<Scenario>> {
    let mut v = Vec::new();
    for item in s.split(',').map(str::trim).filter(|x| !x.is_empty()) {
        let (pk, steps) = match item.split_once(':') {
            Some((pk, st)) => (pk, st.parse().with_context(|| format!("scenario {item:?}: bad STEPS"))?),
            None => (item, default_steps),
        };
        let (p, k) = pk.split_once('x').with_context(|| format!("scenario {item:?}: expected PxK[:STEPS]"))?;
        let processes: u32 = p.parse().with_context(|| format!("scenario {item:?}: bad P"))?;
        let per_process: u32 = k.parse().with_context(|| format!("scenario {item:?}: bad K"))?;
        if processes == 0 || per_process == 0 || steps == 0 {
            bail!("scenario {item:?}: P, K and STEPS must be positive");
        }
        v.push(Scenario { processes, per_process, steps });
    }
    Ok(v)
}

fn run(args: &BenchNetArgs, sc: Scenario, bare: bool, security: &Security) -> Result<NetOutcome> {
    let mut cfg = RunConfig::default();
    cfg.world.agents = sc.processes * sc.per_process;
    cfg.steps = if bare { args.bare_steps } else { sc.steps };
    cfg.seed = args.seed;
    let spec = cfg.validate()?;
    let opts = NetOptions {
        processes: sc.processes,
        agents_per_process: Some(sc.per_process),
        zenoh: args.zenoh.clone(),
        bin_dir: args.bin_dir.clone(),
        bare,
        subscribe: args.subscribe.clone(),
        quiet_children: true,
        security: security.clone(),
        ..NetOptions::default()
    };
    Ok(run_net(&spec, &opts, |_, _| {})?)
}

/// Minimum, median (the mean of the middle two of an even count) and maximum.
fn spread(v: &[f64]) -> Option<(f64, f64, f64)> {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    let median = match n {
        0 => return None,
        _ if n % 2 == 1 => s[n / 2],
        _ => (s[n / 2 - 1] + s[n / 2]) / 2.0,
    };
    Some((s[0], median, s[n - 1]))
}

fn mib(kib: f64) -> f64 {
    kib / 1024.0
}

pub fn bench_net_cmd(args: BenchNetArgs) -> Result<()> {
    let scenarios = parse_scenarios(&args.scenarios, args.steps)?;
    let modes = args.security.modes();
    println!(
        "geese bench-net: {} scenario(s) on {} cores; bare = tick out, empty replies back; learning = foraging, seed {}; {}",
        scenarios.len(),
        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        args.seed,
        modes.iter().map(|m| format!("{} = {}", mode_name(m), m.describe())).collect::<Vec<_>>().join(", ")
    );
    for sc in scenarios {
        let agents = sc.processes * sc.per_process;
        let label = format!("{} process(es) x {} agent(s) = {agents} agents", sc.processes, sc.per_process);
        let mut bare_rates = Vec::new();
        for m in &modes {
            let bare = run(&args, sc, true, m).with_context(|| format!("{label}: bare lock-step"))?;
            let bare_rate = bare.reports as f64 / bare.run_seconds.max(1e-9);
            println!(
                "{label}, {}: bare lock-step {} steps in {:.2} s = {:.1} steps/s (wall with start-up {:.1} s)",
                mode_name(m),
                bare.reports,
                bare.run_seconds,
                bare_rate,
                bare.wall_seconds
            );
            bare_rates.push(bare_rate);
        }
        if args.bare_only {
            continue;
        }
        // Runs of the modes alternate, so a drift of the machine's speed hits both alike.
        let mut rates = vec![Vec::new(); modes.len()];
        let mut last = None;
        for r in 1..=args.repeat {
            for (k, m) in modes.iter().enumerate() {
                let learn = run(&args, sc, false, m).with_context(|| format!("{label}: learning run"))?;
                let rate = learn.reports as f64 / learn.run_seconds.max(1e-9);
                let of = if args.repeat > 1 { format!(" (run {r} of {})", args.repeat) } else { String::new() };
                println!(
                    "{label}, {}: learning {} steps in {:.2} s = {:.1} steps/s ({:.0} agent-steps/s), {:.3} of bare; \
                     wall with start-up {:.1} s; final task {:.2} %{of}",
                    mode_name(m),
                    learn.reports,
                    learn.run_seconds,
                    rate,
                    rate * agents as f64,
                    rate / bare_rates[k].max(1e-9),
                    learn.wall_seconds,
                    learn.summary.final_task_pct
                );
                rates[k].push(rate);
                last = Some(learn);
            }
        }
        for (k, m) in modes.iter().enumerate() {
            if let Some((min, median, max)) = spread(&rates[k]).filter(|_| rates[k].len() > 1) {
                println!(
                    "{label}, {}: learning over {} runs: min {min:.1}, median {median:.1}, max {max:.1} steps/s",
                    mode_name(m),
                    rates[k].len()
                );
            }
        }
        let Some(learn) = last else { continue };
        let (mean, max) = mean_max(&learn.agent_rss_kib);
        let (private, _) = mean_max(&learn.agent_private_kib);
        println!(
            "{label}: RSS per agent process {:.1} MiB mean, {:.1} MiB max ({:.2} MiB per agent), {:.1} MiB of it \
             private (the rest is code, resident once for all); world server {:.1} MiB",
            mib(mean),
            mib(max),
            mib(mean) / sc.per_process as f64,
            mib(private),
            mib(learn.world_rss_kib.unwrap_or(0) as f64)
        );
    }
    Ok(())
}

/// Mean and maximum of some KiB figures (0, 0 for none).
fn mean_max(kib: &[u64]) -> (f64, f64) {
    match kib.iter().max() {
        Some(&max) => (kib.iter().sum::<u64>() as f64 / kib.len() as f64, max as f64),
        None => (0.0, 0.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenarios_parse() {
        let v = parse_scenarios("10x1, 100x1:500,10x100", 12_000).unwrap();
        assert_eq!(v[0], Scenario { processes: 10, per_process: 1, steps: 12_000 });
        assert_eq!(v[1], Scenario { processes: 100, per_process: 1, steps: 500 });
        assert_eq!(v[2].per_process, 100);
        assert!(parse_scenarios("10", 1).is_err());
        assert!(parse_scenarios("0x1", 1).is_err());
    }

    #[test]
    fn spread_is_min_median_max() {
        assert_eq!(spread(&[]), None);
        assert_eq!(spread(&[3.0]), Some((3.0, 3.0, 3.0)));
        assert_eq!(spread(&[101.0, 99.0, 108.0]), Some((99.0, 101.0, 108.0)));
        assert_eq!(spread(&[4.0, 1.0, 2.0, 10.0]), Some((1.0, 3.0, 10.0)));
    }
}
