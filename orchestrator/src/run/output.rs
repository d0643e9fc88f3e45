//! Where a run's results go: a per-step CSV and a manifest.
//!
//! The manifest records everything needed to reproduce the run: the resolved config,
//! the seed and how streams derive from it, the grammar and its digest, versions and the
//! git revision.
use crate::run::config::RunSpec;
use crate::run::trial::TrialSummary;
use geese_proto::seed::Fnv64;
use geese_proto::{ObjectKind, StepReport};
use serde::{Deserialize, Serialize};
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
    /// How a distributed run was secured (logins and access control, or none).
    #[serde(skip_serializing_if = "Option::is_none")]
    security: Option<&'a str>,
    config: &'a crate::run::config::RunConfig,
    /// Perturbations received on the control plane during the run (`geese control`).
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    control: &'a [geese_proto::Control],
    summary: &'a TrialSummary,
    /// The locality map's window, file and the arena it was counted on.
    #[serde(skip_serializing_if = "Option::is_none")]
    locality: Option<LocalityManifest>,
}

/// File name of the locality map in a run's output directory.
pub const LOCALITY_CSV: &str = "locality.csv";

/// What the manifest says of a run's locality map: enough to draw it without the
/// config (`geese locality`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocalityManifest {
    /// `FROM:TO` as configured.
    pub window: String,
    pub from: u64,
    pub to: u64,
    /// Steps of the window the run reached (fewer than TO − FROM + 1 if it stopped
    /// early).
    pub steps_counted: u64,
    pub file: String,
    pub counted: String,
    pub width: i32,
    pub height: i32,
    pub grid: i32,
    /// Hub, sites, boundaries and obstacles as the world was built (obstacles that
    /// perturbations add later are not listed).
    pub landmarks: Vec<Landmark>,
}

/// An object drawn on the locality map, with the box of grid cells it occupies
/// (REFERENCE §1.2: at GS 10 every object of the paper's worlds covers one cell).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    pub kind: String,
    pub x: i32,
    pub y: i32,
    pub radius: i32,
    /// (x1, y1, x2, y2) of its cells.
    pub cells: (i32, i32, i32, i32),
}

/// The manifest's locality section of a stage that counted `steps` steps.
pub fn locality_manifest(spec: &RunSpec, steps: u64) -> Option<LocalityManifest> {
    let w = spec.locality?;
    let c = &spec.config;
    let geom = c.world.validate().ok()?;
    // The layout is a function of the world config and the seed: the launcher of a
    // distributed run, which holds no world, builds the same one.
    let landmarks = geese_world::World::new(c.world.clone(), c.seed)
        .map(|world| {
            world
                .objects()
                .map(|o| o.info)
                .filter(|o| {
                    matches!(o.kind, ObjectKind::Hub | ObjectKind::Sites | ObjectKind::Boundary | ObjectKind::Obstacles)
                })
                .map(|o| Landmark {
                    kind: o.kind.name().into(),
                    x: o.pos.x,
                    y: o.pos.y,
                    radius: o.radius,
                    cells: geom.neighbourhood_box(o.pos, o.radius),
                })
                .collect()
        })
        .unwrap_or_default();
    Some(LocalityManifest {
        window: w.to_string(),
        from: w.from,
        to: w.to,
        steps_counted: w.steps_in(steps),
        file: LOCALITY_CSV.into(),
        counted: "after each step FROM..=TO (step 1 is the first), every live agent once, at its integer \
                  position, under the behaviour class of its tree (after that step's genetic operators), \
                  before the perturbations scheduled after that step"
            .into(),
        width: c.world.width,
        height: c.world.height,
        grid: c.world.grid,
        landmarks,
    })
}

/// Write the locality map `counts` to `dir/locality.csv`.
pub fn write_locality(dir: &Path, counts: &[geese_world::locality::Count]) -> std::io::Result<std::path::PathBuf> {
    let path = dir.join(LOCALITY_CSV);
    geese_world::locality::write_csv(counts, std::io::BufWriter::new(std::fs::File::create(&path)?))?;
    Ok(path)
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
    security: Option<&str>,
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
        security,
        config: &spec.config,
        control,
        summary,
        locality: locality_manifest(spec, summary.steps),
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
