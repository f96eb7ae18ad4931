//! Which kernel and whether packets: chosen once per process, from the CPU and the
//! `RAYFARM_KERNEL` and `RAYFARM_PACKETS` variables.

use std::sync::OnceLock;

/// Which instructions traverse the tree. All give the same hits to the bit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// One box and one triangle at a time: runs anywhere, the reference.
    Scalar,
    /// Four boxes (two halves of a node) and four triangles at a time, SSE2: any x86-64.
    Sse,
    /// Eight boxes at a time with AVX2 and FMA, four triangles with SSE (and POPCNT, which
    /// every AVX2 CPU has, to order a node's children).
    Avx2,
}

impl Kernel {
    /// Every kernel, slowest first.
    pub const ALL: [Kernel; 3] = [Kernel::Scalar, Kernel::Sse, Kernel::Avx2];

    /// The name `RAYFARM_KERNEL` takes.
    pub fn name(self) -> &'static str {
        match self {
            Kernel::Scalar => "scalar",
            Kernel::Sse => "sse",
            Kernel::Avx2 => "avx2",
        }
    }

    /// The kernel named `name` (as `RAYFARM_KERNEL` spells it).
    pub fn parse(name: &str) -> Result<Kernel, String> {
        Kernel::ALL
            .into_iter()
            .find(|k| k.name() == name.trim().to_ascii_lowercase())
            .ok_or_else(|| format!("RAYFARM_KERNEL={name:?}: expected avx2, sse or scalar"))
    }

    /// Whether this CPU can run the kernel.
    pub fn supported(self) -> bool {
        match self {
            Kernel::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => {
                is_x86_feature_detected!("avx2")
                    && is_x86_feature_detected!("fma")
                    && is_x86_feature_detected!("popcnt")
            }
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The fastest kernel this CPU runs.
    pub fn detect() -> Kernel {
        Kernel::ALL
            .into_iter()
            .rev()
            .find(|k| k.supported())
            .unwrap_or(Kernel::Scalar)
    }

    /// The process's kernel: `RAYFARM_KERNEL` if set to one this CPU runs, else [`Kernel::detect`].
    /// Decided once; a value that cannot be honoured is reported and the detected kernel used.
    pub fn selected() -> Kernel {
        static SELECTED: OnceLock<Kernel> = OnceLock::new();
        *SELECTED.get_or_init(|| {
            let detected = Kernel::detect();
            let Ok(value) = std::env::var("RAYFARM_KERNEL") else {
                return detected;
            };
            match Kernel::parse(&value) {
                Ok(k) if k.supported() => {
                    tracing::info!(kernel = k.name(), "traversal kernel forced");
                    k
                }
                Ok(k) => {
                    tracing::warn!(
                        forced = k.name(),
                        kernel = detected.name(),
                        "this CPU cannot run the forced traversal kernel"
                    );
                    detected
                }
                Err(e) => {
                    tracing::warn!(kernel = detected.name(), "{e}");
                    detected
                }
            }
        })
    }
}

/// Whether packets are on for this process: `RAYFARM_PACKETS=0` (or `off`) turns them off, to
/// measure them or rule them out; decided once.
pub fn packets_selected() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| match std::env::var("RAYFARM_PACKETS") {
        Ok(v) if matches!(v.trim(), "0" | "off" | "false" | "no") => {
            tracing::info!("ray packets off");
            false
        }
        _ => true,
    })
}
