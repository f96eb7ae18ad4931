//! Credentials: the cluster secret workers present to the coordinator and to each other, the
//! user tokens of the job API, and the tonic interceptors that check them (servers) or add
//! them (clients).

use std::fmt;
use std::path::Path;
use std::sync::Arc;

use subtle::ConstantTimeEq;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::{Request, Status};
use tracing::warn;

use super::{SECRET_HEADER, SecurityError, TOKEN_HEADER, header_safe, read};

/// The secret every worker presents to the coordinator and to its peers. Never printed.
#[derive(Clone)]
pub struct ClusterSecret(Arc<[u8]>);

impl fmt::Debug for ClusterSecret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("ClusterSecret(<redacted>)")
    }
}

impl ClusterSecret {
    /// Reads the secret from `path`; surrounding whitespace (a final newline) is ignored.
    pub fn from_file(path: &Path) -> Result<Self, SecurityError> {
        let bytes = read(path, "cluster secret file")?;
        let secret = bytes.trim_ascii();
        if secret.is_empty() {
            return Err(SecurityError::EmptySecret {
                path: path.to_path_buf(),
            });
        }
        if !header_safe(secret) {
            return Err(SecurityError::NotHeaderSafe {
                what: "the cluster secret".into(),
                path: path.to_path_buf(),
            });
        }
        Ok(ClusterSecret(secret.into()))
    }

    /// Reads the secret if a file is given.
    pub fn load(path: Option<&Path>) -> Result<Option<Self>, SecurityError> {
        path.map(Self::from_file).transpose()
    }

    fn matches(&self, presented: &[u8]) -> bool {
        bool::from(self.0.as_ref().ct_eq(presented))
    }

    fn header_value(&self) -> MetadataValue<Ascii> {
        let mut v =
            MetadataValue::try_from(self.0.as_ref()).expect("checked printable ASCII when loaded");
        v.set_sensitive(true);
        v
    }
}

/// The user tokens the job API accepts, each with its user (name and role).
#[derive(Clone)]
pub struct UserTokens(Arc<Vec<(Vec<u8>, User)>>);

impl fmt::Debug for UserTokens {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let names: Vec<&str> = self.0.iter().map(|(_, u)| u.name.as_str()).collect();
        f.debug_tuple("UserTokens").field(&names).finish()
    }
}

impl UserTokens {
    /// Reads `path`: one token per line, optionally followed by the user's name and then a
    /// role (`admin` may cancel anyone's jobs; `user`, the default, only their own); blank
    /// lines and lines starting with `#` are ignored. A token without a name is called
    /// `user-LINE`.
    pub fn from_file(path: &Path) -> Result<Self, SecurityError> {
        let bytes = read(path, "user tokens file")?;
        let text = String::from_utf8_lossy(&bytes);
        let mut tokens: Vec<(Vec<u8>, User)> = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (token, name) = line.split_once(char::is_whitespace).unwrap_or((line, ""));
            if !header_safe(token.as_bytes()) {
                return Err(SecurityError::NotHeaderSafe {
                    what: format!("the token on line {}", i + 1),
                    path: path.to_path_buf(),
                });
            }
            if tokens.iter().any(|(t, _)| t == token.as_bytes()) {
                return Err(SecurityError::DuplicateToken {
                    path: path.to_path_buf(),
                    line: i + 1,
                });
            }
            let mut words = name.split_whitespace();
            let name = match words.next() {
                None => format!("user-{}", i + 1),
                Some(n) => n.to_string(),
            };
            let admin = match words.next() {
                None | Some("user") => false,
                Some("admin") => true,
                Some(_) => {
                    return Err(SecurityError::BadRole {
                        path: path.to_path_buf(),
                        line: i + 1,
                    });
                }
            };
            tokens.push((token.as_bytes().to_vec(), User { name, admin }));
        }
        if tokens.is_empty() {
            return Err(SecurityError::NoTokens {
                path: path.to_path_buf(),
            });
        }
        Ok(UserTokens(Arc::new(tokens)))
    }

    /// Reads the tokens if a file is given.
    pub fn load(path: Option<&Path>) -> Result<Option<Self>, SecurityError> {
        path.map(Self::from_file).transpose()
    }

    /// Number of tokens.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Never true for a loaded file (an empty one is refused).
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The name of `presented`'s user. Every token is compared, in constant time, so the
    /// time taken tells nothing about which one nearly matched.
    fn user(&self, presented: &[u8]) -> Option<&User> {
        let mut found = None;
        for (token, user) in self.0.iter() {
            if bool::from(token.as_slice().ct_eq(presented)) {
                found = Some(user);
            }
        }
        found
    }
}

