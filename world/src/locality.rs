//! The locality map of the paper's Fig. 5 (REFERENCE §8.3): how many agent-steps each
//! behaviour class spent at each integer location over a window of steps.
//!
//! The reference records, after every agent's step, the agent's integer location and
//! the class of its current tree (after that step's genetic operators), and the figure
//! sums these records over a window of steps. [`Locality`] does the same from the world:
//! [`World`](crate::World) feeds it the bodies once every step is resolved, so the
//! in-process driver and the world server count the same thing.
//!
//! Which steps count: a [`Window`] `FROM:TO` counts the steps numbered FROM to TO, both
//! included. Steps are numbered as the world numbers them: step 1 is the first step of
//! the run (the reference's step counter also starts at 1). After step s has been
//! resolved, every agent live at that moment counts once, at the position it ended the
//! step on, under the class its intent of step s reported; this is before the
//! perturbations scheduled after step s, as the reference's agents record inside their
//! own step and its hooks run after every agent has stepped. So an agent killed after
//! step s counts at step s and never again, and a live agent whose intent did not
//! arrive counts where it stands under the class it last reported. The reference's
//! extra record of the start positions, before step 1 (its array index 0), has no step
//! here: its figure's `[0:3000]` is the start plus steps 1–2999, 3000 records per
//! agent, as many as `1:3000` counts.
//!
//! Counters are `u64`: at most 10⁷ steps × 10⁶ agents ([`geese_proto::limits`]) = 10¹³
//! agent-steps, far from 2⁶⁴. The reference keeps 8-bit counts per step, exact only
//! while at most 127 agents share a location in one step (NOTES.md).
use crate::world::Body;
use geese_proto::{BehaviourClass, Pos};
use std::collections::HashMap;
use std::io::Write;

/// Header of `locality.csv`.
pub const CSV_HEADER: &str = "x,y,class,count";

/// Why a window or a locality file is not acceptable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LocalityError {
    #[error("{0:?}: expected FROM:TO, two step numbers such as 1:3000")]
    Form(String),
    #[error("{value:?}: {part} {text:?} is not a step number")]
    NotANumber { value: String, part: &'static str, text: String },
    #[error("{0:?}: steps count from 1 (step 1 is the first step of the run); the paper's steps 0–3000 are 1:3000")]
    Zero(String),
    #[error("{value:?}: FROM {from} comes after TO {to}")]
    Reversed { value: String, from: u64, to: u64 },
    #[error("line {line}: {reason}")]
    Csv { line: usize, reason: String },
}

/// The steps a locality map counts: FROM to TO, both included (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Window {
    pub from: u64,
    pub to: u64,
}

impl Window {
    /// Does step `step` count?
    pub fn contains(&self, step: u64) -> bool {
        self.from <= step && step <= self.to
    }

    /// How many steps of a run of `steps` steps count.
    pub fn steps_in(&self, steps: u64) -> u64 {
        let last = self.to.min(steps);
        if last < self.from {
            0
        } else {
            last - self.from + 1
        }
    }
}

impl std::str::FromStr for Window {
    type Err = LocalityError;

    /// `FROM:TO`, with 1 ≤ FROM ≤ TO.
    fn from_str(s: &str) -> Result<Self, LocalityError> {
        let (a, b) = s.split_once(':').ok_or_else(|| LocalityError::Form(s.into()))?;
        let num = |part, t: &str| {
            t.trim().parse::<u64>().map_err(|_| LocalityError::NotANumber { value: s.into(), part, text: t.into() })
        };
        let (from, to) = (num("FROM", a)?, num("TO", b)?);
        if from == 0 {
            return Err(LocalityError::Zero(s.into()));
        }
        if from > to {
            return Err(LocalityError::Reversed { value: s.into(), from, to });
        }
        Ok(Window { from, to })
    }
}

impl std::fmt::Display for Window {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.from, self.to)
    }
}

/// Agent-steps of one class at one location.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Count {
    pub x: i32,
    pub y: i32,
    /// The reference's class number, 0–5 ([`BehaviourClass::number`]).
    pub class: u8,
    pub count: u64,
}

