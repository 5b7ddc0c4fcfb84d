//! Seed derivation: every sample's random stream is a pure function of (seed, index).

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Mixes two 64-bit values into a well-spread seed (SplitMix64 finaliser over a combination).
pub fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b
        .wrapping_add(0x9e37_79b9_7f4a_7c15)
        .wrapping_add(a << 6)
        .wrapping_add(a >> 2);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The random stream of sample `index` of a run seeded with `seed`.
pub fn sample_rng(seed: u64, index: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix(seed, index))
}
