//! Authenticated frames for peer and operator messages, and the team key file they are keyed
//! from.
//!
//! # Wire frame
//!
//! ```text
//! [b"MH"][frame version: u8][key epoch: u32 BE][tag: 32 bytes][JSON envelope]
//!  0..2   2                  3..7               7..39          39..
//! ```
//!
//! `tag = HMAC-SHA256(key of the envelope's sender, frame[0..7] ‖ JSON)`: the MAC covers the
//! magic, the frame version and the key epoch as well as the envelope, so none of them can be
//! changed without the tag failing. The receiver ([`crate::validator::Validator::receive_frame`])
//! checks, in order: size, magic and frame version, key epoch, then reads only the `sender` (and
//! `version`) from the JSON to pick the key, verifies the tag in constant time, and only then
//! trusts anything in the envelope. Every protocol version keeps `sender` at the top level of
//! the envelope so that the key can always be found.
//!
//! # Keys and what they protect against
//!
//! Each sender (unit `0..team_size` and the operator) has its own 32-byte secret, and a frame is
//! tagged with its sender's key. The keys are **symmetric**, and every unit's key file holds
//! every sender's key (a receiver needs the key to verify), so **any holder of a team key file
//! can forge a frame from any sender**, the operator included. Per-sender keys therefore do not
//! stop a compromised unit; they keep each sender's MAC domain separate and let a key file be
//! rotated (a new [`KeyFile::epoch`]) without changing the frame format.
//!
//! We chose HMAC over signatures because the threat is an outsider on the team's network (a
//! stray process, another team, a replayed capture), not a compromised team member; HMAC-SHA256
//! needs no asymmetric-crypto dependency (`hmac` and `sha2` are small RustCrypto crates); and at
//! 50 Hz × a few hundred bytes per unit a MAC costs about a microsecond, far below a tick.
//! Replays within an epoch are stopped by the validator's sequence and stamp checks; rotating
//! the key files (a new epoch) retires every frame recorded before.
//!
//! # Key file
//!
//! TOML, every key required, unknown keys refused:
//!
//! ```toml
//! team = "moonhaul"
//! epoch = 1
//! operator = "<64 hex digits>"
//! units = ["<64 hex digits>", "<64 hex digits>"]   # unit 0, unit 1, …
//! ```
//!
//! It lives outside the repository (e.g. `~/.config/moonhaul/<team>.keys.toml`), is written
//! with mode 0600 by `moonhaul keys generate`, and [`KeyFile::load`] refuses one that group or
//! others may read. Errors name the file and the field, never a secret.

use crate::config::TeamSettings;
use crate::message::{self, EncodeError, Envelope, Rejection, Sender, MAX_MESSAGE_BYTES};
use hmac::digest::KeyInit;
use hmac::{Hmac, Mac};
use moonhaul_core::input::{self, InputError};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use sha2::Sha256;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

type HmacSha256 = Hmac<Sha256>;

/// The first two bytes of every frame.
pub const FRAME_MAGIC: [u8; 2] = *b"MH";
/// The frame layout this build speaks (independent of the envelope's protocol version).
pub const FRAME_VERSION: u8 = 1;
/// Bytes of a secret key.
pub const KEY_BYTES: usize = 32;
/// Bytes of a frame's tag (HMAC-SHA256).
pub const TAG_BYTES: usize = 32;
/// Bytes the tag covers before the envelope: magic, frame version, key epoch.
const SIGNED_HEADER_BYTES: usize = 2 + 1 + 4;
/// Bytes before the envelope: the signed header and the tag.
pub const FRAME_HEADER_BYTES: usize = SIGNED_HEADER_BYTES + TAG_BYTES;
/// Largest frame accepted: the header and an envelope of at most [`MAX_MESSAGE_BYTES`].
pub const MAX_FRAME_BYTES: usize = FRAME_HEADER_BYTES + MAX_MESSAGE_BYTES;
/// Largest key file accepted, bytes (a team of 64 holds ~5 kB).
pub const MAX_KEY_FILE_BYTES: u64 = 64 << 10;
/// Most units a key file may hold keys for.
pub const MAX_KEY_FILE_UNITS: usize = 64;
/// Longest team name, bytes: it is part of every message's key expression.
pub const MAX_TEAM_NAME_BYTES: usize = 64;

