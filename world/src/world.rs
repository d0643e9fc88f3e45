//! Authoritative world state: objects, agent bodies, grid registration, percepts,
//! intent resolution, task percentage and scheduled perturbations.
use crate::config::{ConfigError, Task, WorldConfig};
use crate::locality::{Locality, Window};
use geese_proto::rules::{self, DropOutcome};
use geese_proto::seed::{derive, Fnv64, Owner, Purpose};
use geese_proto::{
    AgentId, AgentPublic, BehaviourClass, CellIdx, GeneticTrigger, Geometry, Intent, ObjectId, ObjectInfo, ObjectKind,
    Op, Percept, Perturbation, Pos, Regime, StepReport,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Agent body constants (REFERENCE §1.5) and the step length, shared with the agents.
pub use geese_proto::rules::{speed, AGENT_CAPACITY, AGENT_FORCE, AGENT_RADIUS, AGENT_WEIGHT};

/// A non-agent object and its bookkeeping.
#[derive(Clone, Debug)]
pub struct Object {
    pub info: ObjectInfo,
    /// Registered in the grid (false while carried or once delivered).
    pub registered: bool,
    /// Delivered objects (hub, boundary).
    pub dropped: Vec<ObjectId>,
}

/// The outcome of a move computed ahead of resolving ([`World::move_hint`]), with the
/// inputs it was computed from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MoveHint {
    from: Pos,
    heading: f64,
    weight: i32,
    dest: Pos,
    new_heading: f64,
}

/// An agent's body as the world keeps it.
#[derive(Clone, Debug)]
pub struct Body {
    pub id: AgentId,
    pub pos: Pos,
    pub heading: f64,
    pub carrying: Vec<ObjectId>,
    pub live: bool,
    pub learning: bool,
    /// The behaviour class its last intent reported (for the view and locality map).
    pub class: BehaviourClass,
}

#[derive(Clone, Debug, Default)]
struct Cell {
    objects: Vec<ObjectId>,
    agents: Vec<AgentId>,
}

/// Why an intent or op was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum Rejection {
    #[error("intent for step {got}, world is at step {expected}")]
    WrongStep { got: u64, expected: u64 },
    #[error("agent {0} does not exist")]
    NoSuchAgent(AgentId),
    #[error("agent {0} is not live")]
    Dead(AgentId),
    #[error("move to {to:?} is not one step along heading {heading}")]
    BadMove { to: Pos, heading: f64 },
    #[error("move into a blocked cell")]
    Blocked,
    #[error("object {0} is gone (picked by an agent with a lower id)")]
    NotHere(ObjectId),
    #[error("object {0} lies outside the agent's cell")]
    OutsideCell(ObjectId),
    #[error("object {0} cannot be picked up")]
    NotCarryable(ObjectId),
    #[error("object {0} is not carried")]
    NotCarried(ObjectId),
    #[error("heading is not finite")]
    BadHeading,
}

pub struct World {
    cfg: WorldConfig,
    geom: Geometry,
    objects: Vec<Object>,
    bodies: Vec<Body>,
    cells: Vec<Cell>,
    hub: ObjectId,
    /// Current step (the step whose percepts are out / whose intents are awaited).
    step: u64,
    regime: Regime,
    schedule: Vec<(u64, Perturbation)>,
    perturb_rng: ChaCha8Rng,
    total_item_weight: i32,
    delivered_weight: i32,
    /// Obstacles that perturbations asked for and the placement rule could not place.
    obstacles_unplaced: u64,
    /// Perturbations applied so far: (step, what), for the live view's chart.
    events: Vec<(u64, String)>,
    /// The locality map being counted, if the run asked for one.
    locality: Option<Locality>,
}

