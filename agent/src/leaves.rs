//! Leaf behaviours: conditions, primitive actions and the composite ("basic") actions
//! of REFERENCE.md §2.3–2.5.
//!
//! A composite leaf (MoveTowards, Explore, CompositeSingleCarry, …) owns a private
//! subtree whose node statuses nobody can observe; only its result matters. So each is
//! written here as the equivalent short-circuit expression (`||` for a Selector, `&&`
//! for a Sequence), which is exact and much cheaper than a node arena.
use crate::view::View;
use geese_proto::{ObjectInfo, ObjectKind, Pos};
use rand::Rng;
use rand_distr::{Distribution, Normal};
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// Motion family of a movement leaf.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Motion {
    /// Obstacle-avoiding (bug-following) variant.
    Avoid,
    /// Plain variant.
    Normal,
}

/// A leaf of an agent's behaviour tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Leaf {
    /// `None` senses every type.
    NeighbourObjects(Option<ObjectKind>),
    IsCarrying(ObjectKind),
    IsVisitedBefore(ObjectKind),
    IsCarryable(ObjectKind),
    IsDropable(ObjectKind),
    DidAvoidedObj(ObjectKind),
    CanMove,
    DummyNode,
    MoveTowards(ObjectKind, Motion),
    MoveAway(ObjectKind, Motion),
    Explore(Motion),
    CompositeSingleCarry(ObjectKind),
    CompositeDrop(ObjectKind),
    /// A Multi-GEESE controller slot whose action the agent's GeneDict lacks: always
    /// FAILURE (REFERENCE §9.4; the reference code raises instead).
    Absent,
}

/// Why a leaf text does not name a behaviour.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum LeafError {
    #[error("unknown behaviour '{0}'")]
    UnknownClass(String),
    #[error("unknown object type '{0}' in '{1}'")]
    UnknownItem(String, String),
    #[error("behaviour '{0}' needs an object type")]
    MissingItem(String),
    #[error("unknown suffix '{0}' in '{1}'")]
    UnknownSuffix(String, String),
}

/// A parsed leaf text: the leaf and whether it is inverted (`_invert`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LeafSpec {
    pub leaf: Leaf,
    pub invert: bool,
}

impl LeafSpec {
    /// Parse a grammar leaf text such as `IsCarrying_Food`, `MoveTowards_Hub_Normal`,
    /// `NeighbourObjects_Sites_invert`, `Explore_0_Avoid`, `CanMove` (REFERENCE §4.2).
    pub fn parse(text: &str) -> Result<LeafSpec, LeafError> {
        let parts: Vec<&str> = text.split('_').collect();
        let (class, item, kind) = match parts.as_slice() {
            [c] => (*c, None, None),
            [c, i] => (*c, Some(*i), None),
            [c, i, k] => (*c, Some(*i), Some(*k)),
            _ => return Err(LeafError::UnknownClass(text.to_string())),
        };
        let (motion, invert) = match kind {
            None | Some("Avoid") => (Motion::Avoid, false),
            Some("Normal") => (Motion::Normal, false),
            Some("invert") => (Motion::Avoid, true),
            Some(other) => return Err(LeafError::UnknownSuffix(other.into(), text.into())),
        };
        // `ExploreNormal` etc. spelled as one word (Multi-GEESE action names).
        let (class, motion) = match class.strip_suffix("Normal") {
            Some(base) if !base.is_empty() => (base, Motion::Normal),
            _ => (class, motion),
        };
        let obj = |req: bool| -> Result<Option<ObjectKind>, LeafError> {
            match item {
                None if req => Err(LeafError::MissingItem(text.into())),
                None => Ok(None),
                Some(i) => {
                    ObjectKind::from_name(i).map(Some).ok_or_else(|| LeafError::UnknownItem(i.into(), text.into()))
                }
            }
        };
        let need = |o: Option<ObjectKind>| o.ok_or_else(|| LeafError::MissingItem(text.into()));
        let leaf = match class {
            "NeighbourObjects" => Leaf::NeighbourObjects(obj(false)?),
            "IsCarrying" => Leaf::IsCarrying(need(obj(true)?)?),
            "IsVisitedBefore" => Leaf::IsVisitedBefore(need(obj(true)?)?),
            "IsCarryable" => Leaf::IsCarryable(need(obj(true)?)?),
            "IsDropable" => Leaf::IsDropable(need(obj(true)?)?),
            "DidAvoidedObj" => Leaf::DidAvoidedObj(need(obj(true)?)?),
            "CanMove" => Leaf::CanMove,
            "AbsentAction" => Leaf::Absent,
            "DummyNode" => Leaf::DummyNode,
            "MoveTowards" => Leaf::MoveTowards(need(obj(true)?)?, motion),
            "MoveAway" => Leaf::MoveAway(need(obj(true)?)?, motion),
            // The item of Explore (`Explore_0_…`) is ignored.
            "Explore" => Leaf::Explore(motion),
            "CompositeSingleCarry" => Leaf::CompositeSingleCarry(need(obj(true)?)?),
            "CompositeDrop" => Leaf::CompositeDrop(need(obj(true)?)?),
            other => return Err(LeafError::UnknownClass(other.into())),
        };
        Ok(LeafSpec { leaf, invert })
    }
}

