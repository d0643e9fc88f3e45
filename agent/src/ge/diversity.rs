//! The diversity fitness D (`bt_diversity`, REFERENCE.md §5.5).
//!
//! Why this exists: D is the fitness every new individual is born with, so it is
//! computed for every offspring of every genetic step. Instead of building an XML tree it
//! runs a small state machine over tokens, reproducing ElementTree's view: every element
//! is visited in document order; elements tagged `Sequence`/`Selector` are skipped; any
//! other element contributes its text (the characters right after its start tag up to
//! the next tag), cut at the first `_`. Only the counts of the nine behaviour names,
//! whether any other name occurred, and the total are needed. The tokens of each run of
//! grammar terminals are scanned once when the grammar is compiled
//! (`ge::compiled`), so the mapper scores an offspring without writing its
//! phenotype (`DiversityScan`, `RunEffect`); [`diversity`] of a string feeds the same
//! machine. It accepts exactly what the [`super::phenotype`] tokenizer accepts (a test
//! checks the two against each other), except that end-tag names are not matched
//! against their start tags.
//!
//! Decisions where the Python would crash, or for input no grammar produces: a phenotype
//! that is not well-formed gives NaN (like an invalid individual); a non-control element
//! without text counts as the empty name (not a behaviour); a phenotype without any
//! non-control element gives 0; a `[?…?]` inside the document element gives NaN.

/// The behaviour names B of §5.5, sorted (L = 9).
pub const BEHAVIOURS: [&str; 9] = [
    "CompositeDrop",
    "CompositeSingleCarry",
    "Explore",
    "IsCarrying",
    "IsDropable",
    "IsVisitedBefore",
    "MoveAway",
    "MoveTowards",
    "NeighbourObjects",
];

fn behaviour_index(name: &[u8]) -> Option<usize> {
    match name {
        b"CompositeDrop" => Some(0),
        b"CompositeSingleCarry" => Some(1),
        b"Explore" => Some(2),
        b"IsCarrying" => Some(3),
        b"IsDropable" => Some(4),
        b"IsVisitedBefore" => Some(5),
        b"MoveAway" => Some(6),
        b"MoveTowards" => Some(7),
        b"NeighbourObjects" => Some(8),
        _ => None,
    }
}

/// Name counts of one phenotype.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Hash)]
struct Counts {
    per_behaviour: [u32; 9],
    other: bool,
    total: u32,
}

impl Counts {
    /// Count one element text (the reference scan in the tests).
    #[cfg(test)]
    fn add(&mut self, text: &[u8]) {
        let name = match text.iter().position(|&c| c == b'_') {
            Some(i) => &text[..i],
            None => text,
        };
        self.total += 1;
        match behaviour_index(name) {
            Some(i) => self.per_behaviour[i] += 1,
            None => self.other = true,
        }
    }
}

fn is_tag_open(c: u8) -> bool {
    c == b'[' || c == b'<'
}

fn is_xml_space(c: u8) -> bool {
    matches!(c, b' ' | b'\t' | b'\n' | b'\r')
}

fn valid_name(name: &[u8]) -> bool {
    !name.is_empty() && name.iter().all(|&c| !is_xml_space(c) && c != b'/' && c != b'[' && c != b'<')
}

/// The counts of a phenotype: tokenised as one run and fed to [`DiversityScan`], the
/// same state machine the mapper drives run by run; the acceptance rules are those of
/// the [`super::phenotype`] tokenizer (checked against it in the tests). `None` = not
/// well-formed.
fn count(phenotype: &str) -> Option<Counts> {
    let toks = tokenize_run(phenotype)?;
    let mut scan = DiversityScan::default();
    scan.feed(&toks);
    scan.finish_counts()
}

