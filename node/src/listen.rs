//! Connection handling of every rayfarm server: TCP connections are accepted under caps (in
//! total and per peer address), must complete TLS (when on) and send the HTTP/2 preface
//! within a deadline, and only then are handed to tonic. A connection that then carries no
//! request for [`ConnectionArgs::idle_timeout_ms`] is closed ([`crate::idle`]).
//!
//! Without this, a peer that opens connections and says nothing holds a descriptor each for
//! as long as it likes, and a few hundred of them starve the process of descriptors (the
//! legitimate clients' handshakes then fail). Here a silent connection holds its slot for at
//! most [`ConnectionArgs::handshake_timeout_ms`], and one past a cap is closed at once, so a
//! client at another address keeps being served.

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::server::TlsStream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::Connected;
use tracing::{debug, warn};

use crate::identity::PeerIdentity;
use crate::idle::Activity;

/// What every HTTP/2 client sends first (RFC 9113, section 3.4).
const PREFACE: &[u8; 24] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

/// Descriptors kept free of connections for the process's own files, database and outgoing
/// links, when the connection cap is derived from the descriptor limit.
const RESERVED_DESCRIPTORS: usize = 64;

/// Limits of a server's connections (flattened into the servers' command lines).
#[derive(clap::Args, Clone, Debug)]
pub struct ConnectionArgs {
    /// Most connections served at once; more are closed when accepted. Never more than the
    /// descriptor limit (ulimit -n) leaves room for, less a reserve of 64.
    #[arg(long, env = "RAYFARM_MAX_CONNECTIONS", default_value_t = 1024)]
    pub max_connections: usize,
    /// Most connections from one IP address at once; more are closed when accepted.
    #[arg(long, env = "RAYFARM_MAX_CONNECTIONS_PER_PEER", default_value_t = 64)]
    pub max_connections_per_peer: usize,
    /// A connection that has not completed TLS and sent the HTTP/2 preface within this many
    /// milliseconds is closed.
    #[arg(long, env = "RAYFARM_HANDSHAKE_TIMEOUT_MS", default_value_t = 10_000)]
    pub handshake_timeout_ms: u64,
    /// A connection past its handshake that carries no request (no stream open) for this
    /// many milliseconds is closed; clients reconnect on their next call.
    #[arg(long, env = "RAYFARM_IDLE_TIMEOUT_MS", default_value_t = 60_000)]
    pub idle_timeout_ms: u64,
}

impl Default for ConnectionArgs {
    fn default() -> Self {
        ConnectionArgs {
            max_connections: 1024,
            max_connections_per_peer: 64,
            handshake_timeout_ms: 10_000,
            idle_timeout_ms: 60_000,
        }
    }
}

impl ConnectionArgs {
    /// The total cap this process can honour: the configured one, or fewer when the
    /// descriptor limit would run out first.
    pub fn effective_max_connections(&self) -> usize {
        let wanted = self.max_connections.max(1);
        match descriptor_limit() {
            Some(limit) => wanted.min(limit.saturating_sub(RESERVED_DESCRIPTORS).max(1)),
            None => wanted,
        }
    }
}

/// The soft limit on open descriptors (`RLIMIT_NOFILE`), if it is finite.
fn descriptor_limit() -> Option<usize> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes into the struct it is given and reads nothing else.
    let ok = unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0;
    (ok && limit.rlim_cur != libc::RLIM_INFINITY).then_some(limit.rlim_cur as usize)
}

/// Connection counts, in total and per peer address.
struct Slots {
    max_total: usize,
    max_per_peer: usize,
    held: Mutex<(usize, HashMap<IpAddr, usize>)>,
    refused: AtomicU64,
}

impl Slots {
    /// A slot for a connection from `ip`, or `None` when a cap is reached.
    fn take(self: &Arc<Self>, ip: IpAddr) -> Option<Slot> {
        let mut held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        let (total, per_peer) = &mut *held;
        let of_peer = per_peer.get(&ip).copied().unwrap_or(0);
        if *total >= self.max_total || of_peer >= self.max_per_peer {
            return None;
        }
        *total += 1;
        per_peer.insert(ip, of_peer + 1);
        Some(Slot {
            slots: self.clone(),
            ip,
        })
    }
}

/// One held connection; released when dropped (the connection closed).
struct Slot {
    slots: Arc<Slots>,
    ip: IpAddr,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut held = self.slots.held.lock().unwrap_or_else(|p| p.into_inner());
        let (total, per_peer) = &mut *held;
        *total = total.saturating_sub(1);
        if let Some(n) = per_peer.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                per_peer.remove(&self.ip);
            }
        }
    }
}

