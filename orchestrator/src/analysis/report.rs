//! Turning a results database into the tables and figures researchers publish:
//! success rate, power, efficiency and wall time per step per condition and per x level
//! (pooled over the other knobs, as the paper pools ablation over insertion times),
//! least-squares slopes across conditions, learning curves, Fig.-6/10-style scatters,
//! Fig.-4/8b-style boxes and Fig.-9b-style run-time boxes.
//!
//! Levels are ordered as the campaign's conditions first name them: numeric levels by
//! value, text levels (`algorithm`, `terms`, conditions) in order of first appearance.
use crate::analysis::metrics::{self, EfficiencyVariant, Outcome, PowerVariant, Stats};
use crate::analysis::plot::{self, BoxAxis, BoxGroup, Curve, PlotError, ScatterPanel};
use crate::campaigns::store::{csv_field, Store, StoreError, StoredTrial};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Which efficiency to report.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum EfficiencyChoice {
    /// The paper's definition.
    #[default]
    Paper,
    /// The reference code's variant the campaign file names (`code_efficiency`).
    Code,
    Variant(EfficiencyVariant),
}

#[derive(Clone, Debug, Default)]
pub struct ReportOptions {
    pub efficiency: EfficiencyChoice,
    pub power: PowerVariant,
    /// Use at most the first N trials of each (task, x level) — the reference plots
    /// cap at 40 (REFERENCE §8.1).
    pub cap: Option<usize>,
}

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Plot(#[from] PlotError),
    #[error(
        "--efficiency code: the campaign file names no code_efficiency; choose paper, sec5-ablation, sec5 or sec7"
    )]
    NoCodeEfficiency,
    #[error("cannot write {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

/// Metrics of one trial.
#[derive(Clone, Debug)]
pub struct Point {
    pub task: String,
    pub condition: String,
    pub seed: u64,
    pub x: f64,
    pub x_label: String,
    /// 1-based position of the x level among the task's levels.
    pub x_pos: f64,
    pub series: String,
    pub power: f64,
    pub efficiency: f64,
    pub final_pct: f64,
    pub success: bool,
    /// Wall milliseconds per step of the trial's last stage (the stage its task % is
    /// from), when the database has it.
    pub ms_per_step: Option<f64>,
}

/// One row of a metrics table.
#[derive(Clone, Debug)]
pub struct Row {
    pub task: String,
    /// Condition label, or the x level for pooled rows.
    pub label: String,
    pub trials: usize,
    pub failed: usize,
    pub success_rate: f64,
    pub power: Option<Stats>,
    pub efficiency: Option<Stats>,
    /// Over the trials whose wall time is known.
    pub ms_per_step: Option<Stats>,
}

/// A fitted line across conditions.
#[derive(Clone, Debug)]
pub struct Fit {
    pub task: String,
    /// The series level the line is fitted to, or empty: one line per series level when
    /// the campaign has a series knob other than x (pooling, say, two mutation rules into
    /// one line would hide the comparison the series is for).
    pub series: String,
    pub metric: &'static str,
    /// Slope per x position (levels at 1, 2, 3, …, as plotted).
    pub slope_per_position: Option<f64>,
    /// Slope per unit of the x knob.
    pub slope_per_unit: Option<f64>,
    pub intercept_per_position: Option<f64>,
    pub n: usize,
}

pub struct Report {
    pub name: String,
    pub description: String,
    pub x_name: String,
    pub series_name: String,
    /// Series levels in plotting order (numeric by value, text by first appearance).
    pub series_levels: Vec<String>,
    pub efficiency: EfficiencyVariant,
    pub power: PowerVariant,
    pub threshold: f64,
    pub trials: Vec<StoredTrial>,
    pub points: Vec<Point>,
    pub conditions: Vec<Row>,
    pub groups: Vec<Row>,
    pub fits: Vec<Fit>,
    /// Recovery from a change of task, per condition and starting task (conditions
    /// with a `switch_at` knob; issue 30.4).
    pub switches: Vec<SwitchRow>,
}

/// How trials of one condition and starting task recovered from a change of task.
#[derive(Clone, Debug)]
pub struct SwitchRow {
    /// The task the trials started with; they end with the other.
    pub task: String,
    pub condition: String,
    /// The switch applied right after this step.
    pub switch_at: u64,
    pub trials: usize,
    /// Trials whose new task reached the threshold after the switch.
    pub reached: usize,
    /// Steps from the switch to the first stored step at the threshold, over the
    /// trials that reached it (stored rows only: every `step_stride`-th step).
    pub recovery: Option<Stats>,
    /// Final task % (of the new task).
    pub final_pct: Option<Stats>,
}

/// The `switch_at` level of a condition label, if it has one.
fn switch_at(condition: &str) -> Option<u64> {
    condition.split(' ').find_map(|kv| kv.strip_prefix("switch_at=")).and_then(|v| v.parse().ok())
}

