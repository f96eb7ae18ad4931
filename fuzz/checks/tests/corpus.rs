//! Replays every committed corpus input (`fuzz/corpus/<target>/`, seeds and what fuzzing
//! kept) through its target's checks, so every CI run holds what fuzzing once found.

use std::path::Path;

type Check = fn(&[u8]);

const TARGETS: [(&str, Check); 12] = [
    ("ray_batch", rayfarm_fuzz::ray_batch),
    ("verdict_batch", rayfarm_fuzz::verdict_batch),
    ("manifest", rayfarm_fuzz::manifest),
    ("mesh", rayfarm_fuzz::mesh),
    ("domain_file", rayfarm_fuzz::domain_file),
    ("job_request", rayfarm_fuzz::job_request),
    ("worker_message", rayfarm_fuzz::worker_message),
    ("peer_bundle", rayfarm_fuzz::peer_bundle),
    ("brick", rayfarm_fuzz::brick),
    ("transfer_function", rayfarm_fuzz::transfer_function),
    ("job_api_request", rayfarm_fuzz::job_api_request),
    ("domain_request", rayfarm_fuzz::domain_request),
];

#[test]
fn every_corpus_input_passes_its_checks() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../corpus");
    for (target, check) in TARGETS {
        let dir = root.join(target);
        let inputs: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        assert!(!inputs.is_empty(), "{} holds no input", dir.display());
        for input in &inputs {
            let bytes = std::fs::read(input).unwrap();
            let run = std::panic::catch_unwind(|| check(&bytes));
            assert!(
                run.is_ok(),
                "{target}: {} fails its checks",
                input.display()
            );
        }
        eprintln!("{target}: {} inputs", inputs.len());
    }
}
