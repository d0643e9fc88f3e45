//! The world's gathering of one step's intents (DESIGN.md §2 step 4), sans IO.
//!
//! Fed the intent batches of the agent processes as they arrive (key and bytes, as
//! received), it keeps the first answer of every agent for the step being gathered and
//! says when nothing is pending any more. Everything else is dropped and counted: a
//! batch that does not decode, one of a future step (hostile: no process can know a
//! step the world has not begun), an intent or idle mark for an agent the sending
//! process does not speak for, a second answer for the same agent. A batch of an
//! earlier step is a straggler that missed its deadline: dropped, not hostile.
//!
//! The Zenoh shell files batches from the subscriber callback (under a lock) so that the
//! world's loop wakes once per step, when [`Gather::on_action`] reports the last one.
use geese_proto::keys::{self, AgentRange, Parsed};
use geese_proto::net::{IntentBatch, NetCounters};
use geese_proto::{decode, Intent};

/// The intents of the step being gathered.
#[derive(Debug)]
pub struct Gather {
    run: String,
    n: usize,
    /// The step whose intents are awaited (0: none).
    step: u64,
    expected: Vec<bool>,
    answered: Vec<bool>,
    intents: Vec<Option<Intent>>,
    pending: usize,
    counters: NetCounters,
}

/// What a gathering yielded when it was closed ([`Gather::close`]).
#[derive(Debug)]
pub struct Gathered {
    /// The intent of every agent, by id (`None`: none arrived, or it idled).
    pub intents: Vec<Option<Intent>>,
    /// Expected agents that answered (an intent or an idle mark).
    pub answered_expected: usize,
    /// Expected agents that had not answered.
    pub pending: usize,
    /// The processes' own drop counters summed, and what the gathering dropped.
    pub counters: NetCounters,
}

impl Gather {
    /// A gathering for a run of `n` agents.
    pub fn new(run: impl Into<String>, n: usize) -> Self {
        Gather {
            run: run.into(),
            n,
            step: 0,
            expected: vec![false; n],
            answered: vec![false; n],
            intents: vec![None; n],
            pending: 0,
            counters: NetCounters::default(),
        }
    }

    /// Open step `step`, awaiting the agents for which `expected(id)` holds. Opened
    /// before the step's percepts go out: fast answers must find it open. The counters
    /// are not reset here ([`Gather::close`] took the last step's): hostile batches that
    /// came between the two steps count in this one.
    pub fn begin(&mut self, step: u64, expected: impl Fn(usize) -> bool) {
        self.step = step;
        self.pending = 0;
        for i in 0..self.n {
            self.intents[i] = None;
            self.answered[i] = false;
            self.expected[i] = expected(i);
            self.pending += self.expected[i] as usize;
        }
    }

    /// The step being gathered (0: none open).
    pub fn step(&self) -> u64 {
        self.step
    }

    /// Expected agents that have not answered yet.
    pub fn pending(&self) -> usize {
        self.pending
    }

    /// Agent `id` is no longer awaited (its process left).
    pub fn forget(&mut self, id: usize) {
        if id < self.n && self.expected[id] {
            self.expected[id] = false;
            if !self.answered[id] {
                self.pending -= 1;
            }
        }
    }

    fn answer(&mut self, id: usize) -> bool {
        if self.answered[id] {
            return false;
        }
        self.answered[id] = true;
        if self.expected[id] {
            self.pending -= 1;
        }
        true
    }

    /// File one intent batch received on `key`; true when nothing is pending any more.
    /// Genes sent ahead with it are dropped: [`Server`](crate::server::Server) takes
    /// them out first ([`Gather::open`], [`Gather::file`]).
    pub fn on_action(&mut self, key: &str, bytes: &[u8]) -> bool {
        self.open(key, bytes).is_some_and(|(from, batch)| self.file(from, batch))
    }

    /// The sender and the batch of intents received on `key`, or `None` (counted as
    /// hostile) when the key names no agent range or the bytes are no batch.
    pub fn open(&mut self, key: &str, bytes: &[u8]) -> Option<(AgentRange, IntentBatch)> {
        let Parsed::Action { from } = keys::parse(&self.run, key) else {
            self.counters.hostile += 1;
            tracing::debug!("intents on a key that names no agent range: {key}");
            return None;
        };
        match decode(bytes) {
            Ok(b) => Some((from, b)),
            Err(e) => {
                tracing::debug!("dropped intent batch on {key}: {e}");
                self.counters.hostile += 1;
                None
            }
        }
    }