/// The connections of `listener` that complete their handshake (TLS with `tls`, then the
/// HTTP/2 preface) within the limits, for `Server::serve_with_incoming`. Accepting and the
/// handshakes run on their own tasks, which end when the stream is dropped.
pub fn incoming(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    limits: &ConnectionArgs,
) -> ReceiverStream<Result<Conn, io::Error>> {
    incoming_of(listener, tls, limits, true)
}

/// [`incoming`] for HTTP/1.1 ([`crate::http`]): the same caps and TLS deadline, no preface.
pub fn incoming_http1(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    limits: &ConnectionArgs,
) -> ReceiverStream<Result<Conn, io::Error>> {
    incoming_of(listener, tls, limits, false)
}

fn incoming_of(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    limits: &ConnectionArgs,
    h2: bool,
) -> ReceiverStream<Result<Conn, io::Error>> {
    let slots = Arc::new(Slots {
        max_total: limits.effective_max_connections(),
        max_per_peer: limits.max_connections_per_peer.max(1),
        held: Mutex::new((0, HashMap::new())),
        refused: AtomicU64::new(0),
    });
    let deadline = Duration::from_millis(limits.handshake_timeout_ms.max(1));
    let idle = Duration::from_millis(limits.idle_timeout_ms.max(1));
    let (tx, rx) = mpsc::channel(16);
    tokio::spawn(accept_loop(listener, tls, slots, deadline, h2, idle, tx));
    ReceiverStream::new(rx)
}

async fn accept_loop(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    slots: Arc<Slots>,
    deadline: Duration,
    h2: bool,
    idle: Duration,
    tx: mpsc::Sender<Result<Conn, io::Error>>,
) {
    loop {
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of descriptors (or a connection reset before accept): pause rather
                    // than spin; connections already held end by their deadline.
                    warn!(error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = tx.closed() => return,
        };
        let Some(slot) = slots.take(peer.ip()) else {
            let refused = slots.refused.fetch_add(1, Ordering::Relaxed) + 1;
            // Every refusal at debug; a flood shows at warn without flooding the log.
            if refused.is_power_of_two() {
                warn!(%peer, refused, "connection refused: connection cap reached");
            } else {
                debug!(%peer, "connection refused: connection cap reached");
            }
            drop(stream);
            continue;
        };
        let _ = stream.set_nodelay(true);
        let tls = tls.clone();
        let tx = tx.clone();
        tokio::spawn(async move {
            match tokio::time::timeout(deadline, handshake(stream, tls, h2)).await {
                Ok(Ok(io)) => {
                    let activity = Activity::new();
                    let info = ConnInfo {
                        remote: Some(peer),
                        peer: io.peer_identity().map(Arc::new),
                        activity: Some(activity.clone()),
                    };
                    let conn = Conn {
                        io,
                        // Without a preface read there is nothing to replay.
                        replayed: if h2 { 0 } else { PREFACE.len() },
                        info,
                        activity,
                        idle,
                        idle_check: Box::pin(tokio::time::sleep(idle)),
                        peer,
                        _slot: slot,
                    };
                    let _ = tx.send(Ok(conn)).await;
                }
                Ok(Err(e)) => debug!(%peer, error = %e, "connection closed in its handshake"),
                Err(_) => debug!(%peer, ?deadline, "connection closed: no handshake in time"),
            }
        });
    }
}

/// TLS (if on), then (with `h2`) the HTTP/2 preface, which [`Conn`] replays to the server.
async fn handshake(stream: TcpStream, tls: Option<TlsAcceptor>, h2: bool) -> io::Result<Io> {
    let mut io = match tls {
        Some(acceptor) => match acceptor.accept(stream).into_fallible().await {
            Ok(tls) => Io::Tls(Box::new(tls)),
            Err((e, mut stream)) => {
                // Read what the client sent before closing: closing with unread data makes
                // the kernel reset the connection, and a client (a plain-text one, say) may
                // then die of SIGPIPE on its next write instead of reading the refusal.
                let mut sink = [0u8; 4096];
                let drain =
                    async { while matches!(stream.read(&mut sink).await, Ok(n) if n > 0) {} };
                let _ = tokio::time::timeout(Duration::from_millis(200), drain).await;
                return Err(e);
            }
        },
        None => Io::Plain(stream),
    };
    if !h2 {
        return Ok(io);
    }
    let mut preface = [0u8; PREFACE.len()];
    io.read_exact(&mut preface).await?;
    if &preface != PREFACE {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            "not an HTTP/2 connection (no client preface)",
        ));
    }
    Ok(io)
}

/// A connection's transport.
enum Io {
    Plain(TcpStream),
    Tls(Box<TlsStream<TcpStream>>),
}

