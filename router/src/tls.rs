//! Certificates for a router reached over TLS, made on this machine: a certificate authority of
//! the deployment, the router's certificate (for the host names and addresses it is reached
//! at) signed by it, and the Zenoh configuration a client needs to trust it. Kept in one
//! folder and reused while they exist, so clients set up once keep working.
//!
//! ```text
//! DIR/ca.pem          the authority's certificate: what every client trusts
//! DIR/ca.key          its private key (mode 0600): keep it off the vehicles
//! DIR/router.pem      the router's certificate, for the names given
//! DIR/router.key      its private key (mode 0600)
//! DIR/client.json5    a Zenoh client configuration trusting ca.pem (a <zenoh config="..">)
//! DIR/clients/NAME.{pem,key,json5}   with --tls-client NAME: a client certificate whose
//!                     common name is NAME (mutual TLS: the router then asks every client for
//!                     one), its key, and the configuration of a client presenting it
//! ```
//! For a real deployment, make the folder on the ground station's machine, copy `ca.pem` and
//! `client.json5` to every node, and keep the keys where they are (docs/zenoh.md).

use std::path::{Path, PathBuf};

use anyhow::Context;

/// The files of a router's TLS folder.
#[derive(Debug, Clone)]
pub struct TlsFiles {
    /// The authority's certificate.
    pub ca: PathBuf,
    /// The authority's private key.
    pub ca_key: PathBuf,
    /// The router's certificate.
    pub cert: PathBuf,
    /// The router's private key.
    pub key: PathBuf,
    /// The client configuration.
    pub client_config: PathBuf,
}

impl TlsFiles {
    /// The files in `dir`.
    pub fn in_dir(dir: &Path) -> TlsFiles {
        TlsFiles {
            ca: dir.join("ca.pem"),
            ca_key: dir.join("ca.key"),
            cert: dir.join("router.pem"),
            key: dir.join("router.key"),
            client_config: dir.join("client.json5"),
        }
    }
}

/// The TLS files of `dir`, made when missing: a new authority and a router certificate for
/// `hosts` (names or IP addresses). Existing files are kept as they are.
///
/// # Errors
/// A file cannot be written, or a certificate cannot be made.
pub fn ensure(dir: &Path, hosts: &[String]) -> anyhow::Result<TlsFiles> {
    let files = TlsFiles::in_dir(dir);
    if [&files.ca, &files.cert, &files.key, &files.client_config]
        .iter()
        .all(|p| p.is_file())
    {
        return Ok(files);
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let ca_key = rcgen::KeyPair::generate().context("making the authority's key")?;
    let ca = authority(&ca_key)?;
    let (cert, key) = signed(
        hosts,
        "usal-router",
        vec![
            rcgen::ExtendedKeyUsagePurpose::ServerAuth,
            rcgen::ExtendedKeyUsagePurpose::ClientAuth,
        ],
        (&ca, &ca_key),
    )
    .context("the router's certificate")?;
    write(&files.ca, &ca.pem(), false)?;
    write(&files.ca_key, &ca_key.serialize_pem(), true)?;
    write(&files.cert, &cert.pem(), false)?;
    write(&files.key, &key.serialize_pem(), true)?;
    write(&files.client_config, &client_config(&files.ca, None), false)?;
    Ok(files)
}

/// A certificate for `names` (host names or addresses) with common name `common_name`, for
/// `usages`, signed by the authority `ca`; and its new key.
fn signed(
    names: &[String],
    common_name: &str,
    usages: Vec<rcgen::ExtendedKeyUsagePurpose>,
    (ca, ca_key): (&rcgen::Certificate, &rcgen::KeyPair),
) -> anyhow::Result<(rcgen::Certificate, rcgen::KeyPair)> {
    let key = rcgen::KeyPair::generate().context("making a key")?;
    let mut params = rcgen::CertificateParams::new(names.to_vec())
        .context("names that are no valid certificate names")?;
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, common_name);
    params.extended_key_usages = usages;
    let cert = params
        .signed_by(&key, ca, ca_key)
        .with_context(|| format!("signing the certificate of {common_name}"))?;
    Ok((cert, key))
}

/// The authority's certificate for `key`: the same subject and key each time it is made, so a
/// certificate it signs later verifies against the `ca.pem` made first.
fn authority(key: &rcgen::KeyPair) -> anyhow::Result<rcgen::Certificate> {
    let mut params = rcgen::CertificateParams::new(Vec::<String>::new())?;
    params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "USAL deployment authority");
    params.key_usages = vec![
        rcgen::KeyUsagePurpose::KeyCertSign,
        rcgen::KeyUsagePurpose::CrlSign,
        rcgen::KeyUsagePurpose::DigitalSignature,
    ];
    params
        .self_signed(key)
        .context("signing the authority's certificate")
}

