//! Key expressions of every topic, defined once (DESIGN.md §2–3).

/// Root of every key of run `run`.
pub fn run_prefix(run: &str) -> String {
    format!("geese/{run}")
}

/// Percepts of cell (cx, cy) (column, row).
pub fn cell_percept(run: &str, cx: i32, cy: i32) -> String {
    format!("geese/{run}/cell/{cx}/{cy}/percept")
}

/// Genes exchanged in cell (cx, cy).
pub fn cell_genes(run: &str, cx: i32, cy: i32) -> String {
    format!("geese/{run}/cell/{cx}/{cy}/genes")
}

/// Intents of agent `id`.
pub fn agent_action(run: &str, id: u32) -> String {
    format!("geese/{run}/agent/{id}/action")
}

/// All intents (the world's subscription).
pub fn all_actions(run: &str) -> String {
    format!("geese/{run}/agent/*/action")
}

/// Step reports.
pub fn report(run: &str) -> String {
    format!("geese/{run}/report")
}

/// Control plane, `what` being e.g. `start`, `stop`, `schedule`.
pub fn ctl(run: &str, what: &str) -> String {
    format!("geese/{run}/ctl/{what}")
}

/// Liveliness token of a process.
pub fn presence(run: &str, who: &str) -> String {
    format!("geese/{run}/presence/{who}")
}

/// The contiguous range of agent ids one agent process speaks for (inclusive). In a key
/// it is one chunk: `7` for a single agent, `0-99` for a hosting process.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct AgentRange {
    pub first: u32,
    pub last: u32,
}

impl AgentRange {
    /// `count` agents from `first` on (`count` ≥ 1).
    pub fn new(first: u32, count: u32) -> Option<Self> {
        let last = first.checked_add(count.checked_sub(1)?)?;
        Some(AgentRange { first, last })
    }
    pub fn contains(&self, id: u32) -> bool {
        (self.first..=self.last).contains(&id)
    }
    pub fn len(&self) -> u32 {
        self.last - self.first + 1
    }
    pub fn is_empty(&self) -> bool {
        false
    }
    pub fn ids(&self) -> std::ops::RangeInclusive<u32> {
        self.first..=self.last
    }
    /// Does the range lie within the ids of a run of `agents` agents (`0..agents`)? A
    /// key naming a range outside it (a presence token for `0-4294967295`, say) is
    /// hostile or stale: reject it before iterating its ids.
    pub fn within(&self, agents: u32) -> bool {
        self.last < agents
    }
    /// Parse a key chunk (`7` or `0-99`); `None` for anything else.
    pub fn parse(chunk: &str) -> Option<Self> {
        let num = |s: &str| -> Option<u32> {
            if s.is_empty() || s.len() > 10 || !s.bytes().all(|b| b.is_ascii_digit()) {
                return None;
            }
            s.parse().ok()
        };
        match chunk.split_once('-') {
            None => num(chunk).map(|id| AgentRange { first: id, last: id }),
            Some((a, b)) => {
                let (first, last) = (num(a)?, num(b)?);
                (first < last).then_some(AgentRange { first, last })
            }
        }
    }
}

impl std::fmt::Display for AgentRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.first == self.last {
            write!(f, "{}", self.first)
        } else {
            write!(f, "{}-{}", self.first, self.last)
        }
    }
}

/// Count a liveliness token of the process speaking for `r` in or out of `tokens`
/// (by range, counted: a restarted process may briefly overlap the token of the one it
/// replaces); a range leaves the map when its last token goes.
pub fn tally(tokens: &mut std::collections::BTreeMap<AgentRange, u32>, r: AgentRange, alive: bool) {
    if alive {
        *tokens.entry(r).or_insert(0) += 1;
    } else if let Some(c) = tokens.get_mut(&r) {
        *c = c.saturating_sub(1);
        if *c == 0 {
            tokens.remove(&r);
        }
    }
}

/// A run name is one key chunk of letters, digits, `_`, `-` and `.`.
pub fn valid_run_name(run: &str) -> bool {
    !run.is_empty() && run.len() <= 64 && run.bytes().all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b))
}

/// Genes published in cell (cx, cy) by the agent process speaking for `from` (the
/// world gathers them and republishes the cell's genes as one batch on [`cell_genes`]).
pub fn cell_genes_from(run: &str, cx: i32, cy: i32, from: AgentRange) -> String {
    format!("geese/{run}/cell/{cx}/{cy}/genes/{from}")
}

