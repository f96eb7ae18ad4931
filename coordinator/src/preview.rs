//! Previews of a job's frame: a PNG of the film with the tiles committed so far, made on
//! demand (`FetchPreview`, the dashboard), at most once per state of the film, on a blocking
//! thread, never under the state lock.
//!
//! [`Previews`] is the one source: whatever adds to the film (a tile committed, of a one-pass
//! frame or of a progressive subframe) calls [`Previews::advance`], which raises the sequence
//! number, and the next fetch encodes the film as it is then, each tile averaged over the
//! samples the film holds of it (`Film::preview_png`). The sequence number only grows,
//! across subframes and a frame's restarts too (a restarted frame's previews start where the
//! last one stopped); so does the number of whole subframes in the preview.

use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use rayfarm_core::render::Film;
use rayfarm_core::render::film::encode::Preview;
use tonic::Status;

/// Longest side of a preview in pixels: larger frames are shrunk by a whole factor, so a
/// preview of a 16384-pixel frame is 1024 pixels across (a few MiB at most).
pub const MAX_SIDE: u32 = 1024;

/// Share of the time a job's previews may spend encoding: a preview of a 1024x1024 film
/// takes about 45 ms here, so a page asking once a second would cost 4.5% of a core; past
/// the allowance below, the newest preview is served until encoding is back under this share
/// of the time since (a new one at most every 2.3 s at 1024x1024, as often as asked for small
/// frames).
const ENCODING_SHARE: f64 = 0.02;

/// Encoding time a job's previews may spend at once before [`ENCODING_SHARE`] holds them
/// back: the first previews of any frame, and every preview of small ones, are made at once.
const ENCODING_ALLOWANCE: Duration = Duration::from_millis(250);

/// An encoded preview and the film state it shows.
#[derive(Debug)]
pub struct Encoded {
    pub sequence: u64,
    /// Subframes wholly in it.
    pub subframe: u32,
    pub preview: Preview,
}

/// The previews of one job (see the module documentation).
pub struct Previews {
    inner: Mutex<Inner>,
    /// One encode at a time per job: fetches that arrive meanwhile wait and take its result.
    encoding: tokio::sync::Mutex<()>,
}

/// See [`Previews::source`].
enum Source {
    Ready(Arc<Encoded>),
    Encode(Arc<Film>, u64, u32),
    Gone,
}

struct Inner {
    /// The running frame's film; gone once the frame is dropped (its file goes with it).
    film: Weak<Film>,
    sequence: u64,
    /// Subframes wholly committed to the film.
    subframe: u32,
    latest: Option<Arc<Encoded>>,
    /// Encoding time still allowed, in seconds, as of `allowed_at` (see [`ENCODING_SHARE`]).
    allowed: f64,
    allowed_at: Instant,
}

impl Inner {
    /// Whether a new encode may start now: the allowance, grown by the share of the time
    /// since it was last spent, is not used up.
    fn may_encode(&mut self, now: Instant) -> bool {
        let grown = now.duration_since(self.allowed_at).as_secs_f64() * ENCODING_SHARE;
        self.allowed = (self.allowed + grown).min(ENCODING_ALLOWANCE.as_secs_f64());
        self.allowed_at = now;
        self.allowed > 0.0
    }
}

