use tonic::Request;
use tonic::service::Interceptor;
use tonic::transport::ClientTlsConfig;

use super::*;

fn file(text: &str) -> tempfile::NamedTempFile {
    let f = tempfile::NamedTempFile::new().unwrap();
    std::fs::write(f.path(), text).unwrap();
    f
}

fn with(key: &'static str, value: &str) -> Request<()> {
    let mut r = Request::new(());
    r.metadata_mut().insert(key, value.parse().unwrap());
    r
}

#[test]
fn the_secret_is_checked_and_never_printed() {
    let f = file("s3cret-value\n");
    let secret = ClusterSecret::from_file(f.path()).unwrap();
    assert!(!format!("{secret:?}").contains("s3cret"));
    let mut check = RequireSecret(Some(secret.clone()));
    assert!(check.call(with(SECRET_HEADER, "s3cret-value")).is_ok());
    let wrong = check.call(with(SECRET_HEADER, "s3cret-valuX")).unwrap_err();
    assert_eq!(wrong.code(), tonic::Code::Unauthenticated);
    assert!(!wrong.message().contains("s3cret"), "{}", wrong.message());
    let missing = check.call(Request::new(())).unwrap_err();
    assert_eq!(missing.code(), tonic::Code::Unauthenticated);
    assert!(missing.message().contains(SECRET_HEADER));
    // The client side adds exactly what the server expects.
    let sent = Credential::secret(Some(&secret))
        .call(Request::new(()))
        .unwrap();
    assert!(check.call(sent).is_ok());
    // Off: anything passes.
    assert!(RequireSecret(None).call(Request::new(())).is_ok());
}

#[test]
fn bad_secret_files_are_refused_with_the_reason() {
    let empty = file(" \n");
    assert!(matches!(
        ClusterSecret::from_file(empty.path()),
        Err(SecurityError::EmptySecret { .. })
    ));
    let spaced = file("two words\n");
    assert!(matches!(
        ClusterSecret::from_file(spaced.path()),
        Err(SecurityError::NotHeaderSafe { .. })
    ));
    let e = ClusterSecret::from_file(Path::new("/nonexistent/secret")).unwrap_err();
    assert!(
        e.to_string()
            .starts_with("cannot read cluster secret file /nonexistent/secret")
    );
}

#[test]
fn tokens_name_their_users() {
    let f = file("# users\nabc123 alice\n\ndef456\nroot1 bob admin\n");
    let tokens = UserTokens::from_file(f.path()).unwrap();
    assert_eq!(tokens.len(), 3);
    let mut check = RequireToken(Some(tokens));
    let ok = check.call(with(TOKEN_HEADER, "Bearer abc123")).unwrap();
    let alice = ok.extensions().get::<User>().unwrap();
    assert_eq!((alice.name.as_str(), alice.admin), ("alice", false));
    let ok = check.call(with(TOKEN_HEADER, "Bearer def456")).unwrap();
    assert_eq!(ok.extensions().get::<User>().unwrap().name, "user-4");
    let ok = check.call(with(TOKEN_HEADER, "Bearer root1")).unwrap();
    assert!(ok.extensions().get::<User>().unwrap().admin);
    for (req, why) in [
        (Request::new(()), "no user token"),
        (with(TOKEN_HEADER, "Bearer nope"), "unknown user token"),
        (with(TOKEN_HEADER, "abc123"), "must be `Bearer TOKEN`"),
    ] {
        let e = check.call(req).unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated);
        assert!(e.message().contains(why), "{}", e.message());
    }
    let sent = Credential::bearer(Some("abc123"))
        .unwrap()
        .call(Request::new(()))
        .unwrap();
    assert!(check.call(sent).is_ok());
    assert_eq!(first_token(f.path()).unwrap(), "abc123");
}

#[test]
fn bad_token_files_are_refused_with_the_line() {
    let none = file("# nobody\n");
    assert!(matches!(
        UserTokens::from_file(none.path()),
        Err(SecurityError::NoTokens { .. })
    ));
    let twice = file("a x\nb y\na z\n");
    assert!(matches!(
        UserTokens::from_file(twice.path()),
        Err(SecurityError::DuplicateToken { line: 3, .. })
    ));
    assert!(Credential::bearer(Some("has space")).is_err());
    let role = file("a x root\n");
    assert!(matches!(
        UserTokens::from_file(role.path()),
        Err(SecurityError::BadRole { line: 1, .. })
    ));
}

#[test]
fn tls_makes_addresses_https_and_https_needs_a_ca() {
    let tls = ClientTlsConfig::new();
    for addr in ["h:1", "http://h:1", "https://h:1"] {
        let e = endpoint(addr, Some(&tls)).unwrap();
        assert_eq!(e.uri().to_string(), "https://h:1/");
    }
    assert_eq!(
        endpoint("h:1", None).unwrap().uri().scheme_str(),
        Some("http")
    );
    let e = endpoint("https://h:1", None).unwrap_err();
    assert!(e.to_string().contains("--tls-ca"), "{e}");
    assert_eq!(url("h:1", true), "https://h:1");
    assert_eq!(url("http://h:1", false), "http://h:1");
}

#[test]
fn only_loopback_may_go_without_protection() {
    let lo: std::net::SocketAddr = "127.0.0.1:1".parse().unwrap();
    let any: std::net::SocketAddr = "0.0.0.0:1".parse().unwrap();
    assert!(check_exposure(lo, &["TLS"], false).is_ok());
    assert!(check_exposure(any, &[], false).is_ok());
    assert!(check_exposure(any, &["TLS"], true).is_ok());
    let e = check_exposure(any, &["TLS", "the cluster secret", "user tokens"], false);
    let e = e.unwrap_err().to_string();
    assert!(
        e.contains("without TLS, the cluster secret and user tokens") && e.contains("--insecure"),
        "{e}"
    );
    // Every listener is checked, each with the protections marked absent as missing.
    assert!(check_listeners([lo, any], &[(true, "TLS"), (true, "a secret")], false).is_ok());
    assert!(check_listeners([lo], &[(false, "TLS")], false).is_ok());
    let e = check_listeners([lo, any], &[(true, "TLS"), (false, "a secret")], false);
    let e = e.unwrap_err().to_string();
    assert!(e.contains("serve 0.0.0.0:1 without a secret:"), "{e}");
}

#[test]
fn a_non_pem_file_is_named() {
    let f = file("not a certificate");
    let args = ConnectTlsArgs {
        tls_ca: Some(f.path().to_path_buf()),
        tls_domain: None,
    };
    let e = args.client_config(None).unwrap_err();
    assert!(e.to_string().contains("is not PEM"), "{e}");
}
