//! The input generator: each input is a pure function of (seed, target, index).
//!
//! Without coverage feedback, what makes a fuzzer reach deep code is starting from valid
//! inputs: a random byte string almost never gets past the version byte and the first
//! length of a postcard message, or the first `::=` of a grammar. So most inputs are a
//! seed input (a valid encoding or file) with a few mutations stacked on it; a few are
//! random bytes, and a few are seed inputs unchanged (the valid path must not panic
//! either). The mutations are the usual ones of libFuzzer and AFL, plus the integers
//! that break decoders (postcard varints of boundary values, over-long varints, IEEE
//! specials) and, for text formats, tokens of the format.
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Longest input generated: far above every seed input, so that growth is possible, and
/// small enough that one input stays cheap.
pub const MAX_LEN: usize = 1 << 16;

/// FNV-1a of `bytes`: names crash files and separates the streams of targets.
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// The random stream of input `index` of target `target` under run seed `seed`.
///
/// Why one stream per input rather than one per run: any input can be made again from
/// three numbers (the watchdog does, for an input whose worker never returns), and a
/// target's inputs do not depend on how many inputs other targets ran.
pub fn input_rng(seed: u64, target: &str, index: u64) -> ChaCha8Rng {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed.to_le_bytes());
    key[8..16].copy_from_slice(&fnv1a(target.as_bytes()).to_le_bytes());
    key[16..24].copy_from_slice(&index.to_le_bytes());
    key[24..].copy_from_slice(b"geesefuz");
    ChaCha8Rng::from_seed(key)
}

/// Seed inputs and tokens of one target: what inputs are made from.
#[derive(Clone, Debug, Default)]
pub struct Material {
    pub seeds: Vec<Vec<u8>>,
    /// Tokens inserted or written over the input (keywords and punctuation of a text
    /// format; empty for binary formats, which get interesting integers instead).
    pub dictionary: Vec<Vec<u8>>,
}

impl Material {
    /// Seeds with a dictionary of the format's `punctuation` plus every word (letters,
    /// digits, `_`, `-`, `.`) found in the seeds: keys, rule and node names, values.
    pub fn text(seeds: Vec<Vec<u8>>, punctuation: &[&str]) -> Material {
        let mut dictionary: Vec<Vec<u8>> = punctuation.iter().map(|p| p.as_bytes().to_vec()).collect();
        dictionary.extend(TEXT_NUMBERS.iter().map(|p| p.as_bytes().to_vec()));
        let mut words = std::collections::BTreeSet::new();
        for s in &seeds {
            let word = |c: &u8| c.is_ascii_alphanumeric() || matches!(c, b'_' | b'-' | b'.');
            for w in s.split(|c| !word(c)).filter(|w| (2..=40).contains(&w.len())) {
                words.insert(w.to_vec());
            }
        }
        dictionary.extend(words.into_iter().take(2_000));
        Material { seeds, dictionary }
    }

