//! REFERENCE §2.3–2.5: each condition and action on small hand-made worlds, for its
//! SUCCESS and its FAILURE case (and §2.2's Find, which most of them use).
//!
//! The worlds (GS = 10, so every object occupies the one cell holding its centre, §1.2):
//! the hub at the origin (cell [0,10)²), a site at (−30,−30) (cell [−30,−20)²) holding
//! two food items, an obstacle centred in [20,30)×[0,10) for the avoidance cases, a
//! boundary at (−30,30).
use super::{bt_rng, object, World, HUB, ME};
use crate::leaves::LeafSpec;
use crate::view::View;
use geese_proto::geometry::round_half_even;
use geese_proto::{ObjectInfo, ObjectKind, Op, Pos};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

fn site() -> ObjectInfo {
    object(2, ObjectKind::Sites, -30, -30)
}
fn food(id: u32) -> ObjectInfo {
    object(id, ObjectKind::Food, -30, -30)
}
fn debris(id: u32) -> ObjectInfo {
    object(id, ObjectKind::Debris, 0, 0)
}
fn obstacle() -> ObjectInfo {
    object(20, ObjectKind::Obstacles, 25, 5)
}
fn boundary() -> ObjectInfo {
    object(3, ObjectKind::Boundary, -30, 30)
}

/// The agent inside the site's cell, which holds the site and two food items.
fn at_site() -> World {
    World::at(-25, -25).with(site()).with(food(10)).with(food(11))
}
/// The agent inside the hub's cell.
fn at_hub() -> World {
    World::at(3, 3).with(HUB)
}
/// The agent in an empty cell ([30,40)²).
fn nowhere() -> World {
    World::at(35, 35)
}

/// Tick the leaf the grammar spells `text` once with stream `rng`.
fn tick_with(text: &str, v: &mut View, rng: &mut ChaCha8Rng) -> bool {
    let spec = LeafSpec::parse(text).expect("a leaf text of the grammars");
    assert!(!spec.invert);
    spec.leaf.tick(v, rng)
}
fn tick(text: &str, v: &mut View) -> bool {
    tick_with(text, v, &mut bt_rng(ME))
}
fn ids(os: &[ObjectInfo]) -> Vec<u32> {
    os.iter().map(|o| o.id).collect()
}
/// Angle difference wrapped into (−π, π].
fn wrap(a: f64) -> f64 {
    let r = a.rem_euclid(TAU);
    if r > PI {
        r - TAU
    } else {
        r
    }
}
fn close(a: f64, b: f64) -> bool {
    wrap(a - b).abs() < 1e-9
}

// ---------------------------------------------------------------------------------------
// §2.3 Conditions
// ---------------------------------------------------------------------------------------

/// §2.3 NeighbourObjects(item): SUCCESS iff an object of that type is registered in the
/// agent's own cell; found food goes to the blackboard.
#[test]
fn neighbour_objects_senses_the_own_cell() {
    let mut v = at_site().view();
    assert!(tick("NeighbourObjects_Food", &mut v));
    assert_eq!(ids(v.blackboard.get(ObjectKind::Food)), [10, 11]);
    assert!(!tick("NeighbourObjects_Debris", &mut at_site().view()));
    assert!(!tick("NeighbourObjects_Food", &mut nowhere().view()));
    assert!(!tick("NeighbourObjects_Food", &mut at_hub().view()));
}

/// §2.3 NeighbourObjects: it first resets the blackboard, so a failed look leaves
/// nothing from earlier sensing (Find then falls back to memory, §2.2).
#[test]
fn neighbour_objects_resets_the_blackboard_first() {
    let mut v = nowhere().view();
    v.blackboard.push(food(10));
    assert!(tick("IsCarryable_Food", &mut v), "food on the blackboard");
    assert!(!tick("NeighbourObjects_Food", &mut v));
    assert!(v.blackboard.get(ObjectKind::Food).is_empty());
    assert!(!tick("IsCarryable_Food", &mut v), "nothing left to find");
    // A successful look replaces the blackboard's contents too.
    let mut v = at_site().view();
    v.blackboard.push(debris(12));
    assert!(tick("NeighbourObjects_Food", &mut v));
    assert!(v.blackboard.get(ObjectKind::Debris).is_empty());
}

