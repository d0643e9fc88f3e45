//! Where a run's results go: a per-step CSV and a manifest.
//!
//! The manifest records everything needed to reproduce the run: the resolved config,
//! the seed and how streams derive from it, the grammar and its digest, versions and the
//! git revision.
use crate::config::RunSpec;
use crate::trial::TrialSummary;
use geese_proto::seed::Fnv64;
use geese_proto::StepReport;
use serde::Serialize;
use std::io::Write;
use std::path::Path;

/// Header of the per-step CSV.
pub const CSV_HEADER: &str =
    "step,task_pct,lt_mean,lt_std,genetic_steps,stagnation_steps,live_agents,missing_intents,rejected,genes_lost";

/// One CSV line of a step report.
pub fn csv_row(r: &StepReport) -> String {
    format!(
        "{},{},{},{},{},{},{},{},{},{}",
        r.step,
        r.task_pct,
        r.lt_mean,
        r.lt_std,
        r.genetic_steps,
        r.stagnation_steps,
        r.live_agents,
        r.missing_intents,
        r.rejected,
        r.genes_lost
    )
}

/// Versions and provenance.
#[derive(Serialize)]
pub struct Versions {
    pub geese: &'static str,
    pub git_revision: &'static str,
    pub wire_version: u8,
}

pub fn versions() -> Versions {
    Versions {
        geese: env!("CARGO_PKG_VERSION"),
        git_revision: env!("GEESE_GIT_REV"),
        wire_version: geese_proto::WIRE_VERSION,
    }
}

#[derive(Serialize)]
struct Manifest<'a> {
    command: Vec<String>,
    versions: Versions,
    seed: u64,
    seed_derivation: &'static str,
    grammar: &'a str,
    grammar_digest: String,
    transport: &'a str,
    config: &'a crate::config::RunConfig,
    /// Perturbations received on the control plane during the run (`geese control`).
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    control: &'a [geese_proto::Control],
    summary: &'a TrialSummary,
}

/// Digest of a grammar text (hex).
pub fn text_digest(text: &str) -> String {
    let mut h = Fnv64::default();
    h.write(text.as_bytes());
    format!("{:016x}", h.finish())
}

/// Write `manifest.json` into `dir`.
pub fn write_manifest(
    dir: &Path,
    spec: &RunSpec,
    transport: &str,
    summary: &TrialSummary,
    control: &[geese_proto::Control],
) -> std::io::Result<()> {
    let m = Manifest {
        command: std::env::args().collect(),
        versions: versions(),
        seed: spec.config.seed,
        seed_derivation: "each stream seeded with proto::seed::derive(run seed, owner, purpose) into ChaCha8",
        grammar: &spec.grammar_name,
        grammar_digest: text_digest(&spec.grammar_text),
        transport,
        config: &spec.config,
        control,
        summary,
    };
    let f = std::fs::File::create(dir.join("manifest.json"))?;
    serde_json::to_writer_pretty(f, &m).map_err(std::io::Error::other)?;
    Ok(())
}

/// A buffered per-step CSV writer.
pub struct StepCsv {
    out: std::io::BufWriter<std::fs::File>,
}

impl StepCsv {
    pub fn create(path: &Path) -> std::io::Result<StepCsv> {
        let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
        writeln!(out, "{CSV_HEADER}")?;
        Ok(StepCsv { out })
    }
    pub fn write(&mut self, r: &StepReport) -> std::io::Result<()> {
        writeln!(self.out, "{}", csv_row(r))
    }
    pub fn finish(mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}
