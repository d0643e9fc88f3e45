//! An agent's local model of the world for one tick.
//!
//! Built from its cell's [`Percept`]: its own body, the objects registered in its cell,
//! impassable objects nearby, plus the agent's own static memory and blackboard. Leaf
//! behaviours read and change this model; every change the world must make is recorded
//! as an [`Op`] for the intent. Nothing here touches the real world.
use geese_proto::rules::{self, DropOutcome};
use geese_proto::{AgentId, CellIdx, Geometry, ObjectId, ObjectInfo, ObjectKind, Op, Percept, Pos};

/// Step length of an agent whose carried objects weigh `w` (the rule the world applies).
pub use geese_proto::rules::speed;

/// Per-agent maps indexed by object kind.
#[derive(Clone, Debug, Default)]
pub struct KindMap {
    lists: [Vec<ObjectInfo>; 7],
    present: u8,
}

impl KindMap {
    fn idx(k: ObjectKind) -> usize {
        k as usize
    }
    pub fn clear(&mut self) {
        if self.present != 0 {
            for l in &mut self.lists {
                l.clear();
            }
            self.present = 0;
        }
    }
    pub fn has(&self, k: ObjectKind) -> bool {
        self.present & (1 << Self::idx(k)) != 0
    }
    pub fn get(&self, k: ObjectKind) -> &[ObjectInfo] {
        if self.has(k) {
            &self.lists[Self::idx(k)]
        } else {
            &[]
        }
    }
    /// Insert if no object with the same id is present (set semantics).
    pub fn insert(&mut self, o: ObjectInfo) {
        let i = Self::idx(o.kind);
        self.present |= 1 << i;
        if !self.lists[i].iter().any(|x| x.id == o.id) {
            self.lists[i].push(o);
        }
    }
    pub fn push(&mut self, o: ObjectInfo) {
        let i = Self::idx(o.kind);
        self.present |= 1 << i;
        self.lists[i].push(o);
    }
}

/// The agent's local world for one tick.
#[derive(Debug)]
pub struct View {
    pub geom: Geometry,
    pub id: AgentId,
    /// Where the agent stands ([`View::pos`]), and its cell: set together, by the
    /// percept and by moves (the cell was computed afresh at every look-up, a few times
    /// each tick).
    pos: Pos,
    here: CellIdx,
    pub heading: f64,
    pub carrying: Vec<ObjectInfo>,
    /// The cell whose objects are known (the one the percept describes).
    pub known_cell: CellIdx,
    /// Non-agent objects registered in `known_cell`, as changed by this tick so far.
    pub cell_objects: Vec<ObjectInfo>,
    /// Other agents registered in `known_cell`.
    pub cell_agents: usize,
    /// Impassable objects near `known_cell`.
    pub impassable: Vec<ObjectInfo>,
    /// Cells within this many columns and rows of `known_cell` are known too: their
    /// objects are in `area` (the percept's reach).
    pub reach: i32,
    /// Non-agent objects of the cells within `reach` of `known_cell` (not in it), as
    /// changed by this tick so far.
    pub area: Vec<ObjectInfo>,
    /// The blackboard (REFERENCE §2.2), one per agent.
    pub blackboard: KindMap,
    /// Static memory of hubs, sites and boundaries ever sensed.
    pub memory: KindMap,
    /// Ops for the world, in order.
    pub ops: Vec<Op>,
    /// Weight this agent dropped into a drop zone (food into the hub, debris into a
    /// boundary) since the learner last cleared it: GEESE-BT's task reward F.
    pub delivered: i32,
}

impl View {
    pub fn new(geom: Geometry, id: AgentId) -> Self {
        View {
            geom,
            id,
            pos: Pos::default(),
            here: geom.cell_of(Pos::default()),
            heading: 0.0,
            carrying: Vec::new(),
            known_cell: 0,
            cell_objects: Vec::new(),
            cell_agents: 0,
            impassable: Vec::new(),
            reach: 0,
            area: Vec::new(),
            blackboard: KindMap::default(),
            memory: KindMap::default(),
            ops: Vec::new(),
            delivered: 0,
        }
    }

    /// Load the percept of the agent's cell. Returns false if the agent is not in it.
    pub fn load(&mut self, p: &Percept) -> bool {
        let Some(me) = p.agents.iter().find(|a| a.id == self.id) else {
            return false;
        };
        self.set_pos(me.pos);
        self.heading = me.heading;
        self.carrying.clear();
        self.carrying.extend_from_slice(&me.carrying);
        self.known_cell = p.cell;
        self.cell_objects.clear();
        self.cell_objects.extend_from_slice(&p.objects);
        self.cell_agents = p.agents.len().saturating_sub(1);
        self.impassable.clear();
        self.impassable.extend(p.objects.iter().filter(|o| !o.kind.passable()));
        self.impassable.extend_from_slice(&p.nearby_impassable);
        self.reach = i32::from(p.reach);
        self.area.clear();
        self.area.extend_from_slice(&p.area);
        self.ops.clear();
        true
    }

