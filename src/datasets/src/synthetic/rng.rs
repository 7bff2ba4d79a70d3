//! The synthetic scene's random streams: the project's SplitMix64 (`seqavatar_core::rng`),
//! seeded with the scene seed XOR a fixed constant (so that seed 0 does not start the
//! generator at state 0). Changing this changes every synthetic scene.

use seqavatar_core::rng::SplitMix64;

/// The generator the scene draws from.
pub type Rng = SplitMix64;

/// Mixed into every scene seed.
const SCENE_STREAM: u64 = 0x5DEE_CE66_D1CE_4E5B;

/// The stream of scene seed `seed`.
pub fn seeded(seed: u64) -> Rng {
    SplitMix64::new(seed ^ SCENE_STREAM)
}