/// One token of a terminal run, pre-scanned for [`DiversityScan`]: the same tokens
/// [`count`] meets in a phenotype, with names already checked and classified, so the
/// genetic step can score an offspring from its terminal runs without building the
/// phenotype string.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Tok {
    /// Text between tags: whether it is all white space, its part before the first `_`
    /// (the only part that can name a behaviour), whether it contains a `_`, and the
    /// class of that part taken alone (behaviour index, or 9 = another name).
    Text { ws: bool, prefix: Box<[u8]>, underscore: bool, class: u8 },
    /// A start tag; `control` for `Sequence`/`Selector`.
    Open { control: bool, self_closing: bool },
    /// An end tag with a valid name.
    Close,
    /// A `[?…?]` declaration.
    Pi,
    /// Something [`count`] rejects (empty tag, `[!…]`, bad name).
    Bad,
}

/// Class of a name: its behaviour index, or 9 for any other name.
fn class_of(name: &[u8]) -> u8 {
    behaviour_index(name).map_or(9, |i| i as u8)
}

/// Tokenise one terminal run exactly as [`count`] scans it. `None` when the run ends
/// inside a tag: a tag could then span runs, and the grammar is scored from strings.
pub(crate) fn tokenize_run(text: &str) -> Option<Vec<Tok>> {
    let b = text.as_bytes();
    let n = b.len();
    let mut toks = Vec::new();
    let mut i = 0usize;
    while i < n {
        let text_start = i;
        while i < n && !is_tag_open(b[i]) {
            i += 1;
        }
        if i > text_start {
            let t = &b[text_start..i];
            let cut = t.iter().position(|&c| c == b'_');
            let prefix = &t[..cut.unwrap_or(t.len())];
            toks.push(Tok::Text {
                ws: t.iter().all(|&c| is_xml_space(c)),
                prefix: prefix.into(),
                underscore: cut.is_some(),
                class: class_of(prefix),
            });
        }
        if i >= n {
            break;
        }
        let inner_start = i + 1;
        i = inner_start;
        while i < n && b[i] != b']' && b[i] != b'>' {
            i += 1;
        }
        if i >= n {
            return None;
        }
        let inner = &b[inner_start..i];
        i += 1;
        toks.push(match inner.first() {
            None | Some(b'!') => Tok::Bad,
            Some(b'?') if inner.len() < 2 || inner[inner.len() - 1] != b'?' => Tok::Bad,
            Some(b'?') => Tok::Pi,
            Some(b'/') => {
                let mut name = &inner[1..];
                while let [rest @ .., last] = name {
                    if !is_xml_space(*last) {
                        break;
                    }
                    name = rest;
                }
                if valid_name(name) {
                    Tok::Close
                } else {
                    Tok::Bad
                }
            }
            Some(_) => {
                let (body, self_closing) = match inner {
                    [body @ .., b'/'] => (body, true),
                    _ => (inner, false),
                };
                let name_len = body.iter().position(|&c| is_xml_space(c)).unwrap_or(body.len());
                let name = &body[..name_len];
                if valid_name(name) {
                    Tok::Open { control: name == b"Sequence" || name == b"Selector", self_closing }
                } else {
                    Tok::Bad
                }
            }
        });
    }
    Some(toks)
}

/// The longest behaviour name (`CompositeSingleCarry`): a longer name is never one.
const LONGEST_NAME: usize = 20;

/// The name being read from an element's text. `Copy` (the name is kept inline, up to
/// the longest behaviour name), so the mapper can snapshot the whole scan cheaply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub(crate) struct PendingName {
    parts: u32,
    class: u8,
    closed: bool,
    /// The name so far; only read when it came in several parts.
    buf: [u8; LONGEST_NAME],
    len: u8,
    /// Longer than any behaviour name.
    overflow: bool,
}

impl PendingName {
    fn push(&mut self, prefix: &[u8], underscore: bool, class: u8) {
        if self.closed {
            return;
        }
        if self.parts == 0 {
            self.class = class;
            self.len = 0;
            self.overflow = false;
        }
        self.append(prefix);
        self.parts += 1;
        self.closed = underscore;
    }

    fn append(&mut self, bytes: &[u8]) {
        let at = self.len as usize;
        match self.buf.get_mut(at..at + bytes.len()) {
            Some(dst) if !self.overflow => {
                dst.copy_from_slice(bytes);
                self.len += bytes.len() as u8;
            }
            _ => self.overflow = true,
        }
    }