/// One sender's 32-byte secret. Its `Debug` never shows the bytes; it is written to and read
/// from a key file as 64 lowercase hex digits.
#[derive(Clone, PartialEq, Eq)]
pub struct SecretKey([u8; KEY_BYTES]);

impl std::fmt::Debug for SecretKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SecretKey(<redacted>)")
    }
}

impl SecretKey {
    fn random() -> Result<Self, KeyFileError> {
        use rand::TryRngCore as _;
        let mut bytes = [0; KEY_BYTES];
        rand::rngs::OsRng
            .try_fill_bytes(&mut bytes)
            .map_err(|e| KeyFileError::Random(e.to_string()))?;
        Ok(SecretKey(bytes))
    }

    fn to_hex(&self) -> String {
        const DIGITS: &[u8; 16] = b"0123456789abcdef";
        let mut text = String::with_capacity(2 * KEY_BYTES);
        for b in self.0 {
            text.push(char::from(DIGITS[usize::from(b >> 4)]));
            text.push(char::from(DIGITS[usize::from(b & 0xf)]));
        }
        text
    }

    /// Parses 64 hex digits; the error never repeats the text (it may be a secret).
    fn from_hex(text: &str) -> Result<Self, String> {
        let digits = text.as_bytes();
        if digits.len() != 2 * KEY_BYTES {
            return Err(format!(
                "expected {} hex digits (a {KEY_BYTES}-byte key), found {} characters",
                2 * KEY_BYTES,
                text.chars().count()
            ));
        }
        let nibble = |i: usize| -> Result<u8, String> {
            let c = digits[i];
            match c {
                b'0'..=b'9' => Ok(c - b'0'),
                b'a'..=b'f' => Ok(c - b'a' + 10),
                b'A'..=b'F' => Ok(c - b'A' + 10),
                _ => Err(format!("character {} is not a hex digit", i + 1)),
            }
        };
        let mut bytes = [0; KEY_BYTES];
        for (i, b) in bytes.iter_mut().enumerate() {
            *b = (nibble(2 * i)? << 4) | nibble(2 * i + 1)?;
        }
        Ok(SecretKey(bytes))
    }

    /// HMAC-SHA256 keyed with this secret. HMAC zero-pads keys shorter than SHA-256's 64-byte
    /// block (RFC 2104), so keying with the padded block is keying with the secret, and `new`
    /// on a block-sized key cannot fail.
    fn mac(&self) -> HmacSha256 {
        let mut block = [0u8; 64];
        block[..KEY_BYTES].copy_from_slice(&self.0);
        <HmacSha256 as KeyInit>::new(&block.into())
    }
}

impl Serialize for SecretKey {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(&self.to_hex())
    }
}

impl<'de> Deserialize<'de> for SecretKey {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Hex;
        impl serde::de::Visitor<'_> for Hex {
            type Value = SecretKey;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                write!(f, "a string of {} hex digits", 2 * KEY_BYTES)
            }
            fn visit_str<E: serde::de::Error>(self, text: &str) -> Result<SecretKey, E> {
                SecretKey::from_hex(text).map_err(E::custom)
            }
        }
        deserializer.deserialize_str(Hex)
    }
}

/// A team's keys: one secret per unit and one for the operator, under a key epoch that is
/// bumped every time the keys are rotated. `Debug` shows no secret.
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyFile {
    team: String,
    epoch: u32,
    operator: SecretKey,
    units: Vec<SecretKey>,
}

impl std::fmt::Debug for KeyFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KeyFile")
            .field("team", &self.team)
            .field("epoch", &self.epoch)
            .field("team_size", &self.units.len())
            .finish_non_exhaustive()
    }
}

