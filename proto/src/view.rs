//! What the live viewer sees: one [`ViewFrame`] per shown step, built by the world
//! (in-process or the world server) and drawn by the page `geese view` serves.
//!
//! A frame is the whole picture, not a delta: a viewer that connects late or reloads
//! needs nothing but the latest one, and frames go out at a bounded rate (a few per
//! second), so their size (~20 bytes an agent) never matters next to the step's traffic.
use crate::{AgentId, BehaviourClass, ObjectKind};
use serde::{Deserialize, Serialize};

/// Most frames a world publishes per second while a viewer is present (the page
/// cannot show more; the bound keeps a viewer's cost fixed whatever the step rate).
pub const MAX_FRAMES_PER_SECOND: f64 = 10.0;

/// The fastest step-rate limit a viewer may ask for (steps per second); 0 means none.
pub const MAX_STEP_RATE: f64 = 10_000.0;

/// The slowest step-rate limit (steps per second): one step every 100 s.
pub const MIN_STEP_RATE: f64 = 0.01;

/// The world at the end of one step, for the viewer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct ViewFrame {
    /// The step just resolved (0 before the first).
    pub step: u64,
    /// Steps the run will make.
    pub steps: u64,
    pub task_pct: f64,
    pub lt_mean: f64,
    pub live_agents: u32,
    /// The arena: width, height and grid size (cell side).
    pub width: i32,
    pub height: i32,
    pub grid: i32,
    pub paused: bool,
    /// The step-rate limit in force (steps per second; 0 = none).
    pub step_rate: f64,
    /// Every agent, live or not.
    pub agents: Vec<AgentMark>,
    /// Every object lying in the arena (carried ones are drawn with their carrier).
    pub objects: Vec<ObjectMark>,
    /// Perturbations applied so far: (step, what), for markers on the chart.
    pub events: Vec<(u64, String)>,
}

/// One agent in a frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AgentMark {
    pub id: AgentId,
    pub x: i32,
    pub y: i32,
    pub heading: f32,
    pub live: bool,
    pub class: BehaviourClass,
    /// Kinds of the objects it carries.
    pub carrying: Vec<ObjectKind>,
}

/// One object in a frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectMark {
    pub kind: ObjectKind,
    pub x: i32,
    pub y: i32,
    pub radius: i32,
}

/// What the viewer shows of one agent when clicked: answered by whoever runs its
/// learner (the in-process trial, or the agent process hosting it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct AgentDetail {
    pub id: AgentId,
    pub phenotype: String,
    pub fitness: f64,
    pub class: BehaviourClass,
    /// The tree as the text listing of `geese grammar tree`.
    pub tree: String,
    /// For Multi-GEESE and fixed agents: the controllers their GeneDict holds
    /// (action class → phenotype).
    pub controllers: Vec<(String, String)>,
}