impl Leaf {
    /// Is this one of the basic actions (what the `[Act]` slot holds)?
    pub fn is_action(&self) -> bool {
        matches!(
            self,
            Leaf::MoveTowards(..)
                | Leaf::MoveAway(..)
                | Leaf::Explore(_)
                | Leaf::CompositeSingleCarry(_)
                | Leaf::CompositeDrop(_)
        )
    }

    /// The GeneDict key of an action leaf: its behaviour class name (REFERENCE §7.1),
    /// the item not included; `None` for a condition.
    pub fn class_key(&self) -> Option<&'static str> {
        let normal = |m: &Motion| *m == Motion::Normal;
        Some(match self {
            Leaf::MoveTowards(_, m) if normal(m) => "MoveTowardsNormal",
            Leaf::MoveTowards(..) => "MoveTowards",
            Leaf::MoveAway(_, m) if normal(m) => "MoveAwayNormal",
            Leaf::MoveAway(..) => "MoveAway",
            Leaf::Explore(m) if normal(m) => "ExploreNormal",
            Leaf::Explore(_) => "Explore",
            Leaf::CompositeSingleCarry(_) => "CompositeSingleCarry",
            Leaf::CompositeDrop(_) => "CompositeDrop",
            _ => return None,
        })
    }

    /// The object types the leaf names.
    pub fn object(&self) -> Option<ObjectKind> {
        match *self {
            Leaf::NeighbourObjects(k) => k,
            Leaf::IsCarrying(k)
            | Leaf::IsVisitedBefore(k)
            | Leaf::IsCarryable(k)
            | Leaf::IsDropable(k)
            | Leaf::DidAvoidedObj(k)
            | Leaf::MoveTowards(k, _)
            | Leaf::MoveAway(k, _)
            | Leaf::CompositeSingleCarry(k)
            | Leaf::CompositeDrop(k) => Some(k),
            Leaf::CanMove | Leaf::DummyNode | Leaf::Explore(_) | Leaf::Absent => None,
        }
    }

    /// Display name as in the reference listings, e.g. `MoveTowards[Hub]`.
    pub fn name(&self) -> String {
        let m = |m: &Motion| if *m == Motion::Normal { "Normal" } else { "" };
        match self {
            Leaf::NeighbourObjects(None) => "NeighbourObjects".into(),
            Leaf::NeighbourObjects(Some(k)) => format!("NeighbourObjects[{}]", k.name()),
            Leaf::IsCarrying(k) => format!("IsCarrying[{}]", k.name()),
            Leaf::IsVisitedBefore(k) => format!("IsVisitedBefore[{}]", k.name()),
            Leaf::IsCarryable(k) => format!("IsCarryable[{}]", k.name()),
            Leaf::IsDropable(k) => format!("IsDropable[{}]", k.name()),
            Leaf::DidAvoidedObj(k) => format!("DidAvoidedObj[{}]", k.name()),
            Leaf::CanMove => "CanMove".into(),
            Leaf::DummyNode => "DummyNode".into(),
            Leaf::MoveTowards(k, mo) => format!("MoveTowards{}[{}]", m(mo), k.name()),
            Leaf::MoveAway(k, mo) => format!("MoveAway{}[{}]", m(mo), k.name()),
            Leaf::Explore(mo) => format!("Explore{}", m(mo)),
            Leaf::CompositeSingleCarry(k) => format!("CompositeSingleCarry[{}]", k.name()),
            Leaf::CompositeDrop(k) => format!("CompositeDrop[{}]", k.name()),
            Leaf::Absent => "AbsentAction".into(),
        }
    }

    /// Tick the leaf once; true = SUCCESS, false = FAILURE.
    pub fn tick<R: Rng>(&self, v: &mut View, rng: &mut R) -> bool {
        match *self {
            Leaf::NeighbourObjects(item) => neighbour_objects(v, item),
            Leaf::IsCarrying(k) => v.carrying.iter().any(|o| o.kind == k),
            Leaf::IsVisitedBefore(k) => !v.find(k).is_empty(),
            Leaf::IsCarryable(k) => v.find(k).first().is_some_and(|o| o.kind.carryable()),
            // CODE: the check always raises and is caught as SUCCESS (REFERENCE §2.3).
            Leaf::IsDropable(_) => true,
            Leaf::DidAvoidedObj(k) => did_avoided(v, k),
            Leaf::CanMove | Leaf::DummyNode => true,
            Leaf::MoveTowards(k, m) => move_rel(v, rng, k, m, false),
            Leaf::MoveAway(k, m) => move_rel(v, rng, k, m, true),
            Leaf::Explore(Motion::Normal) => random_walk(v, rng) && v.do_move(),
            Leaf::Explore(Motion::Avoid) => {
                (random_walk(v, rng) && !probe(v, ObjectKind::Obstacles) && !probe(v, ObjectKind::Traps) && v.do_move())
                    || avoid_and_move(v, ObjectKind::Obstacles)
                    || avoid_and_move(v, ObjectKind::Traps)
            }
            Leaf::CompositeSingleCarry(k) => {
                v.carrying.iter().any(|o| o.kind == k)
                    || (neighbour_objects(v, Some(k))
                        && v.find(k).first().is_some_and(|o| o.kind.carryable())
                        && is_single_carry(v, k)
                        && single_carry(v, k))
            }
            Leaf::Absent => false,
            Leaf::CompositeDrop(k) => {
                // FailureIsSuccess(NeighbourObjects(none)): senses, result ignored.
                neighbour_objects(v, None);
                v.carrying.iter().any(|o| o.kind == k) && v.drop_item(k)
            }
        }
    }
}