impl World {
    /// Build the world of `cfg` for run seed `seed` (REFERENCE §1.4).
    pub fn new(cfg: WorldConfig, seed: u64) -> Result<Self, ConfigError> {
        let geom = cfg.validate()?;
        let mut w = World {
            geom,
            objects: Vec::new(),
            bodies: Vec::new(),
            cells: vec![Cell::default(); geom.cell_count()],
            hub: 0,
            step: 1,
            regime: Regime::default(),
            schedule: Vec::new(),
            perturb_rng: ChaCha8Rng::seed_from_u64(derive(seed, Owner::World, Purpose::Perturb)),
            total_item_weight: 0,
            delivered_weight: 0,
            obstacles_unplaced: 0,
            events: Vec::new(),
            locality: None,
            cfg,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(derive(seed, Owner::World, Purpose::Layout));
        crate::layout::build(&mut w, &mut rng)?;
        Ok(w)
    }

    pub fn config(&self) -> &WorldConfig {
        &self.cfg
    }
    pub fn geometry(&self) -> Geometry {
        self.geom
    }
    pub fn step(&self) -> u64 {
        self.step
    }
    pub fn regime(&self) -> Regime {
        self.regime
    }
    /// Set the regime in force (initial IP, LT switch) before the run starts.
    pub fn set_regime(&mut self, r: Regime) {
        self.regime = r;
    }
    pub fn hub(&self) -> ObjectInfo {
        self.objects[self.hub as usize].info
    }
    pub fn objects(&self) -> impl Iterator<Item = &Object> {
        self.objects.iter()
    }
    pub fn bodies(&self) -> &[Body] {
        &self.bodies
    }
    pub fn live_agents(&self) -> u32 {
        self.bodies.iter().filter(|b| b.live).count() as u32
    }
    /// Obstacles that perturbations asked for and the obstacle rule could not place, over
    /// the whole run (each shortfall is also logged).
    pub fn events(&self) -> &[(u64, String)] {
        &self.events
    }

    pub fn obstacles_unplaced(&self) -> u64 {
        self.obstacles_unplaced
    }

    /// Count the locality map of `window` from now on (steps already resolved are not
    /// counted again). Without this call the world counts nothing and pays one branch a
    /// step.
    pub fn record_locality(&mut self, window: Window) {
        self.locality = Some(Locality::new(window));
    }

    /// The locality map counted so far, if [`World::record_locality`] asked for one.
    pub fn locality(&self) -> Option<&Locality> {
        self.locality.as_ref()
    }

    // ---------------------------------------------------------------- construction

    pub(crate) fn add_object(&mut self, kind: ObjectKind, pos: Pos, radius: i32) -> ObjectId {
        let (weight, capacity) = rules::item_load(kind, radius);
        let id = self.objects.len() as ObjectId;
        let info = ObjectInfo { id, kind, pos, radius, weight, capacity };
        self.objects.push(Object { info, registered: false, dropped: Vec::new() });
        self.register_object(id);
        if kind.carryable() {
            self.total_item_weight += weight;
        }
        if kind == ObjectKind::Hub && self.objects.iter().filter(|o| o.info.kind == kind).count() == 1 {
            self.hub = id;
        }
        id
    }

    pub(crate) fn add_body(&mut self, pos: Pos, heading: f64) {
        let id = self.bodies.len() as AgentId;
        self.bodies.push(Body {
            id,
            pos,
            heading,
            carrying: Vec::new(),
            live: true,
            learning: true,
            class: BehaviourClass::None,
        });
        self.register_agent(id);
    }

    fn register_object(&mut self, id: ObjectId) {
        let o = &mut self.objects[id as usize];
        o.registered = true;
        let (p, r) = (o.info.pos, o.info.radius);
        let cells = &mut self.cells;
        self.geom.for_each_neighbourhood_cell(p, r, |c| cells[c as usize].objects.push(id));
    }

    fn deregister_object(&mut self, id: ObjectId) {
        let o = &mut self.objects[id as usize];
        o.registered = false;
        let (p, r) = (o.info.pos, o.info.radius);
        let cells = &mut self.cells;
        self.geom.for_each_neighbourhood_cell(p, r, |c| {
            cells[c as usize].objects.retain(|&x| x != id);
        });
    }

    fn register_agent(&mut self, id: AgentId) {
        let p = self.bodies[id as usize].pos;
        let cells = &mut self.cells;
        self.geom.for_each_neighbourhood_cell(p, AGENT_RADIUS, |c| {
            let v = &mut cells[c as usize].agents;
            let at = v.partition_point(|&a| a < id);
            v.insert(at, id);
        });
    }

    fn deregister_agent(&mut self, id: AgentId) {
        let p = self.bodies[id as usize].pos;
        let cells = &mut self.cells;
        self.geom.for_each_neighbourhood_cell(p, AGENT_RADIUS, |c| {
            cells[c as usize].agents.retain(|&x| x != id);
        });
    }

    /// Non-agent objects registered in `cell`.
    pub fn objects_in(&self, cell: CellIdx) -> impl Iterator<Item = &ObjectInfo> {
        self.cells[cell as usize].objects.iter().map(|&id| &self.objects[id as usize].info)
    }

    /// Is any non-agent object registered in any cell of N(p, r)?
    pub(crate) fn area_has_objects(&self, p: Pos, r: i32) -> bool {
        self.geom.any_neighbourhood_cell(p, r, |c| !self.cells[c as usize].objects.is_empty())
    }

    /// Is an impassable object registered in any cell of N(p, r)?
    pub(crate) fn area_blocked(&self, p: Pos, r: i32) -> bool {
        self.geom.any_neighbourhood_cell(p, r, |c| self.cell_blocked(c))
    }

    fn cell_blocked(&self, cell: CellIdx) -> bool {
        self.objects_in(cell).any(|o| !o.kind.passable())
    }

    // ---------------------------------------------------------------- percepts

    /// The percepts of step `self.step`, one per cell holding a live agent's centre,
    /// in cell order.
    pub fn percepts(&self) -> Vec<Percept> {
        self.occupied_cells().into_iter().map(|c| self.percept(c)).collect()
    }

    /// The cells a live agent is in, ascending: those [`World::percepts`] describes, for
    /// a caller that builds their percepts on several threads.
    pub fn occupied_cells(&self) -> Vec<CellIdx> {
        let mut cells = Vec::new();
        self.occupied_cells_into(self.bodies.iter().map(|b| self.body_cell(b)), &mut Vec::new(), &mut cells);
        cells
    }

    /// The cell of a body, if it is live (what [`World::occupied_cells_into`] is given).
    pub fn body_cell(&self, b: &Body) -> Option<CellIdx> {
        b.live.then(|| self.geom.cell_of(b.pos))
    }

    /// [`World::occupied_cells`] into `out`, from the cells of the bodies computed by
    /// the caller (a trial computes them on its worker threads), with `seen` as scratch
    /// (both kept by a caller that asks every step): each cell once, ascending. Read
    /// off a map of the arena's cells where it has at most 16 per occupied one (sorting
    /// 10,000 cells was a sixth of a sparse step's one-thread part), else sorted.
    pub fn occupied_cells_into(
        &self,
        cells: impl IntoIterator<Item = Option<CellIdx>>,
        seen: &mut Vec<bool>,
        out: &mut Vec<CellIdx>,
    ) {
        out.clear();
        out.extend(cells.into_iter().flatten());
        let count = self.geom.cell_count();
        if count <= 16 * out.len() {
            seen.clear();
            seen.resize(count, false);
            for &c in out.iter() {
                seen[c as usize] = true;
            }
            out.clear();
            out.extend((0..count as CellIdx).filter(|&c| seen[c as usize]));
        } else {
            out.sort_unstable();
            out.dedup();
        }
    }

    /// The bodies of the agents registered in `cell`, in registration order.
    pub fn agents_in(&self, cell: CellIdx) -> impl Iterator<Item = &Body> {
        self.cells.get(cell as usize).into_iter().flat_map(|c| c.agents.iter().map(|&id| &self.bodies[id as usize]))
    }

    /// The percept of one cell.
    pub fn percept(&self, cell: CellIdx) -> Percept {
        let here = &self.cells[cell as usize];
        let objects: Vec<ObjectInfo> = self.objects_in(cell).copied().collect();
        // Impassable objects a move or probe from this cell can meet: cells within
        // ceil(3 / GS) columns and rows (at least one).
        let reach = ((AGENT_RADIUS + self.geom.grid() - 1) / self.geom.grid()).max(1);
        let mut nearby_impassable: Vec<ObjectInfo> = Vec::new();
        for idx in self.cells_around(cell, reach) {
            for o in self.objects_in(idx) {
                if !o.kind.passable()
                    && !objects.iter().any(|x| x.id == o.id)
                    && !nearby_impassable.iter().any(|x| x.id == o.id)
                {
                    nearby_impassable.push(*o);
                }
            }
        }
        let agents = here.agents.iter().map(|&id| self.public(id)).collect();
        let reach = self.cfg.percept_reach.unwrap_or(0).min(u8::MAX as u32) as u8;
        let area = if reach == 0 { Vec::new() } else { self.area(cell, i32::from(reach), &objects) };
        Percept { step: self.step, cell, regime: self.regime, objects, nearby_impassable, agents, reach, area }
    }

    /// Non-agent objects registered within `reach` cells of `cell` but not in `own`
    /// (the cell's objects), each once.
    fn area(&self, cell: CellIdx, reach: i32, own: &[ObjectInfo]) -> Vec<ObjectInfo> {
        let mut seen = vec![false; self.objects.len()];
        for o in own {
            seen[o.id as usize] = true;
        }
        let mut area = Vec::new();
        for idx in self.cells_around(cell, reach) {
            for o in self.objects_in(idx) {
                if !std::mem::replace(&mut seen[o.id as usize], true) {
                    area.push(*o);
                }
            }
        }
        area
    }

    /// The cells within `reach` columns and rows of `cell`, row-major, `cell` itself
    /// left out (clipped at the arena's edges).
    fn cells_around(&self, cell: CellIdx, reach: i32) -> impl Iterator<Item = CellIdx> {
        let (c0, r0) = self.geom.cell_col_row(cell);
        let (rows, cols) = (self.geom.rows(), self.geom.cols());
        ((r0 - reach).max(0)..=(r0 + reach).min(rows - 1))
            .flat_map(move |r| {
                ((c0 - reach).max(0)..=(c0 + reach).min(cols - 1)).map(move |c| (r * cols + c) as CellIdx)
            })
            .filter(move |&idx| idx != cell)
    }

    fn public(&self, id: AgentId) -> AgentPublic {
        let b = &self.bodies[id as usize];
        AgentPublic {
            id,
            pos: b.pos,
            heading: b.heading,
            carrying: b.carrying.iter().map(|&o| self.objects[o as usize].info).collect(),
            live: b.live,
            learning: b.learning,
        }
    }

    // ---------------------------------------------------------------- resolution

    /// Resolve step `self.step`: `intents[i]` is agent i's intent (`None` if it did not
    /// arrive). Applies them in agent-id order, runs scheduled perturbations, advances the
    /// step counter and returns the step report.
    pub fn resolve(&mut self, intents: &[Option<Intent>]) -> StepReport {
        self.resolve_hinted(intents, &[])
    }

    /// [`World::resolve`] with the outcome of each intent's first move computed
    /// beforehand (`hints[i]` for agent i, [`World::move_hint`]): an in-process trial
    /// computes them on its worker threads, and the one thread that applies the intents
    /// in order then only checks that a hint's inputs are the agent's.
    pub fn resolve_hinted(&mut self, intents: &[Option<Intent>], hints: &[Option<MoveHint>]) -> StepReport {
        self.resolve_each(
            |_, id| intents.get(id as usize).and_then(Option::as_ref),
            |id| hints.get(id as usize).copied().flatten(),
        )
    }

    /// Where an intent's first op, if it is a move, takes its agent, computed from the
    /// world as the step starts: nothing applied before that op changes the agent's
    /// body (no other intent touches it), so it is what applying the op computes.
    pub fn move_hint(&self, intent: &Intent) -> Option<MoveHint> {
        let Some(&Op::Move { heading, .. }) = intent.ops.first() else { return None };
        let body = self.bodies.get(intent.agent as usize)?;
        if !heading.is_finite() {
            return None;
        }
        let weight = rules::carried_weight(self.carried(intent.agent));
        let (dest, new_heading) = rules::destination(&self.geom, body.pos, heading, weight);
        Some(MoveHint { from: body.pos, heading, weight, dest, new_heading })
    }

    /// Resolve step `self.step`, asking `next` for each live agent's intent in agent-id
    /// order and applying it before asking for the next one: `next` sees the world as the
    /// agents before it left it. [`World::resolve`] hands over intents decided on the
    /// step's snapshot (simultaneous steps, DESIGN §2); an in-process trial can decide
    /// each one in turn on the world of the moment (the reference code's sequential
    /// step, REFERENCE §1.8, §9.3). `None` counts as a missing intent.
    pub fn resolve_by<I: std::borrow::Borrow<Intent>>(
        &mut self,
        next: impl FnMut(&World, AgentId) -> Option<I>,
    ) -> StepReport {
        self.resolve_each(next, |_| None)
    }

    fn resolve_each<I: std::borrow::Borrow<Intent>>(
        &mut self,
        mut next: impl FnMut(&World, AgentId) -> Option<I>,
        hint: impl Fn(AgentId) -> Option<MoveHint>,
    ) -> StepReport {
        let mut rep = StepReport { step: self.step, ..Default::default() };
        let mut lt = Vec::new();
        let mut digest = Fnv64::default();
        for id in 0..self.bodies.len() as AgentId {
            if !self.bodies[id as usize].live {
                continue;
            }
            let Some(intent) = next(self, id) else {
                rep.missing_intents += 1;
                continue;
            };
            let intent: &Intent = intent.borrow();
            if intent.agent != id {
                rep.rejected += 1;
                continue;
            }
            match self.apply_hinted(intent, hint(id)) {
                Ok(n) => rep.rejected += n,
                Err(_) => rep.rejected += 1,
            }
            let s = &intent.stats;
            if s.lt_rate > 0 {
                lt.push(s.lt_rate as f64);
            }
            match s.genetic {
                GeneticTrigger::Storage => rep.genetic_steps += 1,
                GeneticTrigger::Stagnation => rep.stagnation_steps += 1,
                GeneticTrigger::None => {}
            }
            rep.genes_lost += s.genes_lost;
            digest.write_word(u64::from(id));
            digest.write_word(s.gene_digest);
        }
        if !lt.is_empty() {
            let n = lt.len() as f64;
            let mean = lt.iter().sum::<f64>() / n;
            let var = lt.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
            rep.lt_mean = round2(mean);
            rep.lt_std = round2(var.sqrt());
        }
        // Word by word: byte-wise FNV over every body was 2 % of a learning run.
        for b in &self.bodies {
            digest.write_word(u64::from(b.id) << 32 | u64::from(b.pos.x as u32));
            digest.write_word(u64::from(b.pos.y as u32) << 32 | b.carrying.len() as u64);
            digest.write_word(b.heading.to_bits());
            for &o in &b.carrying {
                digest.write_word(u64::from(o));
            }
        }
        rep.digest = digest.finish();
        rep.task_pct = self.task_pct();
        // Where everyone stands after acting, before the hooks (crate::locality docs).
        if let Some(l) = self.locality.as_mut() {
            l.record(self.step, &self.bodies);
        }
        self.run_hooks();
        rep.live_agents = self.live_agents();
        self.step += 1;
        rep
    }

    /// Apply one intent; returns how many of its ops were refused. An error refuses the
    /// whole intent.
    pub fn apply(&mut self, intent: &Intent) -> Result<u32, Rejection> {
        self.apply_hinted(intent, None)
    }

    /// [`World::apply`], with the outcome of the intent's first move if known.
    fn apply_hinted(&mut self, intent: &Intent, hint: Option<MoveHint>) -> Result<u32, Rejection> {
        if intent.step != self.step {
            return Err(Rejection::WrongStep { got: intent.step, expected: self.step });
        }
        let id = intent.agent;
        let b = self.bodies.get(id as usize).ok_or(Rejection::NoSuchAgent(id))?;
        if !b.live {
            return Err(Rejection::Dead(id));
        }
        if !intent.heading.is_finite() {
            return Err(Rejection::BadHeading);
        }
        let mut refused = 0;
        // A pick that got the next equivalent item instead of the one the agent saw
        // (another agent took that one this step): the agent's later ops of this tick
        // that name the item it saw mean the item it holds (issue 30). Multi-action
        // trees only: a one-action tree has no op after its pick.
        let mut swapped: Option<(ObjectId, ObjectId)> = None;
        for (k, op) in intent.ops.iter().enumerate() {
            let r = match *op {
                Op::Move { to, heading } => self.apply_move(id, to, heading, hint.filter(|_| k == 0)),
                Op::Pick { object } => self.apply_pick(id, object).map(|got| {
                    if got != object {
                        swapped = Some((object, got));
                    }
                }),
                Op::Drop { object } => {
                    let object = match swapped {
                        Some((saw, got)) if saw == object => got,
                        _ => object,
                    };
                    self.apply_drop(id, object)
                }
            };
            match r {
                Ok(()) => {}
                // A lost race for an item, or a drop the cell refuses, is not
                // misbehaviour: the agent learns the outcome from its next percept.
                Err(Rejection::Blocked) | Err(Rejection::NotHere(_)) => {}
                Err(_) => refused += 1,
            }
        }
        let b = &mut self.bodies[id as usize];
        b.heading = intent.heading.rem_euclid(std::f64::consts::TAU);
        b.class = intent.stats.class;
        Ok(refused)
    }

    /// The objects agent `id` carries.
    fn carried(&self, id: AgentId) -> impl Iterator<Item = &ObjectInfo> {
        self.bodies[id as usize].carrying.iter().map(|&o| &self.objects[o as usize].info)
    }

    fn apply_move(&mut self, id: AgentId, to: Pos, heading: f64, hint: Option<MoveHint>) -> Result<(), Rejection> {
        if !heading.is_finite() {
            return Err(Rejection::BadHeading);
        }
        let from = self.bodies[id as usize].pos;
        let weight = rules::carried_weight(self.carried(id));
        // A hint counts only if it was computed from these very inputs.
        let (dest, new_heading) = match hint {
            Some(h) if h.from == from && h.heading.to_bits() == heading.to_bits() && h.weight == weight => {
                (h.dest, h.new_heading)
            }
            _ => rules::destination(&self.geom, from, heading, weight),
        };
        if dest != to {
            return Err(Rejection::BadMove { to, heading });
        }
        let (old_c, new_c) = (self.geom.cell_of(from), self.geom.cell_of(dest));
        if old_c != new_c && self.cell_blocked(new_c) {
            return Err(Rejection::Blocked);
        }
        if old_c != new_c || AGENT_RADIUS > self.geom.grid() {
            self.deregister_agent(id);
            self.bodies[id as usize].pos = dest;
            self.register_agent(id);
        } else {
            self.bodies[id as usize].pos = dest;
        }
        let b = &mut self.bodies[id as usize];
        b.heading = new_heading;
        for &o in &b.carrying {
            self.objects[o as usize].info.pos = dest;
        }
        Ok(())
    }

    /// Pick `object`, or the next item of its kind in the agent's cell if it is gone
    /// (a race lost this step); returns the item picked.
    fn apply_pick(&mut self, id: AgentId, object: ObjectId) -> Result<ObjectId, Rejection> {
        let o = self.objects.get(object as usize).ok_or(Rejection::NotHere(object))?;
        if !o.info.kind.carryable() {
            return Err(Rejection::NotCarryable(object));
        }
        let kind = o.info.kind;
        let cell = self.geom.cell_of(self.bodies[id as usize].pos);
        let here = &self.cells[cell as usize].objects;
        // Simultaneous steps: agents that saw the same item at the same time all ask for
        // it. The first (lowest id) gets it; later ones get the next equivalent item of
        // the cell, as they would have in the reference's sequential step, where the item
        // was already gone when they looked.
        let object = if here.contains(&object) {
            object
        } else if o.registered {
            return Err(Rejection::OutsideCell(object));
        } else {
            match here.iter().copied().find(|&x| self.objects[x as usize].info.kind == kind) {
                Some(x) => x,
                None => return Err(Rejection::NotHere(object)),
            }
        };
        let o = &self.objects[object as usize];
        if !rules::is_single_carry(self.carried(id), &o.info) {
            return Err(Rejection::NotCarryable(object));
        }
        self.deregister_object(object);
        self.bodies[id as usize].carrying.push(object);
        Ok(object)
    }

    fn apply_drop(&mut self, id: AgentId, object: ObjectId) -> Result<(), Rejection> {
        let b = &self.bodies[id as usize];
        let Some(slot) = b.carrying.iter().position(|&o| o == object) else {
            return Err(Rejection::NotCarried(object));
        };
        let pos = b.pos;
        let cell = self.geom.cell_of(pos);
        let kind = self.objects[object as usize].info.kind;
        // Final (type-aware) drop rules, REFERENCE §2.4.
        let target: Option<ObjectId> = match rules::drop_rule(kind, |k| self.objects_in(cell).any(|o| o.kind == k)) {
            DropOutcome::Refused => return Err(Rejection::Blocked),
            DropOutcome::Into(k) => self.objects_in(cell).find(|o| o.kind == k).map(|o| o.id),
            DropOutcome::Floor => None,
        };
        self.bodies[id as usize].carrying.remove(slot);
        self.objects[object as usize].info.pos = pos;
        match target {
            Some(t) => {
                self.objects[t as usize].dropped.push(object);
                let w = self.objects[object as usize].info.weight;
                if (kind == ObjectKind::Food && self.cfg.task == Task::Foraging)
                    || (kind == ObjectKind::Debris && self.cfg.task == Task::Nest)
                {
                    self.delivered_weight += w;
                }
            }
            None => self.register_object(object),
        }
        Ok(())
    }

    /// Task percentage (REFERENCE §1.7), rounded to 2 decimals.
    pub fn task_pct(&self) -> f64 {
        if self.total_item_weight == 0 {
            return 0.0;
        }
        round2(100.0 * self.delivered_weight as f64 / self.total_item_weight as f64)
    }

    // ---------------------------------------------------------------- perturbations

    /// Schedule `change` to happen right after step `at_step` is resolved (the reference
    /// code's hook timing), so it is in force from step `at_step + 1`. A change scheduled
    /// for step 0 applies at once.
    pub fn schedule(&mut self, at_step: u64, change: Perturbation) {
        if at_step < self.step {
            self.perturb(change);
        } else {
            self.schedule.push((at_step, change));
        }
    }

    fn run_hooks(&mut self) {
        let now = self.step;
        let due: Vec<Perturbation> = {
            let mut due = Vec::new();
            self.schedule.retain(|(t, p)| {
                if *t == now {
                    due.push(p.clone());
                    false
                } else {
                    true
                }
            });
            due
        };
        for p in due {
            self.perturb(p);
        }
    }

    /// Apply a perturbation now. Returns how many of the obstacles it adds could not be
    /// placed (0 for other changes): the obstacle rule found no free place for one, so
    /// it stops there, counts the rest as unplaced ([`World::obstacles_unplaced`]) and
    /// logs a warning. The arena holds only so many obstacles, so this bounds the work
    /// of any count.
    pub fn perturb(&mut self, change: Perturbation) -> u32 {
        let mut unplaced = 0;
        self.events.push((self.step, format!("{change:?}")));
        match change {
            Perturbation::AddObstacleAt { x, y, radius } => {
                if crate::layout::place_obstacle_at(self, Pos::new(x, y), radius).is_none() {
                    unplaced = 1;
                    self.obstacles_unplaced += 1;
                    warn_unplaced(self.step, 1, radius, 1);
                }
            }
            Perturbation::AddObstacles { count, radius } => {
                let mut rng = std::mem::replace(&mut self.perturb_rng, ChaCha8Rng::seed_from_u64(0));
                for placed in 0..count {
                    if crate::layout::place_obstacle(self, &mut rng, radius).is_none() {
                        unplaced = count - placed;
                        break;
                    }
                }
                self.perturb_rng = rng;
                if unplaced > 0 {
                    self.obstacles_unplaced += u64::from(unplaced);
                    warn_unplaced(self.step, count, radius, unplaced);
                }
            }
            Perturbation::SetIp(ip) => self.regime.ip = ip.clamp(0.0, 1.0),
            Perturbation::SetLateralTransfer(on) => self.regime.lateral_transfer = on,
            Perturbation::SetGeneLoss(p) => self.regime.gene_loss = p.clamp(0.0, 1.0),
            Perturbation::SwitchTask(task) => self.switch_task(task),
            Perturbation::KillFraction(f) => {
                let mut live: Vec<AgentId> = self.bodies.iter().filter(|b| b.live).map(|b| b.id).collect();
                let k = ((f.clamp(0.0, 1.0) * live.len() as f64).floor()) as usize;
                for i in 0..k {
                    let j = self.perturb_rng.random_range(i..live.len());
                    live.swap(i, j);
                }
                for &id in &live[..k] {
                    self.kill(id);
                }
            }
        }
        unplaced
    }

    /// The task in force, changed by [`Perturbation::SwitchTask`].
    pub fn task(&self) -> Task {
        self.cfg.task
    }

    /// The task that will be in force after step `at` is resolved, given the switches
    /// scheduled so far (the world's own view of its future, so that a switch asked for
    /// on the control plane can be checked against the switches before it).
    pub fn task_after(&self, at: u64) -> Task {
        let mut switches: Vec<(u64, Task)> = self
            .schedule
            .iter()
            .filter_map(|(t, p)| match p {
                Perturbation::SwitchTask(k) if *t <= at => Some((*t, *k)),
                _ => None,
            })
            .collect();
        switches.sort_by_key(|&(t, _)| t);
        switches.last().map_or(self.cfg.task, |&(_, k)| k)
    }

    /// Turn the world to `task` (issue 30.4): every item and place of the old task
    /// leaves the grid and the agents' hands, the new task's are laid out as a fresh
    /// world of that task has them (REFERENCE §1.4; drawn from the perturbation stream),
    /// and the task % starts from 0 over the new items. Hub, obstacles and agents stay.
    /// A switch to the task already in force changes nothing and says so: the
    /// configuration and the control plane refuse one before it gets here.
    fn switch_task(&mut self, task: Task) {
        if task == self.cfg.task {
            tracing::warn!(step = self.step, "SwitchTask to {task}: the world already runs it; nothing changes");
            return;
        }
        let old = self.cfg.task.objects();
        let gone: Vec<ObjectId> =
            self.objects.iter().filter(|o| old.contains(&o.info.kind)).map(|o| o.info.id).collect();
        for &id in &gone {
            if self.objects[id as usize].registered {
                self.deregister_object(id);
            }
        }
        // `gone` is in id order (objects are stored by id): a binary search per look-up.
        let is_gone = |id: &ObjectId| gone.binary_search(id).is_ok();
        for b in &mut self.bodies {
            b.carrying.retain(|o| !is_gone(o));
        }
        for o in &mut self.objects {
            o.dropped.retain(|d| !is_gone(d));
        }
        self.cfg.task = task;
        self.total_item_weight = 0;
        self.delivered_weight = 0;
        let hub = self.hub().pos;
        let mut rng = std::mem::replace(&mut self.perturb_rng, ChaCha8Rng::seed_from_u64(0));
        if let Err(e) = crate::layout::place_task(self, &mut rng, task, hub) {
            // Only the paper layout's ring rule can fail (every place at its distance
            // taken, by obstacles added since): the task runs with what was placed.
            tracing::warn!(step = self.step, "SwitchTask to {task}: {e}");
        }
        self.perturb_rng = rng;
    }

    /// Mark an agent dead: its body idles and whatever it carried is dropped where it
    /// stands (re-registered in the grid).
    pub fn kill(&mut self, id: AgentId) {
        let Some(b) = self.bodies.get_mut(id as usize) else { return };
        if !b.live {
            return;
        }
        b.live = false;
        let pos = b.pos;
        let carried = std::mem::take(&mut b.carrying);
        for o in carried {
            self.objects[o as usize].info.pos = pos;
            self.register_object(o);
        }
    }

    /// Put an agent's body somewhere (scenario set-up and tests).
    pub fn place_agent(&mut self, id: AgentId, pos: Pos, heading: f64) {
        if (id as usize) < self.bodies.len() && self.geom.contains(pos) {
            self.deregister_agent(id);
            self.bodies[id as usize].pos = pos;
            self.bodies[id as usize].heading = heading;
            self.register_agent(id);
        }
    }

    /// Bring a dead agent back (a restarted process with the same id).
    pub fn revive(&mut self, id: AgentId) {
        if let Some(b) = self.bodies.get_mut(id as usize) {
            b.live = true;
        }
    }
}

/// Report obstacles a perturbation could not place, in every build.
fn warn_unplaced(step: u64, count: u32, radius: i32, unplaced: u32) {
    tracing::warn!(step, count, radius, unplaced, "no free place for an obstacle: {unplaced} of {count} not placed");
}

pub fn round2(v: f64) -> f64 {
    (v * 100.0).round() / 100.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Layout, Start};
    use geese_proto::AgentStats;