/// §2.3 NeighbourObjects: Sites, Hub and Boundary go to the agent's static memory (never
/// the blackboard), and only objects of the asked type are looked at.
#[test]
fn neighbour_objects_memorises_sites_hubs_and_boundaries() {
    let mut v = at_site().view();
    assert!(tick("NeighbourObjects_Food", &mut v));
    assert!(v.memory.get(ObjectKind::Sites).is_empty(), "asked for food only");
    assert!(!tick("IsVisitedBefore_Sites", &mut v));
    assert!(tick("NeighbourObjects_Sites", &mut v));
    assert!(!v.blackboard.has(ObjectKind::Sites));
    assert_eq!(ids(v.memory.get(ObjectKind::Sites)), [2]);
    assert!(tick("IsVisitedBefore_Sites", &mut v));
    let mut v = World::at(-25, 25).with(boundary()).view();
    assert!(tick("NeighbourObjects_Boundary", &mut v));
    assert_eq!(ids(v.memory.get(ObjectKind::Boundary)), [3]);
    let mut v = at_hub().amnesic().view();
    assert!(tick("NeighbourObjects_Hub", &mut v));
    assert_eq!(ids(v.memory.get(ObjectKind::Hub)), [1]);
}

/// §2.3 NeighbourObjects with no item: senses every type, the agent itself excluded (so
/// other agents count); CODE quirk: a type not yet on the blackboard resets it, so
/// only the last-seen type survives.
#[test]
fn neighbour_objects_without_item() {
    assert!(!tick("NeighbourObjects", &mut nowhere().view()), "alone: only itself, which is removed");
    assert!(tick("NeighbourObjects", &mut nowhere().mates(1).view()), "another agent is an object");
    let mut v = nowhere().with(food(10)).with(debris(12)).with(food(11)).view();
    assert!(tick("NeighbourObjects", &mut v));
    assert_eq!(ids(v.blackboard.get(ObjectKind::Food)), [11]);
    assert!(v.blackboard.get(ObjectKind::Debris).is_empty());
    let mut v = at_site().view();
    assert!(tick("NeighbourObjects", &mut v));
    assert_eq!(ids(v.memory.get(ObjectKind::Sites)), [2], "memorised as with an item");
}

/// §2.3 IsCarrying(item): SUCCESS iff the agent carries an object of that type.
#[test]
fn is_carrying() {
    let w = nowhere().carrying(food(10));
    assert!(tick("IsCarrying_Food", &mut w.view()));
    assert!(!tick("IsCarrying_Debris", &mut w.view()));
    assert!(!tick("IsCarrying_Food", &mut nowhere().view()));
    assert!(tick("IsCarrying_Debris", &mut nowhere().carrying(debris(12)).view()));
}

/// §2.3 IsVisitedBefore(item): SUCCESS iff Find(item) is non-empty — the hub for an agent
/// that knows it, a site once sensed, anything on the blackboard.
#[test]
fn is_visited_before() {
    assert!(tick("IsVisitedBefore_Hub", &mut nowhere().view()));
    assert!(!tick("IsVisitedBefore_Hub", &mut nowhere().amnesic().view()));
    assert!(!tick("IsVisitedBefore_Sites", &mut nowhere().view()));
    assert!(tick("IsVisitedBefore_Sites", &mut nowhere().knowing(site()).view()));
    let mut v = nowhere().view();
    v.blackboard.push(food(10));
    assert!(tick("IsVisitedBefore_Food", &mut v));
}

