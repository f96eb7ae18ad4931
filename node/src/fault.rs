//! Test instrumentation, off unless asked for: random delays on outgoing messages, to show
//! that no arrival order can make a tile complete early. Set `RAYFARM_FAULT_DELAY_MS` (the
//! largest delay) and `RAYFARM_FAULT_SEED`. Each link keeps its order; links drift apart.

use std::time::Duration;

use tokio::sync::mpsc;

/// Delay settings read from the environment.
#[derive(Clone, Copy, Debug, Default)]
pub struct Faults {
    max_delay_ms: u64,
    seed: u64,
}

impl Faults {
    /// Reads the environment; no variables means no delays.
    pub fn from_env() -> Self {
        let var = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<u64>().ok());
        Faults {
            max_delay_ms: var("RAYFARM_FAULT_DELAY_MS").unwrap_or(0),
            seed: var("RAYFARM_FAULT_SEED").unwrap_or(0),
        }
    }

    /// Whether any fault is injected.
    pub fn active(&self) -> bool {
        self.max_delay_ms > 0
    }

    /// A receiver yielding what `rx` yields, each message held back by a pseudo-random delay
    /// (the same sequence for the same seed and link); `rx` itself when no faults are set.
    pub fn delayed<T: Send + 'static>(
        &self,
        link: &str,
        mut rx: mpsc::UnboundedReceiver<T>,
    ) -> mpsc::UnboundedReceiver<T> {
        if !self.active() {
            return rx;
        }
        let (tx, out) = mpsc::unbounded_channel();
        let mut state = self.seed ^ xxhash_rust::xxh3::xxh3_64(link.as_bytes());
        let max = self.max_delay_ms;
        tokio::spawn(async move {
            while let Some(msg) = rx.recv().await {
                state = splitmix(state);
                tokio::time::sleep(Duration::from_micros(state % (max * 1000 + 1))).await;
                if tx.send(msg).is_err() {
                    break;
                }
            }
        });
        out
    }
}

fn splitmix(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
