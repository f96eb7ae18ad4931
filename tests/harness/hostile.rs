//! A hostile client's tools for the attack tests (`hostile_*.rs`): connections from another
//! loopback address than the legitimate client's, and raw HTTP/2 frames written by hand, so a
//! test can do what no well-behaved gRPC client would (leave streams unfinished, never read).

use tokio::net::{TcpSocket, TcpStream};

/// Where the hostile connections come from: another loopback address than the legitimate
/// client's 127.0.0.1, as an attacker on another machine would.
pub const HOSTILE_IP: [u8; 4] = [127, 0, 0, 2];

/// A runtime for a test's async clients, two threads like the machine.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// A connection from [`HOSTILE_IP`] to `addr`.
pub async fn hostile_connect(addr: &str) -> std::io::Result<TcpStream> {
    let socket = TcpSocket::new_v4()?;
    socket.bind((std::net::Ipv4Addr::from(HOSTILE_IP), 0).into())?;
    socket.connect(addr.parse().unwrap()).await
}

/// The HPACK encoding of one header as a literal with a literal name (RFC 7541, 6.2.2).
pub fn hpack_literal(out: &mut Vec<u8>, name: &str, value: &str) {
    assert!(name.len() < 127 && value.len() < 127);
    out.push(0x00);
    out.push(name.len() as u8);
    out.extend_from_slice(name.as_bytes());
    out.push(value.len() as u8);
    out.extend_from_slice(value.as_bytes());
}

/// Appends an HTTP/2 frame (its 9-byte header, then `payload`) to `out`.
pub fn frame(out: &mut Vec<u8>, kind: u8, flags: u8, stream: u32, payload: &[u8]) {
    let len = payload.len() as u32;
    out.extend_from_slice(&len.to_be_bytes()[1..]);
    out.push(kind);
    out.push(flags);
    out.extend_from_slice(&stream.to_be_bytes());
    out.extend_from_slice(payload);
}

/// The HTTP/2 connection preface (RFC 9113, 3.4).
pub const PREFACE_BYTES: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";
