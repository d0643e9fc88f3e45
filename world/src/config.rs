//! World configuration. Every field defaults to the setting of the reference runs
//! (REFERENCE.md §1.4, §5.1); `validate` turns bad values into errors naming the field.
use geese_proto::limits::{max_radius, MAX_AGENTS, MAX_ITEMS};
use geese_proto::{Geometry, Pos};
use serde::{Deserialize, Serialize};

/// Which task the world is laid out for (defined with the wire types: a
/// `SwitchTask` perturbation names one).
pub use geese_proto::Task;

/// Which world layout (REFERENCE §1.4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// The reference code's evolution worlds: fixed site at `site` (foraging), five
    /// boundaries at distance 31 (nest), agents at random positions.
    #[default]
    Reference,
    /// The paper's description: site(s) placed by the site rule at distance 30 from the
    /// hub, agents start at the hub.
    Paper,
}

/// Where agents start.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Start {
    Random,
    Hub,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorldConfig {
    pub task: Task,
    pub layout: Layout,
    pub width: i32,
    pub height: i32,
    /// Grid-cell size GS.
    pub grid: i32,
    /// Number of agents N.
    pub agents: u32,
    /// Food or debris units; `None` = one per agent, as the reference code does.
    pub items: Option<u32>,
    /// Reference-layout site position (foraging).
    pub site: Pos,
    /// Paper-layout number of sites; food is split among them at random.
    pub sites: u32,
    /// Distance of sites from the hub in the paper layout.
    pub site_distance: i32,
    /// Nest: number of boundary drop zones and their distance from the hub.
    pub boundaries: u32,
    pub boundary_distance: i32,
    /// Obstacles placed by the obstacle rule when the world is built.
    pub obstacles: u32,
    /// Obstacles at these positions, placed right after the hub (before the sites,
    /// items and rule-placed obstacles): the locality world of Fig. 5 has four
    /// (REFERENCE §1.4). Radius `obstacle_radius`.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub fixed_obstacles: Vec<Pos>,
    pub obstacle_radius: i32,
    /// Start positions; `None` = the layout's default (random / hub).
    pub start: Option<Start>,
    /// Cells around an agent's cell whose objects its percept carries, so that an agent
    /// whose tree moves and then senses, picks up or drops within one tick sees the
    /// cell it moved into (REFERENCE §1.8: the reference code's agents act on the live
    /// world). `None`: decided by the run (0 when every tree acts once a tick, 1
    /// otherwise); at most 3.
    pub percept_reach: Option<u32>,
}

