//! Throughput benchmark of the simulation core: learning agent-steps per second on one
//! thread or several (`--threads`), in any arena (`--width`); and (`geese bench
//! --micro`) micro-benchmarks of one genetic step and one
//! mapping. A benchmark prints figures; it is not a test and asserts nothing.
use crate::run::config::RunConfig;
use crate::run::trial::Trial;
use std::time::Instant;

/// Result of one benchmark run.
#[derive(Debug, Clone)]
pub struct BenchResult {
    pub agents: u32,
    pub steps: u64,
    pub seconds: f64,
    pub agent_steps_per_sec: f64,
    pub genetic_steps: u64,
    pub final_task_pct: f64,
}

/// Time `steps` lock-step steps of the configured trial on the calling thread.
pub fn bench_core(cfg: RunConfig) -> anyhow::Result<BenchResult> {
    let steps = cfg.steps;
    let agents = cfg.world.agents;
    let spec = cfg.validate()?;
    let mut t = Trial::new(&spec)?;
    let start = Instant::now();
    for _ in 0..steps {
        t.step();
    }
    let seconds = start.elapsed().as_secs_f64();
    Ok(BenchResult {
        agents,
        steps,
        seconds,
        agent_steps_per_sec: (agents as f64 * steps as f64) / seconds,
        genetic_steps: t.summary().genetic_steps + t.summary().stagnation_steps,
        final_task_pct: t.summary().final_task_pct,
    })
}

/// This process's peak resident memory (VmHWM) in MiB, where Linux tells it.
pub fn peak_rss_mib() -> Option<f64> {
    crate::distributed::launch::proc_number("/proc/self/status", "VmHWM:").map(|kib| kib as f64 / 1024.0)
}

/// Batches of the genetic-step micro-benchmark (the best one is reported).
pub const MICRO_BATCHES: usize = 30;
/// Genetic steps per batch of the micro-benchmark.
pub const MICRO_BATCH: usize = 2000;
/// Calls of each mapper entry point per golden genome.
pub const MICRO_MAPPINGS: usize = 200_000;

/// Figures of `geese bench --micro`.
#[derive(Debug, Clone)]
pub struct MicroResult {
    pub step: geese_agent::ge::micro::StepTiming,
    pub mapping: Vec<geese_agent::ge::micro::MappingTiming>,
}

/// Run the micro-benchmarks of [`geese_agent::ge::micro`] with the batch sizes above.
pub fn bench_micro() -> MicroResult {
    use geese_agent::ge::micro;
    MicroResult { step: micro::genetic_step_us(MICRO_BATCHES, MICRO_BATCH), mapping: micro::mapping_ns(MICRO_MAPPINGS) }
}