/// The recovery table of the trials that switched task (none: no `switch_at` knob).
fn switch_rows(store: &Store, trials: &[&StoredTrial], threshold: f64) -> Result<Vec<SwitchRow>, ReportError> {
    let at: HashMap<i64, u64> = trials.iter().filter_map(|t| Some((t.id, switch_at(&t.condition)?))).collect();
    if at.is_empty() {
        return Ok(Vec::new());
    }
    let mut first: HashMap<i64, u64> = HashMap::new();
    let mut last: HashMap<i64, f64> = HashMap::new();
    store.for_each_task_pct(|id, step, v| {
        if let Some(&a) = at.get(&id) {
            if step > a && v >= threshold {
                first.entry(id).or_insert(step - a);
            }
            last.insert(id, v);
        }
    })?;
    let mut rows: Vec<SwitchRow> = Vec::new();
    for t in trials.iter().filter(|t| at.contains_key(&t.id)) {
        let i = match rows.iter().position(|r| r.task == t.task && r.condition == t.condition) {
            Some(i) => i,
            None => {
                rows.push(SwitchRow {
                    task: t.task.clone(),
                    condition: t.condition.clone(),
                    switch_at: at[&t.id],
                    trials: 0,
                    reached: 0,
                    recovery: None,
                    final_pct: None,
                });
                rows.len() - 1
            }
        };
        rows[i].trials += 1;
        rows[i].reached += usize::from(first.contains_key(&t.id));
    }
    for r in &mut rows {
        let ids = || trials.iter().filter(|t| t.task == r.task && t.condition == r.condition).map(|t| t.id);
        let rec: Vec<f64> = ids().filter_map(|id| first.get(&id).map(|&s| s as f64)).collect();
        let fin: Vec<f64> = ids().filter_map(|id| last.get(&id).copied()).collect();
        r.recovery = metrics::stats(&rec);
        r.final_pct = metrics::stats(&fin);
    }
    Ok(rows)
}

fn row(task: &str, label: String, pts: &[&Point], failed: usize) -> Row {
    let succ: Vec<bool> = pts.iter().map(|p| p.success).collect();
    let pw: Vec<f64> = pts.iter().map(|p| p.power).collect();
    let ef: Vec<f64> = pts.iter().map(|p| p.efficiency).collect();
    let ms: Vec<f64> = pts.iter().filter_map(|p| p.ms_per_step).collect();
    Row {
        task: task.to_string(),
        label,
        trials: pts.len(),
        failed,
        success_rate: metrics::success_rate(&succ),
        power: metrics::stats(&pw),
        efficiency: metrics::stats(&ef),
        ms_per_step: metrics::stats(&ms),
    }
}

/// Distinct labels in plotting order: by value when every label is a number, else in
/// order of `first` (the first condition index naming the label).
fn level_order<'a>(labels: impl Iterator<Item = (&'a str, i64)>) -> Vec<String> {
    let mut first: Vec<(String, i64)> = Vec::new();
    for (l, ci) in labels {
        match first.iter_mut().find(|(x, _)| x == l) {
            Some(e) => e.1 = e.1.min(ci),
            None => first.push((l.to_string(), ci)),
        }
    }
    if first.iter().all(|(l, _)| l.parse::<f64>().is_ok()) {
        first.sort_by(|a, b| a.0.parse::<f64>().unwrap_or(0.0).total_cmp(&b.0.parse::<f64>().unwrap_or(0.0)));
    } else {
        first.sort_by_key(|e| e.1);
    }
    first.into_iter().map(|(l, _)| l).collect()
}

