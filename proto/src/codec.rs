//! The versioned envelope: one version byte, then the `postcard` encoding.
//!
//! A message of another version or that does not decode is an error the receiver counts
//! and drops; nothing here can panic on network input.
use serde::{de::DeserializeOwned, Serialize};

/// Bumped whenever a message type changes shape.
pub const WIRE_VERSION: u8 = 4;

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

pub fn encode<T: Serialize>(msg: &T) -> Result<Vec<u8>, CodecError> {
    let mut out = vec![WIRE_VERSION];
    let body = postcard::to_stdvec(msg).map_err(|e| CodecError::Encode(e.to_string()))?;
    out.extend_from_slice(&body);
    Ok(out)
}

pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CodecError> {
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
}
