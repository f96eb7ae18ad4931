//! The check that every successful run of a bench made the same image, and if not, which
//! runs made which.

use super::RunOutcome;

/// Whether every successful run made the same image.
#[derive(Clone, Debug, PartialEq)]
pub enum HashCheck {
    /// No run succeeded: nothing to compare.
    NoImages,
    /// `count` images, all with hash `hash`.
    Identical { count: usize, hash: String },
    /// Each distinct hash with the runs ("run 3 (domain, repeat 1)") that made it, the most
    /// common first.
    Differ(Vec<(String, Vec<String>)>),
}

/// Compares the image hashes of every successful run.
pub fn check_hashes(runs: &[RunOutcome]) -> HashCheck {
    let mut groups: Vec<(String, Vec<String>)> = Vec::new();
    for r in runs {
        let Some(s) = r.stats() else { continue };
        let label = format!("run {} ({}, repeat {})", r.run, r.schedule, r.repeat);
        match groups.iter_mut().find(|(h, _)| *h == s.image_hash) {
            Some((_, labels)) => labels.push(label),
            None => groups.push((s.image_hash.clone(), vec![label])),
        }
    }
    match groups.len() {
        0 => HashCheck::NoImages,
        1 => {
            let (hash, labels) = groups.remove(0);
            HashCheck::Identical {
                count: labels.len(),
                hash,
            }
        }
        _ => {
            // Stable: equal counts keep their first-seen order.
            groups.sort_by_key(|(_, labels)| std::cmp::Reverse(labels.len()));
            HashCheck::Differ(groups)
        }
    }
}
