//! Resilience metrics of REFERENCE.md §8.1 as pure functions: success rate, power,
//! efficiency (the paper's definitions and the reference code's variants), summary
//! statistics and the least-squares slope across conditions.
//!
//! They are kept free of I/O so that each can be checked against hand-computed numbers,
//! and so that the report and any external tool compute exactly the same thing.
use serde::{Deserialize, Serialize};

/// T_min of the reference code's Sec.-5 ablation efficiency (`resilience_metrics.py`).
pub const T_MIN_SEC5_ABLATION: f64 = 5200.0;
/// T_min of the reference code's Sec.-5 addition/distortion/shift efficiency.
pub const T_MIN_SEC5: f64 = 2756.0;

/// What one trial's task-% series amounts to for the metrics.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    /// Steps run (T_max).
    pub steps: u64,
    /// Task % after the last step.
    pub final_pct: f64,
    pub max_pct: f64,
    /// First step whose task % is ≥ θ.
    pub first_at_threshold: Option<u64>,
    /// Number of steps whose task % is ≥ θ (the reference's one-row artefact needs it).
    pub rows_at_threshold: u64,
    /// Task % exceeded θ at some step (PAPER Sec. 3.3: "more than 80 %").
    pub success: bool,
}

/// Summarise a series of task % values, one per step (step 1 first).
pub fn outcome(series: &[f64], theta: f64) -> Outcome {
    let mut o = Outcome {
        steps: series.len() as u64,
        final_pct: series.last().copied().unwrap_or(0.0),
        max_pct: 0.0,
        first_at_threshold: None,
        rows_at_threshold: 0,
        success: false,
    };
    for (i, &v) in series.iter().enumerate() {
        o.max_pct = o.max_pct.max(v);
        if v >= theta {
            o.rows_at_threshold += 1;
            o.first_at_threshold.get_or_insert(i as u64 + 1);
        }
        o.success |= v > theta;
    }
    o
}

/// Percentage of successful trials.
pub fn success_rate(success: &[bool]) -> f64 {
    if success.is_empty() {
        return 0.0;
    }
    100.0 * success.iter().filter(|&&s| s).count() as f64 / success.len() as f64
}

/// Which power definition.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum PowerVariant {
    /// PAPER: the maximum success probability attained before T (in %). Per trial this is
    /// the success indicator (100 or 0); its mean over a condition's trials is the
    /// condition's success probability. Because task % never decreases in this world
    /// (delivered items stay delivered), the probability is largest at T, so the maximum
    /// over time equals the success rate.
    #[default]
    Paper,
    /// CODE: the task % of the last step, one value per trial.
    Code,
}

/// Per-trial power value.
pub fn power(o: &Outcome, v: PowerVariant) -> f64 {
    match v {
        PowerVariant::Paper => {
            if o.success {
                100.0
            } else {
                0.0
            }
        }
        PowerVariant::Code => o.final_pct,
    }
}

/// Which efficiency definition.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum EfficiencyVariant {
    /// PAPER: e = (T_max − t_θ)/T_max · 100, 0 when θ is never reached.
    #[default]
    Paper,
    /// CODE Sec. 5 ablation: e = (1 − (t_θ − 5200)/(T_max − 5200))·100.
    Sec5Ablation,
    /// CODE Sec. 5 addition/distortion/shift: e = (1 − |t_θ − 2756|/(T_max − 2756))·100.
    Sec5,
    /// CODE Sec. 7: t_min = the smallest t_θ among the condition's trials.
    Sec7,
}

impl EfficiencyVariant {
    pub fn name(self) -> &'static str {
        match self {
            EfficiencyVariant::Paper => "paper",
            EfficiencyVariant::Sec5Ablation => "sec5-ablation",
            EfficiencyVariant::Sec5 => "sec5",
            EfficiencyVariant::Sec7 => "sec7",
        }
    }
}

/// PAPER efficiency of one trial.
pub fn efficiency_paper(first_at_threshold: Option<u64>, t_max: u64) -> f64 {
    match first_at_threshold {
        Some(t) if t_max > 0 => (t_max.saturating_sub(t)) as f64 / t_max as f64 * 100.0,
        _ => 0.0,
    }
}

/// The reference code's t_θ: the first row whose value is ≥ θ, rows numbered by the step
/// counter with row 1 = the state before the first step (so the row after step s is
/// s + 1); T_max when θ is never reached — or reached in exactly one row, an indexing
/// artefact of `resilience_metrics.py` that the CODE variants reproduce.
pub fn t_theta_code(o: &Outcome) -> f64 {
    match o.first_at_threshold {
        Some(s) if o.rows_at_threshold >= 2 => (s + 1) as f64,
        _ => o.steps as f64,
    }
}