/// NeighbourObjects(item): reset the blackboard, sense the own cell (REFERENCE §2.3).
fn neighbour_objects(v: &mut View, item: Option<ObjectKind>) -> bool {
    v.blackboard.clear();
    let cell = v.cell();
    let known = cell == v.known_cell;
    let mut found = false;
    // Take the list out to satisfy the borrow checker without cloning.
    let objs = if known { std::mem::take(&mut v.cell_objects) } else { Vec::new() };
    let extra: Vec<ObjectInfo> = if known {
        Vec::new()
    } else {
        let around: &[ObjectInfo] = if v.in_area(cell) { &v.area } else { &v.impassable };
        around.iter().filter(|o| v.registered_in(o, cell)).copied().collect()
    };
    for o in objs.iter().chain(extra.iter()) {
        if item.is_some_and(|k| k != o.kind) {
            continue;
        }
        found = true;
        if o.kind.memorised() {
            v.memory.insert(*o);
        } else {
            if item.is_none() && !v.blackboard.has(o.kind) {
                // CODE quirk: a new type resets the whole blackboard.
                v.blackboard.clear();
            }
            v.blackboard.push(*o);
        }
    }
    if known {
        v.cell_objects = objs;
    }
    if item.is_none() && known && v.cell_agents > 0 {
        found = true;
    }
    found
}

