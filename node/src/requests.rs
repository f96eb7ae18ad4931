//! The checks a server runs on a request's fields before any work, shared by the servers and
//! the fuzz targets that drive them with hostile input (`fuzz/`), so what fuzzing exercises
//! is the code that serves.

use tonic::Status;

use crate::bounds::check_field;
use crate::proto::{self, PROTOCOL_VERSION};

/// Jobs in a page of ListJobs when the client names no size.
pub const DEFAULT_PAGE: usize = 100;
/// The most jobs a page of ListJobs holds, whatever the client asks.
pub const MAX_PAGE: usize = 1000;

/// Chunk size of a streamed result fetch when the client names none.
pub const DEFAULT_RESULT_CHUNK: usize = 1 << 20;
/// The largest chunk a streamed result fetch sends (a fetch holds a few chunks at most, so
/// this sets what each one may hold).
pub const MAX_RESULT_CHUNK: usize = 1 << 20;

/// Largest domain chunk a worker serves (and takes): 1 MiB keeps a transfer's buffered
/// bytes small and each message far under the peer link's message cap.
pub const MAX_DOMAIN_CHUNK: usize = 1 << 20;
/// Smallest domain chunk served, whatever the request asks: fewer, larger messages.
pub const MIN_DOMAIN_CHUNK: usize = 64 << 10;

/// A page of ListJobs as a request asks for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ListPage {
    /// Jobs in the page, 1 to [`MAX_PAGE`].
    pub size: usize,
    /// The sequence number the page starts from (a previous response's token); `None`: the
    /// newest job.
    pub from_seq: Option<u64>,
}

/// ListJobs's size and token, checked: the token must be one a ListJobs response gives, a
/// sequence number in canonical decimal (no sign, no leading zero), so every accepted token
/// names one place in the list.
pub fn list_page(r: &proto::ListJobsRequest) -> Result<ListPage, Status> {
    check_field("page_token", &r.page_token)?;
    let size = match r.page_size {
        0 => DEFAULT_PAGE,
        n => (n as usize).min(MAX_PAGE),
    };
    let from_seq = match r.page_token.as_str() {
        "" => None,
        token => Some(parse_page_token(token).ok_or_else(|| {
            Status::invalid_argument("page_token is not one a ListJobs response gave")
        })?),
    };
    Ok(ListPage { size, from_seq })
}

/// The token a ListJobs response gives for a page starting at `seq`.
pub fn page_token(seq: u64) -> String {
    seq.to_string()
}

/// The sequence number of a token [`page_token`] made; `None` for any other string.
fn parse_page_token(token: &str) -> Option<u64> {
    // `u64::from_str` also takes "+7" and "007": tokens no response gives.
    let canonical =
        token.bytes().all(|b| b.is_ascii_digit()) && !(token.len() > 1 && token.starts_with('0'));
    if !canonical {
        return None;
    }
    token.parse().ok()
}

/// The chunk size a FetchResultStream request gets, its job id checked (the offset is
/// checked against the file, which only the server has).
pub fn result_chunk(r: &proto::FetchResultStreamRequest) -> Result<usize, Status> {
    check_field("job_id", &r.job_id)?;
    Ok(match r.chunk_bytes {
        0 => DEFAULT_RESULT_CHUNK,
        n => (n as usize).min(MAX_RESULT_CHUNK),
    })
}

/// A peer's `FetchDomain` request, checked before the serving worker looks at its frame:
/// fields within bounds and the protocol this worker speaks. Gives the chunk size to serve,
/// between [`MIN_DOMAIN_CHUNK`] and [`MAX_DOMAIN_CHUNK`].
pub fn domain_request(req: &proto::DomainRequest) -> Result<usize, Status> {
    check_field("sender", &req.sender)?;
    check_field("job_id", &req.job_id)?;
    if req.protocol_version != PROTOCOL_VERSION {
        return Err(Status::failed_precondition(format!(
            "peer speaks protocol {}, this worker {PROTOCOL_VERSION}",
            req.protocol_version
        )));
    }
    Ok((req.max_chunk_bytes as usize).clamp(MIN_DOMAIN_CHUNK, MAX_DOMAIN_CHUNK))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn list(page_size: u32, page_token: &str) -> Result<ListPage, Status> {
        list_page(&proto::ListJobsRequest {
            page_size,
            page_token: page_token.into(),
        })
    }

    #[test]
    fn page_tokens_are_only_those_a_response_gives() {
        assert_eq!(
            list(0, "").unwrap(),
            ListPage {
                size: DEFAULT_PAGE,
                from_seq: None
            }
        );
        for seq in [0, 7, 1234, u64::MAX] {
            let page = list(5000, &page_token(seq)).unwrap();
            assert_eq!(page.from_seq, Some(seq));
            assert_eq!(page.size, MAX_PAGE);
        }
        // `str::parse` alone takes a sign and leading zeros.
        for bad in [
            "+7",
            "007",
            "00",
            "-1",
            " 7",
            "7 ",
            "18446744073709551616",
            "x",
        ] {
            assert!(list(1, bad).is_err(), "{bad:?} accepted");
        }
    }

    #[test]
    fn domain_chunks_stay_within_the_servers_bounds() {
        let req = |max_chunk_bytes| proto::DomainRequest {
            protocol_version: PROTOCOL_VERSION,
            sender: "w1".into(),
            job_id: "j1".into(),
            domain: 0,
            max_chunk_bytes,
        };
        assert_eq!(domain_request(&req(0)).unwrap(), MIN_DOMAIN_CHUNK);
        assert_eq!(domain_request(&req(u32::MAX)).unwrap(), MAX_DOMAIN_CHUNK);
        let old = proto::DomainRequest {
            protocol_version: PROTOCOL_VERSION + 1,
            ..req(0)
        };
        assert_eq!(
            domain_request(&old).unwrap_err().code(),
            tonic::Code::FailedPrecondition
        );
    }
}