/// CODE Sec.-5 efficiency: (1 − (t_θ − t_min)/(T_max − t_min))·100, with |t_θ − t_min|
/// when `absolute` (addition, distortion, shift). Not clamped: the reference isn't.
pub fn efficiency_sec5(t_theta: f64, t_min: f64, t_max: f64, absolute: bool) -> f64 {
    let d = t_theta - t_min;
    let d = if absolute { d.abs() } else { d };
    (1.0 - d / (t_max - t_min)) * 100.0
}

/// CODE Sec.-7 efficiency of each trial of one condition: t_min is the condition's
/// fastest t_θ, so that trial scores 100 and failures (t_θ = T_max) 0. When every trial
/// failed (t_min = T_max, 0/0 in the reference) all score 0.
pub fn efficiency_sec7(t_thetas: &[f64], t_max: f64) -> Vec<f64> {
    let t_min = t_thetas.iter().copied().fold(f64::INFINITY, f64::min);
    t_thetas
        .iter()
        .map(|&t| if t_max - t_min <= 0.0 { 0.0 } else { (1.0 - (t - t_min) / (t_max - t_min)) * 100.0 })
        .collect()
}

/// Efficiency of every trial of one condition under `v`.
pub fn efficiencies(outcomes: &[Outcome], v: EfficiencyVariant) -> Vec<f64> {
    match v {
        EfficiencyVariant::Paper => outcomes.iter().map(|o| efficiency_paper(o.first_at_threshold, o.steps)).collect(),
        EfficiencyVariant::Sec5Ablation => outcomes
            .iter()
            .map(|o| efficiency_sec5(t_theta_code(o), T_MIN_SEC5_ABLATION, o.steps as f64, false))
            .collect(),
        EfficiencyVariant::Sec5 => {
            outcomes.iter().map(|o| efficiency_sec5(t_theta_code(o), T_MIN_SEC5, o.steps as f64, true)).collect()
        }
        EfficiencyVariant::Sec7 => {
            let t_max = outcomes.iter().map(|o| o.steps).max().unwrap_or(0) as f64;
            efficiency_sec7(&outcomes.iter().map(t_theta_code).collect::<Vec<_>>(), t_max)
        }
    }
}

/// Quantile with linear interpolation between order statistics (NumPy's default).
/// `sorted` must be sorted ascending; `None` when empty.
pub fn quantile(sorted: &[f64], p: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let pos = p.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    Some(sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64))
}

/// Mean, median and quartiles of a sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub n: usize,
    pub mean: f64,
    pub median: f64,
    pub q1: f64,
    pub q3: f64,
    pub min: f64,
    pub max: f64,
}

impl Stats {
    pub fn iqr(&self) -> f64 {
        self.q3 - self.q1
    }
}

/// Summary statistics; `None` for an empty sample.
pub fn stats(values: &[f64]) -> Option<Stats> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    Some(Stats {
        n: v.len(),
        mean: v.iter().sum::<f64>() / v.len() as f64,
        median: quantile(&v, 0.5)?,
        q1: quantile(&v, 0.25)?,
        q3: quantile(&v, 0.75)?,
        min: v[0],
        max: v[v.len() - 1],
    })
}

