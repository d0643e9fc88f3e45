//! REFERENCE §2.1: py_trees 2.1.6 node semantics as truth tables, with children that
//! return fixed statuses over two ticks to show which statuses go stale; and §6.5: what
//! the BT feedback B counts.
//!
//! The children are four side-effect-free conditions whose results the hand-made world
//! fixes for each tick: A = IsCarrying_Food (the agent carries food), B =
//! IsCarrying_Debris (carries debris), C = IsVisitedBefore_Sites (knows a site), D =
//! IsVisitedBefore_Boundary (knows a boundary). Their statuses after a tick are read
//! through [`Bt::actions`] (they are tagged `Act`; the tag has no execution meaning, §4.1).
use super::{bt_rng, object, World};
use crate::bt::Bt;
use crate::bt::Status::{self, Failure as F, Invalid as I, Success as S};
use crate::ge::{CompositeKind, PNode};
use crate::view::View;
use geese_proto::ObjectKind;

const A: &str = "IsCarrying_Food";
const B: &str = "IsCarrying_Debris";
const C: &str = "IsVisitedBefore_Sites";
const D: &str = "IsVisitedBefore_Boundary";

/// A leaf whose status is observable (tag `Act`).
fn leaf(text: &str) -> PNode {
    tagged(text, "Act")
}
fn tagged(text: &str, tag: &str) -> PNode {
    PNode::Leaf { text: text.into(), tag: tag.into() }
}
fn seq(children: Vec<PNode>) -> PNode {
    PNode::Composite { kind: CompositeKind::Sequence, children }
}
fn sel(children: Vec<PNode>) -> PNode {
    PNode::Composite { kind: CompositeKind::Selector, children }
}
fn tree(p: PNode) -> Bt {
    Bt::from_pnode(&p).expect("tree builds")
}

/// The world in which A, B, C, D have results `r` (missing entries are false).
fn world(r: &[bool]) -> View {
    let on = |i: usize| r.get(i).copied().unwrap_or(false);
    let mut w = World::at(35, 35);
    if on(0) {
        w = w.carrying(object(10, ObjectKind::Food, 35, 35));
    }
    if on(1) {
        w = w.carrying(object(11, ObjectKind::Debris, 35, 35));
    }
    if on(2) {
        w = w.knowing(object(2, ObjectKind::Sites, -30, -30));
    }
    if on(3) {
        w = w.knowing(object(3, ObjectKind::Boundary, -30, 30));
    }
    w.view()
}

/// Tick once in the world `r`; the root status and the statuses of the `Act` leaves in
/// tree order.
fn tick(bt: &mut Bt, r: &[bool]) -> (Status, Vec<Status>) {
    let mut v = world(r);
    let st = bt.tick(&mut v, &mut bt_rng(0));
    assert_eq!(st, bt.root_status());
    (st, bt.actions().map(|(_, s)| s).collect())
}

const T: bool = true;
const X: bool = false;

/// §2.1 Sequence: ticks children in order, stops at the first that does not succeed and
/// takes its status; later children stay INVALID; all succeed → SUCCESS.
#[test]
fn sequence_truth_table() {
    let rows: [([bool; 3], Status, [Status; 3]); 8] = [
        ([T, T, T], S, [S, S, S]),
        ([T, T, X], F, [S, S, F]),
        ([T, X, T], F, [S, F, I]),
        ([T, X, X], F, [S, F, I]),
        ([X, T, T], F, [F, I, I]),
        ([X, T, X], F, [F, I, I]),
        ([X, X, T], F, [F, I, I]),
        ([X, X, X], F, [F, I, I]),
    ];
    for (r, root, leaves) in rows {
        let mut bt = tree(seq(vec![leaf(A), leaf(B), leaf(C)]));
        assert_eq!(tick(&mut bt, &r), (root, leaves.to_vec()), "Sequence(A, B, C) with {r:?}");
    }
}

/// §2.1 Sequence: at the start of every tick it resets every child to INVALID, so
/// children it does not reach this tick do not keep last tick's SUCCESS.
#[test]
fn sequence_resets_its_children_at_the_start_of_each_tick() {
    let mut bt = tree(seq(vec![leaf(A), leaf(B), leaf(C)]));
    assert_eq!(tick(&mut bt, &[T, T, T]), (S, vec![S, S, S]));
    assert_eq!(tick(&mut bt, &[X, T, T]), (F, vec![F, I, I]));
    assert_eq!(tick(&mut bt, &[T, X, T]), (F, vec![S, F, I]));
}