/// Why a key file could not be made, read or written. Every variant names the file (where
/// there is one) and the field at fault; none shows a secret.
#[derive(Debug, thiserror::Error)]
pub enum KeyFileError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error(
        "{} may be read by group or others (mode {mode:03o}); key files must be private: \
         run `chmod 600 {}`",
        path.display(),
        path.display()
    )]
    Permissions { path: PathBuf, mode: u32 },
    /// The file is not valid TOML of the key-file layout. `field` is the dotted path the parser
    /// stopped at (empty for syntax errors); the source line is given by number only, since it
    /// may hold a secret.
    #[error("{}: {}{message}{}", path.display(), field_prefix(field), line_suffix(*line))]
    Parse {
        path: PathBuf,
        field: String,
        line: Option<usize>,
        message: String,
    },
    #[error("{}: field `{field}`: {reason}", path.display())]
    Invalid {
        path: PathBuf,
        field: String,
        reason: String,
    },
    #[error("cannot make a key file: `{field}` {reason}")]
    Request { field: &'static str, reason: String },
    #[error("{} already exists; a key file is only replaced when forced", path.display())]
    Exists { path: PathBuf },
    // The I/O error is part of the message, not a `source`, so a chain prints it once.
    #[error("cannot write {}: {error}", path.display())]
    Write { path: PathBuf, error: io::Error },
    #[error("the operating system's random source failed: {0}")]
    Random(String),
}

fn field_prefix(field: &str) -> String {
    if field.is_empty() || field == "." {
        String::new()
    } else {
        format!("field `{field}`: ")
    }
}

fn line_suffix(line: Option<usize>) -> String {
    line.map(|l| format!(" (line {l})")).unwrap_or_default()
}

/// Why a key file does not fit the team a unit runs in, or lacks a sender's key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum KeyMismatch {
    #[error("the key file is for team {keys:?}, but this unit is in team {settings:?}")]
    Team { keys: String, settings: String },
    #[error("the key file holds keys for {keys} units, but the team has {settings}")]
    TeamSize { keys: usize, settings: usize },
    #[error("the key file holds no key for {sender}")]
    NoKey { sender: Sender },
}

impl KeyFile {
    /// Fresh keys for `team` (units `0..team_size` and the operator) from the operating
    /// system's random source.
    pub fn generate(team: &str, team_size: usize, epoch: u32) -> Result<KeyFile, KeyFileError> {
        let request = |field, reason: String| KeyFileError::Request { field, reason };
        if let Err(reason) = check_team_name(team) {
            return Err(request("team", reason));
        }
        if !(1..=MAX_KEY_FILE_UNITS).contains(&team_size) {
            return Err(request(
                "team_size",
                format!("must be 1 to {MAX_KEY_FILE_UNITS}, not {team_size}"),
            ));
        }
        let units = (0..team_size)
            .map(|_| SecretKey::random())
            .collect::<Result<Vec<_>, _>>()?;
        Ok(KeyFile {
            team: team.to_owned(),
            epoch,
            operator: SecretKey::random()?,
            units,
        })
    }

    /// Reads a key file: refused (on unix) if group or others may read it, size-capped, strictly
    /// parsed and checked (team name, at least one unit, every key 64 hex digits, no two keys
    /// equal, no all-zero key).
    pub fn load(path: &Path) -> Result<KeyFile, KeyFileError> {
        check_private(path)?;
        let text = input::read_capped_text(path, MAX_KEY_FILE_BYTES)?;
        Self::parse(&text, path)
    }

    /// Parses and checks key-file text; `path` names the source in errors.
    pub fn parse(text: &str, path: &Path) -> Result<KeyFile, KeyFileError> {
        let parse_error = |field: String, error: toml::de::Error| {
            let line = error
                .span()
                .map(|span| text[..span.start.min(text.len())].matches('\n').count() + 1);
            KeyFileError::Parse {
                path: path.to_owned(),
                field,
                line,
                message: error.message().trim_end().to_owned(),
            }
        };
        let deserializer =
            toml::Deserializer::parse(text).map_err(|e| parse_error(String::new(), e))?;
        let keys: KeyFile = serde_path_to_error::deserialize(deserializer).map_err(|e| {
            let field = e.path().to_string();
            parse_error(field, e.into_inner())
        })?;
        keys.check()
            .map_err(|(field, reason)| KeyFileError::Invalid {
                path: path.to_owned(),
                field,
                reason,
            })?;
        Ok(keys)
    }