/// Every agent process's gene batches in every cell (the world's subscription).
pub fn all_gene_batches(run: &str) -> String {
    format!("geese/{run}/cell/*/*/genes/*")
}

/// The percepts the world hands the hosting process speaking for `to`
/// ([`crate::net::HostPercepts`]).
pub fn host_percepts(run: &str, to: AgentRange) -> String {
    format!("geese/{run}/agent/{to}/in/percepts")
}

/// The genes the world hands the hosting process speaking for `to`
/// ([`crate::net::HostGenes`]).
pub fn host_genes(run: &str, to: AgentRange) -> String {
    format!("geese/{run}/agent/{to}/in/genes")
}

/// The gene batches of every shared cell of the agent process speaking for `from`, as
/// one [`crate::net::GeneBundle`] per step.
pub fn agents_genes(run: &str, from: AgentRange) -> String {
    format!("geese/{run}/agent/{from}/genes")
}

/// Every agent process's gene bundles (the world's subscription).
pub fn all_agents_genes(run: &str) -> String {
    format!("geese/{run}/agent/*/genes")
}

/// Intents of the agents of `from` (`agent/<id>/action` for one agent).
pub fn agents_action(run: &str, from: AgentRange) -> String {
    format!("geese/{run}/agent/{from}/action")
}

/// The world's per-step announcement of where every agent is ([`crate::net::Tick`]).
pub fn tick(run: &str) -> String {
    format!("geese/{run}/tick")
}

/// The world's run information queryable ([`crate::net::RunInfo`]).
pub fn info(run: &str) -> String {
    ctl(run, "info")
}

/// Every control key of a run.
pub fn all_ctl(run: &str) -> String {
    format!("geese/{run}/ctl/**")
}

/// Liveliness token of the world server.
pub fn world_presence(run: &str) -> String {
    presence(run, "world")
}

/// Liveliness token of the orchestrator.
pub fn orchestrator_presence(run: &str) -> String {
    presence(run, "orchestrator")
}

/// Liveliness token of an agent process speaking for `agents`.
pub fn agents_presence(run: &str, agents: AgentRange) -> String {
    format!("geese/{run}/presence/agents/{agents}")
}

/// Liveliness token of an agent process that reads cells one topic per cell (not the
/// world's bundles): while one is present the world publishes per-cell messages.
pub fn cells_presence(run: &str, agents: AgentRange) -> String {
    format!("geese/{run}/presence/cells/{agents}")
}

/// Liveliness token of a live viewer (`geese view`, `geese run --view`): while one is
/// present the world publishes [`view_frame`]s.
pub fn viewer_presence(run: &str, name: &str) -> String {
    format!("geese/{run}/presence/viewer/{name}")
}

/// The live viewer's frames ([`crate::view::ViewFrame`]).
pub fn view_frame(run: &str) -> String {
    format!("geese/{run}/view/frame")
}

/// Queried for agent `id`'s [`crate::view::AgentDetail`]; answered by the process that
/// hosts the agent, on [`agent_detail_reply`].
pub fn agent_detail(run: &str, id: u32) -> String {
    format!("geese/{run}/agent/*/detail/{id}")
}

/// The queryable of the agent process speaking for `agents`: the range is in the key,
/// so access control can let a process answer for its own agents only.
pub fn agents_detail(run: &str, agents: AgentRange) -> String {
    format!("geese/{run}/agent/{agents}/detail/*")
}

/// The key a reply about agent `id` comes back on from the process speaking for
/// `agents`.
pub fn agent_detail_reply(run: &str, agents: AgentRange, id: u32) -> String {
    format!("geese/{run}/agent/{agents}/detail/{id}")
}

/// Does a detail reply's key name a process range holding `id`? (A receiver checks it;
/// the access-control list makes sure the range is the replier's own.)
pub fn detail_reply_holds(run: &str, key: &str, id: u32) -> bool {
    let Some(rest) = key.strip_prefix(&format!("geese/{run}/agent/")) else { return false };
    let mut parts = rest.split('/');
    match (parts.next().and_then(AgentRange::parse), parts.next(), parts.next(), parts.next()) {
        (Some(r), Some("detail"), Some(i), None) => r.contains(id) && i == id.to_string(),
        _ => false,
    }
}

/// Every liveliness token of a run.
pub fn all_presence(run: &str) -> String {
    format!("geese/{run}/presence/**")
}