    fn world(task: Task, agents: u32) -> World {
        let cfg = WorldConfig { task, agents, items: Some(100), start: Some(Start::Hub), ..Default::default() };
        World::new(cfg, 7).unwrap()
    }

    fn intent(w: &World, agent: AgentId, heading: f64, ops: Vec<Op>) -> Intent {
        Intent { step: w.step(), agent, heading, ops, stats: AgentStats::default() }
    }

    /// The live viewer's click: an obstacle at a point is in the next percepts of its
    /// cell, logged as an event; one that would cover the hub or another obstacle is
    /// refused and counted unplaced.
    #[test]
    fn an_obstacle_added_at_a_point_is_in_the_next_percepts() {
        let mut w = world(Task::Foraging, 5);
        let p = Pos::new(-25, 25);
        let cell = w.geometry().cell_of(p);
        let obstacles =
            |w: &World| w.percept(cell).objects.iter().any(|o| o.kind == ObjectKind::Obstacles && o.pos == p);
        assert!(!obstacles(&w));
        assert_eq!(w.perturb(Perturbation::AddObstacleAt { x: -25, y: 25, radius: 10 }), 0);
        assert!(obstacles(&w));
        assert_eq!(w.events().len(), 1);
        assert!(w.events()[0].1.starts_with("AddObstacleAt"));
        assert_eq!(w.perturb(Perturbation::AddObstacleAt { x: -24, y: 25, radius: 10 }), 1, "on top of the first");
        assert_eq!(w.perturb(Perturbation::AddObstacleAt { x: 0, y: 0, radius: 10 }), 1, "on the hub");
        assert_eq!(w.obstacles_unplaced(), 2);
    }