    fn check(&self) -> Result<(), (String, String)> {
        check_team_name(&self.team).map_err(|reason| ("team".to_owned(), reason))?;
        if self.units.is_empty() || self.units.len() > MAX_KEY_FILE_UNITS {
            return Err((
                "units".to_owned(),
                format!(
                    "must hold 1 to {MAX_KEY_FILE_UNITS} keys, holds {}",
                    self.units.len()
                ),
            ));
        }
        let named = std::iter::once(("operator".to_owned(), &self.operator)).chain(
            self.units
                .iter()
                .enumerate()
                .map(|(i, k)| (format!("units[{i}]"), k)),
        );
        let mut seen: Vec<(String, &SecretKey)> = Vec::with_capacity(self.units.len() + 1);
        for (name, key) in named {
            if key.0 == [0; KEY_BYTES] {
                return Err((name, "is all zeros, not a generated key".to_owned()));
            }
            if let Some((first, _)) = seen.iter().find(|(_, k)| *k == key) {
                return Err((name, format!("is the same key as `{first}`")));
            }
            seen.push((name, key));
        }
        Ok(())
    }

    /// Writes the key file whole and private through [`moonhaul_core::atomic_file::write_private`]
    /// (a temporary sibling created with mode 0600, synced, then moved into place), so a reader
    /// never sees half a file and the secrets are never readable by others, not even for a
    /// moment. Refuses to replace an existing file unless `force` (also one that appears while
    /// the file is written), and refuses a target that is not a regular file (a symlink is not
    /// followed).
    pub fn write_new(&self, path: &Path, force: bool) -> Result<(), KeyFileError> {
        let write_error = |error| KeyFileError::Write {
            path: path.to_owned(),
            error,
        };
        let body = toml::to_string(self).map_err(|e| write_error(io::Error::other(e)))?;
        let text = format!(
            "# moonhaul team key file: SECRET. Every holder can authenticate as any unit or as\n\
             # the operator of team {:?}. Keep it mode 0600, outside the repository; rotate by\n\
             # generating a new file with a higher epoch and giving it to every unit.\n{body}",
            self.team
        );
        match moonhaul_core::atomic_file::write_private(path, text.as_bytes(), force) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                return Err(KeyFileError::Exists {
                    path: path.to_owned(),
                })
            }
            Err(e) => return Err(write_error(e)),
        }
        sync_parent(path);
        Ok(())
    }

    pub fn team(&self) -> &str {
        &self.team
    }

    /// The key epoch: frames sealed under another epoch are rejected.
    pub fn epoch(&self) -> u32 {
        self.epoch
    }

    /// Number of units the file holds keys for.
    pub fn team_size(&self) -> usize {
        self.units.len()
    }

    /// Checks the file belongs to the team of `settings` and has a key for each of its units.
    pub fn check_matches(&self, settings: &TeamSettings) -> Result<(), KeyMismatch> {
        if self.team != settings.team {
            return Err(KeyMismatch::Team {
                keys: self.team.clone(),
                settings: settings.team.clone(),
            });
        }
        if self.units.len() != settings.team_size {
            return Err(KeyMismatch::TeamSize {
                keys: self.units.len(),
                settings: settings.team_size,
            });
        }
        Ok(())
    }

    fn key(&self, sender: Sender) -> Option<&SecretKey> {
        match sender {
            Sender::Unit(i) => self.units.get(i),
            Sender::Operator => Some(&self.operator),
        }
    }

    /// The sealing half for `sender` (a unit's own index, or the operator).
    pub fn sealer(&self, sender: Sender) -> Result<Sealer, KeyMismatch> {
        let key = self.key(sender).ok_or(KeyMismatch::NoKey { sender })?;
        Ok(Sealer {
            sender,
            epoch: self.epoch,
            mac: key.mac(),
        })
    }

    /// The verifying half: every sender's key, ready to check tags.
    pub fn verifier(&self) -> Verifier {
        Verifier {
            epoch: self.epoch,
            macs: self
                .units
                .iter()
                .chain(std::iter::once(&self.operator))
                .map(SecretKey::mac)
                .collect(),
        }
    }
}

/// The one rule for a team name, shared by key files and `unit.toml`: 1 to
/// [`MAX_TEAM_NAME_BYTES`] ASCII letters, digits, '_' or '-' (it is a segment of every zenoh
/// key expression the team uses, where '/', '*', '$', '#' and '?' mean something else).
pub fn check_team_name(team: &str) -> Result<(), String> {
    let allowed = |b: u8| b.is_ascii_alphanumeric() || b == b'_' || b == b'-';
    if team.is_empty() || team.len() > MAX_TEAM_NAME_BYTES || !team.bytes().all(allowed) {
        let mut shown = team.to_owned();
        moonhaul_core::input::clip_for_message(&mut shown, 2 * MAX_TEAM_NAME_BYTES);
        return Err(format!(
            "{shown:?} must be 1 to {MAX_TEAM_NAME_BYTES} ASCII letters, digits, '_' or '-'"
        ));
    }
    Ok(())
}

