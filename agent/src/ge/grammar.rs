//! BNF grammars read with PonyGE2's conventions (REFERENCE.md §3.1) plus the
//! pre-computation of §5.2.
//!
//! Why this exists: a genome means nothing without its grammar. Codon → choice numbering
//! (`codon % number_of_alternatives`, alternatives in file order, unit rules consuming a
//! codon) and the terminal tokenisation must match PonyGE2 exactly, or golden genomes map
//! to different programs. The per-rule `min_steps`, per-alternative `max_path`,
//! `max_arity` and `min_path` values drive the `uniform_tree` initialiser.
//!
//! Conventions (one rule per line):
//! * `<name> ::= alt | alt | …`; the first rule is the start rule; `#` starts a comment
//!   that runs to the end of the line; blank lines are ignored.
//! * Each alternative is trimmed; empty alternatives are skipped (as PonyGE2's regex
//!   does), so `a | | b` has two choices.
//! * Every maximal run of characters between non-terminal references is one terminal,
//!   spaces included.
//! * Deliberate deviations from PonyGE2, all of which are absent from the reference
//!   grammars: quote characters (`'`, `"`) are rejected instead of being given PonyGE2's
//!   quoting meaning (they would change tokenisation and choice counts); backslash escapes
//!   are kept literally; a rule cannot continue on the next line; `<` must start a
//!   well-formed `<name>` reference.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};

use super::ceiling::{Bound, Ceilings};
use super::compiled::Compiled;

/// One symbol of an alternative: an index into [`Grammar::terminal`] or into the rules.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Symbol {
    /// Terminal string id (see [`Grammar::terminal`]).
    Terminal(u32),
    /// Rule id (see [`Grammar::rule`]); rule 0 is the start rule.
    NonTerminal(u32),
}

/// One alternative (production choice) of a rule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Alternative {
    pub(crate) symbols: Box<[Symbol]>,
    pub(crate) max_path: u32,
    pub(crate) nt_count: u32,
    /// The symbols right to left, packed for the mapper's stack ([`pack_symbol`]).
    pub(crate) packed_rev: Box<[u64]>,
}

/// Bit marking a non-terminal in a packed symbol.
pub(crate) const PACKED_NT: u64 = 1 << 31;

/// Pack a symbol into the low 32 bits of a mapper stack entry (the high 32 bits carry the
/// depth): terminal id, or rule id with [`PACKED_NT`] set.
pub(crate) fn pack_symbol(s: Symbol) -> u64 {
    match s {
        Symbol::Terminal(t) => u64::from(t),
        Symbol::NonTerminal(r) => PACKED_NT | u64::from(r),
    }
}

impl Alternative {
    /// The symbols, left to right.
    pub fn symbols(&self) -> &[Symbol] {
        &self.symbols
    }
    /// §5.2 `max_path`: the largest `min_steps` over the alternative's symbols (terminals 0).
    pub fn max_path(&self) -> u32 {
        self.max_path
    }
    /// Number of non-terminal symbols.
    pub fn nt_count(&self) -> usize {
        self.nt_count as usize
    }
}

/// One rule (`<name> ::= …`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rule {
    pub(crate) name: String,
    pub(crate) line: usize,
    pub(crate) alternatives: Vec<Alternative>,
    pub(crate) min_steps: u32,
    pub(crate) min_path: Vec<u32>,
    /// Multiplier for [`fast_mod`] by the number of alternatives.
    pub(crate) mod_magic: u64,
}

/// `a % d` for `d = alternatives`, without a division (Lemire, Kaser & Kurz 2019,
/// "Faster remainder by direct computation"): exact for every `u32` `a` and `d ≥ 1`
/// when `magic = u64::MAX / d + 1` (wrapping, so 0 for `d = 1`).
#[inline]
pub(crate) fn fast_mod(a: u32, magic: u64, d: u32) -> u32 {
    ((u128::from(magic.wrapping_mul(u64::from(a))) * u128::from(d)) >> 64) as u32
}

/// The [`fast_mod`] multiplier for divisor `d ≥ 1`.
pub(crate) fn mod_magic(d: u32) -> u64 {
    (u64::MAX / u64::from(d.max(1))).wrapping_add(1)
}