    /// `resolve_by` asks for each agent's intent only after applying the intents before
    /// it: agent 1 sees agent 0 where agent 0 went this step (the reference's sequential
    /// step, REFERENCE §1.8).
    #[test]
    fn resolve_by_shows_each_agent_the_world_the_agents_before_it_left() {
        let mut w = world(Task::Foraging, 2);
        let start = w.bodies()[0].pos;
        let (to, _) = rules::destination(&w.geometry(), start, 0.0, 0);
        assert_ne!(to, start);
        let mut seen = None;
        let rep = w.resolve_by(|w, id| {
            if id == 1 {
                seen = Some(w.bodies()[0].pos);
            }
            let ops = if id == 0 { vec![Op::Move { to, heading: 0.0 }] } else { Vec::new() };
            Some(intent(w, id, 0.0, ops))
        });
        assert_eq!(seen, Some(to));
        assert_eq!((rep.rejected, rep.missing_intents), (0, 0));
        // An agent that gives no intent idles and is counted.
        let rep = w.resolve_by(|_, _| None::<Intent>);
        assert_eq!(rep.missing_intents, 2);
    }

    #[test]
    fn reference_foraging_layout() {
        let w = World::new(WorldConfig::default(), 1).unwrap();
        let g = w.geometry();
        assert_eq!(w.hub().pos, Pos::new(0, 0));
        let site_cell = g.cell_of(Pos::new(30, 30));
        let food = w.objects_in(site_cell).filter(|o| o.kind == ObjectKind::Food).count();
        assert_eq!(food, 100);
        assert_eq!(w.bodies().len(), 100);
        assert!(w.bodies().iter().all(|b| b.pos.x >= -50 && b.pos.x < 50 && b.pos.y >= -50 && b.pos.y < 50));
        assert_eq!(w.task_pct(), 0.0);
    }

