//! A room's keys: its authority, and each participant's certificate and private key (issue 37).
//!
//! `lungdyn remote keys --room ROOM --out DIR` makes them ([`make`]); every remote role given
//! `--keys DIR --identity NAME` loads them ([`Room::load`]) and then
//! * reaches the others over Zenoh's TLS link with mutual authentication: every participant
//!   presents its certificate, signed by the room's authority, and accepts only such peers;
//! * seals every packet it sends with its own key and opens every packet it receives against the
//!   room's certificates ([`crate::seal`]): the origin, its role and a sequence are authenticated
//!   end to end, so neither an outsider nor a router nor a participant of another role can forge
//!   a state, an event or a clock answer.
//!
//! Keys are Ed25519 (small, fast to sign and check; rustls and ring take them for TLS 1.3).
//!
//! The folder (documented in `docs/REMOTE_SECURITY.md` and in the `README.txt` written into it):
//! ```text
//! DIR/authority.crt   the room's authority (public; every participant needs it)
//! DIR/authority.key   its private key (0600): only to make more participants; keep it off the
//!                     participants' machines
//! DIR/NAME.crt        each participant's certificate (public; every participant needs them all:
//!                     they are how a packet's origin is checked)
//! DIR/NAME.key        each participant's private key (0600): only on that participant's machine
//! ```
//! A certificate says who (common name = the participant's name), which room (organisation
//! `lungdyn room ROOM`) and which role (organisational unit: source, site, observer or router).

use std::fs;
use std::io::Write;
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use thiserror::Error;

/// A participant's part in a room, as its certificate states it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// Runs the simulation; publishes states, answers probes, takes events.
    Source,
    /// Follows the source and may send interventions (events).
    Site,
    /// Follows the source; sends nothing but clock probes.
    Observer,
    /// A classroom's router and its time relay: relays, answers the sites' clock probes in the
    /// source's time; can forge nothing (it holds no source or site key).
    Router,
}

impl Role {
    /// The role's word (in certificates, on the command line).
    pub fn name(self) -> &'static str {
        match self {
            Role::Source => "source",
            Role::Site => "site",
            Role::Observer => "observer",
            Role::Router => "router",
        }
    }

    /// The role a word names.
    pub fn parse(s: &str) -> Option<Role> {
        Some(match s {
            "source" => Role::Source,
            "site" => Role::Site,
            "observer" => Role::Observer,
            "router" => Role::Router,
            _ => return None,
        })
    }
}

/// Why a room's keys could not be made or used.
#[derive(Debug, Error)]
pub enum KeysError {
    /// A bad option or name.
    #[error("{0}")]
    Usage(String),
    /// A file could not be read or written.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: PathBuf,
        /// What went wrong, and what to do.
        message: String,
    },
    /// A certificate or key is not what the room needs.
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong with it, and what to do.
        message: String,
    },
}

fn file_err(path: &Path, e: impl std::fmt::Display) -> KeysError {
    KeysError::File {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn invalid(path: &Path, message: impl Into<String>) -> KeysError {
    KeysError::Invalid {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// One participant to make keys for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Participant {
    /// Its name (the certificate's common name and the files' stem).
    pub name: String,
    /// Its role.
    pub role: Role,
}

impl std::str::FromStr for Participant {
    type Err = String;

    /// `NAME:ROLE` (e.g. `ward-3:site`).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (name, role) = s.split_once(':').ok_or_else(|| {
            format!("participant {s:?}: write NAME:ROLE, e.g. ward-3:site (roles: source, site, observer, router)")
        })?;
        check_name(name)?;
        let role = Role::parse(role).ok_or_else(|| {
            format!("participant {s:?}: role {role:?} is not one of source, site, observer, router")
        })?;
        Ok(Participant {
            name: name.to_string(),
            role,
        })
    }
}

/// A participant's name: 1–32 lower-case letters, digits, `-` (a file stem and a DNS label).
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty()
        || name.len() > 32
        || name.starts_with('-')
        || name == "authority"
        || !name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
    {
        return Err(format!(
            "participant name {name:?}: use 1–32 lower-case letters, digits or '-', not starting \
             with '-' (and not \"authority\")"
        ));
    }
    Ok(())
}

