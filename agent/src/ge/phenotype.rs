//! Bracket phenotype string → composite/leaf tree (REFERENCE.md §4.1–4.3).
//!
//! Why this exists: the behaviour-tree builder needs the tree the swarm code builds from a
//! phenotype, *including* its composite construction quirk (§4.3): while converting the
//! children of one element a "current composite" slot is kept and never cleared, so a leaf
//! that follows a composite sibling becomes an extra child of that most recent composite
//! sibling. That quirk changes Multi-GEESE semantics, so it lives here, in one place.
//!
//! The phenotype is read as XML after `[`→`<`, `]`→`>`, `%`→`"` — without materialising
//! the converted string: `[`/`<` open and `]`/`>` close a tag, `%` in leaf text becomes
//! `"`. Only the XML subset the grammars produce is accepted: the `[?xml …?]` declaration
//! (and other `?` processing instructions), start/end/self-closing tags (attributes are
//! ignored), and text. Entities are not decoded. Whitespace-only text between elements is
//! ignored; any other text outside a leaf is an error (the Python builder ignores it,
//! but it can only come from a broken grammar). Malformed input is reported as a
//! [`PhenotypeError`]; the parser never panics.

use std::fmt;

/// Composite node kinds (`Parallel` occurs only in the unpublished `moore` grammar).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CompositeKind {
    Sequence,
    Selector,
    Parallel,
}

impl CompositeKind {
    /// The kind for an element tag, if the tag is a composite tag.
    pub fn from_tag(tag: &str) -> Option<CompositeKind> {
        match tag {
            "Sequence" => Some(CompositeKind::Sequence),
            "Selector" => Some(CompositeKind::Selector),
            "Parallel" => Some(CompositeKind::Parallel),
            _ => None,
        }
    }
    pub fn as_str(self) -> &'static str {
        match self {
            CompositeKind::Sequence => "Sequence",
            CompositeKind::Selector => "Selector",
            CompositeKind::Parallel => "Parallel",
        }
    }
}

impl fmt::Display for CompositeKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A node of the phenotype tree after the §4.3 construction rule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PNode {
    Composite {
        kind: CompositeKind,
        children: Vec<PNode>,
    },
    /// A leaf wrapper element: `text` is its leaf spec (e.g. `IsCarrying_Food`,
    /// `MoveTowardsNormal`), `tag` the wrapper tag (`PostCnd`, `PreCnd`, `Cnstr`, `Act`, …).
    Leaf {
        text: String,
        tag: String,
    },
}

impl PNode {
    /// Indented one-node-per-line listing: composites by kind, leaves as `text (tag)`,
    /// two spaces per level, each line ending in `\n`.
    pub fn render(&self) -> String {
        let mut s = String::new();
        self.render_into(&mut s, 0);
        s
    }

    fn render_into(&self, s: &mut String, level: usize) {
        for _ in 0..level {
            s.push_str("  ");
        }
        match self {
            PNode::Composite { kind, children } => {
                s.push_str(kind.as_str());
                s.push('\n');
                for c in children {
                    c.render_into(s, level + 1);
                }
            }
            PNode::Leaf { text, tag } => {
                s.push_str(text);
                s.push_str(" (");
                s.push_str(tag);
                s.push_str(")\n");
            }
        }
    }

    /// Number of nodes in the tree.
    pub fn size(&self) -> usize {
        match self {
            PNode::Composite { children, .. } => 1 + children.iter().map(PNode::size).sum::<usize>(),
            PNode::Leaf { .. } => 1,
        }
    }

    /// Leaves in document order.
    pub fn leaves(&self) -> Vec<(&str, &str)> {
        fn walk<'a>(n: &'a PNode, out: &mut Vec<(&'a str, &'a str)>) {
            match n {
                PNode::Composite { children, .. } => children.iter().for_each(|c| walk(c, out)),
                PNode::Leaf { text, tag } => out.push((text, tag)),
            }
        }
        let mut out = Vec::new();
        walk(self, &mut out);
        out
    }
}