impl Default for WorldConfig {
    fn default() -> Self {
        WorldConfig {
            task: Task::Foraging,
            layout: Layout::Reference,
            width: 100,
            height: 100,
            grid: 10,
            agents: 100,
            items: None,
            site: Pos::new(30, 30),
            sites: 1,
            site_distance: 30,
            boundaries: 5,
            boundary_distance: 31,
            obstacles: 0,
            fixed_obstacles: Vec::new(),
            obstacle_radius: 10,
            start: None,
            percept_reach: None,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConfigError {
    #[error("world.{field}: {reason}")]
    Invalid { field: &'static str, reason: String },
}

fn bad(field: &'static str, reason: impl Into<String>) -> ConfigError {
    ConfigError::Invalid { field, reason: reason.into() }
}

impl WorldConfig {
    /// Check every field; the error names the first bad one. Sizes have upper limits
    /// ([`geese_proto::limits`]): width and height at most 10,000, at most 1,000,000
    /// cells, agents and items at most 1,000,000 each, obstacle radius at most the
    /// larger side of the arena.
    pub fn validate(&self) -> Result<Geometry, ConfigError> {
        let geom = Geometry::new(self.width, self.height, self.grid).map_err(|e| bad(e.field(), e.to_string()))?;
        if self.agents == 0 {
            return Err(bad("agents", "need at least one agent"));
        }
        if self.agents > MAX_AGENTS {
            return Err(bad("agents", format!("{} exceeds {MAX_AGENTS}", self.agents)));
        }
        if let Some(0) = self.items {
            return Err(bad("items", "need at least one item"));
        }
        if self.item_count() > MAX_ITEMS {
            return Err(bad("items", format!("{} exceeds {MAX_ITEMS}", self.item_count())));
        }
        if !geom.contains(self.site) {
            return Err(bad("site", format!("{:?} lies outside the arena", self.site)));
        }
        if self.sites == 0 || self.sites > 36 {
            return Err(bad("sites", "must be between 1 and 36"));
        }
        if self.site_distance <= 0 || self.site_distance >= geom.half_w().min(geom.half_h()) {
            return Err(bad("site_distance", "must be positive and inside the arena"));
        }
        if self.boundaries == 0 || self.boundaries > 36 {
            return Err(bad("boundaries", "must be between 1 and 36"));
        }
        if self.boundary_distance <= 0 || self.boundary_distance >= geom.half_w().min(geom.half_h()) {
            return Err(bad("boundary_distance", "must be positive and inside the arena"));
        }
        if self.obstacle_radius <= 0 {
            return Err(bad("obstacle_radius", "must be positive"));
        }
        if self.obstacle_radius > max_radius(&geom) {
            return Err(bad(
                "obstacle_radius",
                format!("{} exceeds {} (the larger side of the arena)", self.obstacle_radius, max_radius(&geom)),
            ));
        }
        if self.obstacles > 100 {
            return Err(bad("obstacles", format!("{} exceeds 100 initial obstacles", self.obstacles)));
        }
        if self.fixed_obstacles.len() > 100 {
            return Err(bad(
                "fixed_obstacles",
                format!("{} exceeds 100 initial obstacles", self.fixed_obstacles.len()),
            ));
        }
        if let Some((i, p)) = self.fixed_obstacles.iter().enumerate().find(|(_, p)| !geom.contains(**p)) {
            return Err(bad("fixed_obstacles", format!("[{i}] ({}, {}) lies outside the arena", p.x, p.y)));
        }
        if self.percept_reach.is_some_and(|r| r > 3) {
            return Err(bad("percept_reach", format!("{} exceeds 3 cells", self.percept_reach.unwrap_or(0))));
        }
        if geom.half_w().min(geom.half_h()) <= 25 && self.obstacles > 0 {
            return Err(bad("obstacles", "the obstacle rule needs an arena wider than 50"));
        }
        Ok(geom)
    }

    pub fn item_count(&self) -> u32 {
        self.items.unwrap_or(self.agents)
    }

    pub fn start(&self) -> Start {
        self.start.unwrap_or(match self.layout {
            Layout::Reference => Start::Random,
            Layout::Paper => Start::Hub,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geese_proto::limits::{MAX_ARENA_SIDE, MAX_CELLS};

    fn field_of(cfg: WorldConfig) -> (&'static str, String) {
        let e = cfg.validate().unwrap_err();
        let msg = e.to_string();
        let ConfigError::Invalid { field, .. } = e;
        (field, msg)
    }

    #[test]
    fn sizes_are_accepted_at_the_limit() {
        let big = WorldConfig { width: MAX_ARENA_SIDE, height: MAX_ARENA_SIDE, grid: 10, ..Default::default() };
        assert_eq!(big.validate().unwrap().cell_count() as u64, MAX_CELLS);
        let many = WorldConfig { agents: MAX_AGENTS, items: Some(MAX_ITEMS), ..Default::default() };
        assert!(many.validate().is_ok());
        assert!(WorldConfig { agents: MAX_AGENTS, items: None, ..Default::default() }.validate().is_ok());
        assert!(WorldConfig { obstacle_radius: 100, ..Default::default() }.validate().is_ok());
    }

    #[test]
    fn sizes_above_the_limit_name_the_key() {
        let cases = [
            (WorldConfig { width: MAX_ARENA_SIDE + 2, ..Default::default() }, "width", "10002"),
            (WorldConfig { height: i32::MAX - 1, ..Default::default() }, "height", "2147483646"),
            (WorldConfig { height: 101, ..Default::default() }, "height", "100x101"),
            (
                WorldConfig { width: MAX_ARENA_SIDE, height: MAX_ARENA_SIDE, grid: 5, ..Default::default() },
                "grid",
                "4000000",
            ),
            (WorldConfig { grid: 7, ..Default::default() }, "grid", "7"),
            (WorldConfig { agents: MAX_AGENTS + 1, ..Default::default() }, "agents", "1000001"),
            (WorldConfig { items: Some(MAX_ITEMS + 1), ..Default::default() }, "items", "1000001"),
            (WorldConfig { agents: u32::MAX, items: Some(5), ..Default::default() }, "agents", "4294967295"),
            (WorldConfig { obstacle_radius: 101, ..Default::default() }, "obstacle_radius", "101"),
            (WorldConfig { obstacle_radius: i32::MAX, ..Default::default() }, "obstacle_radius", "2147483647"),
            (WorldConfig { obstacles: 101, ..Default::default() }, "obstacles", "101"),
            (
                WorldConfig { fixed_obstacles: vec![Pos::new(0, 51)], ..Default::default() },
                "fixed_obstacles",
                "(0, 51)",
            ),
        ];
        for (cfg, key, value) in cases {
            let (field, msg) = field_of(cfg);
            assert_eq!(field, key, "{msg}");
            assert!(msg.starts_with(&format!("world.{key}: ")), "{msg}");
            assert!(msg.contains(value), "{msg} should name {value}");
        }
    }
}
