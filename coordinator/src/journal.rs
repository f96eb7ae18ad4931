//! The job store's writer: the state hands it job records under its lock, in the order the
//! changes happened, and one thread writes them (a redb commit, with its fsync) outside that
//! lock, so no request waits on the disk for another's change. Whoever needs a record on disk
//! before going on (a job the client is told about, a frame's start before any worker hears
//! of it) is told when it is written.

use std::path::PathBuf;
use std::sync::{Arc, Mutex, mpsc};
use std::thread::JoinHandle;

use tracing::error;

use crate::store::{Store, StoredJob};

/// What to do once a record is written: `Ok` or why it was not.
pub type Then = Box<dyn FnOnce(Result<(), String>) + Send>;

enum Op {
    Put(Box<StoredJob>, Option<Then>),
    /// Closes the store (after every record before it) and says so.
    Close(mpsc::Sender<()>),
}

/// See the module documentation.
pub struct Journal {
    tx: Option<mpsc::Sender<Op>>,
    path: PathBuf,
    /// The store, shared with the writer thread (see `Drop`); `None` once closed.
    store: Arc<Mutex<Option<Store>>>,
    thread: Option<JoinHandle<()>>,
}

impl Journal {
    /// Starts the writer thread over `store`.
    pub fn start(store: Store) -> std::io::Result<Journal> {
        let path = store.path().to_path_buf();
        let store = Arc::new(Mutex::new(Some(store)));
        let (tx, rx) = mpsc::channel();
        let shared = store.clone();
        let thread = std::thread::Builder::new()
            .name("job-store".into())
            .spawn(move || write_all(&shared, rx))?;
        Ok(Journal {
            tx: Some(tx),
            path,
            store,
            thread: Some(thread),
        })
    }

    /// The database file.
    pub fn path(&self) -> &std::path::Path {
        &self.path
    }

    /// Writes `job` after every record handed over before; a failure is logged (the change is
    /// lost only if the coordinator restarts before the next write of this job).
    pub fn put(&self, job: StoredJob) {
        self.send(Op::Put(Box::new(job), None));
    }

    /// [`put`](Self::put), then calls `then` on the writer thread with the outcome. `then`
    /// must not wait for anything that waits for the journal.
    pub fn put_then(&self, job: StoredJob, then: Then) {
        self.send(Op::Put(Box::new(job), Some(then)));
    }

    /// A handle that reads records from the store (waiting, at most, for the record being
    /// written): for callers outside the coordinator's state lock.
    pub fn reader(&self) -> Reader {
        Reader {
            store: self.store.clone(),
        }
    }

    /// Closes the store once every record handed over so far is written; the receiver hears
    /// when it is closed. Later records are not written.
    pub fn close(&self) -> mpsc::Receiver<()> {
        let (done, closed) = mpsc::channel();
        self.send(Op::Close(done));
        closed
    }

    fn send(&self, op: Op) {
        let sent = self.tx.as_ref().is_some_and(|tx| tx.send(op).is_ok());
        if !sent {
            error!(store = %self.path.display(), "the job store's writer is gone: record not saved");
        }
    }
}

// Dropped with the coordinator: the records handed over are written and the store is closed
// before the drop returns, so the next opener of the file finds it free. A `then` on the
// writer thread may hold the coordinator's last reference: that thread cannot wait for
// itself, so it closes the store at once (whoever handed over a record still queued holds a
// reference too, so none is).
impl Drop for Journal {
    fn drop(&mut self) {
        drop(self.tx.take());
        if let Some(thread) = self.thread.take() {
            if thread.thread().id() == std::thread::current().id() {
                drop(lock(&self.store).take());
            } else {
                let _ = thread.join();
            }
        }
    }
}

/// Reads the journal's store; see [`Journal::reader`].
#[derive(Clone)]
pub struct Reader {
    store: Arc<Mutex<Option<Store>>>,
}

impl Reader {
    /// Job `id`'s stored record; an error says why it could not be read (the store closed,
    /// or damaged).
    pub fn get(&self, id: &str) -> Result<Option<StoredJob>, String> {
        match lock(&self.store).as_ref() {
            Some(store) => store.get(id).map_err(|e| e.with_causes()),
            None => Err("the job store is closed".into()),
        }
    }

    /// A page of the stored jobs (see [`Store::page`]); an error says why it could not be
    /// read.
    pub fn page(
        &self,
        size: usize,
        from_seq: u64,
    ) -> Result<(Vec<StoredJob>, Option<u64>), String> {
        match lock(&self.store).as_ref() {
            Some(store) => store.page(size, from_seq).map_err(|e| e.with_causes()),
            None => Err("the job store is closed".into()),
        }
    }
}

fn lock(store: &Mutex<Option<Store>>) -> std::sync::MutexGuard<'_, Option<Store>> {
    // A write that panicked leaves the store as redb left it: still usable.
    store.lock().unwrap_or_else(|p| p.into_inner())
}

fn write_all(store: &Mutex<Option<Store>>, rx: mpsc::Receiver<Op>) {
    for op in rx {
        match op {
            Op::Put(job, then) => {
                let id = job.summary.as_ref().map(|s| s.job_id.clone());
                let written = match lock(store).as_ref() {
                    Some(store) => store.put(&job).map_err(|e| e.with_causes()),
                    None => Err("the job database is closed".to_string()),
                };
                if let Err(e) = &written {
                    error!(job = id.as_deref().unwrap_or(""), error = %e, "job state not saved");
                }
                if let Some(then) = then {
                    then(written);
                }
            }
            Op::Close(done) => {
                if let Some(store) = lock(store).as_mut() {
                    store.close();
                }
                let _ = done.send(());
            }
        }
    }
}
