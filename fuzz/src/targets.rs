//! The registry of fuzz targets.
//!
//! Each target takes arbitrary bytes and hands them to the decoder or parser that a
//! GEESE binary runs on what it receives or reads, with the checks and the follow-up
//! decoding the binary does (a pack's nested batches are opened, a batch's genomes
//! decoded into the inbox, a phenotype built into a tree), because a panic can hide in
//! what is done with a decoded value as well as in the decoding. A target's only
//! contract is: return, whatever the bytes, quickly and without panicking. Errors are
//! expected and ignored; `black_box` keeps the optimiser from skipping work whose
//! result is unused.
use crate::corpus;
use crate::corpus::Seeds;
use geese_agent::bt::Bt;
use geese_agent::ge::{diversity, evaluate, parse_phenotype, GeParams, Grammar};
use geese_agent::inbox::Inbox;
use geese_agent::{grammars, LearnerConfig};
use geese_orchestrator::campaigns::campaign::Campaign;
use geese_orchestrator::RunConfig;
use geese_proto::keys::AgentRange;
use geese_proto::net::{
    unpack, GeneBatch, GeneBatchCell, GeneBatchHead, GeneBundle, HostGenes, HostPercepts, IntentBatch, NetReport, Raw,
    ReportMsg, RunInfo, Tick, AHEAD_CELL, NO_CELL,
};
use geese_proto::{decode, genome_codons_into, Control, GeneMsg, Geometry, Intent, Percept, StepReport};
use std::borrow::Cow;
use std::hint::black_box;
use std::sync::OnceLock;

/// One named target.
pub struct Target {
    pub name: &'static str,
    /// What it feeds, and to which code.
    pub about: &'static str,
    /// Run one input; true if the outermost decoder or parser accepted it (the share
    /// accepted tells whether inputs get past the first checks to the deep code).
    pub run: fn(&[u8]) -> bool,
    /// The seed inputs and dictionary an engine starts from.
    pub seeds: fn() -> Seeds,
}

/// Every target, in the order they run.
pub const TARGETS: &[Target] = &[
    Target {
        name: "envelope",
        about: "any enveloped message decoded as every message type (version byte, postcard)",
        run: envelope,
        seeds: || Seeds::binary(corpus::wire::envelope()),
    },
    Target {
        name: "percept",
        about: "a cell's Percept, as an agent reading cells one by one takes it",
        run: percept,
        seeds: || Seeds::binary(corpus::wire::percept()),
    },
    Target {
        name: "host_percepts",
        about: "HostPercepts: nested percepts and genes sent ahead (packs unpacked, batches filed by sender)",
        run: host_percepts,
        seeds: || Seeds::binary(corpus::wire::host_percepts()),
    },
    Target {
        name: "intents",
        about: "an agent process's IntentBatch, as the world takes it",
        run: intents,
        seeds: || Seeds::binary(corpus::wire::intents()),
    },
    Target {
        name: "gene_batch",
        about: "a GeneBatch on a cell key: GeneBatchHead, honesty check, whole batch, inbox filing",
        run: gene_batch,
        seeds: || Seeds::binary(corpus::wire::gene_batch()),
    },
    Target {
        name: "gene_bundle",
        about: "a GeneBundle as the world files it: LZ4 pack unpacked, batches peeked, checked and opened",
        run: gene_bundle,
        seeds: || Seeds::binary(corpus::wire::gene_bundle()),
    },
    Target {
        name: "gene_pack",
        about: "a bare LZ4 pack (net::unpack) and its nested batches, as a hosting agent process reads them",
        run: gene_pack,
        seeds: || Seeds::binary(corpus::wire::gene_pack()),
    },
    Target {
        name: "host_genes",
        about: "HostGenes: cells complete and the packs of other processes",
        run: host_genes,
        seeds: || Seeds::binary(corpus::wire::host_genes()),
    },
    Target {
        name: "tick",
        about: "the world's Tick, as an agent process takes it",
        run: tick,
        seeds: || Seeds::binary(corpus::wire::tick()),
    },
    Target {
        name: "run_info",
        about: "RunInfo of a joining agent process: learner JSON, grammar text, geometry",
        run: run_info,
        seeds: || Seeds::binary(corpus::wire::run_info()),
    },
    Target {
        name: "report",
        about: "a ReportMsg, as the orchestrator's launcher takes it",
        run: report,
        seeds: || Seeds::binary(corpus::wire::report()),
    },
    Target {
        name: "control",
        about: "a Control command, as the world and the agent processes take it",
        run: control,
        seeds: || Seeds::binary(corpus::wire::control()),
    },
    Target {
        name: "world_server",
        about: "the world's Server (geese_world::server) with one hostile intent batch, gene bundle or batch, control or presence message mid-step, run to its end",
        run: crate::protocol::world_server,
        seeds: || Seeds::binary(crate::protocol::world_server_seeds()),
    },
    Target {
        name: "agent_host",
        about: "an agent process's Host (geese_agent::host) with one hostile tick, percept, gene or presence message mid-step, run to its end",
        run: crate::protocol::agent_host,
        seeds: || Seeds::binary(crate::protocol::agent_host_seeds()),
    },
    Target {
        name: "genome",
        about: "a genome on the wire decoded and mapped with every shipped grammar, its tree built",
        run: genome,
        seeds: || Seeds::binary(corpus::genome_bytes()),
    },
    Target {
        name: "bnf",
        about: "Grammar::parse of a BNF text, then a mapping with the grammar",
        run: bnf,
        seeds: || {
            Seeds::text(
                corpus::grammar_texts(),
                &["<", ">", "::=", "|", "#", "\n", " ", "%", "[", "]", "\"", "'", "<>", "< >"],
            )
        },
    },
    Target {
        name: "phenotype",
        about: "parse_phenotype, the behaviour tree built from it, and the diversity scan",
        run: phenotype,
        seeds: || {
            Seeds::text(
                corpus::phenotypes(),
                &[
                    "[",
                    "]",
                    "[/",
                    "/]",
                    "<",
                    ">",
                    "%",
                    "[?",
                    "?]",
                    "[!",
                    " ",
                    "\n",
                    "[Sequence]",
                    "[/Sequence]",
                    "[Selector]",
                    "[/Selector]",
                    "[Parallel]",
                    "[/Parallel]",
                    "[?xml version=%1.0% encoding=%UTF-8%?]",
                ],
            )
        },
    },
    Target {
        name: "run_config",
        about: "a `geese run` TOML configuration, parsed and validated",
        run: run_config,
        seeds: || Seeds::text(corpus::run_config_texts(), TOML_TOKENS),
    },
    Target {
        name: "campaign",
        about: "a campaign file, parsed and validated (grid expanded, every condition's run checked)",
        run: campaign,
        seeds: || Seeds::text(corpus::campaign_texts(), TOML_TOKENS),
    },
];

