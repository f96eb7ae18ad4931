//! Bounds on the string fields of requests (scene names, job ids, worker ids, addresses):
//! checked before any work, and refused with their size only, never their contents, so an
//! oversized or hostile value is neither used nor echoed back.

use tonic::Status;

/// Most bytes of a name, id or address in any request.
pub const MAX_FIELD_BYTES: usize = 256;

/// Refuses `value` (the request field `field`) when it is longer than [`MAX_FIELD_BYTES`].
pub fn check_field(field: &str, value: &str) -> Result<(), Status> {
    if value.len() > MAX_FIELD_BYTES {
        return Err(Status::invalid_argument(format!(
            "{field} is {} bytes long; at most {MAX_FIELD_BYTES} are accepted",
            value.len()
        )));
    }
    Ok(())
}

/// `value` cut to at most [`MAX_FIELD_BYTES`] (at a character boundary), for logging a
/// field that may be oversized.
pub fn shown(value: &str) -> &str {
    let mut end = value.len().min(MAX_FIELD_BYTES);
    while !value.is_char_boundary(end) {
        end -= 1;
    }
    &value[..end]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_fields_are_refused_without_their_contents() {
        assert!(check_field("job_id", &"a".repeat(MAX_FIELD_BYTES)).is_ok());
        let e = check_field("job_id", &"secret".repeat(100)).unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(e.message().contains("600 bytes"), "{}", e.message());
        assert!(!e.message().contains("secret"), "{}", e.message());
        assert_eq!(shown(&"é".repeat(200)).len(), MAX_FIELD_BYTES);
    }
}
