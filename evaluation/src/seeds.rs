//! Held episode seeds: derived from a server secret, the task and the position (threshold, episode), so they are
//! fixed per task, identical for every submission and every re-run of a job, and never shown to a submitter.

use sha2::{Digest, Sha256};

/// The held-seed policy as the protocol version names it: how `HeldSeeds::seeds` derives a seed. A change to the
/// derivation must change this name (and so the protocol version).
pub const POLICY: &str =
    "sha256(\"dsrl-evaluation-seed/1\", server secret, task, threshold index, episode) & (2^31 - 1)";

pub struct HeldSeeds {
    secret: String,
}

impl HeldSeeds {
    pub fn new(secret: String) -> HeldSeeds {
        HeldSeeds { secret }
    }

    /// The seeds of `episodes` episodes at the task's `threshold_index`-th threshold. They fit in 31 bits, which
    /// every simulator's seeding accepts (Bullet's NumPy `RandomState` takes at most 32).
    pub fn seeds(&self, task: &str, threshold_index: usize, episodes: u32) -> Vec<u64> {
        (0..episodes)
            .map(|episode| {
                let mut h = Sha256::new();
                h.update(b"dsrl-evaluation-seed/1\0");
                h.update(self.secret.as_bytes());
                h.update(b"\0");
                h.update(task.as_bytes());
                h.update((threshold_index as u64).to_le_bytes());
                h.update(u64::from(episode).to_le_bytes());
                let d = h.finalize();
                u64::from_le_bytes(d[..8].try_into().expect("8 bytes")) & 0x7fff_ffff
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_depend_on_the_secret_task_and_position_only() {
        let a = HeldSeeds::new("s1".into());
        assert_eq!(a.seeds("T", 0, 20), HeldSeeds::new("s1".into()).seeds("T", 0, 20));
        assert_eq!(a.seeds("T", 0, 5), a.seeds("T", 0, 20)[..5]);
        assert_ne!(a.seeds("T", 0, 20), a.seeds("T", 1, 20));
        assert_ne!(a.seeds("T", 0, 20), a.seeds("U", 0, 20));
        assert_ne!(a.seeds("T", 0, 20), HeldSeeds::new("s2".into()).seeds("T", 0, 20));
        let s = a.seeds("T", 2, 20);
        assert!(s.iter().all(|&x| x < 1 << 31));
        let mut unique = s.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), s.len());
    }
}