/// §2.1 Sequence: the reset goes recursively through each child's whole subtree — a
/// selector below the sequence loses its SUCCESS too, so B (§6.5) drops with it.
#[test]
fn sequence_reset_reaches_the_whole_subtree() {
    let mut bt = tree(seq(vec![leaf(A), sel(vec![leaf(B), leaf(C)])]));
    assert_eq!(tick(&mut bt, &[T, X, T]), (S, vec![S, F, S]));
    assert_eq!(bt.successful_selectors(), 1);
    assert_eq!(tick(&mut bt, &[X, X, T]), (F, vec![F, I, I]));
    assert_eq!(bt.successful_selectors(), 0, "the inner selector was reset, not left stale");
}

/// §2.1 Selector: ticks children from the first; SUCCESS at the first child that
/// succeeds (later children not ticked), FAILURE if every child fails.
#[test]
fn selector_truth_table() {
    let rows: [([bool; 3], Status, [Status; 3]); 8] = [
        ([T, T, T], S, [S, I, I]),
        ([T, T, X], S, [S, I, I]),
        ([T, X, T], S, [S, I, I]),
        ([T, X, X], S, [S, I, I]),
        ([X, T, T], S, [F, S, I]),
        ([X, T, X], S, [F, S, I]),
        ([X, X, T], S, [F, F, S]),
        ([X, X, X], F, [F, F, F]),
    ];
    for (r, root, leaves) in rows {
        let mut bt = tree(sel(vec![leaf(A), leaf(B), leaf(C)]));
        assert_eq!(tick(&mut bt, &r), (root, leaves.to_vec()), "Selector(A, B, C) with {r:?}");
    }
}

/// §2.1 Selector: it does not reset its children at the start of a tick, and when the
/// *first* child succeeds the later children keep the statuses of earlier ticks
/// ("stale" statuses) — here B stays SUCCESS although B is now false.
#[test]
fn selector_keeps_stale_statuses_when_its_first_child_succeeds() {
    let mut bt = tree(sel(vec![leaf(A), leaf(B)]));
    assert_eq!(tick(&mut bt, &[X, T]), (S, vec![F, S]));
    assert_eq!(tick(&mut bt, &[T, X]), (S, vec![S, S]), "B keeps its stale SUCCESS");
    assert_eq!(tick(&mut bt, &[T, X]), (S, vec![S, S]), "and keeps it over further ticks");
    // A stale FAILURE is kept the same way.
    let mut bt = tree(sel(vec![leaf(A), leaf(B), leaf(C)]));
    assert_eq!(tick(&mut bt, &[X, X, T]), (S, vec![F, F, S]));
    assert_eq!(tick(&mut bt, &[T, T, X]), (S, vec![S, F, S]));
}

/// §2.1 Selector: when a child that is *not* the first succeeds, every later child with
/// a non-INVALID status is reset to INVALID.
#[test]
fn selector_resets_later_children_when_a_later_child_succeeds() {
    let mut bt = tree(sel(vec![leaf(A), leaf(B), leaf(C)]));
    assert_eq!(tick(&mut bt, &[X, X, T]), (S, vec![F, F, S]));
    assert_eq!(tick(&mut bt, &[X, T, X]), (S, vec![F, S, I]), "C reset, not left stale");
}

/// §2.1 Selector: that reset is recursive (a later child's whole subtree), so a nested
/// selector's SUCCESS no longer counts in B (§6.5).
#[test]
fn selector_reset_of_later_children_is_recursive() {
    let mut bt = tree(sel(vec![leaf(A), leaf(B), sel(vec![leaf(C), leaf(D)])]));
    assert_eq!(tick(&mut bt, &[X, X, X, T]), (S, vec![F, F, F, S]));
    assert_eq!(bt.successful_selectors(), 2);
    assert_eq!(tick(&mut bt, &[X, T, X, X]), (S, vec![F, S, I, I]));
    assert_eq!(bt.successful_selectors(), 1);
}

/// §2.1 + §6.5: a selector left stale with SUCCESS below a selector whose first child
/// succeeds still counts in B ("statuses may be stale").
#[test]
fn stale_selector_success_counts_in_b() {
    let mut bt = tree(sel(vec![leaf(A), sel(vec![leaf(B), leaf(C)])]));
    assert_eq!(tick(&mut bt, &[X, X, T]), (S, vec![F, F, S]));
    assert_eq!(bt.successful_selectors(), 2);
    // Now A succeeds: the inner selector is not ticked, yet keeps its SUCCESS.
    assert_eq!(tick(&mut bt, &[T, X, X]), (S, vec![S, F, S]));
    assert_eq!(bt.successful_selectors(), 2);
}