/// Why a phenotype string could not be turned into a tree. Offsets are byte offsets into
/// the phenotype string.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PhenotypeError {
    #[error("phenotype has no document element")]
    NoRoot,
    #[error("unterminated tag starting at byte {offset}: `[` without a closing `]`")]
    UnterminatedTag { offset: usize },
    #[error("malformed tag `{text}` at byte {offset}")]
    BadTag { offset: usize, text: String },
    #[error("unsupported markup `{text}` at byte {offset} (comments, CDATA, DOCTYPE and processing instructions inside the document element are not produced by the grammars)")]
    Unsupported { offset: usize, text: String },
    #[error("end tag [/{found}] at byte {offset} does not match the open element [{expected}]")]
    MismatchedEndTag { offset: usize, expected: String, found: String },
    #[error("end tag [/{found}] at byte {offset} has no open element")]
    UnexpectedEndTag { offset: usize, found: String },
    #[error("element [{tag}] is never closed")]
    Unclosed { tag: String },
    #[error("content after the document element at byte {offset}")]
    TrailingContent { offset: usize },
    #[error("text {text:?} outside the document element at byte {offset}")]
    TextOutsideRoot { offset: usize, text: String },
    #[error("document element [{tag}] is not a composite (Sequence, Selector or Parallel)")]
    RootNotComposite { tag: String },
    #[error("leaf element [{tag}] at byte {offset} contains a child element")]
    LeafWithChild { tag: String, offset: usize },
    #[error("leaf element [{tag}] at byte {offset} has no text")]
    LeafWithoutText { tag: String, offset: usize },
    #[error("unexpected text {text:?} inside a composite at byte {offset}")]
    UnexpectedText { offset: usize, text: String },
    #[error("elements nested deeper than {limit} levels (at byte {offset})")]
    TooDeep { offset: usize, limit: usize },
}

/// Deepest element nesting accepted (the grammars produce ≤ 10).
pub const MAX_NESTING: usize = 256;

/// One lexical item of a bracket phenotype.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Token<'a> {
    /// `[?…?]`: XML declaration or processing instruction.
    Decl {
        offset: usize,
    },
    Start {
        name: &'a str,
        self_closing: bool,
        offset: usize,
    },
    End {
        name: &'a str,
        offset: usize,
    },
    Text {
        text: &'a str,
        offset: usize,
    },
}

/// Streaming tokenizer shared by the tree parser and the diversity scan.
pub(crate) struct Tokenizer<'a> {
    s: &'a str,
    pos: usize,
}

impl<'a> Tokenizer<'a> {
    pub(crate) fn new(s: &'a str) -> Self {
        Tokenizer { s, pos: 0 }
    }

    pub(crate) fn next_token(&mut self) -> Result<Option<Token<'a>>, PhenotypeError> {
        let s = self.s;
        let b = s.as_bytes();
        let start = self.pos;
        if start >= b.len() {
            return Ok(None);
        }
        if b[start] == b'[' || b[start] == b'<' {
            let Some(rel) = b[start + 1..].iter().position(|&c| c == b']' || c == b'>') else {
                self.pos = b.len();
                return Err(PhenotypeError::UnterminatedTag { offset: start });
            };
            let end = start + 1 + rel;
            self.pos = end + 1;
            // `[`, `<`, `]` and `>` are ASCII, so these are char boundaries.
            let inner = &s[start + 1..end];
            let bad = || PhenotypeError::BadTag { offset: start, text: s[start..=end].to_string() };
            if let Some(pi) = inner.strip_prefix('?') {
                if pi.ends_with('?') && !pi.is_empty() {
                    return Ok(Some(Token::Decl { offset: start }));
                }
                return Err(bad());
            }
            if inner.starts_with('!') {
                return Err(PhenotypeError::Unsupported { offset: start, text: s[start..=end].to_string() });
            }
            if let Some(rest) = inner.strip_prefix('/') {
                let name = rest.trim_end_matches([' ', '\t', '\n', '\r']);
                if !valid_name(name) {
                    return Err(bad());
                }
                return Ok(Some(Token::End { name, offset: start }));
            }
            let (body, self_closing) = match inner.strip_suffix('/') {
                Some(b) => (b, true),
                None => (inner, false),
            };
            let name_len = body.bytes().position(is_xml_space).unwrap_or(body.len());
            let name = &body[..name_len];
            if !valid_name(name) {
                return Err(bad());
            }
            return Ok(Some(Token::Start { name, self_closing, offset: start }));
        }
        let rel = b[start..].iter().position(|&c| c == b'[' || c == b'<').unwrap_or(b.len() - start);
        self.pos = start + rel;
        Ok(Some(Token::Text { text: &s[start..start + rel], offset: start }))
    }
}