impl Rule {
    /// Name without the angle brackets (`root` for `<root>`).
    pub fn name(&self) -> &str {
        &self.name
    }
    /// 1-based line of the definition.
    pub fn line(&self) -> usize {
        self.line
    }
    /// Alternatives in file order (codon `c` picks `c % len`).
    pub fn alternatives(&self) -> &[Alternative] {
        &self.alternatives
    }
    /// §5.2 `min_steps` (the level at which the rule first can terminate; ≥ 1).
    pub fn min_steps(&self) -> u32 {
        self.min_steps
    }
    /// §5.2 `min_path`: indices of the alternatives with the smallest `max_path`.
    pub fn min_path(&self) -> &[u32] {
        &self.min_path
    }
}

/// A parsed, checked and pre-computed grammar.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Grammar {
    rules: Vec<Rule>,
    terminals: Vec<Box<str>>,
    by_name: HashMap<String, u32>,
    max_arity: u32,
    max_alternatives: usize,
    /// Runs-and-non-terminals form for the mapper's hot path.
    compiled: Compiled,
    /// The highest D of a valid individual, per depth limit (`ge::ceiling`).
    ceilings: Ceilings,
    /// Which parse this is, for caches of what its derivations write.
    uid: Uid,
}

/// A number no other grammar parsed in this process has (its clones share it, being
/// the same grammar): caches that hold what a grammar's derivations write (run ids,
/// `ge::operators`) key by it, as one process may hold several grammars (Multi-GEESE).
/// Not part of a grammar's value: grammars compare equal by their rules.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Uid(pub(crate) u64);

impl Uid {
    fn next() -> Uid {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        Uid(NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed))
    }
}

impl PartialEq for Uid {
    fn eq(&self, _: &Uid) -> bool {
        true
    }
}
impl Eq for Uid {}

/// Why a grammar text (or file) was rejected. Lines and columns are 1-based.
#[derive(Debug, thiserror::Error)]
pub enum GrammarError {
    #[error("grammar is empty: it contains no rule definitions")]
    Empty,
    #[error("line {line}: missing `::=` (every non-blank, non-comment line must be `<name> ::= alternatives`)")]
    MissingDefinition { line: usize },
    #[error(
        "line {line}: bad left-hand side `{lhs}`: expected exactly one non-terminal such as `<name>` before `::=`"
    )]
    BadLhs { line: usize, lhs: String },
    #[error("line {line}: rule <{name}> is defined a second time (first definition on line {first_line})")]
    DuplicateRule { line: usize, name: String, first_line: usize },
    #[error("line {line}: rule <{name}> has no alternatives after `::=`")]
    NoAlternatives { line: usize, name: String },
    #[error("line {line}, column {column}: unterminated `<`: a non-terminal reference must be closed by `>`")]
    UnterminatedNonTerminal { line: usize, column: usize },
    #[error("line {line}, column {column}: malformed non-terminal reference `{text}`: the name between `<` and `>` must be non-empty and contain no whitespace or `<`")]
    BadReference { line: usize, column: usize, text: String },
    #[error("line {line}, column {column}: quote character {quote:?} is not supported in terminals (PonyGE2 gives quotes a special meaning; the reference grammars write `%` for `\"`)")]
    UnsupportedQuote { line: usize, column: usize, quote: char },
    #[error("line {line}: reference to undefined non-terminal <{name}>")]
    UndefinedNonTerminal { line: usize, name: String },
    #[error("line {line}: non-terminal <{name}> can never derive a string of terminals (each of its alternatives needs a non-terminal that never terminates)")]
    NonTerminating { line: usize, name: String },
    #[error("cannot read grammar file {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("grammar file {path}: {source}")]
    InFile {
        path: PathBuf,
        #[source]
        source: Box<GrammarError>,
    },
}

/// A symbol while parsing, before references are resolved.
enum RawSym {
    T(u32),
    N { name: String },
}

struct RawRule {
    name: String,
    line: usize,
    alternatives: Vec<Vec<RawSym>>,
}

/// Byte offset of `inner` inside `outer` (both must point into the same string).
fn offset_in(outer: &str, inner: &str) -> usize {
    (inner.as_ptr() as usize).saturating_sub(outer.as_ptr() as usize)
}

/// 1-based character column of byte offset `off` in `line`.
fn column(line: &str, off: usize) -> usize {
    line.get(..off).map_or(off, |s| s.chars().count()) + 1
}

