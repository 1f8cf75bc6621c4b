//! TLS and QUIC configuration for both sides of a cosurg link.
//!
//! * The coordinator presents either a certificate chain given on the command line or a
//!   self-signed certificate generated with rcgen (SANs `localhost`, `127.0.0.1`, `::1` and
//!   the host name) and persisted in the state directory (`coordinator-cert.pem`,
//!   `coordinator-key.pem`), so its fingerprint stays the same across restarts.
//! * The **fingerprint** is the SHA-256 of the DER-encoded end-entity certificate, printed as
//!   upper-case hex pairs separated by colons (`AB:CD:…`, as `openssl x509 -fingerprint
//!   -sha256` prints it). [`parse_fingerprint`] also accepts plain hex, any case.
//! * Sites verify the coordinator either by pinning that fingerprint
//!   ([`client_config_pinned`]: exactly this certificate, with the handshake signature checked
//!   against its key; names and expiry are not checked) or with a CA
//!   ([`client_config_ca`]: ordinary WebPKI validation, the server name must match).
//! * Both sides offer only the ALPN [`proto::ALPN`] (`cosurg/1`); a peer offering another
//!   protocol is refused by TLS (alert 120, no_application_protocol).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use quinn::crypto::rustls::{QuicClientConfig, QuicServerConfig};
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};
use sha2::{Digest, Sha256};

/// File name of the persisted self-signed certificate inside the state directory.
pub const CERT_FILE: &str = "coordinator-cert.pem";
/// File name of the persisted private key inside the state directory.
pub const KEY_FILE: &str = "coordinator-key.pem";