/// What a key of a run is, as far as a receiver cares.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Parsed {
    Percept {
        cx: i32,
        cy: i32,
    },
    /// Genes in a cell; `from` is `None` on the bare `genes` key (no sender named).
    Genes {
        cx: i32,
        cy: i32,
        from: Option<AgentRange>,
    },
    Action {
        from: AgentRange,
    },
    /// [`host_percepts`].
    HostPercepts {
        to: AgentRange,
    },
    /// [`host_genes`].
    HostGenes {
        to: AgentRange,
    },
    /// [`agents_genes`].
    GeneBundle {
        from: AgentRange,
    },
    WorldPresence,
    OrchestratorPresence,
    AgentsPresence {
        agents: AgentRange,
    },
    /// [`cells_presence`].
    CellsPresence {
        agents: AgentRange,
    },
    /// [`viewer_presence`].
    ViewerPresence,
    Other,
}

impl Parsed {
    /// The agent range a key names, if any.
    pub fn agents(&self) -> Option<AgentRange> {
        match *self {
            Parsed::Genes { from, .. } => from,
            Parsed::Action { from } | Parsed::GeneBundle { from } => Some(from),
            Parsed::HostPercepts { to } | Parsed::HostGenes { to } => Some(to),
            Parsed::AgentsPresence { agents } | Parsed::CellsPresence { agents } => Some(agents),
            Parsed::Percept { .. }
            | Parsed::WorldPresence
            | Parsed::OrchestratorPresence
            | Parsed::ViewerPresence
            | Parsed::Other => None,
        }
    }

    /// False if the key names an agent range not within a run of `agents` agents
    /// ([`AgentRange::within`]); true for keys that name none.
    pub fn within(&self, agents: u32) -> bool {
        self.agents().is_none_or(|r| r.within(agents))
    }
}