    #[test]
    fn paper_layout_sites_at_distance_30_and_nest_boundaries() {
        let cfg = WorldConfig { layout: Layout::Paper, sites: 3, ..Default::default() };
        let w = World::new(cfg, 3).unwrap();
        let sites: Vec<_> = w.objects().filter(|o| o.info.kind == ObjectKind::Sites).collect();
        assert_eq!(sites.len(), 3);
        for s in &sites {
            let d = ((s.info.pos.x.pow(2) + s.info.pos.y.pow(2)) as f64).sqrt();
            assert!((28.0..=30.0).contains(&d), "site at {:?}", s.info.pos);
        }
        assert!(w.bodies().iter().all(|b| b.pos == Pos::new(0, 0)));
        let n = World::new(WorldConfig { task: Task::Nest, ..Default::default() }, 3).unwrap();
        assert_eq!(n.objects().filter(|o| o.info.kind == ObjectKind::Boundary).count(), 5);
        assert_eq!(n.objects_in(55).filter(|o| o.kind == ObjectKind::Debris).count(), 100);
    }

    #[test]
    fn the_locality_world_has_its_four_fixed_obstacles() {
        // REFERENCE §1.4: hub (0,0), site (−30,30), obstacles at (−30,−30), (30,−30),
        // (30,30), (−15,0), agents at the hub.
        let at = [Pos::new(-30, -30), Pos::new(30, -30), Pos::new(30, 30), Pos::new(-15, 0)];
        let cfg = WorldConfig {
            site: Pos::new(-30, 30),
            fixed_obstacles: at.to_vec(),
            start: Some(Start::Hub),
            ..Default::default()
        };
        let w = World::new(cfg.clone(), 1).unwrap();
        let obs: Vec<Pos> = w.objects().filter(|o| o.info.kind == ObjectKind::Obstacles).map(|o| o.info.pos).collect();
        assert_eq!(obs, at);
        assert!(w.objects().any(|o| o.info.kind == ObjectKind::Sites && o.info.pos == Pos::new(-30, 30)));
        assert!(w.bodies().iter().all(|b| b.pos == Pos::new(0, 0)));
        // An obstacle on the hub or under the site, or two in one cell, is refused by name.
        for (bad, field) in [
            (vec![Pos::new(3, 3)], "fixed_obstacles"),
            (vec![Pos::new(-25, 35)], "site"),
            (vec![Pos::new(30, -30), Pos::new(31, -29)], "fixed_obstacles"),
        ] {
            let e = World::new(WorldConfig { fixed_obstacles: bad, ..cfg.clone() }, 1).err().expect("refused");
            assert!(e.to_string().starts_with(&format!("world.{field}: ")), "{e}");
        }
    }