/// TLS setup failure.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: no {what} found in PEM")]
    NoPem { path: String, what: &'static str },
    #[error("{path}: bad PEM: {detail}")]
    BadPem { path: String, detail: String },
    #[error("invalid certificate fingerprint {0:?}: expected 32 bytes as hex (colons optional)")]
    BadFingerprint(String),
    #[error("certificate generation failed: {0}")]
    Rcgen(#[from] rcgen::Error),
    #[error("TLS configuration: {0}")]
    Rustls(#[from] rustls::Error),
    #[error("QUIC crypto configuration: {0}")]
    Quic(String),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TlsError + '_ {
    move |source| TlsError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The crypto provider used everywhere (ring).
pub fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// SHA-256 of a DER certificate.
pub fn fingerprint_bytes(cert_der: &[u8]) -> [u8; 32] {
    Sha256::digest(cert_der).into()
}

/// Fingerprint formatted as `AB:CD:…` (upper-case hex with colons).
pub fn fingerprint(cert_der: &[u8]) -> String {
    format_fingerprint(&fingerprint_bytes(cert_der))
}

/// Format 32 bytes as `AB:CD:…`.
pub fn format_fingerprint(fp: &[u8; 32]) -> String {
    fp.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(":")
}

/// Parse a fingerprint: 64 hex digits, colons/spaces optional, any case.
pub fn parse_fingerprint(s: &str) -> Result<[u8; 32], TlsError> {
    let clean: String = s
        .chars()
        .filter(|c| !matches!(c, ':' | ' ' | '-'))
        .collect();
    let v = hex::decode(&clean).map_err(|_| TlsError::BadFingerprint(s.to_string()))?;
    v.try_into()
        .map_err(|_| TlsError::BadFingerprint(s.to_string()))
}

/// A certificate chain and its private key.
#[derive(Debug)]
pub struct Identity {
    pub chain: Vec<CertificateDer<'static>>,
    pub key: PrivateKeyDer<'static>,
}

impl Clone for Identity {
    fn clone(&self) -> Self {
        Self {
            chain: self.chain.clone(),
            key: self.key.clone_key(),
        }
    }
}

impl Identity {
    /// Fingerprint of the end-entity certificate.
    pub fn fingerprint(&self) -> String {
        fingerprint(self.chain.first().map(|c| c.as_ref()).unwrap_or(&[]))
    }

    /// Parse PEM text (certificate chain, private key). `label` names the source in errors.
    pub fn from_pem(cert_pem: &[u8], key_pem: &[u8], label: &str) -> Result<Self, TlsError> {
        let chain = CertificateDer::pem_slice_iter(cert_pem)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| TlsError::BadPem {
                path: label.to_string(),
                detail: e.to_string(),
            })?;
        if chain.is_empty() {
            return Err(TlsError::NoPem {
                path: label.to_string(),
                what: "CERTIFICATE",
            });
        }
        let key = PrivateKeyDer::from_pem_slice(key_pem).map_err(|e| TlsError::BadPem {
            path: label.to_string(),
            detail: format!("private key: {e}"),
        })?;
        Ok(Self { chain, key })
    }

    /// Load a certificate chain and key from PEM files.
    pub fn load(cert: &Path, key: &Path) -> Result<Self, TlsError> {
        let c = std::fs::read(cert).map_err(io_err(cert))?;
        let k = std::fs::read(key).map_err(io_err(key))?;
        Self::from_pem(&c, &k, &format!("{} / {}", cert.display(), key.display()))
    }

    /// Generate a self-signed certificate for `localhost`, `127.0.0.1`, `::1` and the host
    /// name. Returns the identity and its PEM texts (certificate, key).
    pub fn generate_self_signed() -> Result<(Self, String, String), TlsError> {
        let mut names = vec![
            "localhost".to_string(),
            "127.0.0.1".to_string(),
            "::1".to_string(),
        ];
        if let Some(h) = hostname()
            && !names.contains(&h)
        {
            names.push(h);
        }
        let ck = rcgen::generate_simple_self_signed(names)?;
        let cert_pem = ck.cert.pem();
        let key_pem = ck.signing_key.serialize_pem();
        let id = Self {
            chain: vec![ck.cert.der().clone()],
            key: PrivateKeyDer::Pkcs8(ck.signing_key.serialize_der().into()),
        };
        Ok((id, cert_pem, key_pem))
    }

    /// Load the persisted self-signed identity from `state_dir`, or generate and persist one
    /// (key file mode 0600 on Unix). Returns the identity and whether it was newly created.
    pub fn load_or_create(state_dir: &Path) -> Result<(Self, bool), TlsError> {
        let cert = state_dir.join(CERT_FILE);
        let key = state_dir.join(KEY_FILE);
        if cert.exists() && key.exists() {
            return Ok((Self::load(&cert, &key)?, false));
        }
        std::fs::create_dir_all(state_dir).map_err(io_err(state_dir))?;
        let (id, cert_pem, key_pem) = Self::generate_self_signed()?;
        write_private(&key, key_pem.as_bytes())?;
        std::fs::write(&cert, cert_pem).map_err(io_err(&cert))?;
        Ok((id, true))
    }
}

fn write_private(path: &Path, data: &[u8]) -> Result<(), TlsError> {
    write_private_file(path, data).map_err(io_err(path))
}

/// Write a secret file, readable by its owner only (mode 0600 on Unix).
pub fn write_private_file(path: &Path, data: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut opts = std::fs::OpenOptions::new();
    opts.write(true).create(true).truncate(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        opts.mode(0o600);
    }
    opts.open(path)?.write_all(data)
}

/// This machine's host name, if it can be found (`/proc/sys/kernel/hostname`,
/// `/etc/hostname`, `$HOSTNAME`).
pub fn hostname() -> Option<String> {
    let from_file = |p: &str| std::fs::read_to_string(p).ok();
    from_file("/proc/sys/kernel/hostname")
        .or_else(|| from_file("/etc/hostname"))
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty() && s.len() < 254)
}

/// QUIC transport settings shared by coordinator and sites: keep-alive 1 s, idle timeout
/// 10 s, datagrams on with a small send buffer (newest wins), initial RTT 50 ms, and BBR
/// congestion control: the default loss-based controller (CUBIC) shrinks its window at
/// every random loss, and at the `average` preset (2 % loss, 200 ms round trip) keyframe
/// streams then queued for seconds (measured: 33 mm divergence with CUBIC, 2–4 mm with
/// BBR; `cosurg bench sync`). quinn marks its BBR as experimental.
pub fn transport_config() -> quinn::TransportConfig {
    let mut t = quinn::TransportConfig::default();
    t.keep_alive_interval(Some(Duration::from_secs(1)))
        .max_idle_timeout(Some(
            Duration::from_secs(10)
                .try_into()
                .expect("10 s fits an idle timeout"),
        ))
        .initial_rtt(Duration::from_millis(50))
        .datagram_receive_buffer_size(Some(256 * 1024))
        .datagram_send_buffer_size(DATAGRAM_SEND_BUFFER)
        .max_concurrent_uni_streams(256u32.into())
        .max_concurrent_bidi_streams(4u32.into());
    t.congestion_controller_factory(std::sync::Arc::new(quinn::congestion::BbrConfig::default()));
    t
}

/// Datagram send buffer (bytes): about 8 full datagrams. quinn drops the oldest queued
/// datagram when it is full, so stale poses never delay fresh ones.
pub const DATAGRAM_SEND_BUFFER: usize = 8 * 1200;

/// Server-side QUIC configuration for an identity.
pub fn server_config(id: &Identity) -> Result<quinn::ServerConfig, TlsError> {
    let mut tls = rustls::ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .with_no_client_auth()
        .with_single_cert(id.chain.clone(), id.key.clone_key())?;
    tls.alpn_protocols = vec![proto::ALPN.to_vec()];
    tls.max_early_data_size = 0;
    let quic = QuicServerConfig::try_from(tls).map_err(|e| TlsError::Quic(e.to_string()))?;
    let mut cfg = quinn::ServerConfig::with_crypto(Arc::new(quic));
    cfg.transport_config(Arc::new(transport_config()));
    Ok(cfg)
}

fn client_from_rustls(mut tls: rustls::ClientConfig) -> Result<quinn::ClientConfig, TlsError> {
    tls.alpn_protocols = vec![proto::ALPN.to_vec()];
    let quic = QuicClientConfig::try_from(tls).map_err(|e| TlsError::Quic(e.to_string()))?;
    let mut cfg = quinn::ClientConfig::new(Arc::new(quic));
    cfg.transport_config(Arc::new(transport_config()));
    Ok(cfg)
}

/// Client configuration accepting exactly the certificate with this SHA-256 fingerprint.
pub fn client_config_pinned(fingerprint: &str) -> Result<quinn::ClientConfig, TlsError> {
    let fp = parse_fingerprint(fingerprint)?;
    let provider = provider();
    let verifier = PinnedCertVerifier {
        fingerprint: fp,
        provider: provider.clone(),
    };
    let tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(verifier))
        .with_no_client_auth();
    client_from_rustls(tls)
}