const TOML_TOKENS: &[&str] = &[
    "=",
    "\n",
    "[",
    "]",
    "[[",
    "]]",
    "{",
    "}",
    ",",
    "\"",
    "'",
    "\"\"\"",
    "'''",
    "#",
    ".",
    "true",
    "false",
    "[]",
    "{}",
    "[base]",
    "[[grid]]",
    "[world]",
    "[learner]",
    "[learner.ge]",
    "[base.world]",
    "[[perturbations]]",
    "1979-05-27T07:32:00Z",
    "\\u0000",
    "\\",
    "_",
    "0x10",
    "0o7",
    "0b1",
    "+",
    "1_000",
];

/// The target called `name`.
pub fn by_name(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}

/// Text from bytes as a file read would give it: binaries read files with
/// `read_to_string`, which refuses invalid UTF-8, so invalid sequences are replaced
/// rather than the input skipped (the replacement character is valid input too).
fn text(b: &[u8]) -> Cow<'_, str> {
    String::from_utf8_lossy(b)
}

/// The geometry of the default run, for what an agent process checks cells against.
fn geom() -> Geometry {
    corpus::geometry()
}

fn envelope(b: &[u8]) -> bool {
    let ok = [
        decode::<Percept>(b).is_ok(),
        decode::<GeneMsg>(b).is_ok(),
        decode::<Intent>(b).is_ok(),
        decode::<StepReport>(b).is_ok(),
        decode::<Control>(b).is_ok(),
        decode::<Tick>(b).is_ok(),
        decode::<RunInfo>(b).is_ok(),
        decode::<IntentBatch>(b).is_ok(),
        decode::<GeneBatch>(b).is_ok(),
        decode::<GeneBatchHead>(b).is_ok(),
        decode::<GeneBatchCell>(b).is_ok(),
        decode::<HostPercepts>(b).is_ok(),
        decode::<HostGenes>(b).is_ok(),
        decode::<GeneBundle>(b).is_ok(),
        decode::<ReportMsg>(b).is_ok(),
        decode::<NetReport>(b).is_ok(),
    ];
    black_box(ok).iter().any(|&x| x)
}