    /// Seeds of a binary format (no dictionary).
    pub fn binary(seeds: Vec<Vec<u8>>) -> Material {
        Material { seeds, dictionary: Vec::new() }
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

/// Unsigned values whose encodings sit on the boundaries of varint lengths, integer
/// widths and "sane" lengths.
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

/// Bytes that mean something to the formats fuzzed: the wire version and genome widths
/// (2, 4, 8), varint continuation (0x80), UTF-8 lead and continuation bytes, brackets.
const INTERESTING_BYTES: &[u8] =
    &[0, 1, 2, 3, 4, 8, 0x10, 0x7f, 0x80, 0x81, 0xc0, 0xe0, 0xf0, 0xfe, 0xff, b'\n', b'<', b'>', b'[', b']', b'"'];

/// Input `index` of `target` under `seed`.
pub fn input(seed: u64, target: &str, index: u64, material: &Material) -> Vec<u8> {
    let mut rng = input_rng(seed, target, index);
    generate(&mut rng, material)
}

/// One input from `rng`: 8 % random bytes, 4 % a seed unchanged, the rest a seed with
/// 1 to 16 mutations (half of them one or two).
pub fn generate<R: Rng>(rng: &mut R, m: &Material) -> Vec<u8> {
    let roll = rng.random_range(0..100u32);
    if m.seeds.is_empty() || roll < 8 {
        let max = [4usize, 16, 64, 512, 4096][rng.random_range(0..5)];
        let mut v = vec![0u8; rng.random_range(0..=max)];
        rng.fill_bytes(&mut v);
        return v;
    }
    let mut data = m.seeds[rng.random_range(0..m.seeds.len())].clone();
    if roll < 12 {
        return data;
    }
    let mut n = 1;
    while n < 16 && rng.random_bool(0.5) {
        n += 1;
    }
    for _ in 0..n {
        mutate_once(rng, &mut data, m);
    }
    data.truncate(MAX_LEN);
    data
}

/// A position in `0..len` (`0` when empty).
fn pos<R: Rng>(rng: &mut R, len: usize) -> usize {
    if len == 0 {
        0
    } else {
        rng.random_range(0..len)
    }
}

/// A short length, mostly 1–8, sometimes up to 64.
fn short_len<R: Rng>(rng: &mut R) -> usize {
    if rng.random_bool(0.8) {
        rng.random_range(1..=8)
    } else {
        rng.random_range(1..=64)
    }
}

/// Postcard's varint (LEB128) of `v`.
fn varint(mut v: u64) -> Vec<u8> {
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

/// An interesting integer or float, in one of the encodings a decoder may read it in.
fn interesting_bytes<R: Rng>(rng: &mut R) -> Vec<u8> {
    let v = INTERESTING[rng.random_range(0..INTERESTING.len())];
    let v = if rng.random_bool(0.2) { v.wrapping_sub(1) } else { v };
    match rng.random_range(0..8u32) {
        0..=2 => varint(v),
        // Zigzag (postcard's signed integers), for negative values.
        3 => varint(v.wrapping_mul(2) ^ 1),
        // Over-long varint: continuation bytes past the tenth.
        4 => {
            let mut b = vec![0x80u8; rng.random_range(5..=12)];
            b.push(if rng.random_bool(0.5) { 0x7f } else { 0x01 });
            b
        }
        5 => (v as u32).to_le_bytes().to_vec(),
        6 => v.to_le_bytes().to_vec(),
        _ => {
            let f = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.0, f64::MAX, f64::MIN_POSITIVE, 1e-310, -1.0, 2.0]
                [rng.random_range(0..9)];
            f.to_le_bytes().to_vec()
        }
    }
}

/// Write `patch` over `data` at `at` (growing it if needed), or insert it there.
fn put<R: Rng>(rng: &mut R, data: &mut Vec<u8>, patch: &[u8]) {
    let at = pos(rng, data.len() + 1);
    if rng.random_bool(0.5) {
        data.splice(at..at, patch.iter().copied());
    } else {
        let end = (at + patch.len()).min(data.len());
        data.splice(at..end, patch.iter().copied());
    }
}

/// Apply one random mutation to `data`.
pub fn mutate_once<R: Rng>(rng: &mut R, data: &mut Vec<u8>, m: &Material) {
    let len = data.len();
    match rng.random_range(0..13u32) {
        // Flip a bit.
        0 if len > 0 => {
            let i = pos(rng, len);
            data[i] ^= 1 << rng.random_range(0..8);
        }
        // A random byte.
        1 if len > 0 => {
            let i = pos(rng, len);
            data[i] = rng.random();
        }
        // An interesting byte.
        2 if len > 0 => {
            let i = pos(rng, len);
            data[i] = INTERESTING_BYTES[rng.random_range(0..INTERESTING_BYTES.len())];
        }
        // A small add or subtract (lengths and counts off by a few).
        3 if len > 0 => {
            let i = pos(rng, len);
            let d = rng.random_range(1..=16u8);
            data[i] = if rng.random_bool(0.5) { data[i].wrapping_add(d) } else { data[i].wrapping_sub(d) };
        }
        // Insert random bytes, or a run of one byte.
        4 => {
            let at = pos(rng, len + 1);
            let n = short_len(rng);
            let run: Vec<u8> =
                if rng.random_bool(0.3) { vec![rng.random(); n * 4] } else { (0..n).map(|_| rng.random()).collect() };
            data.splice(at..at, run);
        }
        // Delete a range.
        5 if len > 0 => {
            let at = pos(rng, len);
            let n = short_len(rng).min(len - at);
            data.drain(at..at + n);
        }
        // Copy a range of the input elsewhere in it (repeated elements).
        6 if len > 0 => {
            let from = pos(rng, len);
            let n = short_len(rng).min(len - from) * if rng.random_bool(0.2) { 8 } else { 1 };
            let chunk: Vec<u8> = data[from..(from + n).min(len)].to_vec();
            let at = pos(rng, len + 1);
            data.splice(at..at, chunk);
        }
        // Splice in part of another seed: its tail after a cut of ours, or a chunk.
        7 if !m.seeds.is_empty() => {
            let other = &m.seeds[rng.random_range(0..m.seeds.len())];
            let from = pos(rng, other.len());
            if rng.random_bool(0.5) {
                data.truncate(pos(rng, len + 1));
                data.extend_from_slice(&other[from..]);
            } else {
                let n = (short_len(rng) * 4).min(other.len() - from);
                let chunk = other[from..from + n].to_vec();
                put(rng, data, &chunk);
            }
        }
        // An interesting integer.
        8 => {
            let b = interesting_bytes(rng);
            put(rng, data, &b);
        }
        // A token of the format.
        9 if !m.dictionary.is_empty() => {
            let t = m.dictionary[rng.random_range(0..m.dictionary.len())].clone();
            put(rng, data, &t);
        }
        // Truncate.
        10 if len > 0 => data.truncate(pos(rng, len)),
        // Swap two ranges' first bytes (reordered fields).
        11 if len > 1 => {
            let (a, b) = (pos(rng, len), pos(rng, len));
            data.swap(a, b);
        }
        // Repeat the whole input (many messages or rules back to back).
        12 if len > 0 && len < MAX_LEN / 2 => {
            let copy = data.clone();
            data.extend_from_slice(&copy);
        }
        // The chosen mutation does not apply (empty input): insert a byte instead.
        _ => {
            let at = pos(rng, len + 1);
            data.insert(at, rng.random());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_are_a_function_of_seed_target_and_index() {
        let m = Material::text(vec![b"a = 1\n".to_vec(), b"[b]\nc = \"d\"\n".to_vec()], &["=", "["]);
        let a: Vec<_> = (0..200).map(|i| input(7, "t", i, &m)).collect();
        let b: Vec<_> = (0..200).map(|i| input(7, "t", i, &m)).collect();
        assert_eq!(a, b);
        assert_ne!(a, (0..200).map(|i| input(8, "t", i, &m)).collect::<Vec<_>>());
        assert_ne!(a, (0..200).map(|i| input(7, "u", i, &m)).collect::<Vec<_>>());
        assert!(a.iter().all(|x| x.len() <= MAX_LEN));
        // Some inputs are the seeds unchanged, most are not.
        let same = a.iter().filter(|x| m.seeds.contains(x)).count();
        assert!((1..60).contains(&same), "{same}");
    }

    #[test]
    fn varints_are_postcards() {
        assert_eq!(varint(0), [0]);
        assert_eq!(varint(127), [127]);
        assert_eq!(varint(128), [0x80, 1]);
        assert_eq!(varint(u64::MAX).len(), 10);
    }

    #[test]
    fn dictionary_holds_punctuation_and_words() {
        let m = Material::text(vec![b"<start> ::= <a> | b_c".to_vec()], &["::="]);
        for w in ["::=", "start", "b_c", "18446744073709551616"] {
            assert!(m.dictionary.contains(&w.as_bytes().to_vec()), "{w}");
        }
    }
}