/// Refuses a key file that group or others may read (unix only; elsewhere nothing to check).
fn check_private(path: &Path) -> Result<(), KeyFileError> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt as _;
        // A missing or unreadable file is reported by the read that follows.
        if let Ok(metadata) = fs::metadata(path) {
            let mode = metadata.permissions().mode() & 0o777;
            if metadata.is_file() && mode & 0o077 != 0 {
                return Err(KeyFileError::Permissions {
                    path: path.to_owned(),
                    mode,
                });
            }
        }
    }
    #[cfg(not(unix))]
    let _ = path;
    Ok(())
}

/// Makes the new directory entry durable (best effort: not every platform can sync a folder).
fn sync_parent(path: &Path) {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    if let Ok(dir) = fs::File::open(dir) {
        let _ = dir.sync_all();
    }
}

/// Seals one sender's envelopes into frames. Keyed once; sealing does not allocate beyond the
/// output buffer.
#[derive(Clone)]
pub struct Sealer {
    sender: Sender,
    epoch: u32,
    mac: HmacSha256,
}

impl std::fmt::Debug for Sealer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sealer")
            .field("sender", &self.sender)
            .field("epoch", &self.epoch)
            .finish_non_exhaustive()
    }
}

impl Sealer {
    pub fn sender(&self) -> Sender {
        self.sender
    }

    pub fn epoch(&self) -> u32 {
        self.epoch
    }

    /// The frame of `envelope`, which must be this sealer's sender's (at most
    /// [`MAX_FRAME_BYTES`]).
    pub fn seal(&self, envelope: &Envelope) -> Result<Vec<u8>, EncodeError> {
        let mut frame = Vec::with_capacity(1024);
        self.seal_into(envelope, &mut frame)?;
        Ok(frame)
    }

    /// [`Sealer::seal`] into `frame`, replacing its content and reusing its allocation. On error
    /// `frame` is left empty.
    pub fn seal_into(&self, envelope: &Envelope, frame: &mut Vec<u8>) -> Result<(), EncodeError> {
        frame.clear();
        if envelope.sender != self.sender {
            return Err(EncodeError::ForeignSender {
                sender: envelope.sender,
                seq: envelope.seq,
                sealer: self.sender,
            });
        }
        frame.extend_from_slice(&signed_header(self.epoch));
        frame.resize(FRAME_HEADER_BYTES, 0);
        if let Err(e) = message::encode_into(envelope, frame) {
            frame.clear();
            return Err(e);
        }
        self.tag_frame(frame);
        Ok(())
    }

    /// Frames raw envelope bytes as they are (no checks): for tests of the receiver.
    #[cfg(test)]
    pub(crate) fn seal_raw(&self, json: &[u8]) -> Vec<u8> {
        let mut frame = signed_header(self.epoch).to_vec();
        frame.resize(FRAME_HEADER_BYTES, 0);
        frame.extend_from_slice(json);
        self.tag_frame(&mut frame);
        frame
    }

    /// Writes the tag of a frame whose header and envelope are in place.
    fn tag_frame(&self, frame: &mut [u8]) {
        let mut mac = self.mac.clone();
        mac.update(&frame[..SIGNED_HEADER_BYTES]);
        mac.update(&frame[FRAME_HEADER_BYTES..]);
        let tag = mac.finalize().into_bytes();
        frame[SIGNED_HEADER_BYTES..FRAME_HEADER_BYTES].copy_from_slice(&tag);
    }
}

fn signed_header(epoch: u32) -> [u8; SIGNED_HEADER_BYTES] {
    let e = epoch.to_be_bytes();
    [
        FRAME_MAGIC[0],
        FRAME_MAGIC[1],
        FRAME_VERSION,
        e[0],
        e[1],
        e[2],
        e[3],
    ]
}

