//! The documents a reader acts on: every command `docs/REPRODUCTION.md` gives parses, the
//! files it reads exist, and every figure and link of the report (and every figure path
//! named in the other documents) is there.
use geese_tests::repo_root;
use std::path::Path;
use std::process::Command;

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// The `geese …` commands of a Markdown text: inline code spans that start with `geese `
/// (a span may wrap onto the next line), and lines of fenced blocks that do (a trailing
/// `# comment` cut off).
fn geese_commands(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut fenced = false;
    let mut prose = String::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        } else if fenced {
            let cmd = line.split(" #").next().unwrap_or("").trim();
            if cmd.starts_with("geese ") {
                out.push(cmd.to_string());
            }
        } else {
            prose.push_str(line);
            prose.push('\n');
        }
    }
    // Inline spans: the text between odd and even backticks.
    for (i, span) in prose.split('`').enumerate() {
        let span = span.split_whitespace().collect::<Vec<_>>().join(" ");
        if i % 2 == 1 && span.starts_with("geese ") {
            out.push(span);
        }
    }
    out
}

/// Relative link targets of a Markdown text (`[text](target)`), without their anchor.
fn link_targets(text: &str) -> Vec<(String, Option<String>)> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("](") {
        rest = &rest[i + 2..];
        let Some(end) = rest.find(')') else { break };
        let target = &rest[..end];
        rest = &rest[end..];
        if target.contains("://") || target.starts_with("mailto:") || target.is_empty() {
            continue;
        }
        match target.split_once('#') {
            Some((file, anchor)) => out.push((file.to_string(), Some(anchor.to_string()))),
            None => out.push((target.to_string(), None)),
        }
    }
    out
}

/// GitHub's anchor of a heading: lower case, letters, digits, `-` and `_` kept, spaces
/// to `-`, everything else dropped.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            '-' | '_' => Some(c),
            c if c.is_alphanumeric() => Some(c),
            _ => None,
        })
        .flat_map(char::to_lowercase)
        .collect()
}

fn anchors(markdown: &str) -> Vec<String> {
    let mut fenced = false;
    let mut out = Vec::new();
    for line in markdown.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        } else if !fenced && line.starts_with('#') {
            out.push(slug(line.trim_start_matches('#')));
        }
    }
    out
}

/// Paths `docs/figures/….png` named anywhere in a text.
fn figure_paths(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("docs/figures/") {
        rest = &rest[i..];
        let end = rest.find(|c: char| c.is_whitespace() || "`)\"',;".contains(c)).unwrap_or(rest.len());
        let path = &rest[..end];
        if path.ends_with(".png") || path.ends_with(".svg") {
            out.push(path.to_string());
        }
        rest = &rest[end..];
    }
    out
}

#[test]
fn reproduction_report_commands_parse_and_its_figures_and_links_exist() {
    let root = repo_root();
    let report_path = root.join("docs/REPRODUCTION.md");
    let report = read(&report_path);
    let geese = geese_tests::bin_path("geese-orchestrator", "geese");
    let mut failures = Vec::new();

    let commands = geese_commands(&report);
    // The report gives a command for every claim; a parser that found none checked nothing.
    assert!(commands.len() >= 20, "only {} geese commands found in docs/REPRODUCTION.md", commands.len());
    for cmd in &commands {
        let args: Vec<&str> = cmd.split_whitespace().skip(1).collect();
        let out = Command::new(&geese).arg("--check-args").args(&args).output().expect("run geese");
        if !out.status.success() {
            failures.push(format!("`{cmd}` does not parse:\n{}", String::from_utf8_lossy(&out.stderr)));
        }
        // The inputs it reads from the repository (campaign files, configs, populations);
        // results/ is where earlier commands write.
        for a in &args {
            let input = [".toml", ".json", ".bnf"].iter().any(|e| a.ends_with(e)) && !a.starts_with("results/");
            if input && !root.join(a).exists() {
                failures.push(format!("`{cmd}` reads {a}, which does not exist"));
            }
        }
    }

    let links = link_targets(&report);
    let figures = links.iter().filter(|(f, _)| f.ends_with(".png")).count();
    assert!(figures >= 15, "only {figures} figure links found in docs/REPRODUCTION.md");
    for (file, anchor) in &links {
        let target =
            if file.is_empty() { report_path.clone() } else { report_path.parent().expect("docs/").join(file) };
        if !target.exists() {
            failures.push(format!("link target {file} does not exist"));
            continue;
        }
        if let (Some(anchor), true) = (anchor, target.extension().is_some_and(|e| e == "md")) {
            if !anchors(&read(&target)).contains(anchor) {
                failures.push(format!("{file} has no heading with anchor #{anchor}"));
            }
        }
    }
    for path in figure_paths(&report) {
        if !root.join(&path).exists() {
            failures.push(format!("figure {path} does not exist"));
        }
    }
    assert!(failures.is_empty(), "docs/REPRODUCTION.md:\n{}", failures.join("\n"));
}

#[test]
fn figures_and_links_named_in_the_documents_exist() {
    let root = repo_root();
    let mut docs = vec![root.join("README.md"), root.join("NOTES.md"), root.join("configs/locality.toml")];
    for dir in ["docs", "docs/research"] {
        for entry in std::fs::read_dir(root.join(dir)).expect("docs directory") {
            let path = entry.expect("docs entry").path();
            if path.extension().is_some_and(|e| e == "md") {
                docs.push(path);
            }
        }
    }
    let mut failures = Vec::new();
    let mut named = 0;
    for doc in &docs {
        let text = read(doc);
        for path in figure_paths(&text) {
            named += 1;
            if !root.join(&path).exists() {
                failures.push(format!("{} names {path}, which does not exist", doc.display()));
            }
        }
        if doc.extension().is_some_and(|e| e == "md") {
            for (file, anchor) in link_targets(&text) {
                let target = if file.is_empty() { doc.clone() } else { doc.parent().expect("dir").join(&file) };
                if !target.exists() {
                    failures.push(format!("{} links {file}, which does not exist", doc.display()));
                } else if let (Some(anchor), true) = (anchor, target.extension().is_some_and(|e| e == "md")) {
                    if !anchors(&read(&target)).contains(&anchor) {
                        failures.push(format!("{} links {file}#{anchor}: no such heading", doc.display()));
                    }
                }
            }
        }
    }
    assert!(named > 0, "no figure path found in the documents");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn slugs_and_extraction_follow_markdown() {
    assert_eq!(slug(" Fig. 9 / the combine phase (issue 16)"), "fig-9--the-combine-phase-issue-16");
    assert_eq!(slug("Départures — GEESE-BT"), "départures--geese-bt");
    let text = "Run `geese run -q` then\n```\ngeese report x.sqlite   # tables\nls\n```\n`cargo x` [a](b.md#c) [d](http://e) `geese\n  merge a b`";
    assert_eq!(geese_commands(text), ["geese report x.sqlite", "geese run -q", "geese merge a b"]);
    assert_eq!(link_targets(text), [("b.md".to_string(), Some("c".to_string()))]);
    assert_eq!(
        figure_paths("see `docs/figures/a.png`, docs/figures/b.svg)"),
        ["docs/figures/a.png", "docs/figures/b.svg"]
    );
}