    fn class(&self) -> u8 {
        match self.parts {
            0 => 9,
            1 => self.class,
            _ if self.overflow => 9,
            _ => class_of(&self.buf[..self.len as usize]),
        }
    }
}

/// The effect of a run of tokens on [`DiversityScan`] while the element depth stays
/// positive, which holds for every run but the first and last of a phenotype: then no
/// well-formedness rule can fire, and the run is applied in O(1) instead of token by
/// token. `None` for runs with declarations, self-closing or malformed tags.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct RunEffect {
    /// Lowest depth reached inside the run, relative to its start (≤ 0).
    min_depth: i32,
    /// Depth change over the run.
    delta: i32,
    /// Text before the run's first tag: (name part, has `_`, class).
    lead: Option<(Box<[u8]>, bool, u8)>,
    has_tag: bool,
    /// Classes of the names the run completes after its first tag.
    completed: Box<[u8]>,
    /// The element whose text is still being read at the run's end.
    tail: Option<PendingName>,
}

impl RunEffect {
    pub(crate) fn of(toks: &[Tok]) -> Option<RunEffect> {
        let (mut depth, mut min_depth) = (0i32, 0i32);
        let mut lead = None;
        let mut has_tag = false;
        let mut completed = Vec::new();
        let mut reading: Option<PendingName> = None;
        for t in toks {
            match t {
                Tok::Text { prefix, underscore, class, .. } => {
                    if !has_tag {
                        lead = Some((prefix.clone(), *underscore, *class));
                    } else if let Some(r) = &mut reading {
                        r.push(prefix, *underscore, *class);
                    }
                }
                Tok::Open { control, self_closing: false } => {
                    has_tag = true;
                    if let Some(r) = reading.take() {
                        completed.push(r.class());
                    }
                    if !control {
                        reading = Some(PendingName::default());
                    }
                    depth += 1;
                }
                Tok::Close => {
                    has_tag = true;
                    if let Some(r) = reading.take() {
                        completed.push(r.class());
                    }
                    depth -= 1;
                    min_depth = min_depth.min(depth);
                }
                Tok::Open { self_closing: true, .. } | Tok::Pi | Tok::Bad => return None,
            }
        }
        Some(RunEffect { min_depth, delta: depth, lead, has_tag, completed: completed.into(), tail: reading })
    }
}

/// The [`count`] state machine fed with pre-scanned tokens, run after run, as the
/// mapper emits them. `Copy` and small, so a genetic step can keep it at a codon
/// (`ge::tape`).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) struct DiversityScan {
    counts: Counts,
    depth: u32,
    root_done: bool,
    bad: bool,
    /// Reading the text of a non-control element.
    collecting: bool,
    name: PendingName,
}

impl DiversityScan {
    pub(crate) fn reset(&mut self) {
        self.counts = Counts::default();
        self.depth = 0;
        self.root_done = false;
        self.bad = false;
        self.collecting = false;
    }

    #[inline]
    fn add_class(&mut self, class: u8) {
        self.counts.total += 1;
        match self.counts.per_behaviour.get_mut(class as usize) {
            Some(n) => *n += 1,
            None => self.counts.other = true,
        }
    }

    fn end_text(&mut self) {
        if self.collecting {
            self.collecting = false;
            self.add_class(self.name.class());
        }
    }

    fn start_text(&mut self) {
        self.collecting = true;
        self.name.parts = 0;
        self.name.closed = false;
    }

    /// Feed one run: in O(1) through its [`RunEffect`] when the depth stays positive,
    /// token by token otherwise.
    #[inline]
    pub(crate) fn feed_run(&mut self, toks: &[Tok], effect: Option<&RunEffect>) {
        match effect {
            Some(e) if !self.bad && self.depth as i32 + e.min_depth >= 1 => {
                if let Some((prefix, underscore, class)) = &e.lead {
                    if self.collecting {
                        self.name.push(prefix, *underscore, *class);
                    }
                }
                if e.has_tag {
                    self.end_text();
                    for &c in e.completed.iter() {
                        self.add_class(c);
                    }
                    if let Some(t) = &e.tail {
                        self.collecting = true;
                        self.name = *t;
                    }
                }
                self.depth = (self.depth as i32 + e.delta) as u32;
            }
            _ => self.feed(toks),
        }
    }