/// The participants `remote keys` makes when none are named: one of each role.
pub fn default_participants() -> Vec<Participant> {
    [
        ("source", Role::Source),
        ("site", Role::Site),
        ("observer", Role::Observer),
        ("router", Role::Router),
    ]
    .into_iter()
    .map(|(n, r)| Participant {
        name: n.into(),
        role: r,
    })
    .collect()
}

/// The authority's files in `dir`.
pub const AUTHORITY_CRT: &str = "authority.crt";
/// The authority's private key in `dir`.
pub const AUTHORITY_KEY: &str = "authority.key";
/// Days a certificate is valid when not told otherwise.
pub const DEFAULT_DAYS: u32 = 365;

fn organisation(room: &str) -> String {
    format!("lungdyn room {room}")
}

/// Write `bytes` to `path` atomically (a temporary beside it, then renamed), with `mode`.
fn write_atomic(path: &Path, bytes: &[u8], mode: u32) -> Result<(), KeysError> {
    let tmp = path.with_extension("part");
    let mut f = fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(mode)
        .open(&tmp)
        .map_err(|e| file_err(&tmp, e))?;
    // The mode asked for at creation is masked by the umask: set it as meant.
    f.set_permissions(fs::Permissions::from_mode(mode))
        .map_err(|e| file_err(&tmp, e))?;
    f.write_all(bytes).map_err(|e| file_err(&tmp, e))?;
    f.sync_all().map_err(|e| file_err(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| file_err(path, e))
}

/// What [`make`] wrote.
#[derive(Debug)]
pub struct Made {
    /// The files, in the order written.
    pub files: Vec<PathBuf>,
    /// When the certificates stop being valid (Unix seconds).
    pub not_after_unix: i64,
}

/// Make `room`'s authority and `participants`' certificates and keys in `dir` (created; refused
/// when it already holds a room's authority), valid for `days`.
pub fn make(
    room: &str,
    dir: &Path,
    participants: &[Participant],
    days: u32,
) -> Result<Made, KeysError> {
    crate::Keys::new(room).map_err(|e| KeysError::Usage(e.to_string()))?;
    if !(1..=3650).contains(&days) {
        return Err(KeysError::Usage(format!(
            "--days {days}: use 1 to 3650 (certificates are checked against it at every start)"
        )));
    }
    if participants.is_empty() {
        return Err(KeysError::Usage("no participants named".into()));
    }
    for (i, p) in participants.iter().enumerate() {
        check_name(&p.name).map_err(KeysError::Usage)?;
        if participants[..i].iter().any(|q| q.name == p.name) {
            return Err(KeysError::Usage(format!(
                "participant {:?} named twice: each name is one certificate",
                p.name
            )));
        }
    }
    if !participants.iter().any(|p| p.role == Role::Source) {
        return Err(KeysError::Usage(
            "no participant with the role source: a room needs its source (add NAME:source)".into(),
        ));
    }
    if dir.join(AUTHORITY_CRT).exists() {
        return Err(KeysError::Usage(format!(
            "{} already holds a room's authority: keys are never overwritten (choose another \
             --out, or remove that folder if its room is finished)",
            dir.display()
        )));
    }
    fs::create_dir_all(dir).map_err(|e| file_err(dir, e))?;
    let rg = |e: rcgen::Error| KeysError::Usage(format!("making a certificate: {e}"));
    let now = time::OffsetDateTime::now_utc();
    // A minute back: a participant whose clock is slightly behind still accepts it.
    let not_before = now - time::Duration::minutes(1);
    let not_after = now + time::Duration::days(days as i64);
    let org = organisation(room);

    let ca_key = rcgen::KeyPair::generate_for(&rcgen::PKCS_ED25519).map_err(rg)?;
    let mut ca = rcgen::CertificateParams::default();
    ca.distinguished_name = rcgen::DistinguishedName::new();
    ca.distinguished_name
        .push(rcgen::DnType::CommonName, format!("{org} authority"));
    ca.distinguished_name
        .push(rcgen::DnType::OrganizationName, org.clone());
    ca.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Constrained(0));
    ca.key_usages = vec![
        rcgen::KeyUsagePurpose::KeyCertSign,
        rcgen::KeyUsagePurpose::CrlSign,
        rcgen::KeyUsagePurpose::DigitalSignature,
    ];
    ca.not_before = not_before;
    ca.not_after = not_after;
    let authority = rcgen::CertifiedIssuer::self_signed(ca, ca_key).map_err(rg)?;

    let mut files = Vec::new();
    let mut put = |name: &str, text: &str, mode: u32| -> Result<(), KeysError> {
        let p = dir.join(name);
        write_atomic(&p, text.as_bytes(), mode)?;
        files.push(p);
        Ok(())
    };
    put(AUTHORITY_CRT, &authority.pem(), 0o644)?;
    for p in participants {
        let key = rcgen::KeyPair::generate_for(&rcgen::PKCS_ED25519).map_err(rg)?;
        let mut params = rcgen::CertificateParams::new(vec![p.name.clone()]).map_err(rg)?;
        params.distinguished_name = rcgen::DistinguishedName::new();
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, p.name.clone());
        params
            .distinguished_name
            .push(rcgen::DnType::OrganizationName, org.clone());
        params
            .distinguished_name
            .push(rcgen::DnType::OrganizationalUnitName, p.role.name());
        params.key_usages = vec![rcgen::KeyUsagePurpose::DigitalSignature];
        // Every participant may listen (server) and connect (client).
        params.extended_key_usages = vec![
            rcgen::ExtendedKeyUsagePurpose::ServerAuth,
            rcgen::ExtendedKeyUsagePurpose::ClientAuth,
        ];
        params.not_before = not_before;
        params.not_after = not_after;
        let cert = params.signed_by(&key, &authority).map_err(rg)?;
        put(&format!("{}.crt", p.name), &cert.pem(), 0o644)?;
        put(&format!("{}.key", p.name), &key_pem(&key)?, 0o600)?;
    }
    // The authority's key last: a folder interrupted before it is missing it, and is refused.
    put(AUTHORITY_KEY, &authority_key_pem(&authority)?, 0o600)?;
    put("README.txt", &readme(room, participants), 0o644)?;
    Ok(Made {
        files,
        not_after_unix: not_after.unix_timestamp(),
    })
}