/// §2.1: no children → Sequence SUCCESS, Selector FAILURE.
#[test]
fn empty_sequence_succeeds_and_empty_selector_fails() {
    assert_eq!(tick(&mut tree(seq(vec![])), &[]).0, S);
    assert_eq!(tick(&mut tree(sel(vec![])), &[]).0, F);
    // And as children: Sequence(Sequence()) succeeds, Sequence(Selector()) fails.
    assert_eq!(tick(&mut tree(seq(vec![seq(vec![])])), &[]).0, S);
    assert_eq!(tick(&mut tree(seq(vec![sel(vec![])])), &[]).0, F);
}

/// §2.1 Inverter (`X_invert`, §4.2): ticks its child and swaps SUCCESS and FAILURE; the
/// child keeps its own status.
#[test]
fn inverter_swaps_success_and_failure() {
    let inv = || leaf(&format!("{A}_invert"));
    let mut bt = tree(seq(vec![inv(), leaf(B)]));
    assert_eq!(tick(&mut bt, &[T, T]), (F, vec![S, I]), "A true → inverted FAILURE stops the sequence");
    assert_eq!(tick(&mut bt, &[X, T]), (S, vec![F, S]), "A false → inverted SUCCESS lets B run");
    let mut bt = tree(sel(vec![inv(), leaf(B)]));
    assert_eq!(tick(&mut bt, &[X, T]), (S, vec![F, I]));
    assert_eq!(tick(&mut bt, &[T, T]), (S, vec![S, S]));
}

/// §2.1 Parallel (success on all; nothing returns RUNNING): ticks *every* child in order
/// with no short-circuit, FAILURE if any child failed, else SUCCESS.
#[test]
fn parallel_ticks_every_child_and_fails_if_any_failed() {
    for a in [T, X] {
        for b in [T, X] {
            for c in [T, X] {
                let mut bt =
                    Bt::parallel(&[tree(seq(vec![leaf(A)])), tree(seq(vec![leaf(B)])), tree(seq(vec![leaf(C)]))]);
                let st = |x: bool| if x { S } else { F };
                let root = if a && b && c { S } else { F };
                assert_eq!(tick(&mut bt, &[a, b, c]), (root, vec![st(a), st(b), st(c)]), "{:?}", [a, b, c]);
            }
        }
    }
}

/// §2.1 Parallel: it resets all children (recursively) before ticking them, so the
/// stale status a selector child would keep (see
/// `selector_keeps_stale_statuses_when_its_first_child_succeeds`) is cleared.
#[test]
fn parallel_resets_all_children_first() {
    let mut bt = Bt::parallel(&[tree(sel(vec![leaf(A), leaf(B)])), tree(seq(vec![leaf(C)]))]);
    assert_eq!(tick(&mut bt, &[X, T, T]), (S, vec![F, S, S]));
    assert_eq!(tick(&mut bt, &[T, X, T]), (S, vec![S, I, S]), "B reset by the parallel");
    assert_eq!(bt.successful_selectors(), 1);
}

/// §6.5 (CODE): B = the number of Selector nodes whose status is SUCCESS after the
/// tick — every selector, not only the root; sequences and failed selectors do not
/// count. The REFERENCE's own example: Sequence(Selector(Dummy, …)) → 1, the same under
/// a Selector root → 2.
#[test]
fn b_counts_every_successful_selector_and_nothing_else() {
    let ppa = || sel(vec![tagged("DummyNode", "PostCnd"), seq(vec![leaf(A)])]);
    let cases: [(PNode, u32); 7] = [
        (seq(vec![ppa()]), 1),
        (sel(vec![ppa()]), 2),
        (seq(vec![seq(vec![tagged("DummyNode", "PostCnd")])]), 0),
        (sel(vec![leaf(A)]), 0),
        (sel(vec![leaf(A), leaf(B)]), 0),
        (seq(vec![sel(vec![leaf(A), leaf(C)]), sel(vec![leaf(C)]), sel(vec![leaf(B)])]), 2),
        // The third selector is not ticked: INVALID, not counted.
        (sel(vec![sel(vec![leaf(A)]), sel(vec![leaf(C)]), sel(vec![leaf(C)])]), 2),
    ];
    for (p, b) in cases {
        let mut bt = tree(p.clone());
        tick(&mut bt, &[X, X, T]);
        assert_eq!(bt.successful_selectors(), b, "B of\n{}", p.render());
    }
}

