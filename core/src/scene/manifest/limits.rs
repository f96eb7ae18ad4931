//! How large a manifest may be: the most domains, the longest names and numbers, and so the
//! most bytes read, every manifest `prepare` writes within them.

/// Most domains a scene may have (`prepare --domains`' limit, checked when a manifest is read).
pub const MAX_DOMAINS: u32 = 1 << 16;

/// Longest file name a domain entry may give (prepare writes 16 to 18 bytes); names are
/// ASCII letters, digits, `.`, `-` and `_`, so TOML writes them unescaped and a domain's text
/// stays within [`MAX_DOMAIN_TEXT_BYTES`].
pub const MAX_FILE_NAME: usize = 32;

/// Longest checksum text: 16 hex digits, a 64-bit hash.
pub(super) const MAX_CHECKSUM: usize = 16;

/// Longest text TOML writes for an `f32`: `{}` never uses an exponent, so the longest are
/// negative normals near the smallest, `-0.` then 37 zeros and up to 9 significant digits
/// (the 9 digits that round-trip any `f32`); subnormals need no digit past the 45th place
/// (their spacing is 1.4e-45), and numbers from 1 up print at most 39 integer digits and `.0`.
/// Checked by `manifest::tests::no_f32_is_longer_than_its_bound`.
pub const MAX_F32_TEXT: usize = 49;

/// Most text one domain adds to a manifest: its entry (with a volume brick's value range and
/// surfaces file) and its two k-d tree nodes (a leaf, and the split that a tree of n leaves
/// has n - 1 of), every number and name at its longest (`manifest::tests`).
pub const MAX_DOMAIN_TEXT_BYTES: u64 = 896;

/// Room for everything but the domains and the k-d tree: name, camera, sky, materials (prepare
/// writes up to 263), lights, a volume's transfer function (prepare reads up to
/// `transfer::MAX_POINTS` points; `manifest::tests`).
pub const MAX_MANIFEST_HEAD_BYTES: u64 = 2 << 20;

/// Largest manifest read: every manifest prepare can write fits, [`MAX_DOMAINS`] domains at
/// their longest after the longest head (`manifest::tests` checks the sum), and nothing larger
/// is read. 58 MiB; a 65,536-domain scene prepare writes is about 23.4 MB (README "Scenes").
pub const MAX_MANIFEST_BYTES: u64 =
    MAX_MANIFEST_HEAD_BYTES + MAX_DOMAINS as u64 * MAX_DOMAIN_TEXT_BYTES;