    #[test]
    fn same_seed_same_world_different_seed_different_world() {
        let a = World::new(WorldConfig::default(), 5).unwrap();
        let b = World::new(WorldConfig::default(), 5).unwrap();
        let c = World::new(WorldConfig::default(), 6).unwrap();
        let pos = |w: &World| w.bodies().iter().map(|b| b.pos).collect::<Vec<_>>();
        assert_eq!(pos(&a), pos(&b));
        assert_ne!(pos(&a), pos(&c));
    }

    #[test]
    fn moves_are_validated_and_applied() {
        let mut w = world(Task::Foraging, 2);
        w.place_agent(0, Pos::new(0, 0), 0.0);
        let ok = intent(&w, 0, 0.0, vec![Op::Move { to: Pos::new(2, 0), heading: 0.0 }]);
        let teleport = intent(&w, 1, 0.0, vec![Op::Move { to: Pos::new(20, 0), heading: 0.0 }]);
        let rep = w.resolve(&[Some(ok), Some(teleport)]);
        assert_eq!(rep.rejected, 1);
        assert_eq!(w.bodies()[0].pos, Pos::new(2, 0));
        assert_eq!(w.bodies()[1].pos, Pos::new(0, 0));
    }

    /// Occupied cells come out ascending and each once, whether read off the map of
    /// the arena's cells (many agents) or sorted (few), dead bodies (`None`) left out.
    #[test]
    fn occupied_cells_are_ascending_and_unique_either_way() {
        let w = world(Task::Foraging, 1);
        let count = w.geometry().cell_count() as CellIdx;
        let (mut seen, mut out) = (Vec::new(), Vec::new());
        let few = [Some(7), None, Some(3), Some(7)];
        w.occupied_cells_into(few, &mut seen, &mut out);
        assert_eq!(out, [3, 7]);
        let many: Vec<Option<CellIdx>> = (0..count).rev().map(|c| (c % 3 != 0).then_some(c / 2)).collect();
        w.occupied_cells_into(many.iter().copied(), &mut seen, &mut out);
        let mut want: Vec<CellIdx> = many.iter().flatten().copied().collect();
        want.sort_unstable();
        want.dedup();
        assert_eq!(out, want);
    }

    /// A hint is what applying the move computes: resolving with hints gives what
    /// resolving without them gives; a hint only counts for the inputs it was computed
    /// from (here another agent's, whose body stands elsewhere), and only for a first op.
    #[test]
    fn move_hints_change_nothing_and_count_only_for_their_inputs() {
        let setup = || {
            let mut w = world(Task::Foraging, 3);
            w.place_agent(0, Pos::new(0, 0), 0.0);
            w.place_agent(1, Pos::new(10, 4), 0.0);
            w.place_agent(2, Pos::new(-6, 7), 0.0);
            w
        };
        let (mut a, mut b) = (setup(), setup());
        let intents: Vec<Option<Intent>> = [(0, 0.3), (1, 2.0), (2, 4.4)]
            .iter()
            .map(|&(id, h)| {
                let body = &a.bodies()[id as usize];
                let (to, _) = rules::destination(&a.geometry(), body.pos, h, 0);
                let (twice, _) = rules::destination(&a.geometry(), to, h, 0);
                Some(intent(&a, id, h, vec![Op::Move { to, heading: h }, Op::Move { to: twice, heading: h }]))
            })
            .collect();
        let hints: Vec<Option<MoveHint>> = intents.iter().map(|i| i.as_ref().and_then(|i| b.move_hint(i))).collect();
        assert!(hints.iter().all(Option::is_some));
        let plain = a.resolve(&intents);
        let hinted = b.resolve_hinted(&intents, &hints);
        assert_eq!(plain, hinted);
        assert_eq!(plain.rejected, 0);
        let pos = |w: &World| w.bodies().iter().map(|b| (b.pos, b.heading.to_bits())).collect::<Vec<_>>();
        assert_eq!(pos(&a), pos(&b));
        // Agent 1's hint handed to agent 0 (other inputs) is ignored: the move is valid.
        let (mut c, mut d) = (setup(), setup());
        let mine = intents[0].clone();
        let swapped = [hints[1], None, None];
        assert_eq!(c.resolve(std::slice::from_ref(&mine)), d.resolve_hinted(&[mine], &swapped));
        assert_eq!(pos(&c), pos(&d));
    }

    #[test]
    fn obstacles_block_entry_not_exit() {
        let mut w = world(Task::Foraging, 1);
        w.perturb(Perturbation::AddObstacles { count: 1, radius: 10 });
        let obs = w.objects().find(|o| o.info.kind == ObjectKind::Obstacles).unwrap().info;
        let g = w.geometry();
        let (x0, y0, _, _) = g.neighbourhood_box(obs.pos, obs.radius);
        // Stand just left of the obstacle's cell, facing it.
        w.place_agent(0, Pos::new(x0 - 1, y0 + 5), 0.0);
        let to = Pos::new(x0 + 1, y0 + 5);
        let i = intent(&w, 0, 0.0, vec![Op::Move { to, heading: 0.0 }]);
        w.resolve(&[Some(i)]);
        assert_eq!(w.bodies()[0].pos, Pos::new(x0 - 1, y0 + 5));
    }