fn authority_key_pem(a: &rcgen::CertifiedIssuer<'_, rcgen::KeyPair>) -> Result<String, KeysError> {
    use std::ops::Deref;
    // `CertifiedIssuer` derefs to its issuer, which holds the key.
    key_pem(a.deref().key())
}

/// The DER of an Ed25519 private key in PKCS#8 v1 (RFC 8410 §7) before its 32-byte seed.
const ED25519_PKCS8_V1: [u8; 16] = [
    0x30, 0x2e, 0x02, 0x01, 0x00, 0x30, 0x05, 0x06, 0x03, 0x2b, 0x65, 0x70, 0x04, 0x22, 0x04, 0x20,
];

/// `key` as PEM in PKCS#8 v1. ring (and so rcgen) writes v2 (RFC 5958, with the public key),
/// which rustls reads but OpenSSL 3.0 and Python's cryptography refuse ("extra data"); v1 holds
/// the same seed and every one of them reads it.
fn key_pem(key: &rcgen::KeyPair) -> Result<String, KeysError> {
    let v2 = key.serialize_der();
    // v2: SEQUENCE, INTEGER 1, the algorithm, OCTET STRING { OCTET STRING seed }, [1] public key.
    let seed = v2
        .get(16..48)
        .filter(|_| {
            v2.get(2..16)
                == Some(
                    &[
                        0x02, 0x01, 0x01, 0x30, 0x05, 0x06, 0x03, 0x2b, 0x65, 0x70, 0x04, 0x22,
                        0x04, 0x20,
                    ][..],
                )
        })
        .ok_or_else(|| KeysError::Usage("an Ed25519 key not in the PKCS#8 form expected".into()))?;
    let mut der = ED25519_PKCS8_V1.to_vec();
    der.extend_from_slice(seed);
    Ok(pem::encode(&pem::Pem::new("PRIVATE KEY", der)))
}

fn readme(room: &str, participants: &[Participant]) -> String {
    let mut s = format!(
        "lungdyn remote keys for the room {room:?} (made by `lungdyn remote keys`).\n\n\
         What goes where:\n\
         - every participant's machine: authority.crt and every NAME.crt (public; a packet's \
         origin is checked against them)\n\
         - each participant's machine: its own NAME.key only (private, mode 0600)\n\
         - authority.key: nowhere but here, offline; it makes more participants\n\n\
         Participants:\n"
    );
    for p in participants {
        s.push_str(&format!("- {} ({})\n", p.name, p.role.name()));
    }
    s.push_str(
        "\nStart each with `--keys DIR --identity NAME` (or [remote] keys/identity in its scene),\n\
         on tls/HOST:PORT endpoints. `lungdyn doctor --keys DIR` checks this folder.\n",
    );
    s
}

