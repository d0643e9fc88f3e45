//! Seed inputs: valid encodings of real values, the shipped grammars, the campaign
//! files and run configurations.
//!
//! Why valid seeds: mutations of a valid message reach the fields deep inside it (a
//! genome's width byte inside a gene inside a batch inside an LZ4 pack inside a
//! bundle); random bytes stop at the version byte. The messages are built with the
//! crate's own encoders ([`encode`], [`nest`], [`pack`]), so the seeds follow the wire
//! format as it is, not as a copy of it here says.
use geese_agent::ge::{random_individual, GeParams, Grammar};
use geese_agent::{grammars, LearnerConfig};
use geese_orchestrator::RunConfig;
use geese_proto::net::{
    nest, pack, Deadlines, GeneBatch, GeneBatchRef, GeneBundle, HostCounters, HostGenes, HostPercepts, IntentBatch,
    LossRates, NetCounters, NetReport, NetRunSpec, Raw, ReportMsg, RunInfo, Tick, AHEAD_CELL, NO_CELL,
};
use geese_proto::{
    encode, AgentPublic, AgentStats, BehaviourClass, Control, GeneMapping, GeneMsg, GeneticTrigger, Geometry, Intent,
    ObjectInfo, ObjectKind, Op, Percept, Perturbation, Pos, Regime, StepReport,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// The seed inputs of one target and the dictionary an engine inserts tokens of.
#[derive(Clone, Debug, Default)]
pub struct Seeds {
    pub inputs: Vec<Vec<u8>>,
    /// Tokens of the format: keywords and punctuation of a text format, the varints and
    /// integer edges of postcard ([`binary_tokens`]) for a binary one.
    pub dictionary: Vec<Vec<u8>>,
}

impl Seeds {
    /// Inputs of a text format, with a dictionary of its `punctuation`, numbers at the
    /// edges of the types values parse into, and every word (letters, digits, `_`, `-`,
    /// `.`) found in the inputs: keys, rule and node names, values.
    pub fn text(inputs: Vec<Vec<u8>>, punctuation: &[&str]) -> Seeds {
        let mut dictionary: Vec<Vec<u8>> = punctuation.iter().map(|p| p.as_bytes().to_vec()).collect();
        dictionary.extend(TEXT_NUMBERS.iter().map(|p| p.as_bytes().to_vec()));
        let mut words = BTreeSet::new();
        for s in &inputs {
            let word = |c: &u8| c.is_ascii_alphanumeric() || matches!(c, b'_' | b'-' | b'.');
            for w in s.split(|c| !word(c)).filter(|w| (2..=40).contains(&w.len())) {
                words.insert(w.to_vec());
            }
        }
        dictionary.extend(words.into_iter().take(2_000));
        Seeds { inputs, dictionary }
    }

    /// Inputs of a postcard format, with [`binary_tokens`] as the dictionary.
    pub fn binary(inputs: Vec<Vec<u8>>) -> Seeds {
        Seeds { inputs, dictionary: binary_tokens() }
    }
}

/// Numbers, as text, at the edges of the types configuration values parse into.
const TEXT_NUMBERS: &[&str] = &[
    "0",
    "-0",
    "1",
    "-1",
    "0.5",
    "-0.0",
    "1e308",
    "1e309",
    "-1e309",
    "nan",
    "inf",
    "-inf",
    "127",
    "128",
    "255",
    "256",
    "65535",
    "65536",
    "2147483647",
    "2147483648",
    "-2147483649",
    "4294967295",
    "4294967296",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "99999999999999999999999999",
];

/// The geometry of the default run (100 × 100, grid 10).
pub fn geometry() -> Geometry {
    Geometry::new(100, 100, 10).expect("the default geometry is valid")
}

fn enveloped<T: serde::Serialize>(msgs: impl IntoIterator<Item = T>) -> Vec<Vec<u8>> {
    msgs.into_iter().map(|m| encode(&m).expect("a real message encodes")).collect()
}

fn object(id: u32, kind: ObjectKind, x: i32, y: i32) -> ObjectInfo {
    ObjectInfo { id, kind, pos: Pos::new(x, y), radius: 3 + (id % 5) as i32, weight: (id % 3) as i32, capacity: 1 }
}

/// Percepts of a few cells: empty, crowded, with carried objects and obstacles nearby.
pub fn percepts() -> Vec<Percept> {
    let regime = Regime::default();
    let kinds = ObjectKind::ALL;
    (0..6u32)
        .map(|k| {
            let objects = (0..k * 2).map(|i| object(100 + i, kinds[(i as usize) % 7], i as i32 - 5, 7)).collect();
            let nearby_impassable = (0..k).map(|i| object(200 + i, ObjectKind::Obstacles, -40, i as i32)).collect();
            let agents = (0..k)
                .map(|i| AgentPublic {
                    id: i * 3,
                    pos: Pos::new(i as i32 * 2 - 45, -45),
                    heading: 0.25 * i as f64 - 1.0,
                    carrying: (0..i % 3).map(|j| object(300 + j, ObjectKind::Food, 0, 0)).collect(),
                    live: i % 4 != 3,
                    learning: i % 5 != 4,
                })
                .collect();
            Percept {
                step: [1, 2, 500, 12_000, u32::MAX as u64 + 7, 3][k as usize],
                cell: k * 17 % 100,
                regime: Regime {
                    ip: 0.1 * k as f64,
                    lateral_transfer: k.is_multiple_of(2),
                    gene_loss: 0.05 * k as f64,
                },
                objects,
                nearby_impassable,
                reach: 0,
                area: vec![],
                agents,
            }
        })
        .chain(std::iter::once(Percept {
            step: 9,
            cell: 0,
            regime,
            objects: vec![],
            nearby_impassable: vec![],
            reach: 0,
            area: vec![],
            agents: vec![],
        }))
        .collect()
}

/// Genomes of real individuals of the default grammar, some with codons above 65,535
/// (so that both wire widths occur).
pub fn genomes() -> Vec<Vec<u32>> {
    let g = Grammar::parse(grammars::builtin("betr-foraging-avoid").expect("shipped")).expect("parses");
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut out: Vec<Vec<u32>> =
        (0..6).map(|_| random_individual(&g, &GeParams::default(), &mut rng).genome.to_vec()).collect();
    let mut wide = out[0].clone();
    wide[1] = 70_000;
    out.push(wide);
    out.push(vec![]);
    out.push(vec![0, 65_535, 65_536, u32::MAX]);
    out
}

fn gene(step: u64, from: u32, genome: &[u32]) -> GeneMsg {
    let mapping = GeneMapping { valid: !from.is_multiple_of(3), used_codons: genome.len() as u32 / 2, depth: 5 };
    GeneMsg { step, from, genome: genome.into(), fitness: 1.5 * from as f64, mapping }
}

/// Gene batches of a few cells and one sent ahead.
pub fn gene_batches() -> Vec<GeneBatch> {
    let gs = genomes();
    let mut out: Vec<GeneBatch> = (0..4u32)
        .map(|c| GeneBatch {
            step: 3,
            cell: c * 11,
            genes: (0..c).map(|i| gene(3, 10 + i, &gs[(c + i) as usize % gs.len()])).collect(),
            absent: (0..c % 3).map(|i| 20 + i).collect(),
        })
        .collect();
    out.push(GeneBatch {
        step: 4,
        cell: AHEAD_CELL,
        genes: (0..3).map(|i| gene(4, 10 + i, &gs[i as usize])).collect(),
        absent: vec![],
    });
    out
}

/// Packs of nested batches, as an agent process sends them: one of several cells, one
/// sent ahead, an empty one.
pub fn packs() -> Vec<Vec<u8>> {
    let batches = gene_batches();
    let nested: Vec<Vec<u8>> = batches.iter().map(|b| nest(b).expect("encodes")).collect();
    let raws = |r: std::ops::Range<usize>| nested[r].iter().map(|b| Raw(b)).collect::<Vec<_>>();
    // The ahead batch encoded from parts, as the agent does.
    let ahead = &batches[4];
    let by_parts =
        nest(&GeneBatchRef { step: ahead.step, cell: ahead.cell, genes: &ahead.genes, absent: &ahead.absent })
            .expect("encodes");
    vec![
        pack(&raws(0..4)).expect("packs"),
        pack(&raws(1..2)).expect("packs"),
        pack(&[Raw(&by_parts)]).expect("packs"),
        pack(&[]).expect("packs"),
    ]
}

fn intents() -> Vec<IntentBatch> {
    let stats = |k: u32| AgentStats {
        lt_rate: k,
        genetic: [GeneticTrigger::None, GeneticTrigger::Storage, GeneticTrigger::Stagnation][k as usize % 3],
        fitness: k as f64 * 0.5,
        gene_digest: 0x1234_5678_9abc_def0 ^ k as u64,
        genes_lost: k % 2,
        class: BehaviourClass::ALL[k as usize % BehaviourClass::ALL.len()],
    };
    let intent = |k: u32| Intent {
        step: 7,
        agent: k,
        heading: -3.0 + k as f64,
        ops: match k % 4 {
            0 => vec![],
            1 => vec![Op::Move { to: Pos::new(k as i32, -(k as i32)), heading: 1.25 }],
            2 => vec![Op::Pick { object: 5 }, Op::Move { to: Pos::new(3, 4), heading: 0.0 }],
            _ => vec![Op::Drop { object: 9 }, Op::Pick { object: 1 }, Op::Drop { object: 1 }],
        },
        stats: stats(k),
    };
    vec![
        IntentBatch {
            step: 7,
            intents: (0..6).map(intent).collect(),
            idle: vec![40, 41],
            counters: HostCounters::default(),
            ahead: None,
        },
        IntentBatch {
            step: 1,
            intents: vec![],
            idle: vec![],
            counters: HostCounters { percepts_lost: 1, genes_late: 3, hostile: 4, ..HostCounters::default() },
            // The ahead pack of `packs` (genes for step 4).
            ahead: Some(packs().swap_remove(2)),
        },
    ]
}

fn controls() -> Vec<Control> {
    let changes = [
        Perturbation::AddObstacles { count: 3, radius: 10 },
        Perturbation::SetIp(0.5),
        Perturbation::SetLateralTransfer(false),
        Perturbation::SetGeneLoss(0.25),
        Perturbation::KillFraction(0.3),
    ];
    let mut out = vec![Control::Start, Control::Stop];
    out.extend(
        changes.into_iter().enumerate().map(|(i, change)| Control::Schedule { at_step: 100 * i as u64, change }),
    );
    out
}

fn reports() -> Vec<ReportMsg> {
    let report = StepReport {
        step: 12,
        task_pct: 42.5,
        lt_mean: 1.5,
        lt_std: 0.5,
        genetic_steps: 3,
        stagnation_steps: 1,
        live_agents: 100,
        missing_intents: 2,
        rejected: 1,
        genes_lost: 4,
        digest: 0xdead_beef,
    };
    let net =
        NetCounters { intents_lost: 1, hostile: 2, processes: 10, wait_us: 1234, genes_ahead: 9, ..Default::default() };
    vec![
        ReportMsg::Step(NetReport { report, net }),
        ReportMsg::Done { steps: 12_000, completed: true, requested: false },
        ReportMsg::Done { steps: 5, completed: false, requested: true },
    ]
}

/// The run information a world sends a joining agent process: a learning run with the
/// default grammar and a bare benchmark.
pub fn run_infos() -> Vec<RunInfo> {
    let cfg = RunConfig::default();
    let grammar_name = cfg.grammar_name();
    let spec = NetRunSpec {
        run: "fuzz".into(),
        seed: 5,
        steps: 100,
        agents: 4,
        world_json: serde_json::to_string(&cfg.world).expect("encodes"),
        learner_json: serde_json::to_string(&LearnerConfig::default()).expect("encodes"),
        program_json: serde_json::to_string(&geese_agent::Program::default()).expect("encodes"),
        grammar_text: grammars::builtin(&grammar_name).expect("shipped").to_string(),
        grammar_name,
        regime: Regime::default(),
        perturbations: vec![(10, Perturbation::SetIp(0.2)), (20, Perturbation::AddObstacles { count: 1, radius: 5 })],
        loss: LossRates { intent: 0.1, percept: 0.0 },
        deadlines: Deadlines::default(),
        bare: false,
        expect_orchestrator: true,
    };
    let hub = object(1, ObjectKind::Hub, 0, 0);
    let learning =
        RunInfo { spec: spec.clone(), geometry: geometry(), hub, next_step: 1, cells: vec![0, 5, NO_CELL, 99] };
    let mut bare = learning.clone();
    bare.spec.bare = true;
    bare.spec.grammar_text = String::new();
    bare.next_step = 77;
    vec![learning, bare]
}

/// Seeds per wire target.
pub mod wire {
    use super::*;

    pub fn percept() -> Vec<Vec<u8>> {
        enveloped(percepts())
    }

    fn raws(n: &[Vec<u8>]) -> Vec<Raw<'_>> {
        n.iter().map(|b| Raw(b)).collect()
    }

    pub fn host_percepts() -> Vec<Vec<u8>> {
        let nested: Vec<Vec<u8>> = percepts().iter().map(|p| nest(p).expect("encodes")).collect();
        let packs = packs();
        let msgs = [
            HostPercepts { step: 1, percepts: raws(&nested), genes: None },
            HostPercepts { step: 4, percepts: raws(&nested[..2]), genes: Some(raws(&packs[2..])) },
            HostPercepts { step: 4, percepts: vec![], genes: Some(vec![]) },
        ];
        msgs.iter().map(|m| encode(m).expect("encodes")).collect()
    }

    pub fn intents() -> Vec<Vec<u8>> {
        enveloped(super::intents())
    }

    pub fn gene_batch() -> Vec<Vec<u8>> {
        enveloped(gene_batches())
    }

    pub fn gene_bundle() -> Vec<Vec<u8>> {
        packs()
            .iter()
            .enumerate()
            .map(|(i, p)| encode(&GeneBundle { step: 3 + i as u64 / 2, packed: Raw(p) }).expect("encodes"))
            .collect()
    }

    pub fn gene_pack() -> Vec<Vec<u8>> {
        packs()
    }

    pub fn host_genes() -> Vec<Vec<u8>> {
        let packs = packs();
        let msgs = [
            HostGenes { step: 3, cells: vec![0, 11, 22], packs: packs.iter().map(|p| Raw(p)).collect() },
            HostGenes { step: 3, cells: vec![33], packs: vec![] },
        ];
        msgs.iter().map(|m| encode(m).expect("encodes")).collect()
    }

    pub fn tick() -> Vec<Vec<u8>> {
        enveloped([Tick { step: 1, cells: vec![0, 1, 2, 3] }, Tick { step: 99, cells: vec![NO_CELL, 55, NO_CELL, 4] }])
    }

    pub fn run_info() -> Vec<Vec<u8>> {
        enveloped(run_infos())
    }

    pub fn report() -> Vec<Vec<u8>> {
        enveloped(reports())
    }

    pub fn control() -> Vec<Vec<u8>> {
        enveloped(controls())
    }

    pub fn gene_msg() -> Vec<Vec<u8>> {
        enveloped(genomes().iter().enumerate().map(|(i, g)| gene(2, i as u32, g)))
    }

    /// Every enveloped message of every type: the envelope target reads each as each.
    pub fn envelope() -> Vec<Vec<u8>> {
        [
            percept(),
            host_percepts(),
            intents(),
            gene_batch(),
            gene_bundle(),
            host_genes(),
            tick(),
            run_info(),
            report(),
            control(),
            gene_msg(),
        ]
        .concat()
    }
}

