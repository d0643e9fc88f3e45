//! Shards: a deterministic, cost-balanced split of a campaign's trials into N parts, so
//! that N independent processes (the tasks of a cluster job array) each run one part
//! into a database of their own, which `geese merge` then combines.
//!
//! The shards never talk to each other: each computes the whole partition itself from
//! the resolved campaign and keeps its own part. The partition therefore depends on the
//! resolved campaign alone — integer costs, a total order on the trials, no clock, hash
//! seed or thread count — so every shard computes the same one.
//!
//! A trial's cost is estimated from its resolved settings as agents × steps × stages
//! (a learning run followed by a fixed test of its population is two stages of `steps`
//! steps, a Multi-GEESE collect-then-combine run two, both and a test three). Trials
//! that test the same learned population (Fig. 8b's sampling sizes: one learning run per
//! algorithm, task and seed, tested at several sizes) share their learning stages in one
//! process ([`crate::campaigns::campaign::StageCache`]), so they are kept in one shard as one unit:
//! split over several shards, each would learn the population again.
//!
//! Units are assigned greedily, longest processing time first: sorted by (cost
//! descending, trial key), each goes to the shard with the least cost so far (the lowest
//! index on ties). Whatever the order, this keeps the most loaded shard within one unit's
//! cost of the least loaded one.
use crate::campaigns::campaign::{Campaign, PlannedTrial, StageCache};
use crate::run::config::{FollowUp, RunSpec};
use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap};
use std::fmt;
use std::str::FromStr;

/// Shard `index` of `count` (`I/N`), `index` counted from 1 as Slurm's
/// `SLURM_ARRAY_TASK_ID` is for `--array=1-N`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Shard {
    index: u32,
    count: u32,
}

/// A shard spec that is not `I/N` with 1 ≤ I ≤ N; each names the value as given.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ShardError {
    #[error("shard '{0}': expected I/N (shard I of N, I counted from 1), e.g. 2/4")]
    Syntax(String),
    #[error("shard '{value}': {what} '{text}' is not a whole number (expected I/N, e.g. 2/4)")]
    NotANumber { value: String, what: &'static str, text: String },
    #[error("shard '{0}': N must be at least 1")]
    NoShards(String),
    #[error("shard '{0}': I counts from 1 (1 ≤ I ≤ N)")]
    Zero(String),
    #[error("shard '{value}': I = {index} is greater than N = {count} (1 ≤ I ≤ N)")]
    TooLarge { value: String, index: u32, count: u32 },
}

impl Shard {
    /// Shard `index` (from 1) of `count`.
    pub fn new(index: u32, count: u32) -> Result<Shard, ShardError> {
        let value = format!("{index}/{count}");
        if count == 0 {
            Err(ShardError::NoShards(value))
        } else if index == 0 {
            Err(ShardError::Zero(value))
        } else if index > count {
            Err(ShardError::TooLarge { value, index, count })
        } else {
            Ok(Shard { index, count })
        }
    }

    /// I, counted from 1.
    pub fn index(&self) -> u32 {
        self.index
    }

    /// N.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// `shard-I-of-N`, for file names (a `/` cannot be in one).
    pub fn file_tag(&self) -> String {
        format!("shard-{}-of-{}", self.index, self.count)
    }
}

impl fmt::Display for Shard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl FromStr for Shard {
    type Err = ShardError;
    fn from_str(s: &str) -> Result<Shard, ShardError> {
        let Some((i, n)) = s.split_once('/') else {
            return Err(ShardError::Syntax(s.into()));
        };
        // Digits only: `u32::from_str` would also take "+2".
        let number = |what: &'static str, text: &str| {
            let parsed = if text.bytes().all(|b| b.is_ascii_digit()) { text.parse::<u32>().ok() } else { None };
            parsed.ok_or_else(|| ShardError::NotANumber { value: s.into(), what, text: text.into() })
        };
        let (index, count) = (number("I", i)?, number("N", n)?);
        Shard::new(index, count).map_err(|e| match e {
            // Name the value as the user wrote it (e.g. "05/4").
            ShardError::NoShards(_) => ShardError::NoShards(s.into()),
            ShardError::Zero(_) => ShardError::Zero(s.into()),
            ShardError::TooLarge { index, count, .. } => ShardError::TooLarge { value: s.into(), index, count },
            other => other,
        })
    }
}

/// Stages a run goes through: 1, plus a combine phase after a Multi-GEESE collect phase,
/// plus the fixed test of a learned population.
pub fn stages(spec: &RunSpec) -> u64 {
    let c = &spec.config;
    match spec.follow_up {
        FollowUp::None => 1,
        FollowUp::FixedTest => 2,
        FollowUp::Combine => 2 + u64::from(c.sample.is_some()),
    }
}

/// Estimated cost of one stage of `spec`: agents × steps (agent-steps).
pub fn stage_cost(spec: &RunSpec) -> u64 {
    u64::from(spec.config.world.agents).saturating_mul(spec.config.steps)
}

/// Estimated cost of a trial run alone: agents × steps × stages.
pub fn trial_cost(spec: &RunSpec) -> u64 {
    stage_cost(spec).saturating_mul(stages(spec))
}