/// One participant of a loaded room.
#[derive(Debug)]
pub struct Member {
    /// Its name (common name).
    pub name: String,
    /// Its role.
    pub role: Role,
    /// Its Ed25519 public key (32 bytes).
    pub public_key: Vec<u8>,
    /// When its certificate stops being valid (Unix seconds).
    pub not_after_unix: i64,
}

/// A room's keys as one participant uses them.
pub struct Room {
    /// The room's name (from the authority's organisation).
    pub room: String,
    /// Every participant with a valid certificate of this room.
    pub members: Vec<Member>,
    /// This participant's index in `members`.
    pub me: usize,
    /// The files Zenoh's TLS link reads.
    pub tls: TlsFiles,
    /// Problems that do not stop the room (certificates expiring soon, others' certificates
    /// refused); said at start-up.
    pub warnings: Vec<String>,
    signer: ring::signature::Ed25519KeyPair,
}

impl std::fmt::Debug for Room {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Room")
            .field("room", &self.room)
            .field("me", &self.members[self.me].name)
            .field("members", &self.members.len())
            .finish_non_exhaustive()
    }
}

/// The certificate and key files of the TLS link.
#[derive(Debug, Clone)]
pub struct TlsFiles {
    /// The room's authority.
    pub authority: PathBuf,
    /// This participant's certificate.
    pub certificate: PathBuf,
    /// This participant's private key.
    pub key: PathBuf,
}

fn read(path: &Path) -> Result<Vec<u8>, KeysError> {
    fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => file_err(
            path,
            "not found (make a room's keys with `lungdyn remote keys --room ROOM --out DIR`)",
        ),
        _ => file_err(path, e),
    })
}

fn pem_der(path: &Path, bytes: &[u8], label: &str) -> Result<Vec<u8>, KeysError> {
    let (_, pem) = x509_parser::pem::parse_x509_pem(bytes)
        .map_err(|e| invalid(path, format!("not a PEM file: {e}")))?;
    if pem.label != label {
        return Err(invalid(
            path,
            format!("holds a {:?}, not a {label:?}", pem.label),
        ));
    }
    Ok(pem.contents)
}

fn attr(
    name: &x509_parser::x509::X509Name<'_>,
    oid: &x509_parser::der_parser::Oid<'_>,
) -> Option<String> {
    name.iter_by_oid(oid)
        .next()
        .and_then(|a| a.as_str().ok())
        .map(str::to_string)
}

fn now_unix() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0)
}

/// The authority of `dir`: its room and public key.
fn authority(dir: &Path) -> Result<(String, Vec<u8>, i64), KeysError> {
    use x509_parser::prelude::*;
    let path = dir.join(AUTHORITY_CRT);
    let der = pem_der(&path, &read(&path)?, "CERTIFICATE")?;
    let (_, ca) = X509Certificate::from_der(&der)
        .map_err(|e| invalid(&path, format!("not a certificate: {e}")))?;
    if !ca.is_ca() {
        return Err(invalid(&path, "not an authority (no CA flag)"));
    }
    ca.verify_signature(None)
        .map_err(|e| invalid(&path, format!("not self-signed as an authority is: {e}")))?;
    let org = attr(ca.subject(), &oid_registry::OID_X509_ORGANIZATION_NAME).unwrap_or_default();
    let room = org
        .strip_prefix("lungdyn room ")
        .ok_or_else(|| {
            invalid(
                &path,
                format!("organisation {org:?} is not a lungdyn room's"),
            )
        })?
        .to_string();
    let not_after = ca.validity().not_after.timestamp();
    let now = now_unix();
    if now > not_after {
        return Err(invalid(
            &path,
            format!(
                "the room's authority expired {} day(s) ago: make new keys (`lungdyn remote keys`)",
                (now - not_after) / 86_400
            ),
        ));
    }
    Ok((room, ca.public_key().raw.to_vec(), not_after))
}