/// §6.5 + §4.4 (CODE): the post-condition (+1) and constraint (−2) terms are 0 — a
/// succeeding `[PostCnd]` leaf and a failing `[Cnstr]` leaf do not change B.
#[test]
fn b_ignores_post_conditions_and_constraints() {
    let mut bt = tree(seq(vec![tagged("DummyNode", "PostCnd"), tagged(A, "Cnstr")]));
    assert_eq!(tick(&mut bt, &[X]).0, F);
    assert_eq!(bt.successful_selectors(), 0);
    assert_eq!(bt.paper_feedback(), 1.0 - 2.0, "the paper's terms do see them");
}

/// §2.1 + §6.5: the private subtree of a composite leaf is invisible to B — MoveTowards
/// at the hub succeeds through its private selector's "already there" child, which is
/// not counted.
#[test]
fn b_does_not_count_selectors_inside_composite_leaves() {
    let mut bt = tree(seq(vec![leaf("MoveTowards_Hub_Normal"), leaf("CompositeSingleCarry_Food")]));
    let mut v = World::at(3, 3).with(super::HUB).carrying(object(10, ObjectKind::Food, 3, 3)).view();
    assert_eq!(bt.tick(&mut v, &mut bt_rng(0)), S);
    assert_eq!(bt.successful_selectors(), 0);
    assert_eq!(bt.len(), 3, "one node per composite leaf");
}

/// §6.5 [switch] `Fidelity::Paper`: B = +1 per successful post-condition (`[PostCnd]`)
/// leaf, −2 per failed constraint (`[Cnstr]`) leaf, +1 if the root is a Selector that
/// succeeded.
#[test]
fn paper_feedback_terms() {
    // Selector[ Sequence[ PostCnd Dummy ✓, Cnstr A ✗ ], PostCnd C ✓ ] → +1 −2 +1, root +1.
    let body = || sel(vec![seq(vec![tagged("DummyNode", "PostCnd"), tagged(A, "Cnstr")]), tagged(C, "PostCnd")]);
    let mut bt = tree(body());
    assert_eq!(tick(&mut bt, &[X, X, T]).0, S);
    assert_eq!(bt.paper_feedback(), 1.0);
    assert_eq!(bt.successful_selectors(), 1);
    // The same under a Sequence root: no root bonus.
    let mut bt = tree(seq(vec![body()]));
    assert_eq!(tick(&mut bt, &[X, X, T]).0, S);
    assert_eq!(bt.paper_feedback(), 0.0);
    // A root selector that fails earns nothing; a constraint that is not ticked costs
    // nothing.
    let mut bt = tree(sel(vec![tagged(C, "PostCnd"), tagged(A, "Cnstr")]));
    assert_eq!(tick(&mut bt, &[X, X, X]).0, F);
    assert_eq!(bt.paper_feedback(), -2.0);
    let mut bt = tree(sel(vec![tagged(C, "PostCnd"), tagged(A, "Cnstr")]));
    assert_eq!(tick(&mut bt, &[X, X, T]).0, S);
    assert_eq!(bt.paper_feedback(), 2.0);
}

/// REFERENCE §8.3: a tree's behaviour class is the first of Explore,
/// CompositeSingleCarry, CompositeDrop, MoveTowards, MoveAway among its leaves in that
/// priority order, not in tree order; a tree with none of them is class 0.
#[test]
fn behaviour_class_follows_the_priority_order_not_the_tree_order() {
    use geese_proto::BehaviourClass as K;
    let class = |leaves: &[&str]| tree(seq(leaves.iter().map(|l| leaf(l)).collect())).behaviour_class();
    assert_eq!(class(&[A, B]), K::None);
    assert_eq!(class(&["MoveAway_Hub"]), K::MoveAway);
    assert_eq!(class(&["MoveAway_Hub", "MoveTowards_Sites"]), K::MoveTowards);
    assert_eq!(class(&["MoveTowards_Sites", "CompositeDrop_Food"]), K::CompositeDrop);
    assert_eq!(class(&["CompositeDrop_Food", "CompositeSingleCarry_Food"]), K::CompositeSingleCarry);
    assert_eq!(class(&["MoveAway_Hub", "CompositeSingleCarry_Food", "Explore_0"]), K::Explore);
    assert_eq!(K::ALL.iter().map(|k| k.number()).collect::<Vec<_>>(), vec![0, 1, 2, 3, 4, 5]);
}
