//! One domain's rays in memory, in order, as the vectors they were queued in: queueing a
//! vector the caller gives up never copies it or regrows what is queued (one growing vector
//! per domain, copied on every doubling and page-faulted afresh, was a twentieth of a
//! predictive worker's event loop: perf, README "Benchmarks"). Rays are copied once, when a
//! pass takes more than one part.

use rayfarm_core::ray::RayRecord;

/// Rays fewer than this are added to a part with room for them rather than kept as a part
/// of their own (so trickles of a few rays do not make a long list of tiny parts).
const SMALL: usize = 256;

/// Rays a part made for such trickles has room for: a part is never grown, since growing a
/// large one would copy it whole for a few rays.
const TRICKLE_PART: usize = 4 * SMALL;

/// See the module documentation.
#[derive(Default)]
pub(super) struct Parts {
    parts: Vec<Vec<RayRecord>>,
    len: usize,
}

impl Parts {
    /// Rays held.
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Appends `rays`, kept as they are unless they are a few.
    pub(super) fn push_owned(&mut self, rays: Vec<RayRecord>) {
        if rays.len() < SMALL {
            return self.push(&rays);
        }
        self.len += rays.len();
        self.parts.push(rays);
    }

    /// Appends a copy of `rays`.
    pub(super) fn push(&mut self, rays: &[RayRecord]) {
        if rays.is_empty() {
            return;
        }
        self.len += rays.len();
        if rays.len() >= SMALL {
            return self.parts.push(rays.to_vec());
        }
        match self.parts.last_mut() {
            Some(last) if last.capacity() - last.len() >= rays.len() => {
                last.extend_from_slice(rays);
            }
            _ => {
                let mut part = Vec::with_capacity(TRICKLE_PART);
                part.extend_from_slice(rays);
                self.parts.push(part);
            }
        }
    }

    /// Takes the last `n` rays held (all if fewer), in their order.
    pub(super) fn take_back(&mut self, n: usize) -> Vec<RayRecord> {
        let n = n.min(self.len);
        self.len -= n;
        // Whole parts from the back while they fit, then the end of the part before them.
        let mut first_whole = self.parts.len();
        let mut whole = 0;
        while first_whole > 0 && whole + self.parts[first_whole - 1].len() <= n {
            first_whole -= 1;
            whole += self.parts[first_whole].len();
        }
        let mut tail = self.parts.split_off(first_whole);
        let partial = n - whole;
        if partial == 0 && tail.len() == 1 {
            // One part taken whole: it goes as it is.
            return tail.pop().unwrap_or_default();
        }
        let mut out = Vec::with_capacity(n);
        if let Some(part) = self.parts.last_mut().filter(|_| partial > 0) {
            let from = part.len() - partial;
            out.extend_from_slice(&part[from..]);
            part.truncate(from);
        }
        for part in tail {
            out.extend(part);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rays(from: u32, n: u32) -> Vec<RayRecord> {
        (from..from + n)
            .map(|pixel| RayRecord {
                pixel,
                ..bytemuck::Zeroable::zeroed()
            })
            .collect()
    }

    /// Taking from the back gives what one vector of all rays pushed would give.
    #[test]
    fn parts_take_as_one_vector_would() {
        let mut parts = Parts::default();
        let mut flat: Vec<RayRecord> = Vec::new();
        let mut next = 0;
        let mut x: u64 = 11;
        for step in 0..300 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let n = ((x >> 33) % 700) as u32;
            match step % 3 {
                0 => {
                    let r = rays(next, n);
                    flat.extend_from_slice(&r);
                    parts.push_owned(r);
                    next += n;
                }
                1 => {
                    let r = rays(next, n);
                    parts.push(&r);
                    flat.extend_from_slice(&r);
                    next += n;
                }
                _ => {
                    let take = n as usize;
                    let want = flat.split_off(flat.len() - take.min(flat.len()));
                    let got = parts.take_back(take);
                    let pixels = |v: &[RayRecord]| v.iter().map(|r| r.pixel).collect::<Vec<_>>();
                    assert_eq!(pixels(&got), pixels(&want), "step {step}");
                }
            }
            assert_eq!(parts.len(), flat.len(), "step {step}");
        }
    }

    #[test]
    fn a_trickle_never_grows_a_large_part() {
        let mut parts = Parts::default();
        let big = rays(0, 1000);
        let at = big.as_ptr();
        parts.push_owned(big);
        parts.push_owned(rays(1000, 3));
        parts.push(&rays(1003, 2));
        assert_eq!(
            parts.parts[0].as_ptr(),
            at,
            "the large part stays where it was"
        );
        assert_eq!((parts.parts.len(), parts.parts[1].len()), (2, 5));
        let pixels: Vec<u32> = parts.take_back(7).iter().map(|r| r.pixel).collect();
        assert_eq!(pixels, (998..1005).collect::<Vec<_>>());
    }

    #[test]
    fn a_part_taken_whole_is_not_copied() {
        let mut parts = Parts::default();
        let big = rays(0, 1000);
        let at = big.as_ptr();
        parts.push_owned(big);
        let taken = parts.take_back(5000);
        assert_eq!(taken.as_ptr(), at);
        assert_eq!(parts.len(), 0);
    }
}
