//! Progressive frames: a frame's samples cut into subframes, each a whole image pass whose
//! fixed-point sums add up in the film. Since every sample's light depends only on (pixel,
//! sample, depth, purpose) and the sums are integers, the film after the last subframe holds
//! the very sums a one-pass render makes: the same image to the bit.

/// A run of consecutive samples of every pixel: a progressive subframe's, or a whole frame's.
/// Sample numbers are the frame's own (the random numbers hash them), so the same sample
/// renders the same light whichever run it is in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Samples {
    /// The run's first sample.
    pub first: u32,
    /// Samples in the run (at least 1 in a frame).
    pub count: u32,
}

impl Samples {
    /// All `spp` samples of a frame rendered in one pass.
    pub fn all(spp: u32) -> Self {
        Samples {
            first: 0,
            count: spp,
        }
    }

    /// One past the run's last sample.
    pub fn end(&self) -> u32 {
        self.first.saturating_add(self.count)
    }

    /// The run's sample numbers.
    pub fn range(&self) -> std::ops::Range<u32> {
        self.first..self.end()
    }

    /// Where `sample` falls in the run (its index among the run's samples of a pixel).
    pub fn offset(&self, sample: u32) -> Option<u32> {
        self.range().contains(&sample).then(|| sample - self.first)
    }
}

/// Most subframes a frame is cut into: each costs a frame start on every worker, so a job
/// asking for more gets subframes this many at most (larger ones).
pub const MAX_SUBFRAMES: u32 = 256;

/// How a frame's samples are cut into subframes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progressive {
    /// All samples in one pass (one subframe).
    OnePass,
    /// 1, 1, 2, 4, 8, ... samples: each subframe as many as all before it, so each preview
    /// has twice the samples of the last.
    Doubling,
    /// This many samples a subframe (the last may have fewer).
    Every(u32),
}

impl Progressive {
    /// The job field's meaning: absent is one pass, 0 doubling, N that many samples a
    /// subframe.
    pub fn from_field(subframe_spp: Option<u32>) -> Self {
        match subframe_spp {
            None => Progressive::OnePass,
            Some(0) => Progressive::Doubling,
            Some(n) => Progressive::Every(n),
        }
    }

    /// The subframes of a frame of `spp` samples, in order: consecutive runs covering
    /// `0..spp` exactly, at most [`MAX_SUBFRAMES`] of them (a fixed size too small for that
    /// is raised to the least that fits).
    pub fn subframes(self, spp: u32) -> Vec<Samples> {
        let spp = spp.max(1);
        let mut out = Vec::new();
        let mut first = 0u32;
        while first < spp {
            let count = match self {
                Progressive::OnePass => spp,
                Progressive::Doubling => first.max(1),
                Progressive::Every(n) => n.max(spp.div_ceil(MAX_SUBFRAMES)),
            };
            let count = count.min(spp - first);
            out.push(Samples { first, count });
            first += count;
        }
        out
    }

    /// The CLI's spelling: `doubling` or a number of samples per subframe.
    pub fn parse(text: &str) -> Result<Self, String> {
        match text {
            "doubling" => Ok(Progressive::Doubling),
            n => match n.parse::<u32>() {
                Ok(n) if n > 0 => Ok(Progressive::Every(n)),
                _ => Err(format!(
                    "progressive {text:?}: expected `doubling` or a number of samples per \
                     subframe (1 or more)"
                )),
            },
        }
    }

    /// The job field for this: see [`from_field`](Self::from_field).
    pub fn field(self) -> Option<u32> {
        match self {
            Progressive::OnePass => None,
            Progressive::Doubling => Some(0),
            Progressive::Every(n) => Some(n),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn counts(p: Progressive, spp: u32) -> Vec<u32> {
        p.subframes(spp).iter().map(|s| s.count).collect()
    }

    #[test]
    fn subframes_cover_every_sample_once_in_order() {
        for spp in [1, 2, 3, 7, 16, 100, 65536] {
            for p in [
                Progressive::OnePass,
                Progressive::Doubling,
                Progressive::Every(1),
                Progressive::Every(3),
                Progressive::Every(70_000),
            ] {
                let subs = p.subframes(spp);
                assert!(subs.len() as u32 <= MAX_SUBFRAMES, "{p:?} {spp}");
                let mut next = 0;
                for s in &subs {
                    assert_eq!(s.first, next);
                    assert!(s.count >= 1);
                    next = s.end();
                }
                assert_eq!(next, spp, "{p:?} {spp}");
            }
        }
    }

    #[test]
    fn doubling_doubles_the_samples_so_far() {
        assert_eq!(counts(Progressive::Doubling, 16), [1, 1, 2, 4, 8]);
        assert_eq!(counts(Progressive::Doubling, 6), [1, 1, 2, 2]);
        assert_eq!(counts(Progressive::Every(3), 8), [3, 3, 2]);
        assert_eq!(counts(Progressive::OnePass, 8), [8]);
        // 1000 subframes asked for: 256 at most.
        assert_eq!(Progressive::Every(1).subframes(1000).len(), 250);
    }

    #[test]
    fn the_field_and_the_flag_round_trip() {
        for p in [
            Progressive::OnePass,
            Progressive::Doubling,
            Progressive::Every(4),
        ] {
            assert_eq!(Progressive::from_field(p.field()), p);
        }
        assert_eq!(Progressive::parse("doubling"), Ok(Progressive::Doubling));
        assert_eq!(Progressive::parse("8"), Ok(Progressive::Every(8)));
        assert!(Progressive::parse("0").is_err());
        assert!(Progressive::parse("fast").is_err());
    }
}