    /// File the intents of the process speaking for `from`; true when nothing is
    /// pending any more.
    pub fn file(&mut self, from: AgentRange, batch: IntentBatch) -> bool {
        let step = self.step;
        tracing::trace!(target: "geese::flow", "intents of step {} from {from} (awaiting {step})", batch.step);
        if batch.step != step || step == 0 {
            // A straggler of an earlier step (after its deadline), or nonsense.
            if batch.step > step {
                tracing::debug!("intents from {from} for step {} while gathering step {step}", batch.step);
                self.counters.hostile += 1;
            }
            return false;
        }
        let c = batch.counters;
        self.counters.percepts_lost = self.counters.percepts_lost.saturating_add(c.percepts_lost);
        self.counters.percepts_missing = self.counters.percepts_missing.saturating_add(c.percepts_missing);
        self.counters.genes_late = self.counters.genes_late.saturating_add(c.genes_late);
        self.counters.hostile = self.counters.hostile.saturating_add(c.hostile);
        self.counters.deadline_hits = self.counters.deadline_hits.saturating_add(c.deadline_hits);
        for id in batch.idle {
            if !from.contains(id) || id as usize >= self.n {
                self.counters.hostile += 1;
                continue;
            }
            self.answer(id as usize);
        }
        for intent in batch.intents {
            let id = intent.agent;
            if !from.contains(id) || id as usize >= self.n || intent.step != step {
                // Claims an agent this process does not speak for.
                self.counters.hostile += 1;
                continue;
            }
            let i = id as usize;
            if self.answer(i) && self.expected[i] {
                self.intents[i] = Some(intent);
            }
        }
        self.pending == 0
    }

