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

#[cfg(test)]
mod tests {
    #[test]
    fn keys_are_stable() {
        assert_eq!(super::cell_percept("r1", 3, 4), "geese/r1/cell/3/4/percept");
        assert_eq!(super::cell_genes("r1", 3, 4), "geese/r1/cell/3/4/genes");
        assert_eq!(super::agent_action("r1", 7), "geese/r1/agent/7/action");
        assert_eq!(super::report("r1"), "geese/r1/report");
    }
}