impl Previews {
    /// Previews of a frame's `film`, numbered on from `floor` (the sequence number the job's
    /// previous frame reached, 0 for its first).
    pub fn new(film: &Arc<Film>, floor: u64) -> Self {
        Previews {
            inner: Mutex::new(Inner {
                film: Arc::downgrade(film),
                sequence: floor,
                subframe: 0,
                latest: None,
                allowed: ENCODING_ALLOWANCE.as_secs_f64(),
                allowed_at: Instant::now(),
            }),
            encoding: tokio::sync::Mutex::new(()),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// `tiles` more tile commits are in the film, and `subframes` subframes wholly: the
    /// next preview shows them.
    pub fn advance(&self, tiles: usize, subframes: u32) {
        let mut inner = self.lock();
        inner.sequence += tiles as u64;
        inner.subframe = inner.subframe.max(subframes);
    }

    /// The sequence number of the newest film state (what [`latest`](Self::latest) shows,
    /// unless encoding is being held back: see [`ENCODING_SHARE`]).
    pub fn sequence(&self) -> u64 {
        self.lock().sequence
    }

    /// What the next preview is made of, or the newest one if it is already made (or the
    /// film is gone, so none newer can be, or `held_back` and encoding has used up its share
    /// of the time).
    fn source(&self, held_back: bool) -> Source {
        let mut inner = self.lock();
        if let Some(latest) = &inner.latest
            && latest.sequence == inner.sequence
        {
            return Source::Ready(latest.clone());
        }
        if held_back
            && let Some(latest) = inner.latest.clone()
            && !inner.may_encode(Instant::now())
        {
            return Source::Ready(latest);
        }
        match (inner.film.upgrade(), &inner.latest) {
            (Some(film), _) => Source::Encode(film, inner.sequence, inner.subframe),
            (None, Some(latest)) => Source::Ready(latest.clone()),
            (None, None) => Source::Gone,
        }
    }

    fn keep(&self, encoded: Encoded) -> Arc<Encoded> {
        let mut inner = self.lock();
        let encoded = Arc::new(encoded);
        if inner
            .latest
            .as_ref()
            .is_none_or(|l| l.sequence < encoded.sequence)
        {
            inner.latest = Some(encoded.clone());
        }
        encoded
    }

    /// The newest preview, encoded now on a blocking thread if the film changed since the
    /// last one (unless encoding has used up its share of the time: then the last one).
    pub async fn latest(&self) -> Result<Arc<Encoded>, Status> {
        let _one = self.encoding.lock().await;
        let (film, sequence, subframe) = match self.source(true) {
            Source::Ready(ready) => return Ok(ready),
            Source::Encode(film, sequence, subframe) => (film, sequence, subframe),
            Source::Gone => {
                return Err(Status::failed_precondition(
                    "the frame ended before a preview of it was made",
                ));
            }
        };
        let started = Instant::now();
        let preview = tokio::task::spawn_blocking(move || film.preview_png(MAX_SIDE))
            .await
            .map_err(|e| Status::internal(format!("encoding the preview failed: {e}")))?
            .map_err(|e| Status::internal(format!("encoding the preview failed: {e}")))?;
        self.lock().allowed -= started.elapsed().as_secs_f64();
        Ok(self.keep(Encoded {
            sequence,
            subframe,
            preview,
        }))
    }

    /// The frame is complete and its film about to go: encodes the final preview now, on
    /// the calling (blocking) thread, so it outlives the film.
    pub fn seal(&self) {
        // Never held back: the final preview is the frame's result.
        let Source::Encode(film, sequence, subframe) = self.source(false) else {
            return;
        };
        match film.preview_png(MAX_SIDE) {
            Ok(preview) => {
                self.keep(Encoded {
                    sequence,
                    subframe,
                    preview,
                });
            }
            Err(e) => tracing::warn!(error = %e, "the final preview could not be encoded"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayfarm_core::tile::TileGrid;

    #[tokio::test]
    async fn one_preview_per_film_state_and_the_numbers_only_grow() {
        let dir = tempfile::tempdir().unwrap();
        let grid = TileGrid::new(20, 10, 8).unwrap();
        let film = Arc::new(Film::temporary_in(dir.path(), grid, 1).unwrap());
        let previews = Previews::new(&film, 5);
        let first = previews.latest().await.unwrap();
        assert_eq!(first.sequence, 5);
        // Nothing new: the same encoding, not a second one.
        assert!(Arc::ptr_eq(&first, &previews.latest().await.unwrap()));
        film.write_tile(0, &[[1 << 24; 3]; 64]).unwrap();
        previews.advance(1, 0);
        let second = previews.latest().await.unwrap();
        assert_eq!((second.sequence, second.subframe), (6, 0));
        assert_ne!(second.preview.png, first.preview.png);
        // The film goes: the newest preview stays.
        previews.advance(2, 1);
        previews.seal();
        drop(film);
        let last = previews.latest().await.unwrap();
        assert_eq!((last.sequence, last.subframe), (8, 1));
        assert!(Arc::ptr_eq(&last, &previews.latest().await.unwrap()));
    }

    #[tokio::test]
    async fn encoding_past_its_share_of_the_time_serves_the_last_preview_but_never_the_final() {
        let dir = tempfile::tempdir().unwrap();
        let grid = TileGrid::new(20, 10, 8).unwrap();
        let film = Arc::new(Film::temporary_in(dir.path(), grid, 1).unwrap());
        let previews = Previews::new(&film, 0);
        let first = previews.latest().await.unwrap();
        // As if the encodes so far had taken the whole allowance and more.
        previews.lock().allowed = -1.0;
        film.write_tile(0, &[[1 << 24; 3]; 64]).unwrap();
        previews.advance(1, 0);
        assert_eq!(previews.sequence(), 1);
        assert!(Arc::ptr_eq(&first, &previews.latest().await.unwrap()));
        // Time gives the allowance back at the share's rate: 1 s of encoding after 50 s.
        previews.lock().allowed_at -= Duration::from_secs_f64(1.01 / ENCODING_SHARE);
        assert_eq!(previews.latest().await.unwrap().sequence, 1);
        // Held back again, but the frame's end is encoded whatever the time spent.
        previews.lock().allowed = -1.0;
        previews.advance(2, 1);
        previews.seal();
        drop(film);
        let last = previews.latest().await.unwrap();
        assert_eq!((last.sequence, last.subframe), (3, 1));
    }
}
