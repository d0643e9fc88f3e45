//! The in-memory transport: dense per-topic mailboxes for a world and its agents in one
//! process.
//!
//! Topics of the lock-step protocol are indexed by cell (percepts, genes) or by agent
//! (intents), so a mailbox is a `Vec` slot rather than a routed key; messages are moved,
//! not encoded. A step's mailboxes are cleared before the next step.

/// Mailboxes indexed by a dense topic number (a cell index or an agent id).
#[derive(Debug)]
pub struct Mailboxes<T> {
    boxes: Vec<Vec<T>>,
    used: Vec<u32>,
}

impl<T> Mailboxes<T> {
    pub fn new(topics: usize) -> Self {
        Mailboxes { boxes: (0..topics).map(|_| Vec::new()).collect(), used: Vec::new() }
    }

    /// Grow to at least `topics` topics (the grid can change size between trials).
    pub fn resize(&mut self, topics: usize) {
        self.clear();
        self.boxes.resize_with(topics, Vec::new);
    }

    pub fn publish(&mut self, topic: u32, msg: T) {
        let b = &mut self.boxes[topic as usize];
        if b.is_empty() {
            self.used.push(topic);
        }
        b.push(msg);
    }

    /// Everything published on `topic` since the last clear, in publication order.
    pub fn get(&self, topic: u32) -> &[T] {
        self.boxes.get(topic as usize).map(Vec::as_slice).unwrap_or(&[])
    }

    /// Empty every mailbox, keeping the allocations.
    pub fn clear(&mut self) {
        for &t in &self.used {
            self.boxes[t as usize].clear();
        }
        self.used.clear();
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn publish_get_clear() {
        let mut m = super::Mailboxes::new(4);
        m.publish(2, "a");
        m.publish(2, "b");
        m.publish(0, "c");
        assert_eq!(m.get(2), &["a", "b"]);
        assert_eq!(m.get(1), &[] as &[&str]);
        assert_eq!(m.get(9), &[] as &[&str]);
        m.clear();
        assert!(m.get(2).is_empty());
    }
}