/// The shipped grammar texts.
pub fn grammar_texts() -> Vec<Vec<u8>> {
    grammars::names().filter_map(grammars::builtin).map(|t| t.as_bytes().to_vec()).collect()
}

/// Phenotypes of random individuals of every shipped grammar (what the mapper makes and
/// a learner builds its tree from), a few of each.
pub fn phenotypes() -> Vec<Vec<u8>> {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut out = Vec::new();
    for text in grammars::names().filter_map(grammars::builtin) {
        let g = Grammar::parse(text).expect("shipped grammars parse");
        for _ in 0..3 {
            if let Some(p) = random_individual(&g, &GeParams::default(), &mut rng).phenotype {
                out.push(p.as_bytes().to_vec());
            }
        }
    }
    out
}

/// Genomes as they travel (a width byte, then the codons).
pub fn genome_bytes() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for g in genomes() {
        // Encoded by the real codec, and taken out of the gene as a receiver sees it.
        let nested = nest(&gene(1, 1, &g)).expect("encodes");
        let head: geese_proto::net::GeneHead = Raw(&nested).open().expect("opens");
        out.push(head.genome.0.to_vec());
    }
    out
}

/// The workspace's `campaigns/` directory, read when the fuzzer starts (not embedded:
/// campaign files come and go, and a new one is a new seed without a rebuild).
pub fn campaigns_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join("campaigns")
}