impl Io {
    /// The names of the client's certificate, when it presented one (mutual TLS: verified
    /// against the client CA in the handshake).
    fn peer_identity(&self) -> Option<PeerIdentity> {
        let Io::Tls(tls) = self else { return None };
        let certs = tls.get_ref().1.peer_certificates()?;
        PeerIdentity::from_der(certs.first()?)
    }
}

/// What handlers can learn of a connection (in each request's extensions): the client's
/// address and, under mutual TLS, its certificate's names ([`crate::identity::of_request`]).
#[derive(Clone, Debug)]
pub struct ConnInfo {
    /// The client's address.
    pub remote: Option<SocketAddr>,
    /// The names of the client's verified certificate.
    pub peer: Option<Arc<PeerIdentity>>,
    /// The requests open on the connection ([`crate::idle`]).
    pub activity: Option<Arc<Activity>>,
}

/// The address of the client that sent `request` (tonic's `remote_addr` knows only its own
/// connection types).
pub fn remote_addr<T>(request: &tonic::Request<T>) -> Option<SocketAddr> {
    request
        .extensions()
        .get::<ConnInfo>()
        .and_then(|info| info.remote)
}

/// An accepted connection past its handshake: it replays the HTTP/2 preface read by the
/// handshake, then reads on, and holds its slot under the caps until dropped. Once it has
/// carried no request for its idle timeout, its reads end (the server then closes it).
pub struct Conn {
    io: Io,
    /// Bytes of [`PREFACE`] already given back to the reader.
    replayed: usize,
    info: ConnInfo,
    activity: Arc<Activity>,
    idle: Duration,
    /// When to look again whether the connection has been idle too long.
    idle_check: Pin<Box<tokio::time::Sleep>>,
    peer: SocketAddr,
    _slot: Slot,
}

impl Conn {
    /// Whether the connection has carried no request for its idle timeout; otherwise arms
    /// the check for the earliest time it could have (waking `cx` then).
    fn idle_past_timeout(&mut self, cx: &mut Context<'_>) -> bool {
        while self.idle_check.as_mut().poll(cx).is_ready() {
            let wait = match self.activity.idle_for() {
                Some(idle) if idle >= self.idle => return true,
                Some(idle) => self.idle - idle,
                None => self.idle,
            };
            let at = tokio::time::Instant::now() + wait;
            self.idle_check.as_mut().reset(at);
        }
        false
    }
}

impl Connected for Conn {
    type ConnectInfo = ConnInfo;

    fn connect_info(&self) -> ConnInfo {
        self.info.clone()
    }
}

impl AsyncRead for Io {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Io::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for Io {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Io::Plain(s) => Pin::new(s).poll_write(cx, buf),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Io::Plain(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            Io::Plain(s) => s.is_write_vectored(),
            Io::Tls(s) => s.is_write_vectored(),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Io::Plain(s) => Pin::new(s).poll_flush(cx),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Io::Plain(s) => Pin::new(s).poll_shutdown(cx),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}

impl AsyncRead for Conn {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        if this.replayed < PREFACE.len() {
            let rest = &PREFACE[this.replayed..];
            let n = rest.len().min(buf.remaining());
            buf.put_slice(&rest[..n]);
            this.replayed += n;
            return Poll::Ready(Ok(()));
        }
        match Pin::new(&mut this.io).poll_read(cx, buf) {
            Poll::Pending if this.idle_past_timeout(cx) => {
                debug!(peer = %this.peer, idle = ?this.idle, "connection closed: idle");
                // End of stream: the server closes the connection.
                Poll::Ready(Ok(()))
            }
            other => other,
        }
    }
}

impl AsyncWrite for Conn {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::Ipv4Addr;

    #[test]
    fn caps_hold_in_total_and_per_peer_and_free_on_drop() {
        let slots = Arc::new(Slots {
            max_total: 3,
            max_per_peer: 2,
            held: Mutex::new((0, HashMap::new())),
            refused: AtomicU64::new(0),
        });
        let a = IpAddr::V4(Ipv4Addr::new(127, 0, 0, 2));
        let b = IpAddr::V4(Ipv4Addr::LOCALHOST);
        let a1 = slots.take(a).unwrap();
        let _a2 = slots.take(a).unwrap();
        assert!(slots.take(a).is_none(), "per-peer cap");
        let _b1 = slots.take(b).unwrap();
        assert!(slots.take(b).is_none(), "total cap");
        drop(a1);
        assert!(
            slots.take(b).is_some(),
            "a closed connection frees its slot"
        );
    }

    #[test]
    fn the_cap_fits_the_descriptor_limit() {
        let args = ConnectionArgs {
            max_connections: usize::MAX,
            ..ConnectionArgs::default()
        };
        if let Some(limit) = descriptor_limit() {
            assert!(args.effective_max_connections() <= limit);
        }
    }
}