fn valid_nt_name(name: &str) -> bool {
    !name.is_empty() && !name.chars().any(|c| c.is_whitespace() || c == '<' || c == '>')
}

impl Grammar {
    /// Parse and pre-compute a grammar text.
    pub fn parse(text: &str) -> Result<Grammar, GrammarError> {
        let mut raw: Vec<RawRule> = Vec::new();
        let mut index: HashMap<String, usize> = HashMap::new();
        let mut terminals: Vec<Box<str>> = Vec::new();
        let mut term_ids: HashMap<String, u32> = HashMap::new();

        for (i, full_line) in text.lines().enumerate() {
            let line = i + 1;
            let content = match full_line.find('#') {
                Some(p) => &full_line[..p],
                None => full_line,
            };
            if content.trim().is_empty() {
                continue;
            }
            let Some(def) = content.find("::=") else {
                return Err(GrammarError::MissingDefinition { line });
            };
            let lhs = content[..def].trim();
            let name = lhs
                .strip_prefix('<')
                .and_then(|s| s.strip_suffix('>'))
                .filter(|n| valid_nt_name(n))
                .ok_or_else(|| GrammarError::BadLhs { line, lhs: lhs.to_string() })?;
            if let Some(&first) = index.get(name) {
                return Err(GrammarError::DuplicateRule { line, name: name.to_string(), first_line: raw[first].line });
            }
            let rhs = &content[def + 3..];
            let mut alternatives = Vec::new();
            for part in rhs.split('|') {
                let alt = part.trim();
                if alt.is_empty() {
                    continue;
                }
                let base = offset_in(full_line, alt);
                alternatives.push(parse_alternative(alt, full_line, base, line, &mut terminals, &mut term_ids)?);
            }
            if alternatives.is_empty() {
                return Err(GrammarError::NoAlternatives { line, name: name.to_string() });
            }
            index.insert(name.to_string(), raw.len());
            raw.push(RawRule { name: name.to_string(), line, alternatives });
        }
        if raw.is_empty() {
            return Err(GrammarError::Empty);
        }

        // Resolve references.
        let mut rules = Vec::with_capacity(raw.len());
        for r in raw {
            let mut alternatives = Vec::with_capacity(r.alternatives.len());
            for alt in r.alternatives {
                let mut symbols = Vec::with_capacity(alt.len());
                let mut nt_count = 0u32;
                for s in alt {
                    symbols.push(match s {
                        RawSym::T(t) => Symbol::Terminal(t),
                        RawSym::N { name } => match index.get(&name) {
                            Some(&id) => {
                                nt_count += 1;
                                Symbol::NonTerminal(id as u32)
                            }
                            None => return Err(GrammarError::UndefinedNonTerminal { line: r.line, name }),
                        },
                    });
                }
                let packed_rev = symbols.iter().rev().map(|&s| pack_symbol(s)).collect();
                alternatives.push(Alternative {
                    symbols: symbols.into_boxed_slice(),
                    max_path: 0,
                    nt_count,
                    packed_rev,
                });
            }
            let mod_magic = mod_magic(alternatives.len() as u32);
            rules.push(Rule {
                name: r.name,
                line: r.line,
                alternatives,
                min_steps: 0,
                min_path: Vec::new(),
                mod_magic,
            });
        }

        let by_name = index.into_iter().map(|(k, v)| (k, v as u32)).collect();
        let mut g = Grammar {
            rules,
            terminals,
            by_name,
            max_arity: 0,
            max_alternatives: 0,
            compiled: Compiled::default(),
            ceilings: Ceilings::default(),
            uid: Uid::next(),
        };
        g.precompute()?;
        g.compiled = Compiled::build(&g);
        Ok(g)
    }

    /// Read and parse a grammar file; errors name the path.
    pub fn load(path: impl AsRef<Path>) -> Result<Grammar, GrammarError> {
        let path = path.as_ref();
        let text =
            std::fs::read_to_string(path).map_err(|source| GrammarError::Io { path: path.to_path_buf(), source })?;
        Grammar::parse(&text).map_err(|e| GrammarError::InFile { path: path.to_path_buf(), source: Box::new(e) })
    }