    #[test]
    fn pick_drop_at_hub_counts_and_races_resolve_by_id() {
        let mut w = world(Task::Foraging, 3);
        let site = Pos::new(30, 30);
        let food = w.objects_in(w.geometry().cell_of(site)).find(|o| o.kind == ObjectKind::Food).unwrap().id;
        for id in 0..3 {
            w.place_agent(id, site, 0.0);
        }
        // All three ask for the same item: each gets one.
        let picks: Vec<_> = (0..3).map(|id| Some(intent(&w, id, 0.0, vec![Op::Pick { object: food }]))).collect();
        w.resolve(&picks);
        assert!(w.bodies().iter().all(|b| b.carrying.len() == 1));
        assert_eq!(w.bodies()[0].carrying[0], food);
        // A second pick while carrying is refused (IsSingleCarry).
        let again = intent(&w, 0, 0.0, vec![Op::Pick { object: food + 5 }]);
        let rep = w.resolve(&[Some(again), None, None]);
        assert_eq!(w.bodies()[0].carrying.len(), 1);
        assert_eq!(rep.missing_intents, 2);
        // Carry to the hub and drop: 1 %.
        w.place_agent(0, Pos::new(1, 1), 0.0);
        let carried = w.bodies()[0].carrying[0];
        let d = intent(&w, 0, 0.0, vec![Op::Drop { object: carried }]);
        let rep = w.resolve(&[Some(d), None, None]);
        assert_eq!(rep.task_pct, 1.0);
        assert!(w.bodies()[0].carrying.is_empty());
    }

    /// Issue 30: an agent that saw item f, lost it to a lower id and got the next item g
    /// instead, and then drops "f" in the same tick (a multi-action tree: pick, then
    /// drop) drops g, as it would have in the reference's sequential step, where it
    /// would have seen and picked g in the first place. Before, the drop was refused
    /// (`NotCarried`) and the agent kept g.
    #[test]
    fn a_later_drop_of_a_lost_item_drops_the_item_picked_instead() {
        let mut w = world(Task::Foraging, 2);
        let site = Pos::new(30, 30);
        let cell = w.geometry().cell_of(site);
        let food = w.objects_in(cell).find(|o| o.kind == ObjectKind::Food).unwrap().id;
        for id in 0..2 {
            w.place_agent(id, site, 0.0);
        }
        let keep = intent(&w, 0, 0.0, vec![Op::Pick { object: food }]);
        let pick_drop = intent(&w, 1, 0.0, vec![Op::Pick { object: food }, Op::Drop { object: food }]);
        let before = w.objects_in(cell).filter(|o| o.kind == ObjectKind::Food).count();
        let rep = w.resolve(&[Some(keep), Some(pick_drop)]);
        assert_eq!(rep.rejected, 0);
        assert_eq!(w.bodies()[0].carrying, vec![food]);
        assert!(w.bodies()[1].carrying.is_empty(), "agent 1 dropped the item it held");
        assert_eq!(w.objects_in(cell).filter(|o| o.kind == ObjectKind::Food).count(), before - 1);
    }

    #[test]
    fn pick_outside_cell_and_acting_for_others_are_rejected() {
        let mut w = world(Task::Foraging, 2);
        let site = Pos::new(30, 30);
        let food = w.objects_in(w.geometry().cell_of(site)).find(|o| o.kind == ObjectKind::Food).unwrap().id;
        let far = intent(&w, 0, 0.0, vec![Op::Pick { object: food }]);
        let mut impostor = intent(&w, 0, 0.0, vec![]);
        impostor.agent = 0; // sent in agent 1's slot
        let rep = w.resolve(&[Some(far), Some(impostor)]);
        assert_eq!(rep.rejected, 2);
        assert!(w.bodies()[0].carrying.is_empty());
    }

    fn registered(w: &World, kind: ObjectKind) -> usize {
        w.objects().filter(|o| o.registered && o.info.kind == kind).count()
    }