fn toml_files(dir: &Path, out: &mut Vec<Vec<u8>>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut paths: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    for p in paths {
        if p.is_dir() {
            toml_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "toml") {
            if let Ok(b) = std::fs::read(&p) {
                out.push(b);
            }
        }
    }
}

/// A campaign used when the campaign files cannot be found.
const FALLBACK_CAMPAIGN: &str = r#"name = "fallback"
tasks = ["foraging", "nest"]
seeds = 2
x = "ip"
[base]
steps = 100
[base.world]
agents = 10
[[grid]]
ip = [0.5, 0.85]
"#;

/// The campaign files of the workspace (`campaigns/`, recursively).
pub fn campaign_texts() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    toml_files(&campaigns_dir(), &mut out);
    if out.is_empty() {
        out.push(FALLBACK_CAMPAIGN.as_bytes().to_vec());
    }
    out
}

/// Run configurations: the defaults written out in full, some with perturbations and
/// other grammars, and the `[base]` table of every campaign file.
pub fn run_config_texts() -> Vec<Vec<u8>> {
    let mut configs = vec![RunConfig::default()];
    let mut c = RunConfig { steps: 50, seed: 9, grammar: Some("geese-bt-nest".into()), ..RunConfig::default() };
    c.world.task = geese_world::Task::Nest;
    c.perturbations = controls()
        .into_iter()
        .filter_map(|c| match c {
            Control::Schedule { at_step, change } => {
                Some(geese_orchestrator::run::config::Scheduled { at: at_step + 1, change })
            }
            _ => None,
        })
        .collect();
    configs.push(c);
    let mut out: Vec<Vec<u8>> =
        configs.iter().filter_map(|c| toml::to_string(c).ok()).map(String::into_bytes).collect();
    out.push(b"steps = 10\n".to_vec());
    for text in campaign_texts() {
        let base = std::str::from_utf8(&text)
            .ok()
            .and_then(|t| t.parse::<toml::Table>().ok())
            .and_then(|mut t| t.remove("base"));
        if let Some(toml::Value::Table(base)) = base {
            if let Ok(s) = toml::to_string(&base) {
                out.push(s.into_bytes());
            }
        }
    }
    out
}