/// The verifying half of a key file: each sender's key, for checking tags. `Debug` shows no
/// secret.
#[derive(Clone)]
pub struct Verifier {
    epoch: u32,
    /// One per unit, then the operator.
    macs: Vec<HmacSha256>,
}

impl std::fmt::Debug for Verifier {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Verifier")
            .field("epoch", &self.epoch)
            .field("senders", &self.macs.len())
            .finish_non_exhaustive()
    }
}

/// A frame split into its parts; nothing in it is authenticated yet.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Frame<'a> {
    pub epoch: u32,
    signed_header: &'a [u8],
    tag: &'a [u8],
    /// The envelope's JSON.
    pub json: &'a [u8],
}

impl<'a> Frame<'a> {
    /// Checks the size, magic and frame version and splits the frame.
    pub fn parse(bytes: &'a [u8]) -> Result<Self, Rejection> {
        let malformed = |detail: String| Rejection::Malformed {
            len: bytes.len(),
            detail,
        };
        if bytes.len() > MAX_FRAME_BYTES {
            return Err(malformed(format!("over the {MAX_FRAME_BYTES}-byte limit")));
        }
        if bytes.len() < FRAME_HEADER_BYTES {
            return Err(malformed(format!(
                "shorter than the {FRAME_HEADER_BYTES}-byte frame header"
            )));
        }
        let (signed_header, rest) = bytes.split_at(SIGNED_HEADER_BYTES);
        let (tag, json) = rest.split_at(TAG_BYTES);
        if signed_header[..2] != FRAME_MAGIC {
            return Err(malformed("not a moonhaul frame (magic)".to_owned()));
        }
        if signed_header[2] != FRAME_VERSION {
            return Err(malformed(format!(
                "frame version {}, expected {FRAME_VERSION}",
                signed_header[2]
            )));
        }
        let epoch = u32::from_be_bytes([
            signed_header[3],
            signed_header[4],
            signed_header[5],
            signed_header[6],
        ]);
        Ok(Frame {
            epoch,
            signed_header,
            tag,
            json,
        })
    }
}

impl Verifier {
    pub fn epoch(&self) -> u32 {
        self.epoch
    }

    /// Number of units it holds keys for.
    pub fn team_size(&self) -> usize {
        self.macs.len() - 1
    }

    /// Whether `frame`'s tag is `sender`'s, compared in constant time. False for a sender it
    /// holds no key for.
    pub(crate) fn verify(&self, sender: Sender, frame: &Frame<'_>) -> bool {
        let slot = match sender {
            Sender::Unit(i) if i < self.team_size() => i,
            Sender::Unit(_) => return false,
            Sender::Operator => self.team_size(),
        };
        let mut mac = self.macs[slot].clone();
        mac.update(frame.signed_header);
        mac.update(frame.json);
        mac.verify_slice(frame.tag).is_ok()
    }
}

