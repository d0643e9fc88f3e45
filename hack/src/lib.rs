//! No code: this crate only depends on other crates with features (see its
//! `Cargo.toml`), so that every build of `geese-agent` compiles them alike.