    /// Issue 30.4: a switch scheduled after step 2 takes the food and the site away
    /// (from the floor, the hub and the agents' hands), lays out debris at the hub and
    /// five boundaries, and the task % counts debris from 0; percepts show the new world
    /// only. A switch back brings food and the site again; one to the running task
    /// changes nothing.
    #[test]
    fn a_task_switch_replaces_items_and_places_and_restarts_the_task_pct() {
        let mut w = world(Task::Foraging, 2);
        let site = Pos::new(30, 30);
        let food = w.objects_in(w.geometry().cell_of(site)).find(|o| o.kind == ObjectKind::Food).unwrap().id;
        w.place_agent(0, site, 0.0);
        w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Pick { object: food }])), None]);
        w.place_agent(0, Pos::new(1, 1), 0.0);
        let rep = w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Drop { object: food }])), None]);
        assert_eq!(rep.task_pct, 1.0);
        let food2 = w.objects_in(w.geometry().cell_of(site)).find(|o| o.kind == ObjectKind::Food).unwrap().id;
        w.place_agent(1, site, 0.0);
        w.schedule(3, Perturbation::SwitchTask(Task::Nest));
        assert_eq!(w.task_after(2), Task::Foraging);
        assert_eq!(w.task_after(3), Task::Nest);
        let rep = w.resolve(&[None, Some(intent(&w, 1, 0.0, vec![Op::Pick { object: food2 }]))]);
        assert_eq!(rep.step, 3);
        // The switch came right after step 3: agent 1's food is gone with the rest.
        assert_eq!(w.task(), Task::Nest);
        assert!(w.bodies()[1].carrying.is_empty());
        assert_eq!((registered(&w, ObjectKind::Food), registered(&w, ObjectKind::Sites)), (0, 0));
        assert_eq!((registered(&w, ObjectKind::Debris), registered(&w, ObjectKind::Boundary)), (100, 5));
        assert_eq!(w.task_pct(), 0.0);
        assert!(w.percepts().iter().all(|p| p.objects.iter().all(|o| !Task::Foraging.objects().contains(&o.kind))));
        assert_eq!(w.events().last().map(|e| e.0), Some(3), "logged for the viewer's marker at the step it followed");
        // Debris into a boundary counts for the new task.
        let debris =
            w.objects_in(w.geometry().cell_of(Pos::new(0, 0))).find(|o| o.kind == ObjectKind::Debris).unwrap().id;
        w.place_agent(0, Pos::new(0, 0), 0.0);
        w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Pick { object: debris }])), None]);
        let b = w.objects().find(|o| o.registered && o.info.kind == ObjectKind::Boundary).unwrap().info.pos;
        w.place_agent(0, b, 0.0);
        let rep = w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Drop { object: debris }])), None]);
        assert_eq!(rep.task_pct, 1.0);
        // Back to foraging: the site and 100 food at it, nothing of the nest left.
        w.perturb(Perturbation::SwitchTask(Task::Foraging));
        assert_eq!((registered(&w, ObjectKind::Debris), registered(&w, ObjectKind::Boundary)), (0, 0));
        assert_eq!((registered(&w, ObjectKind::Food), registered(&w, ObjectKind::Sites)), (100, 1));
        assert_eq!(w.objects_in(w.geometry().cell_of(site)).filter(|o| o.kind == ObjectKind::Food).count(), 100);
        assert_eq!(w.task_pct(), 0.0);
        // The same task again: nothing changes.
        let before = w.objects().count();
        w.perturb(Perturbation::SwitchTask(Task::Foraging));
        assert_eq!((w.objects().count(), registered(&w, ObjectKind::Food)), (before, 100));
    }

    #[test]
    fn nest_debris_counts_only_in_boundary() {
        let mut w = world(Task::Nest, 1);
        let debris = w.objects_in(55).find(|o| o.kind == ObjectKind::Debris).unwrap().id;
        w.place_agent(0, Pos::new(0, 0), 0.0);
        w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Pick { object: debris }]))]);
        // Dropping at the hub is refused, elsewhere it stays on the floor.
        w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Drop { object: debris }]))]);
        assert_eq!(w.bodies()[0].carrying.len(), 1);
        let b = w.objects().find(|o| o.info.kind == ObjectKind::Boundary).unwrap().info.pos;
        w.place_agent(0, b, 0.0);
        let rep = w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Drop { object: debris }]))]);
        assert_eq!(rep.task_pct, 1.0);
    }

    #[test]
    fn percepts_cover_live_agents_and_nearby_obstacles() {
        let mut w = world(Task::Foraging, 4);
        w.perturb(Perturbation::AddObstacles { count: 3, radius: 10 });
        let ps = w.percepts();
        assert_eq!(ps.len(), 1); // everyone at the hub
        assert_eq!(ps[0].agents.len(), 4);
        assert!(ps[0].objects.iter().any(|o| o.kind == ObjectKind::Hub));
        w.kill(2);
        assert_eq!(w.live_agents(), 3);
        let rep = w.resolve(&[None, None, None, None]);
        assert_eq!(rep.missing_intents, 3);
    }

    #[test]
    fn kill_drops_carried_items_where_the_agent_stands() {
        let mut w = world(Task::Foraging, 1);
        let site = Pos::new(30, 30);
        let cell = w.geometry().cell_of(site);
        let food = w.objects_in(cell).find(|o| o.kind == ObjectKind::Food).unwrap().id;
        w.place_agent(0, site, 0.0);
        w.resolve(&[Some(intent(&w, 0, 0.0, vec![Op::Pick { object: food }]))]);
        w.place_agent(0, Pos::new(-20, -20), 0.0);
        w.kill(0);
        let here = w.geometry().cell_of(Pos::new(-20, -20));
        assert!(w.objects_in(here).any(|o| o.id == food));
    }

    #[test]
    fn unplaceable_obstacles_are_counted_and_the_work_is_bounded() {
        // The 100 × 100 arena has 5 distances × 36 angles for obstacles: a count of
        // u32::MAX used to retry 10,000 times per obstacle, for ever.
        let mut w = world(Task::Foraging, 1);
        let t = std::time::Instant::now();
        let unplaced = w.perturb(Perturbation::AddObstacles { count: u32::MAX, radius: 10 });
        let placed = w.objects().filter(|o| o.info.kind == ObjectKind::Obstacles).count() as u32;
        assert!(placed > 0 && placed < 180, "{placed}");
        assert_eq!(unplaced, u32::MAX - placed);
        assert_eq!(w.obstacles_unplaced(), u64::from(unplaced));
        assert!(t.elapsed() < std::time::Duration::from_secs(5), "{:?}", t.elapsed());
        // Another change counts on; other perturbations place nothing.
        assert_eq!(w.perturb(Perturbation::AddObstacles { count: 2, radius: 10 }), 2);
        assert_eq!(w.obstacles_unplaced(), u64::from(unplaced) + 2);
        assert_eq!(w.perturb(Perturbation::SetIp(0.5)), 0);
        // A radius covering the hub's cell can never be placed, and costs no scan.
        let mut w = world(Task::Foraging, 1);
        assert_eq!(w.perturb(Perturbation::AddObstacles { count: 3, radius: 1_000 }), 3);
        assert_eq!(w.perturb(Perturbation::AddObstacles { count: 1, radius: i32::MAX }), 1);
        assert_eq!(w.obstacles_unplaced(), 4);
        // Fine where there is room: nothing unplaced.
        let mut w = world(Task::Foraging, 1);
        assert_eq!(w.perturb(Perturbation::AddObstacles { count: 5, radius: 10 }), 0);
        assert_eq!(w.obstacles_unplaced(), 0);
    }

    #[test]
    fn obstacle_placement_matches_the_plain_rule() {
        // The plain rule of REFERENCE §1.4 (draw until free, at most 10,000 draws):
        // the bounded rule must place the same obstacles from the same stream.
        fn plain(w: &mut World, rng: &mut ChaCha8Rng, radius: i32) -> Option<ObjectId> {
            let half = w.geometry().half_w().min(w.geometry().half_h());
            let steps = ((half - 25) + 4) / 5;
            for _ in 0..10_000 {
                let d = 25 + 5 * rng.random_range(0..steps);
                let theta = std::f64::consts::TAU * rng.random_range(0..36u32) as f64 / 35.0;
                let p = Pos::new((d as f64 * theta.cos()).trunc() as i32, (d as f64 * theta.sin()).trunc() as i32);
                if !w.area_has_objects(p, radius) {
                    return Some(w.add_object(ObjectKind::Obstacles, p, radius));
                }
            }
            None
        }
        for (size, grid, radius) in [(100, 10, 10), (100, 2, 5), (200, 10, 25), (100, 10, 3)] {
            let cfg = WorldConfig { width: size, height: size, grid, agents: 1, ..Default::default() };
            let (mut a, mut b) = (World::new(cfg.clone(), 1).unwrap(), World::new(cfg, 1).unwrap());
            let (mut ra, mut rb) = (ChaCha8Rng::seed_from_u64(9), ChaCha8Rng::seed_from_u64(9));
            for _ in 0..40 {
                let x = crate::layout::place_obstacle(&mut a, &mut ra, radius);
                let y = plain(&mut b, &mut rb, radius);
                assert_eq!(x, y, "{size}/{grid}/{radius}");
                if x.is_none() {
                    break;
                }
            }
            let pos = |w: &World| w.objects().map(|o| o.info.pos).collect::<Vec<_>>();
            assert_eq!(pos(&a), pos(&b));
        }
    }

    #[test]
    fn the_locality_map_counts_live_agents_after_each_step_before_its_hooks() {
        let mut w = world(Task::Foraging, 4);
        assert!(w.locality().is_none());
        w.record_locality("2:3".parse().expect("window"));
        // Half the agents die right after step 2: they count at step 2, not at 3.
        w.schedule(2, Perturbation::KillFraction(0.5));
        let mut mover = intent(&w, 0, 0.0, vec![Op::Move { to: Pos::new(2, 0), heading: 0.0 }]);
        mover.stats.class = BehaviourClass::MoveTowards;
        w.resolve(&[Some(mover), None, None, None]);
        for _ in 2..=4 {
            w.resolve(&[None, None, None, None]);
        }
        let l = w.locality().expect("recording");
        assert_eq!((l.steps(), l.agent_steps()), (2, 4 + 2));
        // Agent 0 stands where its step-1 intent took it, under the class it reported
        // (missing intents since); the others never reported a class.
        for c in l.counts() {
            assert!(matches!((c.x, c.y, c.class), (2, 0, 4) | (0, 0, 0)), "{c:?}");
        }
    }

    #[test]
    fn scheduled_perturbations_fire_after_their_step() {
        let mut w = world(Task::Foraging, 1);
        w.schedule(2, Perturbation::SetLateralTransfer(false));
        w.resolve(&[None]);
        assert!(w.regime().lateral_transfer);
        w.resolve(&[None]);
        assert!(!w.regime().lateral_transfer);
    }
}
