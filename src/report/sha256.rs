//! SHA-256 of the plan and sensor texts for `verdict.json`'s provenance: two identical
//! hashes mean byte-identical inputs. Computed by the `sha2` crate (RustCrypto), which
//! replaced a hand-written FIPS 180-4 implementation; the tests keep that
//! implementation's outputs (block-boundary lengths included) as test vectors, so the
//! hashes in existing `verdict.json` files stay reproducible.

use sha2::{Digest, Sha256};

/// SHA-256 of `data` as 64 lowercase hex digits.
pub fn sha256_hex(data: &[u8]) -> String {
    Sha256::digest(data)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fips_180_4_example_vectors() {
        assert_eq!(
            sha256_hex(b""),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(
            sha256_hex(b"abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
            "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1"
        );
        // One million 'a': many full blocks.
        assert_eq!(
            sha256_hex(&vec![b'a'; 1_000_000]),
            "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0"
        );
    }

    /// Hashes the hand-written implementation gave before `sha2` replaced it (also
    /// checked against Python's hashlib), at the padding's edge cases: 55 and 56
    /// bytes (the length fits in the last block or not), 63/64/65 and 119/120/127/128.
    #[test]
    fn same_hashes_as_the_hand_written_implementation_at_block_boundaries() {
        let recorded = [
            (
                55,
                "8af594de0e003fdee5c8bb088216c824349b4137070f559574f4a4bddd27b714",
            ),
            (
                56,
                "db81bc2bfd43620591df192139062da77d4c376f1888ea3d2190bd07c8d901f9",
            ),
            (
                63,
                "bd535b38bf0d0d1a09d370b7e34b2696cea3767801a45d5611a4aaa6954e8527",
            ),
            (
                64,
                "292be91abe8c0909fe3d26575af5755eee74d23816dc68c3ba41765136967654",
            ),
            (
                65,
                "ba65aedf7884642499a59ae124894611d986cf429e69f569488048af3a99e25a",
            ),
            (
                119,
                "d367ab298e74477421127b0b448667c37c006c636f5738f081c39388756e5fad",
            ),
            (
                120,
                "be7beb9c82089eb08da8fe6eb30c13b9d56869014e228a8c3eb0fdfe832efab2",
            ),
            (
                127,
                "770cba7b80c7615a327db5812ccd3f80895d801b587448fcd0b2c1a10f5c88a3",
            ),
            (
                128,
                "cb5311e1d7aa8e11d6af7081f3ffc3e4efa008c7483a1a791fe170bf37546ba7",
            ),
        ];
        for (n, hex) in recorded {
            let data: Vec<u8> = (0..n).map(|i| (i * 7 % 251) as u8).collect();
            assert_eq!(sha256_hex(&data), hex, "{n} bytes");
        }
        // A plan text as `verdict.json` hashes it.
        assert_eq!(
            sha256_hex(b"name = \"fig7\"\nsensor = \"paper_sensor.toml\"\n"),
            "c30c5e0d9ead2dbad5d4707bd892371ce2b9929c7171f06d6fbc8c6d9145c79d"
        );
    }
}