/// Compute the report from a database.
pub fn build(store: &Store, opts: &ReportOptions) -> Result<Report, ReportError> {
    let meta = |k: &str| -> Result<String, ReportError> { Ok(store.meta(k)?.unwrap_or_default()) };
    let efficiency = match opts.efficiency {
        EfficiencyChoice::Paper => EfficiencyVariant::Paper,
        EfficiencyChoice::Variant(v) => v,
        EfficiencyChoice::Code => match meta("code_efficiency")?.as_str() {
            "sec5-ablation" => EfficiencyVariant::Sec5Ablation,
            "sec5" => EfficiencyVariant::Sec5,
            "sec7" => EfficiencyVariant::Sec7,
            _ => return Err(ReportError::NoCodeEfficiency),
        },
    };
    let threshold = meta("threshold")?.parse().unwrap_or(80.0);
    let trials = store.trials()?;
    // Cap: first N finished trials per (task, x level), in condition/seed order.
    let mut kept: Vec<&StoredTrial> = Vec::new();
    let mut per_group: HashMap<(String, String), usize> = HashMap::new();
    for t in trials.iter().filter(|t| t.outcome.is_some()) {
        let n = per_group.entry((t.task.clone(), t.x_label.clone())).or_default();
        if opts.cap.is_none_or(|c| *n < c) {
            *n += 1;
            kept.push(t);
        }
    }
    // Efficiency is computed per condition (Sec.-7 t_min is per condition).
    let mut by_cond: BTreeMap<(String, i64), Vec<&StoredTrial>> = BTreeMap::new();
    for t in &kept {
        by_cond.entry((t.task.clone(), t.condition_index)).or_default().push(t);
    }
    // x positions per task: sorted distinct x values.
    let mut xs: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for t in &kept {
        let v = xs.entry(t.task.clone()).or_default();
        if !v.contains(&t.x) {
            v.push(t.x);
        }
    }
    for v in xs.values_mut() {
        v.sort_by(|a, b| a.total_cmp(b));
    }
    let mut points = Vec::new();
    for ((task, _), ts) in &by_cond {
        let outcomes: Vec<Outcome> = ts.iter().filter_map(|t| t.outcome).collect();
        let effs = metrics::efficiencies(&outcomes, efficiency);
        for (t, (o, e)) in ts.iter().zip(outcomes.iter().zip(effs)) {
            let pos = xs.get(task).and_then(|v| v.iter().position(|x| *x == t.x)).unwrap_or(0) as f64 + 1.0;
            points.push(Point {
                task: task.clone(),
                condition: t.condition.clone(),
                seed: t.seed,
                x: t.x,
                x_label: t.x_label.clone(),
                x_pos: pos,
                series: t.series.clone(),
                power: metrics::power(o, opts.power),
                efficiency: e,
                final_pct: o.final_pct,
                success: o.success,
                ms_per_step: t.ms_per_step(),
            });
        }
    }
    points.sort_by(|a, b| {
        a.task.cmp(&b.task).then(a.x.total_cmp(&b.x)).then(a.condition.cmp(&b.condition)).then(a.seed.cmp(&b.seed))
    });
    // Per-condition rows (failed trials counted from all trials).
    let mut conditions = Vec::new();
    let mut cond_order: Vec<(String, i64, String)> =
        trials.iter().map(|t| (t.task.clone(), t.condition_index, t.condition.clone())).collect();
    cond_order.sort();
    cond_order.dedup();
    for (task, _, label) in &cond_order {
        let pts: Vec<&Point> = points.iter().filter(|p| &p.task == task && &p.condition == label).collect();
        let failed = trials.iter().filter(|t| &t.task == task && &t.condition == label && t.outcome.is_none()).count();
        conditions.push(row(task, label.clone(), &pts, failed));
    }
    // Pooled per x level, and fits: one line per series level when the series knob is
    // not x itself, else one over all trials.
    let x_name = meta("x")?;
    let series_name = meta("series")?;
    let series_levels = level_order(kept.iter().map(|t| (t.series.as_str(), t.condition_index)));
    let fit_series: Vec<String> =
        if series_name.is_empty() || series_name == x_name { vec![String::new()] } else { series_levels.clone() };
    let mut groups = Vec::new();
    let mut fits = Vec::new();
    for (task, levels) in &xs {
        for x in levels {
            let pts: Vec<&Point> = points.iter().filter(|p| &p.task == task && p.x == *x).collect();
            let label = pts.first().map(|p| p.x_label.clone()).unwrap_or_default();
            let failed = trials.iter().filter(|t| &t.task == task && t.x == *x && t.outcome.is_none()).count();
            groups.push(row(task, label, &pts, failed));
        }
        for series in &fit_series {
            let pts: Vec<&Point> =
                points.iter().filter(|p| &p.task == task && (series.is_empty() || &p.series == series)).collect();
            if pts.is_empty() {
                continue;
            }
            let pos: Vec<f64> = pts.iter().map(|p| p.x_pos).collect();
            let unit: Vec<f64> = pts.iter().map(|p| p.x).collect();
            for (metric, ys) in [
                ("power", pts.iter().map(|p| p.power).collect::<Vec<_>>()),
                ("efficiency", pts.iter().map(|p| p.efficiency).collect::<Vec<_>>()),
            ] {
                let by_pos = metrics::ols(&pos, &ys);
                fits.push(Fit {
                    task: task.clone(),
                    series: series.clone(),
                    metric,
                    slope_per_position: by_pos.map(|f| f.0),
                    intercept_per_position: by_pos.map(|f| f.1),
                    slope_per_unit: metrics::ols(&unit, &ys).map(|f| f.0),
                    n: ys.len(),
                });
            }
        }
    }
    let switches = switch_rows(store, &kept, threshold)?;
    Ok(Report {
        name: meta("name")?,
        description: meta("description")?,
        x_name,
        series_name,
        series_levels,
        efficiency,
        power: opts.power,
        threshold,
        trials,
        points,
        conditions,
        groups,
        fits,
        switches,
    })
}

/// A slope with three decimals, or three significant digits when it is smaller (a
/// slope per step of an insertion time is about 1e-4).
fn fmt_opt(v: Option<f64>) -> String {
    match v {
        None => "-".into(),
        Some(x) if x != 0.0 && x.abs() < 0.01 => format!("{x:.2e}"),
        Some(x) => format!("{x:.3}"),
    }
}

