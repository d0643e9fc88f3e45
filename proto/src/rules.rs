//! Rules the world and the agents must agree on, written once (issue 17).
//!
//! The world applies them to decide what an intent may do; an agent applies them to
//! predict, within its tick, what the world will do. Were they written twice, a change
//! on one side only would make agents act on a world that is not there.
//!
//! - the agent's body (REFERENCE §1.5): radius, weight, force, carrying capacity;
//! - the step length ([`speed`]) and the `Move` destination ([`destination`], §1.6);
//! - the weight and capacity of an item ([`item_load`], §1.3);
//! - IsSingleCarry ([`is_single_carry`], §2.4);
//! - the final, type-aware drop rules ([`drop_rule`], §2.4).
use crate::geometry::{step_destination, Geometry, Pos};
use crate::message::{ObjectInfo, ObjectKind};

/// Radius of an agent's body (grid registration and look-ahead rays).
pub const AGENT_RADIUS: i32 = 3;
/// An agent's own weight.
pub const AGENT_WEIGHT: i32 = 5;
/// An agent's force.
pub const AGENT_FORCE: i32 = 10;
/// An agent's carrying capacity.
pub const AGENT_CAPACITY: i32 = 10;

/// Step length of an agent whose carried objects weigh `carried_weight`:
/// force / (own weight + carried weight).
pub fn speed(carried_weight: i32) -> f64 {
    AGENT_FORCE as f64 / (AGENT_WEIGHT + carried_weight) as f64
}

/// Total weight of the objects an agent carries.
pub fn carried_weight<'a>(carrying: impl IntoIterator<Item = &'a ObjectInfo>) -> i32 {
    carrying.into_iter().map(|o| o.weight).sum()
}

/// Where a `Move` from `from` along `heading` ends for an agent carrying
/// `carried_weight` (step length [`speed`], then the border rule), and the heading after
/// it.
pub fn destination(geom: &Geometry, from: Pos, heading: f64, carried_weight: i32) -> (Pos, f64) {
    step_destination(geom, from, heading, speed(carried_weight))
}

/// Weight and carrying capacity of an object of `kind` and `radius`: food weighs and
/// takes up ⌊radius/2⌋, debris weighs 5 and takes up ⌊radius/2⌋, other objects nothing.
pub fn item_load(kind: ObjectKind, radius: i32) -> (i32, i32) {
    match kind {
        ObjectKind::Food => (radius / 2, radius / 2),
        ObjectKind::Debris => (5, radius / 2),
        _ => (0, 0),
    }
}

/// IsSingleCarry: an agent carrying `carrying` may pick up `item` only if the item has a
/// weight and the agent's free capacity (capacity − Σ capacities carried) exceeds it.
/// With capacity 10 and 5-unit items an agent carries at most one.
pub fn is_single_carry<'a>(carrying: impl IntoIterator<Item = &'a ObjectInfo>, item: &ObjectInfo) -> bool {
    let used: i32 = carrying.into_iter().map(|c| c.capacity).sum();
    item.weight > 0 && AGENT_CAPACITY - used > item.weight
}

/// What dropping a carried object does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DropOutcome {
    /// The drop is refused; the agent keeps the object.
    Refused,
    /// The object goes into the first object of this kind in the cell (a hub or a
    /// boundary takes it: it leaves the grid).
    Into(ObjectKind),
    /// The object is put down where the agent stands (registered in the grid again).
    Floor,
}

/// The final drop rules (REFERENCE §2.4) for a carried object of kind `item` in a cell
/// where `has(k)` says whether a non-agent object of kind `k` is registered.
/// Food: refused on a boundary or an obstacle, or where hub and debris meet; into the
/// hub; else on the floor. Anything else: refused on a hub or an obstacle; into a
/// boundary; else on the floor.
pub fn drop_rule(item: ObjectKind, has: impl Fn(ObjectKind) -> bool) -> DropOutcome {
    let target = if item == ObjectKind::Food {
        if has(ObjectKind::Boundary) || has(ObjectKind::Obstacles) {
            return DropOutcome::Refused;
        }
        if has(ObjectKind::Hub) && has(ObjectKind::Debris) {
            return DropOutcome::Refused;
        }
        ObjectKind::Hub
    } else {
        if has(ObjectKind::Hub) || has(ObjectKind::Obstacles) {
            return DropOutcome::Refused;
        }
        ObjectKind::Boundary
    };
    if has(target) {
        DropOutcome::Into(target)
    } else {
        DropOutcome::Floor
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ObjectKind::*;

    fn item(kind: ObjectKind) -> ObjectInfo {
        let (weight, capacity) = item_load(kind, 10);
        ObjectInfo { id: 0, kind, pos: Pos::default(), radius: 10, weight, capacity }
    }

    #[test]
    fn speeds_are_force_over_weight() {
        assert_eq!(speed(0), 2.0);
        assert_eq!(speed(5), 1.0);
        assert_eq!(carried_weight(&[item(Food)]), 5);
        let g = Geometry::new(100, 100, 10).unwrap();
        assert_eq!(destination(&g, Pos::new(0, 0), 0.0, 0).0, Pos::new(2, 0));
        assert_eq!(destination(&g, Pos::new(0, 0), 0.0, 5).0, Pos::new(1, 0));
    }

    #[test]
    fn loads_of_the_reference_world() {
        assert_eq!(item_load(Food, 10), (5, 5));
        assert_eq!(item_load(Debris, 10), (5, 5));
        assert_eq!(item_load(Food, 7), (3, 3));
        assert_eq!(item_load(Hub, 10), (0, 0));
        assert_eq!(item_load(Obstacles, 10), (0, 0));
    }

    #[test]
    fn one_item_at_a_time() {
        let food = item(Food);
        assert!(is_single_carry(&[], &food));
        assert!(!is_single_carry(&[food], &food), "5 > 5 is false");
        assert!(!is_single_carry(&[], &item(Hub)), "no weight");
        let light = ObjectInfo { weight: 1, capacity: 1, ..food };
        assert!(is_single_carry(&[light], &light));
        let heavy = ObjectInfo { weight: AGENT_CAPACITY, ..food };
        assert!(!is_single_carry(&[], &heavy));
    }

    #[test]
    fn drop_rules_by_type() {
        let with = |kinds: &'static [ObjectKind]| move |k: ObjectKind| kinds.contains(&k);
        assert_eq!(drop_rule(Food, with(&[Hub])), DropOutcome::Into(Hub));
        assert_eq!(drop_rule(Food, with(&[])), DropOutcome::Floor);
        assert_eq!(drop_rule(Food, with(&[Sites, Food])), DropOutcome::Floor);
        assert_eq!(drop_rule(Food, with(&[Hub, Debris])), DropOutcome::Refused);
        assert_eq!(drop_rule(Food, with(&[Boundary])), DropOutcome::Refused);
        assert_eq!(drop_rule(Food, with(&[Hub, Obstacles])), DropOutcome::Refused);
        assert_eq!(drop_rule(Debris, with(&[Boundary])), DropOutcome::Into(Boundary));
        assert_eq!(drop_rule(Debris, with(&[])), DropOutcome::Floor);
        assert_eq!(drop_rule(Debris, with(&[Hub])), DropOutcome::Refused);
        assert_eq!(drop_rule(Debris, with(&[Boundary, Obstacles])), DropOutcome::Refused);
        assert_eq!(drop_rule(Debris, with(&[Food])), DropOutcome::Floor);
    }
}