/// A token as a line of an AFL dictionary: `"…"` with `"`, `\` and every byte outside
/// printable ASCII written `\xNN`.
pub fn dictionary_line(token: &[u8]) -> String {
    let mut s = String::from("\"");
    for &b in token {
        if (0x20..0x7f).contains(&b) && b != b'"' && b != b'\\' {
            s.push(b as char);
        } else {
            s.push_str(&format!("\\x{b:02x}"));
        }
    }
    s.push('"');
    s
}

/// What [`export`] wrote for one target.
#[derive(Clone, Debug)]
pub struct Exported {
    pub target: &'static str,
    pub seeds: usize,
    /// Tokens in `<dir>/<target>.dict`.
    pub tokens: usize,
}

/// Write the seeds of every target as files, `<dir>/<target>/seed-NNN.bin`, and the
/// dictionary of each text target as `<dir>/<target>.dict` (AFL's format): the input
/// directory and `-x` file of an engine run. Seeds are made in code from the crates'
/// own encoders, so they follow every change of a message without a file to update.
pub fn export(dir: &Path) -> std::io::Result<Vec<Exported>> {
    let mut out = Vec::new();
    for t in crate::TARGETS {
        let m = (t.seeds)();
        let d = dir.join(t.name);
        std::fs::create_dir_all(&d)?;
        for (i, s) in m.inputs.iter().enumerate() {
            std::fs::write(d.join(format!("seed-{i:03}.bin")), s)?;
        }
        // AFL skips tokens longer than 128 bytes.
        let tokens: Vec<String> =
            m.dictionary.iter().filter(|t| !t.is_empty() && t.len() <= 128).map(|t| dictionary_line(t)).collect();
        if !tokens.is_empty() {
            std::fs::write(dir.join(format!("{}.dict", t.name)), tokens.join("\n") + "\n")?;
        }
        out.push(Exported { target: t.name, seeds: m.inputs.len(), tokens: tokens.len() });
    }
    Ok(out)
}