fn fmt_stats(s: &Option<Stats>) -> [String; 3] {
    match s {
        Some(s) => [format!("{:.2}", s.mean), format!("{:.2}", s.median), format!("{:.2}", s.iqr())],
        None => ["-".into(), "-".into(), "-".into()],
    }
}

fn table(out: &mut dyn Write, first: &str, rows: &[Row]) -> std::io::Result<()> {
    let w = rows.iter().map(|r| r.label.chars().count()).max().unwrap_or(0).max(first.len());
    writeln!(
        out,
        "{:<9} {:<w$} {:>6} {:>6} {:>8}  {:>8} {:>8} {:>8}  {:>8} {:>8} {:>8}  {:>8} {:>8}",
        "task",
        first,
        "trials",
        "failed",
        "success%",
        "pow.mean",
        "pow.med",
        "pow.IQR",
        "eff.mean",
        "eff.med",
        "eff.IQR",
        "ms/step",
        "ms.IQR"
    )?;
    for r in rows {
        let [pm, pmed, piqr] = fmt_stats(&r.power);
        let [em, emed, eiqr] = fmt_stats(&r.efficiency);
        let [msmed, msiqr] = match &r.ms_per_step {
            Some(s) => [format!("{:.3}", s.median), format!("{:.3}", s.iqr())],
            None => ["-".into(), "-".into()],
        };
        writeln!(
            out,
            "{:<9} {:<w$} {:>6} {:>6} {:>8.2}  {:>8} {:>8} {:>8}  {:>8} {:>8} {:>8}  {:>8} {:>8}",
            r.task, r.label, r.trials, r.failed, r.success_rate, pm, pmed, piqr, em, emed, eiqr, msmed, msiqr
        )?;
    }
    Ok(())
}

impl Report {
    /// Print the metric tables.
    pub fn print(&self, out: &mut dyn Write) -> std::io::Result<()> {
        let done = self.trials.iter().filter(|t| t.outcome.is_some()).count();
        writeln!(
            out,
            "campaign {}: {} trials stored ({} done, {} failed)",
            self.name,
            self.trials.len(),
            done,
            self.trials.len() - done
        )?;
        if !self.description.is_empty() {
            writeln!(out, "{}", self.description.trim())?;
        }
        writeln!(
            out,
            "threshold {} %; power: {}; efficiency: {}",
            self.threshold,
            match self.power {
                PowerVariant::Paper => "paper (max success probability, per trial 100/0)",
                PowerVariant::Code => "code (final task %)",
            },
            match self.efficiency {
                EfficiencyVariant::Paper => "paper ((T − t80)/T·100)",
                EfficiencyVariant::Sec5Ablation => "code sec5-ablation (t_min 5200)",
                EfficiencyVariant::Sec5 => "code sec5 (t_min 2756, |·|)",
                EfficiencyVariant::Sec7 => "code sec7 (t_min per condition)",
            }
        )?;
        writeln!(
            out,
            "ms/step: median wall milliseconds per step of each trial's last stage (a fixed test's, \
             if it has one){}",
            if self.points.iter().any(|p| p.ms_per_step.is_none()) {
                "; unknown for trials stored before the database kept it"
            } else {
                ""
            }
        )?;
        writeln!(out, "\nPer condition:")?;
        table(out, "condition", &self.conditions)?;
        if !self.x_name.is_empty() {
            writeln!(out, "\nPooled by {}:", self.x_name)?;
            table(out, &self.x_name, &self.groups)?;
            writeln!(out, "\nLeast-squares slope across conditions (per trial metric vs {}):", self.x_name)?;
            let w = self.fits.iter().map(|f| f.series.len()).max().unwrap_or(0);
            let series = if w == 0 { String::new() } else { format!("{:<w$} ", self.series_name, w = w.max(6)) };
            writeln!(
                out,
                "{:<9} {series}{:<10} {:>6} {:>14} {:>14}",
                "task", "metric", "trials", "slope/position", "slope/unit"
            )?;
            for f in &self.fits {
                let series = if w == 0 { String::new() } else { format!("{:<w$} ", f.series, w = w.max(6)) };
                writeln!(
                    out,
                    "{:<9} {series}{:<10} {:>6} {:>14} {:>14}",
                    f.task,
                    f.metric,
                    f.n,
                    fmt_opt(f.slope_per_position),
                    fmt_opt(f.slope_per_unit)
                )?;
            }
        }
        if !self.switches.is_empty() {
            writeln!(
                out,
                "\nTask switch: steps from the switch until the new task first reached {} % (stored rows), \
                 over the trials that got there; share of trials that got there; final % of the new task:",
                self.threshold
            )?;
            writeln!(
                out,
                "{:<9} {:<9} {:<60} {:>8} {:>9} {:>9} {:>15} {:>9}",
                "from", "to", "condition", "reached", "share", "median", "IQR", "final med"
            )?;
            for r in &self.switches {
                let to = r.task.parse::<geese_proto::Task>().map_or("?", |t| t.other().name());
                let (med, iqr) = match &r.recovery {
                    Some(s) => (format!("{:.0}", s.median), format!("{:.0}-{:.0}", s.q1, s.q3)),
                    None => ("-".into(), "-".into()),
                };
                writeln!(
                    out,
                    "{:<9} {:<9} {:<60} {:>8} {:>9.2} {:>9} {:>15} {:>9}",
                    r.task,
                    to,
                    r.condition,
                    format!("{}/{}", r.reached, r.trials),
                    r.reached as f64 / r.trials.max(1) as f64,
                    med,
                    iqr,
                    r.final_pct.as_ref().map_or("-".into(), |s| format!("{:.2}", s.median))
                )?;
            }
        }
        let failed: Vec<&StoredTrial> = self.trials.iter().filter(|t| t.outcome.is_none()).collect();
        if !failed.is_empty() {
            writeln!(out, "\nFailed trials:")?;
            for t in failed.iter().take(20) {
                writeln!(
                    out,
                    "  {} task {} seed {}: {}",
                    t.condition,
                    t.task,
                    t.seed,
                    t.error.as_deref().unwrap_or("?")
                )?;
            }
            if failed.len() > 20 {
                writeln!(out, "  … and {} more", failed.len() - 20)?;
            }
        }
        Ok(())
    }