/// NeighbourObjectsDist(kind): probe 0, 1 and 2 units ahead for an impassable object of
/// `kind`; on a hit it goes to the blackboard.
fn probe(v: &mut View, kind: ObjectKind) -> bool {
    v.blackboard.clear();
    // Nothing of the kind nearby: no look-ahead point can find one (most probes; the
    // three points cost a sine, a cosine and three cell look-ups).
    if kind.passable() || !v.impassable.iter().any(|o| o.kind == kind) {
        return false;
    }
    let (c, s) = (v.heading.cos(), v.heading.sin());
    for d in 0..3 {
        let p = Pos::new(
            (v.pos().x as f64 + d as f64 * c).trunc() as i32,
            (v.pos().y as f64 + d as f64 * s).trunc() as i32,
        );
        let (p, _) = v.geom.reflect(p, v.heading);
        let cell = v.geom.cell_of(p);
        if let Some(o) = v.impassable.iter().find(|o| o.kind == kind && v.registered_in(o, cell)) {
            let o = *o;
            v.blackboard.push(o);
            return true;
        }
    }
    false
}

/// Sequence[NeighbourObjectsDist(kind), AvoidSObjects(kind), CanMove, Move].
fn avoid_and_move(v: &mut View, kind: ObjectKind) -> bool {
    probe(v, kind) && avoid(v, kind) && v.do_move()
}

/// AvoidSObjects: turn along the first edge of the obstacle's cell box that the
/// 3-unit look-ahead ray crosses (bottom, right, top, left). Always SUCCESS.
fn avoid(v: &mut View, kind: ObjectKind) -> bool {
    let Some(o) = v.find(kind).first().copied() else {
        return true;
    };
    let a = (v.pos().x as f64, v.pos().y as f64);
    let b = ((a.0 + 3.0 * v.heading.cos()).ceil(), (a.1 + 3.0 * v.heading.sin()).ceil());
    let (x1, y1, x2, y2) = v.geom.neighbourhood_box(o.pos, o.radius);
    let (x1, y1, x2, y2) = (x1 as f64, y1 as f64, x2 as f64, y2 as f64);
    let edges = [
        ((x1, y1), (x2, y1), 0.0),
        ((x2, y1), (x2, y2), FRAC_PI_2),
        ((x2, y2), (x1, y2), PI),
        ((x1, y2), (x1, y1), -FRAC_PI_2),
    ];
    for (p, q, h) in edges {
        if segments_intersect(a, b, p, q) {
            v.heading = h;
            break;
        }
    }
    true
}

type P2 = (f64, f64);

fn orient(a: P2, b: P2, c: P2) -> i8 {
    let v = (b.1 - a.1) * (c.0 - b.0) - (b.0 - a.0) * (c.1 - b.1);
    if v > 0.0 {
        1
    } else if v < 0.0 {
        2
    } else {
        0
    }
}

fn on_segment(a: P2, b: P2, c: P2) -> bool {
    b.0 <= a.0.max(c.0) && b.0 >= a.0.min(c.0) && b.1 <= a.1.max(c.1) && b.1 >= a.1.min(c.1)
}

/// Standard orientation test; touching and collinear overlap count as intersecting.
pub fn segments_intersect(p1: P2, q1: P2, p2: P2, q2: P2) -> bool {
    let (o1, o2, o3, o4) = (orient(p1, q1, p2), orient(p1, q1, q2), orient(p2, q2, p1), orient(p2, q2, q1));
    (o1 != o2 && o3 != o4)
        || (o1 == 0 && on_segment(p1, p2, q1))
        || (o2 == 0 && on_segment(p1, q2, q1))
        || (o3 == 0 && on_segment(p2, p1, q2))
        || (o4 == 0 && on_segment(p2, q1, q2))
}

/// GoTo(kind): aim at a uniformly chosen known object of that kind.
fn goto<R: Rng>(v: &mut View, rng: &mut R, kind: ObjectKind) -> bool {
    let targets = v.find(kind);
    if targets.is_empty() {
        return false;
    }
    let t = targets[rng.random_range(0..targets.len())].pos;
    v.heading = ((t.y - v.pos().y) as f64).atan2((t.x - v.pos().x) as f64).rem_euclid(TAU);
    true
}