    pub(crate) fn feed(&mut self, toks: &[Tok]) {
        for t in toks {
            match t {
                Tok::Text { ws, prefix, underscore, class } => {
                    if self.depth == 0 && !ws {
                        self.bad = true;
                    }
                    if self.collecting {
                        self.name.push(prefix, *underscore, *class);
                    }
                }
                Tok::Open { control, self_closing } => {
                    self.end_text();
                    if self.root_done {
                        self.bad = true;
                    }
                    if !control {
                        self.start_text();
                        if *self_closing {
                            self.end_text();
                        }
                    }
                    if *self_closing {
                        self.root_done = self.depth == 0;
                    } else {
                        self.depth += 1;
                    }
                }
                Tok::Close => {
                    self.end_text();
                    if self.depth == 0 {
                        self.bad = true;
                    } else {
                        self.depth -= 1;
                        self.root_done = self.depth == 0;
                    }
                }
                Tok::Pi => {
                    self.end_text();
                    if self.depth > 0 {
                        self.bad = true;
                    }
                }
                Tok::Bad => self.bad = true,
            }
        }
    }

    /// The counts of everything fed since the last reset (`None` if not well-formed).
    fn finish_counts(&mut self) -> Option<Counts> {
        self.end_text();
        (!self.bad && self.depth == 0 && self.root_done).then_some(self.counts)
    }

    /// D of everything fed since the last reset (NaN if not well-formed).
    pub(crate) fn finish(&mut self) -> f64 {
        self.finish_counts().map_or(f64::NAN, |c| score(&c))
    }
}

/// Most totals the ceiling search tells apart: from 10 elements on the divisor is at
/// least 18, whatever the total.
const CEILING_TOTAL: u32 = 10;

impl DiversityScan {
    /// This state with everything the scan can no longer read cleared, each behaviour
    /// count capped at 1 and the total at [`CEILING_TOTAL`] (`ge::ceiling`). The scan
    /// decides nothing from its counts, so feeding the same runs to two states with the
    /// same abstraction gives states with the same abstraction.
    pub(crate) fn abstracted(&self) -> DiversityScan {
        let mut a = *self;
        for n in &mut a.counts.per_behaviour {
            *n = (*n).min(1);
        }
        a.counts.total = a.counts.total.min(CEILING_TOTAL);
        let name = &mut a.name;
        if !a.collecting {
            *name = PendingName::default();
        } else if name.parts == 0 {
            *name = PendingName { closed: name.closed, ..PendingName::default() };
        } else {
            name.parts = name.parts.min(2);
            let len = name.len as usize;
            name.buf[len..].fill(0);
        }
        a
    }

    /// An upper bound of D for any phenotype whose scan ends in a state with this
    /// abstraction (`None` if not well-formed): exact while the total is below
    /// [`CEILING_TOTAL`] and not all nine names alone occur, otherwise the largest D such
    /// counts allow (25 with all nine names alone, 25 · present / 18 from 10 elements).
    pub(crate) fn ceiling_of(mut self) -> Option<f64> {
        let c = self.finish_counts()?;
        let all_nine = !c.other && c.per_behaviour.iter().all(|&n| n > 0);
        Some(if all_nine { 25.0 } else { score(&c) })
    }
}

/// Diversity D of a phenotype string (§5.5), rounded to 4 decimals like Python's
/// `round(x, 4)`. NaN if the string is not well-formed.
///
/// End-tag names are not matched against their start tags here (the mapper only emits
/// balanced tags); [`super::parse_phenotype`] does check them.
pub fn diversity(phenotype: &str) -> f64 {
    match count(phenotype) {
        Some(c) => score(&c),
        None => f64::NAN,
    }
}