    /// Write `conditions.csv`, `pooled.csv`, `fits.csv` and `points.csv` into `dir`
    /// (and `switch.csv` when trials switched task).
    pub fn write_csv(&self, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
        std::fs::create_dir_all(dir).map_err(|source| ReportError::Io { path: dir.into(), source })?;
        let mut files = Vec::new();
        if !self.switches.is_empty() {
            let mut s = String::from(
                "task,condition,switch_at,trials,reached,share,recovery_median,recovery_q1,recovery_q3,final_median\n",
            );
            for r in &self.switches {
                let q = |f: &dyn Fn(&Stats) -> f64| r.recovery.as_ref().map_or(String::new(), |x| f(x).to_string());
                s.push_str(&format!(
                    "{},{},{},{},{},{},{},{},{},{}\n",
                    r.task,
                    csv_field(&r.condition),
                    r.switch_at,
                    r.trials,
                    r.reached,
                    r.reached as f64 / r.trials.max(1) as f64,
                    q(&|x| x.median),
                    q(&|x| x.q1),
                    q(&|x| x.q3),
                    r.final_pct.as_ref().map_or(String::new(), |x| x.median.to_string())
                ));
            }
            files.push(write_file(&dir.join("switch.csv"), &s)?);
        }
        let rows_csv = |name: &str, rows: &[Row]| -> Result<PathBuf, ReportError> {
            let mut s = String::from(
                "task,label,trials,failed,success_rate,power_mean,power_median,power_q1,power_q3,efficiency_mean,efficiency_median,efficiency_q1,efficiency_q3,ms_per_step_mean,ms_per_step_median,ms_per_step_q1,ms_per_step_q3\n",
            );
            for r in rows {
                let st = |v: &Option<Stats>| match v {
                    Some(s) => format!("{},{},{},{}", s.mean, s.median, s.q1, s.q3),
                    None => ",,,".into(),
                };
                s.push_str(&format!(
                    "{},{},{},{},{},{},{},{}\n",
                    r.task,
                    csv_field(&r.label),
                    r.trials,
                    r.failed,
                    r.success_rate,
                    st(&r.power),
                    st(&r.efficiency),
                    st(&r.ms_per_step)
                ));
            }
            write_file(&dir.join(name), &s)
        };
        files.push(rows_csv("conditions.csv", &self.conditions)?);
        files.push(rows_csv("pooled.csv", &self.groups)?);
        let mut s =
            String::from("task,series,metric,trials,slope_per_position,intercept_per_position,slope_per_unit\n");
        let o = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
        for f in &self.fits {
            s.push_str(&format!(
                "{},{},{},{},{},{},{}\n",
                f.task,
                csv_field(&f.series),
                f.metric,
                f.n,
                o(f.slope_per_position),
                o(f.intercept_per_position),
                o(f.slope_per_unit)
            ));
        }
        files.push(write_file(&dir.join("fits.csv"), &s)?);
        let mut s = String::from(
            "task,condition,seed,x,x_position,series,success,power,efficiency,final_task_pct,ms_per_step\n",
        );
        for p in &self.points {
            s.push_str(&format!(
                "{},{},{},{},{},{},{},{},{},{},{}\n",
                p.task,
                csv_field(&p.condition),
                p.seed,
                p.x,
                p.x_pos,
                csv_field(&p.series),
                p.success,
                p.power,
                p.efficiency,
                p.final_pct,
                p.ms_per_step.map(|v| v.to_string()).unwrap_or_default()
            ));
        }
        files.push(write_file(&dir.join("points.csv"), &s)?);
        Ok(files)
    }