/// Secrets for other protocols, derived from the key file so that a team provisions nothing
/// new (the zenoh transport's credentials, `moonhaul_deploy::network`).
impl KeyFile {
    /// `HMAC-SHA256(key of sender, purpose)`: independent secrets for distinct purposes, none
    /// of which reveals the key. The caller puts the team, epoch and role into `purpose`.
    pub fn derive_secret(&self, sender: Sender, purpose: &str) -> Result<[u8; 32], KeyMismatch> {
        let key = self.key(sender).ok_or(KeyMismatch::NoKey { sender })?;
        let mut mac = key.mac();
        mac.update(purpose.as_bytes());
        Ok(mac.finalize().into_bytes().into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::{Body, OperatorCommand, PROTOCOL_VERSION};

    fn stop(seq: u64) -> Envelope {
        Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender: Sender::Operator,
            seq,
            stamp_us: 1_000_000,
            body: Body::Operator(OperatorCommand::Stop { mission: None }),
        }
    }

    #[test]
    fn padded_block_key_is_the_hmac_of_the_secret() {
        let key = SecretKey::from_hex(&"0b".repeat(32)).unwrap();
        let mut ours = key.mac();
        let mut reference = <HmacSha256 as Mac>::new_from_slice(&key.0).unwrap();
        ours.update(b"what do ya want for nothing?");
        reference.update(b"what do ya want for nothing?");
        assert_eq!(
            ours.finalize().into_bytes(),
            reference.finalize().into_bytes()
        );
    }

    #[test]
    fn frames_have_the_documented_layout() {
        let keys = KeyFile::generate("moonhaul", 2, 0x0102_0304).unwrap();
        let sealer = keys.sealer(Sender::Operator).unwrap();
        let frame = sealer.seal(&stop(5)).unwrap();
        assert_eq!(&frame[..3], b"MH\x01");
        assert_eq!(&frame[3..7], &[1, 2, 3, 4]);
        let json = crate::message::encode(&stop(5)).unwrap();
        assert_eq!(&frame[FRAME_HEADER_BYTES..], &json[..]);
        let parsed = Frame::parse(&frame).unwrap();
        assert_eq!(parsed.epoch, 0x0102_0304);
        let verifier = keys.verifier();
        assert!(verifier.verify(Sender::Operator, &parsed));
        assert!(!verifier.verify(Sender::Unit(0), &parsed));
        assert!(!verifier.verify(Sender::Unit(7), &parsed));
        // seal_into reuses the buffer and gives the same frame.
        let mut buffer = vec![0xff; 3];
        sealer.seal_into(&stop(5), &mut buffer).unwrap();
        assert_eq!(buffer, frame);
        // A sealer signs only its own sender's envelopes.
        let unit = keys.sealer(Sender::Unit(1)).unwrap();
        assert!(matches!(
            unit.seal_into(&stop(5), &mut buffer),
            Err(EncodeError::ForeignSender { .. })
        ));
        assert!(buffer.is_empty());
        assert_eq!(
            keys.sealer(Sender::Unit(2)).unwrap_err(),
            KeyMismatch::NoKey {
                sender: Sender::Unit(2)
            }
        );
    }

    #[test]
    fn generated_keys_differ_and_never_show_in_debug() {
        let a = KeyFile::generate("moonhaul", 3, 1).unwrap();
        let b = KeyFile::generate("moonhaul", 3, 1).unwrap();
        assert_ne!(a, b);
        a.check().unwrap();
        let text = format!("{a:?} {:?}", a.sealer(Sender::Unit(0)).unwrap());
        assert!(!text.contains(&a.units[0].to_hex()), "{text}");
        assert!(!format!("{:?}", a.verifier()).contains(&a.operator.to_hex()));
        // Team names a unit config refuses (key-expression characters, non-ASCII, space,
        // too long) cannot be given a key file either.
        for team in [
            "a/b",
            "team*",
            "$x",
            "a?b",
            "a#b",
            "mönhaul",
            "two words",
            "tab\t",
            &"t".repeat(MAX_TEAM_NAME_BYTES + 1),
        ] {
            let err = KeyFile::generate(team, 2, 1).unwrap_err().to_string();
            assert!(
                err.contains("`team`") && err.contains("ASCII"),
                "{team:?}: {err}"
            );
        }
        KeyFile::generate(&"t".repeat(MAX_TEAM_NAME_BYTES), 2, 1).unwrap();
        KeyFile::generate("moon_haul-2", 2, 1).unwrap();
        for (team, size) in [
            ("", 2),
            ("moonhaul", 0),
            ("moonhaul", MAX_KEY_FILE_UNITS + 1),
        ] {
            let err = KeyFile::generate(team, size, 1).unwrap_err().to_string();
            let field = if team.is_empty() { "team" } else { "team_size" };
            assert!(err.contains(&format!("`{field}`")), "{err}");
        }
    }

    #[cfg(unix)]
    fn mode(path: &Path) -> u32 {
        use std::os::unix::fs::PermissionsExt as _;
        fs::metadata(path).unwrap().permissions().mode() & 0o777
    }

    #[test]
    fn key_file_round_trips_privately_and_is_not_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("moonhaul.keys.toml");
        let keys = KeyFile::generate("moon_haul-7", 3, 7).unwrap();
        keys.write_new(&path, false).unwrap();
        #[cfg(unix)]
        assert_eq!(mode(&path), 0o600);
        assert_eq!(KeyFile::load(&path).unwrap(), keys);
        // No temporary is left beside it.
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);