    /// Where the agent stands.
    pub fn pos(&self) -> Pos {
        self.pos
    }

    /// The cell the agent stands in.
    pub fn cell(&self) -> CellIdx {
        self.here
    }

    fn set_pos(&mut self, p: Pos) {
        self.pos = p;
        self.here = self.geom.cell_of(p);
    }

    /// Is `o` registered in `cell` (its neighbourhood covers the cell)?
    pub fn registered_in(&self, o: &ObjectInfo, cell: CellIdx) -> bool {
        self.geom.registered_in(o.pos, o.radius, cell)
    }

    /// Is `cell` one of the cells around the percept's whose objects are known?
    pub fn in_area(&self, cell: CellIdx) -> bool {
        if self.reach == 0 || cell == self.known_cell {
            return false;
        }
        let ((c, r), (kc, kr)) = (self.geom.cell_col_row(cell), self.geom.cell_col_row(self.known_cell));
        (c - kc).abs() <= self.reach && (r - kr).abs() <= self.reach
    }

    /// Non-agent objects registered in the agent's current cell, as far as it knows:
    /// everything for the percept's cell and the cells of its area, only impassable
    /// objects elsewhere.
    pub fn objects_here(&self) -> impl Iterator<Item = &ObjectInfo> {
        let cell = self.cell();
        let known = cell == self.known_cell;
        let (a, b): (&[ObjectInfo], &[ObjectInfo]) = if known {
            (&self.cell_objects, &[])
        } else if self.in_area(cell) {
            (&[], &self.area)
        } else {
            (&[], &self.impassable)
        };
        a.iter().chain(b.iter().filter(move |o| self.registered_in(o, cell)))
    }

    pub fn cell_blocked(&self, cell: CellIdx) -> bool {
        self.impassable.iter().any(|o| self.registered_in(o, cell))
    }

    /// Find(kind): the blackboard entry if present, else static memory (REFERENCE §2.2).
    pub fn find(&self, kind: ObjectKind) -> &[ObjectInfo] {
        if self.blackboard.has(kind) {
            self.blackboard.get(kind)
        } else {
            self.memory.get(kind)
        }
    }

    pub fn carried_weight(&self) -> i32 {
        rules::carried_weight(&self.carrying)
    }

    /// The Move primitive (REFERENCE §1.6). Records the op on success.
    pub fn do_move(&mut self) -> bool {
        let before = self.heading;
        let (dest, h) = rules::destination(&self.geom, self.pos, before, self.carried_weight());
        let (old_c, new_c) = (self.cell(), self.geom.cell_of(dest));
        if old_c != new_c && self.cell_blocked(new_c) {
            return false;
        }
        self.pos = dest;
        self.here = new_c;
        self.heading = h;
        self.ops.push(Op::Move { to: dest, heading: before });
        true
    }

    /// Pick up `o` (SingleCarry). False if it is no longer in the cell.
    pub fn pick(&mut self, o: ObjectId) -> bool {
        let cell = self.cell();
        let obj = if cell == self.known_cell {
            let Some(i) = self.cell_objects.iter().position(|x| x.id == o) else {
                return false;
            };
            self.cell_objects.remove(i)
        } else if self.in_area(cell) {
            let Some(i) = self.area.iter().position(|x| x.id == o && self.geom.registered_in(x.pos, x.radius, cell))
            else {
                return false;
            };
            self.area.remove(i)
        } else {
            return false;
        };
        self.carrying.push(obj);
        self.ops.push(Op::Pick { object: o });
        true
    }

    /// Drop the first carried object of `kind` under the final drop rules.
    pub fn drop_item(&mut self, kind: ObjectKind) -> bool {
        let Some(slot) = self.carrying.iter().position(|o| o.kind == kind) else {
            return false;
        };
        let into_target = match rules::drop_rule(kind, |k| self.objects_here().any(|o| o.kind == k)) {
            DropOutcome::Refused => return false,
            DropOutcome::Into(_) => true,
            DropOutcome::Floor => false,
        };
        let mut o = self.carrying.remove(slot);
        if into_target {
            self.delivered += o.weight;
        }
        o.pos = self.pos;
        self.ops.push(Op::Drop { object: o.id });
        if !into_target {
            let cell = self.cell();
            if cell == self.known_cell {
                self.cell_objects.push(o);
            } else if self.in_area(cell) {
                self.area.push(o);
            }
        }
        true
    }
}