/// The recorder: per location, agent-steps per class (sparse: only places agents
/// stood on take memory, whatever the arena's size).
#[derive(Clone, Debug)]
pub struct Locality {
    window: Window,
    cells: HashMap<Pos, [u64; 6], foldhash::fast::FixedState>,
    steps: u64,
    agent_steps: u64,
}

impl Locality {
    pub fn new(window: Window) -> Self {
        Locality { window, cells: HashMap::default(), steps: 0, agent_steps: 0 }
    }

    pub fn window(&self) -> Window {
        self.window
    }

    /// Steps counted so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Agent-steps counted so far (the sum of every count).
    pub fn agent_steps(&self) -> u64 {
        self.agent_steps
    }

    /// Count the live `bodies` as they stand after step `step`, if it is in the window.
    pub fn record(&mut self, step: u64, bodies: &[Body]) {
        if !self.window.contains(step) {
            return;
        }
        self.steps += 1;
        for b in bodies.iter().filter(|b| b.live) {
            self.cells.entry(b.pos).or_default()[usize::from(b.class.number())] += 1;
            self.agent_steps += 1;
        }
    }

    /// Every non-zero count, sorted by x, then y, then class.
    pub fn counts(&self) -> Vec<Count> {
        let mut v: Vec<Count> = self
            .cells
            .iter()
            .flat_map(|(p, c)| {
                c.iter().enumerate().filter(|(_, &n)| n > 0).map(|(k, &n)| Count {
                    x: p.x,
                    y: p.y,
                    class: k as u8,
                    count: n,
                })
            })
            .collect();
        v.sort_unstable();
        v
    }
}

/// Write `counts` as `locality.csv`: the header, then one `x,y,class,count` line each,
/// in the order given ([`Locality::counts`] sorts them).
pub fn write_csv(counts: &[Count], mut out: impl Write) -> std::io::Result<()> {
    writeln!(out, "{CSV_HEADER}")?;
    for c in counts {
        writeln!(out, "{},{},{},{}", c.x, c.y, c.class, c.count)?;
    }
    out.flush()
}