        let other = KeyFile::generate("moonhaul", 2, 8).unwrap();
        let err = other.write_new(&path, false).unwrap_err();
        assert!(matches!(err, KeyFileError::Exists { .. }), "{err}");
        assert_eq!(KeyFile::load(&path).unwrap(), keys);
        other.write_new(&path, true).unwrap();
        assert_eq!(KeyFile::load(&path).unwrap(), other);
        #[cfg(unix)]
        assert_eq!(mode(&path), 0o600);
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);

        // Not through a directory or a symlink.
        let sub = dir.path().join("sub");
        fs::create_dir(&sub).unwrap();
        assert!(matches!(
            keys.write_new(&sub, true),
            Err(KeyFileError::Write { .. })
        ));
        #[cfg(unix)]
        {
            let link = dir.path().join("link.toml");
            std::os::unix::fs::symlink(&path, &link).unwrap();
            assert!(matches!(
                keys.write_new(&link, true),
                Err(KeyFileError::Write { .. })
            ));
            assert_eq!(KeyFile::load(&path).unwrap(), other);
        }
    }

    #[cfg(unix)]
    #[test]
    fn key_files_readable_by_others_are_refused() {
        use std::os::unix::fs::PermissionsExt as _;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("team.keys.toml");
        KeyFile::generate("moonhaul", 2, 1)
            .unwrap()
            .write_new(&path, false)
            .unwrap();
        for bad in [0o640, 0o604, 0o644, 0o660] {
            fs::set_permissions(&path, fs::Permissions::from_mode(bad)).unwrap();
            let err = KeyFile::load(&path).unwrap_err().to_string();
            assert!(
                err.contains("chmod 600") && err.contains("team.keys.toml"),
                "{err}"
            );
        }
        fs::set_permissions(&path, fs::Permissions::from_mode(0o400)).unwrap();
        KeyFile::load(&path).unwrap();
        let missing = KeyFile::load(&dir.path().join("absent.toml"))
            .unwrap_err()
            .to_string();
        assert!(missing.contains("absent.toml"), "{missing}");
    }

    #[test]
    fn malformed_key_files_name_file_and_field_never_the_secret() {
        let keys = KeyFile::generate("moonhaul", 2, 3).unwrap();
        let good = toml::to_string(&keys).unwrap();
        let secret = keys.units[1].to_hex();
        let op = keys.operator.to_hex();
        let zero = "0".repeat(64);
        let short = &secret[..63];
        let cases: Vec<(String, &str)> = vec![
            (good.replace(&secret, short), "units[1]"),
            (good.replace(&secret, &format!("{}g", short)), "units[1]"),
            (good.replace(&op, &zero), "operator"),
            (good.replace(&secret, &keys.units[0].to_hex()), "units[1]"),
            (good.replace(&op, &keys.units[0].to_hex()), "units[0]"),
            (good.replace("epoch = 3", "epoch = -1"), "epoch"),
            (good.replace("epoch = 3", "epoch = \"3\""), "epoch"),
            (good.replace("epoch = 3", "epochs = 3"), "epochs"),
            (good.replace("team = \"moonhaul\"", "team = \"\""), "team"),
            (format!("{good}extra = 1\n"), "extra"),
            (
                good.lines()
                    .filter(|l| !l.starts_with("units"))
                    .collect::<Vec<_>>()
                    .join("\n"),
                "units",
            ),
            (
                good.lines()
                    .map(|l| {
                        if l.starts_with("units") {
                            "units = []"
                        } else {
                            l
                        }
                    })
                    .collect::<Vec<_>>()
                    .join("\n"),
                "units",
            ),
        ];
        let dir = tempfile::tempdir().unwrap();
        for (i, (text, field)) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("bad{i}.keys.toml"));
            let err = KeyFile::parse(&text, &path).unwrap_err().to_string();
            assert!(
                err.contains(&format!("`{field}`")) && err.contains(&format!("bad{i}.keys")),
                "{field}: {err}"
            );
            for s in [&secret, &op, &keys.units[0].to_hex()] {
                assert!(!err.contains(&s[..16]), "secret in {err}");
            }
        }
        // A syntax error gives the line by number, not its text.
        let broken = good.replace(&format!("\"{secret}\""), &format!("\"{secret}"));
        let err = KeyFile::parse(&broken, Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("x.toml") && err.contains("line"), "{err}");
        assert!(!err.contains(&secret[..16]), "{err}");
    }
}