/// A trial's key in the results database: (condition label, task, seed).
pub type TrialKey = (String, String, u64);

/// Trials that must run in the same shard (those testing one learned population), with
/// their joint cost.
#[derive(Clone, Debug, PartialEq)]
pub struct Unit {
    /// Indices into [`Campaign::plan`], ascending.
    pub trials: Vec<usize>,
    /// The learning stages once, plus every trial's last stage.
    pub cost: u64,
    /// The smallest key of its trials: the tie-break of the assignment order.
    pub key: TrialKey,
}

/// The campaign's trials grouped into units, in plan order of their first trial.
pub fn units(campaign: &Campaign) -> Vec<Unit> {
    let plan = campaign.plan();
    let mut units: Vec<Unit> = Vec::new();
    // Units by the cache key of the learning stage their trials share.
    let mut shared: BTreeMap<String, usize> = BTreeMap::new();
    for (i, t) in plan.iter().enumerate() {
        let spec = campaign.spec(t);
        let key = trial_key(campaign, t);
        if spec.follow_up == FollowUp::None {
            units.push(Unit { trials: vec![i], cost: trial_cost(&spec), key });
            continue;
        }
        let stage = stage_cost(&spec);
        match shared.get(&StageCache::key(&spec)) {
            Some(&u) => {
                // Another test of a population already counted: only its own last stage.
                let unit = &mut units[u];
                unit.trials.push(i);
                unit.cost = unit.cost.saturating_add(stage);
                unit.key = unit.key.clone().min(key);
            }
            None => {
                shared.insert(StageCache::key(&spec), units.len());
                units.push(Unit { trials: vec![i], cost: trial_cost(&spec), key });
            }
        }
    }
    units
}

fn trial_key(campaign: &Campaign, t: &PlannedTrial) -> TrialKey {
    (campaign.conditions[t.condition].label(), t.task.to_string(), t.seed)
}

/// Longest processing time first: the shard (0-based) of each unit, given as (cost,
/// key), over `n` shards. Units are taken by cost, descending, then by key; each goes to
/// the shard with the least cost so far, the lowest index on ties. Afterwards the most
/// loaded shard carries at most one unit's cost more than the least loaded one.
pub fn assign<K: Ord>(units: &[(u64, K)], n: u32) -> Vec<u32> {
    let mut order: Vec<usize> = (0..units.len()).collect();
    order.sort_by(|&a, &b| units[b].0.cmp(&units[a].0).then_with(|| units[a].1.cmp(&units[b].1)));
    let mut loads: BinaryHeap<Reverse<(u64, u32)>> = (0..n.max(1)).map(|s| Reverse((0, s))).collect();
    let mut out = vec![0; units.len()];
    for u in order {
        if let Some(Reverse((load, s))) = loads.pop() {
            out[u] = s;
            loads.push(Reverse((load.saturating_add(units[u].0), s)));
        }
    }
    out
}

/// The shard (0-based) of every trial of [`Campaign::plan`], over `n` shards.
pub fn partition(campaign: &Campaign, n: u32) -> Vec<u32> {
    let units = units(campaign);
    let keyed: Vec<(u64, TrialKey)> = units.iter().map(|u| (u.cost, u.key.clone())).collect();
    let mut out = vec![0; campaign.plan().len()];
    for (u, s) in units.iter().zip(assign(&keyed, n)) {
        for &t in &u.trials {
            out[t] = s;
        }
    }
    out
}