/// MoveTowards / MoveAway in either motion family (REFERENCE §2.5).
fn move_rel<R: Rng>(v: &mut View, rng: &mut R, k: ObjectKind, m: Motion, away: bool) -> bool {
    if neighbour_objects(v, Some(k)) {
        return true;
    }
    let turn = |v: &mut View| {
        if away {
            v.heading = (v.heading + PI).rem_euclid(TAU);
        }
        true
    };
    match m {
        Motion::Normal => goto(v, rng, k) && turn(v) && v.do_move(),
        Motion::Avoid => {
            (goto(v, rng, k)
                && turn(v)
                && !probe(v, ObjectKind::Obstacles)
                && !probe(v, ObjectKind::Traps)
                && v.do_move())
                || avoid_and_move(v, ObjectKind::Obstacles)
                || avoid_and_move(v, ObjectKind::Traps)
        }
    }
}

/// RandomWalk: heading plus Gaussian noise of standard deviation 0.1 rad.
fn random_walk<R: Rng>(v: &mut View, rng: &mut R) -> bool {
    // Normal::new only fails for a negative or NaN deviation.
    if let Ok(n) = Normal::new(0.0, 0.1) {
        v.heading = (v.heading + n.sample(rng)).rem_euclid(TAU);
    }
    true
}

/// DidAvoidedObj: SUCCESS unless the agent is heading towards the object.
fn did_avoided(v: &View, k: ObjectKind) -> bool {
    let Some(o) = v.find(k).first() else { return true };
    let alpha = ((v.pos().y - o.pos.y) as f64).atan2((v.pos().x - o.pos.x) as f64);
    (v.heading - alpha).abs() >= FRAC_PI_2
}

/// IsSingleCarry on the first found object of `k` (the rule the world applies).
fn is_single_carry(v: &View, k: ObjectKind) -> bool {
    let Some(o) = v.find(k).first() else { return false };
    geese_proto::rules::is_single_carry(&v.carrying, o)
}

/// SingleCarry: take the first found object; FAILURE if it is gone.
fn single_carry(v: &mut View, k: ObjectKind) -> bool {
    let Some(o) = v.find(k).first().copied() else { return false };
    v.pick(o.id)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_leaf_texts() {
        let p = |s| LeafSpec::parse(s).unwrap();
        assert_eq!(p("IsCarrying_Food").leaf, Leaf::IsCarrying(ObjectKind::Food));
        assert_eq!(p("MoveTowards_Hub").leaf, Leaf::MoveTowards(ObjectKind::Hub, Motion::Avoid));
        assert_eq!(p("MoveAway_Sites_Normal").leaf, Leaf::MoveAway(ObjectKind::Sites, Motion::Normal));
        assert_eq!(p("Explore_0_Normal").leaf, Leaf::Explore(Motion::Normal));
        assert_eq!(p("Explore").leaf, Leaf::Explore(Motion::Avoid));
        assert_eq!(p("ExploreNormal").leaf, Leaf::Explore(Motion::Normal));
        assert_eq!(p("MoveTowardsNormal_Hub").leaf, Leaf::MoveTowards(ObjectKind::Hub, Motion::Normal));
        let inv = p("IsVisitedBefore_Sites_invert");
        assert!(inv.invert);
        assert_eq!(inv.leaf, Leaf::IsVisitedBefore(ObjectKind::Sites));
        assert_eq!(p("NeighbourObjects").leaf, Leaf::NeighbourObjects(None));
        assert!(LeafSpec::parse("Fly_Hub").is_err());
        assert!(LeafSpec::parse("IsCarrying_Gold").is_err());
        assert!(LeafSpec::parse("IsCarrying").is_err());
        assert!(LeafSpec::parse("IsCarrying_Food_sideways").is_err());
    }

    #[test]
    fn segment_test() {
        assert!(segments_intersect((0.0, 0.0), (2.0, 2.0), (0.0, 2.0), (2.0, 0.0)));
        assert!(!segments_intersect((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)));
        assert!(segments_intersect((0.0, 0.0), (1.0, 0.0), (1.0, 0.0), (1.0, 5.0)));
    }
}
