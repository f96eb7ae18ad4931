//! Shared by the `*_fuzz` suites: a proptest runner whose case count follows `PROPTEST_CASES`
//! and which reports how many inputs it tried, and an allocator that measures what one call
//! allocates, so a lying count that makes a parser reserve memory is caught before it is
//! large enough to take the machine down.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use proptest::strategy::Strategy;
use proptest::test_runner::{Config, FileFailurePersistence, TestCaseError, TestRunner};

/// Passes every request to the system allocator, counting bytes per thread.
pub struct Measuring;

thread_local! {
    // Const-initialised, so reading them never allocates (which would recurse).
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn grew(bytes: usize) {
    let _ = LIVE.try_with(|live| {
        live.set(live.get() + bytes as isize);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(live.get())));
    });
}

fn shrank(bytes: usize) {
    let _ = LIVE.try_with(|live| live.set(live.get() - bytes as isize));
}

// SAFETY: every call is forwarded unchanged to `System`; the counters only observe.
unsafe impl GlobalAlloc for Measuring {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        grew(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        grew(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        shrank(layout.size());
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        grew(new_size);
        shrank(layout.size());
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Measuring = Measuring;

/// Runs `f` and returns its result with the most bytes it held at once on this thread, beyond
/// what was held before (the result's own memory included).
pub fn peak_bytes<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let r = f();
    let peak = PEAK.with(Cell::get);
    (r, (peak - base).max(0) as usize)
}

/// Cases per property: `PROPTEST_CASES` if set, else `default`.
pub fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Runs property `name` over `cases(default)` inputs of `strategy`, printing how many were
/// tried (shown with `--nocapture`). Failures are saved next to the calling test file, where the
/// `proptest!` macro saves them in this crate's tests.
pub fn check<S: Strategy>(
    source_file: &'static str,
    name: &str,
    default: u32,
    strategy: S,
    test: impl Fn(S::Value) -> Result<(), TestCaseError>,
) {
    let config = Config {
        cases: cases(default),
        source_file: Some(source_file),
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource(
            "proptest-regressions",
        ))),
        ..Config::default()
    };
    let tried = Cell::new(0u64);
    let mut runner = TestRunner::new(config);
    let result = runner.run(&strategy, |value| {
        tried.set(tried.get() + 1);
        test(value)
    });
    if let Err(e) = result {
        panic!("{name}: {e}");
    }
    println!("fuzz {name}: {} inputs tried", tried.get());
}

/// One edit of an encoded input: the byte-level damage every suite that parses bytes tries.
#[derive(Clone, Debug)]
#[allow(dead_code, reason = "the manifest suite edits lines, not bytes")]
pub enum ByteEdit {
    FlipBit(usize, u8),
    SetByte(usize, u8),
    Truncate(usize),
    /// Removes up to `len` bytes at a position.
    Delete(usize, usize),
    /// Inserts bytes at a position.
    Insert(usize, Vec<u8>),
}

/// Edits drawing set bytes from `byte` and deleting or inserting up to `span` bytes, each kind
/// equally likely.
#[allow(dead_code, reason = "the manifest suite edits lines, not bytes")]
pub fn byte_edit(
    byte: impl Strategy<Value = u8> + 'static,
    span: usize,
) -> impl Strategy<Value = ByteEdit> {
    use proptest::prelude::*;
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(at, bit)| ByteEdit::FlipBit(at, bit)),
        (any::<usize>(), byte).prop_map(|(at, v)| ByteEdit::SetByte(at, v)),
        any::<usize>().prop_map(ByteEdit::Truncate),
        (any::<usize>(), 1usize..span).prop_map(|(at, n)| ByteEdit::Delete(at, n)),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..span))
            .prop_map(|(at, b)| ByteEdit::Insert(at, b)),
    ]
}

impl ByteEdit {
    /// Applies the edit; positions wrap around the input's length.
    #[allow(dead_code, reason = "the manifest suite edits lines, not bytes")]
    pub fn apply(&self, bytes: &mut Vec<u8>) {
        let len = bytes.len();
        match self {
            ByteEdit::FlipBit(i, bit) if len > 0 => bytes[i % len] ^= 1 << bit,
            ByteEdit::SetByte(i, v) if len > 0 => bytes[i % len] = *v,
            ByteEdit::Truncate(n) => bytes.truncate(n % (len + 1)),
            ByteEdit::Delete(i, n) => {
                let i = i % (len + 1);
                bytes.drain(i..(i + n).min(len));
            }
            ByteEdit::Insert(i, b) => {
                let i = i % (len + 1);
                bytes.splice(i..i, b.iter().copied());
            }
            _ => {}
        }
    }
}