/// §2.3 IsCarryable(item): the first of Find(item) exists and is carryable; it reads the
/// blackboard, it does not sense.
#[test]
fn is_carryable() {
    let mut v = at_site().view();
    assert!(!tick("IsCarryable_Food", &mut v), "food in the cell but not yet sensed");
    assert!(tick("NeighbourObjects_Food", &mut v));
    assert!(tick("IsCarryable_Food", &mut v));
    assert!(!tick("IsCarryable_Sites", &mut nowhere().knowing(site()).view()), "a known site is not carryable");
    assert!(!tick("IsCarryable_Hub", &mut nowhere().view()));
    let mut v = nowhere().view();
    v.blackboard.push(debris(12));
    assert!(tick("IsCarryable_Debris", &mut v));
}

/// §2.3 IsDropable (CODE): always SUCCESS — with the item known, unknown, or a type that
/// is no drop surface.
#[test]
fn is_dropable_always_succeeds() {
    for text in ["IsDropable_Hub", "IsDropable_Sites", "IsDropable_Boundary"] {
        assert!(tick(text, &mut nowhere().view()), "{text}");
        assert!(tick(text, &mut nowhere().amnesic().view()), "{text}, nothing known");
    }
    assert!(tick("IsDropable_Sites", &mut nowhere().knowing(site()).view()));
}

/// §2.3 CanMove (always SUCCESS in every paper experiment) and DummyNode (always
/// SUCCESS).
#[test]
fn can_move_and_dummy_node_always_succeed() {
    for w in [nowhere(), at_site(), at_hub().carrying(food(10)), World::at(31, 5).near(obstacle())] {
        assert!(tick("CanMove", &mut w.view()));
        assert!(tick("DummyNode", &mut w.view()));
    }
}

/// §2.3 DidAvoidedObj(item): α = direction from the object to the agent; FAILURE if
/// |θ − α| < π/2 with no angle wrapping, else SUCCESS; SUCCESS if nothing is found.
#[test]
fn did_avoided_obj() {
    // The hub at (0,0), the agent at (20,0): α = 0.
    let at = |h: f64| World::at(20, 0).heading(h).view();
    assert!(!tick("DidAvoidedObj_Hub", &mut at(0.0)), "heading along α");
    assert!(!tick("DidAvoidedObj_Hub", &mut at(1.5)));
    assert!(tick("DidAvoidedObj_Hub", &mut at(1.6)));
    assert!(tick("DidAvoidedObj_Hub", &mut at(PI)), "heading at the hub");
    // No wrapping: from (20,−1) α ≈ −0.05; θ = 6.25 is 0.017 rad from it on the circle,
    // but |6.25 − α| ≈ 6.3 ≥ π/2.
    assert!(tick("DidAvoidedObj_Hub", &mut World::at(20, -1).heading(6.25).view()));
    assert!(!tick("DidAvoidedObj_Hub", &mut World::at(20, -1).heading(0.0).view()));
    // Nothing to find.
    assert!(tick("DidAvoidedObj_Sites", &mut at(0.0)));
}

// ---------------------------------------------------------------------------------------
// §2.4–2.5 Actions (the composite "basic" behaviours and the primitives inside them)
// ---------------------------------------------------------------------------------------

/// §2.5 MoveTowards (both families): post-condition "already in a cell with the item" —
/// at the hub it succeeds without moving or turning.
#[test]
fn move_towards_at_the_item_does_nothing() {
    for text in ["MoveTowards_Hub_Normal", "MoveTowards_Hub_Avoid", "MoveTowards_Hub"] {
        let mut v = at_hub().heading(1.0).view();
        assert!(tick(text, &mut v), "{text}");
        assert!(v.ops.is_empty(), "{text}");
        assert_eq!((v.pos(), v.heading), (Pos::new(3, 3), 1.0), "{text}");
    }
}

