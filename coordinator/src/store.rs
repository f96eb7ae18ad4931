//! The job store: every job, its state and where its result is, in an embedded redb database
//! at `<data dir>/rayfarm.redb`, so a restarted coordinator carries on where the last one
//! stopped. Images and statistics stay in files under `<data dir>/jobs/` (see `results`); the
//! store keeps their hash and statistics beside the job.
//!
//! Why redb: pure Rust (no C toolchain, no bundled SQLite), one file, ACID transactions that
//! are fsynced on commit, and typed key-value tables, which is all a job store needs; nothing
//! here wants SQL. Records are protobuf (prost) so fields can be added without a migration.
//!
//! Writes happen once per job state change (submit, start, finish, fail, cancel), never per
//! ray or tile.

use std::path::{Path, PathBuf};

use rayfarm_machine::coordinator::cluster::JobRecord;
use rayfarm_node::proto;
use redb::{ReadableDatabase, ReadableTable, ReadableTableMetadata, TableDefinition};

/// File name of the database inside the data directory.
pub const FILE_NAME: &str = "rayfarm.redb";

/// The database's page cache (see [`Store::open`]).
const CACHE_BYTES: usize = 1 << 20;

/// Job id -> [`StoredJob`] (protobuf).
const JOBS: TableDefinition<&str, &[u8]> = TableDefinition::new("jobs");
/// Sequence number -> job id: the list of jobs, newest first, read a page at a time.
const BY_SEQ: TableDefinition<u64, &str> = TableDefinition::new("jobs_by_seq");
/// Small facts about the store itself, by name.
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");
/// Meta key: the layout version of the records.
const SCHEMA_KEY: &str = "schema";
/// Meta key: the highest submission sequence number handed out.
const SEQ_KEY: &str = "seq";
/// The layout this coordinator writes and reads.
const SCHEMA: u64 = 1;

/// One job as stored.
#[derive(Clone, PartialEq, prost::Message)]
pub struct StoredJob {
    /// The job as the API lists it (spec, state, times, error).
    #[prost(message, optional, tag = "1")]
    pub summary: Option<proto::JobSummary>,
    /// Submission sequence number: equal priorities run in this order.
    #[prost(uint64, tag = "2")]
    pub seq: u64,
    /// Frames of this job started so far, across restarts. A restarted frame starts its tiles
    /// at this epoch, so rays and results of an abandoned run are told apart from the new
    /// run's and dropped.
    #[prost(uint32, tag = "3")]
    pub attempts: u32,
    /// Hash of the finished image.
    #[prost(string, tag = "4")]
    pub image_hash: String,
    /// Statistics of the finished frame as JSON.
    #[prost(string, tag = "5")]
    pub stats_json: String,
    /// One past the highest tile epoch any frame of the job announced (0 in records written
    /// before it was kept: their attempts stand in).
    #[prost(uint32, tag = "6")]
    pub epoch_floor: u32,
}

impl StoredJob {
    /// The job's id (empty if the record has no summary).
    pub fn id(&self) -> &str {
        self.summary.as_ref().map_or("", |s| s.job_id.as_str())
    }

    /// The stored form of the machine's record.
    pub fn from_record(r: &JobRecord) -> Self {
        StoredJob {
            summary: Some(r.summary.clone()),
            seq: r.seq,
            attempts: r.attempts,
            epoch_floor: r.epoch_floor,
            image_hash: r.image_hash.clone(),
            stats_json: r.stats_json.clone(),
        }
    }

    /// The machine's record of it; `None` for a record without a summary (skipped).
    pub fn into_record(self) -> Option<JobRecord> {
        let Some(summary) = self.summary else {
            tracing::warn!(seq = self.seq, "a stored job without a summary; skipped");
            return None;
        };
        Some(JobRecord {
            summary,
            seq: self.seq,
            attempts: self.attempts,
            epoch_floor: self.epoch_floor,
            image_hash: self.image_hash,
            stats_json: self.stats_json,
        })
    }
}