/// The trials of `shard`, in plan order.
pub fn plan(campaign: &Campaign, shard: Shard) -> Vec<PlannedTrial> {
    let part = partition(campaign, shard.count);
    campaign.plan().into_iter().zip(part).filter(|(_, s)| *s + 1 == shard.index).map(|(t, _)| t).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn shard_specs_parse_and_bad_ones_name_the_value() {
        assert_eq!("2/4".parse::<Shard>(), Shard::new(2, 4));
        assert_eq!("1/1".parse::<Shard>().map(|s| (s.index(), s.count())), Ok((1, 1)));
        assert_eq!(Shard::new(3, 8).map(|s| (s.to_string(), s.file_tag())), Ok(("3/8".into(), "shard-3-of-8".into())));
        for (bad, says) in [
            ("5/4", "shard '5/4': I = 5 is greater than N = 4"),
            ("0/0", "shard '0/0': N must be at least 1"),
            ("0/4", "shard '0/4': I counts from 1"),
            ("a/b", "shard 'a/b': I 'a' is not a whole number"),
            ("2/b", "shard '2/b': N 'b' is not a whole number"),
            ("3", "shard '3': expected I/N"),
            ("", "shard '': expected I/N"),
            ("+1/4", "shard '+1/4': I '+1' is not a whole number"),
            ("1/4/2", "shard '1/4/2': N '4/2' is not a whole number"),
            ("-1/4", "shard '-1/4': I '-1'"),
            ("1/99999999999", "shard '1/99999999999': N '99999999999' is not a whole number"),
        ] {
            let e = bad.parse::<Shard>().expect_err(bad).to_string();
            assert!(e.starts_with(says), "{bad}: {e}");
        }
    }

    #[test]
    fn assignment_is_balanced_within_one_unit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for round in 0..200 {
            let len = rng.random_range(0..60);
            let n = rng.random_range(1..9);
            let units: Vec<(u64, usize)> = (0..len).map(|i| (rng.random_range(1..1000), i)).collect();
            let a = assign(&units, n);
            assert_eq!(a, assign(&units, n), "deterministic");
            let mut loads = vec![0u64; n as usize];
            for (u, s) in units.iter().zip(&a) {
                loads[*s as usize] += u.0;
            }
            let max_unit = units.iter().map(|u| u.0).max().unwrap_or(0);
            let (lo, hi) = (loads.iter().min().copied().unwrap_or(0), loads.iter().max().copied().unwrap_or(0));
            assert!(hi <= lo + max_unit, "round {round}: loads {loads:?}, largest unit {max_unit}");
        }
        // Equal costs are taken in key order.
        assert_eq!(assign(&[(5, "c"), (5, "a"), (5, "b"), (9, "z")], 2), [0, 1, 1, 0]);
    }

    /// 3 agent levels × 2 tasks × 5 seeds = 30 trials of unequal costs.
    const MIXED: &str = r#"
        tasks = ["foraging", "nest"]
        seeds = 5
        [base]
        steps = 100
        [[grid]]
        agents = [10, 20, 70]
    "#;

    /// Check `campaign` split over `n` shards: every trial in exactly one shard, the
    /// same split when computed again, and loads within one unit of each other.
    fn check_partition(campaign: &Campaign, n: u32) -> Vec<u64> {
        let all = campaign.plan();
        let part = partition(campaign, n);
        assert_eq!(part, partition(campaign, n), "deterministic");
        let mut seen = vec![0; all.len()];
        let mut loads = vec![0u64; n as usize];
        for i in 1..=n {
            let shard = Shard::new(i, n).expect("shard");
            for t in plan(campaign, shard) {
                let at = all.iter().position(|p| (p.condition, p.task, p.seed) == (t.condition, t.task, t.seed));
                seen[at.expect("a planned trial")] += 1;
            }
        }
        assert!(seen.iter().all(|&k| k == 1), "every trial exactly once: {seen:?}");
        let units = units(campaign);
        for u in &units {
            assert!(u.trials.iter().all(|&t| part[t] == part[u.trials[0]]), "a unit is split");
            loads[part[u.trials[0]] as usize] += u.cost;
        }
        let max_unit = units.iter().map(|u| u.cost).max().unwrap_or(0);
        let (lo, hi) = (loads.iter().min().copied().unwrap_or(0), loads.iter().max().copied().unwrap_or(0));
        assert!(hi <= lo + max_unit, "{n} shards: loads {loads:?}, largest unit {max_unit}");
        loads
    }

    #[test]
    fn trials_are_partitioned_deterministically_and_balanced() {
        let c = Campaign::from_toml(MIXED, "mixed").expect("campaign");
        // Without shared stages every trial is its own unit, costing agents × steps.
        let units = units(&c);
        assert_eq!(units.len(), 30);
        assert_eq!(units.iter().map(|u| u.cost).max(), Some(70 * 100));
        for n in [1, 2, 3, 4, 7, 30, 31, 64] {
            let loads = check_partition(&c, n);
            assert_eq!(loads.iter().sum::<u64>(), 10 * 100 * (10 + 20 + 70));
        }
        assert_eq!(check_partition(&c, 2), [50_000, 50_000]);
        // The same campaign built again (another process) splits the same way.
        let again = Campaign::from_toml(MIXED, "mixed").expect("campaign");
        assert_eq!(partition(&c, 4), partition(&again, 4));
    }

    #[test]
    fn tests_of_one_learned_population_stay_in_one_shard() {
        // 2 algorithms × 3 sampling sizes × 4 seeds: 8 learning runs, each tested 3 times.
        let text = r#"
            tasks = ["foraging"]
            seeds = 4
            x = "sample"
            [base]
            steps = 50
            [base.world]
            agents = 10
            [[grid]]
            algorithm = ["geese-bt", "multi-geese"]
            sample = [0.2, 0.5, 1.0]
        "#;
        let c = Campaign::from_toml(text, "sampling").expect("campaign");
        let units = units(&c);
        assert_eq!(units.len(), 8);
        for u in &units {
            let specs: Vec<RunSpec> = u.trials.iter().map(|&t| c.spec(&c.plan()[t])).collect();
            assert_eq!(specs.len(), 3);
            assert!(specs.iter().all(|s| s.config.seed == specs[0].config.seed));
            // GEESE-BT: learn once + 3 tests; Multi-GEESE: collect and combine once + 3 tests.
            let learning = if specs[0].follow_up == FollowUp::Combine { 2 } else { 1 };
            assert_eq!(u.cost, (learning + 3) * 10 * 50);
        }
        for n in [1, 2, 3, 5, 8, 9] {
            check_partition(&c, n);
        }
    }
}