/// Ordinary least-squares line y = slope·x + intercept (REFERENCE §8.1, degree-1 fit).
/// `None` with fewer than two points or when every x is the same.
pub fn ols(xs: &[f64], ys: &[f64]) -> Option<(f64, f64)> {
    let n = xs.len().min(ys.len());
    if n < 2 {
        return None;
    }
    let mx = xs[..n].iter().sum::<f64>() / n as f64;
    let my = ys[..n].iter().sum::<f64>() / n as f64;
    let sxx: f64 = xs[..n].iter().map(|x| (x - mx).powi(2)).sum();
    if sxx == 0.0 {
        return None;
    }
    let sxy: f64 = xs[..n].iter().zip(&ys[..n]).map(|(x, y)| (x - mx) * (y - my)).sum();
    let slope = sxy / sxx;
    Some((slope, my - slope * mx))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) {
        assert!((a - b).abs() < 1e-9, "{a} != {b}");
    }

    #[test]
    fn outcome_of_a_series() {
        let o = outcome(&[0.0, 10.0, 80.0, 80.0, 95.0], 80.0);
        assert_eq!(o.steps, 5);
        assert_eq!(o.first_at_threshold, Some(3));
        assert_eq!(o.rows_at_threshold, 3);
        assert!(o.success);
        close(o.final_pct, 95.0);
        // Reaching exactly 80 is not "more than 80 %".
        let o = outcome(&[0.0, 80.0, 80.0], 80.0);
        assert!(!o.success);
        assert_eq!(o.first_at_threshold, Some(2));
        let o = outcome(&[], 80.0);
        assert_eq!((o.steps, o.first_at_threshold, o.success), (0, None, false));
    }

    #[test]
    fn success_rate_and_power() {
        close(success_rate(&[true, false, true, true]), 75.0);
        close(success_rate(&[]), 0.0);
        let o = outcome(&[10.0, 50.0, 70.0], 80.0);
        close(power(&o, PowerVariant::Paper), 0.0);
        close(power(&o, PowerVariant::Code), 70.0);
        let o = outcome(&[10.0, 90.0, 90.0], 80.0);
        close(power(&o, PowerVariant::Paper), 100.0);
    }

    #[test]
    fn paper_efficiency() {
        // T_max 12000, reached at 3000: (12000 − 3000)/12000 · 100 = 75.
        close(efficiency_paper(Some(3000), 12_000), 75.0);
        close(efficiency_paper(None, 12_000), 0.0);
        close(efficiency_paper(Some(12_000), 12_000), 0.0);
    }

    fn o(first: Option<u64>, rows: u64, steps: u64) -> Outcome {
        Outcome {
            steps,
            final_pct: 0.0,
            max_pct: 0.0,
            first_at_threshold: first,
            rows_at_threshold: rows,
            success: first.is_some(),
        }
    }

    #[test]
    fn code_t_theta_and_its_one_row_artefact() {
        close(t_theta_code(&o(Some(5000), 7001, 12_000)), 5001.0);
        close(t_theta_code(&o(Some(12_000), 1, 12_000)), 12_000.0);
        close(t_theta_code(&o(Some(11_999), 2, 12_000)), 12_000.0);
        close(t_theta_code(&o(None, 0, 12_000)), 12_000.0);
    }

    #[test]
    fn sec5_efficiency() {
        // Ablation: t_θ 8600, t_min 5200, T_max 12000: 1 − 3400/6800 = 0.5 → 50.
        close(efficiency_sec5(8600.0, 5200.0, 12_000.0, false), 50.0);
        // Faster than t_min scores above 100 in the signed form ...
        close(efficiency_sec5(1800.0, 5200.0, 12_000.0, false), 150.0);
        // ... and symmetrically below it in the absolute form: |1000 − 2756| = 1756,
        // 1 − 1756/9244 = 0.81003894418...
        close(efficiency_sec5(1000.0, 2756.0, 12_000.0, true), (1.0 - 1756.0 / 9244.0) * 100.0);
        let es = efficiencies(&[o(Some(8599), 3401, 12_000), o(None, 0, 12_000)], EfficiencyVariant::Sec5Ablation);
        close(es[0], 50.0);
        close(es[1], 0.0);
    }

    #[test]
    fn sec7_efficiency() {
        // t_θ 2000, 4000, 12000 (failure): t_min 2000 → 100, 80, 0.
        let e = efficiency_sec7(&[2000.0, 4000.0, 12_000.0], 12_000.0);
        close(e[0], 100.0);
        close(e[1], 80.0);
        close(e[2], 0.0);
        assert_eq!(efficiency_sec7(&[12_000.0, 12_000.0], 12_000.0), vec![0.0, 0.0]);
        let es = efficiencies(&[o(Some(1999), 10, 12_000), o(Some(3999), 10, 12_000)], EfficiencyVariant::Sec7);
        close(es[0], 100.0);
        close(es[1], 80.0);
    }

    #[test]
    fn quartiles_like_numpy() {
        // numpy.percentile([1, 2, 3, 4], [25, 50, 75]) = [1.75, 2.5, 3.25]
        let s = stats(&[4.0, 1.0, 3.0, 2.0]).unwrap();
        close(s.q1, 1.75);
        close(s.median, 2.5);
        close(s.q3, 3.25);
        close(s.mean, 2.5);
        close(s.iqr(), 1.5);
        assert_eq!((s.min, s.max, s.n), (1.0, 4.0, 4));
        let s = stats(&[7.0]).unwrap();
        close(s.q1, 7.0);
        assert!(stats(&[]).is_none());
    }

    #[test]
    fn least_squares_slope() {
        // Points (1,10) (2,8) (3,9) (4,5): x̄ 2.5, ȳ 8, Sxy = −1.5·2 + −0.5·0 + 0.5·1 + 1.5·(−3)
        // = −7, Sxx = 5 → slope −1.4, intercept 8 + 3.5 = 11.5.
        let (m, b) = ols(&[1.0, 2.0, 3.0, 4.0], &[10.0, 8.0, 9.0, 5.0]).unwrap();
        close(m, -1.4);
        close(b, 11.5);
        assert!(ols(&[1.0, 1.0], &[2.0, 3.0]).is_none());
        assert!(ols(&[1.0], &[2.0]).is_none());
    }
}