/// Unsigned values on the boundaries of varint lengths, integer widths and "sane"
/// lengths and counts.
const INTERESTING: &[u64] = &[
    0,
    1,
    2,
    3,
    4,
    7,
    8,
    16,
    31,
    32,
    64,
    100,
    127,
    128,
    255,
    256,
    1000,
    4095,
    4096,
    16_383,
    16_384,
    32_767,
    32_768,
    65_535,
    65_536,
    1 << 20,
    1 << 24,
    (1 << 31) - 1,
    1 << 31,
    u32::MAX as u64,
    1 << 32,
    1 << 53,
    i64::MAX as u64,
    1 << 63,
    u64::MAX,
];

/// Postcard's varint (LEB128) of `v`.
pub fn varint(mut v: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(10);
    loop {
        let b = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            out.push(b);
            return out;
        }
        out.push(b | 0x80);
    }
}

/// The dictionary of the postcard targets: interesting integers in the encodings a
/// decoder reads them in (varint, zigzag varint for negatives, over-long varints,
/// 4- and 8-byte little-endian), IEEE specials, and the wire version byte. An engine
/// does not know postcard's varints, so a length or count on a boundary would otherwise
/// take it many tries.
pub fn binary_tokens() -> Vec<Vec<u8>> {
    let mut out = vec![vec![geese_proto::WIRE_VERSION]];
    for &v in INTERESTING {
        out.push(varint(v));
        out.push(varint(v.wrapping_mul(2) ^ 1));
        if v > 255 {
            out.push(varint(v - 1));
            out.push((v as u32).to_le_bytes().to_vec());
            out.push(v.to_le_bytes().to_vec());
        }
    }
    for n in [5, 10, 12] {
        let mut b = vec![0x80u8; n];
        b.push(0x01);
        out.push(b);
    }
    for f in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.0, f64::MAX, f64::MIN_POSITIVE, 1e-310, -1.0] {
        out.push(f.to_le_bytes().to_vec());
    }
    out.sort();
    out.dedup();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varints_are_postcards() {
        assert_eq!(varint(0), [0]);
        assert_eq!(varint(127), [127]);
        assert_eq!(varint(128), [0x80, 1]);
        assert_eq!(varint(u64::MAX).len(), 10);
        let t = binary_tokens();
        assert!(t.contains(&vec![0x80, 1]) && t.contains(&vec![geese_proto::WIRE_VERSION]));
        // Zigzag -1 (postcard's i32/i64 of -1) is 1.
        assert!(t.contains(&vec![1]));
    }

    #[test]
    fn text_dictionary_holds_punctuation_words_and_edge_numbers() {
        let m = Seeds::text(vec![b"<start> ::= <a> | b_c".to_vec()], &["::="]);
        for w in ["::=", "start", "b_c", "18446744073709551616"] {
            assert!(m.dictionary.contains(&w.as_bytes().to_vec()), "{w}");
        }
    }

    #[test]
    fn dictionary_lines_escape_what_afl_would_misread() {
        assert_eq!(dictionary_line(b"::="), r#""::=""#);
        assert_eq!(dictionary_line(b"a\"b\\c\n\x00\xff"), r#""a\x22b\x5cc\x0a\x00\xff""#);
    }

    #[test]
    fn export_writes_every_target_s_seeds_and_dictionary() {
        let dir = std::env::temp_dir().join(format!("geese-fuzz-export-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let exported = export(&dir).expect("temp dir is writable");
        assert_eq!(exported.len(), crate::TARGETS.len());
        for (e, t) in exported.iter().zip(crate::TARGETS) {
            let seeds = (t.seeds)().inputs;
            assert_eq!(e.seeds, seeds.len(), "{}", t.name);
            assert_eq!(std::fs::read(dir.join(t.name).join("seed-000.bin")).ok().as_ref(), seeds.first(), "{}", t.name);
            let dict = std::fs::read_to_string(dir.join(format!("{}.dict", t.name))).expect("a dictionary");
            assert_eq!(dict.lines().count(), e.tokens, "{}", t.name);
            assert!(dict.lines().all(|l| l.starts_with('"') && l.ends_with('"')), "{}", t.name);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
