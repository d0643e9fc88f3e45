//! Task layouts and placement rules (REFERENCE.md §1.4).
use crate::config::{ConfigError, Layout, Start, Task};
use crate::world::World;
use geese_proto::{ObjectId, ObjectKind, Pos};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Radius of hub, sites, food, debris and boundaries in every paper world.
pub const BIG_RADIUS: i32 = 10;
/// Attempts before a placement rule gives up (the reference retries forever).
const MAX_ATTEMPTS: u32 = 10_000;

/// Number of angles of the placement rules.
const ANGLES: u32 = 36;

/// One of the 36 angles of `linspace(0, 2π, 36)` (both 0 and 2π occur).
fn angle(rng: &mut ChaCha8Rng) -> f64 {
    angle_at(rng.random_range(0..ANGLES))
}

/// The `i`-th angle of `linspace(0, 2π, 36)`.
fn angle_at(i: u32) -> f64 {
    std::f64::consts::TAU * i as f64 / 35.0
}

/// (trunc(d cos θ), trunc(d sin θ)) around `centre`.
fn polar(centre: Pos, d: f64, theta: f64) -> Pos {
    Pos::new(centre.x + (d * theta.cos()).trunc() as i32, centre.y + (d * theta.sin()).trunc() as i32)
}

/// Site/boundary rule: distance `d` from the hub at one of the 36 angles, redrawn while
/// its neighbourhood already holds an object.
fn place_ring(w: &mut World, rng: &mut ChaCha8Rng, kind: ObjectKind, d: i32) -> Result<ObjectId, ConfigError> {
    let hub = w.hub().pos;
    for _ in 0..MAX_ATTEMPTS {
        let p = polar(hub, d as f64, angle(rng));
        if !w.area_has_objects(p, BIG_RADIUS) {
            return Ok(w.add_object(kind, p, BIG_RADIUS));
        }
    }
    Err(ConfigError::Invalid {
        field: if kind == ObjectKind::Sites { "sites" } else { "boundaries" },
        reason: format!("no free place for another {} at distance {d}", kind.name()),
    })
}

/// Obstacle rule: distance from {25, 30, …} below W/2, one of the 36 angles, redrawn
/// while a non-agent object is registered in its neighbourhood. `None` if no place.
///
/// Bounded: nothing changes between two draws, so a place refused once is refused
/// again. Each (distance, angle) is examined at most once, and the rule gives up when
/// all of them have been refused or after [`MAX_ATTEMPTS`] draws. A place whose block
/// of cells meets the hub's is refused without looking at the cells (the hub is always
/// registered). The draws are those of the plain rule, so a place found is the same.
pub fn place_obstacle(w: &mut World, rng: &mut ChaCha8Rng, radius: i32) -> Option<ObjectId> {
    let g = w.geometry();
    let half = g.half_w().min(g.half_h());
    let steps = ((half - 25) + 4) / 5; // arange(25, half, 5)
    if steps <= 0 {
        return None;
    }
    let hub = w.hub();
    let (hx1, hy1, hx2, hy2) = g.neighbourhood_box(hub.pos, hub.radius);
    let mut refused = vec![false; steps as usize * ANGLES as usize];
    let mut left = refused.len();
    for _ in 0..MAX_ATTEMPTS {
        let k = rng.random_range(0..steps);
        let i = rng.random_range(0..ANGLES);
        let slot = k as usize * ANGLES as usize + i as usize;
        if refused[slot] {
            continue;
        }
        let p = polar(Pos::new(0, 0), f64::from(25 + 5 * k), angle_at(i));
        let (x1, y1, x2, y2) = g.neighbourhood_box(p, radius);
        let meets_hub = x1 < hx2 && hx1 < x2 && y1 < hy2 && hy1 < y2;
        if !meets_hub && !w.area_has_objects(p, radius) {
            return Some(w.add_object(ObjectKind::Obstacles, p, radius));
        }
        refused[slot] = true;
        left -= 1;
        if left == 0 {
            return None;
        }
    }
    None
}