    /// §5.2: levelled `min_steps`, per-alternative `max_path`, `max_arity`, `min_path`.
    fn precompute(&mut self) -> Result<(), GrammarError> {
        let n = self.rules.len();
        let mut level = vec![0u32; n];
        let mut counter = 1u32;
        loop {
            let newly: Vec<usize> = (0..n)
                .filter(|&r| level[r] == 0)
                .filter(|&r| {
                    self.rules[r].alternatives.iter().any(|a| {
                        a.symbols.iter().all(|s| match *s {
                            Symbol::Terminal(_) => true,
                            Symbol::NonTerminal(c) => level[c as usize] != 0,
                        })
                    })
                })
                .collect();
            if newly.is_empty() {
                break;
            }
            for r in newly {
                level[r] = counter;
            }
            counter += 1;
        }
        if let Some(r) = (0..n).find(|&r| level[r] == 0) {
            return Err(GrammarError::NonTerminating { line: self.rules[r].line, name: self.rules[r].name.clone() });
        }
        for (rule, &l) in self.rules.iter_mut().zip(&level) {
            rule.min_steps = l;
        }
        self.max_arity = level.iter().copied().max().unwrap_or(0);
        self.max_alternatives = self.rules.iter().map(|r| r.alternatives.len()).max().unwrap_or(0);
        for rule in &mut self.rules {
            for alt in &mut rule.alternatives {
                alt.max_path = alt
                    .symbols
                    .iter()
                    .map(|s| match *s {
                        Symbol::Terminal(_) => 0,
                        Symbol::NonTerminal(c) => level[c as usize],
                    })
                    .max()
                    .unwrap_or(0);
            }
            let best = rule.alternatives.iter().map(|a| a.max_path).min().unwrap_or(0);
            rule.min_path = (0..rule.alternatives.len() as u32)
                .filter(|&i| rule.alternatives[i as usize].max_path == best)
                .collect();
        }
        Ok(())
    }

    /// The start rule's id (always 0: the first rule of the file).
    pub fn start(&self) -> u32 {
        0
    }
    /// All rules in file order (index = rule id).
    pub fn rules(&self) -> &[Rule] {
        &self.rules
    }
    /// Rule by id. Panics on an id not produced by this grammar.
    pub fn rule(&self, id: u32) -> &Rule {
        &self.rules[id as usize]
    }
    /// Rule id by name, with or without angle brackets.
    pub fn rule_id(&self, name: &str) -> Option<u32> {
        let name = name.strip_prefix('<').and_then(|s| s.strip_suffix('>')).unwrap_or(name);
        self.by_name.get(name).copied()
    }
    /// Rule by name, with or without angle brackets.
    pub fn rule_by_name(&self, name: &str) -> Option<&Rule> {
        self.rule_id(name).map(|id| self.rule(id))
    }
    pub(crate) fn compiled(&self) -> &Compiled {
        &self.compiled
    }
    /// This parse's [`Uid`].
    pub(crate) fn uid(&self) -> Uid {
        self.uid
    }
    /// The highest diversity D a valid individual can score under the depth limit
    /// `max_tree_depth` (0 = none), when the grammar allows finding it (`ge::ceiling`).
    pub fn d_ceiling(&self, max_tree_depth: usize) -> Option<f64> {
        self.d_bound(max_tree_depth).d
    }
    /// Whether an individual can map valid yet deeper than `max_tree_depth` (only its
    /// very last symbol can be); `true` when unknown.
    #[cfg(test)]
    pub(crate) fn deep_last_possible(&self, max_tree_depth: usize) -> bool {
        self.d_bound(max_tree_depth).deep_last
    }
    /// Both of the above from one look-up (a genetic step needs both).
    pub(crate) fn d_bound(&self, max_tree_depth: usize) -> Bound {
        self.ceilings.get(&self.compiled, self.start(), max_tree_depth)
    }
    /// Terminal string by id. Panics on an id not produced by this grammar.
    pub fn terminal(&self, id: u32) -> &str {
        &self.terminals[id as usize]
    }
    /// Number of distinct terminal strings.
    pub fn terminal_count(&self) -> usize {
        self.terminals.len()
    }
    /// §5.2 `max_arity`: the largest `min_steps` of any rule.
    pub fn max_arity(&self) -> u32 {
        self.max_arity
    }
    /// The largest number of alternatives of any rule (CODON_SIZE must exceed it for the
    /// initialiser to draw codons the way PonyGE2 does).
    pub fn max_alternatives(&self) -> usize {
        self.max_alternatives
    }
}

