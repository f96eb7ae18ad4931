//! Plain HTTP/1.1 requests to a process's HTTP listener (dashboard, metrics, health), by hand so
//! the tests depend on no HTTP client.

use crate::process::START_TIMEOUT;

/// A plain HTTP/1.1 request to `addr` (host:port): the status code and the body. Panics if
/// the server cannot be reached or does not answer within `START_TIMEOUT`.
pub fn http_request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> (u16, String) {
    try_http_request(addr, method, path, headers, body)
        .unwrap_or_else(|e| panic!("{method} {path} from {addr}: {e}"))
}

/// [`http_request`], with an error for a server that cannot be reached or answers badly.
pub fn try_http_request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> Result<(u16, String), String> {
    use std::io::Write;
    let mut stream = std::net::TcpStream::connect(addr).map_err(|e| format!("connect: {e}"))?;
    stream
        .set_read_timeout(Some(START_TIMEOUT))
        .map_err(|e| e.to_string())?;
    let mut request = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    for (k, v) in headers {
        request.push_str(&format!("{k}: {v}\r\n"));
    }
    request.push_str("\r\n");
    request.push_str(body);
    stream
        .write_all(request.as_bytes())
        .map_err(|e| format!("send: {e}"))?;
    read_answer(stream)
}

/// An HTTP/1.1 answer's status and body: the body read to its Content-Length when the answer
/// gives one (some servers, chromedriver among them, keep the connection open whatever the
/// request asks), else to the end of the stream.
fn read_answer(stream: std::net::TcpStream) -> Result<(u16, String), String> {
    use std::io::{BufRead, Read};
    let mut reader = std::io::BufReader::new(stream);
    let mut status_line = String::new();
    reader
        .read_line(&mut status_line)
        .map_err(|e| format!("read: {e}"))?;
    let status = status_line
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| format!("no status in {status_line:?}"))?;
    let mut length = None;
    loop {
        let mut line = String::new();
        let read = reader
            .read_line(&mut line)
            .map_err(|e| format!("read: {e}"))?;
        let line = line.trim_end();
        if read == 0 || line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':')
            && k.eq_ignore_ascii_case("content-length")
        {
            length = Some(v.trim().parse().map_err(|_| format!("bad length {v:?}"))?);
        }
    }
    let mut body = Vec::new();
    match length {
        Some(n) => {
            body.resize(n, 0);
            reader
                .read_exact(&mut body)
                .map_err(|e| format!("read body: {e}"))?;
        }
        None => {
            reader
                .read_to_end(&mut body)
                .map_err(|e| format!("read body: {e}"))?;
        }
    }
    Ok((status, String::from_utf8_lossy(&body).into_owned()))
}

/// `GET path` from `addr`; panics unless the answer is 200.
pub fn http_get(addr: &str, path: &str) -> String {
    let (status, body) = http_request(addr, "GET", path, &[], "");
    assert_eq!(status, 200, "GET {path} from {addr}: {body}");
    body
}