    /// The power and efficiency panels of `task` (Figs. 6, 10): every trial's point
    /// against its x level, and the least-squares line of each series level. `prefix`
    /// starts the panel titles (a figure of several campaigns names each).
    pub fn resilience_panels(&self, task: &str, prefix: &str) -> Vec<ScatterPanel> {
        let pts: Vec<&Point> = self.points.iter().filter(|p| p.task == task).collect();
        let mut ticks: Vec<(f64, String)> = pts.iter().map(|p| (p.x_pos, p.x_label.clone())).collect();
        ticks.sort_by(|a, b| a.0.total_cmp(&b.0));
        ticks.dedup();
        let x_label = if self.x_name.is_empty() { "condition".to_string() } else { self.x_name.clone() };
        let line = |f: &Fit| Some((f.slope_per_position?, f.intercept_per_position?));
        let panel = |m: &'static str, y: &dyn Fn(&Point) -> f64, y_label: String| {
            let fits: Vec<&Fit> = self.fits.iter().filter(|f| f.task == task && f.metric == m).collect();
            let slopes: Vec<String> = fits
                .iter()
                .map(|f| {
                    let who = if f.series.is_empty() { String::new() } else { format!("{}: ", f.series) };
                    match line(f) {
                        Some((a, b)) if fits.len() == 1 => format!("{who}least squares {a:.3}·level + {b:.2}"),
                        Some((a, _)) => format!("{who}{a:+.2}/level"),
                        None => format!("{who}no fitted line (one level)"),
                    }
                })
                .collect();
            ScatterPanel {
                title: format!("{prefix}{m}: {}", slopes.join(", ")),
                x_label: x_label.clone(),
                y_label,
                series: fits
                    .iter()
                    .map(|f| plot::ScatterSeries {
                        label: if f.series.is_empty() {
                            String::new()
                        } else {
                            format!("{} = {}", self.series_name, f.series)
                        },
                        points: pts
                            .iter()
                            .filter(|p| f.series.is_empty() || p.series == f.series)
                            .map(|p| (p.x_pos, y(p)))
                            .collect(),
                        fit: line(f),
                    })
                    .collect(),
                ticks: ticks.clone(),
            }
        };
        vec![
            panel(
                "power",
                &|p| p.power,
                format!("power ({})", if self.power == PowerVariant::Paper { "paper" } else { "code" }),
            ),
            panel("efficiency", &|p| p.efficiency, format!("efficiency ({})", self.efficiency.name())),
        ]
    }

    /// Draw every figure into `dir` (PNG and SVG each); returns the files written.
    ///
    /// Per task:
    /// * `curves-{task}`: task % over time, one median and IQR band per x level; with a
    ///   series knob other than x, one such figure per series level instead,
    ///   `curves-{task}-{series}-{level}` (Fig. 4a);
    /// * `learning-{task}` (when trials tested learned populations): task % over time of
    ///   the learning runs they tested, one curve per series level, or per x level
    ///   without a series knob (Fig. 8a);
    /// * `resilience-{task}`: per-trial power and efficiency against x (Figs. 6, 10);
    /// * `final-{task}`: box plots of the final task % per x level, grouped by series
    ///   level (Figs. 4b, 8b);
    /// * `walltime-{task}` (when wall times are stored): box plots of the wall
    ///   milliseconds per step per x level, grouped by series level (Fig. 9b).
    pub fn plot(&self, store: &Store, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
        std::fs::create_dir_all(dir).map_err(|source| ReportError::Io { path: dir.into(), source })?;
        let mut files = Vec::new();
        let x_name = if self.x_name.is_empty() { "condition".to_string() } else { self.x_name.clone() };
        let tasks: Vec<String> = {
            let mut t: Vec<String> = self.points.iter().map(|p| p.task.clone()).collect();
            t.dedup();
            t
        };
        // A series knob that is also the x knob adds nothing to the curves.
        let by_series = !self.series_name.is_empty() && self.series_name != x_name;
        let kept: HashMap<i64, &StoredTrial> = {
            let keys: std::collections::HashSet<(String, String, u64)> =
                self.points.iter().map(|p| (p.task.clone(), p.condition.clone(), p.seed)).collect();
            self.trials
                .iter()
                .filter(|t| keys.contains(&(t.task.clone(), t.condition.clone(), t.seed)))
                .map(|t| (t.id, t))
                .collect()
        };
        // Learning curves: median and IQR of task % per step, per x level (and series).
        type Key = (String, String, u64, String); // task, series, x order bits, x label
        let mut acc: BTreeMap<Key, BTreeMap<u64, Vec<f64>>> = BTreeMap::new();
        store.for_each_task_pct(|id, step, v| {
            if let Some(t) = kept.get(&id) {
                let series = if by_series { t.series.clone() } else { String::new() };
                let key = (t.task.clone(), series, order_bits(t.x), t.x_label.clone());
                acc.entry(key).or_default().entry(step).or_default().push(v);
            }
        })?;
        let mut panels: BTreeMap<(String, String), Vec<Curve>> = BTreeMap::new();
        for ((task, series, _, x_label), by_step) in acc {
            panels.entry((task, series)).or_default().push(curve(format!("{x_name} = {x_label}"), by_step));
        }
        for ((task, series), curves) in &panels {
            let (stem, title) = if series.is_empty() {
                (
                    format!("curves-{task}"),
                    format!("{} ({task}): task % over time by {x_name} (median, IQR band)", self.name),
                )
            } else {
                (
                    format!("curves-{task}-{}-{}", self.series_name, sanitize(series)),
                    format!(
                        "{} ({task}, {} = {series}): task % over time by {x_name} (median, IQR band)",
                        self.name, self.series_name
                    ),
                )
            };
            // A change of task is marked where it happened (issue 30.4).
            let marks: Vec<u64> = {
                let mut m: Vec<u64> = self.switches.iter().filter(|r| &r.task == task).map(|r| r.switch_at).collect();
                m.sort_unstable();
                m.dedup();
                m
            };
            files.extend(plot::learning_curves_marked(&dir.join(stem), &title, curves, self.threshold, &marks)?);
        }
        files.extend(self.plot_learning(store, dir, &kept, by_series, &x_name)?);
        for task in &tasks {
            let pts: Vec<&Point> = self.points.iter().filter(|p| &p.task == task).collect();
            let title = format!("{} ({task}): power and efficiency vs {x_name}", self.name);
            let panels = self.resilience_panels(task, "");
            files.extend(plot::scatter(&dir.join(format!("resilience-{task}")), &title, &panels, 2)?);
            let ticks = panels.first().map(|p| p.ticks.clone()).unwrap_or_default();
            // Box plots per x level, grouped by series level.
            let series: Vec<&String> =
                self.series_levels.iter().filter(|s| pts.iter().any(|p| &p.series == *s)).collect();
            let series_labels: Vec<String> = series
                .iter()
                .map(|s| if s.is_empty() { String::new() } else { format!("{} = {s}", self.series_name) })
                .collect();
            let groups = |value: &dyn Fn(&Point) -> Option<f64>| -> Vec<BoxGroup> {
                ticks
                    .iter()
                    .map(|(pos, label)| BoxGroup {
                        label: label.clone(),
                        boxes: series
                            .iter()
                            .map(|s| {
                                pts.iter()
                                    .filter(|p| p.x_pos == *pos && &p.series == *s)
                                    .filter_map(|p| value(p))
                                    .collect()
                            })
                            .collect(),
                    })
                    .collect()
            };
            let title = format!("{} ({task}): final task % by {x_name}", self.name);
            files.extend(plot::boxes(
                &dir.join(format!("final-{task}")),
                &title,
                &groups(&|p| Some(p.final_pct)),
                &series_labels,
                &x_name,
                &BoxAxis::task_pct(),
            )?);
            let ms: Vec<f64> = pts.iter().filter_map(|p| p.ms_per_step).collect();
            if let Some(max) = ms.iter().copied().reduce(f64::max) {
                let title = format!("{} ({task}): wall time per step by {x_name} (each trial's last stage)", self.name);
                let axis =
                    BoxAxis { label: "wall ms per step".into(), range: (0.0, if max > 0.0 { max * 1.3 } else { 1.0 }) };
                files.extend(plot::boxes(
                    &dir.join(format!("walltime-{task}")),
                    &title,
                    &groups(&|p| p.ms_per_step),
                    &series_labels,
                    &x_name,
                    &axis,
                )?);
            }
        }
        Ok(files)
    }

    /// `learning-{task}`: the learning runs whose populations the trials tested, one
    /// curve per series level (without a series knob, or with x as the series, one per
    /// x level). A learning run tested by several trials of a curve (one per sample
    /// size, say) counts once.
    fn plot_learning(
        &self,
        store: &Store,
        dir: &Path,
        kept: &HashMap<i64, &StoredTrial>,
        by_series: bool,
        x_name: &str,
    ) -> Result<Vec<PathBuf>, ReportError> {
        let mut runs: BTreeMap<i64, Vec<(u64, f64)>> = BTreeMap::new();
        store.for_each_learning_pct(|id, step, v| {
            if kept.contains_key(&id) {
                runs.entry(id).or_default().push((step, v));
            }
        })?;
        let mut seen = std::collections::HashSet::new();
        // (task, curve order, curve label) → step → values
        let mut acc: BTreeMap<(String, u64, String), BTreeMap<u64, Vec<f64>>> = BTreeMap::new();
        for (id, rows) in runs {
            let t = kept[&id];
            let (order, label) = if by_series {
                let si = self.series_levels.iter().position(|s| s == &t.series).unwrap_or(usize::MAX);
                (si as u64, format!("{} = {}", self.series_name, t.series))
            } else {
                (order_bits(t.x), format!("{x_name} = {}", t.x_label))
            };
            let digest: Vec<(u64, u64)> = rows.iter().map(|(s, v)| (*s, v.to_bits())).collect();
            if !seen.insert((t.task.clone(), order, t.seed, digest)) {
                continue;
            }
            let by_step = acc.entry((t.task.clone(), order, label)).or_default();
            for (step, v) in rows {
                by_step.entry(step).or_default().push(v);
            }
        }
        let mut panels: BTreeMap<String, Vec<Curve>> = BTreeMap::new();
        for ((task, _, label), by_step) in acc {
            panels.entry(task).or_default().push(curve(label, by_step));
        }
        let mut files = Vec::new();
        let by = if by_series { &self.series_name } else { x_name };
        for (task, curves) in &panels {
            let title =
                format!("{} ({task}): task % of the learning runs tested, by {by} (median, IQR band)", self.name);
            files.extend(plot::learning_curves(&dir.join(format!("learning-{task}")), &title, curves, self.threshold)?);
        }
        Ok(files)
    }
}