fn score(c: &Counts) -> f64 {
    const L: u32 = 9;
    let s = c.total;
    if s == 0 {
        return 0.0;
    }
    let present = c.per_behaviour.iter().filter(|&&n| n > 0).count() as u32;
    let keys_equal_b = !c.other && present == L;
    let d = if keys_equal_b {
        let mut sorted = c.per_behaviour;
        sorted.sort_unstable();
        let min = sorted[0];
        // S mod L = 0 and min = S/L, i.e. min·L = S.
        if min * L == s {
            1.0
        } else {
            // min ≤ ⌊S/L⌋ always holds when all nine names are present.
            let k = c.per_behaviour.iter().filter(|&&n| n > min).count() as u64;
            let second_largest = u64::from(sorted[sorted.len() - 2]);
            1.0 - (k * second_largest) as f64 / 100.0
        }
    } else {
        let divisor = s.div_ceil(L) * L;
        f64::from(present) / f64::from(divisor)
    };
    python_round4(d * 25.0)
}

/// Python's `round(x, 4)` for a float: the exact binary value rounded to 4 decimals
/// (ties to even), returned as the nearest double.
pub fn python_round4(x: f64) -> f64 {
    // Beyond 2^39 the spacing of doubles exceeds 1e-4, so x is its own rounding.
    if !x.is_finite() || x == 0.0 || x.abs() >= (1u64 << 39) as f64 {
        return x;
    }
    let bits = x.abs().to_bits();
    let exp_bits = ((bits >> 52) & 0x7ff) as i32;
    let frac = bits & ((1u64 << 52) - 1);
    let (mant, exp) = if exp_bits == 0 { (frac, -1074) } else { (frac | (1u64 << 52), exp_bits - 1075) };
    // |x| = mant · 2^exp; an integer needs no rounding.
    if exp >= 0 {
        return x;
    }
    let shift = exp.unsigned_abs();
    // mant · 10^4 < 2^67, so for shift ≥ 100 the quotient is 0 and the remainder < half.
    let q: u64 = if shift >= 100 {
        0
    } else {
        let v = u128::from(mant) * 10_000;
        let q = v >> shift;
        let rem = v - (q << shift);
        let half = 1u128 << (shift - 1);
        let up = rem > half || (rem == half && q & 1 == 1);
        (q + u128::from(up)) as u64
    };
    let r = q as f64 / 10_000.0;
    if x.is_sign_negative() {
        -r
    } else {
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::mapper::tests::{forge_golden, sf_golden, test_new_golden};
    use crate::ge::testdata::HEADER;
    use proptest::prelude::*;

    use crate::ge::phenotype::{PhenotypeError, Token, Tokenizer};

    /// Reference implementation of the scan on top of the phenotype tokenizer.
    pub(super) fn count_with_tokens(phenotype: &str) -> Result<Counts, PhenotypeError> {
        let mut t = Tokenizer::new(phenotype);
        let mut c = Counts::default();
        let mut depth = 0usize;
        let mut root_done = false;
        // A non-control start tag was just read; its text (if any) is the next token.
        let mut awaiting_text = false;
        while let Some(tok) = t.next_token()? {
            match tok {
                Token::Decl { offset } => {
                    if depth > 0 {
                        return Err(PhenotypeError::Unsupported { offset, text: String::new() });
                    }
                }
                Token::Text { text, offset } => {
                    if awaiting_text {
                        c.add(text.as_bytes());
                        awaiting_text = false;
                    } else if depth == 0 && !text.chars().all(char::is_whitespace) {
                        return Err(PhenotypeError::TextOutsideRoot { offset, text: text.to_string() });
                    }
                }
                Token::Start { name, self_closing, offset } => {
                    if root_done {
                        return Err(PhenotypeError::TrailingContent { offset });
                    }
                    if awaiting_text {
                        c.add(b"");
                    }
                    awaiting_text = !matches!(name, "Sequence" | "Selector");
                    if self_closing {
                        if awaiting_text {
                            c.add(b"");
                            awaiting_text = false;
                        }
                        root_done = depth == 0;
                    } else {
                        depth += 1;
                    }
                }
                Token::End { offset, name } => {
                    if awaiting_text {
                        c.add(b"");
                        awaiting_text = false;
                    }
                    if depth == 0 {
                        return Err(PhenotypeError::UnexpectedEndTag { offset, found: name.to_string() });
                    }
                    depth -= 1;
                    root_done = depth == 0;
                }
            }
        }
        if depth != 0 {
            return Err(PhenotypeError::Unclosed { tag: String::new() });
        }
        if !root_done {
            return Err(PhenotypeError::NoRoot);
        }
        Ok(c)
    }

    #[test]
    fn golden_values() {
        let forge = forge_golden();
        assert_eq!(diversity(&forge[0].3), 5.5556);
        assert_eq!(diversity(&forge[1].3), 8.3333);
        assert_eq!(diversity(&forge[2].3), 5.5556);
        let sf = sf_golden();
        assert_eq!(diversity(&sf[0].3), 5.5556);
        assert_eq!(diversity(&sf[1].3), 13.8889);
        assert_eq!(diversity(&test_new_golden().3), 6.9444);
    }

    #[test]
    fn spec_examples() {
        // Dummy + IsCarrying + CompositeDrop → 2/9·25.
        let p = format!("{HEADER}[Sequence][Selector][PostCnd]DummyNode[/PostCnd][Sequence][Sequence][PreCnd]IsCarrying_Food[/PreCnd][/Sequence][Act]CompositeDrop_Food[/Act][/Sequence][/Selector][/Sequence]");
        assert_eq!(diversity(&p), 5.5556);
        // NeighbourObjects + IsDropable + CompositeSingleCarry (+ an IsDropable constraint).
        let p = format!("{HEADER}[Sequence][Selector][Sequence][PostCnd]NeighbourObjects_Food[/PostCnd][/Sequence][Sequence][Sequence][PreCnd]IsDropable_Hub[/PreCnd][/Sequence][Sequence][Cnstr]IsDropable_Sites[/Cnstr][/Sequence][Act]CompositeSingleCarry_Food[/Act][/Sequence][/Selector][/Sequence]");
        assert_eq!(diversity(&p), 8.3333);
    }

    fn leaves(names: &[&str]) -> String {
        let mut s = String::from(HEADER);
        s.push_str("[Sequence]");
        for n in names {
            s.push_str("[L]");
            s.push_str(n);
            s.push_str("[/L]");
        }
        s.push_str("[/Sequence]");
        s
    }

    #[test]
    fn case_a_all_nine_equally_often() {
        assert_eq!(diversity(&leaves(&BEHAVIOURS)), 25.0);
        let twice: Vec<&str> = BEHAVIOURS.iter().chain(BEHAVIOURS.iter()).copied().collect();
        assert_eq!(diversity(&leaves(&twice)), 25.0);
    }

    #[test]
    fn case_b_all_nine_unequal() {
        // Counts 1×8, 2×1: subtract min 1 → one positive entry; second largest = 1.
        let mut names: Vec<&str> = BEHAVIOURS.to_vec();
        names.push("Explore_0_Avoid");
        assert_eq!(diversity(&leaves(&names)), python_round4((1.0 - 1.0 / 100.0) * 25.0));
        assert_eq!(diversity(&leaves(&names)), 24.75);
        // Counts 1×6, 3×3: k = 3, second largest 3 → 1 − 9/100.
        let mut names: Vec<&str> = BEHAVIOURS.to_vec();
        for n in &BEHAVIOURS[..3] {
            names.push(n);
            names.push(n);
        }
        assert_eq!(diversity(&leaves(&names)), 22.75);
    }

    #[test]
    fn usual_case_and_divisor() {
        // 10 leaves of 3 names, one not a behaviour: divisor ⌈10/9⌉·9 = 18, 2 matches.
        let names = [
            "MoveTowards_Hub",
            "Explore",
            "Explore",
            "CanMove",
            "CanMove",
            "CanMove",
            "CanMove",
            "CanMove",
            "CanMove",
            "CanMove",
        ];
        assert_eq!(diversity(&leaves(&names)), python_round4(2.0 / 18.0 * 25.0));
        assert_eq!(diversity(&leaves(&names)), 2.7778);
        // Nine behaviours plus an extra non-behaviour name: keys ≠ B → 9/18.
        let mut names: Vec<&str> = BEHAVIOURS.to_vec();
        names.push("DummyNode");
        assert_eq!(diversity(&leaves(&names)), 12.5);
        // Multi-GEESE action names only match the two composite behaviours.
        assert_eq!(diversity(&leaves(&["ExploreNormal", "MoveTowardsNormal", "CompositeDrop"])), 2.7778);
    }

    #[test]
    fn edge_cases() {
        assert!(diversity("").is_nan());
        assert!(diversity("[Sequence][L]x[/L]").is_nan());
        assert!(diversity("[Sequence][L]x[/L][/Sequence][Sequence][/Sequence]").is_nan());
        assert!(diversity("junk[Sequence][/Sequence]").is_nan());
        assert!(diversity("[Sequence][L]x[/L").is_nan());
        // No behaviour element at all: 0.
        assert_eq!(diversity("[Sequence][Selector][/Selector][/Sequence]"), 0.0);
        // Empty text counts as a (non-behaviour) name.
        assert_eq!(diversity("[Sequence][L][/L][M]Explore[/M][/Sequence]"), python_round4(1.0 / 9.0 * 25.0));
        // Text of an element is cut at the first underscore.
        assert_eq!(diversity("[Sequence][L]_Explore[/L][/Sequence]"), 0.0);
        // Whitespace between elements (sf.bnf) does not count.
        assert_eq!(diversity("[Sequence] [L]Explore[/L] [/Sequence] "), 2.7778);
    }

    #[test]
    fn python_rounding() {
        // Values checked against CPython's round(x, 4).
        assert_eq!(python_round4(0.03125), 0.0312);
        assert_eq!(python_round4(1.00005), 1.0001);
        assert_eq!(python_round4(2.00005), 2.0);
        assert_eq!(python_round4(0.00015), 0.0001);
        assert_eq!(python_round4(5.55555), 5.5556);
        assert_eq!(python_round4(0.12345), 0.1235);
        assert_eq!(python_round4(3.0 / 9.0 * 25.0), 8.3333);
        assert_eq!(python_round4(-0.12345), -0.1235);
        assert_eq!(python_round4(25.0), 25.0);
        assert_eq!(python_round4(1e-300), 0.0);
        assert!(python_round4(f64::NAN).is_nan());
    }

    proptest! {
        #[test]
        fn round4_matches_decimal_formatting_away_from_ties(x in -1.0e6f64..1.0e6) {
            // Rust's `{:.4}` is exact decimal rounding too; ties are measure-zero here.
            let via_fmt: f64 = format!("{x:.4}").parse().unwrap_or(f64::NAN);
            prop_assert_eq!(python_round4(x), via_fmt);
        }

        #[test]
        fn diversity_never_panics(s in "\\PC{0,60}") {
            let _ = diversity(&s);
        }

        #[test]
        fn fast_scan_agrees_with_tokenizer(
            parts in proptest::collection::vec(
                prop_oneof![
                    Just("[Sequence]"), Just("[/Sequence]"), Just("[Selector]"), Just("[/Selector ]"),
                    Just("[Act]"), Just("[/Act]"), Just("[PostCnd]"), Just("[/PostCnd]"), Just("[x/]"),
                    Just("Explore_0_Avoid"), Just("IsCarrying_Food"), Just("CanMove"), Just(" "), Just("["),
                    Just("]"), Just("[?xml?]"), Just("[?]"), Just("<"), Just(">"), Just("/"), Just("_"),
                    Just("[!--]"), Just("[a b]"), Just("[ a]"), Just("é"),
                ],
                0..30,
            )
        ) {
            let s = parts.concat();
            prop_assert_eq!(count(&s), count_with_tokens(&s).ok(), "{}", s);
        }
    }
}
