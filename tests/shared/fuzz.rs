//! The proptest configuration of every fuzz property in the test binaries
//! that include this file: a fixed seed, so a CI run is reproducible.

use proptest::test_runner::{Config, RngSeed};

/// `cases` per property, or `PROPTEST_CASES` (the opt-in long run), with a
/// fixed seed that `PROPTEST_RNG_SEED` overrides; no failure files.
pub fn seeded(cases: u32) -> Config {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<u64>().ok());
    Config {
        cases: env("PROPTEST_CASES").map_or(cases, |c| c as u32),
        rng_seed: RngSeed::Fixed(env("PROPTEST_RNG_SEED").unwrap_or(20_261_123)),
        failure_persistence: None,
        ..Config::default()
    }
}