/// The median and quartiles of task % per step (at most about 600 steps drawn, the last
/// always), starting from 0 % at step 0.
/// Print the power and efficiency slopes of several campaigns (one row per campaign,
/// task, series level and metric), write them to `stem.csv`, and draw them on one
/// figure `stem.png`/`.svg`: a row per task, each campaign's power and efficiency panels
/// side by side.
pub fn slopes(reports: &[Report], stem: &Path, out: &mut dyn Write) -> Result<Vec<PathBuf>, ReportError> {
    let io = |source| ReportError::Io { path: stem.into(), source };
    let mut tasks: Vec<&str> = Vec::new();
    for r in reports {
        for p in &r.points {
            if !tasks.contains(&p.task.as_str()) {
                tasks.push(&p.task);
            }
        }
    }
    let mut csv = String::from("campaign,x,task,series,metric,trials,slope_per_position,slope_per_unit\n");
    writeln!(
        out,
        "{:<24} {:<9} {:<8} {:<10} {:>6} {:>14} {:>14}",
        "campaign", "task", "series", "metric", "trials", "slope/position", "slope/unit"
    )
    .map_err(io)?;
    for r in reports {
        for f in &r.fits {
            writeln!(
                out,
                "{:<24} {:<9} {:<8} {:<10} {:>6} {:>14} {:>14}",
                r.name,
                f.task,
                f.series,
                f.metric,
                f.n,
                fmt_opt(f.slope_per_position),
                fmt_opt(f.slope_per_unit)
            )
            .map_err(io)?;
            let o = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
            csv.push_str(&format!(
                "{},{},{},{},{},{},{},{}\n",
                csv_field(&r.name),
                csv_field(&r.x_name),
                f.task,
                csv_field(&f.series),
                f.metric,
                f.n,
                o(f.slope_per_position),
                o(f.slope_per_unit)
            ));
        }
    }
    if let Some(dir) = stem.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| ReportError::Io { path: dir.into(), source })?;
    }
    let mut files = vec![write_file(&stem.with_extension("csv"), &csv)?];
    let panels: Vec<ScatterPanel> = tasks
        .iter()
        .flat_map(|task| reports.iter().flat_map(move |r| r.resilience_panels(task, &format!("{} ({task}), ", r.name))))
        .collect();
    let names: Vec<&str> = reports.iter().map(|r| r.name.as_str()).collect();
    let title = format!("power and efficiency slopes: {}", names.join(", "));
    files.extend(plot::scatter(stem, &title, &panels, 2 * reports.len())?);
    Ok(files)
}

