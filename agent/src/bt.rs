//! Behaviour-tree engine with py_trees 2.1.6 semantics (REFERENCE.md §2.1).
//!
//! Nodes live in an arena in pre-order, so a node's subtree is the contiguous range
//! `i..end[i]` and "reset the whole subtree" is a slice fill. Statuses persist between
//! ticks exactly as in py_trees, including the stale statuses a Selector leaves behind
//! when its first child succeeds — fitness reads them (§6.5).
//!
//! `render` draws a tree as text, a Graphviz digraph or an SVG picture ([`TreeFormat`]).
use crate::ge::{CompositeKind, PNode};
use crate::leaves::{Leaf, LeafError, LeafSpec};
use crate::view::View;
use geese_proto::BehaviourClass;
use rand::Rng;
use std::fmt::Write;
use std::sync::Arc;

mod render;
pub use render::TreeFormat;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Status {
    Invalid,
    Success,
    Failure,
}

/// Grammar tag a leaf came from; fitness and GeneDict rules select nodes by it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Tag {
    PostCnd,
    PreCnd,
    Cnstr,
    Act,
    Other(String),
}

impl Tag {
    fn from_str(s: &str) -> Tag {
        match s {
            "PostCnd" => Tag::PostCnd,
            "PreCnd" => Tag::PreCnd,
            "Cnstr" => Tag::Cnstr,
            "Act" | "act" => Tag::Act,
            other => Tag::Other(other.to_string()),
        }
    }
    fn label(&self) -> &str {
        match self {
            Tag::PostCnd => "PostCnd",
            Tag::PreCnd => "PreCnd",
            Tag::Cnstr => "Cnstr",
            Tag::Act => "Act",
            Tag::Other(s) => s,
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum Kind {
    Sequence,
    Selector,
    Parallel,
    Inverter,
    Leaf(Leaf, Tag),
}

impl Kind {
    /// How the text rendering and the pictures name a node: the composite kind, or the
    /// leaf's name and the grammar tag it came from.
    fn label(&self) -> String {
        match self {
            Kind::Sequence => "Sequence".into(),
            Kind::Selector => "Selector".into(),
            Kind::Parallel => "Parallel".into(),
            Kind::Inverter => "Inverter".into(),
            Kind::Leaf(l, t) => format!("{} ({})", l.name(), t.label()),
        }
    }
}

#[derive(Clone, Debug)]
struct Node {
    kind: Kind,
    /// Children indices (for Inverter: exactly one).
    children: Vec<u32>,
    /// One past the last node of this subtree.
    end: u32,
}

/// Why a phenotype cannot become a tree.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum BuildError {
    #[error(transparent)]
    Leaf(#[from] LeafError),
    #[error("composite node has no children where one is required")]
    Empty,
    #[error("phenotype does not parse: {0}")]
    Parse(String),
    #[error("{0}")]
    Program(String),
}

/// A behaviour tree plus its node statuses.
#[derive(Clone, Debug)]
pub struct Bt {
    /// The shape, fixed once built (and shared by the copies of one gene's tree).
    nodes: Arc<[Node]>,
    /// The Selector nodes, for the fitness's count of successful ones every tick
    /// (scanning every node for them was ~0.7 % of a learning run); shared likewise.
    selectors: Arc<[u32]>,
    status: Vec<Status>,
}

fn push(nodes: &mut Vec<Node>, kind: Kind) -> u32 {
    nodes.push(Node { kind, children: Vec::new(), end: 0 });
    (nodes.len() - 1) as u32
}

/// Append the nodes of `p` (depth first, a subtree's nodes contiguous); returns its root.
fn add(nodes: &mut Vec<Node>, p: &PNode) -> Result<u32, BuildError> {
    let i = match p {
        PNode::Composite { kind, children } => {
            let k = match kind {
                CompositeKind::Sequence => Kind::Sequence,
                CompositeKind::Selector => Kind::Selector,
                CompositeKind::Parallel => Kind::Parallel,
            };
            let i = push(nodes, k);
            for c in children {
                let ci = add(nodes, c)?;
                nodes[i as usize].children.push(ci);
            }
            i
        }
        PNode::Leaf { text, tag } => {
            let spec = LeafSpec::parse(text.trim())?;
            let leaf = Kind::Leaf(spec.leaf, Tag::from_str(tag));
            if spec.invert {
                let i = push(nodes, Kind::Inverter);
                let c = push(nodes, leaf);
                nodes[c as usize].end = c + 1;
                nodes[i as usize].children.push(c);
                i
            } else {
                push(nodes, leaf)
            }
        }
    };
    nodes[i as usize].end = nodes.len() as u32;
    Ok(i)
}

impl Bt {
    /// Build from a parsed phenotype tree (the construction rule of §4.3 is applied by
    /// the phenotype parser). Leaf texts follow §4.2.
    pub fn from_pnode(root: &PNode) -> Result<Bt, BuildError> {
        let mut nodes = Vec::new();
        add(&mut nodes, root)?;
        Ok(Bt::of(nodes))
    }

    /// A tree of these nodes, every status fresh.
    fn of(nodes: Vec<Node>) -> Bt {
        let selectors = (0..nodes.len() as u32).filter(|&i| nodes[i as usize].kind == Kind::Selector).collect();
        Bt { status: vec![Status::Invalid; nodes.len()], nodes: nodes.into(), selectors }
    }

    /// Compose several trees under one Parallel root (the fixed-agent "Parallel
    /// strategy", REFERENCE §6.8).
    pub fn parallel(trees: &[Bt]) -> Bt {
        let mut nodes = vec![Node { kind: Kind::Parallel, children: Vec::new(), end: 0 }];
        for t in trees {
            let off = nodes.len() as u32;
            nodes[0].children.push(off);
            for n in t.nodes.iter() {
                nodes.push(Node {
                    kind: n.kind.clone(),
                    children: n.children.iter().map(|c| c + off).collect(),
                    end: n.end + off,
                });
            }
        }
        nodes[0].end = nodes.len() as u32;
        Bt::of(nodes)
    }

    /// The same tree with every status fresh, as [`Bt::from_pnode`] builds it; the
    /// nodes are shared.
    pub fn fresh(&self) -> Bt {
        Bt {
            nodes: self.nodes.clone(),
            selectors: self.selectors.clone(),
            status: vec![Status::Invalid; self.nodes.len()],
        }
    }

    pub fn len(&self) -> usize {
        self.nodes.len()
    }
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Tick the root once.
    pub fn tick<R: Rng>(&mut self, view: &mut View, rng: &mut R) -> Status {
        if self.nodes.is_empty() {
            return Status::Failure;
        }
        self.tick_node(0, view, rng)
    }

    fn reset(&mut self, i: u32) {
        let end = self.nodes[i as usize].end as usize;
        self.status[i as usize..end].fill(Status::Invalid);
    }

    fn tick_node<R: Rng>(&mut self, i: u32, view: &mut View, rng: &mut R) -> Status {
        let iu = i as usize;
        let st = match &self.nodes[iu].kind {
            Kind::Leaf(leaf, _) => {
                if leaf.tick(view, rng) {
                    Status::Success
                } else {
                    Status::Failure
                }
            }
            Kind::Inverter => {
                let c = self.nodes[iu].children[0];
                match self.tick_node(c, view, rng) {
                    Status::Success => Status::Failure,
                    Status::Failure => Status::Success,
                    s => s,
                }
            }
            Kind::Sequence => {
                let n = self.nodes[iu].children.len();
                for k in 0..n {
                    let c = self.nodes[iu].children[k];
                    if self.status[c as usize] != Status::Invalid {
                        self.reset(c);
                    }
                }
                let mut st = Status::Success;
                for k in 0..n {
                    let c = self.nodes[iu].children[k];
                    let s = self.tick_node(c, view, rng);
                    if s != Status::Success {
                        st = s;
                        break;
                    }
                }
                st
            }
            Kind::Selector => {
                let n = self.nodes[iu].children.len();
                let mut st = Status::Failure;
                for k in 0..n {
                    let c = self.nodes[iu].children[k];
                    if self.tick_node(c, view, rng) == Status::Success {
                        st = Status::Success;
                        // Interrupting a lower-priority child: invalidate those after
                        // the winner, unless the winner is the first child (py_trees
                        // only resets when the running child changed).
                        if k > 0 {
                            for j in k + 1..n {
                                let c2 = self.nodes[iu].children[j];
                                if self.status[c2 as usize] != Status::Invalid {
                                    self.reset(c2);
                                }
                            }
                        }
                        break;
                    }
                }
                st
            }
            Kind::Parallel => {
                let n = self.nodes[iu].children.len();
                for k in 0..n {
                    let c = self.nodes[iu].children[k];
                    self.reset(c);
                }
                let mut st = Status::Success;
                for k in 0..n {
                    let c = self.nodes[iu].children[k];
                    if self.tick_node(c, view, rng) == Status::Failure {
                        st = Status::Failure;
                    }
                }
                st
            }
        };
        self.status[iu] = st;
        st
    }

    /// BT feedback of the reference code: the number of Selector nodes whose status is
    /// SUCCESS after the tick (stale statuses included).
    pub fn successful_selectors(&self) -> u32 {
        self.selectors.iter().filter(|&&i| self.status[i as usize] == Status::Success).count() as u32
    }

    /// BT feedback as the paper defines it: +1 per successful post-condition, −2 per
    /// failed constraint, +1 if the root is a Selector that succeeded.
    pub fn paper_feedback(&self) -> f64 {
        let mut b = 0.0;
        for (n, s) in self.nodes.iter().zip(&self.status) {
            match (&n.kind, s) {
                (Kind::Leaf(_, Tag::PostCnd), Status::Success) => b += 1.0,
                (Kind::Leaf(_, Tag::Cnstr), Status::Failure) => b -= 2.0,
                _ => {}
            }
        }
        if matches!(self.nodes.first(), Some(n) if n.kind == Kind::Selector) && self.status[0] == Status::Success {
            b += 1.0;
        }
        b
    }

    /// The `[Act]` leaves and their statuses.
    pub fn actions(&self) -> impl Iterator<Item = (&Leaf, Status)> {
        self.nodes.iter().zip(&self.status).filter_map(|(n, s)| match &n.kind {
            Kind::Leaf(l, Tag::Act) => Some((l, *s)),
            _ => None,
        })
    }

    /// Every leaf of the tree.
    pub fn leaves(&self) -> impl Iterator<Item = &Leaf> {
        self.nodes.iter().filter_map(|n| match &n.kind {
            Kind::Leaf(l, _) => Some(l),
            _ => None,
        })
    }

    /// The tree's behaviour class (REFERENCE §8.3): the first of Explore,
    /// CompositeSingleCarry, CompositeDrop, MoveTowards, MoveAway among its leaves, in
    /// that priority order, whatever their position in the tree.
    pub fn behaviour_class(&self) -> BehaviourClass {
        let rank = |l: &Leaf| match l {
            Leaf::Explore(_) => Some(BehaviourClass::Explore),
            Leaf::CompositeSingleCarry(_) => Some(BehaviourClass::CompositeSingleCarry),
            Leaf::CompositeDrop(_) => Some(BehaviourClass::CompositeDrop),
            Leaf::MoveTowards(..) => Some(BehaviourClass::MoveTowards),
            Leaf::MoveAway(..) => Some(BehaviourClass::MoveAway),
            _ => None,
        };
        self.leaves().filter_map(rank).min_by_key(|c| c.number()).unwrap_or(BehaviourClass::None)
    }

    /// Status of the root after the last tick.
    pub fn root_status(&self) -> Status {
        self.status.first().copied().unwrap_or(Status::Invalid)
    }

    /// Indented text listing in the style of REFERENCE §4.5.
    pub fn render(&self) -> String {
        let mut out = String::new();
        if !self.nodes.is_empty() {
            self.render_node(0, 0, &mut out);
        }
        out
    }

    fn render_node(&self, i: u32, depth: usize, out: &mut String) {
        let n = &self.nodes[i as usize];
        let _ = writeln!(out, "{}{}", "  ".repeat(depth), n.kind.label());
        for &c in &n.children {
            self.render_node(c, depth + 1, out);
        }
    }
}