/// Parse a key expression of run `run`; anything unexpected is [`Parsed::Other`].
pub fn parse(run: &str, key: &str) -> Parsed {
    let Some(rest) = key.strip_prefix("geese/").and_then(|k| k.strip_prefix(run)).and_then(|k| k.strip_prefix('/'))
    else {
        return Parsed::Other;
    };
    let parts: Vec<&str> = rest.split('/').collect();
    let coord = |s: &str| -> Option<i32> {
        if s.is_empty() || s.len() > 6 || !s.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        s.parse().ok()
    };
    match parts.as_slice() {
        ["cell", cx, cy, "percept"] => match (coord(cx), coord(cy)) {
            (Some(cx), Some(cy)) => Parsed::Percept { cx, cy },
            _ => Parsed::Other,
        },
        ["cell", cx, cy, "genes"] => match (coord(cx), coord(cy)) {
            (Some(cx), Some(cy)) => Parsed::Genes { cx, cy, from: None },
            _ => Parsed::Other,
        },
        ["cell", cx, cy, "genes", from] => match (coord(cx), coord(cy), AgentRange::parse(from)) {
            (Some(cx), Some(cy), Some(from)) => Parsed::Genes { cx, cy, from: Some(from) },
            _ => Parsed::Other,
        },
        ["agent", from, "action"] => match AgentRange::parse(from) {
            Some(from) => Parsed::Action { from },
            None => Parsed::Other,
        },
        ["agent", from, "genes"] => match AgentRange::parse(from) {
            Some(from) => Parsed::GeneBundle { from },
            None => Parsed::Other,
        },
        ["agent", to, "in", "percepts"] => match AgentRange::parse(to) {
            Some(to) => Parsed::HostPercepts { to },
            None => Parsed::Other,
        },
        ["agent", to, "in", "genes"] => match AgentRange::parse(to) {
            Some(to) => Parsed::HostGenes { to },
            None => Parsed::Other,
        },
        ["presence", "world"] => Parsed::WorldPresence,
        ["presence", "orchestrator"] => Parsed::OrchestratorPresence,
        ["presence", "agents", a] => match AgentRange::parse(a) {
            Some(agents) => Parsed::AgentsPresence { agents },
            None => Parsed::Other,
        },
        ["presence", "cells", a] => match AgentRange::parse(a) {
            Some(agents) => Parsed::CellsPresence { agents },
            None => Parsed::Other,
        },
        ["presence", "viewer", _] => Parsed::ViewerPresence,
        _ => Parsed::Other,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn keys_are_stable() {
        assert_eq!(super::cell_percept("r1", 3, 4), "geese/r1/cell/3/4/percept");
        assert_eq!(super::cell_genes("r1", 3, 4), "geese/r1/cell/3/4/genes");
        assert_eq!(super::agent_action("r1", 7), "geese/r1/agent/7/action");
        assert_eq!(super::report("r1"), "geese/r1/report");
    }

    #[test]
    fn ranges_and_parsing() {
        use super::{parse, AgentRange, Parsed};
        let one = AgentRange::new(7, 1).unwrap();
        let many = AgentRange::new(0, 100).unwrap();
        assert_eq!(one.to_string(), "7");
        assert_eq!(many.to_string(), "0-99");
        assert_eq!(AgentRange::parse("0-99"), Some(many));
        assert_eq!(AgentRange::parse("7"), Some(one));
        for bad in ["", "-", "5-5", "9-3", "x", "1-2-3", "+1", "99999999999"] {
            assert_eq!(AgentRange::parse(bad), None, "{bad}");
        }
        assert_eq!(super::agents_action("r", one), super::agent_action("r", 7));
        assert_eq!(parse("r", &super::cell_percept("r", 3, 4)), Parsed::Percept { cx: 3, cy: 4 });
        assert_eq!(
            parse("r", &super::cell_genes_from("r", 3, 4, many)),
            Parsed::Genes { cx: 3, cy: 4, from: Some(many) }
        );
        assert_eq!(parse("r", &super::agents_action("r", many)), Parsed::Action { from: many });
        assert_eq!(parse("r", &super::agents_presence("r", one)), Parsed::AgentsPresence { agents: one });
        assert_eq!(parse("r", &super::world_presence("r")), Parsed::WorldPresence);
        assert_eq!(parse("r", &super::cells_presence("r", many)), Parsed::CellsPresence { agents: many });
        assert_eq!(parse("r", &super::host_percepts("r", many)), Parsed::HostPercepts { to: many });
        assert_eq!(parse("r", &super::host_genes("r", one)), Parsed::HostGenes { to: one });
        assert_eq!(parse("r", &super::agents_genes("r", many)), Parsed::GeneBundle { from: many });
        assert_eq!(parse("r", "geese/r/agent/1/in/other"), Parsed::Other);
        assert_eq!(parse("r", "geese/r/agent/x/genes"), Parsed::Other);
        assert_eq!(parse("r", "geese/other/agent/1/action"), Parsed::Other);
        assert_eq!(parse("r", "geese/r/agent/x/action"), Parsed::Other);
        assert_eq!(parse("r", "geese/r/cell/-1/2/percept"), Parsed::Other);
        let mut tokens = std::collections::BTreeMap::new();
        super::tally(&mut tokens, one, true);
        super::tally(&mut tokens, one, true);
        super::tally(&mut tokens, one, false);
        assert_eq!(tokens.get(&one), Some(&1));
        super::tally(&mut tokens, one, false);
        super::tally(&mut tokens, many, false);
        assert!(tokens.is_empty());
        assert!(super::valid_run_name("geese-1.a_b"));
    }

    #[test]
    fn ranges_outside_the_run_are_refused() {
        use super::{parse, AgentRange, Parsed};
        let r = |s: &str| AgentRange::parse(s).unwrap();
        // A run of 10 agents: ids 0..=9.
        assert!(r("0-9").within(10));
        assert!(r("9").within(10));
        assert!(!r("10").within(10));
        assert!(!r("5-10").within(10));
        assert!(!r("0-4294967295").within(10));
        assert!(!r("0").within(0));
        assert!(r("0-4294967294").within(u32::MAX));
        let hostile = parse("r", "geese/r/presence/agents/0-4294967295");
        assert_eq!(hostile.agents(), Some(r("0-4294967295")));
        assert!(!hostile.within(10));
        assert!(parse("r", &super::agents_presence("r", r("0-9"))).within(10));
        assert!(!parse("r", &super::cells_presence("r", r("3-12"))).within(10));
        assert!(!parse("r", &super::agents_action("r", r("10"))).within(10));
        assert!(!parse("r", &super::host_genes("r", r("8-11"))).within(10));
        assert!(!parse("r", &super::cell_genes_from("r", 1, 1, r("99"))).within(10));
        assert_eq!(parse("r", &super::world_presence("r")).agents(), None);
        assert!(parse("r", &super::world_presence("r")).within(0));
        assert!(Parsed::Other.within(0));
        assert!(!super::valid_run_name("a/b") && !super::valid_run_name("*") && !super::valid_run_name(""));
    }
}