/// The configuration of a client of the router of `files` presenting the certificate of
/// `name` (mutual TLS), made in `DIR/clients/` with its certificate and key when missing:
/// the router knows the client as `name` (its certificate's common name).
///
/// # Errors
/// The authority's key cannot be read, or a file cannot be written.
pub fn ensure_client(files: &TlsFiles, name: &str) -> anyhow::Result<PathBuf> {
    let dir = files
        .ca
        .parent()
        .map_or_else(|| PathBuf::from("clients"), |d| d.join("clients"));
    let (cert, key, config) = (
        dir.join(format!("{name}.pem")),
        dir.join(format!("{name}.key")),
        dir.join(format!("{name}.json5")),
    );
    if [&cert, &key, &config].iter().all(|p| p.is_file()) {
        return Ok(config);
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let ca_key = std::fs::read_to_string(&files.ca_key)
        .with_context(|| format!("reading the authority's key {}", files.ca_key.display()))?;
    let ca_key = rcgen::KeyPair::from_pem(&ca_key)
        .with_context(|| format!("{} is no private key", files.ca_key.display()))?;
    let ca = authority(&ca_key)?;
    let (signed_cert, client_key) = signed(
        &[],
        name,
        vec![rcgen::ExtendedKeyUsagePurpose::ClientAuth],
        (&ca, &ca_key),
    )?;
    write(&cert, &signed_cert.pem(), false)?;
    write(&key, &client_key.serialize_pem(), true)?;
    let text = client_config(&files.ca, Some((&cert, &key)));
    write(&config, &text, false)?;
    Ok(config)
}

/// A Zenoh client configuration trusting the authority at `ca`, presenting the certificate and
/// key `presented` (mutual TLS) if given: no multicast, and a client that waits a while for its
/// router at start, as a `<zenoh>` link without a file does.
fn client_config(ca: &Path, presented: Option<(&Path, &Path)>) -> String {
    let quoted = |p: &Path| format!("{:?}", p.display().to_string());
    let mtls = presented.map_or_else(String::new, |(cert, key)| {
        format!(
            "enable_mtls: true, connect_certificate: {}, connect_private_key: {}, ",
            quoted(cert),
            quoted(key)
        )
    });
    format!(
        r#"// A Zenoh client of a USAL router over TLS, made by usal-router: it trusts the
// deployment's authority ({ca}). Name it in a node's network.xml:
//   <zenoh mode="client" connect="tls/HOST:PORT" config="THIS FILE"/>
{{
  mode: "client",
  scouting: {{ multicast: {{ enabled: false }} }},
  connect: {{ timeout_ms: 15000 }},
  transport: {{ link: {{ tls: {{ {mtls}root_ca_certificate: {root} }} }} }},
}}
"#,
        ca = ca.display(),
        root = quoted(ca),
    )
}

fn write(path: &Path, text: &str, private: bool) -> anyhow::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(if private { 0o600 } else { 0o644 })
        .open(path)
        .with_context(|| format!("writing {}", path.display()))?;
    f.write_all(text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// Sets the router's side of TLS in `config`: its certificate and key, and with `mutual`
/// a certificate asked of every client.
///
/// # Errors
/// Zenoh refuses a value.
pub fn configure_router(
    config: &mut zenoh::Config,
    files: &TlsFiles,
    mutual: bool,
) -> anyhow::Result<()> {
    let path = |p: &Path| format!("{:?}", p.display().to_string());
    for (key, value) in [
        ("transport/link/tls/listen_certificate", path(&files.cert)),
        ("transport/link/tls/listen_private_key", path(&files.key)),
        ("transport/link/tls/root_ca_certificate", path(&files.ca)),
        ("transport/link/tls/enable_mtls", mutual.to_string()),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("Zenoh refused {key}"))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_folder_is_made_once_and_its_keys_are_private() {
        let dir = tempfile::tempdir().unwrap();
        let files = ensure(dir.path(), &["127.0.0.1".into(), "localhost".into()]).unwrap();
        let ca = std::fs::read_to_string(&files.ca).unwrap();
        assert!(ca.starts_with("-----BEGIN CERTIFICATE-----"), "{ca}");
        use std::os::unix::fs::PermissionsExt;
        for key in [&files.key, &dir.path().join("ca.key")] {
            let mode = std::fs::metadata(key).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode, 0o600, "{}", key.display());
        }
        // The client configuration is one Zenoh takes, trusting this authority.
        let client = zenoh::Config::from_file(&files.client_config).unwrap();
        let root = client
            .get_json("transport/link/tls/root_ca_certificate")
            .unwrap();
        assert!(root.contains("ca.pem"), "{root}");
        // Made again: the same files, untouched.
        let again = ensure(dir.path(), &["127.0.0.1".into()]).unwrap();
        assert_eq!(std::fs::read_to_string(&again.ca).unwrap(), ca);
    }
}
