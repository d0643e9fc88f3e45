//! The grammar files shipped with GEESE, embedded so a run needs no files on disk.
//!
//! Texts are byte-for-byte the reference grammars (REFERENCE.md §3, `grammars/README`),
//! plus the nest variants derived from them (`betr-nest-avoid`: `forge.bnf` with
//! Hub|Boundary and Debris; `geese-bt-nest`: `sf.bnf` likewise), and the union
//! variants (`betr-union-avoid`, `geese-bt-union`, `multi-collect-union`,
//! `multi-combine-union`): the foraging grammar with the objects of both tasks
//! (Hub|Sites|Boundary, Food|Debris), for runs whose task changes (`SwitchTask`,
//! issue 30.4), whose learners must be able to express the task that comes.

/// (name, text) of every built-in grammar.
pub const BUILTIN: &[(&str, &str)] = &[
    ("betr-foraging-avoid", include_str!("../grammars/betr-foraging-avoid.bnf")),
    ("betr-foraging-addition", include_str!("../grammars/betr-foraging-addition.bnf")),
    ("betr-nest-avoid", include_str!("../grammars/betr-nest-avoid.bnf")),
    ("betr-nest-addition", include_str!("../grammars/betr-nest-addition.bnf")),
    ("betr-table2-reference", include_str!("../grammars/betr-table2-reference.bnf")),
    ("geese-bt-foraging", include_str!("../grammars/geese-bt-foraging.bnf")),
    ("geese-bt-nest", include_str!("../grammars/geese-bt-nest.bnf")),
    ("multi-collect-foraging", include_str!("../grammars/multi-collect-foraging.bnf")),
    ("multi-collect-nest", include_str!("../grammars/multi-collect-nest.bnf")),
    ("multi-combine-foraging", include_str!("../grammars/multi-combine-foraging.bnf")),
    ("multi-combine-nest", include_str!("../grammars/multi-combine-nest.bnf")),
    ("betr-union-avoid", include_str!("../grammars/betr-union-avoid.bnf")),
    ("geese-bt-union", include_str!("../grammars/geese-bt-union.bnf")),
    ("multi-collect-union", include_str!("../grammars/multi-collect-union.bnf")),
    ("multi-combine-union", include_str!("../grammars/multi-combine-union.bnf")),
];

/// The text of a built-in grammar by name (with or without `.bnf`).
pub fn builtin(name: &str) -> Option<&'static str> {
    let name = name.strip_suffix(".bnf").unwrap_or(name);
    BUILTIN.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// Names of the built-in grammars.
pub fn names() -> impl Iterator<Item = &'static str> {
    BUILTIN.iter().map(|(n, _)| *n)
}
