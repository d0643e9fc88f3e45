//! Seed derivation: every random stream is named by (run seed, owner, purpose) so that
//! the same draws happen whether the owner lives in this process or another.

/// Who owns a random stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Owner {
    World,
    Agent(u32),
    Orchestrator,
}

/// What a stream is used for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Purpose {
    /// World layout: positions, headings, placements.
    Layout = 1,
    /// Run-time perturbations (obstacle placement, kills).
    Perturb = 2,
    /// Behaviour-tree randomness (GoTo target choice, RandomWalk noise).
    Behaviour = 3,
    /// Grammatical evolution (initialisation, crossover, mutation).
    Evolution = 4,
    /// Interaction-probability draws.
    Interaction = 5,
    /// Injected message loss.
    Loss = 6,
}

/// SplitMix64 finaliser: a well-mixed 64-bit hash of one word.
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The seed of stream (run seed, owner, purpose).
pub fn derive(run_seed: u64, owner: Owner, purpose: Purpose) -> u64 {
    let o = match owner {
        Owner::World => 1u64 << 40,
        Owner::Agent(id) => (2u64 << 40) | id as u64,
        Owner::Orchestrator => 3u64 << 40,
    };
    mix64(mix64(run_seed ^ mix64(o)) ^ (purpose as u64).wrapping_mul(0xA076_1D64_78BD_642F))
}

/// FNV-1a, for digests that must agree across processes and builds.
#[derive(Clone, Copy, Debug)]
pub struct Fnv64(u64);

impl Default for Fnv64 {
    fn default() -> Self {
        Fnv64(0xcbf2_9ce4_8422_2325)
    }
}

impl Fnv64 {
    pub fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01B3);
        }
    }
    /// One FNV-1a round over a whole 64-bit word instead of its eight bytes: digests
    /// computed every step (the world's) take one multiply per word.
    pub fn write_word(&mut self, v: u64) {
        self.0 = (self.0 ^ v).wrapping_mul(0x0000_0100_0000_01B3);
    }
    pub fn finish(&self) -> u64 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn streams_differ_and_are_stable() {
        let a = derive(1, Owner::Agent(0), Purpose::Behaviour);
        let b = derive(1, Owner::Agent(1), Purpose::Behaviour);
        let c = derive(1, Owner::Agent(0), Purpose::Evolution);
        let d = derive(2, Owner::Agent(0), Purpose::Behaviour);
        assert!(a != b && a != c && a != d);
        assert_eq!(a, derive(1, Owner::Agent(0), Purpose::Behaviour));
        let mut h = Fnv64::default();
        h.write(b"a");
        assert_eq!(h.finish(), 0xaf63dc4c8601ec8c);
    }
}