fn parse_alternative(
    alt: &str,
    full_line: &str,
    base: usize,
    line: usize,
    terminals: &mut Vec<Box<str>>,
    term_ids: &mut HashMap<String, u32>,
) -> Result<Vec<RawSym>, GrammarError> {
    let bytes = alt.as_bytes();
    let mut out = Vec::new();
    let mut term_start = 0usize;
    let mut i = 0usize;
    let mut flush = |from: usize, to: usize, out: &mut Vec<RawSym>| {
        if to > from {
            let t = &alt[from..to];
            let id = *term_ids.entry(t.to_string()).or_insert_with(|| {
                terminals.push(t.into());
                (terminals.len() - 1) as u32
            });
            out.push(RawSym::T(id));
        }
    };
    while i < bytes.len() {
        match bytes[i] {
            b'<' => {
                let Some(rel) = alt[i + 1..].find('>') else {
                    return Err(GrammarError::UnterminatedNonTerminal { line, column: column(full_line, base + i) });
                };
                let j = i + 1 + rel;
                let name = &alt[i + 1..j];
                if !valid_nt_name(name) {
                    return Err(GrammarError::BadReference {
                        line,
                        column: column(full_line, base + i),
                        text: alt[i..=j].to_string(),
                    });
                }
                flush(term_start, i, &mut out);
                out.push(RawSym::N { name: name.to_string() });
                i = j + 1;
                term_start = i;
            }
            q @ (b'"' | b'\'') => {
                return Err(GrammarError::UnsupportedQuote {
                    line,
                    column: column(full_line, base + i),
                    quote: q as char,
                });
            }
            _ => i += 1,
        }
    }
    flush(term_start, bytes.len(), &mut out);
    Ok(out)
}

impl fmt::Display for Grammar {
    /// The grammar in BNF, one rule per line (terminals verbatim).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for rule in &self.rules {
            write!(f, "<{}> ::=", rule.name)?;
            for (k, alt) in rule.alternatives.iter().enumerate() {
                f.write_str(if k == 0 { " " } else { " | " })?;
                for s in alt.symbols.iter() {
                    match *s {
                        Symbol::Terminal(t) => f.write_str(self.terminal(t))?,
                        Symbol::NonTerminal(r) => write!(f, "<{}>", self.rules[r as usize].name)?,
                    }
                }
            }
            writeln!(f)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::testdata::{FORGE, SF, TEST_NEW};

    fn g(text: &str) -> Grammar {
        match Grammar::parse(text) {
            Ok(g) => g,
            Err(e) => panic!("grammar failed to parse: {e}"),
        }
    }

    fn err(text: &str) -> GrammarError {
        match Grammar::parse(text) {
            Ok(_) => panic!("grammar unexpectedly parsed: {text:?}"),
            Err(e) => e,
        }
    }

    #[test]
    fn reference_grammars_parse() {
        let forge = g(FORGE);
        assert_eq!(forge.rules().len(), 20);
        assert_eq!(forge.rule(forge.start()).name(), "s");
        let sf = g(SF);
        assert_eq!(sf.rules().len(), 11);
        assert_eq!(sf.rule(0).name(), "s");
        let tn = g(TEST_NEW);
        assert_eq!(tn.rules().len(), 26);
        for (name, text) in crate::grammars::BUILTIN {
            if let Err(e) = Grammar::parse(text) {
                panic!("built-in grammar {name} failed: {e}");
            }
        }
    }