/// XML white space (`S` production): space, tab, CR, LF.
fn is_xml_space(c: u8) -> bool {
    matches!(c, b' ' | b'\t' | b'\n' | b'\r')
}

fn valid_name(name: &str) -> bool {
    !name.is_empty() && name.bytes().all(|c| !is_xml_space(c) && c != b'/' && c != b'[' && c != b'<')
}

fn is_blank(t: &str) -> bool {
    t.chars().all(char::is_whitespace)
}

/// Parse a phenotype string into its tree (root = composite of the document element's
/// kind; §4.3 applied at every level).
pub fn parse_phenotype(phenotype: &str) -> Result<PNode, PhenotypeError> {
    let mut t = Tokenizer::new(phenotype);
    // Prolog.
    let (name, self_closing) = loop {
        match t.next_token()? {
            None => return Err(PhenotypeError::NoRoot),
            Some(Token::Decl { .. }) => {}
            Some(Token::Text { text, offset }) => {
                if !is_blank(text) {
                    return Err(PhenotypeError::TextOutsideRoot { offset, text: text.to_string() });
                }
            }
            Some(Token::End { name, offset }) => {
                return Err(PhenotypeError::UnexpectedEndTag { offset, found: name.to_string() })
            }
            Some(Token::Start { name, self_closing, .. }) => break (name, self_closing),
        }
    };
    let kind =
        CompositeKind::from_tag(name).ok_or_else(|| PhenotypeError::RootNotComposite { tag: name.to_string() })?;
    let children = if self_closing { Vec::new() } else { children(&mut t, name, 1)? };
    // Epilog.
    loop {
        match t.next_token()? {
            None => break,
            Some(Token::Decl { .. }) => {}
            Some(Token::Text { text, offset }) => {
                if !is_blank(text) {
                    return Err(PhenotypeError::TrailingContent { offset });
                }
            }
            Some(Token::Start { offset, .. }) | Some(Token::End { offset, .. }) => {
                return Err(PhenotypeError::TrailingContent { offset })
            }
        }
    }
    Ok(PNode::Composite { kind, children })
}