/// Client configuration trusting the CA certificate(s) in `ca_pem` (WebPKI validation; the
/// server name given to `connect` must match the certificate).
pub fn client_config_ca(ca_pem: &[u8]) -> Result<quinn::ClientConfig, TlsError> {
    let mut roots = rustls::RootCertStore::empty();
    let mut n = 0;
    for cert in CertificateDer::pem_slice_iter(ca_pem) {
        let cert = cert.map_err(|e| TlsError::BadPem {
            path: "CA".into(),
            detail: e.to_string(),
        })?;
        roots.add(cert)?;
        n += 1;
    }
    if n == 0 {
        return Err(TlsError::NoPem {
            path: "CA".into(),
            what: "CERTIFICATE",
        });
    }
    let tls = rustls::ClientConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .with_root_certificates(roots)
        .with_no_client_auth();
    client_from_rustls(tls)
}

/// Accepts exactly one certificate, identified by the SHA-256 of its DER encoding. The
/// handshake signature is still verified against that certificate's public key, so only
/// the holder of the matching private key is accepted.
#[derive(Debug)]
pub struct PinnedCertVerifier {
    fingerprint: [u8; 32],
    provider: Arc<CryptoProvider>,
}

impl PinnedCertVerifier {
    pub fn new(fingerprint: [u8; 32]) -> Self {
        Self {
            fingerprint,
            provider: provider(),
        }
    }
}

impl ServerCertVerifier for PinnedCertVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        let got = fingerprint_bytes(end_entity.as_ref());
        // Not secret, but compare without early exit anyway.
        if got
            .iter()
            .zip(self.fingerprint.iter())
            .fold(0u8, |a, (x, y)| a | (x ^ y))
            == 0
        {
            Ok(ServerCertVerified::assertion())
        } else {
            tracing::warn!(
                got = %format_fingerprint(&got),
                pinned = %format_fingerprint(&self.fingerprint),
                "coordinator certificate does not match the pinned fingerprint"
            );
            Err(rustls::Error::InvalidCertificate(
                rustls::CertificateError::ApplicationVerificationFailure,
            ))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.provider
            .signature_verification_algorithms
            .supported_schemes()
    }
}

/// Default state directory: `$XDG_DATA_HOME/cosurg`, else `$HOME/.local/share/cosurg`,
/// else `./.cosurg`.
pub fn default_state_dir() -> PathBuf {
    if let Some(x) = std::env::var_os("XDG_DATA_HOME").filter(|x| !x.is_empty()) {
        return PathBuf::from(x).join("cosurg");
    }
    if let Some(h) = std::env::var_os("HOME").filter(|x| !x.is_empty()) {
        return PathBuf::from(h).join(".local/share/cosurg");
    }
    PathBuf::from(".cosurg")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_format_and_parse() {
        let fp = fingerprint(b"hello");
        assert_eq!(fp.len(), 32 * 3 - 1);
        assert!(fp.starts_with("2C:F2:4D:BA"));
        let plain = fp.replace(':', "").to_lowercase();
        assert_eq!(
            parse_fingerprint(&fp).unwrap(),
            parse_fingerprint(&plain).unwrap()
        );
        assert!(parse_fingerprint("abcd").is_err());
        assert!(parse_fingerprint(&"zz".repeat(32)).is_err());
    }

    #[test]
    fn self_signed_persisted_and_reused() {
        let dir = tempfile::tempdir().unwrap();
        let (a, created) = Identity::load_or_create(dir.path()).unwrap();
        assert!(created);
        let (b, created) = Identity::load_or_create(dir.path()).unwrap();
        assert!(!created);
        assert_eq!(a.fingerprint(), b.fingerprint());
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(dir.path().join(KEY_FILE))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        server_config(&b).unwrap();
        client_config_pinned(&b.fingerprint()).unwrap();
        let pem = std::fs::read(dir.path().join(CERT_FILE)).unwrap();
        client_config_ca(&pem).unwrap();
    }

    #[test]
    fn bad_pem_errors_name_the_source() {
        let e = Identity::from_pem(b"nothing", b"nothing", "x.pem").unwrap_err();
        assert!(e.to_string().contains("x.pem"), "{e}");
        assert!(client_config_ca(b"").is_err());
    }
}
