//! Helpers shared by this crate's unit tests.

/// A valid music-to-dance manifest with a small window (T = 8, stride 4, 6 mel frames, DDIM 10
/// steps); the same file serves the package tests in `models/tests/`.
pub(crate) fn manifest_text(sha256: &str) -> String {
    include_str!("../tests/data/tiny-manifest.toml").replace("@SHA256@", sha256)
}

/// A sha256 that parses (the file check happens at load, not parse).
pub(crate) const ANY_SHA: &str = "0000000000000000000000000000000000000000000000000000000000000000";
