//! The job queue: higher priority first, equal priorities in submission order. Pure, so the
//! order is unit-tested without a server.

use std::cmp::Reverse;
use std::collections::BTreeSet;

/// Queued job ids in the order they will run.
#[derive(Debug, Default)]
pub struct JobQueue {
    /// (priority descending, submission sequence ascending, id).
    order: BTreeSet<(Reverse<i32>, u64, String)>,
}

impl JobQueue {
    /// Queues `id`, submitted as the `seq`-th job, at `priority`.
    pub fn push(&mut self, id: String, priority: i32, seq: u64) {
        self.order.insert((Reverse(priority), seq, id));
    }

    /// Takes the job that runs next.
    pub fn pop(&mut self) -> Option<String> {
        self.order.pop_first().map(|(_, _, id)| id)
    }

    /// Removes `id` if queued; true if it was.
    pub fn remove(&mut self, id: &str) -> bool {
        let found = self.order.iter().find(|(_, _, i)| i == id).cloned();
        found.is_some_and(|key| self.order.remove(&key))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn higher_priority_first_then_submission_order() {
        let mut q = JobQueue::default();
        q.push("a".into(), 0, 1);
        q.push("b".into(), 5, 2);
        q.push("c".into(), 0, 3);
        q.push("d".into(), 5, 4);
        q.push("e".into(), -1, 5);
        assert!(q.remove("c"));
        assert!(!q.remove("c"));
        let order: Vec<String> = std::iter::from_fn(|| q.pop()).collect();
        assert_eq!(order, ["b", "d", "a", "e"]);
        assert_eq!(q.pop(), None);
    }
}