/// §2.5 MoveTowards (both families) + §2.4 GoTo/Towards + §1.6 Move: aims at the known
/// item and steps 2 units (1 while carrying); FAILURE if the item is unknown.
#[test]
fn move_towards_steps_to_a_known_item() {
    for text in ["MoveTowards_Hub_Normal", "MoveTowards_Hub_Avoid"] {
        let mut v = World::at(30, 0).heading(1.0).view();
        assert!(tick(text, &mut v), "{text}");
        assert_eq!(v.ops, [Op::Move { to: Pos::new(28, 0), heading: PI }], "{text}");
        assert_eq!((v.pos(), v.heading), (Pos::new(28, 0), PI), "{text}");
        let mut v = World::at(30, 0).carrying(food(10)).view();
        assert!(tick(text, &mut v), "{text}, carrying");
        assert_eq!(v.pos(), Pos::new(29, 0), "{text}: one unit while carrying");
        // Sites never sensed: GoTo finds nothing.
        let mut v = World::at(30, 0).heading(1.0).view();
        assert!(!tick(&text.replace("Hub", "Sites"), &mut v), "{text} → Sites");
        assert!(v.ops.is_empty());
        assert_eq!((v.pos(), v.heading), (Pos::new(30, 0), 1.0));
    }
}

/// §2.4 GoTo: with several known items it picks one uniformly at random, re-drawn on
/// every tick.
#[test]
fn go_to_picks_a_known_item_uniformly_on_every_tick() {
    let (a, b) = (site(), object(4, ObjectKind::Sites, 30, 30));
    let mut rng = bt_rng(ME);
    let (mut to_a, mut to_b) = (0, 0);
    for _ in 0..400 {
        let mut v = at_hub().knowing(a).knowing(b).heading(0.0).view();
        assert!(tick_with("MoveTowards_Sites_Normal", &mut v, &mut rng));
        let Some(Op::Move { heading, .. }) = v.ops.first().copied() else { panic!("moved") };
        if close(heading, 5.0 * PI / 4.0) {
            to_a += 1;
        } else if close(heading, PI / 4.0) {
            to_b += 1;
        } else {
            panic!("heading {heading} aims at neither site");
        }
    }
    assert!((160..=240).contains(&to_a) && to_a + to_b == 400, "{to_a} vs {to_b}");
}

/// §2.5 MoveTowardsNormal does not avoid: a step into an obstacle's cell is refused by
/// Move (§1.6), so the behaviour FAILS and the agent stays.
#[test]
fn move_towards_normal_is_stopped_by_an_obstacle() {
    let mut v = World::at(31, 5).near(obstacle()).view();
    assert!(!tick("MoveTowards_Hub_Normal", &mut v));
    assert!(v.ops.is_empty());
    assert_eq!(v.pos(), Pos::new(31, 5));
}

/// §2.5 MoveTowards [Avoid] + §2.3 NeighbourObjectsDist + §2.4 AvoidSObjects: an
/// obstacle within 2 units ahead blocks the direct step; the agent turns along the
/// first edge of the obstacle's cell that its 3-unit look-ahead ray crosses (here the
/// right edge, x = 30: θ = π/2) and steps.
#[test]
fn move_towards_avoid_follows_the_obstacle_wall() {
    for text in ["MoveTowards_Hub_Avoid", "MoveTowards_Hub"] {
        let mut v = World::at(31, 5).near(obstacle()).view();
        assert!(tick(text, &mut v), "{text}");
        assert_eq!(v.ops, [Op::Move { to: Pos::new(31, 7), heading: FRAC_PI_2 }], "{text}");
        assert_eq!(v.heading, FRAC_PI_2);
    }
}

/// §2.3 NeighbourObjectsDist probes at distances 0, 1, 2 only: an obstacle 3 units
/// ahead is not seen, and the direct step (which stays out of its cell) is taken.
#[test]
fn obstacle_probe_reaches_two_units() {
    let mut v = World::at(32, 5).near(obstacle()).view();
    assert!(tick("MoveTowards_Hub_Avoid", &mut v));
    let aim = (-5f64).atan2(-32.0).rem_euclid(TAU);
    assert_eq!(v.ops, [Op::Move { to: Pos::new(30, 5), heading: aim }]);
}