/// Convert the children of the open element `parent` (consumes its end tag).
fn children(t: &mut Tokenizer<'_>, parent: &str, depth: usize) -> Result<Vec<PNode>, PhenotypeError> {
    let mut out: Vec<PNode> = Vec::new();
    // The §4.3 "current composite" slot: index into `out`, never cleared.
    let mut current: Option<usize> = None;
    loop {
        match t.next_token()? {
            None => return Err(PhenotypeError::Unclosed { tag: parent.to_string() }),
            Some(Token::Decl { offset }) => return Err(pi_inside(t, offset)),
            Some(Token::Text { text, offset }) => {
                if !is_blank(text) {
                    return Err(PhenotypeError::UnexpectedText { offset, text: text.to_string() });
                }
            }
            Some(Token::End { name, offset }) => {
                if name != parent {
                    return Err(PhenotypeError::MismatchedEndTag {
                        offset,
                        expected: parent.to_string(),
                        found: name.to_string(),
                    });
                }
                return Ok(out);
            }
            Some(Token::Start { name, self_closing, offset }) => {
                if let Some(kind) = CompositeKind::from_tag(name) {
                    if depth >= MAX_NESTING {
                        return Err(PhenotypeError::TooDeep { offset, limit: MAX_NESTING });
                    }
                    let ch = if self_closing { Vec::new() } else { children(t, name, depth + 1)? };
                    out.push(PNode::Composite { kind, children: ch });
                    current = Some(out.len() - 1);
                } else {
                    let leaf = leaf(t, name, self_closing, offset)?;
                    match current.and_then(|i| out.get_mut(i)) {
                        Some(PNode::Composite { children, .. }) => children.push(leaf),
                        _ => out.push(leaf),
                    }
                }
            }
        }
    }
}

/// Error for a `[?…?]` inside the document element (XML allows it there, but the
/// grammars never produce one and ElementTree's text handling around it is subtle).
fn pi_inside(t: &Tokenizer<'_>, offset: usize) -> PhenotypeError {
    let end = t.s.get(offset..).and_then(|r| r.find([']', '>'])).map_or(t.s.len(), |e| offset + e + 1);
    PhenotypeError::Unsupported { offset, text: t.s.get(offset..end).unwrap_or("").to_string() }
}