/// What an agent process does with a percept: finds its agents' cells in it.
fn take_percept(p: &Percept, g: Geometry) {
    for a in &p.agents {
        black_box(a.live && g.cell_of(a.pos) == p.cell);
    }
    black_box(p.objects.len() + p.nearby_impassable.len());
}

fn percept(b: &[u8]) -> bool {
    let Ok(p) = decode::<Percept>(b) else { return false };
    take_percept(&p, geom());
    true
}

/// File a batch of genes in an inbox, lend them and retire them (an agent process).
fn file_in_inbox(batch: &GeneBatchHead<'_>, by_sender: bool) {
    let mut inbox = Inbox::default();
    let filed = if by_sender {
        inbox.file_by_sender(batch, |from| (!from.is_multiple_of(3)).then_some(from % 100))
    } else {
        inbox.file(batch)
    };
    if filed {
        let mut out = Vec::new();
        inbox.lend(batch.step, |from| from == 0, &mut out);
        black_box(out.iter().map(|(c, g)| *c as usize + g.genome.len()).sum::<usize>());
        inbox.retire(batch.step.saturating_sub(1));
        inbox.retire(batch.step);
        black_box(inbox.is_empty());
    }
}

/// A hosting agent process's handling of a pack it receives: batches peeked
/// (`GeneBatchCell`), opened without decoding genomes (`GeneBatchHead`) and filed.
/// True if the pack unpacked.
fn agent_pack(packed: &[u8], step: u64, ahead: bool) -> bool {
    let mut scratch = Vec::new();
    let Ok(mut nested) = unpack(packed, &mut scratch) else { return false };
    nested.retain(|r| r.open::<GeneBatchCell>().map_or(true, |h| h.step != step || h.cell.is_multiple_of(2)));
    for raw in nested {
        match raw.open::<GeneBatchHead>() {
            Ok(b) if ahead && b.step == step && b.cell == AHEAD_CELL => file_in_inbox(&b, true),
            Ok(b) if !ahead && (b.cell as usize) < geom().cell_count() => file_in_inbox(&b, false),
            _ => {}
        }
    }
    true
}

fn host_percepts(b: &[u8]) -> bool {
    let Ok(h) = decode::<HostPercepts>(b) else { return false };
    for raw in &h.percepts {
        if let Ok(p) = raw.open::<Percept>() {
            take_percept(&p, geom());
        }
    }
    for pack in h.genes.iter().flatten() {
        agent_pack(pack.0, h.step, true);
    }
    true
}

fn intents(b: &[u8]) -> bool {
    let Ok(batch) = decode::<IntentBatch>(b) else { return false };
    let range = AgentRange::new(0, 50).expect("a valid range");
    black_box(batch.intents.iter().all(|i| range.contains(i.agent) && i.step == batch.step));
    black_box(batch.intents.iter().map(|i| i.ops.len()).sum::<usize>() + batch.idle.len());
    true
}

/// What the world checks of a batch it files, and how it opens it whole when it
/// aggregates a cell for readers of the cell's key.
fn world_batch(batch: &GeneBatchHead<'_>, nested: Raw<'_>, from: AgentRange) {
    if batch.honest(from) && (batch.cell as usize) < geom().cell_count() {
        if let Ok(whole) = nested.open::<GeneBatch>() {
            black_box(whole.genes.iter().map(|g| g.genome.len()).sum::<usize>());
        }
    }
}

fn gene_batch(b: &[u8]) -> bool {
    let Ok(batch) = decode::<GeneBatchHead>(b) else { return false };
    // The world: the body after the version byte is the batch's nested encoding.
    world_batch(&batch, Raw(&b[1..]), AgentRange::new(10, 10).expect("a valid range"));
    // An agent process reading the cell's key: the aggregate goes to its inbox.
    file_in_inbox(&batch, false);
    true
}

fn gene_bundle(b: &[u8]) -> bool {
    let Ok(bundle) = decode::<GeneBundle>(b) else { return false };
    let from = AgentRange::new(10, 10).expect("a valid range");
    let mut scratch = Vec::new();
    let Ok(nested) = unpack(bundle.packed.0, &mut scratch) else { return true };
    if nested.len() == 1 && nested[0].open::<GeneBatchCell>().is_ok_and(|h| h.cell == AHEAD_CELL) {
        if let Ok(batch) = nested[0].open::<GeneBatchHead>() {
            black_box(batch.step == bundle.step && batch.honest(from));
        }
        return true;
    }
    for raw in &nested {
        if let Ok(batch) = raw.open::<GeneBatchHead>() {
            if batch.step == bundle.step {
                world_batch(&batch, *raw, from);
            }
        }
    }
    true
}