/// §2.5 MoveAway (both families): the same post-condition as MoveTowards — in a cell with
/// the item it succeeds without moving (the CODE quirk) — otherwise it aims at the item,
/// turns by π (§2.4 Away) and steps; FAILURE if the item is unknown.
#[test]
fn move_away() {
    for text in ["MoveAway_Hub_Normal", "MoveAway_Hub_Avoid", "MoveAway_Hub"] {
        let mut v = at_hub().heading(1.0).view();
        assert!(tick(text, &mut v), "{text} at the hub");
        assert!(v.ops.is_empty(), "{text} at the hub does not move");
        let mut v = World::at(30, 0).heading(1.0).view();
        assert!(tick(text, &mut v), "{text}");
        assert_eq!(v.ops, [Op::Move { to: Pos::new(32, 0), heading: 0.0 }], "{text}");
        assert_eq!(v.heading, 0.0);
        let mut v = World::at(30, 0).heading(1.0).view();
        assert!(!tick(&text.replace("Hub", "Sites"), &mut v), "{text} → Sites");
        assert!(v.ops.is_empty());
    }
}

/// §2.5 ExploreNormal = Sequence[RandomWalk, CanMove, Move]: one random turn, then one
/// 2-unit step along the new heading.
#[test]
fn explore_normal_turns_a_little_and_steps() {
    let mut rng = bt_rng(ME);
    for _ in 0..50 {
        let mut v = nowhere().heading(0.0).view();
        assert!(tick_with("Explore_0_Normal", &mut v, &mut rng));
        let h = v.heading;
        assert!(wrap(h).abs() < 0.5, "a turn of {h} rad is not N(0, 0.1²)");
        let to = Pos::new(round_half_even(35.0 + 2.0 * h.cos()), round_half_even(35.0 + 2.0 * h.sin()));
        assert_eq!(v.ops, [Op::Move { to, heading: h }]);
        assert_eq!(v.pos(), to);
    }
}