/// Why the store cannot be used. Every variant names the database file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// Another process holds the file's lock.
    #[error(
        "job database {path} is in use by another process (is another coordinator running on \
         this data directory?)"
    )]
    InUse { path: PathBuf },
    /// The file cannot be opened: unreadable, not a redb database, or corrupt.
    #[error(
        "job database {path} cannot be opened; it is left as it is (move it away to start with \
         no jobs)"
    )]
    Open {
        path: PathBuf,
        source: redb::DatabaseError,
    },
    /// Written by a coordinator with another record layout.
    #[error(
        "job database {path} has record layout {found}; this coordinator reads layout {SCHEMA}"
    )]
    Schema { path: PathBuf, found: u64 },
    /// A read or write failed.
    #[error("job database {path}: {what}")]
    Db {
        path: PathBuf,
        what: &'static str,
        source: Box<redb::Error>,
    },
    /// The thread that writes the store could not be started.
    #[error("job database {path}: no writer thread: {reason}")]
    Writer { path: PathBuf, reason: String },
    /// Closed by a coordinator that is stopping.
    #[error("job database {path} is closed: the coordinator is shutting down")]
    Closed { path: PathBuf },
    /// A record does not decode.
    #[error("job database {path}: the record of job {id:?} is unreadable")]
    Record {
        path: PathBuf,
        id: String,
        source: prost::DecodeError,
    },
    /// A record filed under another job's id.
    #[error("job database {path}: the record under {key:?} is of job {found:?}")]
    Misfiled {
        path: PathBuf,
        key: String,
        found: String,
    },
}

impl StoreError {
    /// The error and its causes on one line, for logs and replies (`Display` alone gives only
    /// the first).
    pub fn with_causes(&self) -> String {
        let mut text = self.to_string();
        let mut source = std::error::Error::source(self);
        while let Some(s) = source {
            text.push_str(": ");
            text.push_str(&s.to_string());
            source = s.source();
        }
        text
    }
}

/// What the store held when the coordinator started.
#[derive(Debug, Default)]
pub struct Loaded {
    /// Every job, in no particular order.
    pub jobs: Vec<StoredJob>,
    /// The highest sequence number handed out.
    pub seq: u64,
}

/// See the module documentation.
pub struct Store {
    /// `None` once closed ([`Store::close`]): the file's lock is released.
    db: Option<redb::Database>,
    path: PathBuf,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("path", &self.path).finish()
    }
}