fn gene_pack(b: &[u8]) -> bool {
    agent_pack(b, 3, false) | agent_pack(b, 4, true)
}

fn host_genes(b: &[u8]) -> bool {
    let Ok(h) = decode::<HostGenes>(b) else { return false };
    black_box(h.cells.iter().filter(|&&c| (c as usize) < geom().cell_count()).count());
    for p in &h.packs {
        agent_pack(p.0, h.step, false);
    }
    true
}

fn tick(b: &[u8]) -> bool {
    let Ok(t) = decode::<Tick>(b) else { return false };
    black_box(t.cells.iter().filter(|&&c| c != NO_CELL).count());
    true
}

/// What a joining agent process does with the run information before step 1.
fn run_info(b: &[u8]) -> bool {
    let Ok(info) = decode::<RunInfo>(b) else { return false };
    // The cells it subscribes to first, and the arena's cell count it checks cells with.
    black_box(info.cells.iter().take(8).filter(|&&c| c != NO_CELL).count());
    black_box(info.geometry.cell_count());
    black_box(info.geometry.cell_of(info.hub.pos));
    if !info.spec.bare {
        if let Ok(cfg) = serde_json::from_str::<LearnerConfig>(&info.spec.learner_json) {
            black_box(cfg.validate().is_ok());
        }
        if let Ok(g) = Grammar::parse(&info.spec.grammar_text) {
            black_box(g.rules().len());
        }
    }
    true
}

fn report(b: &[u8]) -> bool {
    black_box(decode::<ReportMsg>(b)).is_ok()
}

fn control(b: &[u8]) -> bool {
    black_box(decode::<Control>(b)).is_ok()
}

/// The shipped grammars, parsed once.
fn shipped() -> &'static [Grammar] {
    static G: OnceLock<Vec<Grammar>> = OnceLock::new();
    G.get_or_init(|| {
        grammars::names()
            .filter_map(grammars::builtin)
            .map(|t| Grammar::parse(t).expect("shipped grammars parse"))
            .collect()
    })
}

/// Map `genome` with `g` (mapper, diversity) and build the tree of a valid phenotype, as
/// a learner does with a gene it adopts.
fn map_and_build(g: &Grammar, genome: &[u32]) {
    let ind = evaluate(g, genome.to_vec(), &GeParams::default());
    if let Some(p) = &ind.phenotype {
        if let Ok(root) = parse_phenotype(p) {
            black_box(Bt::from_pnode(&root).map(|t| t.len()).ok());
        }
    }
    black_box(ind.fitness);
}

fn genome(b: &[u8]) -> bool {
    let mut codons = Vec::new();
    if !genome_codons_into(b, &mut codons) {
        return false;
    }
    for g in shipped() {
        map_and_build(g, &codons);
    }
    true
}

/// Codons for a mapping with a fuzzed grammar, from the input's own bytes.
fn codons_of(b: &[u8]) -> Vec<u32> {
    b.chunks(3).take(200).map(|c| c.iter().fold(0u32, |a, &x| a.wrapping_mul(257).wrapping_add(u32::from(x)))).collect()
}

fn bnf(b: &[u8]) -> bool {
    let Ok(g) = Grammar::parse(&text(b)) else { return false };
    black_box(g.to_string().len());
    black_box((g.max_arity(), g.max_alternatives(), g.terminal_count()));
    map_and_build(&g, &codons_of(b));
    true
}

fn phenotype(b: &[u8]) -> bool {
    let t = text(b);
    black_box(diversity(&t));
    let Ok(root) = parse_phenotype(&t) else { return false };
    black_box((root.size(), root.leaves().len(), root.render().len()));
    black_box(Bt::from_pnode(&root).map(|t| t.render().len()).ok());
    true
}

fn run_config(b: &[u8]) -> bool {
    let Ok(c) = RunConfig::from_toml(&text(b)) else { return false };
    black_box(c.validate().is_ok());
    true
}

fn campaign(b: &[u8]) -> bool {
    black_box(Campaign::from_toml(&text(b), "fuzz").map(|c| c.conditions.len())).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_found() {
        let mut names: Vec<_> = TARGETS.iter().map(|t| t.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), TARGETS.len());
        assert!(TARGETS.iter().all(|t| by_name(t.name).is_some_and(|f| f.about == t.about)));
        assert!(by_name("no-such-target").is_none());
    }
}
