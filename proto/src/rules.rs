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
//! - the final, type-aware drop rules ([`drop_rule`], §2.4);
//! - the cells an agent's gene must reach ([`for_each_gene_cell`], §1.2 and §6.2): the
//!   world's gene hub waits for it there, and agents send it there.
use crate::geometry::{step_destination, CellIdx, Geometry, Pos};
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

/// Whether an agent's gene must reach more than its own cell on this grid: whether an
/// agent is registered in more than one cell (GS < [`AGENT_RADIUS`]; at GS 2 a 3×3
/// block, REFERENCE §1.2). At GS ≥ 3 every agent is registered in its own cell only.
pub fn genes_spread(geom: &Geometry) -> bool {
    geom.reach(AGENT_RADIUS) > 0
}

/// The cells the gene of a live agent centred at `p` must reach at a step: every cell
/// it is registered in (N(p, [`AGENT_RADIUS`])) whose percept some live agent reads,
/// that is, where `read(c)` says a live agent has its centre. Calls `f` for each, in
/// row-major order.
///
/// Why: lateral transfer takes the genes of every learning agent registered in the
/// agent's own cell (REFERENCE §6.2), and a percept lists every agent registered in its
/// cell, so every live agent whose centre is in a cell of N(p, r) expects this gene.
/// Those are the only cells whose percepts are read. Agents all have the same radius,
/// so the relation is symmetric: an agent is registered in the cell of another's
/// centre exactly when the other is registered in the cell of its centre.
///
/// At GS ≥ [`AGENT_RADIUS`] that is the agent's own cell, read by the agent itself:
/// `read` is not asked.
pub fn for_each_gene_cell(geom: &Geometry, p: Pos, read: impl Fn(CellIdx) -> bool, mut f: impl FnMut(CellIdx)) {
    if !genes_spread(geom) {
        f(geom.cell_of(p));
        return;
    }
    geom.for_each_neighbourhood_cell(p, AGENT_RADIUS, |c| {
        if read(c) {
            f(c);
        }
    });
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
    fn a_gene_reaches_the_read_cells_it_is_registered_in() {
        let cells = |g: &Geometry, p: Pos, read: &dyn Fn(CellIdx) -> bool| {
            let mut v = Vec::new();
            for_each_gene_cell(g, p, read, |c| v.push(c));
            v
        };
        // GS 10 (and 5, and 3): its own cell, whatever else is read.
        for gs in [10, 5] {
            let g = Geometry::new(100, 100, gs).unwrap();
            assert!(!genes_spread(&g));
            assert_eq!(cells(&g, Pos::new(3, -7), &|_| true), vec![g.cell_of(Pos::new(3, -7))]);
        }
        assert!(!genes_spread(&Geometry::new(60, 60, 3).unwrap()));
        // GS 2: the read cells of its 3×3 block, clipped at the edge.
        let g = Geometry::new(100, 100, 2).unwrap();
        assert!(genes_spread(&g));
        let p = Pos::new(0, 0);
        let block = g.neighbourhood(p, AGENT_RADIUS);
        assert_eq!(block.len(), 9);
        assert_eq!(cells(&g, p, &|_| true), block);
        let right = g.cell_of(Pos::new(2, 0));
        let far = g.cell_of(Pos::new(6, 0));
        assert_eq!(cells(&g, p, &|c| c == right || c == far || c == g.cell_of(p)), vec![g.cell_of(p), right]);
        assert_eq!(cells(&g, Pos::new(-50, -50), &|_| true).len(), 4);
        // Symmetric: a registered in b's centre cell exactly when b in a's.
        for (a, b) in
            [(Pos::new(0, 0), Pos::new(2, 2)), (Pos::new(0, 0), Pos::new(4, 0)), (Pos::new(-3, 1), Pos::new(-1, 3))]
        {
            assert_eq!(
                g.registered_in(a, AGENT_RADIUS, g.cell_of(b)),
                g.registered_in(b, AGENT_RADIUS, g.cell_of(a)),
                "{a:?} {b:?}"
            );
        }
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
