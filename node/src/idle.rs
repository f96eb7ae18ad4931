//! Connections that carry no request are closed. A client that completes its handshake and
//! the HTTP/2 preface and then opens no stream would otherwise hold a descriptor (and a
//! connection slot) for as long as it answers the server's pings.
//!
//! Each accepted connection has an [`Activity`]: the requests open on it and when the last
//! one ended. [`ActivityLayer`] counts every request on the connection it came in on, from
//! its arrival to the end of its response body, so a streaming RPC counts for as long as it
//! runs; the connection's reads ([`crate::listen::Conn`]) end it once nothing has been open
//! for the idle timeout. rayfarm's own long-lived links (a worker's control stream, peer
//! bundle streams) are streams, so they are never idle while they last.

use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body::{Body, Frame, SizeHint};

use crate::listen::ConnInfo;

/// The requests open on one connection (see the module documentation).
#[derive(Debug)]
pub struct Activity {
    /// Requests open, and when the count last fell to zero (or the connection began).
    state: Mutex<(usize, Instant)>,
}

impl Activity {
    /// A connection that has carried nothing yet.
    pub fn new() -> Arc<Self> {
        Arc::new(Activity {
            state: Mutex::new((0, Instant::now())),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (usize, Instant)> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A request begins; it is open until the guard is dropped.
    pub fn begin(self: &Arc<Self>) -> Open {
        self.lock().0 += 1;
        Open(self.clone())
    }

    /// How long the connection has carried no request, or `None` while one is open.
    pub fn idle_for(&self) -> Option<Duration> {
        let (open, since) = *self.lock();
        (open == 0).then(|| since.elapsed())
    }
}

/// One open request of a connection (see [`Activity::begin`]).
#[derive(Debug)]
pub struct Open(Arc<Activity>);

impl Drop for Open {
    fn drop(&mut self) {
        let mut state = self.0.lock();
        state.0 = state.0.saturating_sub(1);
        if state.0 == 0 {
            state.1 = Instant::now();
        }
    }
}

/// Counts each request on its connection's [`Activity`] (a `tower` layer for the servers).
#[derive(Clone, Copy, Debug, Default)]
pub struct ActivityLayer;

impl<S> tower::Layer<S> for ActivityLayer {
    type Service = Counted<S>;

    fn layer(&self, inner: S) -> Counted<S> {
        Counted(inner)
    }
}

/// A service whose requests are counted (see [`ActivityLayer`]).
#[derive(Clone, Debug)]
pub struct Counted<S>(S);

type BoxError = Box<dyn std::error::Error + Send + Sync>;

impl<S, ReqBody, ResBody> tower::Service<http::Request<ReqBody>> for Counted<S>
where
    S: tower::Service<http::Request<ReqBody>, Response = http::Response<ResBody>>,
    S::Future: Send + 'static,
    ResBody: Body<Data = Bytes> + Send + 'static,
    ResBody::Error: Into<BoxError>,
{
    type Response = http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<ReqBody>) -> Self::Future {
        let open = request
            .extensions()
            .get::<ConnInfo>()
            .and_then(|info| info.activity.as_ref())
            .map(Activity::begin);
        let response = self.0.call(request);
        Box::pin(async move {
            let response = response.await?;
            Ok(response.map(|body| {
                tonic::body::Body::new(Tracked {
                    inner: Box::pin(body),
                    _open: open,
                })
            }))
        })
    }
}

/// A response body that keeps its request open until it is dropped.
struct Tracked<B> {
    inner: Pin<Box<B>>,
    _open: Option<Open>,
}

impl<B: Body> Body for Tracked<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        self.inner.as_mut().poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_connection_is_idle_only_while_no_request_is_open() {
        let a = Activity::new();
        assert!(a.idle_for().is_some());
        let first = a.begin();
        let second = a.begin();
        assert_eq!(a.idle_for(), None);
        drop(first);
        assert_eq!(a.idle_for(), None, "one still open");
        drop(second);
        assert!(a.idle_for().expect("idle") < Duration::from_secs(5));
    }
}
