//! The coordinator machine: jobs, workers, rounds, the tile ledger, job store records.