/// Read and check one participant's certificate against the authority.
fn member(path: &Path, room: &str, ca_spki: &[u8]) -> Result<Member, KeysError> {
    use x509_parser::prelude::*;
    let der = pem_der(path, &read(path)?, "CERTIFICATE")?;
    let (_, cert) = X509Certificate::from_der(&der)
        .map_err(|e| invalid(path, format!("not a certificate: {e}")))?;
    let (_, ca_key) = SubjectPublicKeyInfo::from_der(ca_spki)
        .map_err(|e| invalid(path, format!("the authority's key: {e}")))?;
    cert.verify_signature(Some(&ca_key)).map_err(|_| {
        invalid(
            path,
            "not signed by this room's authority (a certificate of another room, or altered)",
        )
    })?;
    let org = attr(cert.subject(), &oid_registry::OID_X509_ORGANIZATION_NAME).unwrap_or_default();
    if org != organisation(room) {
        return Err(invalid(
            path,
            format!("names {org:?}, not \"lungdyn room {room}\""),
        ));
    }
    let name = attr(cert.subject(), &oid_registry::OID_X509_COMMON_NAME).unwrap_or_default();
    check_name(&name).map_err(|e| invalid(path, e))?;
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    if stem != name {
        return Err(invalid(
            path,
            format!("is {name:?}'s certificate under another file name (expected {name}.crt)"),
        ));
    }
    let role_word =
        attr(cert.subject(), &oid_registry::OID_X509_ORGANIZATIONAL_UNIT).unwrap_or_default();
    let role = Role::parse(&role_word)
        .ok_or_else(|| invalid(path, format!("role {role_word:?} is not a lungdyn role")))?;
    let v = cert.validity();
    let now = now_unix();
    if now < v.not_before.timestamp() {
        return Err(invalid(
            path,
            "not valid yet: is this machine's clock right?",
        ));
    }
    if now > v.not_after.timestamp() {
        return Err(invalid(
            path,
            format!(
                "expired {} day(s) ago: make new keys for the room",
                (now - v.not_after.timestamp()) / 86_400
            ),
        ));
    }
    let spki = cert.public_key();
    if spki.algorithm.algorithm != oid_registry::OID_SIG_ED25519 {
        return Err(invalid(
            path,
            "its key is not Ed25519 (lungdyn's rooms use Ed25519)",
        ));
    }
    Ok(Member {
        name,
        role,
        public_key: spki.subject_public_key.data.to_vec(),
        not_after_unix: v.not_after.timestamp(),
    })
}

/// Whether a private key file is readable by others than its owner.
fn key_mode_problem(path: &Path) -> Result<Option<String>, KeysError> {
    let mode = fs::metadata(path)
        .map_err(|e| file_err(path, e))?
        .permissions()
        .mode();
    Ok((mode & 0o077 != 0).then(|| {
        format!(
            "a private key readable by others (mode {:o}): `chmod 600 {}`",
            mode & 0o777,
            path.display()
        )
    }))
}

/// Everything in a room's folder, checked (for `doctor` and [`Room::load`]).
#[derive(Debug)]
pub struct Inspection {
    /// The room.
    pub room: String,
    /// When the authority expires (Unix seconds).
    pub authority_not_after_unix: i64,
    /// The participants whose certificates are valid.
    pub members: Vec<Member>,
    /// Certificates refused, with why.
    pub refused: Vec<String>,
    /// Private keys present, with a problem if any (permissions, not matching its certificate).
    pub keys: Vec<(String, Option<String>)>,
}