/// Read a leaf element's text and end tag.
fn leaf(t: &mut Tokenizer<'_>, tag: &str, self_closing: bool, offset: usize) -> Result<PNode, PhenotypeError> {
    let no_text = || PhenotypeError::LeafWithoutText { tag: tag.to_string(), offset };
    if self_closing {
        return Err(no_text());
    }
    let text = match t.next_token()? {
        Some(Token::Text { text, .. }) => text,
        Some(Token::End { name, offset: o }) => {
            return Err(if name == tag {
                no_text()
            } else {
                PhenotypeError::MismatchedEndTag { offset: o, expected: tag.to_string(), found: name.to_string() }
            });
        }
        Some(Token::Decl { offset }) => return Err(pi_inside(t, offset)),
        Some(Token::Start { .. }) => return Err(PhenotypeError::LeafWithChild { tag: tag.to_string(), offset }),
        None => return Err(PhenotypeError::Unclosed { tag: tag.to_string() }),
    };
    match t.next_token()? {
        Some(Token::End { name, .. }) if name == tag => {}
        Some(Token::End { name, offset: o }) => {
            return Err(PhenotypeError::MismatchedEndTag {
                offset: o,
                expected: tag.to_string(),
                found: name.to_string(),
            })
        }
        Some(Token::Decl { offset }) => return Err(pi_inside(t, offset)),
        Some(Token::Start { .. }) | Some(Token::Text { .. }) => {
            return Err(PhenotypeError::LeafWithChild { tag: tag.to_string(), offset })
        }
        None => return Err(PhenotypeError::Unclosed { tag: tag.to_string() }),
    }
    Ok(PNode::Leaf { text: text.replace('%', "\""), tag: tag.to_string() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::mapper::tests::{forge_golden, grammar, sf_golden, test_new_golden};
    use crate::ge::testdata::{FORGE, HEADER};
    use proptest::prelude::*;

    fn parse(s: &str) -> PNode {
        match parse_phenotype(s) {
            Ok(p) => p,
            Err(e) => panic!("phenotype failed to parse: {e}\n{s}"),
        }
    }

    fn err(s: &str) -> PhenotypeError {
        match parse_phenotype(s) {
            Ok(p) => panic!("unexpectedly parsed {s:?} into {p:?}"),
            Err(e) => e,
        }
    }

    fn leaf(text: &str, tag: &str) -> PNode {
        PNode::Leaf { text: text.into(), tag: tag.into() }
    }
    fn seq(children: Vec<PNode>) -> PNode {
        PNode::Composite { kind: CompositeKind::Sequence, children }
    }
    fn sel(children: Vec<PNode>) -> PNode {
        PNode::Composite { kind: CompositeKind::Selector, children }
    }

    #[test]
    fn worked_example_1_constraints_absorb_action() {
        let p = format!("{HEADER}[Sequence][Selector][PostCnd]DummyNode[/PostCnd][Sequence][Sequence][PreCnd]IsCarrying_Food[/PreCnd][/Sequence][Sequence][Cnstr]CanMove[/Cnstr][Cnstr]IsCarryable_Food[/Cnstr][/Sequence][Act]MoveAway_Hub_Avoid[/Act][/Sequence][/Selector][/Sequence]");
        let tree = parse(&p);
        let expect = seq(vec![sel(vec![
            leaf("DummyNode", "PostCnd"),
            seq(vec![
                seq(vec![leaf("IsCarrying_Food", "PreCnd")]),
                seq(vec![
                    leaf("CanMove", "Cnstr"),
                    leaf("IsCarryable_Food", "Cnstr"),
                    leaf("MoveAway_Hub_Avoid", "Act"),
                ]),
            ]),
        ])]);
        assert_eq!(tree, expect);
        assert_eq!(
            tree.render(),
            "Sequence\n  Selector\n    DummyNode (PostCnd)\n    Sequence\n      Sequence\n        IsCarrying_Food (PreCnd)\n      Sequence\n        CanMove (Cnstr)\n        IsCarryable_Food (Cnstr)\n        MoveAway_Hub_Avoid (Act)\n"
        );
        // It is the third forge golden vector's phenotype.
        assert_eq!(p, forge_golden()[2].3);
    }

    #[test]
    fn worked_example_2_preconditions_absorb_action() {
        let p = format!("{HEADER}[Selector][Selector][Sequence][PostCnd]IsCarrying_Food[/PostCnd][/Sequence][Sequence][Sequence][PreCnd]IsVisitedBefore_Sites_invert[/PreCnd][/Sequence][Act]MoveAway_Hub_Avoid[/Act][/Sequence][/Selector][/Selector]");
        let tree = parse(&p);
        let expect = sel(vec![sel(vec![
            seq(vec![leaf("IsCarrying_Food", "PostCnd")]),
            seq(vec![seq(vec![leaf("IsVisitedBefore_Sites_invert", "PreCnd"), leaf("MoveAway_Hub_Avoid", "Act")])]),
        ])]);
        assert_eq!(tree, expect);
        assert_eq!(
            tree.render(),
            "Selector\n  Selector\n    Sequence\n      IsCarrying_Food (PostCnd)\n    Sequence\n      Sequence\n        IsVisitedBefore_Sites_invert (PreCnd)\n        MoveAway_Hub_Avoid (Act)\n"
        );
    }

    #[test]
    fn worked_example_3_multi_geese_aar_blocks() {
        let p = "[Sequence][Sequence][Selector][Sequence][PreCnd]IsVisitedBefore_Hub[/PreCnd][/Sequence][Act]MoveTowardsNormal[/Act][/Selector][PostCnd]DidAvoidedObj_Sites[/PostCnd][/Sequence][Sequence][Selector][Sequence][PreCnd]IsDropable_Hub[/PreCnd][/Sequence][Act]ExploreNormal[/Act][/Selector][PostCnd]DidAvoidedObj_Sites[/PostCnd][PostCnd]NeighbourObjects_Hub[/PostCnd][/Sequence][/Sequence]";
        let tree = parse(p);
        let expect = seq(vec![
            seq(vec![sel(vec![
                seq(vec![leaf("IsVisitedBefore_Hub", "PreCnd"), leaf("MoveTowardsNormal", "Act")]),
                leaf("DidAvoidedObj_Sites", "PostCnd"),
            ])]),
            seq(vec![sel(vec![
                seq(vec![leaf("IsDropable_Hub", "PreCnd"), leaf("ExploreNormal", "Act")]),
                leaf("DidAvoidedObj_Sites", "PostCnd"),
                leaf("NeighbourObjects_Hub", "PostCnd"),
            ])]),
        ]);
        assert_eq!(tree, expect);
        assert_eq!(tree.size(), 14);
    }

    #[test]
    fn leaves_before_any_composite_stay_siblings() {
        let tree = parse("[Selector][cond]A[/cond][cond]B_Hub[/cond][act]C[/act][/Selector]");
        assert_eq!(tree, sel(vec![leaf("A", "cond"), leaf("B_Hub", "cond"), leaf("C", "act")]));
        // The slot is not cleared by a later composite: leaves join the *latest* composite.
        let tree = parse(
            "[Sequence][a]1[/a][Selector][b]2[/b][/Selector][c]3[/c][Sequence][/Sequence][d]4[/d][e]5[/e][/Sequence]",
        );
        assert_eq!(
            tree,
            seq(vec![
                leaf("1", "a"),
                sel(vec![leaf("2", "b"), leaf("3", "c")]),
                seq(vec![leaf("4", "d"), leaf("5", "e")]),
            ])
        );
        // Whitespace between elements is ignored (sf.bnf emits a space); `%` becomes `"`.
        let tree = parse("  [Sequence] [Selector][x]a%b[/x][/Selector]\n [Parallel/] [/Sequence] ");
        assert_eq!(
            tree,
            seq(vec![
                sel(vec![leaf("a\"b", "x")]),
                PNode::Composite { kind: CompositeKind::Parallel, children: vec![] }
            ])
        );
    }

    #[test]
    fn golden_phenotypes_all_parse() {
        let mut all: Vec<String> = forge_golden().into_iter().map(|g| g.3).collect();
        all.extend(sf_golden().into_iter().map(|g| g.3));
        all.push(test_new_golden().3);
        for p in &all {
            let tree = parse(p);
            assert!(matches!(tree, PNode::Composite { .. }));
        }
        // test_new: five AAR blocks, each Sequence(Selector(Sequence(PreCnd.., Act), PostCnd..)).
        let tree = parse(&test_new_golden().3);
        let PNode::Composite { kind: CompositeKind::Sequence, children } = &tree else { panic!("root") };
        assert_eq!(children.len(), 5);
        let acts: Vec<&str> = tree.leaves().into_iter().filter(|(_, tag)| *tag == "Act").map(|(t, _)| t).collect();
        assert_eq!(acts, vec!["MoveTowardsNormal", "ExploreNormal", "ExploreNormal", "CompositeDrop", "CompositeDrop"]);
        for block in children {
            let PNode::Composite { kind: CompositeKind::Sequence, children: b } = block else { panic!("block") };
            assert_eq!(b.len(), 1);
            let PNode::Composite { kind: CompositeKind::Selector, children: s } = &b[0] else { panic!("selector") };
            assert!(matches!(&s[0], PNode::Composite { kind: CompositeKind::Sequence, .. }));
            assert!(s[1..].iter().all(|n| matches!(n, PNode::Leaf { tag, .. } if tag == "PostCnd")));
        }
        // The sf tree has three siblings under one Selector, with no absorption.
        let tree = parse(&sf_golden()[0].3);
        assert_eq!(
            tree,
            sel(vec![leaf("IsDropable_Hub", "cond"), leaf("IsDropable_Hub", "cond"), leaf("MoveTowards_Hub", "act")])
        );
    }

    #[test]
    fn malformed_inputs_are_errors() {
        assert_eq!(err(""), PhenotypeError::NoRoot);
        assert_eq!(err(HEADER), PhenotypeError::NoRoot);
        assert!(matches!(err("[Sequence][a]x[/a]"), PhenotypeError::Unclosed { tag } if tag == "Sequence"));
        assert!(matches!(err("[Sequence][a]x[/b][/Sequence]"), PhenotypeError::MismatchedEndTag { .. }));
        assert!(matches!(err("[Sequence][Selector][/Sequence]"), PhenotypeError::MismatchedEndTag { .. }));
        assert!(matches!(err("[/Sequence]"), PhenotypeError::UnexpectedEndTag { .. }));
        assert!(matches!(err("[Sequence][a]x[/a"), PhenotypeError::UnterminatedTag { offset: 14 }));
        assert!(matches!(err("[Sequence][/Sequence][Sequence][/Sequence]"), PhenotypeError::TrailingContent { .. }));
        assert!(matches!(err("[Sequence][/Sequence]junk"), PhenotypeError::TrailingContent { .. }));
        assert!(matches!(err("junk[Sequence][/Sequence]"), PhenotypeError::TextOutsideRoot { .. }));
        assert!(matches!(err("[PostCnd]x[/PostCnd]"), PhenotypeError::RootNotComposite { tag } if tag == "PostCnd"));
        assert!(matches!(err("[Sequence][a][b]x[/b][/a][/Sequence]"), PhenotypeError::LeafWithChild { .. }));
        assert!(matches!(err("[Sequence][a][/a][/Sequence]"), PhenotypeError::LeafWithoutText { .. }));
        assert!(matches!(err("[Sequence][a/][/Sequence]"), PhenotypeError::LeafWithoutText { .. }));
        assert!(matches!(err("[Sequence]stray[/Sequence]"), PhenotypeError::UnexpectedText { .. }));
        assert!(matches!(err("[Sequence][][/Sequence]"), PhenotypeError::BadTag { .. }));
        assert!(matches!(err("[Sequence][!-- c --][/Sequence]"), PhenotypeError::Unsupported { .. }));
        assert!(matches!(err("[Sequence][?pi?][/Sequence]"), PhenotypeError::Unsupported { offset: 10, .. }));
        assert!(matches!(err("[Sequence][a]x[?pi?][/a][/Sequence]"), PhenotypeError::Unsupported { offset: 14, .. }));
        assert!(parse_phenotype("[?xml?] [Sequence][/Sequence] [?pi?]").is_ok());
        let deep = "[Sequence]".repeat(MAX_NESTING + 1);
        assert!(matches!(err(&deep), PhenotypeError::TooDeep { .. }));
        let msg = err("[Sequence][a]x[/b][/Sequence]").to_string();
        assert!(msg.contains("[/b]") && msg.contains("[a]"), "{msg}");
    }

    #[test]
    fn init_phenotypes_parse_with_exactly_one_action() {
        use rand::SeedableRng;
        let g = grammar(FORGE);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..200 {
            let d = crate::ge::init::uniform_tree(&g, 2000, 10, &mut rng);
            let tree = parse(&d.phenotype);
            let acts = tree.leaves().into_iter().filter(|(_, tag)| *tag == "Act").count();
            assert_eq!(acts, 1, "{}", d.phenotype);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(1000))]

        #[test]
        fn parser_never_panics_on_arbitrary_text(s in "\\PC{0,80}") {
            let _ = parse_phenotype(&s);
        }

        #[test]
        fn parser_never_panics_on_bracket_soup(
            parts in proptest::collection::vec(
                prop_oneof![
                    Just("[Sequence]"), Just("[/Sequence]"), Just("[Selector]"), Just("[/Selector]"),
                    Just("[Act]"), Just("[/Act]"), Just("x_y"), Just(" "), Just("["), Just("]"),
                    Just("[?xml?]"), Just("<"), Just(">"), Just("/"), Just("%"), Just("é"),
                ],
                0..40,
            )
        ) {
            let s = parts.concat();
            let _ = parse_phenotype(&s);
        }
    }
}