    #[test]
    fn forge_precompute_matches_reference() {
        let forge = g(FORGE);
        let expect = [
            ("s", 8),
            ("root", 7),
            ("sequence", 6),
            ("selector", 6),
            ("ppa", 5),
            ("ppasequence", 4),
            ("preconditions", 4),
            ("postcondition", 3),
            ("precondition", 3),
            ("constraints", 3),
            ("postconditions", 2),
            ("postconditiont", 2),
            ("preconditiont", 2),
            ("constraint", 2),
            ("objects", 2),
            ("constraintt", 1),
            ("action", 1),
            ("sobjects", 1),
            ("dobjects", 1),
            ("SuccessNode", 1),
        ];
        for (name, steps) in expect {
            let r = forge.rule_by_name(name).unwrap_or_else(|| panic!("missing rule {name}"));
            assert_eq!(r.min_steps(), steps, "min_steps of <{name}>");
        }
        assert_eq!(forge.max_arity(), 8);
        assert_eq!(forge.max_alternatives(), 7);

        let paths = |name: &str| -> Vec<u32> {
            forge
                .rule_by_name(name)
                .map(|r| r.alternatives().iter().map(|a| a.max_path()).collect())
                .unwrap_or_default()
        };
        let min_path = |name: &str| forge.rule_by_name(name).map(|r| r.min_path().to_vec()).unwrap_or_default();
        assert_eq!(paths("root"), vec![6, 6]);
        assert_eq!(min_path("root"), vec![0, 1]);
        assert_eq!(paths("sequence"), vec![5, 7, 7]);
        assert_eq!(min_path("sequence"), vec![0]);
        assert_eq!(paths("postconditions"), vec![1, 5, 3]);
        assert_eq!(min_path("postconditions"), vec![0]);
        assert_eq!(paths("ppasequence"), vec![4, 3, 4]);
        assert_eq!(min_path("ppasequence"), vec![1]);
        assert_eq!(paths("objects"), vec![1, 1]);
        assert_eq!(paths("sobjects"), vec![0, 0]);
        assert_eq!(paths("postcondition"), vec![3, 2]);
        assert_eq!(min_path("postcondition"), vec![1]);
    }

    #[test]
    fn terminal_runs_are_single_symbols_including_spaces() {
        let forge = g(FORGE);
        let seq = forge.rule_by_name("<sequence>").expect("sequence");
        let alt = &seq.alternatives()[2];
        let shown: Vec<String> = alt
            .symbols()
            .iter()
            .map(|s| match *s {
                Symbol::Terminal(t) => format!("T{:?}", forge.terminal(t)),
                Symbol::NonTerminal(r) => format!("<{}>", forge.rule(r).name()),
            })
            .collect();
        assert_eq!(shown, vec!["T\"[Sequence]\"", "<sequence>", "T\" \"", "<root>", "T\"[/Sequence]\""]);
        // `<ppasequence> ::=  [Sequence]…` (two spaces) is trimmed.
        let ppas = forge.rule_by_name("ppasequence").expect("ppasequence");
        match ppas.alternatives()[0].symbols()[0] {
            Symbol::Terminal(t) => assert_eq!(forge.terminal(t), "[Sequence]"),
            Symbol::NonTerminal(_) => panic!("expected a terminal"),
        }
        // `<preconditiont> ::=IsDropable_<sobjects>|…`: no space after `::=`, bare `|`.
        let pre = forge.rule_by_name("preconditiont").expect("preconditiont");
        assert_eq!(pre.alternatives().len(), 7);
        match pre.alternatives()[2].symbols() {
            [Symbol::Terminal(a), Symbol::NonTerminal(_), Symbol::Terminal(b)] => {
                assert_eq!(forge.terminal(*a), "NeighbourObjects_");
                assert_eq!(forge.terminal(*b), "_invert");
            }
            other => panic!("unexpected symbols {other:?}"),
        }
        // The start rule: header terminal then <root>.
        match forge.rule(0).alternatives()[0].symbols() {
            [Symbol::Terminal(h), Symbol::NonTerminal(r)] => {
                assert_eq!(forge.terminal(*h), "[?xml version=%1.0% encoding=%UTF-8%?]");
                assert_eq!(forge.rule(*r).name(), "root");
            }
            other => panic!("unexpected start rule {other:?}"),
        }
    }

    #[test]
    fn comments_blank_lines_and_empty_alternatives() {
        let gr = g("# a comment\n\n<a> ::= x <b> | | y # trailing comment\n   \n<b>::=z|w\n");
        assert_eq!(gr.rules().len(), 2);
        assert_eq!(gr.rule(0).alternatives().len(), 2, "empty alternative skipped");
        assert_eq!(gr.rule(1).alternatives().len(), 2);
        assert_eq!(gr.rule(1).line(), 5);
        let shown = gr.to_string();
        assert_eq!(shown, "<a> ::= x <b> | y\n<b> ::= z | w\n");
    }

    #[test]
    fn error_missing_definition_names_line() {
        let e = err("<a> ::= x\n\n<b> x | y\n");
        assert!(matches!(e, GrammarError::MissingDefinition { line: 3 }), "{e:?}");
        assert!(e.to_string().contains("line 3"), "{e}");
        assert!(e.to_string().contains("::="), "{e}");
    }