    /// Close the step: what was gathered; later batches of it are stragglers.
    pub fn close(&mut self) -> Gathered {
        self.step = 0;
        let answered_expected = (0..self.n).filter(|&i| self.expected[i] && self.answered[i]).count();
        Gathered {
            intents: std::mem::replace(&mut self.intents, vec![None; self.n]),
            answered_expected,
            pending: self.pending,
            counters: std::mem::take(&mut self.counters),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geese_proto::net::HostCounters;
    use geese_proto::{encode, Op};

    const RUN: &str = "t";

    fn key(first: u32, count: u32) -> String {
        keys::agents_action(RUN, AgentRange::new(first, count).unwrap())
    }

    fn intent(agent: u32, step: u64) -> Intent {
        Intent { agent, step, heading: 0.0, ops: vec![Op::Drop { object: 1 }], stats: Default::default() }
    }

    fn batch(step: u64, intents: Vec<Intent>, idle: Vec<u32>) -> Vec<u8> {
        encode(&IntentBatch { step, intents, idle, counters: HostCounters::default(), ahead: None }).unwrap()
    }

    #[test]
    fn completes_when_every_expected_agent_answered() {
        let mut g = Gather::new(RUN, 4);
        g.begin(3, |i| i != 2);
        assert_eq!(g.pending(), 3);
        assert!(!g.on_action(&key(0, 2), &batch(3, vec![intent(0, 3)], vec![1])));
        assert_eq!(g.pending(), 1);
        assert!(g.on_action(&key(3, 1), &batch(3, vec![intent(3, 3)], vec![])));
        let got = g.close();
        assert_eq!(got.answered_expected, 3);
        assert!(got.intents[0].is_some() && got.intents[1].is_none() && got.intents[3].is_some());
        assert_eq!(got.counters.hostile, 0);
    }

    #[test]
    fn late_messages_are_dropped_but_not_hostile_future_ones_are() {
        let mut g = Gather::new(RUN, 2);
        g.begin(5, |_| true);
        assert!(!g.on_action(&key(0, 1), &batch(4, vec![intent(0, 4)], vec![])));
        assert_eq!(g.counters.hostile, 0, "a straggler is not hostile");
        assert!(!g.on_action(&key(0, 1), &batch(6, vec![intent(0, 6)], vec![])));
        assert_eq!(g.counters.hostile, 1, "a future step is hostile");
        assert_eq!(g.pending(), 2);
    }

    /// What arrives after a step closed and before the next begins (a paced run waits
    /// there) counts in the next step, not nowhere.
    #[test]
    fn hostile_batches_between_steps_count_in_the_next() {
        let mut g = Gather::new(RUN, 2);
        g.begin(1, |_| true);
        assert_eq!(g.close().counters.hostile, 0);
        g.on_action(&key(0, 1), b"\x01garbage");
        g.on_action(&key(0, 1), &batch(7, vec![intent(0, 7)], vec![]));
        g.begin(2, |_| true);
        assert_eq!(g.close().counters.hostile, 2);
    }

    #[test]
    fn duplicates_keep_the_first_answer() {
        let mut g = Gather::new(RUN, 1);
        g.begin(1, |_| true);
        let first = intent(0, 1);
        let second = Intent { ops: vec![], ..intent(0, 1) };
        assert!(g.on_action(&key(0, 1), &batch(1, vec![first.clone()], vec![])));
        g.on_action(&key(0, 1), &batch(1, vec![second], vec![]));
        assert_eq!(g.close().intents[0], Some(first));
    }

    #[test]
    fn foreign_ids_undecodable_bytes_and_bad_keys_are_hostile() {
        let mut g = Gather::new(RUN, 4);
        g.begin(1, |_| true);
        // Process 0-1 speaks for agent 2 and marks agent 3 idle: both hostile.
        g.on_action(&key(0, 2), &batch(1, vec![intent(2, 1)], vec![3]));
        assert_eq!(g.counters.hostile, 2);
        // An intent of another step inside a batch of this one.
        g.on_action(&key(0, 2), &batch(1, vec![intent(0, 9)], vec![]));
        assert_eq!(g.counters.hostile, 3);
        g.on_action(&key(0, 2), b"\x01garbage");
        g.on_action("geese/t/agent/x/action", &batch(1, vec![], vec![]));
        g.on_action("geese/other/agent/0/action", &batch(1, vec![], vec![]));
        assert_eq!(g.counters.hostile, 6);
        // An id beyond the run, even from a range that claims it.
        g.on_action(&key(0, 9), &batch(1, vec![intent(7, 1)], vec![8]));
        assert_eq!(g.counters.hostile, 8);
        assert_eq!(g.pending(), 4);
    }

    #[test]
    fn nothing_is_taken_between_steps() {
        let mut g = Gather::new(RUN, 1);
        assert!(!g.on_action(&key(0, 1), &batch(0, vec![intent(0, 0)], vec![])));
        g.begin(1, |_| true);
        g.close();
        assert!(!g.on_action(&key(0, 1), &batch(1, vec![intent(0, 1)], vec![])));
    }

    #[test]
    fn a_forgotten_agent_is_no_longer_awaited() {
        let mut g = Gather::new(RUN, 3);
        g.begin(2, |_| true);
        g.on_action(&key(0, 1), &batch(2, vec![intent(0, 2)], vec![]));
        g.forget(1);
        g.forget(1); // twice: no underflow
        g.forget(99); // out of range: ignored
        assert_eq!(g.pending(), 1);
        assert!(g.on_action(&key(2, 1), &batch(2, vec![intent(2, 2)], vec![])));
    }

    #[test]
    fn process_counters_are_summed_without_overflow() {
        let mut g = Gather::new(RUN, 2);
        g.begin(1, |_| true);
        let c =
            HostCounters { percepts_lost: u32::MAX, percepts_missing: 1, genes_late: 2, hostile: 3, deadline_hits: 1 };
        let b =
            |id| encode(&IntentBatch { step: 1, intents: vec![], idle: vec![id], counters: c, ahead: None }).unwrap();
        g.on_action(&key(0, 1), &b(0));
        g.on_action(&key(1, 1), &b(1));
        let got = g.close();
        assert_eq!(got.counters.percepts_lost, u32::MAX);
        assert_eq!(got.counters.genes_late, 4);
        assert_eq!(got.counters.hostile, 6);
        assert_eq!(got.counters.deadline_hits, 2);
    }
}