/// §2.4 RandomWalk: θ := θ + N(0, 0.1²) — mean 0, standard deviation 0.1 rad.
#[test]
fn random_walk_noise_is_normal_with_deviation_one_tenth() {
    let mut rng = bt_rng(ME);
    let n = 4000;
    let turns: Vec<f64> = (0..n)
        .map(|_| {
            let mut v = nowhere().heading(1.0).view();
            assert!(tick_with("ExploreNormal", &mut v, &mut rng));
            wrap(v.heading - 1.0)
        })
        .collect();
    let mean = turns.iter().sum::<f64>() / n as f64;
    let sd = (turns.iter().map(|t| (t - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt();
    assert!(mean.abs() < 0.01, "mean turn {mean}");
    assert!((0.095..0.105).contains(&sd), "deviation {sd}");
}

/// §2.5 ExploreNormal does not avoid: blocked by an obstacle cell it FAILS in place;
/// Explore [Avoid] follows the obstacle's wall instead (θ = π/2 along the right edge).
#[test]
fn explore_normal_is_blocked_and_explore_avoid_goes_around() {
    let mut v = World::at(31, 5).heading(PI).near(obstacle()).view();
    assert!(!tick("Explore_0_Normal", &mut v));
    assert!(v.ops.is_empty());
    assert_eq!(v.pos(), Pos::new(31, 5));
    for text in ["Explore_0_Avoid", "Explore"] {
        let mut v = World::at(31, 5).heading(PI).near(obstacle()).view();
        assert!(tick(text, &mut v), "{text}");
        assert_eq!(v.ops, [Op::Move { to: Pos::new(31, 7), heading: FRAC_PI_2 }], "{text}");
    }
    // Nothing in the way: Explore [Avoid] is the plain random step.
    let mut v = nowhere().heading(PI).view();
    assert!(tick("Explore", &mut v));
    assert!(matches!(v.ops[..], [Op::Move { .. }]));
}

/// §2.5 CompositeSingleCarry(item) = Selector[IsCarrying(item), Sequence[NeighbourObjects,
/// IsCarryable, IsSingleCarry, SingleCarry]]: picks the first item in the cell; succeeds
/// at once when already carrying one; FAILS with nothing to pick.
#[test]
fn composite_single_carry() {
    let mut v = at_site().view();
    assert!(tick("CompositeSingleCarry_Food", &mut v));
    assert_eq!(v.ops, [Op::Pick { object: 10 }], "the first food registered in the cell");
    assert_eq!(ids(&v.carrying), [10]);
    // Post-condition: already carrying food → SUCCESS, nothing done.
    let mut v = at_site().carrying(object(9, ObjectKind::Food, -25, -25)).view();
    assert!(tick("CompositeSingleCarry_Food", &mut v));
    assert!(v.ops.is_empty());
    // Nothing to pick.
    for w in [nowhere(), at_hub()] {
        let mut v = w.view();
        assert!(!tick("CompositeSingleCarry_Food", &mut v));
        assert!(v.ops.is_empty() && v.carrying.is_empty());
    }
    assert!(!tick("CompositeSingleCarry_Debris", &mut at_site().view()));
    // Debris likewise.
    let mut v = at_hub().with(debris(12)).view();
    assert!(tick("CompositeSingleCarry_Debris", &mut v));
    assert_eq!(v.ops, [Op::Pick { object: 12 }]);
}

/// §2.4 IsSingleCarry: capacity 10 − 5 already carried is not more than the item's
/// weight 5, so an agent carrying one item cannot pick another.
#[test]
fn an_agent_carries_at_most_one_object() {
    let mut v = at_site().carrying(object(12, ObjectKind::Debris, -25, -25)).view();
    assert!(!tick("CompositeSingleCarry_Food", &mut v));
    assert!(v.ops.is_empty());
    assert_eq!(ids(&v.carrying), [12]);
}

/// §2.5 CompositeDrop(item) = Sequence[FailureIsSuccess(NeighbourObjects(none)),
/// IsCarrying(item), IsDropable, Drop(item)]: it FAILS when not carrying the item, even
/// at the hub.
#[test]
fn composite_drop_fails_when_not_carrying_the_item() {
    for w in [at_hub(), nowhere(), at_hub().carrying(debris(12))] {
        let mut v = w.view();
        assert!(!tick("CompositeDrop_Food", &mut v));
        assert!(v.ops.is_empty());
    }
}

/// §2.4 Drop (final version) of food: into the hub's dropped list in the hub cell (not
/// re-registered); re-registered at the agent's position in a cell with no hub,
/// boundary or obstacle. The sensing step's FAILURE (empty cell) is turned into SUCCESS.
#[test]
fn composite_drop_of_food_succeeds_at_the_hub_and_in_open_cells() {
    let mut v = at_hub().carrying(object(10, ObjectKind::Food, 3, 3)).view();
    assert!(tick("CompositeDrop_Food", &mut v));
    assert_eq!(v.ops, [Op::Drop { object: 10 }]);
    assert!(v.carrying.is_empty());
    assert!(!v.cell_objects.iter().any(|o| o.id == 10), "delivered, not back in the grid");
    let mut v = nowhere().carrying(object(10, ObjectKind::Food, 35, 35)).view();
    assert!(tick("CompositeDrop_Food", &mut v), "FailureIsSuccess around the empty cell's sensing");
    assert_eq!(v.ops, [Op::Drop { object: 10 }]);
    assert!(v.cell_objects.iter().any(|o| o.id == 10 && o.pos == Pos::new(35, 35)), "re-registered where it fell");
    assert!(tick("NeighbourObjects_Food", &mut v), "and can be sensed again");
}

/// §2.4 Drop (final version) of food FAILS in a boundary cell, an obstacle cell, or a
/// hub cell that also holds debris.
#[test]
fn composite_drop_of_food_fails_at_boundaries_obstacles_and_littered_hubs() {
    let carrying = |w: World| w.carrying(food(10));
    let worlds = [
        carrying(World::at(-25, 25).with(boundary())),
        carrying(World::at(25, 5).with(obstacle())),
        carrying(at_hub().with(debris(12))),
    ];
    for w in worlds {
        let mut v = w.view();
        assert!(!tick("CompositeDrop_Food", &mut v), "{:?}", w.objects);
        assert!(v.ops.is_empty());
        assert_eq!(ids(&v.carrying), [10]);
    }
}

/// §2.4 Drop (final version) of debris: FAILS in a hub or obstacle cell; into the
/// boundary's dropped list in a boundary cell; re-registered elsewhere.
#[test]
fn composite_drop_of_debris() {
    for w in [at_hub(), World::at(25, 5).with(obstacle())] {
        let mut v = w.carrying(debris(12)).view();
        assert!(!tick("CompositeDrop_Debris", &mut v));
        assert!(v.ops.is_empty());
    }
    let mut v = World::at(-25, 25).with(boundary()).carrying(debris(12)).view();
    assert!(tick("CompositeDrop_Debris", &mut v));
    assert_eq!(v.ops, [Op::Drop { object: 12 }]);
    assert!(!v.cell_objects.iter().any(|o| o.id == 12), "into the boundary's list");
    let mut v = nowhere().carrying(debris(12)).view();
    assert!(tick("CompositeDrop_Debris", &mut v));
    assert!(v.cell_objects.iter().any(|o| o.id == 12));
}

/// §2.5 CompositeDrop: its sensing step (NeighbourObjects with no item) memorises the
/// site, so a drop attempt at the site cell teaches the agent the site — whether or not
/// the drop itself succeeds.
#[test]
fn composite_drop_at_the_site_teaches_the_site() {
    let mut v = at_site().view();
    assert!(!tick("CompositeDrop_Food", &mut v));
    assert_eq!(ids(v.memory.get(ObjectKind::Sites)), [2]);
    let mut v = at_site().carrying(object(9, ObjectKind::Food, -25, -25)).view();
    assert!(tick("CompositeDrop_Food", &mut v));
    assert_eq!(ids(v.memory.get(ObjectKind::Sites)), [2]);
}

/// §2.4 AvoidSObjects: the ray (agent → (⌈x + 3cosθ⌉, ⌈y + 3sinθ⌉)) is tested against the
/// obstacle cell's edges in the order bottom, right, top, left, touching counts, and the
/// first that meets it sets θ to its direction: 0, π/2, π, −π/2. At (30,1) the ray meets
/// both the right edge (it starts on it) and the bottom edge (it ends on it): bottom
/// wins.
#[test]
fn avoid_takes_the_first_edge_met_in_the_order_bottom_right_top_left() {
    let sites = |x, y| object(4, ObjectKind::Sites, x, y);
    let cases = [
        ("MoveTowards_Sites", World::at(30, 1).knowing(site()), Pos::new(32, 1), 0.0),
        ("MoveTowards_Hub", World::at(31, 5), Pos::new(31, 7), FRAC_PI_2),
        ("MoveTowards_Hub", World::at(25, 10), Pos::new(23, 10), PI),
        ("MoveTowards_Sites", World::at(19, 5).knowing(sites(45, 5)), Pos::new(19, 3), -FRAC_PI_2),
    ];
    for (text, w, to, h) in cases {
        let from = w.pos;
        let mut v = w.near(obstacle()).view();
        assert!(tick(text, &mut v), "{text} from {from:?}");
        assert_eq!(v.ops, [Op::Move { to, heading: h }], "{text} from {from:?}");
        assert!(close(v.heading, h));
    }
}

/// §2.4 AvoidSObjects always succeeds and leaves θ unchanged when the ray meets no edge —
/// here the agent stands inside the obstacle's cell (obstacles may be placed over
/// agents, §1.4), the ray stays inside it, and the move within the cell is allowed (§1.6).
#[test]
fn avoid_keeps_the_heading_when_the_ray_meets_no_edge() {
    let mut v = World::at(25, 5).with(obstacle()).view();
    assert!(tick("MoveTowards_Hub_Avoid", &mut v));
    let aim = (-5f64).atan2(-25.0).rem_euclid(TAU);
    assert_eq!(v.ops, [Op::Move { to: Pos::new(23, 5), heading: aim }]);
}

/// REFERENCE §1.8 + §2.3: the reference world is sequential and NeighbourObjects senses
/// the cell the agent is in *now*, after its own moves earlier in the same tick, so
/// Sequence[MoveTowards_Sites, CompositeSingleCarry_Food] from (−19,−25) moves to
/// (−21,−26), inside the site's cell, and picks its food in one tick. An agent sees the
/// world through its start-of-step percept (DESIGN §2); a percept of reach 1 carries the
/// objects of the cells around its own, and with it the pick happens as in the
/// reference. Runs whose trees hold several actions (GEESE-BT, Multi-GEESE combine,
/// fixed populations) get reach 1; with reach 0 (BeTr-GEESE: one action a tick, after
/// which nothing senses) the food in the new cell is not seen.
#[test]
fn sensing_after_a_move_in_the_same_tick_sees_the_cell_moved_into() {
    use crate::bt::{Bt, Status};
    use crate::ge::{CompositeKind, PNode};
    let act = |t: &str| PNode::Leaf { text: t.into(), tag: "Act".into() };
    let p = PNode::Composite {
        kind: CompositeKind::Sequence,
        children: vec![act("MoveTowards_Sites_Normal"), act("CompositeSingleCarry_Food")],
    };
    let mut bt = Bt::from_pnode(&p).expect("tree");
    // The site's cell holds the site and food 10; the agent's own cell is empty.
    let mut v = World::at(-19, -25).knowing(site()).around(site()).around(food(10)).view();
    assert_eq!(bt.tick(&mut v, &mut bt_rng(ME)), Status::Success);
    assert_eq!(v.pos(), Pos::new(-21, -26), "the move into the site's cell happens");
    assert_eq!(v.ops.last(), Some(&Op::Pick { object: 10 }), "and the food there is picked");
    // Reach 0: only the start cell is known.
    let mut bt = Bt::from_pnode(&p).expect("tree");
    let mut v = World::at(-19, -25).knowing(site()).view();
    assert_eq!(bt.tick(&mut v, &mut bt_rng(ME)), Status::Failure);
    assert_eq!(v.pos(), Pos::new(-21, -26));
    assert!(!v.ops.contains(&Op::Pick { object: 10 }), "the food there is not seen");
}

/// With reach 1, a drop after a move lands where the agent ends up: food carried into
/// the hub's cell within the tick is delivered there (REFERENCE §2.4 Drop), and an
/// object picked from a neighbouring cell is gone from the view's area.
#[test]
fn drops_and_picks_after_a_move_use_the_cell_moved_into() {
    use crate::bt::{Bt, Status};
    use crate::ge::{CompositeKind, PNode};
    let act = |t: &str| PNode::Leaf { text: t.into(), tag: "Act".into() };
    let p = PNode::Composite {
        kind: CompositeKind::Sequence,
        children: vec![act("MoveTowards_Hub_Normal"), act("CompositeDrop_Food")],
    };
    let mut bt = Bt::from_pnode(&p).expect("tree");
    // From (10, 5), carrying (step length 1), heading to the hub: the move ends at
    // (9, 5), in the hub's cell.
    let mut v = World::at(10, 5).carrying(food(10)).around(HUB).view();
    assert_eq!(bt.tick(&mut v, &mut bt_rng(ME)), Status::Success);
    assert_eq!(v.pos(), Pos::new(9, 5));
    assert_eq!(v.pos(), Pos::new(9, 5));
    assert_eq!(v.ops.last(), Some(&Op::Drop { object: 10 }));
    assert_eq!(v.delivered, 5, "into the hub: the task reward F counts it");
    assert!(v.area.iter().all(|o| o.id != 10), "delivered, not lying in the area");
}