    #[test]
    fn error_bad_lhs() {
        for text in ["a ::= x\n", "<a> <b> ::= x\n", "<> ::= x\n", "<a b> ::= x\n", " ::= x\n"] {
            let e = err(text);
            assert!(matches!(e, GrammarError::BadLhs { line: 1, .. }), "{text:?}: {e:?}");
            assert!(e.to_string().contains("line 1"), "{e}");
        }
    }

    #[test]
    fn error_undefined_nonterminal_named() {
        let e = err("<a> ::= x<b>\n<b> ::= y | <foo>z\n");
        assert!(matches!(&e, GrammarError::UndefinedNonTerminal { line: 2, name } if name == "foo"), "{e:?}");
        let msg = e.to_string();
        assert!(msg.contains("<foo>") && msg.contains("line 2"), "{msg}");
    }

    #[test]
    fn error_duplicate_rule() {
        let e = err("<a> ::= x<b>\n<b> ::= y\n# c\n<b> ::= z\n");
        assert!(matches!(&e, GrammarError::DuplicateRule { line: 4, name, first_line: 2 } if name == "b"), "{e:?}");
        assert!(e.to_string().contains("line 4") && e.to_string().contains("line 2"), "{e}");
    }

    #[test]
    fn error_empty_file() {
        assert!(matches!(err(""), GrammarError::Empty));
        assert!(matches!(err("# only a comment\n\n   \n"), GrammarError::Empty));
    }

    #[test]
    fn error_unterminated_and_bad_reference() {
        let e = err("<a> ::= x\n<b> ::= [Sequence]<root[/Sequence]\n");
        assert!(matches!(e, GrammarError::UnterminatedNonTerminal { line: 2, column: 19 }), "{e:?}");
        assert!(e.to_string().contains("line 2"), "{e}");
        let e = err("<a> ::= x <b c> y\n");
        assert!(matches!(e, GrammarError::BadReference { line: 1, column: 11, .. }), "{e:?}");
        let e = err("<a> ::= x <> y\n");
        assert!(matches!(e, GrammarError::BadReference { line: 1, .. }), "{e:?}");
    }

    #[test]
    fn error_no_alternatives_and_quotes() {
        let e = err("<a> ::= x<b>\n<b> ::=   | \n");
        assert!(matches!(&e, GrammarError::NoAlternatives { line: 2, name } if name == "b"), "{e:?}");
        let e = err("<a> ::= say \"hi\"\n");
        assert!(matches!(e, GrammarError::UnsupportedQuote { line: 1, column: 13, quote: '"' }), "{e:?}");
    }

    #[test]
    fn error_non_terminating() {
        let e = err("<a> ::= x<b> | y\n<b> ::= <b>z | <c>\n<c> ::= <b>\n");
        assert!(matches!(&e, GrammarError::NonTerminating { line: 2, name } if name == "b"), "{e:?}");
        assert!(e.to_string().contains("<b>"), "{e}");
        // Also when the start rule itself cannot terminate.
        let e = err("<a> ::= x<a>\n");
        assert!(matches!(e, GrammarError::NonTerminating { line: 1, .. }), "{e:?}");
    }

    #[test]
    fn load_names_path() {
        let path = std::env::temp_dir().join("geese-ge-no-such-dir/none.bnf");
        let e = match Grammar::load(&path) {
            Ok(_) => panic!("loading a missing file succeeded"),
            Err(e) => e,
        };
        assert!(matches!(e, GrammarError::Io { .. }), "{e:?}");
        assert!(e.to_string().contains("none.bnf"), "{e}");

        let dir = std::env::temp_dir().join(format!("geese-ge-grammar-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let bad = dir.join("bad.bnf");
        std::fs::write(&bad, "<a> ::= <zz>\n").expect("write");
        let e = match Grammar::load(&bad) {
            Ok(_) => panic!("bad grammar loaded"),
            Err(e) => e,
        };
        let msg = e.to_string();
        assert!(msg.contains("bad.bnf") && msg.contains("<zz>") && msg.contains("line 1"), "{msg}");
        let good = dir.join("good.bnf");
        std::fs::write(&good, FORGE).expect("write");
        let loaded = Grammar::load(&good).expect("load forge");
        assert_eq!(loaded, g(FORGE));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