fn curve(label: String, by_step: BTreeMap<u64, Vec<f64>>) -> Curve {
    let mut c = Curve { label, steps: vec![0], median: vec![0.0], q1: vec![0.0], q3: vec![0.0] };
    let every = (by_step.len() / 600).max(1);
    let last = by_step.keys().next_back().copied();
    for (i, (step, mut vals)) in by_step.into_iter().enumerate() {
        if i % every != 0 && Some(step) != last {
            continue;
        }
        vals.sort_by(|a, b| a.total_cmp(b));
        c.steps.push(step);
        c.median.push(metrics::quantile(&vals, 0.5).unwrap_or(0.0));
        c.q1.push(metrics::quantile(&vals, 0.25).unwrap_or(0.0));
        c.q3.push(metrics::quantile(&vals, 0.75).unwrap_or(0.0));
    }
    c
}

/// Sort key of an f64 that orders like the number (for BTreeMap keys).
fn order_bits(x: f64) -> u64 {
    let b = x.to_bits();
    if b >> 63 == 1 {
        !b
    } else {
        b | (1 << 63)
    }
}

fn sanitize(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '.' || c == '-' { c } else { '_' }).collect()
}

fn write_file(path: &Path, text: &str) -> Result<PathBuf, ReportError> {
    std::fs::write(path, text).map_err(|source| ReportError::Io { path: path.into(), source })?;
    Ok(path.into())
}