/// The user a request was authenticated as (in the request's extensions).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct User {
    /// The name from the tokens file: owner of the jobs the user submits.
    pub name: String,
    /// The admin role: may cancel anyone's jobs.
    pub admin: bool,
}

/// Server interceptor: refuses requests without the cluster secret (`UNAUTHENTICATED`).
/// Without a secret configured, every request passes.
#[derive(Clone, Debug)]
pub struct RequireSecret(pub Option<ClusterSecret>);

impl Interceptor for RequireSecret {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(secret) = &self.0 else {
            return Ok(request);
        };
        let refusal = match request.metadata().get(SECRET_HEADER) {
            Some(v) if secret.matches(v.as_bytes()) => return Ok(request),
            None => format!(
                "no cluster secret: this service requires the {SECRET_HEADER} header \
                 (start the worker with --cluster-secret-file)"
            ),
            Some(_) => "wrong cluster secret (check --cluster-secret-file)".to_string(),
        };
        warn!(client = ?crate::listen::remote_addr(&request), "refused: {refusal}");
        Err(Status::unauthenticated(refusal))
    }
}

/// Server interceptor: refuses requests without a known user token (`UNAUTHENTICATED`) and
/// records the [`User`] of the others. Without tokens configured, every request passes.
#[derive(Clone, Debug)]
pub struct RequireToken(pub Option<UserTokens>);

impl RequireToken {
    /// Who the `authorization` header value `presented` authenticates (`None` when user
    /// tokens are off), or why it is refused: the one check of the job API and of the
    /// dashboard's HTTP API.
    pub fn authenticate(&self, presented: Option<&[u8]>) -> Result<Option<User>, &'static str> {
        let Some(tokens) = &self.0 else {
            return Ok(None);
        };
        match presented.map(|v| v.strip_prefix(b"Bearer ")) {
            None => Err(
                "no user token: the job API requires `authorization: Bearer TOKEN` \
                 (rayfarm: --token, --token-file or RAYFARM_TOKEN)",
            ),
            Some(None) => Err("the authorization header must be `Bearer TOKEN`"),
            Some(Some(token)) => match tokens.user(token.trim_ascii()) {
                Some(user) => Ok(Some(user.clone())),
                None => Err("unknown user token"),
            },
        }
    }
}

impl Interceptor for RequireToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let presented = request.metadata().get(TOKEN_HEADER).map(|v| v.as_bytes());
        match self.authenticate(presented) {
            Ok(None) => Ok(request),
            Ok(Some(user)) => {
                request.extensions_mut().insert(user);
                Ok(request)
            }
            Err(refusal) => {
                warn!(client = ?crate::listen::remote_addr(&request), "refused: {refusal}");
                Err(Status::unauthenticated(refusal))
            }
        }
    }
}

/// Client interceptor: adds a credential header to every request (nothing when `None`).
#[derive(Clone, Debug, Default)]
pub struct Credential(Option<(&'static str, MetadataValue<Ascii>)>);

impl Credential {
    /// No credential.
    pub fn none() -> Self {
        Credential(None)
    }

    /// The cluster secret, if any.
    pub fn secret(secret: Option<&ClusterSecret>) -> Self {
        Credential(secret.map(|s| (SECRET_HEADER, s.header_value())))
    }

    /// A user token, if any. Fails when it cannot travel in a header.
    pub fn bearer(token: Option<&str>) -> Result<Self, InvalidToken> {
        let Some(token) = token.map(str::trim) else {
            return Ok(Credential(None));
        };
        if !header_safe(token.as_bytes()) {
            return Err(InvalidToken);
        }
        let mut v = MetadataValue::try_from(format!("Bearer {token}")).map_err(|_| InvalidToken)?;
        v.set_sensitive(true);
        Ok(Credential(Some((TOKEN_HEADER, v))))
    }
}

/// A user token that cannot travel in a gRPC header.
#[derive(Debug, thiserror::Error)]
#[error("the user token must be printable ASCII without spaces")]
pub struct InvalidToken;

impl Interceptor for Credential {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some((key, value)) = &self.0 {
            request.metadata_mut().insert(*key, value.clone());
        }
        Ok(request)
    }
}

/// The first token of a user tokens file (what a client presents when given the file).
pub fn first_token(path: &Path) -> Result<String, SecurityError> {
    let tokens = UserTokens::from_file(path)?;
    Ok(String::from_utf8_lossy(&tokens.0[0].0).into_owned())
}