/// Check every certificate and key in `dir`.
pub fn inspect(dir: &Path) -> Result<Inspection, KeysError> {
    let (room, ca_spki_raw, ca_not_after) = authority(dir)?;
    let mut members = Vec::new();
    let mut refused = Vec::new();
    let mut keys = Vec::new();
    let mut entries: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(|e| file_err(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for p in &entries {
        let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
        if stem == "authority" {
            if p.extension().is_some_and(|e| e == "key") {
                if let Some(problem) = key_mode_problem(p)? {
                    keys.push(("authority".into(), Some(problem)));
                }
            }
            continue;
        }
        match p.extension().and_then(|e| e.to_str()) {
            Some("crt") => match member(p, &room, &ca_spki_raw) {
                Ok(m) => members.push(m),
                Err(e) => refused.push(e.to_string()),
            },
            Some("key") => {
                let problem = match key_mode_problem(p)? {
                    Some(x) => Some(x),
                    None => signer(p).err().map(|e| e.to_string()),
                };
                keys.push((stem.to_string(), problem));
            }
            _ => {}
        }
    }
    // Keys against their certificates.
    for (name, problem) in keys.iter_mut() {
        if problem.is_some() || name == "authority" {
            continue;
        }
        let Some(m) = members.iter().find(|m| &m.name == name) else {
            *problem = Some(format!("{name}.key has no valid {name}.crt beside it"));
            continue;
        };
        if let Ok(s) = signer(&dir.join(format!("{name}.key"))) {
            use ring::signature::KeyPair;
            if s.public_key().as_ref() != m.public_key.as_slice() {
                *problem = Some(format!("{name}.key is not the key of {name}.crt"));
            }
        }
    }
    Ok(Inspection {
        room,
        authority_not_after_unix: ca_not_after,
        members,
        refused,
        keys,
    })
}

/// The Ed25519 signer in a PEM private key file.
fn signer(path: &Path) -> Result<ring::signature::Ed25519KeyPair, KeysError> {
    let der = pem_der(path, &read(path)?, "PRIVATE KEY")?;
    ring::signature::Ed25519KeyPair::from_pkcs8_maybe_unchecked(&der)
        .map_err(|e| invalid(path, format!("not an Ed25519 private key: {e}")))
}

impl Room {
    /// Load `dir` as `identity`: the authority, every participant's certificate (each checked
    /// against the authority, the room and the date), and this participant's private key (its
    /// permissions and that it matches its certificate).
    pub fn load(dir: &Path, identity: &str) -> Result<Room, KeysError> {
        check_name(identity).map_err(KeysError::Usage)?;
        let ins = inspect(dir)?;
        let mut warnings = ins.refused.clone();
        let me = ins
            .members
            .iter()
            .position(|m| m.name == identity)
            .ok_or_else(|| {
                let known: Vec<&str> = ins.members.iter().map(|m| m.name.as_str()).collect();
                let why = ins
                    .refused
                    .iter()
                    .find(|r| r.contains(&format!("{identity}.crt")))
                    .cloned()
                    .unwrap_or_else(|| format!("{identity}.crt is not there"));
                KeysError::Usage(format!(
                    "--identity {identity}: no valid certificate in {} ({why}); the room's \
                     participants: {}",
                    dir.display(),
                    known.join(", ")
                ))
            })?;
        let key = dir.join(format!("{identity}.key"));
        if let Some(problem) = key_mode_problem(&key)? {
            return Err(invalid(&key, problem));
        }
        let signer = signer(&key)?;
        {
            use ring::signature::KeyPair;
            if signer.public_key().as_ref() != ins.members[me].public_key.as_slice() {
                return Err(invalid(
                    &key,
                    format!("is not the key of {identity}.crt (mixed up folders?)"),
                ));
            }
        }
        let now = now_unix();
        for m in &ins.members {
            let days = (m.not_after_unix - now) / 86_400;
            if days < 30 {
                warnings.push(format!(
                    "{}'s certificate expires in {days} day(s): make new keys soon",
                    m.name
                ));
            }
        }
        Ok(Room {
            room: ins.room,
            tls: TlsFiles {
                authority: dir.join(AUTHORITY_CRT),
                certificate: dir.join(format!("{identity}.crt")),
                key,
            },
            members: ins.members,
            me,
            warnings,
            signer,
        })
    }

    /// This participant.
    pub fn identity(&self) -> &Member {
        &self.members[self.me]
    }

    /// Sign `message` with this participant's key (64 bytes).
    pub fn sign(&self, message: &[u8]) -> [u8; 64] {
        let sig = self.signer.sign(message);
        let mut out = [0u8; 64];
        out.copy_from_slice(sig.as_ref());
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("lungdyn-keys-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn a_room_made_loads_as_each_participant_with_private_keys_0600() {
        let d = tmp("made");
        let made = make("ward", &d, &default_participants(), 10).unwrap();
        assert_eq!(made.files.len(), 1 + 2 * 4 + 2);
        for p in &made.files {
            let mode = fs::metadata(p).unwrap().permissions().mode() & 0o777;
            let want = if p.extension().is_some_and(|e| e == "key") {
                0o600
            } else {
                0o644
            };
            assert_eq!(mode, want, "{}", p.display());
        }
        for p in default_participants() {
            let r = Room::load(&d, &p.name).unwrap();
            assert_eq!(r.room, "ward");
            assert_eq!(r.identity().role, p.role);
            assert_eq!(r.members.len(), 4);
            // 10 days: every certificate warns that it expires soon.
            assert!(
                r.warnings.iter().any(|w| w.contains("expires in")),
                "{:?}",
                r.warnings
            );
        }
        // Never overwritten.
        let e = make("ward", &d, &default_participants(), 30).unwrap_err();
        assert!(e.to_string().contains("never overwritten"), "{e}");
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_certificate_of_another_room_a_loose_key_and_a_swapped_key_are_refused() {
        let (a, b) = (tmp("room-a"), tmp("room-b"));
        make("a", &a, &default_participants(), 365).unwrap();
        make("b", &b, &default_participants(), 365).unwrap();
        // b's site certificate dropped into a's folder under a new name.
        fs::copy(b.join("site.crt"), a.join("intruder.crt")).unwrap();
        let ins = inspect(&a).unwrap();
        assert_eq!(ins.members.len(), 4);
        assert!(
            ins.refused
                .iter()
                .any(|r| r.contains("intruder.crt") && r.contains("not signed by this room")),
            "{:?}",
            ins.refused
        );
        let e = Room::load(&a, "intruder").unwrap_err().to_string();
        assert!(e.contains("not signed by this room"), "{e}");
        // A private key others can read.
        fs::set_permissions(a.join("site.key"), fs::Permissions::from_mode(0o644)).unwrap();
        let e = Room::load(&a, "site").unwrap_err().to_string();
        assert!(e.contains("chmod 600"), "{e}");
        // Another participant's key under this name.
        fs::remove_file(a.join("site.key")).unwrap();
        fs::copy(a.join("observer.key"), a.join("site.key")).unwrap();
        fs::set_permissions(a.join("site.key"), fs::Permissions::from_mode(0o600)).unwrap();
        let e = Room::load(&a, "site").unwrap_err().to_string();
        assert!(e.contains("is not the key of site.crt"), "{e}");
        // An unknown identity names the room's participants.
        let e = Room::load(&a, "nobody").unwrap_err().to_string();
        assert!(e.contains("observer, router, site, source"), "{e}");
        for d in [a, b] {
            fs::remove_dir_all(d).unwrap();
        }
    }

    #[test]
    fn with_keys_the_endpoints_are_tls_and_without_them_tls_is_refused() {
        let d = tmp("endpoints");
        make("ward", &d, &default_participants(), 10).unwrap();
        let room = std::sync::Arc::new(Room::load(&d, "site").unwrap());
        let tcp = ["tcp/127.0.0.1:7447".to_string()];
        let tls = ["tls/127.0.0.1:7447".to_string()];
        let e = crate::Net::peer(&[], &tcp)
            .with_keys(Some(room.clone()))
            .config()
            .unwrap_err()
            .to_string();
        assert!(e.contains("tls/HOST:PORT"), "{e}");
        let e = crate::Net::peer(&[], &tls)
            .config()
            .unwrap_err()
            .to_string();
        assert!(e.contains("TLS needs the room's keys"), "{e}");
        let net = crate::Net::peer(&[], &tls).with_keys(Some(room));
        assert_eq!(net.transport_word(), "tls");
        let c = net.config().unwrap();
        let mtls = c.get_json("transport/link/tls/enable_mtls").unwrap();
        assert_eq!(mtls, "true");
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn bad_participant_lists_are_refused_with_the_fix() {
        let d = tmp("bad");
        for (ps, word) in [
            (vec!["a:site"], "no participant with the role source"),
            (vec!["s:source", "s:site"], "named twice"),
        ] {
            let ps: Vec<Participant> = ps.iter().map(|p| p.parse().unwrap()).collect();
            let e = make("r", &d, &ps, 10).unwrap_err().to_string();
            assert!(e.contains(word), "{e}");
        }
        for (p, word) in [
            ("nocolon", "NAME:ROLE"),
            ("Ward:site", "lower-case"),
            ("authority:site", "authority"),
            ("x:king", "not one of"),
        ] {
            let e = p.parse::<Participant>().unwrap_err();
            assert!(e.contains(word), "{p}: {e}");
        }
        let e = make("bad room", &d, &default_participants(), 10)
            .unwrap_err()
            .to_string();
        assert!(e.contains("room"), "{e}");
        let e = make("r", &d, &default_participants(), 0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("--days"), "{e}");
        assert!(!d.join(AUTHORITY_CRT).exists());
    }
}
