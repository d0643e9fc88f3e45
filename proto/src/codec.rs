//! The versioned envelope: one version byte, then the `postcard` encoding.
//!
//! A message of another version or that does not decode is an error the receiver counts
//! and drops; nothing here can panic on network input.
use serde::{Deserialize, Serialize};

/// Bumped whenever a message type changes shape.
pub const WIRE_VERSION: u8 = 12;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CodecError {
    #[error("empty message")]
    Empty,
    #[error("wire version {got}, expected {expected}")]
    Version { got: u8, expected: u8 },
    #[error("message does not decode: {0}")]
    Decode(String),
    #[error("message does not encode: {0}")]
    Encode(String),
}

pub fn encode<T: Serialize + ?Sized>(msg: &T) -> Result<Vec<u8>, CodecError> {
    encode_sized(msg, 64)
}

/// [`encode`] into a buffer of `capacity` bytes to begin with: a large message (the
/// world's gene and percept bundles, hundreds of kilobytes) grown from a small buffer
/// was copied over and over as it grew.
pub fn encode_sized<T: Serialize + ?Sized>(msg: &T, capacity: usize) -> Result<Vec<u8>, CodecError> {
    let mut out = Vec::with_capacity(capacity.max(1));
    out.push(WIRE_VERSION);
    postcard::to_extend(msg, out).map_err(|e| CodecError::Encode(e.to_string()))
}

/// Decode an enveloped message; it may borrow from `bytes` (nested messages do).
pub fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, CodecError> {
    let (&v, body) = bytes.split_first().ok_or(CodecError::Empty)?;
    if v != WIRE_VERSION {
        return Err(CodecError::Version { got: v, expected: WIRE_VERSION });
    }
    postcard::from_bytes(body).map_err(|e| CodecError::Decode(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::*;

    #[test]
    fn round_trip_and_rejects() {
        let mapping = GeneMapping { valid: true, used_codons: 2, depth: 3 };
        let g = GeneMsg { step: 3, from: 9, genome: vec![1, 2, 2000].into(), fitness: 1.5, mapping };
        let b = encode(&g).unwrap();
        assert_eq!(decode::<GeneMsg>(&b).unwrap(), g);
        let mut bad = b.clone();
        bad[0] = 99;
        assert!(matches!(decode::<GeneMsg>(&bad), Err(CodecError::Version { got: 99, .. })));
        assert_eq!(decode::<GeneMsg>(&[]), Err(CodecError::Empty));
        assert!(matches!(decode::<GeneMsg>(&b[..3]), Err(CodecError::Decode(_))));
    }

    #[test]
    fn genomes_travel_as_two_or_four_byte_codons_and_malformed_ones_are_rejected() {
        let mapping = GeneMapping::default();
        let gene = |genome: Vec<u32>| GeneMsg { step: 1, from: 2, genome: genome.into(), fitness: 0.0, mapping };
        let narrow = encode(&gene(vec![7; 100])).unwrap();
        let wide = encode(&gene(vec![70_000; 100])).unwrap();
        assert!(wide.len() > narrow.len() + 150, "{} vs {}", wide.len(), narrow.len());
        for g in [gene(vec![]), gene(vec![0, 65_535]), gene(vec![65_536, 1, u32::MAX])] {
            assert_eq!(decode::<GeneMsg>(&encode(&g).unwrap()).unwrap(), g);
        }
        // Step 1, from 2, then the genome's length and width byte: a width of 3, or an
        // odd number of bytes at width 2, does not decode.
        let b = encode(&gene(vec![1, 2])).unwrap();
        assert_eq!(&b[1..5], &[1, 2, 5, 2]);
        for (at, byte) in [(4, 3u8), (3, 4)] {
            let mut bad = b.clone();
            bad[at] = byte;
            assert!(matches!(decode::<GeneMsg>(&bad), Err(CodecError::Decode(_))), "byte {at} = {byte}");
        }
    }
}