/// Read a `locality.csv`; every line is checked (four integers, class 0–5).
pub fn parse_csv(text: &str) -> Result<Vec<Count>, LocalityError> {
    let mut lines = text.lines().enumerate();
    match lines.next() {
        Some((_, h)) if h.trim() == CSV_HEADER => {}
        _ => return Err(LocalityError::Csv { line: 1, reason: format!("expected the header {CSV_HEADER}") }),
    }
    let mut v = Vec::new();
    for (i, l) in lines {
        if l.trim().is_empty() {
            continue;
        }
        let bad = |reason: String| LocalityError::Csv { line: i + 1, reason };
        let f: Vec<&str> = l.split(',').map(str::trim).collect();
        let [x, y, class, count] = f[..] else {
            return Err(bad(format!("{l:?} has {} fields, expected 4 (x,y,class,count)", f.len())));
        };
        let x = x.parse().map_err(|_| bad(format!("x {x:?} is not an integer")))?;
        let y = y.parse().map_err(|_| bad(format!("y {y:?} is not an integer")))?;
        let class = class.parse::<u8>().ok().filter(|&c| usize::from(c) < BehaviourClass::ALL.len());
        let class = class.ok_or_else(|| bad(format!("class {:?} is not 0–5", f[2])))?;
        let count = count.parse().map_err(|_| bad(format!("count {count:?} is not a non-negative integer")))?;
        v.push(Count { x, y, class, count });
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(id: u32, x: i32, y: i32, class: BehaviourClass, live: bool) -> Body {
        Body { id, pos: Pos::new(x, y), heading: 0.0, carrying: Vec::new(), live, learning: true, class }
    }

    #[test]
    fn windows_parse_and_bad_ones_name_the_value() {
        assert_eq!("5:20".parse(), Ok(Window { from: 5, to: 20 }));
        assert_eq!("1:1".parse(), Ok(Window { from: 1, to: 1 }));
        assert_eq!(Window { from: 1, to: 3000 }.to_string(), "1:3000");
        for (bad, names) in [
            ("5:3", "\"5:3\""),
            ("a:b", "\"a\""),
            ("10", "\"10\""),
            ("0:10", "\"0:10\""),
            ("1:-2", "\"-2\""),
            ("", "\"\""),
        ] {
            let e = bad.parse::<Window>().unwrap_err().to_string();
            assert!(e.contains(names), "{bad}: {e}");
        }
        assert!(matches!("5:3".parse::<Window>(), Err(LocalityError::Reversed { from: 5, to: 3, .. })));
    }

    #[test]
    fn both_ends_of_the_window_count_and_nothing_outside() {
        let w = Window { from: 5, to: 20 };
        assert!(!w.contains(4) && w.contains(5) && w.contains(20) && !w.contains(21));
        assert_eq!((w.steps_in(30), w.steps_in(20), w.steps_in(10), w.steps_in(4)), (16, 16, 6, 0));
        let mut l = Locality::new(w);
        let bodies = [body(0, 1, 2, BehaviourClass::Explore, true)];
        for step in 1..=30 {
            l.record(step, &bodies);
        }
        assert_eq!((l.steps(), l.agent_steps()), (16, 16));
        assert_eq!(l.counts(), vec![Count { x: 1, y: 2, class: 1, count: 16 }]);
    }

    #[test]
    fn dead_agents_do_not_count_and_counts_add_up_to_live_agents_times_steps() {
        let mut l = Locality::new(Window { from: 1, to: 10 });
        let mut bodies: Vec<Body> =
            (0..7).map(|i| body(i, i as i32 % 3, -(i as i32), BehaviourClass::ALL[i as usize % 6], i != 3)).collect();
        for step in 1..=10 {
            if step == 6 {
                bodies[5].live = false;
            }
            l.record(step, &bodies);
        }
        // 6 live for steps 1–5, 5 live for steps 6–10.
        assert_eq!(l.agent_steps(), 6 * 5 + 5 * 5);
        assert_eq!(l.counts().iter().map(|c| c.count).sum::<u64>(), l.agent_steps());
        assert!(!l.counts().iter().any(|c| (c.x, c.y) == (0, -3)), "the dead agent 3 was counted");
        assert!(l.counts().contains(&Count { x: 2, y: -5, class: 5, count: 5 }));
        // Sorted by x, y, class; one line per non-zero (location, class).
        let c = l.counts();
        assert!(c.windows(2).all(|p| (p[0].x, p[0].y, p[0].class) < (p[1].x, p[1].y, p[1].class)));
    }

    #[test]
    fn counts_go_past_the_reference_8_bit_and_32_bit_counters() {
        let mut l = Locality::new(Window { from: 1, to: u64::MAX });
        let crowd: Vec<Body> = (0..1000).map(|i| body(i, 0, 0, BehaviourClass::CompositeDrop, true)).collect();
        for step in 1..=300 {
            l.record(step, &crowd);
        }
        assert_eq!(l.counts(), vec![Count { x: 0, y: 0, class: 3, count: 300_000 }]);
        // Beyond u32 without four billion steps: start the counter there.
        l.cells.insert(Pos::new(0, 0), [0, 0, 0, u64::from(u32::MAX), 0, 0]);
        l.record(301, &crowd[..1]);
        assert_eq!(l.counts()[0].count, u64::from(u32::MAX) + 1);
    }

    #[test]
    fn csv_round_trips_and_bad_lines_are_named() {
        let counts = vec![
            Count { x: -50, y: 3, class: 0, count: 7 },
            Count { x: 0, y: 0, class: 5, count: u64::from(u32::MAX) + 9 },
        ];
        let mut buf = Vec::new();
        write_csv(&counts, &mut buf).unwrap();
        let text = String::from_utf8(buf).unwrap();
        assert_eq!(text, "x,y,class,count\n-50,3,0,7\n0,0,5,4294967304\n");
        assert_eq!(parse_csv(&text), Ok(counts));
        for (bad, line, what) in [
            ("x,y\n", 1, "header"),
            ("x,y,class,count\n1,2,3\n", 2, "4"),
            ("x,y,class,count\n1,2,6,1\n", 2, "class \"6\""),
            ("x,y,class,count\n1,2,1,1\n1,q,1,1\n", 3, "y \"q\""),
            ("x,y,class,count\n1,2,1,-1\n", 2, "count \"-1\""),
        ] {
            let e = parse_csv(bad).unwrap_err();
            assert!(matches!(e, LocalityError::Csv { line: l, .. } if l == line), "{bad:?}: {e}");
            assert!(e.to_string().contains(what), "{e}");
        }
    }
}