impl Store {
    /// Opens (or creates) `<data_dir>/rayfarm.redb`. A file that is not a sound redb database
    /// is refused, never replaced.
    pub fn open(data_dir: &Path) -> Result<Store, StoreError> {
        let path = data_dir.join(FILE_NAME);
        // The whole file is checked on open: a damaged file then fails here with an error
        // instead of misbehaving later. The store is small, so the check is cheap.
        // The coordinator reads the whole store once, at start, and then only a finished
        // job's record when its result is fetched: a larger cache would only hold the pages
        // it wrote, and grow the process by as much.
        let db = redb::Builder::new()
            .set_cache_size(CACHE_BYTES)
            .set_check_integrity_on_open(true)
            .create(&path)
            .map_err(|source| match source {
                redb::DatabaseError::DatabaseAlreadyOpen => {
                    StoreError::InUse { path: path.clone() }
                }
                source => StoreError::Open {
                    path: path.clone(),
                    source,
                },
            })?;
        let store = Store { db: Some(db), path };
        store.init()?;
        Ok(store)
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Closes the database and releases its lock, so another coordinator may open the file
    /// at once (a stopping coordinator does this before its last connections close). Later
    /// writes fail with [`StoreError::Closed`].
    pub fn close(&mut self) {
        if self.db.take().is_some() {
            tracing::info!(store = %self.path.display(), "job database closed");
        }
    }

    /// The open database.
    fn db(&self) -> Result<&redb::Database, StoreError> {
        self.db.as_ref().ok_or_else(|| StoreError::Closed {
            path: self.path.clone(),
        })
    }

    fn err(&self, what: &'static str) -> impl Fn(redb::Error) -> StoreError + '_ {
        move |e| StoreError::Db {
            path: self.path.clone(),
            what,
            source: Box::new(e),
        }
    }

    /// Creates the tables of a new file and checks the layout of an old one.
    fn init(&self) -> Result<(), StoreError> {
        let e = self.err("creating the tables");
        let txn = self.db()?.begin_write().map_err(|x| e(x.into()))?;
        {
            let jobs = txn.open_table(JOBS).map_err(|x| e(x.into()))?;
            let mut by_seq = txn.open_table(BY_SEQ).map_err(|x| e(x.into()))?;
            // A store written before the index existed gets it now (a record replaced in
            // place keeps its sequence number, so the counts differ only then).
            if by_seq.len().map_err(|x| e(x.into()))? != jobs.len().map_err(|x| e(x.into()))? {
                by_seq.retain(|_, _| false).map_err(|x| e(x.into()))?;
                for entry in jobs.iter().map_err(|x| e(x.into()))? {
                    let (id, bytes) = entry.map_err(|x| e(x.into()))?;
                    let job = self.decode(id.value(), bytes.value())?;
                    by_seq
                        .insert(job.seq, id.value())
                        .map_err(|x| e(x.into()))?;
                }
            }
            let mut meta = txn.open_table(META).map_err(|x| e(x.into()))?;
            let found = meta
                .get(SCHEMA_KEY)
                .map_err(|x| e(x.into()))?
                .map(|v| v.value());
            match found {
                None => {
                    meta.insert(SCHEMA_KEY, SCHEMA).map_err(|x| e(x.into()))?;
                }
                Some(SCHEMA) => {}
                Some(found) => {
                    return Err(StoreError::Schema {
                        path: self.path.clone(),
                        found,
                    });
                }
            }
        }
        txn.commit().map_err(|x| e(x.into()))
    }

    /// Every stored job, without its statistics (read them with [`get`](Self::get)), and
    /// the highest sequence number.
    pub fn load(&self) -> Result<Loaded, StoreError> {
        let e = self.err("reading the jobs");
        let txn = self.db()?.begin_read().map_err(|x| e(x.into()))?;
        let table = txn.open_table(JOBS).map_err(|x| e(x.into()))?;
        let meta = txn.open_table(META).map_err(|x| e(x.into()))?;
        let mut loaded = Loaded {
            seq: meta
                .get(SEQ_KEY)
                .map_err(|x| e(x.into()))?
                .map_or(0, |v| v.value()),
            ..Loaded::default()
        };
        for entry in table.iter().map_err(|x| e(x.into()))? {
            let (id, bytes) = entry.map_err(|x| e(x.into()))?;
            let mut job = self.decode(id.value(), bytes.value())?;
            if job.id() != id.value() {
                return Err(StoreError::Misfiled {
                    path: self.path.clone(),
                    key: id.value().to_string(),
                    found: job.id().to_string(),
                });
            }
            // The bulk of a finished job's record, and nothing a starting coordinator needs.
            job.stats_json = String::new();
            loaded.seq = loaded.seq.max(job.seq);
            loaded.jobs.push(job);
        }
        Ok(loaded)
    }

    /// At most `size` stored jobs, newest first, from sequence number `from_seq` down; and
    /// the sequence number the next page starts at, if any.
    pub fn page(
        &self,
        size: usize,
        from_seq: u64,
    ) -> Result<(Vec<StoredJob>, Option<u64>), StoreError> {
        let e = self.err("listing jobs");
        let txn = self.db()?.begin_read().map_err(|x| e(x.into()))?;
        let by_seq = txn.open_table(BY_SEQ).map_err(|x| e(x.into()))?;
        let table = txn.open_table(JOBS).map_err(|x| e(x.into()))?;
        let mut ids = by_seq.range(..=from_seq).map_err(|x| e(x.into()))?.rev();
        let mut jobs = Vec::new();
        for entry in ids.by_ref().take(size) {
            let (_, id) = entry.map_err(|x| e(x.into()))?;
            if let Some(bytes) = table.get(id.value()).map_err(|x| e(x.into()))? {
                jobs.push(self.decode(id.value(), bytes.value())?);
            }
        }
        let next = match ids.next() {
            Some(entry) => Some(entry.map_err(|x| e(x.into()))?.0.value()),
            None => None,
        };
        Ok((jobs, next))
    }

    /// The record stored under `id`.
    fn decode(&self, id: &str, bytes: &[u8]) -> Result<StoredJob, StoreError> {
        <StoredJob as prost::Message>::decode(bytes).map_err(|source| StoreError::Record {
            path: self.path.clone(),
            id: id.to_string(),
            source,
        })
    }

    /// Job `id`'s record, if stored.
    pub fn get(&self, id: &str) -> Result<Option<StoredJob>, StoreError> {
        let e = self.err("reading a job");
        let txn = self.db()?.begin_read().map_err(|x| e(x.into()))?;
        let table = txn.open_table(JOBS).map_err(|x| e(x.into()))?;
        let Some(bytes) = table.get(id).map_err(|x| e(x.into()))? else {
            return Ok(None);
        };
        self.decode(id, bytes.value()).map(Some)
    }

    /// Writes `job` (replacing its previous record) and raises the stored sequence number to
    /// its `seq`, in one transaction that is on disk when this returns.
    pub fn put(&self, job: &StoredJob) -> Result<(), StoreError> {
        let e = self.err("writing a job");
        let bytes = prost::Message::encode_to_vec(job);
        let txn = self.db()?.begin_write().map_err(|x| e(x.into()))?;
        {
            let mut table = txn.open_table(JOBS).map_err(|x| e(x.into()))?;
            table
                .insert(job.id(), bytes.as_slice())
                .map_err(|x| e(x.into()))?;
            let mut by_seq = txn.open_table(BY_SEQ).map_err(|x| e(x.into()))?;
            by_seq.insert(job.seq, job.id()).map_err(|x| e(x.into()))?;
            let mut meta = txn.open_table(META).map_err(|x| e(x.into()))?;
            let seq = meta
                .get(SEQ_KEY)
                .map_err(|x| e(x.into()))?
                .map_or(0, |v| v.value());
            if job.seq > seq {
                meta.insert(SEQ_KEY, job.seq).map_err(|x| e(x.into()))?;
            }
        }
        txn.commit().map_err(|x| e(x.into()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::JobState;

    fn job(id: &str, seq: u64, state: JobState) -> StoredJob {
        StoredJob {
            summary: Some(proto::JobSummary {
                job_id: id.into(),
                spec: Some(proto::JobSpec {
                    scene: "nb".into(),
                    width: 96,
                    height: 72,
                    spp: 2,
                    priority: -3,
                    ..Default::default()
                }),
                state: state as i32,
                submitted_unix_ms: 1_700_000_000_000,
                ..Default::default()
            }),
            seq,
            attempts: 0,
            epoch_floor: 0,
            image_hash: String::new(),
            stats_json: String::new(),
        }
    }

    #[test]
    fn jobs_survive_reopening_and_the_last_write_wins() {
        let dir = tempfile::tempdir().unwrap();
        let a = job("job-1", 1, JobState::Queued);
        let mut b = job("job-2", 2, JobState::Running);
        {
            let store = Store::open(dir.path()).unwrap();
            assert!(store.load().unwrap().jobs.is_empty());
            store.put(&a).unwrap();
            store.put(&b).unwrap();
            b.summary.as_mut().unwrap().state = JobState::Succeeded as i32;
            b.attempts = 2;
            b.image_hash = "00ff00ff00ff00ff".into();
            b.stats_json = "{\"wall_seconds\":1.5}".into();
            store.put(&b).unwrap();
        }
        let store = Store::open(dir.path()).unwrap();
        assert_eq!(store.get("job-2").unwrap().as_ref(), Some(&b));
        let mut loaded = store.load().unwrap();
        loaded.jobs.sort_by_key(|j| j.seq);
        // Loaded without the statistics, which only a fetch of the result reads.
        b.stats_json = String::new();
        assert_eq!(loaded.jobs, vec![a, b]);
        assert_eq!(loaded.seq, 2);
    }

    #[test]
    fn jobs_come_in_pages_newest_first_even_from_a_store_written_before_the_index() {
        let dir = tempfile::tempdir().unwrap();
        {
            let store = Store::open(dir.path()).unwrap();
            for seq in 1..=5 {
                store
                    .put(&job(&format!("job-{seq}"), seq, JobState::Queued))
                    .unwrap();
            }
            // Its state changes are written in place: still one entry each.
            store.put(&job("job-2", 2, JobState::Succeeded)).unwrap();
            // As a coordinator of the last version left it: no index.
            let txn = store.db().unwrap().begin_write().unwrap();
            assert!(txn.delete_table(BY_SEQ).unwrap());
            txn.commit().unwrap();
        }
        let store = Store::open(dir.path()).unwrap();
        let ids = |jobs: Vec<StoredJob>| -> Vec<String> {
            jobs.iter().map(|j| j.id().to_string()).collect()
        };
        let (first, next) = store.page(2, u64::MAX).unwrap();
        assert_eq!(
            (ids(first), next),
            (vec!["job-5".into(), "job-4".into()], Some(3))
        );
        let (second, next) = store.page(2, 3).unwrap();
        assert_eq!(
            second[1].summary.as_ref().unwrap().state(),
            JobState::Succeeded
        );
        assert_eq!(
            (ids(second), next),
            (vec!["job-3".into(), "job-2".into()], Some(1))
        );
        let (last, next) = store.page(2, 1).unwrap();
        assert_eq!((ids(last), next), (vec!["job-1".to_string()], None));
    }

    #[test]
    fn a_second_opener_is_told_the_file_is_in_use() {
        let dir = tempfile::tempdir().unwrap();
        let _first = Store::open(dir.path()).unwrap();
        let err = Store::open(dir.path()).unwrap_err();
        assert!(matches!(err, StoreError::InUse { .. }), "{err}");
        assert!(err.to_string().contains(FILE_NAME), "{err}");
    }

    #[test]
    fn a_closed_store_releases_the_file_and_refuses_writes() {
        let dir = tempfile::tempdir().unwrap();
        let mut first = Store::open(dir.path()).unwrap();
        first.put(&job("a", 1, JobState::Queued)).unwrap();
        first.close();
        let err = first.put(&job("b", 2, JobState::Queued)).unwrap_err();
        assert!(matches!(err, StoreError::Closed { .. }), "{err}");
        let second = Store::open(dir.path()).unwrap();
        assert_eq!(second.load().unwrap().jobs.len(), 1);
    }

    #[test]
    fn a_file_that_is_not_a_database_is_refused_and_left_alone() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE_NAME);
        let junk =
            b"these are not the bytes of a redb database, whatever else they are\n".repeat(100);
        std::fs::write(&path, &junk).unwrap();
        let err = Store::open(dir.path()).unwrap_err();
        let text = err.with_causes();
        assert!(matches!(err, StoreError::Open { .. }), "{text}");
        assert!(text.contains("Not a redb database"), "{text}");
        assert!(text.contains(&path.display().to_string()), "{text}");
        assert_eq!(std::fs::read(&path).unwrap(), junk, "the file was changed");
    }

    #[test]
    fn a_damaged_database_is_refused_with_its_name() {
        let dir = tempfile::tempdir().unwrap();
        {
            let store = Store::open(dir.path()).unwrap();
            for i in 1..=50 {
                store
                    .put(&job(&format!("job-{i}"), i, JobState::Queued))
                    .unwrap();
            }
        }
        let path = dir.path().join(FILE_NAME);
        let mut bytes = std::fs::read(&path).unwrap();
        // Past the header and the first pages: the region of the committed tree.
        let len = bytes.len();
        for b in &mut bytes[len / 4..] {
            *b ^= 0x5a;
        }
        std::fs::write(&path, &bytes).unwrap();
        let err = Store::open(dir.path()).unwrap_err();
        let text = err.to_string();
        assert!(text.contains(&path.display().to_string()), "{text}");
        assert_eq!(std::fs::read(&path).unwrap(), bytes, "the file was changed");
    }
}