/// An obstacle of `radius` centred at `p` (the live viewer's click): placed when its
/// block of cells keeps clear of the hub's and no other non-agent object lies in its
/// neighbourhood, the test the obstacle rule applies to each place it draws.
pub fn place_obstacle_at(w: &mut World, p: Pos, radius: i32) -> Option<ObjectId> {
    let g = w.geometry();
    if !g.contains(p) {
        return None;
    }
    let hub = w.hub();
    let (hx1, hy1, hx2, hy2) = g.neighbourhood_box(hub.pos, hub.radius);
    let (x1, y1, x2, y2) = g.neighbourhood_box(p, radius);
    let meets_hub = x1 < hx2 && hx1 < x2 && y1 < hy2 && hy1 < y2;
    (!meets_hub && !w.area_has_objects(p, radius)).then(|| w.add_object(ObjectKind::Obstacles, p, radius))
}

/// Populate a fresh world.
pub(crate) fn build(w: &mut World, rng: &mut ChaCha8Rng) -> Result<(), ConfigError> {
    let cfg = w.config().clone();
    let hub = w.add_object(ObjectKind::Hub, Pos::new(0, 0), BIG_RADIUS);
    let hub_pos = w.objects().nth(hub as usize).map(|o| o.info.pos).unwrap_or_default();
    // Before everything the rules place, so that those rules avoid them.
    for (i, &p) in cfg.fixed_obstacles.iter().enumerate() {
        if w.area_has_objects(p, cfg.obstacle_radius) {
            return Err(ConfigError::Invalid {
                field: "fixed_obstacles",
                reason: format!("[{i}] ({}, {}) overlaps the hub or an earlier obstacle", p.x, p.y),
            });
        }
        w.add_object(ObjectKind::Obstacles, p, cfg.obstacle_radius);
    }
    if (cfg.task, cfg.layout) == (Task::Foraging, Layout::Reference) && w.area_blocked(cfg.site, BIG_RADIUS) {
        return Err(ConfigError::Invalid {
            field: "site",
            reason: format!("({}, {}) lies under a fixed obstacle", cfg.site.x, cfg.site.y),
        });
    }
    place_task(w, rng, cfg.task, hub_pos)?;
    for _ in 0..cfg.obstacles {
        if place_obstacle(w, rng, cfg.obstacle_radius).is_none() {
            return Err(ConfigError::Invalid {
                field: "obstacles",
                reason: "no free place for another obstacle".into(),
            });
        }
    }
    let g = w.geometry();
    for _ in 0..cfg.agents {
        let pos = match cfg.start() {
            Start::Hub => hub_pos,
            Start::Random => {
                Pos::new(rng.random_range(-g.half_w()..g.half_w()), rng.random_range(-g.half_h()..g.half_h()))
            }
        };
        let heading = rng.random::<f64>() * std::f64::consts::TAU;
        w.add_body(pos, heading);
    }
    Ok(())
}

/// Lay out the items and places of `task` (sites and food, or debris and boundaries),
/// as a fresh world has them: when the world is built, and when a `SwitchTask`
/// perturbation brings the task in (with the world's perturbation stream, so the
/// switched world is a function of the run seed).
pub(crate) fn place_task(w: &mut World, rng: &mut ChaCha8Rng, task: Task, hub_pos: Pos) -> Result<(), ConfigError> {
    let cfg = w.config().clone();
    let items = cfg.item_count();
    match (task, cfg.layout) {
        (Task::Foraging, Layout::Reference) => {
            w.add_object(ObjectKind::Sites, cfg.site, BIG_RADIUS);
            for _ in 0..items {
                w.add_object(ObjectKind::Food, cfg.site, BIG_RADIUS);
            }
        }
        (Task::Foraging, Layout::Paper) => {
            let mut sites = Vec::new();
            for _ in 0..cfg.sites {
                let id = place_ring(w, rng, ObjectKind::Sites, cfg.site_distance)?;
                sites.push(w.objects().nth(id as usize).map(|o| o.info.pos).unwrap_or_default());
            }
            for _ in 0..items {
                let s = sites[rng.random_range(0..sites.len())];
                w.add_object(ObjectKind::Food, s, BIG_RADIUS);
            }
        }
        (Task::Nest, _) => {
            for _ in 0..items {
                w.add_object(ObjectKind::Debris, hub_pos, BIG_RADIUS);
            }
            for _ in 0..cfg.boundaries {
                place_ring(w, rng, ObjectKind::Boundary, cfg.boundary_distance)?;
            }
        }
    }
    Ok(())
}
