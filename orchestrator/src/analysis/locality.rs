//! `geese locality`: a run's locality map (`locality.csv`, and the manifest beside it
//! for the arena, the window and the landmarks) drawn as the paper's Fig. 5 — one
//! panel per behaviour class 1–5, the same axes on each.
use crate::analysis::plot::{self, LocalityBox, LocalityPanel, PlotError};
use crate::run::output::{LocalityManifest, LOCALITY_CSV};
use geese_proto::BehaviourClass;
use geese_world::locality::{parse_csv, Count, LocalityError};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum LocalityMapError {
    #[error("cannot read {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {source}")]
    Csv { path: PathBuf, source: LocalityError },
    #[error("{path}: {message}")]
    Manifest { path: PathBuf, message: String },
    #[error(transparent)]
    Plot(#[from] PlotError),
}

/// A locality map as read from a run's directory.
#[derive(Clone, Debug)]
pub struct LocalityMap {
    pub counts: Vec<Count>,
    /// The manifest's locality section, when a manifest with one lies beside the CSV.
    pub manifest: Option<LocalityManifest>,
    /// The CSV read.
    pub csv: PathBuf,
}

/// Read `path`: a run's output directory (its `locality.csv` and `manifest.json`) or a
/// `locality.csv` (with the `manifest.json` of its directory, if there is one).
pub fn load(path: &Path) -> Result<LocalityMap, LocalityMapError> {
    let (csv, dir) = if path.is_dir() {
        (path.join(LOCALITY_CSV), path.to_path_buf())
    } else {
        (path.to_path_buf(), path.parent().map(Path::to_path_buf).unwrap_or_default())
    };
    let read =
        |p: &Path| std::fs::read_to_string(p).map_err(|source| LocalityMapError::Read { path: p.into(), source });
    let counts = parse_csv(&read(&csv)?).map_err(|source| LocalityMapError::Csv { path: csv.clone(), source })?;
    let mpath = dir.join("manifest.json");
    let manifest = if mpath.is_file() {
        let bad = |message: String| LocalityMapError::Manifest { path: mpath.clone(), message };
        let v: serde_json::Value = serde_json::from_str(&read(&mpath)?).map_err(|e| bad(e.to_string()))?;
        match v.get("locality") {
            Some(l) => Some(serde_json::from_value(l.clone()).map_err(|e| bad(format!("locality: {e}")))?),
            None => None,
        }
    } else {
        None
    };
    Ok(LocalityMap { counts, manifest, csv })
}

impl LocalityMap {
    /// Agent-steps per class number 0–5.
    pub fn totals(&self) -> [u64; 6] {
        let mut t = [0u64; 6];
        for c in &self.counts {
            t[usize::from(c.class)] += c.count;
        }
        t
    }

    /// Half the arena's width and height: from the manifest, else the smallest square
    /// around the origin in steps of 10 holding every location.
    pub fn extent(&self) -> (i32, i32) {
        if let Some(m) = &self.manifest {
            return (m.width / 2, m.height / 2);
        }
        let far = self.counts.iter().map(|c| c.x.unsigned_abs().max(c.y.unsigned_abs())).max().unwrap_or(0);
        let half = (far.div_ceil(10) * 10).clamp(10, i32::MAX as u32) as i32;
        (half, half)
    }

    /// One panel per class 1–5 (class 0, "no class", is not drawn).
    pub fn panels(&self) -> Vec<LocalityPanel> {
        let totals = self.totals();
        BehaviourClass::ALL[1..]
            .iter()
            .map(|k| {
                let n = k.number();
                LocalityPanel {
                    title: format!("{n} {} ({} agent-steps)", k.name(), totals[usize::from(n)]),
                    points: self
                        .counts
                        .iter()
                        .filter(|c| c.class == n && c.count > 0)
                        .map(|c| (c.x, c.y, c.count))
                        .collect(),
                }
            })
            .collect()
    }

    /// The manifest's landmarks as boxes to draw.
    pub fn boxes(&self) -> Vec<LocalityBox> {
        let Some(m) = &self.manifest else { return Vec::new() };
        m.landmarks
            .iter()
            .map(|l| LocalityBox {
                label: match l.kind.as_str() {
                    "Hub" => "hub".into(),
                    "Sites" => "site".into(),
                    "Obstacles" => "obstacle".into(),
                    other => other.to_lowercase(),
                },
                cells: l.cells,
                solid: l.kind == "Obstacles",
            })
            .collect()
    }

    /// The figure's title: the window and how markers scale.
    pub fn title(&self) -> String {
        let max = self.counts.iter().filter(|c| c.class > 0).map(|c| c.count).max().unwrap_or(0);
        let steps = match &self.manifest {
            Some(m) => format!("steps {}–{} ({} steps counted)", m.from, m.to, m.steps_counted),
            None => self.csv.display().to_string(),
        };
        format!("Locality map, {steps}; marker area ∝ agent-steps at the location (largest {max})")
    }

    /// Draw `<stem>.png` and `<stem>.svg`.
    pub fn draw(&self, stem: &Path) -> Result<Vec<PathBuf>, LocalityMapError> {
        Ok(plot::locality(stem, &self.title(), &self.panels(), self.extent(), &self.boxes())?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn panels_split_the_counts_by_class_and_the_extent_covers_them() {
        let counts = vec![
            Count { x: -30, y: 30, class: 2, count: 40 },
            Count { x: 0, y: 0, class: 0, count: 9 },
            Count { x: 0, y: 0, class: 3, count: 50 },
            Count { x: 7, y: -43, class: 1, count: 1 },
        ];
        let m = LocalityMap { counts, manifest: None, csv: PathBuf::from("x/locality.csv") };
        assert_eq!(m.totals(), [9, 1, 40, 50, 0, 0]);
        let p = m.panels();
        assert_eq!(p.len(), 5);
        assert_eq!(p[1].points, vec![(-30, 30, 40)]);
        assert!(p[0].title.starts_with("1 Explore (1 agent-steps)"), "{}", p[0].title);
        assert!(p[4].points.is_empty());
        assert_eq!(m.extent(), (50, 50));
        assert!(m.title().contains("largest 50"), "{}", m.title());
    }
}
